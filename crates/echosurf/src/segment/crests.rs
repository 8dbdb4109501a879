//! Echo crests in the frames themselves: where a wall's echo peaks across its line in the image.
//!
//! The fitted field flattens faint echoes (smoothing, sample thinning), so on walls that turn away from
//! the beam its ridges stop where the frames still show the echo (docs/decisions/0044). Here each frame,
//! lightly smoothed, is read across each ridge of its image (the direction of its most negative
//! curvature, on a copy smoothed a little more; only lines, not spots, and no steeper than
//! [`MAX_TILT_FROM_BEAM_DEG`]), every sample averaged over [`ALONG_MM`] along the line, for maxima that
//! stand out of their own neighbourhood: `min_prominence_grey` above the lowest grey within
//! [`PROMINENCE_REACH_MM`] on both sides, and `min_contrast_ratio` times the mean of the darker side
//! over [`DARK_SIDE_MM`]. Read down the columns instead, a steep wall's echo is too wide to fall by the
//! prominence within reach and too faint to rise out of single speckle pixels (docs/decisions/0046).
//! A wall echo has dark water, a shadow or a lumen on at least one side; speckle inside tissue has
//! tissue on both. No global grey level enters. Crests chain across neighbouring columns; chains
//! shorter than `min_chain_mm` (speckle grains) are dropped.

use glam::DMat4;
use rayon::prelude::*;

use super::crop::{effective_clip, load_grey_crop};
use super::filters::{gaussian_taps, smooth};
use crate::io::{ClipRect, FramePose, PoseResolution, TrackedSequence};
use crate::{Error, Result};

/// Which maxima across an echo line count as echo crests ([`echo_crests`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CrestOptions {
    /// Gaussian smoothing of the frame before the search (mm): takes the speckle off the echo's peak.
    pub smoothing_mm: f64,
    /// Least rise (grey) of the crest over the lowest grey within [`PROMINENCE_REACH_MM`] on each side.
    pub min_prominence_grey: f64,
    /// Least ratio of the crest's grey to the mean grey of its darker side.
    pub min_contrast_ratio: f64,
    /// Shortest chain of crests across columns kept (mm).
    pub min_chain_mm: f64,
    /// A crest is kept where its height over its darker side is at least this fraction of the highest
    /// crest of its chain within [`LOCAL_PEAK_REACH_MM`] along the chain: an echo ends where it has
    /// fallen to half its peak, not where the lateral blur of its end fades out (a wire's ribbon, a
    /// wall's rim). Along the chain, not across the beam, so a wall turned away from the beam is not
    /// cut where its echo fades with the angle. 0: off.
    pub min_local_peak_fraction: f64,
}

impl Default for CrestOptions {
    /// Measured on both generators and the real sweeps in docs/decisions/0044-image-crests.md.
    fn default() -> Self {
        CrestOptions {
            smoothing_mm: 0.2,
            min_prominence_grey: 12.0,
            min_contrast_ratio: 1.5,
            min_chain_mm: 1.0,
            min_local_peak_fraction: 0.5,
        }
    }
}

impl CrestOptions {
    /// Every field finite and within its range, or an error naming it.
    pub fn validate(&self) -> Result<()> {
        let check = |name: &str, value: f64, ok: bool| {
            if value.is_finite() && ok {
                Ok(())
            } else {
                Err(Error::InvalidInput(format!(
                    "crest option {name} must be a finite number in its range, got {value}"
                )))
            }
        };
        check("smoothing_mm", self.smoothing_mm, self.smoothing_mm >= 0.0)?;
        check(
            "min_prominence_grey",
            self.min_prominence_grey,
            self.min_prominence_grey >= 0.0,
        )?;
        check(
            "min_contrast_ratio",
            self.min_contrast_ratio,
            self.min_contrast_ratio >= 1.0,
        )?;
        check("min_chain_mm", self.min_chain_mm, self.min_chain_mm >= 0.0)?;
        check(
            "min_local_peak_fraction",
            self.min_local_peak_fraction,
            (0.0..=1.0).contains(&self.min_local_peak_fraction),
        )
    }
}

/// The prominence is measured within this distance (mm) of the crest, across its line.
pub const PROMINENCE_REACH_MM: f64 = 1.0;

/// The darker side's mean is taken over this range of distances (mm) from the crest across its line:
/// past the echo's own blur, within the wall's neighbourhood.
pub const DARK_SIDE_MM: [f64; 2] = [0.5, 1.5];

/// The strongest crest a crest is compared with lies within this distance (mm) along its chain.
pub const LOCAL_PEAK_REACH_MM: f64 = 1.0;

/// Crests of neighbouring columns chain when their rows are at most this many pixels apart.
const CHAIN_ROWS: i64 = 2;

/// A crest's chain direction is read over this distance (mm) across the beam on each side.
pub const TANGENT_REACH_MM: f64 = 0.5;

/// One crest in an image: its sub-pixel position and how its chain runs there.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImageCrest {
    pub column: f64,
    pub row: f64,
    /// The chain's rise in rows per column, over [`TANGENT_REACH_MM`] on each side.
    pub row_slope: f64,
}

/// One frame's crests, positions in the full frame.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameCrests {
    pub frame_index: usize,
    pub image_to_world: DMat4,
    pub crests: Vec<ImageCrest>,
}

