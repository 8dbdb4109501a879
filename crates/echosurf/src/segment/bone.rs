//! Bone echoes: a bright echo with an acoustic shadow below it. Bone reflects nearly all the sound, so
//! under its surface the column is dark and holds no strong echo; the tissue layers under the probe
//! return speckle all the way down and cast no such shadow. Where the probe is in contact with tissue
//! (not a water bath) and such echoes run through most frames, the band is the bone's surface alone.

/// How bone echoes are found in a column of the smoothed frame (lengths in mm along the beam).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct BoneEchoOptions {
    /// Gaussian smoothing of the frame before the column scan (speckle grain).
    pub smoothing_mm: f64,
    /// The echo must stand out of the tissue just above it, from `above_mm[0]` to `above_mm[1]` above:
    /// by at least this fraction of its own brightness.
    pub prominence: f64,
    pub above_mm: [f64; 2],
    /// The shadow: the mean from `shadow_mm[0]` to `shadow_mm[1]` below the echo is at most
    /// `shadow_ratio` of the echo and at most `tissue_ratio` of the tissue above it.
    pub shadow_mm: [f64; 2],
    pub shadow_ratio: f64,
    pub tissue_ratio: f64,
    /// No echo deeper than `clear_below_mm` under it reaches `strong_ratio` of its brightness.
    pub clear_below_mm: f64,
    pub strong_ratio: f64,
    /// The echo reaches at least this fraction of the frame's brightest (smoothed) pixel: the dark
    /// margins beside the scan and the last faint rows are not echoes, however they compare locally.
    pub min_echo_fraction: f64,
    /// Neighbouring columns within this distance (mm)...
    pub agree_width_mm: f64,
    /// ...must, for at least this fraction of them, hold a bone echo within `agree_depth_mm`.
    pub agree_fraction: f64,
    pub agree_depth_mm: f64,
    /// The echo's core along its column, this far above and below it (mm), is fitted against the
    /// echo's contrast; the rest of a bone frame is fitted as floor (see [`contrast_normalised`]).
    pub band_above_mm: f64,
    pub band_below_mm: f64,
}

impl Default for BoneEchoOptions {
    fn default() -> Self {
        BoneEchoOptions {
            smoothing_mm: 0.3,
            prominence: 0.1,
            above_mm: [1.0, 4.0],
            shadow_mm: [2.0, 12.0],
            shadow_ratio: 0.4,
            tissue_ratio: 0.5,
            clear_below_mm: 3.0,
            strong_ratio: 0.6,
            min_echo_fraction: 0.2,
            agree_width_mm: 1.0,
            agree_fraction: 0.6,
            agree_depth_mm: 1.0,
            band_above_mm: 1.5,
            band_below_mm: 1.5,
        }
    }
}

impl BoneEchoOptions {
    pub fn validate(&self) -> Result<(), String> {
        let lengths = [
            self.smoothing_mm,
            self.above_mm[0],
            self.above_mm[1],
            self.shadow_mm[0],
            self.shadow_mm[1],
            self.clear_below_mm,
            self.agree_width_mm,
            self.agree_depth_mm,
            self.band_above_mm,
            self.band_below_mm,
        ];
        if lengths.iter().any(|l| !l.is_finite() || *l < 0.0) {
            return Err("bone echo lengths must be finite and non-negative (mm)".into());
        }
        if self.above_mm[0] >= self.above_mm[1] || self.shadow_mm[0] >= self.shadow_mm[1] {
            return Err("bone echo windows must run from a nearer to a farther depth".into());
        }
        let fractions = [
            self.prominence,
            self.shadow_ratio,
            self.tissue_ratio,
            self.strong_ratio,
            self.min_echo_fraction,
            self.agree_fraction,
        ];
        if fractions
            .iter()
            .any(|f| !f.is_finite() || *f < 0.0 || *f > 1.0)
        {
            return Err("bone echo ratios must lie in [0, 1]".into());
        }
        Ok(())
    }
}

