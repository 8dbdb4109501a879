//! Ultrasound-like benchmark samples: ~100 tilted, irregularly spaced planar frames through an ellipsoid,
//! with an echo-like intensity of the distance to its surface and multiplicative speckle.

use glam::{DQuat, DVec3};
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

/// Semi-axes (mm) of the benchmark ellipsoid, centred at the origin.
pub const BENCH_ELLIPSOID_MM: DVec3 = DVec3::new(30.0, 20.0, 15.0);

/// `n` samples (positions in mm, grey levels 0..255) on 100 frames; same `n` and `seed` give the same data.
pub fn ultrasound_like_samples(n: usize, seed: u64) -> (Vec<DVec3>, Vec<f64>) {
    let frames = 100.min(n.max(1));
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let speckle = Normal::new(1.0, 0.25).expect("valid normal");
    let mut points = Vec::with_capacity(n);
    let mut values = Vec::with_capacity(n);
    // Irregular sweep: frame positions along z with jittered steps, small random tilts.
    let mut z = -22.0;
    let mean_step = 44.0 / frames as f64;
    for f in 0..frames {
        let count = n / frames + usize::from(f < n % frames);
        let tilt = DQuat::from_rotation_x(rng.random_range(-0.05..0.05))
            * DQuat::from_rotation_y(rng.random_range(-0.05..0.05));
        let centre = DVec3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), z);
        z += mean_step * rng.random_range(0.4..1.6);
        // A rectangular image of 80 x 60 mm sampled on a regular pixel grid with ~count pixels.
        let cols = ((count as f64 * 4.0 / 3.0).sqrt().ceil() as usize).max(1);
        let rows = count.div_ceil(cols).max(1);
        for k in 0..count {
            let (r, c) = (k / cols, k % cols);
            let u = -40.0 + 80.0 * (c as f64 + 0.5) / cols as f64;
            let v = -30.0 + 60.0 * (r as f64 + 0.5) / rows as f64;
            let p = centre + tilt * DVec3::new(u, v, 0.0);
            let q = p / BENCH_ELLIPSOID_MM;
            let distance_mm = (q.length() - 1.0) * BENCH_ELLIPSOID_MM.min_element();
            let echo = 15.0
                + 115.0 * (-(distance_mm / 1.5).powi(2)).exp()
                + if distance_mm < 0.0 { 25.0 } else { 0.0 };
            let value = (echo * speckle.sample(&mut rng)).clamp(0.0, 255.0);
            points.push(p);
            values.push(value);
        }
    }
    (points, values)
}

/// One row of [`bench_fit_scaling`].
#[derive(Debug, Clone, serde::Serialize)]
pub struct ScalingRow {
    pub samples: usize,
    pub fit_seconds: f64,
    pub iterations: usize,
    pub max_residual: f64,
    pub rms_residual: f64,
    pub solver: super::SolverChoice,
    /// Partition-of-unity patches (0 for global solvers).
    pub patches: usize,
    pub mean_patch_points: f64,
    /// Time to evaluate values and gradients at `samples` fresh points.
    pub eval_seconds: f64,
    pub solver_bytes_per_sample: f64,
    /// Time breakdown of the global fast solver (None for the other solvers).
    pub fast_breakdown: Option<super::FastBreakdown>,
}

/// Fits [`ultrasound_like_samples`] of each size with `options` and times fit and evaluation.
pub fn bench_fit_scaling(
    sizes: &[usize],
    options: &super::FitOptions,
    seed: u64,
) -> crate::Result<Vec<ScalingRow>> {
    let mut rows = Vec::new();
    for &n in sizes {
        let (points, values) = ultrasound_like_samples(n, seed);
        let (model, report) = super::fit(&points, &values, options, &crate::progress::NoProgress)?;
        let (probes, _) = ultrasound_like_samples(n, seed.wrapping_add(1));
        let start = std::time::Instant::now();
        let (v, _) = model.values_and_gradients(&probes);
        let eval_seconds = start.elapsed().as_secs_f64();
        debug_assert_eq!(v.len(), n);
        rows.push(ScalingRow {
            samples: n,
            fit_seconds: report.fit_seconds,
            iterations: report.iterations,
            max_residual: report.max_residual,
            rms_residual: report.rms_residual,
            solver: report.solver,
            patches: report.patches,
            mean_patch_points: report.mean_patch_points,
            eval_seconds,
            solver_bytes_per_sample: report.solver_bytes as f64 / n as f64,
            fast_breakdown: report.fast_breakdown,
        });
    }
    Ok(rows)
}

/// The issue-27 band-pixel rule: frame smoothed with a Gaussian of this sigma (px), ...
pub const BAND_SMOOTHING_SIGMA_PX: f64 = 2.0;
/// ... pixels of the smoothed frame above this grey level seed the band, ...
pub const BAND_THRESHOLD_GREY: f32 = 45.0;
/// ... and the seeds are dilated by this Euclidean radius (px).
pub const BAND_DILATION_PX: u32 = 10;

