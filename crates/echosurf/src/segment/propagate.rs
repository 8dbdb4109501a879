//! The paper's band propagation on one clipped frame ([`Propagator`]) and along a sequence
//! ([`BandPropagation`]): edgels, the prior-weighted proximity, the threshold, recovery from a lost band.

use super::EdgePolarity;
use super::crop::{add_to_mask, band_from_mask, load_grey_crop};
use super::filters::{
    Edgel, EdgelSelection, gaussian_taps, smooth, squared_distance_capped, strongest_column_edgels,
};
use super::init::find_echo_structures;
use super::options::{EdgelChaining, ResolvedParameters, SegmentOptions};
use crate::io::{ClipRect, TrackedSequence};

/// Per-frame working state, reused from frame to frame (no per-frame or per-pixel allocation in the loop
/// once the buffers have their size).
#[derive(Debug, Default)]
pub(super) struct Workspace {
    grey: Vec<f32>,
    tmp: Vec<f32>,
    pub(super) smoothed: Vec<f32>,
    edgels: Vec<Edgel>,
    column: Vec<u32>,
    dist_inside: Vec<f32>,
    dist_outside: Vec<f32>,
    labels: Vec<u32>,
    stack: Vec<u32>,
    /// Echo strength of the boundary seen so far in this sweep, decaying per frame (see
    /// `min_edgel_relative_strength`); reset when the band is (re-)initialised.
    reference_strength: f32,
}

/// The paper's step on one (clipped) frame: pixel-unit parameters and the proximity lookup table.
#[derive(Debug)]
pub(super) struct Propagator {
    width: usize,
    height: usize,
    taps: Vec<f32>,
    auto_taps: Vec<f32>,
    edgel_count: usize,
    min_edgel_gradient: f32,
    relative_floor: f32,
    reference_decay: f32,
    polarity: EdgePolarity,
    chaining: Option<EdgelChaining>,
    min_chain_columns: usize,
    min_edgels_in_band: usize,
    prior_inside: f32,
    prior_outside: f32,
    /// What an edgel outside the carried band carries: C0, or 0 with [`SegmentOptions::follow_band`].
    outside_edgel_prior: f32,
    threshold: f32,
    /// Distances are capped one pixel beyond the truncation.
    cap_px: u32,
    /// `G(sqrt(d2))` for integer squared distances `d2 < cap^2` (0 beyond the truncation).
    proximity: Vec<f32>,
    band_radius_inside_px: f64,
    auto_keep_fraction: f32,
    shadow_offset_px: usize,
    shadow_length_px: usize,
}

impl Propagator {
    fn proximity_at(&self, d2: f32) -> f32 {
        let i = d2 as usize;
        if i < self.proximity.len() {
            self.proximity[i]
        } else {
            0.0
        }
    }

