//! Reading and writing what the field stores: PLUS tracked sequences (`.mha`, `.mhd` + `.raw`/`.zraw`,
//! `.igs.nrrd`), PLUS device-set XML (calibration), meshes (PLY/STL/OBJ/VTK) and point clouds (PLY).
//! Everything written goes through [`atomic`] so an interrupted run never leaves a half-written file.

pub mod atomic;
pub mod mesh_io;
pub mod metaimage;
pub mod nrrd;
pub mod plus_config;
pub mod ply;
mod polygons;
pub mod pose;
mod seq_decode;
pub mod sequence;
pub mod summary;
pub(crate) mod vtk;

pub use summary::{SequenceSummary, summarise};

use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};

pub use mesh_io::{
    Space, read_mesh, read_mesh_and_space, read_vertex_colours, write_mesh, write_mesh_in,
    write_ply_with_vertex_values,
};
pub use plus_config::{check_clip_fits, read_calibration, write_calibration};
pub use ply::{PointCloud, read_point_cloud, write_point_cloud};
pub use pose::{
    FramePose, MIN_SWEEP_SPAN_MM, PathStats, PoseResolution, ReferenceChoice, Sweep,
    clip_corners_px, clipped_world_bounds, frame_corners, image_centre, needs_calibration,
    path_stats, resolve_poses, split_path, split_sweeps, sweep_span_mm, world_bounds,
    world_frame_for,
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

/// The files a sequence is read from: the header, and the detached data file it names (`.mhd` +
/// `.raw`/`.zraw`, NRRD `data file:`), so that a command can refuse to write over any of them. Best
/// effort and cheap: a header that cannot be scanned gives the header alone, and the reader reports
/// what is wrong with it.
pub fn sequence_files(path: &Path) -> Vec<PathBuf> {
    let mut files = vec![path.to_path_buf()];
    if let Some(name) = detached_data_name(path) {
        let listed = name.eq_ignore_ascii_case("LOCAL") || name.eq_ignore_ascii_case("LIST");
        if !(name.is_empty() || listed || name.contains('%')) {
            files.push(metaimage::sibling_path(path, &name));
        }
    }
    files
}

/// The value of `ElementDataFile` (MetaImage) or `data file` / `datafile` (NRRD), read from the header
/// only: the scan stops at the first of them, at the blank line that ends a NRRD header, or after
/// `HEADER_SCAN_BYTES` (PLUS headers run to about 300 bytes a frame).
fn detached_data_name(path: &Path) -> Option<String> {
    const HEADER_SCAN_BYTES: u64 = 16 << 20;
    let file = std::fs::File::open(path).ok()?;
    let mut reader = BufReader::new(file.take(HEADER_SCAN_BYTES));
    let mut line = Vec::new();
    let mut nrrd = false;
    for line_number in 0.. {
        line.clear();
        if reader.read_until(b'\n', &mut line).ok()? == 0 {
            return None;
        }
        let text = String::from_utf8_lossy(&line);
        let text = text.trim();
        if line_number == 0 {
            nrrd = text.starts_with("NRRD");
            continue;
        }
        if nrrd {
            if text.is_empty() {
                return None;
            }
            if let Some((key, value)) = text.split_once(':')
                && !value.starts_with('=')
                && matches!(
                    key.trim().to_ascii_lowercase().as_str(),
                    "data file" | "datafile"
                )
            {
                return Some(value.trim().to_string());
            }
        } else if let Some((key, value)) = text.split_once('=')
            && key.trim() == "ElementDataFile"
        {
            return Some(value.trim().to_string());
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::sequence_files;
    use std::path::PathBuf;

    #[test]
    fn sequence_files_name_a_detached_data_file_and_nothing_else() {
        let dir = tempfile::tempdir().unwrap();
        let write = |name: &str, text: &str| {
            let path = dir.path().join(name);
            std::fs::write(&path, text).unwrap();
            path
        };
        let mhd = write(
            "a.mhd",
            "ObjectType = Image\nNDims = 3\nElementDataFile = a.raw\n",
        );
        assert_eq!(
            sequence_files(&mhd),
            vec![mhd.clone(), dir.path().join("a.raw")]
        );
        let local = write(
            "b.mha",
            "ObjectType = Image\nNDims = 3\nElementDataFile = LOCAL\n\x01=\x02",
        );
        assert_eq!(sequence_files(&local), vec![local.clone()]);
        let nrrd = write(
            "c.nrrd",
            "NRRD0004\ntype: uint8\nSeq_Frame0000_Note:=data file: x\ndata file: c.raw.gz\n\n",
        );
        assert_eq!(
            sequence_files(&nrrd),
            vec![nrrd.clone(), dir.path().join("c.raw.gz")]
        );
        let nrrd_attached = write("d.nrrd", "NRRD0004\ntype: uint8\n\ndata file: no\n");
        assert_eq!(sequence_files(&nrrd_attached), vec![nrrd_attached.clone()]);
        let pattern = write("e.mhd", "NDims = 3\nElementDataFile = e%03d.raw\n");
        assert_eq!(sequence_files(&pattern), vec![pattern.clone()]);
        let missing = PathBuf::from("/nonexistent/f.mhd");
        assert_eq!(sequence_files(&missing), vec![missing.clone()]);
    }
}
