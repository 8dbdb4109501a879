//! echosurf vs ferreus_rbf 0.2.2 on identical samples (synthetic ultrasound-like ones, or the band pixels of a
//! PLY given as an argument) at equal fitting accuracy.
//!
//! Both fit the linear kernel |x - y| with a linear trend to the same points, stop at the same absolute
//! fitting accuracy (max |s(x_i) - f_i| in grey levels) and are then checked on those samples with an exact
//! direct sum, so neither side is credited for an accuracy it did not reach. Smoothing is 0 on both sides
//! (interpolation) because the two libraries scale their smoothing terms differently.

use std::time::Instant;

use echosurf::progress::NoProgress;
use echosurf::rbf::{FitOptions, SolverChoice, fit, ultrasound_like_samples};
use faer::Mat;
use ferreus_rbf::RBFInterpolator;
use ferreus_rbf::interpolant_config::{
    Drift, FittingAccuracy, FittingAccuracyType, InterpolantSettings, RBFKernelType,
};

/// Samples for one run: `N` synthetic ultrasound-like samples, or the points and `intensity` of a PLY
/// (e.g. band pixels from `echosurf-bench`'s `band_pixels` example).
fn samples(arg: &str) -> Option<(String, Vec<glam::DVec3>, Vec<f64>)> {
    if arg.ends_with(".ply") {
        let cloud = match echosurf::io::read_point_cloud(std::path::Path::new(arg)) {
            Ok(c) => c,
            Err(e) => {
                // echosurf's read errors name the file.
                eprintln!("{e}");
                return None;
            }
        };
        let Some((_, intensity)) = cloud.scalars.iter().find(|(name, _)| name == "intensity")
        else {
            eprintln!("{arg}: no intensity property");
            return None;
        };
        let values = intensity.iter().map(|&v| f64::from(v)).collect();
        return Some((arg.to_string(), cloud.positions, values));
    }
    let Ok(n) = arg.parse::<usize>() else {
        eprintln!("{arg}: neither a sample count nor a .ply file");
        return None;
    };
    let (points, values) = ultrasound_like_samples(n, 1);
    Some((n.to_string(), points, values))
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let args = if args.is_empty() {
        vec!["10000".to_string(), "90000".to_string()]
    } else {
        args
    };
    let accuracy: f64 = std::env::var("ACC")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(2.0);
    println!(
        "{:>9} | {:>12} {:>10} | {:>12} {:>10} | {:>7}",
        "samples", "echosurf s", "max err", "ferreus s", "max err", "speedup"
    );
    for arg in &args {
        // `samples` has said why it skips an argument.
        let Some((label, points, values)) = samples(arg) else {
            continue;
        };
        let n = points.len();
        let check: Vec<usize> = (0..n).step_by((n / 2000).max(1)).collect();
        let exact_error = |eval: &dyn Fn(&[glam::DVec3]) -> Vec<f64>| {
            let pts: Vec<glam::DVec3> = check.iter().map(|&i| points[i]).collect();
            let v = eval(&pts);
            check
                .iter()
                .zip(&v)
                .fold(0.0f64, |m, (&i, s)| m.max((s - values[i]).abs()))
        };

        let options = FitOptions {
            smoothing: 0.0,
            accuracy,
            merge_distance_mm: 0.0,
            // SOLVER=fast: the single global spline (the same model as ferreus); default Auto
            // (partition of unity above 2,000 samples).
            solver: match std::env::var("SOLVER").as_deref() {
                Ok("fast") => SolverChoice::Fast,
                _ => SolverChoice::Auto,
            },
            ..FitOptions::default()
        };
        let start = Instant::now();
        let ours = fit(&points, &values, &options, &NoProgress);
        let ours_seconds = start.elapsed().as_secs_f64();
        let ours_error = match &ours {
            Ok((model, _)) => exact_error(&|p| p.iter().map(|&x| model.value(x)).collect()),
            Err(e) => {
                eprintln!("echosurf failed: {e}");
                f64::NAN
            }
        };

        let source = Mat::<f64>::from_fn(n, 3, |i, j| points[i][j]);
        let source_values = Mat::<f64>::from_fn(n, 1, |i, _| values[i]);
        let settings = InterpolantSettings::builder(RBFKernelType::Linear)
            .drift(Drift::Linear)
            .fitting_accuracy(FittingAccuracy {
                tolerance: accuracy,
                tolerance_type: FittingAccuracyType::Absolute,
            })
            .build();
        let start = Instant::now();
        let theirs = RBFInterpolator::builder(source, source_values, settings).build();
        let theirs_seconds = start.elapsed().as_secs_f64();
        let theirs_error = exact_error(&|p| {
            let targets = Mat::<f64>::from_fn(p.len(), 3, |i, j| p[i][j]);
            let v = theirs.evaluate(targets.as_ref());
            (0..p.len()).map(|i| v[(i, 0)]).collect()
        });
        println!(
            "{label:>9} | {ours_seconds:>12.2} {ours_error:>10.3} | {theirs_seconds:>12.2} {theirs_error:>10.3} | {:>6.1}x",
            theirs_seconds / ours_seconds
        );
    }
}
