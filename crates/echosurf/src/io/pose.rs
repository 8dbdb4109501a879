//! The pose chain: each frame's Image->World matrix from its tracked transforms and the calibration, and
//! the split of a recording into sweeps.

use std::collections::BTreeMap;
use std::ops::Range;
use std::path::Path;

use glam::{DMat4, DVec3};

use super::sequence::{Calibration, ClipRect, TrackedFrame, TrackedSequence};
use crate::{Error, FormatProblem, Result};

/// Consecutive usable frames whose image centres are further apart than this start a new sweep.
pub const SWEEP_BREAK_MM: f64 = 5.0;
/// Consecutive usable frames further apart in time than this start a new sweep.
pub const SWEEP_BREAK_S: f64 = 1.0;

/// A tracked rigid transform whose rotation part has |det| below this is degenerate (a rotation has 1).
const MIN_TRACKED_DET: f64 = 1e-6;

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

impl PoseResolution {
    /// Skip reasons with how many frames each applies to, most frequent first.
    pub fn skip_summary(&self) -> Vec<(String, usize)> {
        let mut counts: BTreeMap<&str, usize> = BTreeMap::new();
        for (_, reason) in &self.skipped {
            *counts.entry(reason.as_str()).or_default() += 1;
        }
        let mut v: Vec<(String, usize)> = counts
            .into_iter()
            .map(|(r, n)| (r.to_string(), n))
            .collect();
        v.sort_by(|a, b| b.1.cmp(&a.1).then_with(|| a.0.cmp(&b.0)));
        v
    }
}

/// A run of consecutive usable frames: a range into `PoseResolution::poses`.
pub type Sweep = Range<usize>;

/// Transform names that play the ProbeToTracker role (old PLUS files say `ToolToTracker`).
const PROBE_TO_TRACKER_NAMES: &[&str] = &["ProbeToTracker", "ToolToTracker"];

/// Whether a sequence has what the Reference chain needs in at least one frame.
fn has_reference_information(sequence: &TrackedSequence) -> bool {
    sequence.frames.iter().any(|f| {
        f.transforms.contains_key("ImageToReference")
            || f.transforms.contains_key("ReferenceToTracker")
            || f.transforms.contains_key("ProbeToReference")
    })
}

/// The world frame a choice resolves to for this sequence (`"Reference"` or `"Tracker"`).
pub fn world_frame_for(sequence: &TrackedSequence, choice: ReferenceChoice) -> &'static str {
    let reference = match choice {
        ReferenceChoice::Auto => has_reference_information(sequence),
        ReferenceChoice::Tracker => false,
        ReferenceChoice::Reference => true,
    };
    if reference { "Reference" } else { "Tracker" }
}

/// Whether placing the frames in `choice`'s world needs an Image->Probe calibration, i.e. no frame
/// carries an already-composed ImageToReference / ImageToTracker or its own ImageToProbe.
pub fn needs_calibration(sequence: &TrackedSequence, choice: ReferenceChoice) -> bool {
    let composed = format!("ImageTo{}", world_frame_for(sequence, choice));
    !sequence
        .frames
        .iter()
        .any(|f| f.transforms.contains_key(&composed) || f.transforms.contains_key("ImageToProbe"))
}

/// A transform of `frame` that must be usable, or why it is not.
fn usable(frame: &TrackedFrame, names: &[&str]) -> std::result::Result<DMat4, String> {
    let Some((name, t)) = names
        .iter()
        .find_map(|n| frame.transforms.get(*n).map(|t| (*n, t)))
    else {
        let wanted: Vec<String> = names.iter().map(|n| format!("{n}Transform")).collect();
        return Err(format!("no {}", wanted.join(" or ")));
    };
    if !t.valid {
        return Err(format!("{name}Transform INVALID"));
    }
    if !t.matrix.to_cols_array().iter().all(|v| v.is_finite()) {
        return Err(format!("{name}Transform not finite"));
    }
    Ok(t.matrix)
}

