//! Echo crests in the frames themselves: where a wall's echo peaks along the beam.
//!
//! The fitted field flattens faint echoes (smoothing, sample thinning), so on walls that turn away from
//! the beam its ridges stop where the frames still show the echo (docs/decisions/0044). Here each frame,
//! lightly smoothed, is searched down its columns (the beam) for maxima that stand out of their own
//! neighbourhood: `min_prominence_grey` above the lowest grey within [`PROMINENCE_REACH_MM`] on both
//! sides, and `min_contrast_ratio` times the mean of the darker side over [`DARK_SIDE_MM`]. A wall
//! echo has dark water, a shadow or a lumen on at least one side; speckle inside tissue has tissue on
//! both. No global grey level enters. Crests chain across neighbouring columns; chains shorter than
//! `min_chain_mm` (speckle grains) are dropped.

use glam::DMat4;
use rayon::prelude::*;

use super::crop::{effective_clip, load_grey_crop};
use super::filters::{gaussian_taps, smooth};
use crate::io::{ClipRect, PoseResolution, TrackedSequence};
use crate::{Error, Result};

/// Which maxima along the beam count as echo crests ([`echo_crests`]).
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
    /// crest of its chain within [`LOCAL_PEAK_REACH_MM`] across the beam: an echo ends where it has
    /// fallen to half its peak, not where the lateral blur of its end fades out (a wire's ribbon, a
    /// wall's rim). 0: off.
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

/// The prominence is measured within this distance (mm) of the crest along the beam.
pub const PROMINENCE_REACH_MM: f64 = 1.0;

/// The darker side's mean is taken over this range of distances (mm) from the crest along the beam:
/// past the echo's own blur, within the wall's neighbourhood.
pub const DARK_SIDE_MM: [f64; 2] = [0.5, 1.5];

/// The strongest crest a crest is compared with lies within this distance (mm) across the beam.
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
    options.validate()?;
    let Some(mut clip) = effective_clip(clip, sequence.width, sequence.height) else {
        return Ok(Vec::new());
    };
    if detect_data_region {
        // All frames black: no crest anywhere.
        let Some(region) = super::data_region(sequence, poses, clip) else {
            return Ok(Vec::new());
        };
        clip = region;
    }
    Ok(poses
        .poses
        .par_iter()
        .map(|pose| {
            let m = pose.image_to_world;
            let pixel_mm = [m.x_axis.truncate().length(), m.y_axis.truncate().length()];
            let (mut grey, mut tmp, mut smoothed) = (Vec::new(), Vec::new(), Vec::new());
            load_grey_crop(sequence, pose.frame_index, clip, &mut grey);
            let [w, h] = clip.size_px;
            smooth(
                &grey,
                w,
                h,
                &gaussian_taps(options.smoothing_mm / pixel_mm[1]),
                &mut tmp,
                &mut smoothed,
            );
            let [u0, v0] = clip.origin_px.map(|x| x as f64);
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
        })
        .collect())
}