/// The echo crests of every placed frame, inside `clip` (the whole frame without one) and, with
/// `detect_data_region`, the frames' data region ([`super::data_region`], as the segmentation takes
/// it), in the order of `poses`. Deterministic and independent of the thread count.
pub fn echo_crests(
    sequence: &TrackedSequence,
    poses: &PoseResolution,
    clip: Option<ClipRect>,
    detect_data_region: bool,
    options: &CrestOptions,
) -> Result<Vec<FrameCrests>> {
    echo_crests_reusing(
        sequence,
        poses,
        clip,
        detect_data_region,
        options,
        &mut CrestCache::default(),
    )
}

/// [`echo_crests`], taking the crests of frames already in `cache` from there and adding the others
/// to it: what [`echo_crests`] gives, when `cache` was only ever filled from this recording (frames
/// may have been added since, but a frame's pixels never change).
pub fn echo_crests_reusing(
    sequence: &TrackedSequence,
    poses: &PoseResolution,
    clip: Option<ClipRect>,
    detect_data_region: bool,
    options: &CrestOptions,
    cache: &mut CrestCache,
) -> Result<Vec<FrameCrests>> {
    options.validate()?;
    let Some(crop) = crest_crop(sequence, poses, clip, detect_data_region) else {
        return Ok(Vec::new());
    };
    cache.fill(sequence, &poses.poses, crop, options);
    Ok(poses
        .poses
        .iter()
        .map(|pose| cache.frames[&CrestCache::key(pose)].clone())
        .collect())
}

/// The part of the frames [`echo_crests`] reads: `clip` (the whole frame without one), narrowed to the
/// frames' data region with `detect_data_region`; `None` when nothing is left (every frame black).
pub fn crest_crop(
    sequence: &TrackedSequence,
    poses: &PoseResolution,
    clip: Option<ClipRect>,
    detect_data_region: bool,
) -> Option<ClipRect> {
    let clip = effective_clip(clip, sequence.width, sequence.height)?;
    if detect_data_region {
        super::data_region(sequence, poses, clip)
    } else {
        Some(clip)
    }
}

/// The crests of the frames of one recording found so far, so that a recording that grows (`live`)
/// reads each frame once. A frame's crests depend only on its pixels, its pose, the crop and the
/// options; the cache keeps the crop and options they were found with and starts afresh when either
/// changes, and holds each frame's crests under its pose (a frame placed anew is searched again).
#[derive(Debug, Clone, Default)]
pub struct CrestCache {
    crop: Option<ClipRect>,
    options: Option<CrestOptions>,
    frames: std::collections::BTreeMap<(usize, [u64; 16]), FrameCrests>,
}

impl CrestCache {
    /// Frame poses whose crests are held.
    pub fn frames(&self) -> usize {
        self.frames.len()
    }

    /// A frame under its pose: its index and the bits of its Image -> World matrix.
    fn key(pose: &FramePose) -> (usize, [u64; 16]) {
        (
            pose.frame_index,
            pose.image_to_world.to_cols_array().map(f64::to_bits),
        )
    }

    /// Finds the crests of the frames of `poses` not held yet (inside `crop`, which lies in the
    /// frames, with `options`, which are valid), in parallel.
    pub(crate) fn fill(
        &mut self,
        sequence: &TrackedSequence,
        poses: &[FramePose],
        crop: ClipRect,
        options: &CrestOptions,
    ) {
        if self.crop != Some(crop) || self.options.as_ref() != Some(options) {
            *self = CrestCache {
                crop: Some(crop),
                options: Some(options.clone()),
                frames: Default::default(),
            };
        }
        let missing: Vec<&FramePose> = poses
            .iter()
            .filter(|pose| !self.frames.contains_key(&Self::key(pose)))
            .collect();
        let found: Vec<((usize, [u64; 16]), FrameCrests)> = missing
            .par_iter()
            .map(|pose| (Self::key(pose), frame_crests(sequence, pose, crop, options)))
            .collect();
        self.frames.extend(found);
    }
}

/// One frame's crests inside `crop`.
fn frame_crests(
    sequence: &TrackedSequence,
    pose: &FramePose,
    crop: ClipRect,
    options: &CrestOptions,
) -> FrameCrests {
    let m = pose.image_to_world;
    let pixel_mm = [m.x_axis.truncate().length(), m.y_axis.truncate().length()];
    let (mut grey, mut tmp, mut smoothed) = (Vec::new(), Vec::new(), Vec::new());
    load_grey_crop(sequence, pose.frame_index, crop, &mut grey);
    let [w, h] = crop.size_px;
    smooth(
        &grey,
        w,
        h,
        &gaussian_taps(options.smoothing_mm / pixel_mm[1]),
        &mut tmp,
        &mut smoothed,
    );
    let [u0, v0] = crop.origin_px.map(|x| x as f64);
    FrameCrests {
        frame_index: pose.frame_index,
        image_to_world: m,
        crests: crests_in_image(&smoothed, w, h, pixel_mm, options)
            .into_iter()
            .map(|c| ImageCrest {
                column: c.column + u0,
                row: c.row + v0,
                ..c
            })
            .collect(),
    }
}