/// A tracked transform that will be inverted: must be non-degenerate.
fn invertible(m: DMat4, name: &str) -> std::result::Result<DMat4, String> {
    let det = glam::DMat3::from_mat4(m).determinant();
    if !det.is_finite() || det.abs() < MIN_TRACKED_DET {
        return Err(format!("{name}Transform singular"));
    }
    Ok(m.inverse())
}

/// Image->World of one frame, or why the frame cannot be placed.
fn frame_pose(
    frame: &TrackedFrame,
    calibration: Option<&DMat4>,
    reference: bool,
) -> std::result::Result<DMat4, String> {
    if !frame.image_valid {
        return Err("image INVALID".into());
    }
    let composed_name = if reference {
        "ImageToReference"
    } else {
        "ImageToTracker"
    };
    let m = if frame.transforms.contains_key(composed_name) {
        usable(frame, &[composed_name])?
    } else {
        let image_to_probe = match calibration {
            Some(m) => *m,
            None => usable(frame, &["ImageToProbe"])
                .map_err(|_| "no ImageToProbe calibration".to_string())?,
        };
        if reference {
            let probe_to_reference = match usable(frame, &["ProbeToReference"]) {
                Ok(m) => m,
                Err(direct) => {
                    let reference_to_tracker = usable(frame, &["ReferenceToTracker"]);
                    let probe_to_tracker = usable(frame, PROBE_TO_TRACKER_NAMES);
                    match (reference_to_tracker, probe_to_tracker) {
                        (Ok(r), Ok(p)) => invertible(r, "ReferenceToTracker")? * p,
                        (Err(e), _) | (_, Err(e)) => {
                            if frame.transforms.contains_key("ProbeToReference") {
                                return Err(direct);
                            }
                            return Err(e);
                        }
                    }
                }
            };
            probe_to_reference * image_to_probe
        } else {
            usable(frame, PROBE_TO_TRACKER_NAMES)? * image_to_probe
        }
    };
    if !m.to_cols_array().iter().all(|v| v.is_finite()) {
        return Err("Image->World not finite".into());
    }
    // The image plane must not collapse: the pixel axes must span a plane.
    let plane = m.x_axis.truncate().cross(m.y_axis.truncate()).length();
    if plane.is_nan() || plane <= 0.0 {
        return Err("Image->World singular (pixel axes collapse)".into());
    }
    Ok(m)
}

/// Resolves every frame's Image->World matrix (see FORMATS.md "Geometry"). `path` names the sequence in
/// errors. Fails when no frame can be placed, or when a needed calibration is missing.
pub fn resolve_poses(
    sequence: &TrackedSequence,
    calibration: Option<&Calibration>,
    choice: ReferenceChoice,
    path: &Path,
) -> Result<PoseResolution> {
    let world_frame = world_frame_for(sequence, choice);
    let reference = world_frame == "Reference";
    if calibration.is_none() && needs_calibration(sequence, choice) {
        return Err(Error::format(
            path,
            FormatProblem::MissingTransform,
            "frame positions need the probe calibration (Image->Probe): give the PLUS device-set XML",
        ));
    }
    if reference && !has_reference_information(sequence) {
        return Err(Error::format(
            path,
            FormatProblem::MissingTransform,
            "the Reference frame was asked for but no frame has ReferenceToTracker, \
             ProbeToReference or ImageToReference",
        ));
    }
    let image_to_probe = calibration.map(|c| c.image_to_probe);
    if let Some(m) = &image_to_probe
        && !m.to_cols_array().iter().all(|v| v.is_finite())
    {
        return Err(Error::InvalidInput(
            "calibration ImageToProbe has non-finite entries".into(),
        ));
    }
    let mut poses = Vec::new();
    let mut skipped = Vec::new();
    for (frame_index, frame) in sequence.frames.iter().enumerate() {
        match frame_pose(frame, image_to_probe.as_ref(), reference) {
            Ok(image_to_world) => poses.push(FramePose {
                frame_index,
                image_to_world,
            }),
            Err(reason) => skipped.push((frame_index, reason)),
        }
    }
    let resolution = PoseResolution {
        poses,
        skipped,
        world_frame: world_frame.to_string(),
    };
    if resolution.poses.is_empty() {
        let summary = resolution
            .skip_summary()
            .iter()
            .map(|(r, n)| format!("{n} x {r}"))
            .collect::<Vec<_>>()
            .join(", ");
        return Err(Error::format(
            path,
            FormatProblem::NoValidFrames,
            format!(
                "none of the {} frames can be placed in the {world_frame} frame{}",
                sequence.frames.len(),
                if summary.is_empty() {
                    String::new()
                } else {
                    format!(" ({summary})")
                }
            ),
        ));
    }
    Ok(resolution)
}