    /// `band_out = (max_e P(e) G(|x - e|) + C0 >= T)` with `P(e)` from `prior_band`. Returns the number of
    /// edgels that lay inside the prior band. `ws.smoothed` must hold the smoothed frame.
    fn step(&self, ws: &mut Workspace, prior_band: &[bool], band_out: &mut Vec<bool>) -> usize {
        use rayon::prelude::*;
        let (w, h) = (self.width, self.height);
        let carried = ws.reference_strength * self.reference_decay;
        let reference = strongest_column_edgels(
            &ws.smoothed,
            w,
            h,
            &EdgelSelection {
                count: self.edgel_count,
                min_strength: self.min_edgel_gradient,
                relative_floor: self.relative_floor,
                reference_at_least: carried,
                polarity: self.polarity,
                per_column: self.chaining.is_some(),
                weak_fraction: self.chaining.map_or(1.0, |c| c.weak_fraction as f32),
                link_rows: self.chaining.map_or(0, |c| c.link_rows),
                min_chain_columns: self.min_chain_columns,
                layers: self.chaining.map_or(1, |c| c.layers),
                layer_gap_rows: self.band_radius_inside_px.ceil() as usize,
            },
            &mut ws.edgels,
        );
        ws.reference_strength = reference.max(carried);
        let inside = ws
            .edgels
            .iter()
            .filter(|e| prior_band[e.index as usize])
            .count();
        let edgels = &ws.edgels;
        squared_distance_capped(
            edgels
                .iter()
                .filter(|e| prior_band[e.index as usize])
                .map(|e| e.index as usize),
            w,
            h,
            self.cap_px,
            &mut ws.column,
            &mut ws.dist_inside,
        );
        squared_distance_capped(
            edgels
                .iter()
                .filter(|e| !prior_band[e.index as usize])
                .map(|e| e.index as usize),
            w,
            h,
            self.cap_px,
            &mut ws.column,
            &mut ws.dist_outside,
        );
        band_out.resize(w * h, false);
        band_out
            .par_chunks_mut(w)
            .zip(
                ws.dist_inside
                    .par_chunks(w)
                    .zip(ws.dist_outside.par_chunks(w)),
            )
            .for_each(|(dst, (din, dout))| {
                for ((b, &di), &d_o) in dst.iter_mut().zip(din).zip(dout) {
                    let l_p = (self.prior_inside * self.proximity_at(di))
                        .max(self.outside_edgel_prior * self.proximity_at(d_o));
                    *b = l_p + self.prior_outside >= self.threshold;
                }
            });
        inside
    }

    /// Automatic band on the current frame (`ws.grey` holds it): bright connected structures of the
    /// strongly smoothed frame, dilated by the in-band radius. Returns false if nothing was found.
    fn auto_band(&self, ws: &mut Workspace, band: &mut Vec<bool>) -> bool {
        let (w, h) = (self.width, self.height);
        let mut smoothed = std::mem::take(&mut ws.tmp);
        let mut scratch = Vec::new();
        smooth(&ws.grey, w, h, &self.auto_taps, &mut scratch, &mut smoothed);
        // Echo over shadow: a boundary is bright with dark below it (no penetration), while near-field
        // reverberation and bright tissue layers have bright tissue below them.
        shadow_contrast(
            &smoothed,
            w,
            h,
            self.shadow_offset_px,
            self.shadow_length_px,
            &mut scratch,
        );
        std::mem::swap(&mut smoothed, &mut scratch);
        let seeds = find_echo_structures(
            &smoothed,
            w,
            h,
            self.auto_keep_fraction,
            &mut ws.labels,
            &mut ws.stack,
        );
        ws.tmp = smoothed;
        band.clear();
        band.resize(w * h, false);
        if seeds.is_empty() {
            return false;
        }
        squared_distance_capped(
            seeds.iter().map(|&s| s as usize),
            w,
            h,
            self.cap_px
                .max(self.band_radius_inside_px.ceil() as u32 + 1),
            &mut ws.column,
            &mut ws.dist_inside,
        );
        let r2 = (self.band_radius_inside_px * self.band_radius_inside_px) as f32;
        for (b, &d) in band.iter_mut().zip(&ws.dist_inside) {
            *b = d <= r2;
        }
        true
    }
}

