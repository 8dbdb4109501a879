//! A live session: decoded messages in, a recorded tracked sequence and surfaces out. IMAGE messages
//! are either already placed in the Reference frame (PlusServer's `ImageToReference`: the image's own
//! matrix is the pose) or paired with a ProbeToReference TRANSFORM stream by timestamp (interpolated
//! between the transforms before and after the frame) and the config's Image->Probe calibration.
//! Every accepted frame is recorded, its pose marked invalid when the tracker said so or no pose could
//! be found, so nothing received is lost.

use std::collections::{BTreeMap, VecDeque};
use std::sync::atomic::{AtomicBool, Ordering};

use glam::{DMat4, DQuat, DVec3};

use echosurf::io::{
    Calibration, FrameTransform, PixelData, TrackedFrame, TrackedSequence, resolve_poses,
};
use echosurf::mesh::Mesh;
use echosurf::pipeline::{self, ExtractOptions};
use echosurf::progress::{NoProgress, Progress};
use echosurf::segment::crests::CrestCache;
use echosurf::segment::{BandMasks, segment_sequence};

use crate::codec::{Decoded, Image, Message, SCALAR_UINT8, STATUS_OK};

/// The transform name frames carry when the IMAGE matrix is their pose.
pub const IMAGE_TO_REFERENCE: &str = "ImageToReference";

/// How frames are placed and when the surface is refitted.
#[derive(Debug, Clone)]
pub struct SessionOptions {
    /// Only IMAGE messages from this device are frames (`None`: any device).
    pub image_device: Option<String>,
    /// `Some(name)`: images are in their own frame, placed by this TRANSFORM device's
    /// ProbeToReference poses and the calibration; `None`: the IMAGE matrix is ImageToReference.
    pub transform_device: Option<String>,
    /// Refit the surface after this many new frames (0: only at the end).
    pub update_every_frames: usize,
    /// Images waiting for a later transform beyond this many are placed with what is there.
    pub max_pending_images: usize,
    /// Transforms older than the newest this many are forgotten.
    pub max_kept_transforms: usize,
}

impl Default for SessionOptions {
    fn default() -> Self {
        SessionOptions {
            image_device: None,
            transform_device: None,
            update_every_frames: 30,
            max_pending_images: 256,
            max_kept_transforms: 1024,
        }
    }
}

/// One received tracker pose.
#[derive(Debug, Clone, Copy, PartialEq)]
struct StampedPose {
    timestamp_s: f64,
    matrix: DMat4,
    valid: bool,
}

/// An image received in transform-pairing mode, waiting for a transform at or after its time.
#[derive(Debug, Clone)]
struct PendingImage {
    timestamp_s: f64,
    pixels: Vec<u8>,
}

/// The growing recording and its pose sources.
#[derive(Debug)]
pub struct LiveSession {
    options: SessionOptions,
    recorded: TrackedSequence,
    transform_name: String,
    poses: VecDeque<StampedPose>,
    pending: VecDeque<PendingImage>,
    frames_since_update: usize,
}

/// Whether a v2/v3 message's metadata says its transform is not OK (PLUS writes
/// `<Name>TransformStatus` = `OK` / `INVALID`).
fn metadata_says_invalid(decoded: &Decoded) -> Option<String> {
    decoded
        .metadata
        .iter()
        .find(|(k, v)| {
            k.to_ascii_lowercase().ends_with("transformstatus")
                && !v.trim().eq_ignore_ascii_case("OK")
        })
        .map(|(k, v)| format!("{k} = {v}"))
}

/// Rigid interpolation between two poses: translation linearly, rotation by slerp (the scale of an
/// affine matrix is kept from `a`).
fn interpolate(a: &DMat4, b: &DMat4, t: f64) -> DMat4 {
    let (scale_a, rot_a, trans_a) = a.to_scale_rotation_translation();
    let (_, rot_b, trans_b) = b.to_scale_rotation_translation();
    let rot = rot_a.slerp(rot_b, t);
    DMat4::from_scale_rotation_translation(scale_a, DQuat::normalize(rot), trans_a.lerp(trans_b, t))
}

