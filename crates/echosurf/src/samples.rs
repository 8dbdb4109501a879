//! Samples: kept pixels mapped to 3D points with their intensity, and their thinning.
//!
//! Every pixel the band segmentation kept becomes one sample: its world position (mm, pixel (u, v) is the
//! Image-frame point (u, v, 0)) and its grey level as read. The paper then thins them by random deletion
//! (~10k points keep large features, ~100k keep detail).

use glam::DVec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::io::{PointCloud, PoseResolution, TrackedSequence};
use crate::segment::BandMasks;

/// Points with intensities, in frame order then row-major pixel order.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SampleSet {
    /// World positions, mm.
    pub positions: Vec<DVec3>,
    /// Grey levels as read (channels averaged).
    pub intensities: Vec<f32>,
    /// Sequence frame index each sample came from.
    pub frame_of_sample: Vec<u32>,
}

impl SampleSet {
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// The samples at `indices`, in that order.
    pub fn select(&self, indices: &[usize]) -> SampleSet {
        SampleSet {
            positions: indices.iter().map(|&i| self.positions[i]).collect(),
            intensities: indices.iter().map(|&i| self.intensities[i]).collect(),
            frame_of_sample: indices.iter().map(|&i| self.frame_of_sample[i]).collect(),
        }
    }

    /// The samples as a point cloud with a float `intensity` property (for `write_point_cloud`).
    pub fn to_point_cloud(&self) -> PointCloud {
        PointCloud {
            positions: self.positions.clone(),
            scalars: vec![("intensity".into(), self.intensities.clone())],
        }
    }
}

/// The placed frames that have a mask, once each, in frame order; `None` when the masks do not fit the
/// sequence or it has no images.
fn frames_in_order<'a>(
    sequence: &TrackedSequence,
    poses: &'a PoseResolution,
    masks: &BandMasks,
) -> Option<Vec<&'a crate::io::FramePose>> {
    if (masks.width, masks.height) != (sequence.width, sequence.height)
        || sequence.is_tracking_only()
    {
        return None;
    }
    let mut ordered: Vec<_> = poses
        .poses
        .iter()
        .filter(|p| p.frame_index < masks.masks.len() && p.frame_index < sequence.frames.len())
        .collect();
    ordered.sort_by_key(|p| p.frame_index);
    ordered.dedup_by_key(|p| p.frame_index);
    Some(ordered)
}

/// Every kept pixel of every frame with a pose, mapped to the world. Frames without a pose contribute
/// nothing (their masks are empty anyway); masks that do not match the sequence size are skipped.
pub fn collect_samples(
    sequence: &TrackedSequence,
    poses: &PoseResolution,
    masks: &BandMasks,
) -> SampleSet {
    let (w, h) = (sequence.width, sequence.height);
    let mut set = SampleSet::default();
    let Some(ordered) = frames_in_order(sequence, poses, masks) else {
        return set;
    };
    let total: usize = ordered
        .iter()
        .map(|p| {
            masks.masks[p.frame_index]
                .iter()
                .filter(|&&m| m != 0)
                .count()
        })
        .sum();
    set.positions.reserve_exact(total);
    set.intensities.reserve_exact(total);
    set.frame_of_sample.reserve_exact(total);
    for pose in ordered {
        let f = pose.frame_index;
        let mask = &masks.masks[f];
        let m = pose.image_to_world;
        for v in 0..h {
            let row = &mask[v * w..(v + 1) * w];
            for (u, _) in row.iter().enumerate().filter(|(_, k)| **k != 0) {
                set.positions
                    .push(m.transform_point3(DVec3::new(u as f64, v as f64, 0.0)));
                set.intensities.push(sequence.pixel_f32(f, u, v));
                set.frame_of_sample.push(f as u32);
            }
        }
    }
    set
}

