//! Band segmentation (Zhang, Rohling & Pai 2002): keep a band of pixels around the boundary in each frame.
//!
//! The fit only sees the pixels kept here, so the band must contain the boundary and some pixels on either
//! side of it (their intensities act as a quasi-distance to the boundary), and should drop the rest.
//!
//! # The propagation, as the paper specifies it
//! For each frame `i` of a sweep, with `B_i` the band carried from the previous frame (for the first frame:
//! the initial band):
//! 1. prior `P = C1` (1.0) on `B_i`, `C0` (0.2) elsewhere;
//! 2. edgels: the `M` largest vertical gradients of the smoothed frame, one local maximum per column
//!    crossing (echoes travel down the columns);
//! 3. likelihood: Gaussian-weighted proximity to the nearest edgel, `G(d) = exp(-d^2 / 2 sigma^2)` for
//!    `d <= truncation` and 0 beyond (sigma 15 px, truncation 32 px);
//! 4. `P_new = L (x) P + C0`;
//! 5. the band kept in frame `i` (and carried to frame `i + 1`) is `P_new >= T` (0.35).
//!
//! **Our reading of `L (x) P`.** The likelihood kernel is centred on the edgels and each edgel carries the
//! prior of the pixel it sits on, so `(L (x) P)(x) = max_e P(e) G(|x - e|)` over the edgels `e`: a
//! convolution of the prior-weighted edgel map with the Gaussian proximity kernel, taken in the max-product
//! sense so that "proximity to the *nearest* edgel" holds and the result does not grow with edgel density.
//! Consequences, with the defaults: an edgel inside the previous band keeps every pixel within
//! `sigma * sqrt(2 ln(C1 / (T - C0)))` = 29.2 px of it (on both sides of the boundary); an edgel outside
//! the band keeps only `sigma * sqrt(2 ln(C0 / (T - C0)))` = 11.4 px around it (a new, unconfirmed echo is
//! kept narrowly and confirmed by the next frame); pixels near no edgel get `C0 < T` and are dropped. The
//! new band is centred on *this* frame's edgels, not on the old band, so it follows a boundary that moves
//! by up to ~29 px between frames and does not drift or widen. (A pointwise product `L * P` would instead
//! shrink the band on the side the boundary moves towards, by the motion, every frame.)
//!
//! **Pixel units.** All lengths are in pixels of the frame, as in the paper, whose frames were about
//! 0.1-0.2 mm/px: there sigma 15 px is 1.5-3 mm and the band is about +/-3-6 mm. On finer images the same
//! pixel values give a band that is narrower in mm (the PLUS spine data at 0.08 mm/px: +/-2.3 mm), and on
//! coarser images a wider one. Each length can instead be given in mm ([`Length::Mm`]); it is converted with
//! the pixel size of the frames' Image->World matrices (mean of the column and row spacing).
//!
//! **Edgels.** "The M largest vertical gradients" is read literally on the signed derivative down the
//! column ([`EdgePolarity::Rising`]: entering a bright echo from the probe side, where the interface
//! facing the probe lies), after non-maximum suppression along the column, so a boundary gives one edgel
//! per column it crosses. M defaults to 0.75 x the columns of the clip rectangle.
//!
//! Beyond the paper (each an option, documented on [`SegmentOptions`]): an automatic initial band
//! ([`InitialBand::Auto`]: bright structures with a shadow below them, dilated by the in-band radius);
//! recovery from a lost band (fewer than `min_edgels_in_band_fraction * M` edgels inside the carried band:
//! a warning naming the frame, then automatic re-initialisation on that frame); a relative floor on edgel
//! strength so speckle edges do not fill up the M where a boundary is in view; the clip rectangle (pixels
//! outside it are never kept and never produce edgels), shrunk to the non-black data region of the frames;
//! a band that follows only what it holds ([`SegmentOptions::follow_band`], CLI `--follow-band`, off by
//! default: edgels outside the carried band are ignored, the paper's step 3 read strictly);
//! a backward pass ([`SegmentOptions::backward_pass`], CLI `--backward-pass`, off by default): after each
//! sweep the band is propagated back from its last frame as well and the union kept, so an echo that
//! enters the view gets the full band on its first frame, not only the narrow band of an unconfirmed
//! edgel. It is not the default: in `extract` it helps the duck and costs the hand (measured in
//! docs/decisions/0002-segmentation-beyond-the-paper.md, "From the segment module's doc").
//! [`SegmentOptions::wall_band`] (CLI `--wall-band`) bundles it with chained edgels in two layers
//! and the paper's band width in mm: every echoing wall in at most 27 % of the pixels (simulated).
//!
//! **Speckle-robust edgels** ([`SegmentOptions::chained`], CLI `--chain-edgels`; off by default, so the
//! extract pipeline keeps its behaviour). Where a boundary's echo is faint (at the top of the image, or
//! where the surface turns away from the beam) the M largest gradients are mostly speckle, the band
//! seeds on them and percolates over the frame. [`EdgelChaining`] takes each column's strongest candidate,
//! keeps chains of neighbouring-column edgels (rows <= 4 px apart) that hold one edgel above the relative
//! floor, lets weak edgels (>= 0.3 x the floor) continue such a chain down a fading flank, and drops
//! chains shorter than 3 mm (speckle grains are ~1 mm wide); then it does the same once more with each
//! column's next candidate beyond the band around what it kept (a second layer: a wall seen through the
//! first, such as a hollow organ's far wall); it is paired with 1 mm smoothing (measured in
//! docs/decisions/0002-segmentation-beyond-the-paper.md, "From the segment module's doc"). With
//! `edgel_chaining: None` the paper's M largest are used.
//!
//! Speed: per frame one separable Gaussian, one gradient/NMS pass, two exact distance transforms (O(N),
//! Felzenszwalb-Huttenlocher) and one lookup per pixel (squared distances are integers, so the Gaussian
//! is a table); rows run in parallel with rayon and all buffers are reused between frames.