impl LiveSession {
    pub fn new(options: SessionOptions) -> LiveSession {
        let transform_name = match &options.transform_device {
            Some(_) => "ProbeToReference".to_string(),
            None => IMAGE_TO_REFERENCE.to_string(),
        };
        LiveSession {
            options,
            recorded: TrackedSequence {
                width: 0,
                height: 0,
                channels: 1,
                orientation: "MF".into(),
                frames: Vec::new(),
                pixels: PixelData::U8(Vec::new()),
                header: BTreeMap::new(),
            },
            transform_name,
            poses: VecDeque::new(),
            pending: VecDeque::new(),
            frames_since_update: 0,
        }
    }

    /// The frames recorded so far.
    pub fn sequence(&self) -> &TrackedSequence {
        &self.recorded
    }

    /// Images still waiting for a pose.
    pub fn pending_images(&self) -> usize {
        self.pending.len()
    }

    /// Takes one decoded message; returns warnings for what was refused or marked invalid.
    pub fn handle(&mut self, decoded: &Decoded) -> Vec<String> {
        let device = decoded.header.device_name.as_str();
        let mut warnings = Vec::new();
        match &decoded.message {
            Message::Image(image) => {
                if self
                    .options
                    .image_device
                    .as_deref()
                    .is_some_and(|d| d != device)
                {
                    return warnings;
                }
                self.take_image(decoded, image, &mut warnings);
            }
            Message::Transform(matrix)
                if self.options.transform_device.as_deref() == Some(device) =>
            {
                let invalid = metadata_says_invalid(decoded);
                if let Some(why) = &invalid {
                    warnings.push(format!(
                        "transform {device} at {:.3} s: {why}",
                        decoded.header.timestamp_s()
                    ));
                }
                self.poses.push_back(StampedPose {
                    timestamp_s: decoded.header.timestamp_s(),
                    matrix: *matrix,
                    valid: invalid.is_none(),
                });
                while self.poses.len() > self.options.max_kept_transforms.max(2) {
                    self.poses.pop_front();
                }
                self.place_pending(false, &mut warnings);
            }
            Message::Status(status) if status.code != STATUS_OK => warnings.push(format!(
                "status from {device}: code {} ({}) {}",
                status.code, status.error_name, status.text
            )),
            _ => {}
        }
        warnings
    }

    fn take_image(&mut self, decoded: &Decoded, image: &Image, warnings: &mut Vec<String>) {
        let device = &decoded.header.device_name;
        let timestamp_s = decoded.header.timestamp_s();
        if image.scalar_type != SCALAR_UINT8 || image.components != 1 || image.size[2] != 1 {
            warnings.push(format!(
                "IMAGE from {device} at {timestamp_s:.3} s dropped: only single-component 8-bit 2D frames \
                 are recorded (scalar type {}, {} components, {:?} pixels)",
                image.scalar_type, image.components, image.size
            ));
            return;
        }
        let (width, height) = (image.size[0] as usize, image.size[1] as usize);
        if self.recorded.frames.is_empty() && self.pending.is_empty() {
            self.recorded.width = width;
            self.recorded.height = height;
        } else if (width, height) != (self.recorded.width, self.recorded.height) {
            warnings.push(format!(
                "IMAGE from {device} at {timestamp_s:.3} s dropped: {width} x {height} px, the recording's \
                 frames are {} x {}",
                self.recorded.width, self.recorded.height
            ));
            return;
        }
        if self.options.transform_device.is_some() {
            self.pending.push_back(PendingImage {
                timestamp_s,
                pixels: image.pixels.clone(),
            });
            self.place_pending(false, warnings);
            return;
        }
        let invalid = metadata_says_invalid(decoded);
        if let Some(why) = &invalid {
            warnings.push(format!(
                "frame {} ({device} at {timestamp_s:.3} s): {why}: recorded, not used",
                self.recorded.frames.len()
            ));
        }
        let pose = FrameTransform {
            matrix: image.ijk_to_world(),
            valid: invalid.is_none(),
        };
        self.record(timestamp_s, &image.pixels, pose);
    }