/// The crests of one smoothed image (`w` x `h`, pixels `pixel_mm` wide and high), row-major order.
pub fn crests_in_image(
    image: &[f32],
    w: usize,
    h: usize,
    pixel_mm: [f64; 2],
    options: &CrestOptions,
) -> Vec<ImageCrest> {
    if image.len() != w * h || w < 5 || h < 5 {
        return Vec::new();
    }
    // One profile step per pixel, but never more than MAX_PROFILE_STEPS over the dark side.
    let step_mm = pixel_mm[0]
        .min(pixel_mm[1])
        .max(DARK_SIDE_MM[1] / MAX_PROFILE_STEPS as f64);
    let steps = |mm: f64| (mm / step_mm).round().max(1.0) as usize;
    let test = CrestTest {
        prominence: options.min_prominence_grey as f32,
        ratio: options.min_contrast_ratio as f32,
        reach: steps(PROMINENCE_REACH_MM),
        dark_from: steps(DARK_SIDE_MM[0]),
        dark_to: steps(DARK_SIDE_MM[1]),
        along: ALONG_OFFSETS.map(|a| a * ALONG_MM / step_mm),
    };
    let oriented = orientation_image(image, w, h, pixel_mm);
    let pixel_steps = |n: [f64; 2]| [n[0] * step_mm / pixel_mm[0], n[1] * step_mm / pixel_mm[1]];
    let crest: Vec<Option<Crest>> = (0..w * h)
        .map(|i| {
            let n = ridge_normal(&oriented, w, h, pixel_mm, [i % w, i / w])?;
            test.at(image, w, h, [i % w, i / w], pixel_steps(n))
        })
        .collect();
    let (span, label) = chain_spans(&crest, w, h);
    // A chain's ends are spread by the averaging along it: a spot shorter than the shortest chain
    // must not pass for one.
    let min_span = (options.min_chain_mm + 2.0 * ALONG_MM) / pixel_mm[0];
    // Per chain and column, the highest crest (height, row): each crest is compared with its chain's
    // nearby peak, and its chain's direction is read from them.
    let fraction = options.min_local_peak_fraction as f32;
    let reach_cols = (LOCAL_PEAK_REACH_MM / pixel_mm[0]).round() as usize;
    let tangent_cols = (TANGENT_REACH_MM / pixel_mm[0]).round().max(1.0) as usize;
    let mut column_peak: std::collections::HashMap<(usize, usize), (f32, f64)> = Default::default();
    for (i, c) in crest.iter().enumerate() {
        if let Some(c) = c {
            let peak = column_peak
                .entry((label[i], i % w))
                .or_insert((c.height, c.row));
            if c.height > peak.0 {
                *peak = (c.height, c.row);
            }
        }
    }
    crest
        .iter()
        .zip(&span)
        .enumerate()
        .filter_map(|(i, (c, &s))| {
            let c = (*c)?;
            if (s as f64) < min_span {
                return None;
            }
            let u = i % w;
            // The farthest columns of the chain within reach on each side (this crest where none).
            let row_at = |col: usize| column_peak.get(&(label[i], col)).map(|&(_, r)| r);
            let left = (u.saturating_sub(tangent_cols)..u)
                .find_map(|col| Some((col, row_at(col)?)))
                .unwrap_or((u, c.row));
            let right = (u + 1..=u + tangent_cols)
                .rev()
                .find_map(|col| Some((col, row_at(col)?)))
                .unwrap_or((u, c.row));
            let row_slope = if right.0 > left.0 {
                (right.1 - left.1) / (right.0 - left.0) as f64
            } else {
                0.0
            };
            if fraction > 0.0 {
                // LOCAL_PEAK_REACH_MM along the chain: fewer columns where it runs steeply.
                let slope_mm = row_slope * pixel_mm[1] / pixel_mm[0];
                let reach = (reach_cols as f64 / slope_mm.hypot(1.0)).round() as usize;
                let peak = (u.saturating_sub(reach)..=u + reach)
                    .filter_map(|c| column_peak.get(&(label[i], c)))
                    .fold(0.0f32, |a, &(b, _)| a.max(b));
                if c.height < fraction * peak {
                    return None;
                }
            }
            Some(ImageCrest {
                column: c.column,
                row: c.row,
                row_slope,
            })
        })
        .collect()
}

/// The image is smoothed by this much more (mm) before its curvature is read for the direction
/// across each ridge: the crest test's own smoothing keeps the peak sharp, the direction needs less
/// speckle.
pub const ORIENTATION_SMOOTHING_MM: f64 = 0.35;

/// Every profile sample is the mean of the image at these offsets along the ridge, in units of
/// [`ALONG_MM`]: a faint echo adds up along its line, speckle does not.
const ALONG_OFFSETS: [f64; 5] = [-1.0, -0.5, 0.0, 0.5, 1.0];

/// Half the length (mm) along the ridge over which each profile sample is averaged.
pub const ALONG_MM: f64 = 0.4;

/// The most profile steps on each side of a crest (the dark side's far end).
const MAX_PROFILE_STEPS: usize = 16;

/// The steepest echo line searched for: its normal at most this far (degrees) from the beam (the
/// image's columns).
pub const MAX_TILT_FROM_BEAM_DEG: f64 = 65.0;

/// The most a ridge may curve down along itself, as a share of how much it curves down across.
const MAX_CURVATURE_ALONG: f64 = 0.3;

/// A pixel is tested for a crest only where the smoothed ridge's top lies within this many pixels
/// of it across the ridge: the full test is costly and cannot pass farther away.
const CREST_NEAR_PX: f64 = 1.0;