/// Whether a sequence is segmented as bone: `Auto` decides from the frames ([`is_bone_sweep`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
pub enum BoneMode {
    #[default]
    Auto,
    Always,
    Never,
}

/// One column's bone echo: its row, its brightness (smoothed), and the means of the tissue above it
/// and of its shadow.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BoneEcho {
    pub row: usize,
    pub echo: f32,
    pub above: f32,
    pub shadow: f32,
}

/// Per column of a smoothed (clipped, row-major) frame, its bone echo: the deepest local maximum down
/// the column that stands out of the tissue above it, has a shadow below (seen over its whole window,
/// so not in the frame's last rows) and no strong echo under it; kept where the neighbouring columns
/// agree.
pub fn bone_echoes(
    smoothed: &[f32],
    width: usize,
    height: usize,
    pixel_size_mm: f64,
    options: &BoneEchoOptions,
) -> Vec<Option<BoneEcho>> {
    let px = |mm: f64| (mm / pixel_size_mm).round().max(1.0) as usize;
    let (a0, a1) = (px(options.above_mm[0]), px(options.above_mm[1]));
    let (s0, s1) = (px(options.shadow_mm[0]), px(options.shadow_mm[1]));
    let clear = px(options.clear_below_mm);
    let mut rows = vec![None; width];
    let mut column = vec![0f32; height];
    let brightest = smoothed
        .iter()
        .copied()
        .filter(|x| x.is_finite())
        .fold(0f32, f32::max);
    let min_echo = options.min_echo_fraction * f64::from(brightest);
    // The whole shadow window lies in the frame, and `clear` rows under the echo are checked.
    let last_row = height
        .saturating_sub(clear + 1)
        .min((height + 1).saturating_sub(s1));
    // Prefix sums give window means; suffix maxima the strongest echo below a depth.
    let mut prefix = vec![0f64; height + 1];
    let mut suffix_max = vec![0f32; height + 1];
    for (u, row_of) in rows.iter_mut().enumerate() {
        for (v, c) in column.iter_mut().enumerate() {
            *c = smoothed[v * width + u];
        }
        for v in 0..height {
            prefix[v + 1] = prefix[v] + f64::from(column[v]);
        }
        suffix_max[height] = f32::MIN;
        for v in (0..height).rev() {
            suffix_max[v] = suffix_max[v + 1].max(column[v]);
        }
        let mean = |lo: usize, hi: usize| {
            let (lo, hi) = (lo.min(height), hi.min(height));
            if hi <= lo {
                0.0
            } else {
                (prefix[hi] - prefix[lo]) / (hi - lo) as f64
            }
        };
        for v in a1.max(1)..last_row {
            let echo = column[v];
            if echo <= 0.0 || echo < column[v - 1] || echo < column[v + 1] {
                continue;
            }
            let echo = f64::from(echo);
            if echo < min_echo {
                continue;
            }
            let above = mean(v - a1, v - a0);
            if echo - above < options.prominence * echo {
                continue;
            }
            let below = mean(v + s0, v + s1);
            if below > options.shadow_ratio * echo || below > options.tissue_ratio * above {
                continue;
            }
            if f64::from(suffix_max[v + clear]) > options.strong_ratio * echo {
                continue;
            }
            *row_of = Some(BoneEcho {
                row: v,
                echo: echo as f32,
                above: above as f32,
                shadow: below as f32,
            });
        }
    }
    let depth_px = (options.agree_depth_mm / pixel_size_mm).round() as usize;
    let row_only: Vec<Option<usize>> = rows.iter().map(|e| e.map(|e| e.row)).collect();
    agreeing(
        &row_only,
        px(options.agree_width_mm),
        depth_px,
        options.agree_fraction,
    )
    .into_iter()
    .zip(rows)
    .map(|(keep, echo)| echo.filter(|_| keep))
    .collect()
}