    /// Places waiting images whose time the transforms now bracket; with `finish` (or past the pending
    /// bound) the rest too, from the nearest transform or invalid.
    fn place_pending(&mut self, finish: bool, warnings: &mut Vec<String>) {
        while let Some(front) = self.pending.front() {
            let t = front.timestamp_s;
            let after = self.poses.iter().position(|p| p.timestamp_s >= t);
            let forced = finish || self.pending.len() > self.options.max_pending_images;
            let pose = match after {
                Some(k) => {
                    let b = self.poses[k];
                    if b.timestamp_s == t || k == 0 {
                        Some(b)
                    } else {
                        let a = self.poses[k - 1];
                        let w = (t - a.timestamp_s) / (b.timestamp_s - a.timestamp_s);
                        Some(StampedPose {
                            timestamp_s: t,
                            matrix: interpolate(&a.matrix, &b.matrix, w),
                            valid: a.valid && b.valid,
                        })
                    }
                }
                None if forced => self.poses.back().copied(),
                None => break,
            };
            let image = self.pending.pop_front().expect("front exists");
            let index = self.recorded.frames.len();
            let transform = match pose {
                Some(p) => {
                    if !p.valid {
                        warnings.push(format!("frame {index} at {t:.3} s: its tracker pose is INVALID: recorded, not used"));
                    }
                    FrameTransform {
                        matrix: p.matrix,
                        valid: p.valid,
                    }
                }
                None => {
                    warnings.push(format!(
                        "frame {index} at {t:.3} s: no tracker pose received: recorded, not used"
                    ));
                    FrameTransform {
                        matrix: DMat4::IDENTITY,
                        valid: false,
                    }
                }
            };
            self.record(t, &image.pixels, transform);
        }
    }

    /// Records every image still waiting (at the end of the session).
    pub fn finish(&mut self) -> Vec<String> {
        let mut warnings = Vec::new();
        self.place_pending(true, &mut warnings);
        warnings
    }

    fn record(&mut self, timestamp_s: f64, pixels: &[u8], transform: FrameTransform) {
        if let PixelData::U8(all) = &mut self.recorded.pixels {
            all.extend_from_slice(pixels);
        }
        let mut frame = TrackedFrame {
            timestamp_s: Some(timestamp_s),
            image_valid: true,
            ..TrackedFrame::default()
        };
        frame
            .transforms
            .insert(self.transform_name.clone(), transform);
        self.recorded.frames.push(frame);
        self.frames_since_update += 1;
    }

    /// Whether enough new frames arrived for the next surface update.
    pub fn update_due(&self) -> bool {
        self.options.update_every_frames > 0
            && self.frames_since_update >= self.options.update_every_frames
    }

    /// Frames recorded since the last update's snapshot.
    pub fn frames_since_update(&self) -> usize {
        self.frames_since_update
    }

    /// A copy of the recording for an update, counting from now to the next.
    pub fn snapshot_for_update(&mut self) -> TrackedSequence {
        self.frames_since_update = 0;
        self.recorded.clone()
    }
}

/// The options of the surface updates during the sweep: `extract`'s defaults on a smaller sample
/// budget, a coarser surfacer lattice and the plain iso-surface, so an update keeps up with the frames
/// (the final mesh uses `extract`'s defaults).
pub fn update_extract_options(max_samples: usize, resolution_mm: f64) -> ExtractOptions {
    let defaults = ExtractOptions::default();
    ExtractOptions {
        max_samples,
        sheet: pipeline::Sheet::Iso,
        surface: echosurf::surface::SurfaceOptions {
            resolution_mm,
            ..defaults.surface.clone()
        },
        ..defaults
    }
}

/// The surface of `sequence` (all its usable frames), as `extract` would make it with `options`: the
/// first level's mesh.
pub fn surface_of(
    sequence: &TrackedSequence,
    calibration: &Calibration,
    options: &ExtractOptions,
) -> echosurf::Result<Mesh> {
    surface_with(sequence, calibration, options, None, &NoProgress)
}