/// The image smoothed by [`ORIENTATION_SMOOTHING_MM`] more, for [`ridge_normal`].
fn orientation_image(image: &[f32], w: usize, h: usize, pixel_mm: [f64; 2]) -> Vec<f32> {
    let (mut tmp, mut smoothed) = (Vec::new(), Vec::new());
    let sigma_px = ORIENTATION_SMOOTHING_MM / pixel_mm[0].min(pixel_mm[1]);
    smooth(
        image,
        w,
        h,
        &gaussian_taps(sigma_px),
        &mut tmp,
        &mut smoothed,
    );
    smoothed
}

/// The unit direction (mm, x along the rows, y down the columns) across the ridge through pixel
/// `[u, v]` of `smoothed` ([`orientation_image`]): the eigenvector of its most negative curvature.
/// `None` where it is no ridge (it curves up in every direction, or down along itself by more than
/// [`MAX_CURVATURE_ALONG`] of across) or where the ridge's top
/// lies farther than [`CREST_NEAR_PX`] away across it.
fn ridge_normal(
    smoothed: &[f32],
    w: usize,
    h: usize,
    pixel_mm: [f64; 2],
    [u, v]: [usize; 2],
) -> Option<[f64; 2]> {
    // The border replicated, as the smoothing does.
    let interior = u >= 2 && v >= 2 && u + 2 < w && v + 2 < h;
    let at = |du: isize, dv: isize| {
        let (x, y) = (u as isize + du, v as isize + dv);
        let (x, y) = if interior {
            (x as usize, y as usize)
        } else {
            (
                x.clamp(0, w as isize - 1) as usize,
                y.clamp(0, h as isize - 1) as usize,
            )
        };
        smoothed[y * w + x] as f64
    };
    let (dx, dy) = (2.0 * pixel_mm[0], 2.0 * pixel_mm[1]);
    let centre = at(0, 0);
    // Second differences two pixels wide: the curvature of the ridge, not of its speckle.
    let xx = (at(2, 0) - 2.0 * centre + at(-2, 0)) / (dx * dx);
    let yy = (at(0, 2) - 2.0 * centre + at(0, -2)) / (dy * dy);
    let xy = (at(1, 1) - at(1, -1) - at(-1, 1) + at(-1, -1)) / (dx * dy);
    let half_trace = 0.5 * (xx + yy);
    let root = (half_trace * half_trace - (xx * yy - xy * xy))
        .max(0.0)
        .sqrt();
    let (lowest, along) = (half_trace - root, half_trace + root);
    // A ridge curves down across itself far more than along: a spot, a grain of speckle or the
    // rounded end of an echo curves down alike every way, and has no direction to read across.
    if lowest >= 0.0 || along < MAX_CURVATURE_ALONG * lowest {
        return None;
    }
    // (xy, lowest - xx) and (lowest - yy, xy) both lie across the ridge; take the longer.
    let square = |x: [f64; 2]| x[0] * x[0] + x[1] * x[1];
    let (a, b) = ([xy, lowest - xx], [lowest - yy, xy]);
    let pick = if square(a) >= square(b) { a } else { b };
    let length = square(pick).sqrt();
    let n = if length > 0.0 && length.is_finite() {
        [pick[0] / length, pick[1] / length]
    } else {
        [0.0, 1.0]
    };
    // A line this steep in the frame is a wall almost along the beam: it sends no echo back, and
    // what looks like one is the lateral blur of an echo's end.
    if n[1].abs() < MAX_TILT_FROM_BEAM_DEG.to_radians().cos() {
        return None;
    }
    // The ridge's top lies where the slope over the curvature puts it (a parabola's vertex).
    let slope = (at(1, 0) - at(-1, 0)) / dx * n[0] + (at(0, 1) - at(0, -1)) / dy * n[1];
    let px = square([n[0] * pixel_mm[0], n[1] * pixel_mm[1]]).sqrt();
    if slope.abs() > CREST_NEAR_PX * px * -lowest {
        return None;
    }
    Some(n)
}

/// A crest found at one pixel: its sub-pixel position and its height over its darker side.
#[derive(Debug, Clone, Copy)]
struct Crest {
    column: f64,
    row: f64,
    height: f32,
}

/// [`CrestOptions`] in profile steps (the smaller pixel side).
struct CrestTest {
    prominence: f32,
    ratio: f32,
    reach: usize,
    dark_from: usize,
    dark_to: usize,
    /// Offsets along the ridge (steps) averaged into every profile sample.
    along: [f64; 5],
}

impl CrestTest {
    /// The mean of `read` at the offsets [`CrestTest::along`] from `centre` in direction `along_line`.
    fn mean_along(
        &self,
        centre: [f64; 2],
        along_line: [f64; 2],
        read: impl Fn(f64, f64) -> f32,
    ) -> f32 {
        let sum: f32 = self
            .along
            .iter()
            .map(|&a| read(centre[0] + a * along_line[0], centre[1] + a * along_line[1]))
            .sum();
        sum / self.along.len() as f32
    }