/// A frame's plane: origin, the world vectors of one pixel along u and v (v: down the beam), the unit
/// normal, and the inverse Gram matrix of (u, v), which projects a world point orthogonally onto the
/// plane in pixel coordinates (whatever the image's third axis in the matrix).
#[derive(Debug, Clone, Copy)]
pub struct FramePlane {
    pub origin: DVec3,
    u: DVec3,
    pub v: DVec3,
    pub normal: DVec3,
    gram_inverse: [[f64; 2]; 2],
}

impl FramePlane {
    pub fn new(image_to_world: DMat4) -> Option<FramePlane> {
        let origin = image_to_world.transform_point3(DVec3::ZERO);
        let u = image_to_world.transform_vector3(DVec3::X);
        let v = image_to_world.transform_vector3(DVec3::Y);
        let normal = u.cross(v).try_normalize()?;
        let (uu, uv, vv) = (u.dot(u), u.dot(v), v.dot(v));
        let det = uu * vv - uv * uv;
        if !(det.is_finite() && det > 0.0 && origin.is_finite()) {
            return None;
        }
        Some(FramePlane {
            origin,
            u,
            v,
            normal,
            gram_inverse: [[vv / det, -uv / det], [-uv / det, uu / det]],
        })
    }

    /// Pixel coordinates of the point's projection onto the plane.
    pub fn pixel_of(&self, p: DVec3) -> [f64; 2] {
        let d = p - self.origin;
        let (a, b) = (self.u.dot(d), self.v.dot(d));
        let g = self.gram_inverse;
        [g[0][0] * a + g[0][1] * b, g[1][0] * a + g[1][1] * b]
    }

    pub fn world_of(&self, pixel: [f64; 2]) -> DVec3 {
        self.origin + self.u * pixel[0] + self.v * pixel[1]
    }
}

/// World position of the centre of a frame: pixel ((W-1)/2, (H-1)/2).
pub fn image_centre(sequence: &TrackedSequence, pose: &FramePose) -> DVec3 {
    let u = sequence.width.saturating_sub(1) as f64 / 2.0;
    let v = sequence.height.saturating_sub(1) as f64 / 2.0;
    pose.image_to_world.transform_point3(DVec3::new(u, v, 0.0))
}

/// World positions of the four corner pixels (0,0), (W-1,0), (0,H-1), (W-1,H-1) of a frame.
pub fn frame_corners(sequence: &TrackedSequence, pose: &FramePose) -> [DVec3; 4] {
    image_corners(sequence.width, sequence.height, pose)
}

/// [`frame_corners`] for a `width` x `height` image.
pub fn image_corners(width: usize, height: usize, pose: &FramePose) -> [DVec3; 4] {
    let u = width.saturating_sub(1) as f64;
    let v = height.saturating_sub(1) as f64;
    [(0.0, 0.0), (u, 0.0), (0.0, v), (u, v)]
        .map(|(x, y)| pose.image_to_world.transform_point3(DVec3::new(x, y, 0.0)))
}

/// Frames all closer than this to one plane do not span a volume, and a fit through them is a
/// sheet of guesses whose iso-surface means nothing: a video recorded without moving the probe, or
/// with a pose that never changes (the PLUS `Prostate10_video` test file). Real sweeps span
/// millimetres to centimetres; tracker jitter alone stays well under it.
pub const MIN_SWEEP_SPAN_MM: f64 = 1.0;

