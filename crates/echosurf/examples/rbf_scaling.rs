//! Fit/evaluate timings on ultrasound-like samples: `cargo run --release --example rbf_scaling -- 10000 100000`.

use echosurf::rbf::{FitOptions, bench_fit_scaling};

fn main() -> echosurf::Result<()> {
    let sizes: Vec<usize> = std::env::args()
        .skip(1)
        .filter_map(|a| a.parse().ok())
        .collect();
    let sizes = if sizes.is_empty() {
        vec![10_000, 100_000]
    } else {
        sizes
    };
    let options = FitOptions {
        accuracy: std::env::var("ACC")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(2.0),
        smoothing: std::env::var("W")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(1.0),
        eval_accuracy: std::env::var("EPS")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(1e-4),
        ..FitOptions::default()
    };
    println!("threads {}", rayon::current_num_threads());
    for row in bench_fit_scaling(&sizes, &options, 1)? {
        println!("{}", serde_json::to_string(&row).expect("serialisable"));
    }
    Ok(())
}
