//! A summary of a tracked sequence (what `echosurf inspect` prints): frames, image, tracking, sweeps and
//! world bounds. Works without a calibration too, then describing the tracked probe path only.

use std::path::Path;

use glam::{DMat4, DVec3};

use super::pose::{
    MIN_SWEEP_SPAN_MM, ReferenceChoice, clipped_world_bounds, image_centre, needs_calibration,
    path_stats, resolve_poses, split_path, sweep_span_mm, world_bounds,
};
use super::sequence::{Calibration, ClipRect, TrackedSequence};
use crate::Result;

/// What the sweep statistics are measured on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum TrackedPoint {
    /// Centre pixel of each frame, placed with the calibration.
    ImageCentre,
    /// Probe origin: no calibration was available, so only the tracked probe path is known.
    ProbeOrigin,
}

#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SpacingMm {
    pub min: f64,
    pub median: f64,
    pub max: f64,
}

#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SweepSummary {
    /// Sequence index of the first and last frame of the sweep.
    pub first_frame: usize,
    pub last_frame: usize,
    pub frames: usize,
    pub path_length_mm: f64,
    /// Distance between consecutive frames' tracked points.
    pub spacing_mm: SpacingMm,
    pub duration_s: Option<f64>,
}

#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct BoundsMm {
    pub min: [f64; 3],
    pub max: [f64; 3],
}

#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SkipCount {
    pub reason: String,
    pub frames: usize,
}

/// Everything `inspect` reports. Serialises to the JSON of `echosurf inspect --json`.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SequenceSummary {
    pub frames: usize,
    pub valid_frames: usize,
    pub skipped: Vec<SkipCount>,
    pub width: usize,
    pub height: usize,
    pub channels: usize,
    /// MetaImage spelling (`MET_UCHAR`, ...), or `null` for a tracking-only sequence.
    pub element_type: Option<String>,
    pub tracking_only: bool,
    /// Orientation as the file said; the pixels are held as MF.
    pub orientation: String,
    pub transforms: Vec<String>,
    /// `Reference` or `Tracker`.
    pub world_frame: String,
    /// From the calibration's Image->Probe matrix (never from ElementSpacing).
    pub pixel_size_mm: Option<[f64; 2]>,
    pub clip: Option<ClipRect>,
    pub first_timestamp_s: Option<f64>,
    pub last_timestamp_s: Option<f64>,
    pub tracked_point: TrackedPoint,
    pub sweeps: Vec<SweepSummary>,
    /// World box of the corner pixels of all valid frames; `null` without a calibration.
    pub bounds_mm: Option<BoundsMm>,
    /// The same for the clip-rectangle corners (what PLUS sizes its reconstruction volume to), if the
    /// calibration has a clip rectangle.
    pub clip_bounds_mm: Option<BoundsMm>,
    /// How far the frames reach off the first frame's plane ([`sweep_span_mm`]); `null` without a
    /// calibration. Under [`MIN_SWEEP_SPAN_MM`] the frames hold no volume and `extract` refuses them.
    pub sweep_span_mm: Option<f64>,
    /// Why something could not be reported, for the reader.
    pub notes: Vec<String>,
}

fn arr(v: DVec3) -> [f64; 3] {
    [v.x, v.y, v.z]
}