/// [`surface_of`], taking the frames' echo crests from `crests` where it holds them (found during the
/// sweep by [`add_echo_crests`]) and adding the others: the same mesh, with less left to do after the
/// last frame.
pub fn surface_of_reusing(
    sequence: &TrackedSequence,
    calibration: &Calibration,
    options: &ExtractOptions,
    crests: &mut CrestCache,
) -> echosurf::Result<Mesh> {
    surface_with(sequence, calibration, options, Some(crests), &NoProgress)
}

/// Frames whose echo crests [`add_echo_crests`] finds between two looks at its stop flag.
pub const CREST_FRAMES_PER_STEP: usize = 8;

/// Adds to `crests` the echo crests of the recorded frames it lacks, as the final mesh (made with
/// `options`) reads them, until `stop` is set (checked every [`CREST_FRAMES_PER_STEP`] frames).
pub fn add_echo_crests(
    sequence: &TrackedSequence,
    calibration: &Calibration,
    options: &ExtractOptions,
    crests: &mut CrestCache,
    stop: &AtomicBool,
) -> echosurf::Result<()> {
    pipeline::add_echo_crests(
        sequence,
        Some(calibration),
        options,
        crests,
        CREST_FRAMES_PER_STEP,
        &|| !stop.load(Ordering::Relaxed),
    )
}

/// [`surface_of`], reporting to `progress`, reusing `crests` when given.
fn surface_with(
    sequence: &TrackedSequence,
    calibration: &Calibration,
    options: &ExtractOptions,
    crests: Option<&mut CrestCache>,
    progress: &dyn Progress,
) -> echosurf::Result<Mesh> {
    let reused = pipeline::Reused {
        masks: None,
        crests,
    };
    let output = pipeline::extract_reusing(sequence, Some(calibration), options, reused, progress)?;
    Ok(first_mesh(output))
}

/// The first level's mesh of an extraction (empty when there is none).
fn first_mesh(output: pipeline::ExtractOutput) -> Mesh {
    output
        .surfaces
        .into_iter()
        .next()
        .map(|s| s.mesh)
        .unwrap_or_default()
}

/// The bands of the frames segmented so far, so an update segments only the frames that arrived since
/// the last one: each batch of new frames is segmented as a sequence of its own (its band starts
/// afresh, as at a sweep start) and its masks are appended. Updates only; the final mesh segments the
/// whole recording as `extract` does.
#[derive(Debug, Default, Clone)]
pub struct IncrementalBands {
    bands: Option<BandMasks>,
    /// Set when a batch came out a bone sweep (its bands are fitted differently): from then on every
    /// update segments the whole recording.
    whole_only: bool,
}

impl IncrementalBands {
    /// Frames whose bands are kept.
    pub fn frames(&self) -> usize {
        self.bands.as_ref().map_or(0, |b| b.masks.len())
    }

    /// Segments the frames of `sequence` after those already done (`sequence` must extend the one of
    /// the previous call); `None` when the whole recording must be segmented instead.
    pub fn extend(
        &mut self,
        sequence: &TrackedSequence,
        calibration: &Calibration,
        options: &ExtractOptions,
    ) -> Option<BandMasks> {
        let done = self.frames();
        if self.whole_only || done > sequence.frames.len() {
            return None;
        }
        if done == sequence.frames.len() {
            return self.bands.clone();
        }
        let PixelData::U8(pixels) = &sequence.pixels else {
            return None;
        };
        let frame_len = sequence.frame_len();
        let batch = TrackedSequence {
            frames: sequence.frames[done..].to_vec(),
            pixels: PixelData::U8(pixels[done * frame_len..].to_vec()),
            header: sequence.header.clone(),
            orientation: sequence.orientation.clone(),
            width: sequence.width,
            height: sequence.height,
            channels: sequence.channels,
        };
        let path = std::path::Path::new("<live frames>");
        let new =
            resolve_poses(&batch, Some(calibration), options.reference, path).and_then(|poses| {
                segment_sequence(
                    &batch,
                    &poses,
                    calibration.clip,
                    &options.init,
                    &options.segment,
                    &NoProgress,
                )
            });
        let new = match new {
            Ok(b) if b.bone_sweep => {
                self.whole_only = true;
                return None;
            }
            Ok(b) => b,
            // No placeable frame in the batch (or nothing to segment): no band for these frames.
            Err(e) => BandMasks {
                masks: vec![vec![0; frame_len]; batch.frames.len()],
                warnings: vec![format!("frames {done}-{}: {e}", sequence.frames.len() - 1)],
                initialised_frames: Vec::new(),
                frames: batch.frames.clone(),
                bone_sweep: false,
                bone_echoes: Vec::new(),
                ..self.bands.clone()?
            },
        };
        match &mut self.bands {
            None => self.bands = Some(new),
            Some(b) => {
                b.masks.extend(new.masks);
                b.frames.extend(new.frames);
                b.initialised_frames
                    .extend(new.initialised_frames.iter().map(|k| k + done));
                b.warnings.extend(new.warnings);
            }
        }
        self.bands.clone()
    }
}

