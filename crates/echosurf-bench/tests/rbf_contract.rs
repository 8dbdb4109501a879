//! The accuracy contract on band pixels of a simulated sweep: every solver meets the requested accuracy
//! at every sample, checked by an evaluation written here from the model's definition (no BVH, no
//! treecode, a sum over every centre), or refuses with the achieved figure.

use echosurf::progress::NoProgress;
use echosurf::rbf::{FitOptions, SolverChoice, definition_max_misfit, fit};
use echosurf::surface::{ScalarField, SurfaceDomain, SurfaceOptions, extract_surfaces_with_stats};
use echosurf_bench::simulated_band_pixels;
use glam::DVec3;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// `count` (at most 12,000) band pixels of a short simulated duck sweep (two sweeps of 12 frames); the
/// sweep is simulated once per test process.
fn band(count: usize) -> (Vec<DVec3>, Vec<f64>) {
    static BAND: std::sync::OnceLock<(Vec<DVec3>, Vec<f64>)> = std::sync::OnceLock::new();
    let (pts, vals) =
        BAND.get_or_init(|| simulated_band_pixels(12_000, 12, 3).expect("simulated band pixels"));
    // A random subset of a random subset: the first `count` after a seeded shuffle.
    let mut order: Vec<usize> = (0..pts.len()).collect();
    order.shuffle(&mut ChaCha8Rng::seed_from_u64(count as u64));
    order.truncate(count);
    (
        order.iter().map(|&i| pts[i]).collect(),
        order.iter().map(|&i| vals[i]).collect(),
    )
}

fn options(solver: SolverChoice, accuracy: f64) -> FitOptions {
    FitOptions {
        smoothing: 0.0,
        accuracy,
        solver,
        ..FitOptions::default()
    }
}

#[test]
fn partition_of_unity_meets_the_accuracy_at_every_band_pixel() {
    let (pts, vals) = band(12_000);
    assert_eq!(pts.len(), 12_000);
    // Small leaves make the patch cap bite everywhere (the case that dropped samples inside supports).
    for leaf in [16, 64] {
        let opts = FitOptions {
            pu_leaf_points: leaf,
            ..options(SolverChoice::PartitionOfUnity, 1.0)
        };
        let (model, report) = fit(&pts, &vals, &opts, &NoProgress).expect("pu fit");
        let misfit = definition_max_misfit(&model, &pts, &vals, opts.merge_distance_mm);
        assert!(
            misfit <= 1.0,
            "leaf {leaf}: max misfit {misfit} by the reference evaluation (report {})",
            report.max_residual
        );
        assert!((misfit - report.max_residual).abs() <= 1e-6 + 1e-6 * misfit);
    }
}

#[test]
fn every_solver_meets_the_accuracy_or_refuses_on_3000_band_pixels() {
    let (pts, vals) = band(3_000);
    for solver in [
        SolverChoice::Direct,
        SolverChoice::PartitionOfUnity,
        SolverChoice::Fast,
        SolverChoice::Auto,
    ] {
        let opts = options(solver, 1.0);
        match fit(&pts, &vals, &opts, &NoProgress) {
            Ok((model, report)) => {
                let misfit = definition_max_misfit(&model, &pts, &vals, opts.merge_distance_mm);
                assert!(misfit <= 1.0, "{solver:?}: reference max misfit {misfit}");
                assert!(report.max_residual <= 1.0, "{solver:?}: {report:?}");
            }
            Err(e) => {
                let text = e.to_string();
                assert!(
                    text.contains("accuracy") && text.contains("grey"),
                    "{solver:?} refused without the figure: {text}"
                );
            }
        }
    }
}