/// Summarises a sequence. Errors as [`resolve_poses`] does (no valid frame, forced Reference without a
/// reference sensor); a missing calibration is not an error here: the probe path is summarised instead.
pub fn summarise(
    sequence: &TrackedSequence,
    calibration: Option<&Calibration>,
    choice: ReferenceChoice,
    path: &Path,
) -> Result<SequenceSummary> {
    let mut notes = Vec::new();
    if sequence.transform_names().is_empty() {
        return Ok(untracked_summary(sequence, calibration));
    }
    let probe_only = sequence.is_tracking_only()
        || (calibration.is_none() && needs_calibration(sequence, choice));
    let identity = Calibration::from_image_to_probe(DMat4::IDENTITY);
    let resolution = if probe_only {
        if sequence.is_tracking_only() {
            notes.push("tracking-only sequence: no images, sweeps follow the probe origin".into());
        } else {
            notes.push(
                "frame positions need the probe calibration (a PLUS device-set XML); \
                 sweeps follow the tracked probe origin and no world bounds are given"
                    .into(),
            );
        }
        resolve_poses(sequence, Some(&identity), choice, path)?
    } else {
        resolve_poses(sequence, calibration, choice, path)?
    };
    let points: Vec<DVec3> = resolution
        .poses
        .iter()
        .map(|p| {
            if probe_only {
                p.image_to_world.w_axis.truncate()
            } else {
                image_centre(sequence, p)
            }
        })
        .collect();
    let times: Vec<Option<f64>> = resolution
        .poses
        .iter()
        .map(|p| sequence.frames[p.frame_index].timestamp_s)
        .collect();
    let sweeps = split_path(&points, &times)
        .into_iter()
        .map(|range| {
            let stats = path_stats(&points[range.clone()]);
            let first = resolution.poses[range.start].frame_index;
            let last = resolution.poses[range.end - 1].frame_index;
            let duration_s = match (times[range.start], times[range.end - 1]) {
                (Some(a), Some(b)) => Some(b - a),
                _ => None,
            };
            SweepSummary {
                first_frame: first,
                last_frame: last,
                frames: stats.frames,
                path_length_mm: stats.path_length_mm,
                spacing_mm: SpacingMm {
                    min: stats.spacing_min_mm,
                    median: stats.spacing_median_mm,
                    max: stats.spacing_max_mm,
                },
                duration_s,
            }
        })
        .collect();
    let bounds_mm = if probe_only {
        None
    } else {
        world_bounds(sequence, &resolution.poses).map(|(lo, hi)| BoundsMm {
            min: arr(lo),
            max: arr(hi),
        })
    };
    let sweep_span_mm = if probe_only {
        None
    } else {
        sweep_span_mm(sequence.width, sequence.height, &resolution.poses)
    };
    if let Some(mm) = sweep_span_mm.filter(|&mm| mm < MIN_SWEEP_SPAN_MM) {
        notes.push(format!(
            "the frames lie within {mm:.2} mm of one plane: they hold no volume, and extract refuses \
             them (the probe was not swept, or its poses do not change)"
        ));
    }
    let clip_bounds_mm = match (probe_only, calibration.and_then(|c| c.clip)) {
        (false, Some(clip)) => {
            clipped_world_bounds(sequence, &resolution.poses, &clip).map(|(lo, hi)| BoundsMm {
                min: arr(lo),
                max: arr(hi),
            })
        }
        _ => None,
    };
    let timestamps: Vec<f64> = sequence
        .frames
        .iter()
        .filter_map(|f| f.timestamp_s)
        .collect();
    Ok(SequenceSummary {
        frames: sequence.frames.len(),
        valid_frames: resolution.poses.len(),
        skipped: resolution
            .skip_summary()
            .into_iter()
            .map(|(reason, frames)| SkipCount { reason, frames })
            .collect(),
        width: sequence.width,
        height: sequence.height,
        channels: sequence.channels,
        element_type: (!sequence.is_tracking_only())
            .then(|| sequence.pixels.element_type().metaimage_name().to_string()),
        tracking_only: sequence.is_tracking_only(),
        orientation: sequence.orientation.clone(),
        transforms: sequence.transform_names(),
        world_frame: resolution.world_frame.clone(),
        pixel_size_mm: calibration.map(Calibration::pixel_size_mm),
        clip: calibration.and_then(|c| c.clip),
        first_timestamp_s: timestamps.first().copied(),
        last_timestamp_s: timestamps.last().copied(),
        tracked_point: if probe_only {
            TrackedPoint::ProbeOrigin
        } else {
            TrackedPoint::ImageCentre
        },
        sweeps,
        bounds_mm,
        clip_bounds_mm,
        sweep_span_mm,
        notes,
    })
}