impl Propagator {
    pub(super) fn new(
        options: &SegmentOptions,
        parameters: &ResolvedParameters,
        px_size: f64,
        clip: ClipRect,
    ) -> Propagator {
        let (sigma_px, truncation_px) = (
            parameters.likelihood_sigma_px,
            parameters.likelihood_truncation_px,
        );
        let cap_px = truncation_px.floor() as u32 + 1;
        let proximity: Vec<f32> = (0..(cap_px * cap_px))
            .map(|d2| {
                let d = (d2 as f64).sqrt();
                if d <= truncation_px {
                    (-(d2 as f64) / (2.0 * sigma_px * sigma_px)).exp() as f32
                } else {
                    0.0
                }
            })
            .collect();
        let edgel_count = parameters.edgel_count;
        Propagator {
            width: clip.size_px[0],
            height: clip.size_px[1],
            taps: gaussian_taps(parameters.smoothing_sigma_px),
            auto_taps: gaussian_taps(options.auto_smoothing_sigma.to_px(px_size)),
            edgel_count,
            min_edgel_gradient: options.min_edgel_gradient as f32,
            polarity: options.edgel_polarity,
            chaining: options.edgel_chaining,
            min_chain_columns: options
                .edgel_chaining
                .map_or(0, |c| c.min_chain_length.to_px(px_size).round() as usize),
            relative_floor: options.min_edgel_relative_strength as f32,
            reference_decay: 0.8,
            min_edgels_in_band: ((options.min_edgels_in_band_fraction * edgel_count as f64).ceil()
                as usize)
                .max(1),
            prior_inside: options.prior_inside as f32,
            prior_outside: options.prior_outside as f32,
            outside_edgel_prior: if options.follow_band {
                0.0
            } else {
                options.prior_outside as f32
            },
            threshold: options.threshold as f32,
            cap_px,
            proximity,
            band_radius_inside_px: parameters.band_radius_inside_px.max(1.0),
            auto_keep_fraction: options.auto_keep_fraction as f32,
            shadow_offset_px: options.auto_shadow_offset.to_px(px_size).round() as usize,
            shadow_length_px: (options.auto_shadow_length.to_px(px_size).round() as usize).max(1),
        }
    }
}

/// The propagation over a sequence: the band carried from frame to frame (and from sweep to sweep), and
/// what has been written so far.
pub(super) struct BandPropagation<'a> {
    pub(super) sequence: &'a TrackedSequence,
    pub(super) clip: ClipRect,
    pub(super) propagator: Propagator,
    pub(super) ws: Workspace,
    /// The band carried into the next frame (after a frame: that frame's band).
    pub(super) prior: Vec<bool>,
    pub(super) band: Vec<bool>,
    pub(super) masks: Vec<Vec<u8>>,
    pub(super) warnings: Vec<String>,
    pub(super) initialised_frames: Vec<usize>,
}