    /// The crest at pixel `[u, v]` if the image, read across its ridge (`step`: one profile step in
    /// pixels, across the ridge), peaks there and stands out of its neighbourhood: its position refined
    /// by the parabola through the three samples around the maximum, and its height over the darker
    /// side.
    fn at(
        &self,
        image: &[f32],
        w: usize,
        h: usize,
        pixel: [usize; 2],
        step: [f64; 2],
    ) -> Option<Crest> {
        let (u, v) = (pixel[0] as f64, pixel[1] as f64);
        let across = [-step[1], step[0]];
        // The frame's border is replicated, as the smoothing does.
        let (last_x, last_y) = ((w - 1) as f64, (h - 1) as f64);
        let spread = self.along[self.along.len() - 1];
        let extent = |k: usize| self.dark_to as f64 * step[k].abs() + spread * across[k].abs();
        let interior =
            u >= extent(0) && v >= extent(1) && u + extent(0) <= last_x && v + extent(1) <= last_y;
        let clamp = |x: f64, y: f64| {
            if interior {
                (x, y)
            } else {
                (x.clamp(0.0, last_x), y.clamp(0.0, last_y))
            }
        };
        let bilinear = |x: f64, y: f64| -> f32 {
            let (x, y) = clamp(x, y);
            let (i, j) = (x as usize, y as usize);
            let (fx, fy) = ((x - i as f64) as f32, (y - j as f64) as f32);
            let (i1, j1) = ((i + 1).min(w - 1), (j + 1).min(h - 1));
            let g = |a: usize, b: usize| image[b * w + a];
            (g(i, j) * (1.0 - fx) + g(i1, j) * fx) * (1.0 - fy)
                + (g(i, j1) * (1.0 - fx) + g(i1, j1) * fx) * fy
        };
        let nearest = |x: f64, y: f64| {
            let (x, y) = clamp(x, y);
            image[(y + 0.5) as usize * w + (x + 0.5) as usize]
        };
        let at = |t: i64| [u + t as f64 * step[0], v + t as f64 * step[1]];
        // The peak and its neighbours interpolated (they place the crest), the sides to the nearest
        // pixel (they only weigh it).
        let peak = |t: i64| self.mean_along(at(t), across, bilinear);
        let side = |t: i64| self.mean_along(at(t), across, nearest);
        let (before, s, after) = (peak(-1), peak(0), peak(1));
        if s <= before || s < after {
            return None;
        }
        // Both sides fall by the prominence within reach.
        let reach = self.reach as i64;
        let falls = |sign: i64, first: f32| {
            first <= s - self.prominence
                || (2..=reach).any(|t| side(sign * t) <= s - self.prominence)
        };
        if !falls(-1, before) || !falls(1, after) {
            return None;
        }
        let (from, to) = (self.dark_from as i64, self.dark_to as i64);
        let n = (to - from + 1) as f32;
        let mean = |sign: i64| (from..=to).map(|t| side(sign * t)).sum::<f32>() / n;
        let dark = mean(-1).min(mean(1));
        if s < self.ratio * dark {
            return None;
        }
        let (a, b, c) = (before as f64, s as f64, after as f64);
        let curvature = a - 2.0 * b + c;
        let offset = if curvature < 0.0 {
            (0.5 * (a - c) / curvature).clamp(-0.5, 0.5)
        } else {
            0.0
        };
        Some(Crest {
            column: u + offset * step[0],
            row: v + offset * step[1],
            height: s - dark,
        })
    }
}