/// A file without any per-frame transform (a reconstructed volume, an untracked recording): described,
/// but nothing can be placed. Not an error: the file is well-formed, it just is not a tracked sweep.
fn untracked_summary(
    sequence: &TrackedSequence,
    calibration: Option<&Calibration>,
) -> SequenceSummary {
    let mut notes = vec![
        "no per-frame transforms: frames cannot be placed (a reconstructed volume or an untracked \
         recording?)"
            .to_string(),
    ];
    if let (Some(offset), Some(spacing)) = (
        sequence.header.get("Offset"),
        sequence.header.get("ElementSpacing"),
    ) {
        notes.push(format!(
            "as a volume: origin {offset} mm, spacing {spacing} mm (header fields)"
        ));
    }
    let timestamps: Vec<f64> = sequence
        .frames
        .iter()
        .filter_map(|f| f.timestamp_s)
        .collect();
    SequenceSummary {
        frames: sequence.frames.len(),
        valid_frames: 0,
        skipped: vec![SkipCount {
            reason: "no transforms".into(),
            frames: sequence.frames.len(),
        }],
        width: sequence.width,
        height: sequence.height,
        channels: sequence.channels,
        element_type: (!sequence.is_tracking_only())
            .then(|| sequence.pixels.element_type().metaimage_name().to_string()),
        tracking_only: sequence.is_tracking_only(),
        orientation: sequence.orientation.clone(),
        transforms: Vec::new(),
        world_frame: "none".into(),
        pixel_size_mm: calibration.map(Calibration::pixel_size_mm),
        clip: calibration.and_then(|c| c.clip),
        first_timestamp_s: timestamps.first().copied(),
        last_timestamp_s: timestamps.last().copied(),
        tracked_point: TrackedPoint::ImageCentre,
        sweeps: Vec::new(),
        bounds_mm: None,
        clip_bounds_mm: None,
        sweep_span_mm: None,
        notes,
    }
}