/// How far the corners of the frames reach from the first frame's plane (mm): the thickness of what
/// the sweep covers, whether the probe slid (a linear sweep) or turned (a fan or a rotation about the
/// beam, whose image centre may not move at all). `None` without frames or with a degenerate image.
pub fn sweep_span_mm(width: usize, height: usize, poses: &[FramePose]) -> Option<f64> {
    let corners = |p: &FramePose| image_corners(width, height, p);
    let [origin, along_u, along_v, _] = corners(poses.first()?);
    let normal = (along_u - origin).cross(along_v - origin).try_normalize()?;
    Some(
        poses
            .iter()
            .flat_map(corners)
            .map(|c| (c - origin).dot(normal).abs())
            .fold(0.0, f64::max),
    )
}

/// Axis-aligned world box (min, max) of the corner pixels of all placed frames.
pub fn world_bounds(sequence: &TrackedSequence, poses: &[FramePose]) -> Option<(DVec3, DVec3)> {
    let mut corners = poses.iter().flat_map(|p| frame_corners(sequence, p));
    let first = corners.next()?;
    Some(corners.fold((first, first), |(lo, hi), c| (lo.min(c), hi.max(c))))
}

/// Pixel-space corners (u0, v0, u1, v1) of the part of a W x H frame inside `clip`, as PLUS bounds its
/// reconstruction volume (vtkPlusVolumeReconstructor::AddImageToExtent): from the clip origin to
/// min(origin + size, last pixel) on each axis. `None` if the rectangle misses the image.
pub fn clip_corners_px(width: usize, height: usize, clip: &ClipRect) -> Option<[f64; 4]> {
    let last = [width.checked_sub(1)? as f64, height.checked_sub(1)? as f64];
    let mut out = [0.0; 4];
    for axis in 0..2 {
        let lo = clip.origin_px[axis] as f64;
        let hi = (clip.origin_px[axis] as f64 + clip.size_px[axis] as f64).min(last[axis]);
        if clip.size_px[axis] == 0 || lo >= hi {
            return None;
        }
        out[axis] = lo;
        out[axis + 2] = hi;
    }
    Some(out)
}

/// Axis-aligned world box (min, max) of the clip-rectangle corners of all placed frames (see
/// [`clip_corners_px`]); what PLUS sizes its reconstruction volume to.
pub fn clipped_world_bounds(
    sequence: &TrackedSequence,
    poses: &[FramePose],
    clip: &ClipRect,
) -> Option<(DVec3, DVec3)> {
    let [u0, v0, u1, v1] = clip_corners_px(sequence.width, sequence.height, clip)?;
    let mut corners = poses.iter().flat_map(|p| {
        [(u0, v0), (u1, v0), (u0, v1), (u1, v1)]
            .map(|(u, v)| p.image_to_world.transform_point3(DVec3::new(u, v, 0.0)))
    });
    let first = corners.next()?;
    Some(corners.fold((first, first), |(lo, hi), c| (lo.min(c), hi.max(c))))
}

/// Splits a path of points (with optional timestamps, same length) into runs: a new run starts where
/// consecutive points are more than [`SWEEP_BREAK_MM`] apart or their timestamps more than
/// [`SWEEP_BREAK_S`] apart.
pub fn split_path(points: &[DVec3], timestamps_s: &[Option<f64>]) -> Vec<Sweep> {
    let mut sweeps = Vec::new();
    if points.is_empty() {
        return sweeps;
    }
    let mut start = 0;
    for i in 1..points.len() {
        let jump = points[i].distance(points[i - 1]) > SWEEP_BREAK_MM;
        let pause = match (
            timestamps_s.get(i).copied().flatten(),
            timestamps_s.get(i - 1).copied().flatten(),
        ) {
            (Some(t), Some(t0)) => (t - t0).abs() > SWEEP_BREAK_S,
            _ => false,
        };
        if jump || pause {
            sweeps.push(start..i);
            start = i;
        }
    }
    sweeps.push(start..points.len());
    sweeps
}