#[test]
fn fast_and_direct_agree_within_the_accuracy_on_3000_band_pixels() {
    let (pts, vals) = band(3_000);
    let accuracy = 1.0;
    // At w = 0, as the contract is stated: both interpolate the speckle to within the accuracy, and
    // between the samples they must still agree.
    let fit_with = |solver| {
        fit(&pts, &vals, &options(solver, accuracy), &NoProgress)
            .expect("fit")
            .0
    };
    let direct = fit_with(SolverChoice::Direct);
    let fast = fit_with(SolverChoice::Fast);
    let lo = pts
        .iter()
        .fold(DVec3::splat(f64::INFINITY), |a, p| a.min(*p));
    let hi = pts
        .iter()
        .fold(DVec3::splat(f64::NEG_INFINITY), |a, p| a.max(*p));
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    // Random points near the samples (the field is only used within a few mm of the data).
    let probes: Vec<DVec3> = (0..10_000)
        .map(|_| {
            let p = pts[rng.random_range(0..pts.len())];
            (p + DVec3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            ))
            .clamp(lo, hi)
        })
        .collect();
    let a = direct.values(&probes);
    let b = fast.values(&probes);
    let worst = a
        .iter()
        .zip(&b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max);
    assert!(worst <= accuracy, "fast vs direct: max difference {worst}");
}

#[test]
fn an_accuracy_out_of_reach_is_refused_with_the_achieved_figure() {
    let (pts, vals) = band(3_000);
    let err = fit(
        &pts,
        &vals,
        &options(SolverChoice::PartitionOfUnity, 1e-13),
        &NoProgress,
    )
    .expect_err("round-off exceeds 1e-13 grey");
    let text = err.to_string();
    assert!(
        text.contains("above the requested accuracy 0.0000000000001")
            && text.contains("FitOptions::solver to fast")
            && err.options().contains(&echosurf::OptionName::FitSolver),
        "{text}"
    );
    let err = fit(
        &pts,
        &vals,
        &FitOptions {
            max_iterations: 1,
            ..options(SolverChoice::Fast, 0.01)
        },
        &NoProgress,
    )
    .expect_err("one iteration cannot reach 0.01");
    assert!(err.to_string().contains("max residual"), "{err}");
}

/// A clean echo shell: samples within 3 mm of a sphere of radius 12 mm, grey level of a Gaussian echo
/// (peak 130 on the sphere over a background of 15).
fn echo_shell(n: usize, seed: u64) -> (Vec<DVec3>, Vec<f64>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut pts = Vec::with_capacity(n);
    let mut vals = Vec::with_capacity(n);
    while pts.len() < n {
        let d = DVec3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        );
        if d.length_squared() > 1.0 || d.length_squared() < 1e-6 {
            continue;
        }
        let r = 12.0 + rng.random_range(-3.0..3.0);
        let p = d.normalize() * r;
        let distance_mm: f64 = r - 12.0;
        pts.push(p);
        vals.push(15.0 + 115.0 * (-(distance_mm / 1.5).powi(2)).exp());
    }
    (pts, vals)
}

#[test]
fn every_vertex_of_a_shell_surface_lies_on_its_level() {
    let (pts, vals) = echo_shell(10_000, 7);
    let opts = options(SolverChoice::PartitionOfUnity, 0.5);
    let (model, _) = fit(&pts, &vals, &opts, &NoProgress).expect("fit");
    let domain = SurfaceDomain {
        bounds_min_mm: DVec3::splat(-16.0),
        bounds_max_mm: DVec3::splat(16.0),
        seeds: pts.clone(),
        trust_points: pts.clone(),
    };
    let (meshes, stats) =
        extract_surfaces_with_stats(&model, &[50.0], &domain, &SurfaceOptions::default())
            .expect("surface");
    assert!(meshes[0].triangles.len() > 1000);
    eprintln!("shell level stats: {:?}", stats.levels[0]);
    assert_eq!(
        stats.levels[0].off_level_vertices, 0,
        "{:?}",
        stats.levels[0]
    );
    let mut values = vec![0.0; meshes[0].vertices.len()];
    ScalarField::values(&model, &meshes[0].vertices, &mut values);
    let worst = values.iter().map(|v| (v - 50.0).abs()).fold(0.0, f64::max);
    assert!(worst <= 0.5, "worst vertex {worst} grey off the level");
    assert!((worst - stats.levels[0].max_level_error).abs() < 1e-9);
}