pub mod bone;
pub mod crests;
mod crop;
pub mod filters;
mod init;
mod masks;
mod options;
mod preview;
mod propagate;
#[doc(hidden)]
pub mod synthetic;

use std::collections::BTreeSet;

pub use crop::data_region;
pub use init::{find_echo_structures, rasterize_polygon};
pub use masks::BandMasks;
pub use options::{EdgelChaining, InitialBand, Length, ResolvedParameters, SegmentOptions};
pub use preview::{default_preview_frames, write_band_preview, write_frame_png};

use crop::{add_to_mask, clip_beyond_frame_warning, crop_bool, effective_clip, pixel_size_of};
use options::{pixel_size_for_lengths, resolve_parameters};
use propagate::{BandPropagation, Propagator, Workspace, load_smoothed};

use crate::io::{ClipRect, PoseResolution, TrackedSequence};
use crate::progress::Progress;
use crate::{Error, Result};

pub use filters::EdgePolarity;
use filters::gaussian_taps;

/// Segments every frame: the paper's band propagation along each sweep (`crate::io::split_sweeps`), the
/// initial band on the first frame of every sweep. Frames without a usable pose get all-zero masks. Pixels
/// outside `clip` are never kept. Deterministic and independent of the thread count.
pub fn segment_sequence(
    sequence: &TrackedSequence,
    poses: &PoseResolution,
    clip: Option<ClipRect>,
    init: &InitialBand,
    options: &SegmentOptions,
    progress: &dyn Progress,
) -> Result<BandMasks> {
    options.validate()?;
    check_segmentable(sequence, poses)?;
    let (width, height) = (sequence.width, sequence.height);
    let init_full = initial_band_pixels(init, width, height)?;
    let pixel_size_mm = poses
        .poses
        .first()
        .map(|p| pixel_size_of(&p.image_to_world));
    let px_size = pixel_size_for_lengths(options, poses, pixel_size_mm)?;
    let given_clip = clip;
    let mut clip = effective_clip(clip, width, height);
    if options.detect_data_region
        && let Some(c) = clip
    {
        clip = data_region(sequence, poses, c);
    }
    let orientation = {
        let third = sequence.orientation.chars().nth(2);
        let mut o = String::from("MF");
        if let Some(c) = third {
            o.push(c);
        }
        o
    };
    let parameters = resolve_parameters(
        options,
        pixel_size_mm,
        px_size,
        clip.map_or(0, |c| c.size_px[0]),
    );
    let masks = vec![vec![0u8; width * height]; sequence.frames.len()];
    let Some(clip) = clip else {
        return Ok(BandMasks {
            width,
            height,
            masks,
            warnings: vec!["the clip rectangle lies outside the frame: every mask is empty".into()],
            initialised_frames: Vec::new(),
            frames: sequence.frames.clone(),
            orientation,
            parameters,
            bone_sweep: false,
            bone_echoes: Vec::new(),
        });
    };
    let init_crop: Option<Vec<bool>> = init_full.map(|full| crop_bool(&full, width, clip));
    if let Some(b) = &init_crop
        && !b.iter().any(|&x| x)
    {
        return Err(Error::InvalidInput(
            "the initial band covers no pixel inside the clip rectangle".into(),
        ));
    }

    if init_crop.is_none() && options.bone != bone::BoneMode::Never {
        let bone_px = pixel_size_mm.filter(|s| s.is_finite() && *s > 0.0);
        if let Some(bone_px) = bone_px
            && let Some(masks) = bone_masks(sequence, poses, clip, bone_px, options)
        {
            let (masks, initialised_frames, bone_echoes) = masks;
            return Ok(BandMasks {
                width,
                height,
                masks,
                warnings: clip_beyond_frame_warning(given_clip, width, height)
                    .into_iter()
                    .collect(),
                initialised_frames,
                frames: sequence.frames.clone(),
                orientation,
                parameters,
                bone_sweep: true,
                bone_echoes,
            });
        }
    }
    let mut run = BandPropagation {
        sequence,
        clip,
        propagator: Propagator::new(options, &parameters, px_size, clip),
        ws: Workspace::default(),
        prior: Vec::new(),
        band: Vec::new(),
        masks,
        warnings: clip_beyond_frame_warning(given_clip, width, height)
            .into_iter()
            .collect(),
        initialised_frames: Vec::new(),
    };
    let sweeps = crate::io::split_sweeps(sequence, poses);
    let total: usize = sweeps.iter().map(|s| s.len()).sum();
    progress.start("segment", total as u64);
    let mut done = 0u64;
    let mut seen = BTreeSet::new();
    // Per sweep, (position in the sweep, frame): a frame posed twice is segmented once, where it first
    // comes.
    let sweep_frames: Vec<Vec<(usize, usize)>> = sweeps
        .into_iter()
        .map(|sweep| {
            sweep
                .enumerate()
                .filter_map(|(k, pose_index)| {
                    let frame = poses.poses[pose_index].frame_index;
                    seen.insert(frame).then_some((k, frame))
                })
                .collect()
        })
        .collect();
    for frames in &sweep_frames {
        for &(k, frame) in frames {
            run.forward(k, frame, init_crop.as_deref());
            done += 1;
            progress.advance(done);
        }
    }
    if options.backward_pass {
        // Back over the sweeps in reverse. Where the forward pass carried the band from one sweep into
        // the next (a given first band), the backward pass carries it back from the next sweep's first
        // frame into this one's last.
        let mut carried: Option<Vec<bool>> = None;
        for frames in sweep_frames.iter().rev().filter(|f| !f.is_empty()) {
            run.backward(frames, carried.as_deref());
            carried = init_crop.is_some().then(|| run.prior.clone());
        }
    }
    progress.finish();
    Ok(BandMasks {
        width,
        height,
        masks: run.masks,
        warnings: run.warnings,
        initialised_frames: run.initialised_frames,
        frames: sequence.frames.clone(),
        orientation,
        parameters,
        bone_sweep: false,
        bone_echoes: Vec::new(),
    })
}

