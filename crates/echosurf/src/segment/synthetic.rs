//! A small synthetic sweep generator for tests and benchmarks: frames of one curved bright boundary (a
//! bone-like echo with an acoustic shadow below) under multiplicative Rayleigh speckle, with the true
//! boundary curve of every frame. Not a physical simulator (that is the `echosurf-sim` crate).

use glam::{DMat4, DVec3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::io::{
    FramePose, FrameTransform, PixelData, PoseResolution, TrackedFrame, TrackedSequence,
};

/// A synthetic sweep and its truth.
#[derive(Debug, Clone)]
pub struct SyntheticSweep {
    pub sequence: TrackedSequence,
    pub poses: PoseResolution,
    pub pixel_size_mm: f64,
    /// True boundary row `v = boundary(frame, u)` for every frame, as a closure-free table: per frame,
    /// the curve's parameters (base row, amplitude, spatial frequency, phase).
    pub curves: Vec<[f64; 4]>,
}

impl SyntheticSweep {
    /// Row of the true boundary at (possibly fractional) column `u` of `frame`.
    pub fn boundary_row(&self, frame: usize, u: f64) -> f64 {
        let [base, amp, freq, phase] = self.curves[frame];
        base + amp * (freq * u + phase).sin()
    }

    /// Euclidean distance (px) from pixel (u, v) to the true boundary curve of `frame`, searched over
    /// columns within `reach_px` of u (exact to the 0.02 px sampling).
    pub fn distance_to_boundary_px(&self, frame: usize, u: usize, v: usize, reach_px: f64) -> f64 {
        let steps = (2.0 * reach_px / 0.02).ceil() as usize;
        (0..=steps)
            .map(|k| {
                let x = u as f64 - reach_px + k as f64 * 0.02;
                let y = self.boundary_row(frame, x);
                ((x - u as f64).powi(2) + (y - v as f64).powi(2)).sqrt()
            })
            .fold(f64::INFINITY, f64::min)
    }
}

/// `frames` frames of `width x height` at `pixel_size_mm`; the boundary moves down by `drift_px` per frame
/// and its shape changes slowly. Deterministic in `seed`.
pub fn synthetic_sweep(
    width: usize,
    height: usize,
    frames: usize,
    pixel_size_mm: f64,
    drift_px: f64,
    seed: u64,
) -> SyntheticSweep {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let curves: Vec<[f64; 4]> = (0..frames)
        .map(|k| {
            [
                0.42 * height as f64 + drift_px * k as f64,
                0.12 * height as f64,
                2.0 * std::f64::consts::PI * 1.3 / width as f64,
                0.25 * k as f64,
            ]
        })
        .collect();
    let mut pixels = Vec::with_capacity(width * height * frames);
    for c in &curves {
        let [base, amp, freq, phase] = *c;
        for v in 0..height {
            for u in 0..width {
                let b = base + amp * (freq * u as f64 + phase).sin();
                let dv = v as f64 - b;
                // Tissue background, a bright specular echo ~0.4 mm thick at the boundary, shadow below.
                let tissue = if dv > 4.0 { 12.0 } else { 45.0 };
                let echo = 190.0 * (-(dv * dv) / (2.0 * 2.5 * 2.5)).exp();
                // Rayleigh speckle of unit mean: sqrt(-2 ln U) has mean sqrt(pi/2) = 1.2533.
                let r = (-2.0 * (1.0 - rng.random::<f64>()).ln()).sqrt() / 1.2533;
                pixels.push(((tissue + echo) * r).clamp(0.0, 255.0) as u8);
            }
        }
    }
    let image_to_probe = DMat4::from_scale(DVec3::new(pixel_size_mm, pixel_size_mm, 1.0));
    let mut seq_frames = Vec::with_capacity(frames);
    let mut poses = Vec::with_capacity(frames);
    for k in 0..frames {
        // Probe translates 0.5 mm per frame along the elevational axis.
        let probe_to_world = DMat4::from_translation(DVec3::new(0.0, 0.0, 0.5 * k as f64));
        let mut frame = TrackedFrame {
            timestamp_s: Some(0.05 * k as f64),
            image_valid: true,
            ..Default::default()
        };
        frame.transforms.insert(
            "ProbeToTracker".into(),
            FrameTransform {
                matrix: probe_to_world,
                valid: true,
            },
        );
        seq_frames.push(frame);
        poses.push(FramePose {
            frame_index: k,
            image_to_world: probe_to_world * image_to_probe,
        });
    }
    SyntheticSweep {
        sequence: TrackedSequence {
            width,
            height,
            channels: 1,
            orientation: "MF".into(),
            frames: seq_frames,
            pixels: PixelData::U8(pixels),
            header: Default::default(),
        },
        poses: PoseResolution {
            poses,
            skipped: Vec::new(),
            world_frame: "Tracker".into(),
        },
        pixel_size_mm,
        curves,
    }
}
