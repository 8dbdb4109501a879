//! Reading and writing what the field stores: PLUS tracked sequences (`.mha`, `.mhd` + `.raw`/`.zraw`,
//! `.igs.nrrd`), PLUS device-set XML (calibration), meshes (PLY/STL/OBJ) and point clouds (PLY).
//! Everything written goes through [`atomic`] so an interrupted run never leaves a half-written file.

pub mod atomic;
pub mod mesh_io;
pub mod metaimage;
pub mod nrrd;
pub mod plus_config;
pub mod ply;
pub mod pose;
mod seq_decode;
pub mod sequence;
pub mod summary;

pub use summary::{SequenceSummary, summarise};

use std::path::Path;

pub use mesh_io::{read_mesh, write_mesh};
pub use plus_config::{read_calibration, write_calibration};
pub use ply::{PointCloud, read_point_cloud, write_point_cloud};
pub use pose::{
    FramePose, PathStats, PoseResolution, ReferenceChoice, Sweep, clip_corners_px,
    clipped_world_bounds, frame_corners, image_centre, needs_calibration, path_stats,
    resolve_poses, split_path, split_sweeps, world_bounds, world_frame_for,
};
pub use sequence::{
    Calibration, ClipRect, ElementType, FrameTransform, PixelData, TrackedFrame, TrackedSequence,
};

use crate::{Error, FormatProblem, Result};

/// Reads a tracked sequence, choosing the reader by extension (`.mha`, `.mhd`, `.nrrd`).
pub fn read_sequence(path: &Path) -> Result<TrackedSequence> {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    if name.ends_with(".mha") || name.ends_with(".mhd") {
        metaimage::read_sequence(path)
    } else if name.ends_with(".nrrd") {
        nrrd::read_sequence(path)
    } else {
        Err(Error::format(
            path,
            FormatProblem::Unsupported,
            "unknown sequence file extension (expected .mha, .mhd or .nrrd)",
        ))
    }
}

/// Writes a tracked sequence as a PLUS `.mha` file (LOCAL data), zlib-compressed if `compress`.
pub fn write_sequence(path: &Path, sequence: &TrackedSequence, compress: bool) -> Result<()> {
    metaimage::write_sequence(path, sequence, compress)
}