/// The bone bands of every posed frame when the sweep is bone ([`bone::BoneEvidence::is_bone`], or
/// [`bone::BoneMode::Always`]); `None` otherwise. Also returns the frames that hold a bone band.
fn bone_masks(
    sequence: &TrackedSequence,
    poses: &PoseResolution,
    clip: ClipRect,
    pixel_size_mm: f64,
    options: &SegmentOptions,
) -> Option<BoneBands> {
    use rayon::prelude::*;
    let frame_count = sequence.frames.len();
    let bone_options = &options.bone_echoes;
    let taps = gaussian_taps(bone_options.smoothing_mm / pixel_size_mm);
    let (cw, ch) = (clip.size_px[0], clip.size_px[1]);
    let mut frames: Vec<usize> = poses.poses.iter().map(|p| p.frame_index).collect();
    frames.sort_unstable();
    frames.dedup();
    let per_frame: Vec<FrameBoneEvidence> = frames
        .par_iter()
        .map(|&frame| {
            let mut ws = Workspace::default();
            load_smoothed(&mut ws, sequence, frame, clip, &taps);
            let levels = bone::near_field_and_echo_levels(&ws.smoothed, cw, ch, pixel_size_mm);
            let rows = bone::bone_echoes(&ws.smoothed, cw, ch, pixel_size_mm, bone_options);
            (levels, rows)
        })
        .collect();
    let min_columns = bone::BONE_FRAME_COLUMN_FRACTION * cw as f64;
    let evidence = bone::BoneEvidence {
        frames: per_frame.len(),
        tissue_frames: bone::tissue_frames(&per_frame.iter().map(|(l, _)| *l).collect::<Vec<_>>()),
        bone_frames: per_frame
            .iter()
            .filter(|(_, rows)| rows.iter().flatten().count() as f64 >= min_columns)
            .count(),
    };
    if options.bone == bone::BoneMode::Auto && !evidence.is_bone() {
        return None;
    }
    let width = sequence.width;
    let mut masks = vec![vec![0u8; width * sequence.height]; frame_count];
    let mut with_band = Vec::new();
    let mut echoes = vec![Vec::new(); frame_count];
    let mut band = Vec::new();
    let [u0, v0] = clip.origin_px;
    for (&frame, (_, rows)) in frames.iter().zip(&per_frame) {
        if rows.iter().all(Option::is_none) {
            continue;
        }
        band.clear();
        band.resize(cw * ch, true);
        add_to_mask(&band, clip, width, &mut masks[frame]);
        let mut full = vec![None; width];
        for (u, e) in rows.iter().enumerate() {
            full[u0 + u] = e.map(|e| bone::BoneEcho {
                row: e.row + v0,
                ..e
            });
        }
        echoes[frame] = full;
        with_band.push(frame);
    }
    Some((masks, with_band, echoes))
}