/// An update's surface: the new frames segmented into `bands`, then the fit and surface of all
/// frames ([`surface_of`] when the bands cannot be reused).
pub fn update_surface(
    bands: &mut IncrementalBands,
    sequence: &TrackedSequence,
    calibration: &Calibration,
    options: &ExtractOptions,
) -> echosurf::Result<Mesh> {
    update_surface_with(bands, sequence, calibration, options, &NoProgress)
}

fn update_surface_with(
    bands: &mut IncrementalBands,
    sequence: &TrackedSequence,
    calibration: &Calibration,
    options: &ExtractOptions,
    progress: &dyn Progress,
) -> echosurf::Result<Mesh> {
    progress.start("update: segment the new frames", 0);
    let masks = bands.extend(sequence, calibration, options);
    progress.finish();
    let Some(masks) = masks else {
        return surface_with(sequence, calibration, options, None, progress);
    };
    let output =
        pipeline::extract_with_masks(sequence, Some(calibration), options, masks, progress)?;
    Ok(first_mesh(output))
}

/// The unwind payload that abandons an update (never a panic: no hook runs, nothing is printed).
struct UpdateAbandoned;

/// Abandons the update it watches at the next stage start or progress report once `stop` is set.
struct StopAtReport<'a>(&'a AtomicBool);

impl StopAtReport<'_> {
    fn check(&self) {
        if self.0.load(Ordering::Relaxed) {
            std::panic::resume_unwind(Box::new(UpdateAbandoned));
        }
    }
}

impl Progress for StopAtReport<'_> {
    fn start(&self, _stage: &str, _total: u64) {
        self.check();
    }
    fn advance(&self, _done: u64) {
        self.check();
    }
    fn finish(&self) {
        self.check();
    }
    fn stage_started(&self, _stage: &str) -> bool {
        self.check();
        false
    }
}

/// [`update_surface`], abandoned (`None`) at its next stage start or progress report once `stop` is
/// set: when the sweep ends, an update still running would take a core from the final mesh (2 cores;
/// docs/decisions/0030-live-openigtlink.md). `bands` stays valid either way (a batch's masks are
/// appended whole or not at all).
pub fn update_surface_unless_stopped(
    bands: &mut IncrementalBands,
    sequence: &TrackedSequence,
    calibration: &Calibration,
    options: &ExtractOptions,
    stop: &AtomicBool,
) -> Option<echosurf::Result<Mesh>> {
    let run = std::panic::AssertUnwindSafe(|| {
        update_surface_with(bands, sequence, calibration, options, &StopAtReport(stop))
    });
    match std::panic::catch_unwind(run) {
        Ok(result) => Some(result),
        Err(payload) if payload.is::<UpdateAbandoned>() => None,
        Err(payload) => std::panic::resume_unwind(payload),
    }
}