impl BandPropagation<'_> {
    /// One frame of the forward pass; `k` is its position in the sweep (0: the initial band, `given`, or
    /// the automatic one).
    pub(super) fn forward(&mut self, k: usize, frame: usize, given: Option<&[bool]>) {
        let (cw, ch) = (self.clip.size_px[0], self.clip.size_px[1]);
        let width = self.sequence.width;
        let p = &self.propagator;
        load_smoothed(&mut self.ws, self.sequence, frame, self.clip, &p.taps);
        let mut needs_auto = false;
        if k == 0 {
            self.ws.reference_strength = 0.0;
            self.initialised_frames.push(frame);
            match given {
                // A later sweep's first frame: the given band joined by the band carried from the
                // previous sweep's last frame (see `InitialBand`).
                Some(b) if self.prior.len() == b.len() => {
                    for (p, &i) in self.prior.iter_mut().zip(b) {
                        *p |= i;
                    }
                }
                Some(b) => self.prior = b.to_vec(),
                None => needs_auto = true,
            }
        }
        if !needs_auto {
            let inside = p.step(&mut self.ws, &self.prior, &mut self.band);
            if k > 0 && inside < p.min_edgels_in_band {
                self.warnings.push(format!(
                    "frame {frame}: band lost ({inside} of {} edgels inside the carried band); \
                     re-initialised automatically",
                    self.ws.edgels.len()
                ));
                self.initialised_frames.push(frame);
                self.ws.reference_strength = 0.0;
                needs_auto = true;
            }
        }
        if needs_auto {
            if p.auto_band(&mut self.ws, &mut self.prior) {
                p.step(&mut self.ws, &self.prior, &mut self.band);
            } else {
                self.warnings.push(format!(
                    "frame {frame}: automatic initialisation found no echo structure; mask left empty"
                ));
                self.band.clear();
                self.band.resize(cw * ch, false);
            }
        }
        if k > 0 && !needs_auto && !self.band.iter().any(|&b| b) {
            self.warnings
                .push(format!("frame {frame}: the band is empty"));
        }
        add_to_mask(&self.band, self.clip, width, &mut self.masks[frame]);
        std::mem::swap(&mut self.prior, &mut self.band);
    }

    /// The backward pass over one sweep, after the forward pass: from its last frame back to its first,
    /// each frame's mask joined by the band carried back from the frame after it. The last frame has a
    /// frame after it only where `carried` (the next sweep's first frame's band) is given; the band
    /// carried on from it is then its forward band joined by what that step kept. Leaves the band of the
    /// sweep's first frame in `prior`, for the sweep before.
    pub(super) fn backward(&mut self, frames: &[(usize, usize)], carried: Option<&[bool]>) {
        let width = self.sequence.width;
        let Some(&(_, last)) = frames.last() else {
            return;
        };
        band_from_mask(&self.masks[last], self.clip, width, &mut self.prior);
        if let Some(carried) = carried {
            let p = &self.propagator;
            load_smoothed(&mut self.ws, self.sequence, last, self.clip, &p.taps);
            if p.step(&mut self.ws, carried, &mut self.band) >= p.min_edgels_in_band {
                add_to_mask(&self.band, self.clip, width, &mut self.masks[last]);
                for (p, &b) in self.prior.iter_mut().zip(&self.band) {
                    *p |= b;
                }
            }
        }
        for &(_, frame) in frames.iter().rev().skip(1) {
            let p = &self.propagator;
            load_smoothed(&mut self.ws, self.sequence, frame, self.clip, &p.taps);
            if p.step(&mut self.ws, &self.prior, &mut self.band) < p.min_edgels_in_band {
                // Lost going back (a frame between two structures): carry on from this frame's
                // forward band.
                band_from_mask(&self.masks[frame], self.clip, width, &mut self.band);
            } else {
                add_to_mask(&self.band, self.clip, width, &mut self.masks[frame]);
            }
            std::mem::swap(&mut self.prior, &mut self.band);
        }
    }
}

/// `out = max(0, s(u, v) - mean of s over rows v+offset .. v+offset+length of the same column)`, zero
/// where the window leaves the image entirely.
pub(super) fn shadow_contrast(
    s: &[f32],
    w: usize,
    h: usize,
    offset: usize,
    length: usize,
    out: &mut Vec<f32>,
) {
    // Column prefix sums, row by row: prefix[v * w + u] = sum of s over rows < v.
    let mut prefix = vec![0f64; (h + 1) * w];
    for v in 0..h {
        for u in 0..w {
            prefix[(v + 1) * w + u] = prefix[v * w + u] + s[v * w + u] as f64;
        }
    }
    out.clear();
    out.resize(w * h, 0.0);
    for v in 0..h {
        let a = (v + offset).min(h);
        let b = (v + offset + length).min(h);
        if b <= a {
            continue;
        }
        let count = (b - a) as f64;
        for u in 0..w {
            let below = (prefix[b * w + u] - prefix[a * w + u]) / count;
            out[v * w + u] = (s[v * w + u] as f64 - below).max(0.0) as f32;
        }
    }
}

/// Loads frame `frame` (cropped to `clip`) into `ws.grey` and its smoothed copy into `ws.smoothed`.
pub(super) fn load_smoothed(
    ws: &mut Workspace,
    sequence: &TrackedSequence,
    frame: usize,
    clip: ClipRect,
    taps: &[f32],
) {
    load_grey_crop(sequence, frame, clip, &mut ws.grey);
    let Workspace {
        grey,
        tmp,
        smoothed,
        ..
    } = ws;
    smooth(grey, clip.size_px[0], clip.size_px[1], taps, tmp, smoothed);
}
