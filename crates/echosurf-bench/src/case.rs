//! Benchmark cases: a simulated phantom at a noise level, or a user's sweep with its truth.

use glam::DMat4;

use echosurf::Result;
use echosurf::io::{Calibration, TrackedSequence, resolve_poses};
use echosurf::mesh::Mesh;
use echosurf::pipeline::{IsoLevels, VoxelRouteOptions};
use echosurf::progress::NoProgress;
use echosurf_sim::{PhantomKind, SimulationOptions, TrackingErrors, simulate};

/// Speckle / noise level of a simulated case.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub enum NoiseLevel {
    /// Noise floor 6 dB lower, half the surface roughness, half the tracker noise.
    Low,
    /// The simulator's defaults.
    Default,
    /// Noise floor 8 dB higher, 1.5x roughness, brighter water speckle (+4 dB), 3x tracker noise.
    High,
}

impl NoiseLevel {
    pub const ALL: [NoiseLevel; 3] = [NoiseLevel::Low, NoiseLevel::Default, NoiseLevel::High];

    pub fn name(self) -> &'static str {
        match self {
            NoiseLevel::Low => "low",
            NoiseLevel::Default => "default",
            NoiseLevel::High => "high",
        }
    }

    /// Applies this level to simulation options (acoustics and tracking errors).
    pub fn apply(self, options: &mut SimulationOptions) {
        let defaults = TrackingErrors::default();
        match self {
            NoiseLevel::Default => {}
            NoiseLevel::Low => {
                options.acoustics.noise_db -= 6.0;
                options.acoustics.roughness *= 0.5;
                options.errors.tracker_noise_mm = 0.5 * defaults.tracker_noise_mm;
                options.errors.tracker_noise_deg = 0.5 * defaults.tracker_noise_deg;
            }
            NoiseLevel::High => {
                options.acoustics.noise_db += 8.0;
                options.acoustics.roughness *= 1.5;
                options.acoustics.water.scatter_db += 4.0;
                options.errors.tracker_noise_mm = 3.0 * defaults.tracker_noise_mm;
                options.errors.tracker_noise_deg = 3.0 * defaults.tracker_noise_deg;
            }
        }
    }
}

/// A sequence with its calibration and ground truth.
#[derive(Debug, Clone)]
pub struct BenchCase {
    pub name: String,
    pub sequence: TrackedSequence,
    pub calibration: Calibration,
    /// All true surfaces merged into one mesh.
    pub truth: Mesh,
    /// Where every used frame's image really was (Image -> World), for the completeness mask.
    pub true_image_to_world: Vec<DMat4>,
}

/// Settings of a benchmark run.
#[derive(Debug, Clone)]
pub struct BenchOptions {
    /// Small images and few frames: a CI-sized run.
    pub quick: bool,
    /// Iso-level for both routes; `Auto` = each route's own automatic level.
    pub iso: IsoLevels,
    /// RBF route's decimation target.
    pub max_samples: usize,
    pub voxel: VoxelRouteOptions,
    pub seed: u64,
}

impl Default for BenchOptions {
    fn default() -> Self {
        BenchOptions {
            quick: false,
            iso: IsoLevels::Auto,
            max_samples: 100_000,
            voxel: VoxelRouteOptions::default(),
            seed: 1,
        }
    }
}

/// Simulation settings of a benchmark phantom: the simulator's defaults, or in quick mode 128 x 100 px
/// at 0.4 mm and 20 frames per sweep.
pub fn simulation_options(
    phantom: PhantomKind,
    noise: NoiseLevel,
    quick: bool,
    seed: u64,
) -> SimulationOptions {
    let mut options = SimulationOptions {
        phantom,
        seed,
        ..SimulationOptions::default()
    };
    if quick {
        options.frames_per_sweep = 20;
        options.width_px = 128;
        options.height_px = 100;
        options.pixel_size_mm = 0.4;
        options.truth_resolution_mm = 1.0;
    }
    noise.apply(&mut options);
    options
}

/// Simulates one benchmark case.
pub fn simulated_case(
    phantom: PhantomKind,
    noise: NoiseLevel,
    quick: bool,
    seed: u64,
) -> Result<BenchCase> {
    let name = format!("{} / {}", phantom.name(), noise.name());
    let options = simulation_options(phantom, noise, quick, seed);
    let sim = simulate(&options, &NoProgress)?;
    Ok(BenchCase {
        name,
        sequence: sim.sequence,
        calibration: sim.calibration_written,
        truth: echosurf_sim::merged_truth(&sim.truth),
        true_image_to_world: sim.true_image_to_world,
    })
}

/// A user case: the recorded poses stand in for the true ones in the completeness mask.
pub fn user_case(
    name: String,
    sequence: TrackedSequence,
    calibration: Calibration,
    truth: Mesh,
) -> Result<BenchCase> {
    let poses = resolve_poses(
        &sequence,
        Some(&calibration),
        echosurf::io::ReferenceChoice::Auto,
        std::path::Path::new(&name),
    )?;
    let true_image_to_world = poses.poses.iter().map(|p| p.image_to_world).collect();
    Ok(BenchCase {
        name,
        sequence,
        calibration,
        truth,
        true_image_to_world,
    })
}
