//! Phantom simulator: tracked B-mode sweeps of known shapes with ground truth.
//!
//! [`simulate`] moves a linear probe over a phantom ([`phantom`]) along freehand sweeps ([`sweep`]), forms
//! each B-mode frame ([`bmode`]) from the *true* poses and calibration, then records what a real system
//! would: poses with tracker noise and a calibration with an error ([`errors`]). [`write_simulation`]
//! writes the PLUS sequence, the calibration, the true surfaces and a JSON description ([`output`]).
//!
//! World = Tracker frame = the phantom's frame at t = 0 (mm, z up). Every random quantity comes from a
//! stream seeded by `(seed, purpose)` or `(seed, frame index)`, and frames are formed in parallel into
//! their own slots, so the output is identical whatever the thread count.

pub mod bmode;
pub mod errors;
pub mod mesh_sdf;
pub mod output;
pub mod phantom;
pub mod sweep;

use std::ops::Range;

use glam::{DMat3, DMat4, DVec3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

pub use bmode::{
    Acoustics, Frame, FrameFormer, ImageGrid, LevelSums, Material, PhysicsPreset, Surround,
};
pub use errors::TrackingErrors;
pub use output::{
    SimulationFiles, SimulationNames, merged_truth, write_preview, write_simulation,
    write_simulation_as,
};
pub use phantom::{Phantom, PhantomKind, build_phantom, phantom_sdf};
pub use sweep::{HandMotion, SweepSpec};

use echosurf::io::{Calibration, FrameTransform, PixelData, TrackedFrame, TrackedSequence};
use echosurf::mesh::Mesh;
use echosurf::progress::Progress;
use echosurf::{Error, Result};

/// Everything that defines a simulation. Same options (including `seed`) => identical output bytes.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SimulationOptions {
    pub phantom: PhantomKind,
    pub seed: u64,
    pub frames_per_sweep: usize,
    /// Number of sweeps; `None` plans enough to cover the object (top passes plus two side sweeps).
    pub sweeps: Option<usize>,
    pub width_px: usize,
    pub height_px: usize,
    /// Square pixels (mm).
    pub pixel_size_mm: f64,
    pub acoustics: Acoustics,
    pub motion: HandMotion,
    pub errors: TrackingErrors,
    /// Lattice spacing of the truth surfaces' extraction (mm). The surfacer puts every vertex back on the
    /// zero level, so the truth's error is the chord sagitta, edge^2 / (8 * radius of curvature): at the
    /// default 0.5 mm it is 0.003 mm on the duck's head (r = 11 mm) and ~0.02 mm inside its beak; 0.25 mm
    /// costs four times the time for no visible gain.
    pub truth_resolution_mm: f64,
    /// zlib-compress the written sequence.
    pub compress: bool,
}

impl Default for SimulationOptions {
    /// The duck with a 7 MHz probe, 256 x 200 px at 0.2 mm, three sweeps of 60 frames.
    fn default() -> Self {
        SimulationOptions {
            phantom: PhantomKind::Duck,
            seed: 1,
            frames_per_sweep: 60,
            sweeps: None,
            width_px: 256,
            height_px: 200,
            pixel_size_mm: 0.2,
            acoustics: Acoustics::default(),
            motion: HandMotion::default(),
            errors: TrackingErrors::default(),
            truth_resolution_mm: 0.5,
            compress: true,
        }
    }
}

impl SimulationOptions {
    /// Turns every tracking error and untracked motion off: a perfect system.
    pub fn without_errors(mut self) -> Self {
        self.errors = TrackingErrors::none();
        self.motion.object_motion_mm = 0.0;
        self
    }

    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(Error::InvalidInput(format!("simulate: {m}")));
        if !(1..=100_000).contains(&self.frames_per_sweep) {
            return bad(format!(
                "frames per sweep must be 1..=100000 (got {})",
                self.frames_per_sweep
            ));
        }
        if let Some(n) = self.sweeps
            && !(1..=1000).contains(&n)
        {
            return bad(format!("sweeps must be 1..=1000 (got {n})"));
        }
        if !(8..=4096).contains(&self.width_px) || !(8..=4096).contains(&self.height_px) {
            return bad(format!(
                "image size must be 8..=4096 px each way (got {} x {})",
                self.width_px, self.height_px
            ));
        }
        if !(self.pixel_size_mm.is_finite() && (0.01..=5.0).contains(&self.pixel_size_mm)) {
            return bad(format!(
                "pixel size must be in [0.01, 5] mm (got {})",
                self.pixel_size_mm
            ));
        }
        if !(self.truth_resolution_mm.is_finite()
            && (0.05..=10.0).contains(&self.truth_resolution_mm))
        {
            return bad(format!(
                "truth resolution must be in [0.05, 10] mm (got {})",
                self.truth_resolution_mm
            ));
        }
        let frames = self.frames_per_sweep as u128 * self.sweeps.unwrap_or(8) as u128;
        let bytes = frames * self.width_px as u128 * self.height_px as u128;
        if bytes > 8 << 30 {
            return Err(Error::ResourceLimit(format!(
                "simulate: {frames} frames of {} x {} px would need {} GiB; reduce frames or image size",
                self.width_px,
                self.height_px,
                bytes >> 30
            )));
        }
        self.acoustics.validate().or_else(bad)?;
        self.motion.validate().or_else(bad)?;
        self.errors.validate().or_else(bad)?;
        Ok(())
    }
}