/// Kept pixels averaged over `bin_px = [columns, rows]` blocks of each frame: one sample per block with
/// at least one kept pixel, at the mean position of its kept pixels, with their mean grey level.
/// Averaging a few pixels (about one speckle cell) removes most of the speckle variance before the fit
/// and lets a fixed sample budget cover much more of the band than single pixels would. `[1, 1]` is
/// [`collect_samples`].
pub fn collect_samples_binned(
    sequence: &TrackedSequence,
    poses: &PoseResolution,
    masks: &BandMasks,
    bin_px: [usize; 2],
) -> SampleSet {
    collect_samples_binned_with_cells(sequence, poses, masks, bin_px).0
}

/// [`collect_samples_binned`], and for every sample its block: `[column, row]` of the block grid of its
/// frame (block `[i, j]` covers pixels `u in i * bin_px[0]..`, `v in j * bin_px[1]..`).
pub fn collect_samples_binned_with_cells(
    sequence: &TrackedSequence,
    poses: &PoseResolution,
    masks: &BandMasks,
    bin_px: [usize; 2],
) -> (SampleSet, Vec<[u32; 2]>) {
    let [bu, bv] = bin_px.map(|b| b.max(1));
    let (w, h) = (sequence.width, sequence.height);
    let mut set = SampleSet::default();
    let mut cells = Vec::new();
    let Some(ordered) = frames_in_order(sequence, poses, masks) else {
        return (set, cells);
    };
    if bu == 1 && bv == 1 {
        set = collect_samples(sequence, poses, masks);
        for pose in ordered {
            let mask = &masks.masks[pose.frame_index];
            cells.extend(
                (0..w * h)
                    .filter(|&i| mask[i] != 0)
                    .map(|i| [(i % w) as u32, (i / w) as u32]),
            );
        }
        return (set, cells);
    }
    for pose in ordered {
        let f = pose.frame_index;
        let mask = &masks.masks[f];
        for v0 in (0..h).step_by(bv) {
            for u0 in (0..w).step_by(bu) {
                let (mut su, mut sv, mut si, mut n) = (0.0f64, 0.0f64, 0.0f64, 0usize);
                for v in v0..(v0 + bv).min(h) {
                    for u in u0..(u0 + bu).min(w) {
                        if mask[v * w + u] != 0 {
                            su += u as f64;
                            sv += v as f64;
                            si += sequence.pixel_f32(f, u, v) as f64;
                            n += 1;
                        }
                    }
                }
                if n > 0 {
                    let k = n as f64;
                    set.positions
                        .push(pose.image_to_world.transform_point3(DVec3::new(
                            su / k,
                            sv / k,
                            0.0,
                        )));
                    set.intensities.push((si / k) as f32);
                    set.frame_of_sample.push(f as u32);
                    cells.push([(u0 / bu) as u32, (v0 / bv) as u32]);
                }
            }
        }
    }
    (set, cells)
}

/// Flags the samples near an echo: within `radius_cells = [columns, rows]` blocks (a box, in the same
/// frame) of a sample at least as bright as `level`. These are the samples that place the iso-surface:
/// the echo itself and the dark pixels on either side of it where the field must fall below the level.
/// `cells` are the blocks of [`collect_samples_binned_with_cells`].
pub fn near_echo_flags(
    set: &SampleSet,
    cells: &[[u32; 2]],
    level: f32,
    radius_cells: [usize; 2],
) -> Vec<bool> {
    let echoes: Vec<bool> = set.intensities.iter().map(|&x| x >= level).collect();
    near_marked_flags(set, cells, &echoes, radius_cells)
}

