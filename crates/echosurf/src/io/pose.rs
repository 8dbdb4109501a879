//! The pose chain: each frame's Image->World matrix from its tracked transforms and the calibration, and
//! the split of a recording into sweeps.

use std::ops::Range;
use std::path::Path;

use glam::DMat4;

use super::sequence::{Calibration, TrackedSequence};
use crate::{Error, Result};

/// Which world frame to place the images in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ReferenceChoice {
    /// Reference if a reference sensor (or a per-frame ImageToReference) is present, else Tracker.
    #[default]
    Auto,
    /// `ProbeToTracker * ImageToProbe`.
    Tracker,
    /// `inverse(ReferenceToTracker) * ProbeToTracker * ImageToProbe` (or a per-frame ImageToReference).
    Reference,
}

/// A usable frame: its index in the sequence and where its pixels are in the world.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FramePose {
    pub frame_index: usize,
    pub image_to_world: DMat4,
}

/// The frames that can be placed, and the ones that cannot with the reason.
#[derive(Debug, Clone, PartialEq)]
pub struct PoseResolution {
    pub poses: Vec<FramePose>,
    pub skipped: Vec<(usize, String)>,
    /// `"Reference"` or `"Tracker"`.
    pub world_frame: String,
}

/// A run of consecutive usable frames: a range into `PoseResolution::poses`.
pub type Sweep = Range<usize>;

/// Resolves every frame's Image->World matrix (see FORMATS.md "Geometry"). `path` names the sequence in
/// errors. Fails when no frame can be placed, or when a needed calibration is missing.
pub fn resolve_poses(
    sequence: &TrackedSequence,
    calibration: Option<&Calibration>,
    choice: ReferenceChoice,
    path: &Path,
) -> Result<PoseResolution> {
    let _ = (sequence, calibration, choice, path);
    Err(Error::InvalidInput(
        "pose resolution is not implemented yet".into(),
    ))
}

/// Splits the usable frames into sweeps: a new sweep starts where the image centre jumps by more than
/// 5 mm or the timestamp by more than 1 s between consecutive usable frames.
pub fn split_sweeps(sequence: &TrackedSequence, poses: &PoseResolution) -> Vec<Sweep> {
    let _ = sequence;
    let all: Sweep = 0..poses.poses.len();
    if all.is_empty() {
        Vec::new()
    } else {
        vec![all]
    }
}