/// Band pixels of a tracked sweep, as a user would feed them to `fit`: every frame smoothed with a
/// [`BAND_SMOOTHING_SIGMA_PX`] Gaussian, thresholded at [`BAND_THRESHOLD_GREY`], dilated by
/// [`BAND_DILATION_PX`]; the kept pixels' *raw* grey levels at their world positions (mm), then a random
/// subset of `count` of them (all if fewer). Frames cross, so pixels of different frames nearly coincide.
/// `image_to_world` lists (frame index, Image -> World); same inputs and seed give the same samples.
pub fn band_pixels(
    sequence: &crate::io::TrackedSequence,
    image_to_world: &[(usize, glam::DMat4)],
    count: usize,
    seed: u64,
) -> (Vec<DVec3>, Vec<f64>) {
    use crate::segment::filters::{gaussian_taps, smooth, squared_distance_capped};
    let (w, h) = (sequence.width, sequence.height);
    let taps = gaussian_taps(BAND_SMOOTHING_SIGMA_PX);
    let (mut tmp, mut smoothed, mut column, mut distance) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let mut points = Vec::new();
    let mut values = Vec::new();
    let radius_sq = (BAND_DILATION_PX * BAND_DILATION_PX) as f32;
    for &(f, m) in image_to_world {
        if f >= sequence.frames.len() || sequence.is_tracking_only() {
            continue;
        }
        let raw = sequence.frame_f32(f);
        smooth(&raw, w, h, &taps, &mut tmp, &mut smoothed);
        let seeds = smoothed
            .iter()
            .enumerate()
            .filter(|(_, v)| **v > BAND_THRESHOLD_GREY)
            .map(|(i, _)| i);
        squared_distance_capped(
            seeds,
            w,
            h,
            BAND_DILATION_PX + 1,
            &mut column,
            &mut distance,
        );
        for (i, d) in distance.iter().enumerate() {
            if *d <= radius_sq {
                let (u, v) = ((i % w) as f64, (i / w) as f64);
                points.push(m.transform_point3(DVec3::new(u, v, 0.0)));
                values.push(f64::from(raw[i]));
            }
        }
    }
    if points.len() > count {
        let mut order: Vec<usize> = (0..points.len()).collect();
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let (chosen, _) = order.partial_shuffle(&mut rng, count);
        let mut chosen = chosen.to_vec();
        chosen.sort_unstable();
        points = chosen.iter().map(|&i| points[i]).collect();
        values = chosen.iter().map(|&i| values[i]).collect();
    }
    (points, values)
}

/// [`band_pixels`] of a duck sweep from our own simulator (true poses, no tracking error; two sweeps of
/// `frames_per_sweep` frames of 256 x 200 px at 0.2 mm, seed `seed`), `count` of them.
pub fn simulated_band_pixels(
    count: usize,
    frames_per_sweep: usize,
    seed: u64,
) -> crate::Result<(Vec<DVec3>, Vec<f64>)> {
    use crate::simulate::{SimulationOptions, simulate};
    let options = SimulationOptions {
        seed,
        frames_per_sweep,
        sweeps: Some(2),
        compress: false,
        ..SimulationOptions::default()
    }
    .without_errors();
    let sim = simulate(&options, &crate::progress::NoProgress)?;
    let poses: Vec<(usize, glam::DMat4)> = sim
        .true_image_to_world
        .iter()
        .copied()
        .enumerate()
        .collect();
    Ok(band_pixels(&sim.sequence, &poses, count, seed))
}

/// `s(x)` from the definition of the fitted model, written apart from the model's evaluator (no BVH, no
/// treecode, a sum over every centre): for a global spline the trend plus the sum over all centres; for
/// partition of unity the Wendland-weighted blend over *all* patches of their local sums.
pub fn definition_value(model: &super::RbfModel, x: DVec3) -> f64 {
    match model.partition_of_unity() {
        None => {
            let (c0, c, origin) = model.trend();
            c0 + c.dot(x - origin)
                + model
                    .centres()
                    .iter()
                    .zip(model.coefficients())
                    .map(|(p, l)| l * (x - *p).length())
                    .sum::<f64>()
        }
        Some(pu) => {
            let xc = x.clamp(pu.root_lo, pu.root_hi);
            let (mut sum_w, mut sum_ws) = (0.0, 0.0);
            for j in 0..pu.patches() {
                let t = (xc - pu.support_centre[j]).abs() / pu.support_half[j];
                if t.max_element() >= 1.0 {
                    continue;
                }
                let phi = |t: f64| (1.0 - t).powi(4) * (4.0 * t + 1.0);
                let w = phi(t.x) * phi(t.y) * phi(t.z);
                let rel = x - pu.support_centre[j];
                let mut s = pu.constant[j] + pu.linear[j].dot(rel);
                for k in pu.offsets[j]..pu.offsets[j + 1] {
                    let d = rel - DVec3::new(pu.xs[k], pu.ys[k], pu.zs[k]);
                    s += pu.coefficients[k] * d.length();
                }
                sum_w += w;
                sum_ws += w * s;
            }
            sum_ws / sum_w
        }
    }
}

/// Largest |f_i - s(x_i)| over the merged samples, by [`definition_value`] (w = 0): the contract check
/// of the tests and the band-pixel benchmark, independent of the model's own evaluator.
pub fn definition_max_misfit(
    model: &super::RbfModel,
    pts: &[DVec3],
    vals: &[f64],
    merge_mm: f64,
) -> f64 {
    let (pts, vals) = super::merge_near_duplicates(pts, vals, merge_mm);
    use rayon::prelude::*;
    pts.par_iter()
        .zip(&vals)
        .map(|(p, f)| (f - definition_value(model, *p)).abs())
        .reduce(|| 0.0, f64::max)
}