impl SequenceSummary {
    /// Compact human-readable text (what `inspect` prints without `--json`).
    pub fn to_text(&self, name: &str) -> String {
        use std::fmt::Write as _;
        let mut s = String::new();
        let _ = writeln!(s, "{name}");
        let skipped = self.frames - self.valid_frames;
        let _ = writeln!(
            s,
            "  frames      {} ({} valid, {skipped} skipped)",
            self.frames, self.valid_frames
        );
        for k in &self.skipped {
            let _ = writeln!(s, "    skipped   {} x {}", k.frames, k.reason);
        }
        if self.tracking_only {
            let _ = writeln!(
                s,
                "  image       none (tracking only, DimSize {} x {})",
                self.width, self.height
            );
        } else {
            let orientation = if self.orientation.is_empty() {
                "not stated, taken as MF".to_string()
            } else {
                format!("{} (held as MF)", self.orientation)
            };
            let _ = writeln!(
                s,
                "  image       {} x {} px, {} channel{}, {}, orientation {orientation}",
                self.width,
                self.height,
                self.channels,
                if self.channels == 1 { "" } else { "s" },
                self.element_type.as_deref().unwrap_or("?"),
            );
        }
        let _ = writeln!(
            s,
            "  transforms  {}",
            if self.transforms.is_empty() {
                "none".to_string()
            } else {
                self.transforms.join(", ")
            }
        );
        if let (Some(a), Some(b)) = (self.first_timestamp_s, self.last_timestamp_s) {
            let _ = writeln!(s, "  time        {a:.3} .. {b:.3} s ({:.2} s)", b - a);
        }
        match self.pixel_size_mm {
            Some([x, y]) => {
                let _ = writeln!(s, "  pixel size  {x:.4} x {y:.4} mm (calibration)");
            }
            None => {
                let _ = writeln!(s, "  pixel size  unknown (no calibration)");
            }
        }
        if let Some(c) = self.clip {
            let beyond = if c.fits(self.width, self.height) {
                String::new()
            } else {
                format!(
                    " (reaches beyond the {} x {} px frames: cut to them; a calibration for another \
                     image size?)",
                    self.width, self.height
                )
            };
            let _ = writeln!(s, "  clip        {}{beyond}", c.describe());
        }
        let what = match self.tracked_point {
            TrackedPoint::ImageCentre => "image centre",
            TrackedPoint::ProbeOrigin => "probe origin",
        };
        let _ = writeln!(
            s,
            "  sweeps      {} (world frame {}, measured at the {what})",
            self.sweeps.len(),
            self.world_frame
        );
        const MAX_SWEEP_LINES: usize = 10;
        for (i, w) in self.sweeps.iter().enumerate().take(MAX_SWEEP_LINES) {
            let _ = writeln!(
                s,
                "    #{:<3} frames {}-{}: {} frames, path {:.1} mm, spacing {:.2}/{:.2}/{:.2} mm (min/median/max){}",
                i + 1,
                w.first_frame,
                w.last_frame,
                w.frames,
                w.path_length_mm,
                w.spacing_mm.min,
                w.spacing_mm.median,
                w.spacing_mm.max,
                w.duration_s
                    .map(|d| format!(", {d:.2} s"))
                    .unwrap_or_default()
            );
        }
        if self.sweeps.len() > MAX_SWEEP_LINES {
            let _ = writeln!(
                s,
                "    ... {} more sweeps (the JSON summary lists all)",
                self.sweeps.len() - MAX_SWEEP_LINES
            );
        }
        for (label, bounds) in [
            ("bounds mm", &self.bounds_mm),
            ("clipped mm", &self.clip_bounds_mm),
        ] {
            let Some(b) = bounds else { continue };
            let f = |v: [f64; 3]| format!("({:.3}, {:.3}, {:.3})", v[0], v[1], v[2]);
            let size = [
                b.max[0] - b.min[0],
                b.max[1] - b.min[1],
                b.max[2] - b.min[2],
            ];
            let _ = writeln!(
                s,
                "  {label:<11} min {} max {} size {:.1} x {:.1} x {:.1}",
                f(b.min),
                f(b.max),
                size[0],
                size[1],
                size[2]
            );
        }
        if let Some(mm) = self.sweep_span_mm {
            let _ = writeln!(s, "  span mm     {mm:.1} off the first frame's plane");
        }
        for n in &self.notes {
            let _ = writeln!(s, "  note        {n}");
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::sequence::{FrameTransform, PixelData, TrackedFrame};

    #[test]
    fn without_calibration_reports_probe_path_only() {
        let frames = (0..3)
            .map(|i| TrackedFrame {
                timestamp_s: Some(i as f64 * 0.1),
                image_valid: true,
                transforms: [(
                    "ProbeToTracker".to_string(),
                    FrameTransform {
                        matrix: DMat4::from_translation(DVec3::new(i as f64, 0.0, 0.0)),
                        valid: true,
                    },
                )]
                .into(),
                fields: Default::default(),
            })
            .collect();
        let seq = TrackedSequence {
            width: 2,
            height: 2,
            channels: 1,
            orientation: "MF".into(),
            frames,
            pixels: PixelData::U8(vec![0; 12]),
            header: Default::default(),
        };
        let s = summarise(&seq, None, ReferenceChoice::Auto, Path::new("x")).unwrap();
        assert_eq!(s.tracked_point, TrackedPoint::ProbeOrigin);
        assert_eq!(s.bounds_mm, None);
        assert_eq!(s.valid_frames, 3);
        assert_eq!(s.sweeps.len(), 1);
        assert!((s.sweeps[0].path_length_mm - 2.0).abs() < 1e-12);
        assert!(!s.notes.is_empty());
        let cal = Calibration::from_image_to_probe(DMat4::from_scale(DVec3::splat(0.5)));
        let s = summarise(&seq, Some(&cal), ReferenceChoice::Auto, Path::new("x")).unwrap();
        let b = s.bounds_mm.clone().unwrap();
        assert_eq!((b.min, b.max), ([0.0, 0.0, 0.0], [2.5, 0.5, 0.0]));
        assert!(s.to_text("x").contains("bounds mm"));
    }
}