/// [`near_echo_flags`] with the echo blocks given: the samples within `radius_cells` blocks (a box, in
/// the same frame) of a sample marked in `echoes` (e.g. bright, or on a line echo:
/// [`crate::line_echo::line_echo_blocks`]).
pub fn near_marked_flags(
    set: &SampleSet,
    cells: &[[u32; 2]],
    echoes: &[bool],
    radius_cells: [usize; 2],
) -> Vec<bool> {
    let n = set.len().min(cells.len()).min(echoes.len());
    let mut flags = vec![false; set.len()];
    for std::ops::Range { start, end } in frame_runs(set, n) {
        let run = &cells[start..end];
        let cols = run.iter().map(|c| c[0] as usize + 1).max().unwrap_or(0);
        let rows = run.iter().map(|c| c[1] as usize + 1).max().unwrap_or(0);
        // Bright blocks, dilated along rows then columns (a separable box).
        let mut bright = vec![false; cols * rows];
        for (c, &echo) in run.iter().zip(&echoes[start..end]) {
            if echo {
                bright[c[1] as usize * cols + c[0] as usize] = true;
            }
        }
        let mut across = vec![false; cols * rows];
        for r in 0..rows {
            let row = &bright[r * cols..(r + 1) * cols];
            for (c, out) in across[r * cols..(r + 1) * cols].iter_mut().enumerate() {
                let lo = c.saturating_sub(radius_cells[0]);
                let hi = (c + radius_cells[0]).min(cols - 1);
                *out = row[lo..=hi].iter().any(|&b| b);
            }
        }
        for (i, c) in (start..end).zip(run) {
            let (col, row) = (c[0] as usize, c[1] as usize);
            let lo = row.saturating_sub(radius_cells[1]);
            let hi = (row + radius_cells[1]).min(rows - 1);
            flags[i] = (lo..=hi).any(|r| across[r * cols + col]);
        }
    }
    flags
}

/// The runs of consecutive samples of one frame among the first `n` (samples are collected frame by
/// frame, so each run is one frame's).
pub(crate) fn frame_runs(set: &SampleSet, n: usize) -> Vec<std::ops::Range<usize>> {
    let mut runs = Vec::new();
    let mut start = 0;
    while start < n {
        let frame = set.frame_of_sample[start];
        let end = (start..n)
            .find(|&i| set.frame_of_sample[i] != frame)
            .unwrap_or(n);
        runs.push(start..end);
        start = end;
    }
    runs
}

/// `target` samples (all when there are fewer), the flagged ones first: up to `max_flagged` of them (a
/// random choice when there are more), the rest of the budget a random choice of the others (and more
/// flagged ones if the others run out). The paper's random deletion spends the budget evenly over the
/// band, which is mostly background; a thin echo then keeps too few samples to stay thin and bright in
/// the fit, and the iso-surface breaks up. Deterministic in `seed`; samples stay in their order.
pub fn priority_decimate(
    set: &SampleSet,
    flags: &[bool],
    target: usize,
    max_flagged: usize,
    seed: u64,
) -> SampleSet {
    if target >= set.len() || flags.len() != set.len() {
        return random_decimate(set, target, seed);
    }
    let (near, far): (Vec<usize>, Vec<usize>) = (0..set.len()).partition(|&i| flags[i]);
    let take_near = max_flagged
        .max(target.saturating_sub(far.len()))
        .min(near.len())
        .min(target);
    let mut idx: Vec<usize> = random_indices(near.len(), take_near, seed)
        .into_iter()
        .map(|k| near[k])
        .collect();
    idx.extend(
        random_indices(far.len(), target - take_near, seed ^ 0x9e37_79b9_7f4a_7c15)
            .into_iter()
            .map(|k| far[k]),
    );
    idx.sort_unstable();
    set.select(&idx)
}

/// At most `target` samples chosen uniformly at random without replacement, in their original order.
/// Deterministic in `seed` (ChaCha8; Floyd's algorithm over indices, so O(target) random draws).
pub fn random_decimate(set: &SampleSet, target: usize, seed: u64) -> SampleSet {
    if target >= set.len() {
        return set.clone();
    }
    set.select(&random_indices(set.len(), target, seed))
}