/// The crests of one smoothed image (`w` x `h`, pixels `pixel_mm` wide and high), row-major order.
pub fn crests_in_image(
    image: &[f32],
    w: usize,
    h: usize,
    pixel_mm: [f64; 2],
    options: &CrestOptions,
) -> Vec<ImageCrest> {
    let rows = |mm: f64| (mm / pixel_mm[1]).round().max(1.0) as usize;
    let test = CrestTest {
        prominence: options.min_prominence_grey as f32,
        ratio: options.min_contrast_ratio as f32,
        reach: rows(PROMINENCE_REACH_MM),
        dark_from: rows(DARK_SIDE_MM[0]),
        dark_to: rows(DARK_SIDE_MM[1]),
    };
    if image.len() != w * h || h <= 2 * test.reach {
        return Vec::new();
    }
    let mut crest = vec![None; w * h];
    for v in test.reach..h - test.reach {
        for u in 0..w {
            crest[v * w + u] = test.at(image, w, h, u, v);
        }
    }
    let (span, label) = chain_spans(&crest, w, h);
    let min_span = options.min_chain_mm / pixel_mm[0];
    // Per chain and column, the highest crest (height, row): each crest is compared with its chain's
    // nearby peak, and its chain's direction is read from them.
    let fraction = options.min_local_peak_fraction as f32;
    let reach_cols = (LOCAL_PEAK_REACH_MM / pixel_mm[0]).round() as usize;
    let tangent_cols = (TANGENT_REACH_MM / pixel_mm[0]).round().max(1.0) as usize;
    let mut column_peak: std::collections::HashMap<(usize, usize), (f32, f64)> = Default::default();
    for (i, c) in crest.iter().enumerate() {
        if let Some((row, height)) = *c {
            let peak = column_peak
                .entry((label[i], i % w))
                .or_insert((height, row));
            if height > peak.0 {
                *peak = (height, row);
            }
        }
    }
    crest
        .iter()
        .zip(&span)
        .enumerate()
        .filter_map(|(i, (c, &s))| {
            let (row, height) = (*c)?;
            if (s as f64) < min_span {
                return None;
            }
            let u = i % w;
            if fraction > 0.0 {
                let peak = (u.saturating_sub(reach_cols)..=u + reach_cols)
                    .filter_map(|c| column_peak.get(&(label[i], c)))
                    .fold(0.0f32, |a, &(b, _)| a.max(b));
                if height < fraction * peak {
                    return None;
                }
            }
            // The farthest columns of the chain within reach on each side (this crest where none).
            let row_at = |c: usize| column_peak.get(&(label[i], c)).map(|&(_, r)| r);
            let left = (u.saturating_sub(tangent_cols)..u)
                .find_map(|c| Some((c, row_at(c)?)))
                .unwrap_or((u, row));
            let right = (u + 1..=u + tangent_cols)
                .rev()
                .find_map(|c| Some((c, row_at(c)?)))
                .unwrap_or((u, row));
            let row_slope = if right.0 > left.0 {
                (right.1 - left.1) / (right.0 - left.0) as f64
            } else {
                0.0
            };
            Some(ImageCrest {
                column: u as f64,
                row,
                row_slope,
            })
        })
        .collect()
}

/// [`CrestOptions`] in pixels.
struct CrestTest {
    prominence: f32,
    ratio: f32,
    reach: usize,
    dark_from: usize,
    dark_to: usize,
}

impl CrestTest {
    /// The crest at column `u`, row `v` (`reach <= v < h - reach`), if any: its row refined by the
    /// parabola through the three samples around the maximum, and its height over the darker side.
    fn at(&self, image: &[f32], w: usize, h: usize, u: usize, v: usize) -> Option<(f64, f32)> {
        let grey = |row: usize| image[row * w + u];
        let s = grey(v);
        if s <= grey(v - 1) || s < grey(v + 1) {
            return None;
        }
        let lowest =
            |rows: std::ops::RangeInclusive<usize>| rows.map(grey).fold(f32::MAX, f32::min);
        let higher_side_min = lowest(v - self.reach..=v - 1).max(lowest(v + 1..=v + self.reach));
        if s - higher_side_min < self.prominence {
            return None;
        }
        let mean = |rows: std::ops::RangeInclusive<usize>| {
            let n = rows.clone().count().max(1) as f32;
            rows.map(grey).sum::<f32>() / n
        };
        let above = mean(v.saturating_sub(self.dark_to)..=v.saturating_sub(self.dark_from));
        let below = mean((v + self.dark_from).min(h - 1)..=(v + self.dark_to).min(h - 1));
        let dark = above.min(below);
        if s < self.ratio * dark {
            return None;
        }
        let (a, b, c) = (grey(v - 1) as f64, s as f64, grey(v + 1) as f64);
        let curvature = a - 2.0 * b + c;
        let offset = if curvature < 0.0 {
            (0.5 * (a - c) / curvature).clamp(-0.5, 0.5)
        } else {
            0.0
        };
        Some((v as f64 + offset, s - dark))
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
        // One crest per column of the echo's 100 (the smoothing spreads its ends by a column or two).
        assert!(
            on_echo.len() >= 98 && on_echo.len() <= 104,
            "{}",
            on_echo.len()
        );
        for c in &on_echo {
            assert!(
                (c.row - echo_row).abs() < 0.1,
                "crest at row {} for {echo_row}",
                c.row
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
        assert!(
            3 * in_tissue < loose_in_tissue,
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
        // A bright spot 3 px wide: a chain of 0.4 mm, under the 1 mm of the default.
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
        assert_eq!(crests_in_image(&image, w, h, PIXEL_MM, &short).len(), 3);
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
}