/// The centre of a frame in the world (for tests and reports).
pub fn frame_centre(sequence: &TrackedSequence, index: usize, name: &str) -> Option<DVec3> {
    let t = sequence.frames.get(index)?.transforms.get(name)?;
    Some(t.matrix.transform_point3(DVec3::new(
        sequence.width as f64 / 2.0,
        sequence.height as f64 / 2.0,
        0.0,
    )))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::codec::{Header, encode_transform};

    fn decoded(
        type_name: &str,
        device: &str,
        t: f64,
        message: Message,
        metadata: Vec<(String, String)>,
    ) -> Decoded {
        Decoded {
            header: Header {
                version: 2,
                type_name: type_name.into(),
                device_name: device.into(),
                timestamp: crate::codec::timestamp_bits(t),
                body_size: 0,
                crc: 0,
            },
            metadata,
            message,
        }
    }

    fn image_at(x: f64) -> Image {
        Image::from_u8_frame(
            4,
            3,
            vec![x as u8; 12],
            &DMat4::from_translation(DVec3::new(x, 0.0, 0.0)),
        )
    }

    #[test]
    fn image_to_reference_frames_are_recorded_with_their_matrix_and_status() {
        let mut s = LiveSession::new(SessionOptions::default());
        for k in 0..3 {
            let meta = if k == 1 {
                vec![("ImageToReferenceTransformStatus".into(), "INVALID".into())]
            } else {
                vec![]
            };
            let w = s.handle(&decoded(
                "IMAGE",
                "Image_Reference",
                k as f64 * 0.5,
                Message::Image(image_at(k as f64)),
                meta,
            ));
            assert_eq!(w.len(), usize::from(k == 1), "{w:?}");
        }
        let seq = s.sequence();
        assert_eq!(seq.frames.len(), 3);
        assert_eq!(
            seq.pixels,
            PixelData::U8([0u8, 1, 2].iter().flat_map(|&v| [v; 12]).collect())
        );
        let valid: Vec<bool> = seq
            .frames
            .iter()
            .map(|f| f.transforms[IMAGE_TO_REFERENCE].valid)
            .collect();
        assert_eq!(valid, [true, false, true]);
        assert_eq!(
            frame_centre(seq, 2, IMAGE_TO_REFERENCE).unwrap(),
            DVec3::new(4.0, 1.5, 0.0)
        );
        // A frame of another size is refused with a warning, not recorded.
        let other = Image::from_u8_frame(5, 3, vec![0; 15], &DMat4::IDENTITY);
        let w = s.handle(&decoded(
            "IMAGE",
            "Image_Reference",
            2.0,
            Message::Image(other),
            vec![],
        ));
        assert_eq!((w.len(), s.sequence().frames.len()), (1, 3));
    }

    /// Paired mode: an image between two transforms gets the interpolated pose (the analytic midpoint
    /// of a translation and a 90-degree turn), images after the last transform wait until the end.
    #[test]
    fn images_are_paired_with_interpolated_transforms() {
        let mut s = LiveSession::new(SessionOptions {
            transform_device: Some("ProbeToReference".into()),
            ..SessionOptions::default()
        });
        let a = DMat4::IDENTITY;
        let b = DMat4::from_rotation_translation(
            DQuat::from_rotation_z(std::f64::consts::FRAC_PI_2),
            DVec3::new(10.0, 0.0, 0.0),
        );
        let _ = crate::codec::decode_transform(&encode_transform(&b)).unwrap();
        s.handle(&decoded(
            "TRANSFORM",
            "ProbeToReference",
            1.0,
            Message::Transform(a),
            vec![],
        ));
        s.handle(&decoded(
            "IMAGE",
            "Image",
            1.5,
            Message::Image(image_at(1.0)),
            vec![],
        ));
        assert_eq!((s.sequence().frames.len(), s.pending_images()), (0, 1));
        s.handle(&decoded(
            "TRANSFORM",
            "ProbeToReference",
            2.0,
            Message::Transform(b),
            vec![],
        ));
        assert_eq!(s.sequence().frames.len(), 1);
        let m = s.sequence().frames[0].transforms["ProbeToReference"];
        assert!(m.valid);
        let expected = DMat4::from_rotation_translation(
            DQuat::from_rotation_z(std::f64::consts::FRAC_PI_4),
            DVec3::new(5.0, 0.0, 0.0),
        );
        assert!(m.matrix.abs_diff_eq(expected, 1e-12), "{}", m.matrix);
        // Bracketed by an INVALID transform: recorded, marked invalid.
        let bad = vec![("ProbeToReferenceTransformStatus".into(), "INVALID".into())];
        s.handle(&decoded(
            "IMAGE",
            "Image",
            2.5,
            Message::Image(image_at(2.0)),
            vec![],
        ));
        let w = s.handle(&decoded(
            "TRANSFORM",
            "ProbeToReference",
            3.0,
            Message::Transform(b),
            bad,
        ));
        assert_eq!(w.len(), 2, "{w:?}");
        assert!(!s.sequence().frames[1].transforms["ProbeToReference"].valid);
        // After the last transform: placed at the end from the last pose.
        s.handle(&decoded(
            "IMAGE",
            "Image",
            3.5,
            Message::Image(image_at(3.0)),
            vec![],
        ));
        assert_eq!(s.pending_images(), 1);
        s.finish();
        assert_eq!((s.sequence().frames.len(), s.pending_images()), (3, 0));
    }

    #[test]
    fn updates_come_every_n_frames() {
        let mut s = LiveSession::new(SessionOptions {
            update_every_frames: 2,
            ..SessionOptions::default()
        });
        let mut due = Vec::new();
        for k in 0..5 {
            s.handle(&decoded(
                "IMAGE",
                "I",
                k as f64,
                Message::Image(image_at(k as f64)),
                vec![],
            ));
            due.push(s.update_due());
            if s.update_due() {
                assert_eq!(s.snapshot_for_update().frames.len(), k + 1);
            }
        }
        assert_eq!(due, [false, true, false, true, false]);
    }

    fn small_sphere() -> echosurf_sim::Simulation {
        let options = echosurf_sim::SimulationOptions {
            phantom: echosurf_sim::PhantomKind::Sphere,
            frames_per_sweep: 20,
            sweeps: Some(1),
            width_px: 96,
            height_px: 80,
            pixel_size_mm: 0.4,
            ..echosurf_sim::SimulationOptions::default()
        };
        echosurf_sim::simulate(&options, &NoProgress).unwrap()
    }

    /// The refit from bands segmented elsewhere is `extract` itself when the bands are the whole
    /// sequence's; growing bands keep each batch as segmenting that batch alone gives it.
    #[test]
    fn bands_grow_by_batches_and_refit_like_extract() {
        let sim = small_sphere();
        let (sequence, calibration) = (&sim.sequence, &sim.calibration_written);
        let options = update_extract_options(4_000, 1.0);
        let whole = surface_of(sequence, calibration, &options).unwrap();
        let poses = resolve_poses(
            sequence,
            Some(calibration),
            options.reference,
            std::path::Path::new("s"),
        )
        .unwrap();
        let masks = segment_sequence(
            sequence,
            &poses,
            calibration.clip,
            &options.init,
            &options.segment,
            &NoProgress,
        )
        .unwrap();
        let from_masks = pipeline::extract_with_masks(
            sequence,
            Some(calibration),
            &options,
            masks.clone(),
            &NoProgress,
        )
        .unwrap();
        assert!(!whole.triangles.is_empty());
        assert_eq!(from_masks.surfaces[0].mesh, whole);

        let prefix = |n: usize| {
            let mut s = sequence.clone();
            s.frames.truncate(n);
            let PixelData::U8(p) = &mut s.pixels else {
                panic!()
            };
            p.truncate(n * sequence.frame_len());
            s
        };
        let mut bands = IncrementalBands::default();
        let first = bands.extend(&prefix(10), calibration, &options).unwrap();
        let both = bands.extend(sequence, calibration, &options).unwrap();
        assert_eq!(both.masks.len(), 20);
        assert_eq!(both.masks[..10], first.masks[..]);
        let second_alone = {
            let mut rest = IncrementalBands::default();
            let mut s = sequence.clone();
            s.frames.drain(..10);
            let PixelData::U8(p) = &mut s.pixels else {
                panic!()
            };
            p.drain(..10 * sequence.frame_len());
            rest.extend(&s, calibration, &options).unwrap()
        };
        assert_eq!(both.masks[10..], second_alone.masks[..]);
        // Both start their band on frame 0 alike.
        assert_eq!(first.masks[0], masks.masks[0]);
        let mesh = update_surface(&mut bands, sequence, calibration, &options).unwrap();
        assert!(!mesh.triangles.is_empty());
    }

    /// An update not stopped is [`update_surface`]'s, byte for byte; one stopped is abandoned without a
    /// mesh, leaves the bands as they were, and the next update is again the plain one.
    #[test]
    fn a_stopped_update_is_abandoned_and_leaves_the_bands_usable() {
        let sim = small_sphere();
        let (sequence, calibration) = (&sim.sequence, &sim.calibration_written);
        let options = update_extract_options(4_000, 1.0);
        let plain = update_surface(
            &mut IncrementalBands::default(),
            sequence,
            calibration,
            &options,
        )
        .unwrap();
        let running = AtomicBool::new(false);
        let mut bands = IncrementalBands::default();
        let watched =
            update_surface_unless_stopped(&mut bands, sequence, calibration, &options, &running)
                .expect("not stopped")
                .unwrap();
        assert_eq!(watched, plain);
        let stopped = AtomicBool::new(true);
        let mut fresh = IncrementalBands::default();
        assert!(
            update_surface_unless_stopped(&mut fresh, sequence, calibration, &options, &stopped)
                .is_none()
        );
        assert_eq!(fresh.frames(), 0);
        let again = update_surface(&mut fresh, sequence, calibration, &options).unwrap();
        assert_eq!(again, plain);
    }

    /// The first `n` frames of `sequence`, as the recording stood then.
    fn prefix_of(sequence: &TrackedSequence, n: usize) -> TrackedSequence {
        let mut s = sequence.clone();
        s.frames.truncate(n);
        let PixelData::U8(p) = &mut s.pixels else {
            panic!("8-bit frames")
        };
        p.truncate(n * sequence.frame_len());
        s
    }

    /// Echo crests found batch by batch as the recording grows make the final mesh `extract` makes
    /// from scratch, byte for byte; with the stop flag set, nothing is found.
    #[test]
    fn crests_found_during_the_sweep_give_extracts_final_mesh() {
        let sim = small_sphere();
        let (sequence, calibration) = (&sim.sequence, &sim.calibration_written);
        let options = ExtractOptions::default();
        let going = AtomicBool::new(false);
        let mut crests = CrestCache::default();
        add_echo_crests(
            &prefix_of(sequence, 8),
            calibration,
            &options,
            &mut crests,
            &AtomicBool::new(true),
        )
        .unwrap();
        assert_eq!(crests.frames(), 0, "stopped before the first frames");
        for n in [8, 14] {
            add_echo_crests(
                &prefix_of(sequence, n),
                calibration,
                &options,
                &mut crests,
                &going,
            )
            .unwrap();
            assert_eq!(crests.frames(), n);
        }
        let reused = pipeline::Reused {
            masks: None,
            crests: Some(&mut crests),
        };
        let final_output =
            pipeline::extract_reusing(sequence, Some(calibration), &options, reused, &NoProgress)
                .unwrap();
        assert_eq!(crests.frames(), 20, "the last frames' crests were added");
        let from_scratch =
            pipeline::extract(sequence, Some(calibration), &options, &NoProgress).unwrap();
        assert!(
            final_output.report.sheets[0].crests_linked > 0,
            "the final mesh reads the frames' crests: {:?}",
            final_output.report.sheets
        );
        assert!(!final_output.surfaces[0].mesh.triangles.is_empty());
        assert_eq!(final_output.surfaces[0].mesh, from_scratch.surfaces[0].mesh);
        assert_eq!(
            final_output.report.sheets[0].crests_linked,
            from_scratch.report.sheets[0].crests_linked
        );
        // The iso-surface reads no crests: nothing is found for it.
        let iso = ExtractOptions {
            sheet: pipeline::Sheet::Iso,
            ..ExtractOptions::default()
        };
        let mut none = CrestCache::default();
        add_echo_crests(sequence, calibration, &iso, &mut none, &going).unwrap();
        assert_eq!(none.frames(), 0);
    }
}