/// A simulated recording with its ground truth.
#[derive(Debug, Clone)]
pub struct Simulation {
    /// Frames (MF, 8 bit) with the *recorded* ProbeToTracker poses (tracker noise included).
    pub sequence: TrackedSequence,
    /// The calibration as written (with the calibration error).
    pub calibration_written: Calibration,
    /// The calibration the images were formed with.
    pub calibration_true: Calibration,
    /// True surfaces (mm, world): ("outer", ..) and ("inner", ..) for the duck, one for solid phantoms.
    pub truth: Vec<(String, Mesh)>,
    /// Iso-level between background and boundary (30 % of the way up, the paper's 50 for 15 / 130).
    pub suggested_iso: f64,
    /// Mean grey level of water away from the object and out of shadows.
    pub background_level: f64,
    /// Mean grey level on boundaries facing the beam (cos theta > 0.9), out of shadows.
    pub boundary_level: f64,
    /// True Image -> World of every frame, in the frame of the truth (the object at t = 0): where the
    /// pixels really were, untracked object motion included.
    pub true_image_to_world: Vec<DMat4>,
    /// Frame ranges of the sweeps, and their plans.
    pub sweeps: Vec<Range<usize>>,
    pub sweep_specs: Vec<SweepSpec>,
    /// Bounds of the phantom (mm).
    pub phantom_bounds: (DVec3, DVec3),
}