/// `target` of the indices `0..n` uniformly at random without replacement, ascending (all of them when
/// `target >= n`). Floyd's algorithm: O(target) ChaCha8 draws.
fn random_indices(n: usize, target: usize, seed: u64) -> Vec<usize> {
    if target >= n {
        return (0..n).collect();
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut chosen = vec![false; n];
    // Floyd: for j in n-target..n pick t in [0, j]; take t unless already taken, else take j.
    for j in (n - target)..n {
        let t = rng.random_range(0..=j);
        if chosen[t] {
            chosen[j] = true;
        } else {
            chosen[t] = true;
        }
    }
    (0..n).filter(|&i| chosen[i]).collect()
}

/// Grey levels of the kept pixels: the background (dark) class, the boundary (bright echo) class, and a
/// suggested iso-level between them.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct IntensityLevels {
    /// Median of the darker Otsu class of the kept intensities.
    pub background: f32,
    /// Median of the brighter Otsu class.
    pub boundary: f32,
    /// Level of the strong echoes, from boundaries facing the beam ([`estimate_echo_levels`]: the
    /// brighter Otsu class of the column peaks; elsewhere equal to `boundary`).
    pub strong_echo: f32,
    /// `background + ISO_FRACTION * (boundary - background)`, and at least
    /// `background + ISO_FLOOR_FRACTION * (strong_echo - background)`.
    pub iso: f32,
}

/// Where the suggested iso-level sits between background and boundary: the paper's duck used 50 between a
/// background of ~15 and a boundary of ~130, i.e. (50 - 15) / (130 - 15) = 0.30 of the way up.
pub const ISO_FRACTION: f32 = 0.30;

/// The suggested iso-level stays at least this far from the background to the strong echoes: below
/// it, the fitted speckle comes through as blobs. Needed where fewer than a quarter of the columns
/// cross an echo (a small object in a wide frame), so that the boundary level (upper quartile of the
/// column peaks) is a speckle peak (measured in docs/decisions/0008-automatic-iso-level.md).
pub const ISO_FLOOR_FRACTION: f32 = 0.18;

/// Background and boundary echo levels read from the images the way echoes form: in every column of
/// every used frame, the brightest kept pixel is the boundary echo of that column and the kept pixels
/// above it (nearer the probe, where the beam crossed the medium before the boundary) are background.
/// The boundary level is the upper quartile of the column peaks (columns that cross no echo, e.g. steep
/// walls, only reach speckle peaks and fall below it); the background is the median of the per-column
/// medians above the peak. Unlike a two-class split of all kept intensities, this is not fooled by a
/// band that is mostly acoustic shadow. The strong-echo level is the median of the brighter class of a
/// two-class (Otsu) split of the column peaks: the columns that cross an echo facing the beam, however
/// few (checked against the simulator's level: docs/decisions/0035-figures-from-code-comments.md).
/// `None` without usable columns.
pub fn estimate_echo_levels(
    sequence: &TrackedSequence,
    poses: &PoseResolution,
    masks: &BandMasks,
) -> Option<IntensityLevels> {
    let (w, h) = (sequence.width, sequence.height);
    if (masks.width, masks.height) != (w, h) || sequence.is_tracking_only() {
        return None;
    }
    let mut peaks: Vec<f32> = Vec::new();
    let mut backgrounds: Vec<f32> = Vec::new();
    let mut above: Vec<f32> = Vec::new();
    for pose in &poses.poses {
        let Some(mask) = masks.masks.get(pose.frame_index) else {
            continue;
        };
        let frame = sequence.frame_f32(pose.frame_index);
        for u in 0..w {
            let mut peak: Option<(usize, f32)> = None;
            for v in 0..h {
                let i = v * w + u;
                if mask[i] != 0 && peak.is_none_or(|(_, p)| frame[i] > p) {
                    peak = Some((v, frame[i]));
                }
            }
            let Some((peak_row, peak_value)) = peak else {
                continue;
            };
            peaks.push(peak_value);
            above.clear();
            above.extend(
                (0..peak_row)
                    .map(|v| v * w + u)
                    .filter(|&i| mask[i] != 0)
                    .map(|i| frame[i]),
            );
            if above.len() >= 3 {
                backgrounds.push(median(&mut above));
            }
        }
    }
    if peaks.is_empty() || backgrounds.is_empty() {
        return None;
    }
    peaks.sort_by(f32::total_cmp);
    let boundary = peaks[(peaks.len() * 3) / 4];
    let background = median(&mut backgrounds);
    if boundary.partial_cmp(&background) != Some(std::cmp::Ordering::Greater) {
        return None;
    }
    let strong_echo = estimate_levels(&peaks)
        .map(|split| split.boundary)
        .unwrap_or(boundary)
        .max(boundary);
    Some(IntensityLevels {
        background,
        boundary,
        strong_echo,
        iso: (background + ISO_FRACTION * (boundary - background))
            .max(background + ISO_FLOOR_FRACTION * (strong_echo - background)),
    })
}