/// Which columns' bone echoes are backed by their neighbours: of the columns within `half_width`,
/// at least `fraction` hold one within `depth_px` rows.
fn agreeing(
    rows: &[Option<usize>],
    half_width: usize,
    depth_px: usize,
    fraction: f64,
) -> Vec<bool> {
    (0..rows.len())
        .map(|u| {
            let Some(r) = rows[u] else { return false };
            let lo = u.saturating_sub(half_width);
            let hi = (u + half_width + 1).min(rows.len());
            let agree = rows[lo..hi]
                .iter()
                .filter(|s| s.is_some_and(|s| r.abs_diff(s) <= depth_px))
                .count();
            agree as f64 >= fraction * (hi - lo) as f64
        })
        .collect()
}

/// The near field's brightness and the frame's brightest echoes: the median of the strip 1-6 mm under
/// the top of the clipped frame (a median, so an echo crossing the strip does not count) and the
/// frame's brightest (smoothed) pixel: a thin echo holds too few pixels for a percentile. `None` for a frame too small to hold the strip.
pub fn near_field_and_echo_levels(
    smoothed: &[f32],
    width: usize,
    height: usize,
    pixel_size_mm: f64,
) -> Option<[f64; 2]> {
    let r0 = ((1.0 / pixel_size_mm).round() as usize).min(height);
    let r1 = ((6.0 / pixel_size_mm).round() as usize).min(height);
    if r1 <= r0 || width == 0 {
        return None;
    }
    let mut near: Vec<f32> = smoothed[r0 * width..r1 * width]
        .iter()
        .copied()
        .filter(|x| x.is_finite())
        .collect();
    let mut all: Vec<f32> = smoothed.iter().copied().filter(|x| x.is_finite()).collect();
    if near.is_empty() || all.is_empty() {
        return None;
    }
    Some([quantile(&mut near, 0.5), quantile(&mut all, 1.0)])
}

fn quantile(values: &mut [f32], q: f64) -> f64 {
    let k = ((values.len() as f64 * q) as usize).min(values.len() - 1);
    f64::from(*values.select_nth_unstable_by(k, f32::total_cmp).1)
}

/// The probe is in contact with tissue (not in a water bath) in the frames whose near field is bright
/// speckle rather than dark water, relative to the sweep's brightest echoes (the median over frames
/// of their brightest pixels: a frame with no echo in view has only its own speckle to compare with).
pub fn tissue_frames(levels: &[Option<[f64; 2]>]) -> usize {
    let mut echo: Vec<f32> = levels.iter().flatten().map(|l| l[1] as f32).collect();
    if echo.is_empty() {
        return 0;
    }
    let echo_level = quantile(&mut echo, 0.5);
    levels
        .iter()
        .flatten()
        .filter(|l| echo_level > 0.0 && l[0] >= NEAR_FIELD_TISSUE_FRACTION * echo_level)
        .count()
}

/// Near field at least this fraction of the sweep's echo level: tissue under the probe. Water's speckle
/// reaches a quarter to a third of a faint echo's level on small simulated sweeps; tissue under the
/// probe is nearly as bright as the brightest echo.
const NEAR_FIELD_TISSUE_FRACTION: f64 = 0.5;

/// A frame counts as showing bone when its agreeing bone echoes cover this fraction of its columns...
pub const BONE_FRAME_COLUMN_FRACTION: f64 = 0.05;
/// ...and a sweep is bone when at least this fraction of its frames do, with tissue under the probe.
pub const BONE_SWEEP_FRAME_FRACTION: f64 = 0.5;

/// Summary of the per-frame evidence for bone.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BoneEvidence {
    pub frames: usize,
    pub tissue_frames: usize,
    pub bone_frames: usize,
}

impl BoneEvidence {
    pub fn is_bone(&self) -> bool {
        let need = BONE_SWEEP_FRAME_FRACTION * self.frames as f64;
        self.frames > 0 && self.tissue_frames as f64 >= need && self.bone_frames as f64 >= need
    }
}