/// Splits the usable frames into sweeps: a new sweep starts where the image centre jumps by more than
/// 5 mm or the timestamp by more than 1 s between consecutive usable frames.
pub fn split_sweeps(sequence: &TrackedSequence, poses: &PoseResolution) -> Vec<Sweep> {
    let centres: Vec<DVec3> = poses
        .poses
        .iter()
        .map(|p| image_centre(sequence, p))
        .collect();
    let times: Vec<Option<f64>> = poses
        .poses
        .iter()
        .map(|p| {
            sequence
                .frames
                .get(p.frame_index)
                .and_then(|f| f.timestamp_s)
        })
        .collect();
    split_path(&centres, &times)
}

/// Path length and frame spacing of one sweep, from the points that represent its frames.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct PathStats {
    pub frames: usize,
    pub path_length_mm: f64,
    /// Distance between consecutive frames; all zero for a one-frame sweep.
    pub spacing_min_mm: f64,
    pub spacing_median_mm: f64,
    pub spacing_max_mm: f64,
}

/// Statistics of consecutive points (e.g. image centres of one sweep).
pub fn path_stats(points: &[DVec3]) -> PathStats {
    let mut steps: Vec<f64> = points.windows(2).map(|w| w[0].distance(w[1])).collect();
    // Folded from +0.0: an empty f64 sum is -0.0, which would print as "-0.0 mm".
    let path_length_mm = steps.iter().fold(0.0, |a, b| a + b);
    steps.sort_by(f64::total_cmp);
    let median = match steps.len() {
        0 => 0.0,
        n if n % 2 == 1 => steps[n / 2],
        n => 0.5 * (steps[n / 2 - 1] + steps[n / 2]),
    };
    PathStats {
        frames: points.len(),
        path_length_mm,
        spacing_min_mm: steps.first().copied().unwrap_or(0.0),
        spacing_median_mm: median,
        spacing_max_mm: steps.last().copied().unwrap_or(0.0),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::sequence::{FrameTransform, PixelData};
    use glam::DQuat;

    fn posed(image_to_world: DMat4) -> FramePose {
        FramePose {
            frame_index: 0,
            image_to_world,
        }
    }

    #[test]
    fn the_sweep_span_is_how_far_the_frames_reach_off_the_first_plane() {
        // 101 x 51 px at 0.2 mm/px: a frame 20 x 10 mm in the world's x-y plane.
        let scale = DMat4::from_scale(DVec3::new(0.2, 0.2, 1.0));
        let moved = |z_mm: f64| posed(DMat4::from_translation(DVec3::new(3.0, -2.0, z_mm)) * scale);
        let still: Vec<FramePose> = (0..10).map(|_| moved(0.0)).collect();
        assert_eq!(sweep_span_mm(101, 51, &still), Some(0.0));
        // Sliding within its own plane covers no thickness either.
        let sliding = [
            moved(0.0),
            posed(DMat4::from_translation(DVec3::X * 5.0) * scale),
        ];
        assert_eq!(sweep_span_mm(101, 51, &sliding), Some(0.0));
        let linear: Vec<FramePose> = (0..10).map(|k| moved(0.4 * k as f64)).collect();
        assert!((sweep_span_mm(101, 51, &linear).unwrap() - 3.6).abs() < 1e-9);
        // A rotation about the frame's own centre line (x = 10 mm) keeps the image centre still;
        // turned by 30 degrees the frame's far edge leaves the plane by 10 mm x sin 30 = 5 mm.
        let about_centre = |degrees: f64| {
            let centre = DVec3::new(10.0, 0.0, 0.0);
            let turn = DMat4::from_translation(centre)
                * DMat4::from_quat(DQuat::from_rotation_y(degrees.to_radians()))
                * DMat4::from_translation(-centre);
            posed(turn * scale)
        };
        let fan = [about_centre(0.0), about_centre(30.0)];
        assert!((sweep_span_mm(101, 51, &fan).unwrap() - 5.0).abs() < 1e-9);
        assert_eq!(sweep_span_mm(101, 51, &[]), None);
        assert_eq!(sweep_span_mm(1, 51, &still), None);
    }

    fn seq_with(frames: Vec<TrackedFrame>) -> TrackedSequence {
        TrackedSequence {
            width: 11,
            height: 21,
            channels: 1,
            orientation: "MF".into(),
            frames,
            pixels: PixelData::U8(Vec::new()),
            header: Default::default(),
        }
    }

    fn frame(t: f64, transforms: &[(&str, DMat4, bool)]) -> TrackedFrame {
        TrackedFrame {
            timestamp_s: Some(t),
            image_valid: true,
            transforms: transforms
                .iter()
                .map(|(n, m, v)| {
                    (
                        n.to_string(),
                        FrameTransform {
                            matrix: *m,
                            valid: *v,
                        },
                    )
                })
                .collect(),
            fields: Default::default(),
        }
    }

    fn translate(x: f64, y: f64, z: f64) -> DMat4 {
        DMat4::from_translation(DVec3::new(x, y, z))
    }

    #[test]
    fn reference_chain_matches_hand_composition() {
        let cal = Calibration::from_image_to_probe(DMat4::from_scale(DVec3::splat(0.1)));
        let p2t = DMat4::from_rotation_z(0.3) * translate(1.0, 2.0, 3.0);
        let r2t = DMat4::from_rotation_x(-0.7) * translate(-5.0, 0.0, 9.0);
        let seq = seq_with(vec![frame(
            0.0,
            &[
                ("ProbeToTracker", p2t, true),
                ("ReferenceToTracker", r2t, true),
            ],
        )]);
        let path = Path::new("s.mha");
        let r = resolve_poses(&seq, Some(&cal), ReferenceChoice::Auto, path).unwrap();
        assert_eq!(r.world_frame, "Reference");
        // Independent check: map pixel (10, 20) step by step.
        let pixel = DVec3::new(10.0, 20.0, 0.0);
        let in_tracker = p2t.transform_point3(pixel * 0.1);
        let expected = r2t.inverse().transform_point3(in_tracker);
        let got = r.poses[0].image_to_world.transform_point3(pixel);
        assert!((got - expected).length() < 1e-12);

        let t = resolve_poses(&seq, Some(&cal), ReferenceChoice::Tracker, path).unwrap();
        assert_eq!(t.world_frame, "Tracker");
        assert!((t.poses[0].image_to_world.transform_point3(pixel) - in_tracker).length() < 1e-12);
    }

    #[test]
    fn skips_invalid_and_degenerate_frames_with_reasons() {
        let cal = Calibration::from_image_to_probe(DMat4::IDENTITY);
        let mut bad_image = frame(0.0, &[("ToolToTracker", DMat4::IDENTITY, true)]);
        bad_image.image_valid = false;
        let mut nan = DMat4::IDENTITY;
        nan.w_axis.x = f64::NAN;
        let seq = seq_with(vec![
            bad_image,
            frame(0.1, &[("ToolToTracker", DMat4::IDENTITY, false)]),
            frame(0.2, &[("ToolToTracker", nan, true)]),
            frame(
                0.3,
                &[("ToolToTracker", DMat4::from_scale(DVec3::ZERO), true)],
            ),
            frame(0.4, &[("ToolToTracker", DMat4::IDENTITY, true)]),
        ]);
        let r = resolve_poses(&seq, Some(&cal), ReferenceChoice::Auto, Path::new("x")).unwrap();
        assert_eq!(r.world_frame, "Tracker");
        assert_eq!(r.poses.len(), 1);
        assert_eq!(r.poses[0].frame_index, 4);
        let reasons: Vec<&str> = r.skipped.iter().map(|(_, s)| s.as_str()).collect();
        assert_eq!(
            reasons,
            [
                "image INVALID",
                "ToolToTrackerTransform INVALID",
                "ToolToTrackerTransform not finite",
                "Image->World singular (pixel axes collapse)"
            ]
        );
    }

    #[test]
    fn all_invalid_is_no_valid_frames_and_missing_calibration_is_reported() {
        let seq = seq_with(vec![frame(
            0.0,
            &[("ProbeToTracker", DMat4::IDENTITY, false)],
        )]);
        let cal = Calibration::from_image_to_probe(DMat4::IDENTITY);
        let e =
            resolve_poses(&seq, Some(&cal), ReferenceChoice::Auto, Path::new("x.mha")).unwrap_err();
        assert_eq!(e.problem(), Some(FormatProblem::NoValidFrames));
        let e = resolve_poses(&seq, None, ReferenceChoice::Auto, Path::new("x.mha")).unwrap_err();
        assert_eq!(e.problem(), Some(FormatProblem::MissingTransform));
        let e = resolve_poses(
            &seq,
            Some(&cal),
            ReferenceChoice::Reference,
            Path::new("x.mha"),
        )
        .unwrap_err();
        assert_eq!(e.problem(), Some(FormatProblem::MissingTransform));
    }

    #[test]
    fn per_frame_image_to_reference_needs_no_calibration() {
        let seq = seq_with(vec![frame(
            0.0,
            &[("ImageToReference", translate(1.0, 0.0, 0.0), true)],
        )]);
        let r = resolve_poses(&seq, None, ReferenceChoice::Auto, Path::new("x")).unwrap();
        assert_eq!(r.world_frame, "Reference");
        assert_eq!(r.poses[0].image_to_world, translate(1.0, 0.0, 0.0));
    }

    #[test]
    fn clip_corners_follow_plus() {
        let clip = ClipRect {
            origin_px: [167, 62],
            size_px: [495, 488],
        };
        assert_eq!(
            clip_corners_px(820, 616, &clip),
            Some([167.0, 62.0, 662.0, 550.0])
        );
        let whole = ClipRect {
            origin_px: [0, 0],
            size_px: [820, 616],
        };
        assert_eq!(
            clip_corners_px(820, 616, &whole),
            Some([0.0, 0.0, 819.0, 615.0])
        );
        let outside = ClipRect {
            origin_px: [900, 0],
            size_px: [10, 10],
        };
        assert_eq!(clip_corners_px(820, 616, &outside), None);
        assert_eq!(clip_corners_px(0, 0, &whole), None);
    }

    #[test]
    fn sweeps_break_on_jump_and_pause() {
        let cal = Calibration::from_image_to_probe(DMat4::IDENTITY);
        let xs = [0.0, 1.0, 2.0, 10.0, 11.0, 12.0];
        let ts = [0.0, 0.1, 0.2, 0.3, 2.0, 2.1];
        let frames = xs
            .iter()
            .zip(ts)
            .map(|(&x, t)| frame(t, &[("ProbeToTracker", translate(x, 0.0, 0.0), true)]))
            .collect();
        let seq = seq_with(frames);
        let r = resolve_poses(&seq, Some(&cal), ReferenceChoice::Auto, Path::new("x")).unwrap();
        assert_eq!(split_sweeps(&seq, &r), vec![0..3, 3..4, 4..6]);
        let stats = path_stats(&[DVec3::ZERO, DVec3::X, DVec3::X * 3.0, DVec3::X * 6.0]);
        assert_eq!(stats.frames, 4);
        assert_eq!(stats.path_length_mm, 6.0);
        assert_eq!(
            (
                stats.spacing_min_mm,
                stats.spacing_median_mm,
                stats.spacing_max_mm
            ),
            (1.0, 2.0, 3.0)
        );
        let (lo, hi) = world_bounds(&seq, &r.poses).unwrap();
        assert_eq!(lo, DVec3::ZERO);
        assert_eq!(hi, DVec3::new(22.0, 20.0, 0.0));
    }
}