fn median(values: &mut [f32]) -> f32 {
    let mid = values.len() / 2;
    *values.select_nth_unstable_by(mid, f32::total_cmp).1
}

/// Background and boundary levels of a sample set (Otsu's two-class split of a 1024-bin histogram of its
/// intensities, then each class's median), and a suggested iso-level for `--iso auto`. `None` when there
/// are no samples or they all have one grey level.
pub fn estimate_levels(intensities: &[f32]) -> Option<IntensityLevels> {
    const BINS: usize = 1024;
    let finite = intensities.iter().copied().filter(|x| x.is_finite());
    let (lo, hi) = finite
        .clone()
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), x| {
            (a.min(x), b.max(x))
        });
    if hi.partial_cmp(&lo) != Some(std::cmp::Ordering::Greater) {
        return None;
    }
    let scale = (BINS - 1) as f64 / (hi - lo) as f64;
    let bin_of = |x: f32| (((x - lo) as f64) * scale) as usize;
    let mut hist = vec![0u64; BINS];
    for x in finite {
        hist[bin_of(x)] += 1;
    }
    let total: u64 = hist.iter().sum();
    let sum_all: f64 = hist
        .iter()
        .enumerate()
        .map(|(i, &c)| i as f64 * c as f64)
        .sum();
    let (mut w0, mut s0, mut best, mut split) = (0u64, 0.0f64, -1.0f64, 0usize);
    for (i, &c) in hist.iter().enumerate() {
        w0 += c;
        s0 += i as f64 * c as f64;
        let w1 = total - w0;
        if w0 == 0 || w1 == 0 {
            continue;
        }
        let (m0, m1) = (s0 / w0 as f64, (sum_all - s0) / w1 as f64);
        let between = w0 as f64 * w1 as f64 * (m1 - m0).powi(2);
        if between > best {
            best = between;
            split = i;
        }
    }
    let value_of = |bin: usize| lo + ((bin as f64 + 0.5) / scale) as f32;
    // Median bin of hist[range].
    let median = |range: std::ops::Range<usize>| {
        let count: u64 = hist[range.clone()].iter().sum();
        let mut acc = 0u64;
        for i in range.clone() {
            acc += hist[i];
            if 2 * acc >= count {
                return value_of(i);
            }
        }
        value_of(range.end - 1)
    };
    let background = median(0..split + 1);
    let boundary = median(split + 1..BINS);
    Some(IntensityLevels {
        background,
        boundary,
        strong_echo: boundary,
        iso: background + ISO_FRACTION * (boundary - background),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::{FramePose, PixelData};
    use crate::progress::NoProgress;
    use crate::segment::{
        InitialBand, SegmentOptions, segment_sequence,
        synthetic::{SyntheticSweep, synthetic_sweep},
    };
    use glam::DMat4;

    /// Band masks of the sweep's frame size with every pixel set to `value` (the segmenter supplies
    /// the frame metadata; the tests set the pixels they need).
    fn uniform_masks(s: &SyntheticSweep, value: u8) -> BandMasks {
        let mut masks = segment_sequence(
            &s.sequence,
            &s.poses,
            None,
            &InitialBand::Auto,
            &SegmentOptions::default(),
            &NoProgress,
        )
        .unwrap();
        for m in &mut masks.masks {
            m.fill(value);
        }
        masks
    }

    #[test]
    fn kept_pixels_map_through_their_frame_pose() {
        let s = synthetic_sweep(40, 30, 3, 0.2, 0.0, 1);
        let mut masks = uniform_masks(&s, 0);
        masks.masks[1][7 * 40 + 5] = 255;
        masks.masks[2][0] = 255;
        masks.masks[2][29 * 40 + 39] = 255;
        let mut poses = s.poses.clone();
        poses.poses[2] = FramePose {
            frame_index: 2,
            image_to_world: DMat4::from_translation(DVec3::new(10.0, 20.0, 30.0)),
        };
        let set = collect_samples(&s.sequence, &poses, &masks);
        assert_eq!(set.frame_of_sample, vec![1, 2, 2]);
        // Frame 1: 0.2 mm/px, 0.5 mm per frame along z.
        assert!((set.positions[0] - DVec3::new(5.0 * 0.2, 7.0 * 0.2, 0.5)).length() < 1e-12);
        assert_eq!(set.positions[1], DVec3::new(10.0, 20.0, 30.0));
        assert_eq!(set.positions[2], DVec3::new(49.0, 49.0, 30.0));
        assert_eq!(set.intensities[0], s.sequence.pixel_f32(1, 5, 7));
        assert_eq!(set.intensities[2], s.sequence.pixel_f32(2, 39, 29));
    }

    /// Frames of background 16 with one speckle peak of 50 per column (row 10) and, in the first
    /// `echo_columns` columns, an echo of 130 at row 30; every pixel kept.
    fn echo_levels_of(echo_columns: usize) -> IntensityLevels {
        let (w, h, frames) = (40, 50, 3);
        let mut s = synthetic_sweep(w, h, frames, 0.2, 0.0, 1);
        let mut pixels = vec![16u8; w * h * frames];
        for f in 0..frames {
            for u in 0..w {
                pixels[f * w * h + 10 * w + u] = 50;
                if u < echo_columns {
                    pixels[f * w * h + 30 * w + u] = 130;
                }
            }
        }
        s.sequence.pixels = PixelData::U8(pixels);
        let masks = uniform_masks(&s, 255);
        estimate_echo_levels(&s.sequence, &s.poses, &masks).unwrap()
    }

    #[test]
    fn echo_levels_follow_the_column_peaks() {
        // Most columns cross the echo: boundary = the echo (upper quartile of the column peaks),
        // iso 30 % of the way up from the background, above the floor.
        let l = echo_levels_of(30);
        assert_eq!((l.background, l.boundary), (16.0, 130.0));
        // The bright class's median, to the 1024-bin histogram's width (80 / 1023 grey levels).
        assert!((l.strong_echo - 130.0).abs() < 0.1, "{l:?}");
        assert!(
            (l.iso - (16.0 + ISO_FRACTION * 114.0)).abs() < 1e-4,
            "{l:?}"
        );
    }

    #[test]
    fn a_small_echo_still_lifts_the_iso_level_above_the_speckle() {
        // 4 of 40 columns cross the echo: the upper quartile of the column peaks is a speckle peak (50)
        // and 30 % of the way to it (26.2) would surface the speckle; the strong-echo level (the bright
        // class of the column peaks) still finds the echo, and the floor lifts the iso-level.
        let l = echo_levels_of(4);
        assert_eq!((l.background, l.boundary), (16.0, 50.0));
        assert!((l.strong_echo - 130.0).abs() < 0.1, "{l:?}");
        let floor = 16.0 + ISO_FLOOR_FRACTION * (l.strong_echo - 16.0);
        assert!((l.iso - floor).abs() < 1e-4, "{l:?}");
        assert!(l.iso > 16.0 + ISO_FRACTION * 34.0);
    }

    fn numbered(n: usize) -> SampleSet {
        SampleSet {
            positions: (0..n).map(|i| DVec3::splat(i as f64)).collect(),
            intensities: (0..n).map(|i| i as f32).collect(),
            frame_of_sample: (0..n).map(|i| i as u32).collect(),
        }
    }

    #[test]
    fn decimation_is_deterministic_ordered_and_without_replacement() {
        let set = numbered(10_000);
        let a = random_decimate(&set, 1234, 42);
        let b = random_decimate(&set, 1234, 42);
        assert_eq!(a, b);
        assert_eq!(a.len(), 1234);
        assert!(
            a.frame_of_sample.windows(2).all(|w| w[0] < w[1]),
            "order kept, no repeats"
        );
        let c = random_decimate(&set, 1234, 43);
        assert_ne!(a.frame_of_sample, c.frame_of_sample);
        assert_eq!(random_decimate(&set, 20_000, 1), set);
    }

    #[test]
    fn decimation_is_uniform() {
        // Each of 10 blocks of 1000 indices should receive ~500 of 5000 picks; the count is
        // hypergeometric with sd ~ 20, so +/-100 (5 sd) never fails by chance in practice.
        let picked = random_decimate(&numbered(10_000), 5000, 7);
        for block in 0..10u32 {
            let k = picked
                .frame_of_sample
                .iter()
                .filter(|&&i| i / 1000 == block)
                .count();
            assert!((400..=600).contains(&k), "block {block}: {k}");
        }
    }

    #[test]
    fn levels_split_background_and_echo() {
        // 80% background around 15, 20% boundary around 130 (the paper's duck levels).
        let mut values = Vec::new();
        for i in 0..880 {
            values.push(10.0 + (i % 11) as f32);
        }
        for i in 0..210 {
            values.push(120.0 + (i % 21) as f32); // 210 values: median exactly 130
        }
        let l = estimate_levels(&values).unwrap();
        assert!((l.background - 15.0).abs() < 0.5, "{l:?}");
        assert!((l.boundary - 130.0).abs() < 0.5, "{l:?}");
        assert!((l.iso - (l.background + 0.3 * (l.boundary - l.background))).abs() < 1e-4);
        assert!(estimate_levels(&[]).is_none());
        assert!(estimate_levels(&[3.0, 3.0]).is_none());
    }
}

#[cfg(test)]
mod binning_tests {
    use super::*;
    use crate::io::{FramePose, PixelData, TrackedFrame};
    use glam::DMat4;

    #[test]
    fn binned_samples_average_kept_pixels_of_each_block() {
        let (w, h) = (4usize, 2usize);
        let pixels: Vec<u8> = vec![10, 20, 30, 40, 50, 60, 70, 80];
        let seq = TrackedSequence {
            width: w,
            height: h,
            channels: 1,
            orientation: "MF".into(),
            frames: vec![TrackedFrame::default()],
            pixels: PixelData::U8(pixels),
            header: Default::default(),
        };
        let poses = PoseResolution {
            poses: vec![FramePose {
                frame_index: 0,
                image_to_world: DMat4::from_scale(glam::DVec3::splat(0.5)),
            }],
            skipped: vec![],
            world_frame: "Tracker".into(),
        };
        // Keep everything but pixel (1, 1) = 60.
        let masks = crate::segment::BandMasks {
            width: w,
            height: h,
            masks: vec![vec![255, 255, 255, 255, 255, 0, 255, 255]],
            warnings: vec![],
            initialised_frames: vec![0],
            frames: seq.frames.clone(),
            orientation: "MF".into(),
            parameters: crate::segment::ResolvedParameters {
                pixel_size_mm: None,
                smoothing_sigma_px: 0.0,
                likelihood_sigma_px: 15.0,
                likelihood_truncation_px: 32.0,
                edgel_count: 1,
                band_radius_inside_px: 1.0,
                band_radius_outside_px: 1.0,
            },
            bone_sweep: false,
            bone_echoes: Vec::new(),
        };
        let set = collect_samples_binned(&seq, &poses, &masks, [2, 2]);
        assert_eq!(set.len(), 2);
        // Block (0..2, 0..2): pixels 10, 20, 50 at (0,0), (1,0), (0,1).
        assert!((set.intensities[0] - (80.0 / 3.0)).abs() < 1e-4);
        assert!(set.positions[0].distance(glam::DVec3::new(0.5 / 3.0, 0.5 / 3.0, 0.0)) < 1e-12);
        // Block (2..4, 0..2): all four kept.
        assert!((set.intensities[1] - 55.0).abs() < 1e-4);
        assert_eq!(
            collect_samples_binned(&seq, &poses, &masks, [1, 1]).len(),
            7
        );
        let (with_cells, cells) = collect_samples_binned_with_cells(&seq, &poses, &masks, [2, 2]);
        assert_eq!(with_cells, set);
        assert_eq!(cells, vec![[0, 0], [1, 0]]);
        let (single, cells) = collect_samples_binned_with_cells(&seq, &poses, &masks, [1, 1]);
        assert_eq!(single.len(), 7);
        assert_eq!(
            cells[5],
            [2, 1],
            "pixel (1, 1) is dropped: the sixth kept pixel is (2, 1)"
        );
        assert_eq!(cells[4], [0, 1]);
    }
}

#[cfg(test)]
mod thinning_tests {
    use super::*;

    /// Two frames of a 10 x 6 block grid, every block a sample; frame 0 has one bright block at
    /// (4, 2), frame 1 none. Intensity 100 bright, 10 elsewhere.
    fn grid() -> (SampleSet, Vec<[u32; 2]>) {
        let mut set = SampleSet::default();
        let mut cells = Vec::new();
        for f in 0..2u32 {
            for r in 0..6u32 {
                for c in 0..10u32 {
                    set.positions.push(DVec3::new(c as f64, r as f64, f as f64));
                    set.intensities.push(if f == 0 && (c, r) == (4, 2) {
                        100.0
                    } else {
                        10.0
                    });
                    set.frame_of_sample.push(f);
                    cells.push([c, r]);
                }
            }
        }
        (set, cells)
    }

    #[test]
    fn near_echo_flags_are_a_box_around_bright_blocks_in_their_own_frame() {
        let (set, cells) = grid();
        let flags = near_echo_flags(&set, &cells, 50.0, [2, 1]);
        for (i, c) in cells.iter().enumerate() {
            let expected =
                set.frame_of_sample[i] == 0 && (2..=6).contains(&c[0]) && (1..=3).contains(&c[1]);
            assert_eq!(flags[i], expected, "sample {i} at {c:?}");
        }
        assert_eq!(flags.iter().filter(|&&f| f).count(), 15);
        // A level above every sample flags nothing.
        assert!(
            !near_echo_flags(&set, &cells, 101.0, [2, 1])
                .iter()
                .any(|&f| f)
        );
    }

    #[test]
    fn priority_decimation_keeps_flagged_samples_up_to_their_share() {
        let (set, cells) = grid();
        let flags = near_echo_flags(&set, &cells, 50.0, [2, 1]);
        let flagged = |s: &SampleSet| {
            s.positions
                .iter()
                .filter(|p| p.z == 0.0 && (2.0..=6.0).contains(&p.x) && (1.0..=3.0).contains(&p.y))
                .count()
        };
        // Budget 40, flagged may take 20: all 15 flagged kept, 25 others.
        let thinned = priority_decimate(&set, &flags, 40, 20, 7);
        assert_eq!(thinned.len(), 40);
        assert_eq!(flagged(&thinned), 15);
        // Flagged capped at 10 of the 15.
        let capped = priority_decimate(&set, &flags, 40, 10, 7);
        assert_eq!((capped.len(), flagged(&capped)), (40, 10));
        // With no share for them, flagged samples only fill what the 105 others cannot.
        let full = priority_decimate(&set, &flags, 110, 0, 7);
        assert_eq!((full.len(), flagged(&full)), (110, 5));
        // Order preserved (positions strictly increase in frame-major raster order), seed-determined.
        let key = |p: &DVec3| (p.z as i64, p.y as i64, p.x as i64);
        assert!(
            thinned
                .positions
                .windows(2)
                .all(|w| key(&w[0]) < key(&w[1]))
        );
        assert_eq!(thinned, priority_decimate(&set, &flags, 40, 20, 7));
        assert_ne!(thinned, priority_decimate(&set, &flags, 40, 20, 8));
        // Uniform random decimation keeps the flagged ones only in proportion (15 of 120 -> ~5 of 40).
        assert!(flagged(&random_decimate(&set, 40, 7)) < 15);
    }
}