/// The grey value a bone echo's peak is mapped to by [`contrast_normalised`], its floor to 0.
pub const NORMALISED_ECHO_LEVEL: f32 = 200.0;

/// The sequence with every pixel near a bone echo re-expressed against its own column's echo:
/// `NORMALISED_ECHO_LEVEL * (g - base) / (echo - base)`, clamped to 0..=255, where `base` is the
/// tissue above the echo for the pixels above its row and the shadow for those below; pixels farther
/// than `core_rows` (above, below) from a bone echo, and kept pixels of columns without one, are 0.
/// Each echo becomes a ridge of one height over a flat floor, so faint and bright bone echoes meet one
/// iso-level at the same fraction of their rise, and the tissue layers under the probe are floor.
pub fn contrast_normalised(
    sequence: &crate::io::TrackedSequence,
    masks: &[Vec<u8>],
    echoes: &[Vec<Option<BoneEcho>>],
    core_rows: [usize; 2],
) -> crate::io::TrackedSequence {
    let (w, h) = (sequence.width, sequence.height);
    let mut pixels = vec![0u8; w * h * sequence.frames.len()];
    for (f, (mask, columns)) in masks.iter().zip(echoes).enumerate() {
        if columns.is_empty() {
            continue;
        }
        let out = &mut pixels[f * w * h..(f + 1) * w * h];
        for v in 0..h {
            for (u, column) in columns.iter().enumerate().take(w) {
                let i = v * w + u;
                if mask[i] == 0 {
                    continue;
                }
                let Some(e) = *column else { continue };
                if v + core_rows[0] < e.row || v > e.row + core_rows[1] {
                    continue;
                }
                let base = if v < e.row { e.above } else { e.shadow };
                let rise = (e.echo - base).max(1e-3);
                let g = (sequence.pixel_f32(f, u, v) - base) / rise * NORMALISED_ECHO_LEVEL;
                out[i] = g.round().clamp(0.0, 255.0) as u8;
            }
        }
    }
    crate::io::TrackedSequence {
        width: w,
        height: h,
        channels: 1,
        orientation: sequence.orientation.clone(),
        frames: sequence.frames.clone(),
        pixels: crate::io::PixelData::U8(pixels),
        header: sequence.header.clone(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A frame of tissue speckle-free grey `tissue` down to `bone_row`, a bright line there, and a
    /// shadow (near black) below: the bone echo is found at its row in every column.
    fn bone_frame(width: usize, height: usize, bone_row: usize) -> Vec<f32> {
        let mut f = vec![0f32; width * height];
        for v in 0..height {
            for u in 0..width {
                f[v * width + u] = match v {
                    v if v < bone_row.saturating_sub(2) => 80.0,
                    v if v <= bone_row + 2 => 220.0 - 20.0 * (v as f32 - bone_row as f32).abs(),
                    _ => 5.0,
                };
            }
        }
        f
    }

    #[test]
    fn finds_a_bright_echo_over_a_shadow() {
        let (w, h) = (40, 240);
        let f = bone_frame(w, h, 90);
        let rows: Vec<Option<usize>> = bone_echoes(&f, w, h, 0.1, &BoneEchoOptions::default())
            .iter()
            .map(|e| e.map(|e| e.row))
            .collect();
        assert!(rows.iter().all(|r| *r == Some(90)), "{rows:?}");
    }

    #[test]
    fn tissue_below_is_not_a_shadow() {
        let (w, h) = (40, 240);
        let mut f = bone_frame(w, h, 90);
        // Speckle-level tissue continues under the echo: no shadow, no bone.
        for x in f[95 * w..].iter_mut() {
            *x = 80.0;
        }
        let rows: Vec<Option<usize>> = bone_echoes(&f, w, h, 0.1, &BoneEchoOptions::default())
            .iter()
            .map(|e| e.map(|e| e.row))
            .collect();
        assert!(rows.iter().all(Option::is_none), "{rows:?}");
    }

    #[test]
    fn a_strong_echo_under_it_is_not_bone() {
        let (w, h) = (40, 240);
        let mut f = bone_frame(w, h, 60);
        for x in f[150 * w..152 * w].iter_mut() {
            *x = 200.0;
        }
        let rows: Vec<Option<usize>> = bone_echoes(&f, w, h, 0.1, &BoneEchoOptions::default())
            .iter()
            .map(|e| e.map(|e| e.row))
            .collect();
        // The deeper line at 150-151 has no tissue above it (it lies in the shadow), so it is no bone
        // either; the echo at 60 has a strong echo under it.
        assert!(rows.iter().all(|r| *r != Some(60)), "{rows:?}");
    }

    #[test]
    fn isolated_columns_are_dropped() {
        let (w, h) = (40, 240);
        let mut f = vec![80f32; w * h];
        // One column with a bone-like profile: its neighbours disagree.
        let col = bone_frame(1, h, 90);
        for v in 0..h {
            f[v * w + 20] = col[v];
        }
        let rows: Vec<Option<usize>> = bone_echoes(&f, w, h, 0.1, &BoneEchoOptions::default())
            .iter()
            .map(|e| e.map(|e| e.row))
            .collect();
        assert!(rows.iter().all(Option::is_none), "{rows:?}");
    }

    #[test]
    fn water_near_field_is_not_tissue() {
        let (w, h) = (40, 240);
        let mut water = vec![5f32; w * h];
        for x in water[100 * w..102 * w].iter_mut() {
            *x = 200.0;
        }
        // Water speckle alone in view: its own percentile is no echo level.
        let empty = vec![5f32; w * h];
        let water_levels =
            [&water, &water, &empty].map(|f| near_field_and_echo_levels(f, w, h, 0.1));
        assert_eq!(tissue_frames(&water_levels), 0);
        // Tissue under the probe: bright speckle level throughout the near field.
        let mut tissue = bone_frame(w, h, 90);
        for x in tissue[..60 * w].iter_mut() {
            *x = 180.0;
        }
        let tissue_levels =
            [&tissue, &tissue, &empty].map(|f| near_field_and_echo_levels(f, w, h, 0.1));
        assert_eq!(tissue_frames(&tissue_levels), 2);
    }

    #[test]
    fn an_echo_whose_shadow_runs_off_the_frame_is_not_bone() {
        // At 0.1 mm/px the 2-12 mm shadow window needs 120 rows under the echo: at row 150 of 240 the
        // frame ends first, so the dark rows after it prove nothing.
        let (w, h) = (40, 240);
        let f = bone_frame(w, h, 150);
        let echoes = bone_echoes(&f, w, h, 0.1, &BoneEchoOptions::default());
        assert!(echoes.iter().all(Option::is_none), "{echoes:?}");
        let f = bone_frame(w, h, 110);
        let echoes = bone_echoes(&f, w, h, 0.1, &BoneEchoOptions::default());
        assert!(echoes.iter().all(|e| e.is_some_and(|e| e.row == 110)));
    }

    #[test]
    fn faint_ripples_in_the_dark_margin_are_not_bone() {
        // Columns 0-19: the scan (tissue, bone echo at 90, shadow); columns 20-39: the black margin
        // beside it with a faint 3-grey line, which stands out of its own zero surroundings.
        let (w, h) = (40, 240);
        let mut f = bone_frame(w, h, 90);
        for v in 0..h {
            for u in 20..w {
                f[v * w + u] = if (60..=61).contains(&v) { 3.0 } else { 0.0 };
            }
        }
        let echoes = bone_echoes(&f, w, h, 0.1, &BoneEchoOptions::default());
        assert!(echoes[..18].iter().all(|e| e.is_some_and(|e| e.row == 90)));
        assert!(echoes[22..].iter().all(Option::is_none), "{echoes:?}");
    }
}