/// Per crest pixel, the number of columns its chain spans minus one, and the chain's label (its first
/// pixel): crests of neighbouring columns whose rows are at most [`CHAIN_ROWS`] apart are one chain.
fn chain_spans<T>(crest: &[Option<T>], w: usize, h: usize) -> (Vec<usize>, Vec<usize>) {
    let mut span = vec![0; w * h];
    let mut label = vec![0; w * h];
    let mut seen = vec![false; w * h];
    let (mut stack, mut members) = (Vec::new(), Vec::new());
    for start in 0..w * h {
        if crest[start].is_none() || seen[start] {
            continue;
        }
        seen[start] = true;
        stack.push(start);
        members.clear();
        let (mut lo, mut hi) = (start % w, start % w);
        while let Some(i) = stack.pop() {
            members.push(i);
            let (u, v) = ((i % w) as i64, (i / w) as i64);
            lo = lo.min(u as usize);
            hi = hi.max(u as usize);
            for du in -1..=1 {
                for dv in -CHAIN_ROWS..=CHAIN_ROWS {
                    let (nu, nv) = (u + du, v + dv);
                    if nu < 0 || nv < 0 || nu >= w as i64 || nv >= h as i64 {
                        continue;
                    }
                    let j = nv as usize * w + nu as usize;
                    if crest[j].is_some() && !seen[j] {
                        seen[j] = true;
                        stack.push(j);
                    }
                }
            }
        }
        for &i in &members {
            span[i] = hi - lo;
            label[i] = start;
        }
    }
    (span, label)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    const PIXEL_MM: [f64; 2] = [0.2, 0.2];

    /// A 120 x 100 image: background 15; a horizontal Gaussian echo (sigma 0.3 mm, peak 70 over the
    /// background) centred on row `echo_row` from column 10 to 109; below row 60 "tissue": speckle
    /// grains of 3 x 2 px, each of a random grey in 30-110. Smoothed as the crest search smooths.
    fn frame(echo_row: f64) -> Vec<f32> {
        let (w, h) = (120, 100);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let mut image = vec![15.0f32; w * h];
        let grains: Vec<f32> = (0..w * h).map(|_| rng.random_range(30.0..110.0)).collect();
        for v in 0..h {
            for u in 0..w {
                let d_mm = (v as f64 - echo_row) * PIXEL_MM[1];
                if (10..110).contains(&u) {
                    image[v * w + u] += (70.0 * (-d_mm * d_mm / (2.0 * 0.09)).exp()) as f32;
                }
                if v >= 60 {
                    image[v * w + u] = grains[(v / 2) * w + u / 3];
                }
            }
        }
        let (mut tmp, mut out) = (Vec::new(), Vec::new());
        smooth(&image, w, h, &gaussian_taps(1.0), &mut tmp, &mut out);
        out
    }

    #[test]
    fn a_wall_echo_gives_one_crest_per_column_on_its_peak_and_tissue_speckle_none() {
        let echo_row = 30.3;
        let crests = crests_in_image(
            &frame(echo_row),
            120,
            100,
            PIXEL_MM,
            &CrestOptions::default(),
        );
        let on_echo: Vec<_> = crests.iter().filter(|c| c.row < 50.0).collect();
        // One crest per column of the echo's 100, give or take its abrupt ends: there the smoothing
        // and the averaging along the echo (ALONG_MM) spread it, and its curvature turns along it
        // (MAX_CURVATURE_ALONG), by up to four columns.
        assert!(
            on_echo.len() >= 92 && on_echo.len() <= 106,
            "{}",
            on_echo.len()
        );
        // On its peak; within the averaging's reach of the abrupt ends the direction across the
        // echo turns, and the crest may sit up to a pixel and a half off.
        for c in &on_echo {
            let off = (c.row - echo_row).abs();
            let inside = (12.0..=107.0).contains(&c.column);
            assert!(
                off < if inside { 0.1 } else { 1.5 },
                "crest at row {} column {} for {echo_row}",
                c.row,
                c.column
            );
        }
        // Tissue on both sides: few of its maxima stand out of it by the contrast ratio (those left
        // are for the link to the fitted sheet to reject, `surface::crest`).
        let in_tissue = crests.iter().filter(|c| c.row > 62.0).count();
        let no_ratio = CrestOptions {
            min_contrast_ratio: 1.0,
            ..CrestOptions::default()
        };
        let loose = crests_in_image(&frame(echo_row), 120, 100, PIXEL_MM, &no_ratio);
        let loose_in_tissue = loose.iter().filter(|c| c.row > 62.0).count();
        eprintln!("tissue crests: {in_tissue} with the ratio test, {loose_in_tissue} without");
        // Most of the tissue's ridges fail the ratio test, and those left are under 2 % of its
        // 37 x 120 pixels.
        assert!(
            2 * in_tissue < loose_in_tissue && in_tissue * 50 < 37 * 120,
            "{in_tissue} of {loose_in_tissue}"
        );
        // The echo's crests do not depend on the ratio test: water lies above it.
        assert_eq!(loose.iter().filter(|c| c.row < 50.0).count(), on_echo.len());
    }

    #[test]
    fn a_crest_knows_which_way_its_chain_runs() {
        // An echo rising 0.4 rows per column (22 degrees from the image's rows): slope 0.4 at every
        // crest away from the chain's ends; a horizontal echo: 0.
        let (w, h) = (100, 80);
        for rise in [0.0, 0.4] {
            let mut image = vec![15.0f32; w * h];
            for u in 10..90 {
                let centre = 20.0 + rise * u as f64;
                for v in 0..h {
                    let d = v as f64 - centre;
                    image[v * w + u] += (70.0 * (-d * d / 2.0).exp()) as f32;
                }
            }
            let crests = crests_in_image(&image, w, h, PIXEL_MM, &CrestOptions::default());
            let inner: Vec<_> = crests
                .iter()
                .filter(|c| (20.0..80.0).contains(&c.column))
                .collect();
            assert!(inner.len() >= 55, "{}", inner.len());
            for c in inner {
                assert!(
                    (c.row_slope - rise).abs() < 0.05,
                    "{} for {rise}",
                    c.row_slope
                );
            }
        }
    }

    #[test]
    fn short_chains_are_dropped_and_a_dark_frame_has_no_crests() {
        // A bright spot 3 px wide: 0.6 mm, under the 1 mm of the default.
        let (w, h) = (60, 60);
        let mut image = vec![15.0f32; w * h];
        for u in 30..33 {
            image[30 * w + u] = 90.0;
            image[29 * w + u] = 50.0;
            image[31 * w + u] = 50.0;
        }
        let options = CrestOptions::default();
        assert!(crests_in_image(&image, w, h, PIXEL_MM, &options).is_empty());
        let short = CrestOptions {
            min_chain_mm: 0.3,
            ..options.clone()
        };
        // Nor is it found once short chains are allowed: a spot curves down alike every way, it is
        // no ridge (MAX_CURVATURE_ALONG). A dash 4 mm long is.
        assert!(crests_in_image(&image, w, h, PIXEL_MM, &short).is_empty());
        let mut dash = vec![15.0f32; w * h];
        for u in 20..40 {
            dash[30 * w + u] = 90.0;
            dash[29 * w + u] = 50.0;
            dash[31 * w + u] = 50.0;
        }
        let found = crests_in_image(&dash, w, h, PIXEL_MM, &short);
        assert!(found.len() >= 8, "{found:?}");
        assert!(
            found.iter().all(|c| (c.row - 30.0).abs() < 0.2),
            "{found:?}"
        );
        assert!(crests_in_image(&vec![15.0; w * h], w, h, PIXEL_MM, &options).is_empty());
        // Wrong sizes give nothing rather than a panic.
        assert!(crests_in_image(&image, w, h + 1, PIXEL_MM, &options).is_empty());
    }

    #[test]
    fn an_echo_ends_where_it_falls_to_half_its_peak_across_the_beam() {
        // A horizontal echo at row 30, full strength (70 over the background) over columns 0-59, then
        // fading linearly to nothing over columns 60-69 (2 mm, a lateral blur).
        let (w, h) = (100, 60);
        let mut image = vec![15.0f32; w * h];
        for u in 0..70 {
            let strength = if u < 60 {
                70.0
            } else {
                70.0 * (70 - u) as f32 / 10.0
            };
            image[30 * w + u] += strength;
            image[29 * w + u] += 0.5 * strength;
            image[31 * w + u] += 0.5 * strength;
        }
        let columns = |fraction: f64| -> Vec<usize> {
            let options = CrestOptions {
                min_local_peak_fraction: fraction,
                ..CrestOptions::default()
            };
            crests_in_image(&image, w, h, PIXEL_MM, &options)
                .iter()
                .map(|c| c.column as usize)
                .collect()
        };
        let (all, halved) = (columns(0.0), columns(0.5));
        // Every full-strength column keeps its crest; the fading end loses the weakest crests.
        assert!((0..60).all(|u| halved.contains(&u)));
        assert!(
            halved.len() < all.len(),
            "{} of {}",
            halved.len(),
            all.len()
        );
        let last = |c: &[usize]| c.iter().copied().max().unwrap_or(0);
        // Column 65 is where the echo has fallen to half its height; without the rule it runs on to
        // where the prominence test stops it.
        assert!((64..=65).contains(&last(&halved)), "{}", last(&halved));
        assert!(
            last(&halved) + 2 < last(&all),
            "{} {}",
            last(&halved),
            last(&all)
        );
    }

    /// Crests of an echo line tilted `tilt_deg` from the image's rows, starting at pixel (20, 20) and
    /// falling by 0.6 per mm along the line from 250 grey over a background of 15: the distances
    /// (mm) along the line of the crests found on it.
    fn crests_along_a_fading_line(tilt_deg: f64) -> Vec<f64> {
        let (w, h) = (120, 120);
        let start = [20.0, 20.0];
        let t = [tilt_deg.to_radians().cos(), tilt_deg.to_radians().sin()];
        let normal = [-t[1], t[0]];
        let line = |u: f64, v: f64| {
            let d = [u - start[0], v - start[1]];
            let along_mm = (d[0] * t[0] + d[1] * t[1]) * PIXEL_MM[0];
            let across_mm = (d[0] * normal[0] + d[1] * normal[1]) * PIXEL_MM[0];
            (along_mm, across_mm)
        };
        let mut image = vec![15.0f32; w * h];
        for v in 0..h {
            for u in 0..w {
                let (along_mm, across_mm) = line(u as f64, v as f64);
                if (0.0..=6.0).contains(&along_mm) {
                    let height = 250.0 * 0.6f64.powf(along_mm);
                    image[v * w + u] +=
                        (height * (-across_mm * across_mm / (2.0 * 0.09)).exp()) as f32;
                }
            }
        }
        crests_in_image(&image, w, h, PIXEL_MM, &CrestOptions::default())
            .iter()
            .map(|c| line(c.column, c.row))
            .filter(|(_, across_mm)| across_mm.abs() < 0.2)
            .map(|(along_mm, _)| along_mm)
            .collect()
    }

    #[test]
    fn a_steep_echo_is_compared_with_its_peak_along_its_line_not_across_the_beam() {
        // Falling by 0.6 per mm, the echo never drops to half of what it was 1 mm back along its line.
        // At 55 degrees, 1 mm across the beam is 1.74 mm along the line (0.6^1.74 = 0.41): compared
        // across the beam, every crest past 1.4 mm from the line's start would be dropped.
        let within = |found: &[f64], lo: f64, hi: f64| {
            found.iter().filter(|&&s| (lo..=hi).contains(&s)).count()
        };
        let level = crests_along_a_fading_line(0.0);
        let steep = crests_along_a_fading_line(55.0);
        // 2-4.5 mm along the line: 12 columns of the level line, 7 of the steep one.
        assert!(within(&level, 2.0, 4.5) >= 10, "{level:?}");
        assert!(within(&steep, 2.0, 4.5) >= 6, "{steep:?}");
    }

    #[test]
    fn a_faint_steep_echo_is_found_across_its_line_not_down_the_column() {
        // An echo line 55 degrees from the image's rows (a wall turned away from the beam), 16 grey
        // over a water background of 15 with speckle of +-8 grey, profile sigma 0.3 mm across the line.
        // Down a column its profile is 1.7 times as wide, and falls by less than the prominence within
        // PROMINENCE_REACH_MM; across the line it is found on almost every row.
        let (w, h) = (120, 120);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let angle = 55f64.to_radians();
        let normal = [-angle.sin(), angle.cos()];
        let mut image = vec![0.0f32; w * h];
        for v in 0..h {
            for u in 0..w {
                let across_mm =
                    ((u as f64 - 60.0) * normal[0] + (v as f64 - 60.0) * normal[1]) * PIXEL_MM[0];
                let echo = 16.0 * (-across_mm * across_mm / (2.0 * 0.09)).exp();
                image[v * w + u] = (15.0 + echo + rng.random_range(-8.0..8.0)) as f32;
            }
        }
        let (mut tmp, mut smoothed) = (Vec::new(), Vec::new());
        smooth(&image, w, h, &gaussian_taps(1.0), &mut tmp, &mut smoothed);
        let options = CrestOptions {
            min_prominence_grey: 8.0,
            ..CrestOptions::default()
        };
        let crests = crests_in_image(&smoothed, w, h, PIXEL_MM, &options);
        let on_line = |c: &&ImageCrest| {
            ((c.column - 60.0) * normal[0] + (c.row - 60.0) * normal[1]).abs() < 1.0
        };
        let found = crests.iter().filter(on_line).count();
        let rows: std::collections::BTreeSet<i64> = crests
            .iter()
            .filter(on_line)
            .map(|c| c.row.round() as i64)
            .collect();
        // The line crosses rows 10-109 inside the image (away from the border).
        assert!(
            rows.len() >= 80,
            "{} rows of 100, {found} crests",
            rows.len()
        );
        // Speckle gives few crests off the line.
        let off_line = crests.len() - found;
        assert!(
            off_line * 5 < found,
            "{off_line} off the line, {found} on it"
        );
        // The column search this replaced: the same image and options, profiles read down the
        // columns without the averaging along the line.
        let column_test = CrestTest {
            prominence: 8.0,
            ratio: options.min_contrast_ratio as f32,
            reach: 5,
            dark_from: 3,
            dark_to: 8,
            along: [0.0; 5],
        };
        let down_columns = (0..w * h)
            .filter_map(|i| column_test.at(&smoothed, w, h, [i % w, i / w], [0.0, 1.0]))
            .filter(|c| ((c.column - 60.0) * normal[0] + (c.row - 60.0) * normal[1]).abs() < 1.0)
            .count();
        assert!(
            2 * down_columns < found,
            "{down_columns} down the columns, {found} across"
        );
    }

    #[test]
    fn options_out_of_range_are_refused_by_name() {
        let bad = CrestOptions {
            min_contrast_ratio: 0.5,
            ..CrestOptions::default()
        };
        let message = bad.validate().unwrap_err().to_string();
        assert!(message.contains("min_contrast_ratio"), "{message}");
        let nan = CrestOptions {
            smoothing_mm: f64::NAN,
            ..CrestOptions::default()
        };
        assert!(nan.validate().is_err());
        assert!(CrestOptions::default().validate().is_ok());
    }

    /// The cache gives what searching each frame on its own gives: filled over a growing recording,
    /// after a pose changed (that frame is searched again), for a frame listed twice under two poses,
    /// and after the crop changed (all are searched again).
    #[test]
    fn crests_from_the_cache_are_those_of_each_frame_searched_alone() {
        let sweep = crate::segment::synthetic::synthetic_sweep(90, 70, 12, 0.2, 0.4, 5);
        let (sequence, poses) = (&sweep.sequence, &sweep.poses);
        let options = CrestOptions::default();
        let alone = |poses: &PoseResolution, clip: Option<ClipRect>| -> Vec<FrameCrests> {
            let crop = crest_crop(sequence, poses, clip, false).unwrap();
            poses
                .poses
                .iter()
                .map(|p| frame_crests(sequence, p, crop, &options))
                .collect()
        };
        let fresh = alone(poses, None);
        assert!(
            fresh.iter().all(|f| !f.crests.is_empty()),
            "an echo in every frame"
        );
        assert_eq!(
            echo_crests(sequence, poses, None, false, &options).unwrap(),
            fresh
        );
        let mut cache = CrestCache::default();
        let first_half = PoseResolution {
            poses: poses.poses[..6].to_vec(),
            ..poses.clone()
        };
        let half = echo_crests_reusing(sequence, &first_half, None, false, &options, &mut cache);
        assert_eq!(half.unwrap()[..], fresh[..6]);
        assert_eq!(cache.frames(), 6);
        let all = echo_crests_reusing(sequence, poses, None, false, &options, &mut cache).unwrap();
        assert_eq!(all, fresh);
        assert_eq!(cache.frames(), 12);

        // Frame 3 moved, and frame 5 listed once more under a moved pose.
        let mut moved = poses.clone();
        let scale = DMat4::from_scale(glam::DVec3::splat(1.5));
        moved.poses[3].image_to_world *= scale;
        let mut again = moved.poses[5];
        again.image_to_world *= scale;
        moved.poses.push(again);
        let refound =
            echo_crests_reusing(sequence, &moved, None, false, &options, &mut cache).unwrap();
        assert_eq!(refound, alone(&moved, None));
        assert_ne!(refound[3], fresh[3]);
        assert_eq!(refound[5], fresh[5]);
        assert_ne!(refound[12], fresh[5]);

        // A narrower crop: every frame is searched again inside it.
        let crop = ClipRect {
            origin_px: [10, 5],
            size_px: [60, 60],
        };
        let cropped =
            echo_crests_reusing(sequence, poses, Some(crop), false, &options, &mut cache).unwrap();
        assert_eq!(cropped, alone(poses, Some(crop)));
        assert_ne!(cropped, fresh);
    }
}