/// One frame's near-field and echo levels, and its bone echoes per column.
type FrameBoneEvidence = (Option<[f64; 2]>, Vec<Option<bone::BoneEcho>>);

/// Bone bands: masks, the frames holding one, and each frame's bone echoes per column.
type BoneBands = (Vec<Vec<u8>>, Vec<usize>, Vec<Vec<Option<bone::BoneEcho>>>);

/// Images, pixel data of the stated size, and poses that name frames of the sequence.
fn check_segmentable(sequence: &TrackedSequence, poses: &PoseResolution) -> Result<()> {
    let (width, height) = (sequence.width, sequence.height);
    if sequence.is_tracking_only() || width == 0 || height == 0 {
        return Err(Error::InvalidInput(
            "cannot segment a tracking-only sequence (it has no images)".into(),
        ));
    }
    let frame_count = sequence.frames.len();
    if sequence.pixels.len() != sequence.frame_len() * frame_count {
        return Err(Error::InvalidInput(format!(
            "sequence pixel data holds {} values, expected {} ({}x{}x{} frames x {} channels)",
            sequence.pixels.len(),
            sequence.frame_len() * frame_count,
            width,
            height,
            frame_count,
            sequence.channels
        )));
    }
    if let Some(&bad) = poses.poses.iter().find(|p| p.frame_index >= frame_count) {
        return Err(Error::InvalidInput(format!(
            "pose for frame {} but the sequence has {frame_count} frames",
            bad.frame_index
        )));
    }
    Ok(())
}

/// A given initial band as a full-frame mask (`None` for the automatic band).
fn initial_band_pixels(
    init: &InitialBand,
    width: usize,
    height: usize,
) -> Result<Option<Vec<bool>>> {
    match init {
        InitialBand::Mask {
            width: mw,
            height: mh,
            data,
        } => {
            if (*mw, *mh) != (width, height) || data.len() != width * height {
                return Err(Error::InvalidInput(format!(
                    "initial band mask is {mw}x{mh} but the frames are {width}x{height}"
                )));
            }
            Ok(Some(data.clone()))
        }
        InitialBand::Polygon(vertices) => Ok(Some(rasterize_polygon(vertices, width, height)?)),
        InitialBand::Auto => Ok(None),
    }
}

#[cfg(test)]
mod tests;