/// Seeds of the independent random streams.
fn stream_seed(seed: u64, purpose: u64, index: u64) -> u64 {
    let mut z = seed ^ purpose.wrapping_mul(0x9e37_79b9_7f4a_7c15);
    z = z.wrapping_add(index.wrapping_mul(0xd1b5_4a32_d192_ed03));
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

const STREAM_PLAN: u64 = 1;
const STREAM_CALIBRATION: u64 = 2;
const STREAM_TRACKER: u64 = 3;
const STREAM_NOISE: u64 = 4;
const STREAM_SCATTER: u64 = 5;
const STREAM_OBJECT: u64 = 6;

/// The true Image -> Probe transform of the simulated probe: pixel pitch, a marker 30 mm above the image
/// with a small mounting rotation, as a real calibration would find.
pub fn true_image_to_probe(width_px: usize, pixel_size_mm: f64) -> DMat4 {
    let rotation = DMat3::from_euler(
        glam::EulerRot::XYZ,
        0.8f64.to_radians(),
        -1.2f64.to_radians(),
        2.0f64.to_radians(),
    );
    let half_width = 0.5 * (width_px as f64 - 1.0) * pixel_size_mm;
    DMat4::from_mat3_translation(
        rotation * DMat3::from_diagonal(DVec3::splat(pixel_size_mm)),
        DVec3::new(-half_width, 30.0, 4.0),
    )
}

/// Simulates the sweeps and extracts the true surfaces.
pub fn simulate(options: &SimulationOptions, progress: &dyn Progress) -> Result<Simulation> {
    let phantom = build_phantom(&options.phantom)?;
    let mut sim = simulate_sweeps_with(phantom.as_ref(), options, progress)?;
    sim.truth = output::truth_meshes(phantom.as_ref(), options.truth_resolution_mm, progress)?;
    if phantom.probe_side_only() {
        for (_, mesh) in &mut sim.truth {
            keep_probe_side(mesh);
        }
    }
    Ok(sim)
}

/// Keeps the triangles whose outward normal points up (z > 0), toward a probe above: the side of a bone
/// an ultrasound scan can show. The normal is the winding's (outward on the truth surfaces, and the one
/// `compare` uses).
pub fn keep_probe_side(mesh: &mut Mesh) {
    let n = mesh.vertices.len();
    let keep: Vec<bool> = mesh
        .triangles
        .iter()
        .map(|t| {
            if t.iter().any(|&i| i as usize >= n) {
                return false;
            }
            let [a, b, c] = t.map(|i| i as usize);
            (mesh.vertices[b] - mesh.vertices[a])
                .cross(mesh.vertices[c] - mesh.vertices[a])
                .z
                > 0.0
        })
        .collect();
    mesh.retain_triangles(&keep);
}

/// Simulates the sweeps only (`truth` left empty): what the benchmark times.
pub fn simulate_sweeps(options: &SimulationOptions, progress: &dyn Progress) -> Result<Simulation> {
    let phantom = build_phantom(&options.phantom)?;
    simulate_sweeps_with(phantom.as_ref(), options, progress)
}

fn simulate_sweeps_with(
    phantom: &dyn Phantom,
    options: &SimulationOptions,
    progress: &dyn Progress,
) -> Result<Simulation> {
    options.validate()?;
    let (width, height, pitch) = (options.width_px, options.height_px, options.pixel_size_mm);
    let probe = sweep::ProbeGeometry {
        width_mm: (width - 1) as f64 * pitch,
        depth_mm: (height - 1) as f64 * pitch,
    };
    let bounds = phantom.bounds();
    let mut specs = sweep::plan_sweeps(
        bounds,
        probe.width_mm,
        options.motion.side_tilt_deg,
        options.sweeps,
    );
    if phantom.probe_side_only() && options.sweeps.is_none() {
        // A bone is scanned from one side: the top passes, no side sweeps looking under it.
        specs.retain(|s| s.tilt_deg == 0.0);
    }

    // Poses, sweep after sweep, 3 s apart.
    let mut plan_rng = ChaCha8Rng::seed_from_u64(stream_seed(options.seed, STREAM_PLAN, 0));
    let mut placements = Vec::new();
    let mut sweeps = Vec::new();
    let mut time_s = 0.0;
    for spec in &specs {
        let start = placements.len();
        let sweep = sweep::sweep_placements(
            &mut plan_rng,
            phantom,
            spec,
            options.frames_per_sweep,
            probe,
            &options.motion,
            time_s,
        );
        time_s = sweep.last().map_or(time_s, |p| p.time_s) + 3.0;
        placements.extend(sweep);
        sweeps.push(start..placements.len());
    }
    let n = placements.len();

    let image_to_probe = true_image_to_probe(width, pitch);
    let (_, cal_rotation, _) = image_to_probe.to_scale_rotation_translation();
    let cal_rotation = DMat3::from_quat(cal_rotation);
    let face_in_probe =
        image_to_probe.transform_point3(DVec3::new(0.5 * (width as f64 - 1.0), 0.0, 0.0));
    let mut object_rng = ChaCha8Rng::seed_from_u64(stream_seed(options.seed, STREAM_OBJECT, 0));
    let object_motion =
        sweep::ObjectMotion::new(&mut object_rng, options.motion.object_motion_mm, time_s);

    let mut probe_to_tracker = Vec::with_capacity(n);
    let mut image_to_object = Vec::with_capacity(n);
    for p in &placements {
        // The image axes are wanted in the world: probe rotation = image rotation * calibration^-1.
        let rotation = p.image_rotation * cal_rotation.transpose();
        let translation = p.face_centre - rotation * face_in_probe;
        let pose = DMat4::from_mat3_translation(rotation, translation);
        let to_world = pose * image_to_probe;
        probe_to_tracker.push(pose);
        image_to_object.push(object_motion.object_to_world(p.time_s).inverse() * to_world);
    }

    let former = FrameFormer {
        phantom,
        acoustics: options.acoustics,
        grid: ImageGrid { width, height },
        scatter_salt: stream_seed(options.seed, STREAM_SCATTER, 0),
    };
    progress.start("simulate", n as u64);
    let done = std::sync::atomic::AtomicU64::new(0);
    let frames: Vec<Frame> = image_to_object
        .par_iter()
        .enumerate()
        .map(|(i, m)| {
            let frame = former.form(m, stream_seed(options.seed, STREAM_NOISE, i as u64), false);
            let k = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
            progress.advance(k);
            frame
        })
        .collect();
    progress.finish();

    // Levels from the truth-labelled pixels, summed in frame order.
    let mut levels = LevelSums::default();
    for f in &frames {
        levels.add(&f.levels);
    }
    let ac = &options.acoustics;
    // Fallbacks when no pixel of a class was seen: the mean of log-compressed Rayleigh speckle is 2.5 dB
    // below the RMS level.
    let expected =
        |db: f64| 255.0 * ((db - 2.51 + ac.dynamic_range_db) / ac.dynamic_range_db).clamp(0.0, 1.0);
    let background_level = if levels.background_count > 0 {
        levels.background_sum / levels.background_count as f64
    } else {
        expected(ac.water.scatter_db)
    };
    let boundary_level = if levels.boundary_count > 0 {
        levels.boundary_sum / levels.boundary_count as f64
    } else {
        expected(ac.reflection_db)
    };
    let suggested_iso = background_level + 0.3 * (boundary_level - background_level);

    // What the tracker and the calibration file say.
    let mut cal_rng = ChaCha8Rng::seed_from_u64(stream_seed(options.seed, STREAM_CALIBRATION, 0));
    let calibration_error = options.errors.calibration_error(&mut cal_rng);
    let written_image_to_probe = calibration_error * image_to_probe;
    let mut pixels = Vec::with_capacity(n * width * height);
    let mut tracked = Vec::with_capacity(n);
    for (i, (frame, placement)) in frames.iter().zip(&placements).enumerate() {
        pixels.extend_from_slice(&frame.grey);
        let mut rng =
            ChaCha8Rng::seed_from_u64(stream_seed(options.seed, STREAM_TRACKER, i as u64));
        let recorded = probe_to_tracker[i] * options.errors.tracker_noise(&mut rng);
        let mut tf = TrackedFrame {
            timestamp_s: Some(round_time(placement.time_s)),
            image_valid: true,
            ..Default::default()
        };
        tf.transforms.insert(
            "ProbeToTracker".into(),
            FrameTransform {
                matrix: recorded,
                valid: true,
            },
        );
        tf.fields.insert("FrameNumber".into(), i.to_string());
        tracked.push(tf);
    }
    let mut header = std::collections::BTreeMap::new();
    header.insert("UltrasoundImageType".into(), "BRIGHTNESS".into());
    let sequence = TrackedSequence {
        width,
        height,
        channels: 1,
        orientation: "MF".into(),
        frames: tracked,
        pixels: PixelData::U8(pixels),
        header,
    };

    Ok(Simulation {
        sequence,
        calibration_written: Calibration::from_image_to_probe(written_image_to_probe),
        calibration_true: Calibration::from_image_to_probe(image_to_probe),
        truth: Vec::new(),
        suggested_iso,
        background_level,
        boundary_level,
        true_image_to_world: image_to_object,
        sweeps,
        sweep_specs: specs,
        phantom_bounds: bounds,
    })
}

/// Timestamps to the microsecond, so that they survive a text round trip unchanged.
fn round_time(t: f64) -> f64 {
    (t * 1e6).round() / 1e6
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Volume enclosed by a closed mesh, positive when its winding is outward (divergence theorem).
    fn signed_volume(mesh: &Mesh) -> f64 {
        mesh.triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| mesh.vertices[i as usize]);
                a.dot(b.cross(c)) / 6.0
            })
            .sum()
    }

    #[test]
    fn bone_truth_is_the_probe_side_and_its_sweeps_look_down() {
        let phantom = build_phantom(&PhantomKind::Bone).unwrap();
        assert!(phantom.probe_side_only());
        let mut truth =
            output::truth_meshes(phantom.as_ref(), 1.0, &echosurf::progress::NoProgress)
                .unwrap()
                .pop()
                .unwrap()
                .1;
        let closed_area = truth.area_mm2();
        let (lo, _) = truth.bounds().unwrap();
        // The closed truth's winding is outward (positive enclosed volume), so "up" by winding is the
        // probe side.
        let closed_volume = signed_volume(&truth);
        assert!(closed_volume > 1000.0, "{closed_volume}");
        keep_probe_side(&mut truth);
        // The underside is gone: nothing near the bottom remains.
        let (kept_lo, _) = truth.bounds().unwrap();
        assert!(kept_lo.z > lo.z + 3.0, "{kept_lo} vs {lo}");
        let share = truth.area_mm2() / closed_area;
        assert!(
            (0.35..0.65).contains(&share),
            "probe side {share} of the area"
        );
        assert!(!build_phantom(&PhantomKind::Duck).unwrap().probe_side_only());

        let options = SimulationOptions {
            phantom: PhantomKind::Bone,
            frames_per_sweep: 2,
            width_px: 32,
            height_px: 32,
            pixel_size_mm: 1.0,
            acoustics: PhysicsPreset::Bone.acoustics(),
            ..Default::default()
        };
        let sim = simulate_sweeps(&options, &echosurf::progress::NoProgress).unwrap();
        assert!(sim.sweep_specs.iter().all(|s| s.tilt_deg == 0.0));
    }
}
