//! Fit/evaluate timings on ultrasound-like samples: `cargo run --release --example rbf_scaling -- 10000 100000`.
//! Environment: `SOLVER` = auto (default) | fast | pu | direct, `W`, `ACC`, `EPS`, `LEAF`, `OVERLAP`, `MINOV`.

use echosurf::rbf::{FitOptions, SolverChoice};
use echosurf_bench::{ScalingSamples, bench_fit_scaling};

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
        solver: match std::env::var("SOLVER").as_deref() {
            Ok("fast") => SolverChoice::Fast,
            Ok("pu") => SolverChoice::PartitionOfUnity,
            Ok("direct") => SolverChoice::Direct,
            _ => SolverChoice::Auto,
        },
        pu_leaf_points: std::env::var("LEAF")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(FitOptions::default().pu_leaf_points),
        pu_overlap: std::env::var("OVERLAP")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(FitOptions::default().pu_overlap),
        pu_min_overlap_mm: std::env::var("MINOV")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(FitOptions::default().pu_min_overlap_mm),
        ..FitOptions::default()
    };
    println!("threads {}", rayon::current_num_threads());
    for row in bench_fit_scaling(&sizes, &options, 1, ScalingSamples::Synthetic)? {
        println!("{}", serde_json::to_string(&row).expect("serialisable"));
    }
    Ok(())
}
