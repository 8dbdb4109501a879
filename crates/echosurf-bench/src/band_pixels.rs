//! Band pixels as a user would feed them to `fit`: the samples of the fit benchmarks and contract tests.

use glam::DVec3;
use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;

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
    sequence: &echosurf::io::TrackedSequence,
    image_to_world: &[(usize, glam::DMat4)],
    count: usize,
    seed: u64,
) -> (Vec<DVec3>, Vec<f64>) {
    let (points, values) = all_band_pixels(sequence, image_to_world);
    if points.len() <= count {
        return (points, values);
    }
    random_subset(&points, &values, count, seed)
}

/// Every band pixel ([`all_band_pixels`]) of the sweep in `sequence_path`, its frames placed by the
/// Image->Probe calibration of the device-set XML `config_path`.
pub fn sweep_band_pixels(
    sequence_path: &std::path::Path,
    config_path: &std::path::Path,
) -> echosurf::Result<(Vec<DVec3>, Vec<f64>)> {
    use echosurf::io;
    let sequence = io::read_sequence(sequence_path)?;
    let calibration = io::read_calibration(config_path)?;
    let poses = io::resolve_poses(
        &sequence,
        Some(&calibration),
        io::ReferenceChoice::Auto,
        sequence_path,
    )?;
    let placed: Vec<_> = poses
        .poses
        .iter()
        .map(|p| (p.frame_index, p.image_to_world))
        .collect();
    Ok(all_band_pixels(&sequence, &placed))
}

/// Every band pixel of [`band_pixels`]' rule (no subset), frame by frame in `image_to_world` order.
pub fn all_band_pixels(
    sequence: &echosurf::io::TrackedSequence,
    image_to_world: &[(usize, glam::DMat4)],
) -> (Vec<DVec3>, Vec<f64>) {
    use echosurf::segment::filters::{gaussian_taps, smooth, squared_distance_capped};
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
    (points, values)
}

/// A random subset of `count` of the points with their values (all when fewer), in their order;
/// same inputs and seed, same subset.
pub fn random_subset(
    points: &[DVec3],
    values: &[f64],
    count: usize,
    seed: u64,
) -> (Vec<DVec3>, Vec<f64>) {
    if points.len() <= count {
        return (points.to_vec(), values.to_vec());
    }
    let mut order: Vec<usize> = (0..points.len()).collect();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (chosen, _) = order.partial_shuffle(&mut rng, count);
    let mut chosen = chosen.to_vec();
    chosen.sort_unstable();
    (
        chosen.iter().map(|&i| points[i]).collect(),
        chosen.iter().map(|&i| values[i]).collect(),
    )
}

/// [`band_pixels`] of a duck sweep from our own simulator (true poses, no tracking error; two sweeps of
/// `frames_per_sweep` frames of 256 x 200 px at 0.2 mm, seed `seed`), `count` of them.
pub fn simulated_band_pixels(
    count: usize,
    frames_per_sweep: usize,
    seed: u64,
) -> echosurf::Result<(Vec<DVec3>, Vec<f64>)> {
    use echosurf_sim::{SimulationOptions, simulate};
    let options = SimulationOptions {
        seed,
        frames_per_sweep,
        sweeps: Some(2),
        compress: false,
        ..SimulationOptions::default()
    }
    .without_errors();
    let sim = simulate(&options, &echosurf::progress::NoProgress)?;
    let poses: Vec<(usize, glam::DMat4)> = sim
        .true_image_to_world
        .iter()
        .copied()
        .enumerate()
        .collect();
    Ok(band_pixels(&sim.sequence, &poses, count, seed))
}
