//! What the segmentation takes: its options (the paper's parameters and echosurf's extras), lengths in
//! px or mm, the initial band, and the options resolved to pixels of the frame.

use super::bone;
use super::filters::EdgePolarity;
use crate::io::PoseResolution;
use crate::{Error, Result};

/// A length given in pixels of the frame or in millimetres (converted with the frames' pixel size).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum Length {
    Px(f64),
    Mm(f64),
}

impl Length {
    /// The length in pixels, given the pixel size in mm (only used for [`Length::Mm`]).
    pub fn to_px(self, pixel_size_mm: f64) -> f64 {
        match self {
            Length::Px(px) => px,
            Length::Mm(mm) => mm / pixel_size_mm,
        }
    }
}

/// The paper's segmentation parameters (defaults = the paper's values) and the extras echosurf adds.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SegmentOptions {
    /// Gaussian smoothing before the gradients (speckle suppression). Not a paper parameter; default
    /// 0.5 mm, about the axial resolution (speckle grain) of a 7 MHz probe, so it scales with the pixel
    /// size (6 px on the PLUS spine data, 3.3 px at 0.15 mm/px). Without poses, 1 px = 1 mm.
    pub smoothing_sigma: Length,
    /// M as a fraction of the number of columns (of the clip rectangle), used unless `edgel_count` is set.
    /// The paper only says M is smaller than the number of columns; default 0.75 (with 0.5 the edgels
    /// gather on the flattest, strongest stretches of a curved boundary and its steep flanks fall out of
    /// the band once smoothing has removed the speckle).
    pub edgel_fraction: f64,
    /// M, the number of edgels kept per frame, overriding `edgel_fraction`.
    pub edgel_count: Option<usize>,
    /// Which vertical gradients count. The paper keeps "the M largest vertical intensity gradients"; we
    /// read "largest" on the signed derivative down the column, i.e. [`EdgePolarity::Rising`] (default):
    /// entering a bright echo from the probe side, where the interface facing the probe lies. This gives
    /// one edgel per column crossing of a boundary; `Both` also counts the echo's far side, which halves
    /// how many columns M edgels cover.
    pub edgel_polarity: EdgePolarity,
    /// Beyond the paper: of the M edgels, drop those weaker than this fraction of the strongest (the edgel
    /// ranked at the top 5 %, or 0.8^k times the strongest seen k frames earlier in the sweep, whichever
    /// is larger, so a boundary fading out of view does not hand the band over to speckle). Where a
    /// boundary is in view, speckle edges are much weaker than its echo
    /// and would otherwise fill the rest of the M, spread blobs over the whole band and keep it alive
    /// (the band then percolates through speckle). 0 = the paper's plain M largest. Default 0.35.
    pub min_edgel_relative_strength: f64,
    /// Beyond the paper: edgels chained from column to column with hysteresis, in layers of one edgel per
    /// column (see [`EdgelChaining`]). `None` = the paper's M largest over the whole frame.
    pub edgel_chaining: Option<EdgelChaining>,
    /// Edgels need a vertical gradient above this (grey levels per pixel); 0 keeps any non-flat pixel.
    pub min_edgel_gradient: f64,
    /// Prior inside the carried band, C1 = 1.0.
    pub prior_inside: f64,
    /// Prior outside the carried band, C0 = 0.2 (also the additive term of `P_new`).
    pub prior_outside: f64,
    /// Sigma of the Gaussian proximity weight, 15 px.
    pub likelihood_sigma: Length,
    /// The proximity weight is zero beyond this distance, 32 px.
    pub likelihood_truncation: Length,
    /// Threshold on `P_new` for the next band, T = 0.35.
    pub threshold: f64,
    /// A carried band holding fewer than this fraction of the M edgels has lost the boundary: warn and
    /// re-initialise automatically on that frame. Default 0.02 (at least one edgel).
    pub min_edgels_in_band_fraction: f64,
    /// Smoothing for the automatic initial band (finds echo structures, not edges). Default 6 px.
    pub auto_smoothing_sigma: Length,
    /// Automatic init keeps every bright connected structure whose echo mass is at least this fraction of
    /// the strongest one. Default 0.25.
    pub auto_keep_fraction: f64,
    /// Automatic init scores echoes by their brightness over the mean of the column below them (the
    /// acoustic shadow of a boundary), from this far below... Default 8 px.
    pub auto_shadow_offset: Length,
    /// ...over this length. Default 64 px.
    pub auto_shadow_length: Length,
    /// Shrink the clip rectangle to the part of the frame that holds image data (the bounding box of the
    /// pixels that are non-zero in any of up to 16 sampled frames), so the black margins of a scanner's
    /// frame grab produce no edgels. Default true.
    pub detect_data_region: bool,
    /// Beyond the paper: after each sweep, propagate the band back from its last frame to its first and
    /// keep the union of both passes. The forward pass admits an echo that was not in the carried band
    /// only narrowly on the frame it appears (`C0` gives 11.4 px instead of 29.2 px around its edgels)
    /// and at full width from the next frame on; going back, that frame inherits the full band. Where
    /// the forward pass carries the band from one sweep into the next (a given first band, see
    /// [`InitialBand`]), the backward pass carries it back from the next sweep's first frame into this
    /// sweep's last, so an echo entering on a sweep's last frame (or on the one frame of a sweep that
    /// holds only one) gets the full band too.
    #[serde(default)]
    pub backward_pass: bool,
    /// The paper's step 3 read strictly ("likelihood for pixels in B_i"): edgels outside the carried
    /// band are ignored, so the band follows only the echoes it already holds and a band drawn around
    /// one structure stays on it (the spine's bone instead of the bright tissue under the probe).
    /// Without it, an edgel outside the band keeps 11.4 px around it and, from the next frame, the full
    /// band: every strong echo in the frame joins within two frames. The cost: an echo that comes into
    /// view away from the band is never picked up (the automatic first band on the simulated duck then
    /// misses its far wall). Off by default.
    #[serde(default)]
    pub follow_band: bool,
    /// Beyond the paper: with the automatic first band, a sweep made in contact with tissue whose
    /// frames mostly show bright echoes over an acoustic shadow is segmented as bone
    /// ([`bone`]): the band is the bone's surface, not the tissue layers under the probe.
    #[serde(default)]
    pub bone: bone::BoneMode,
    #[serde(default)]
    pub bone_echoes: bone::BoneEchoOptions,
}

impl Default for SegmentOptions {
    fn default() -> Self {
        SegmentOptions {
            smoothing_sigma: Length::Mm(0.5),
            edgel_fraction: 0.75,
            edgel_count: None,
            edgel_polarity: EdgePolarity::Rising,
            min_edgel_gradient: 0.0,
            min_edgel_relative_strength: 0.35,
            edgel_chaining: None,
            prior_inside: 1.0,
            prior_outside: 0.2,
            likelihood_sigma: Length::Px(15.0),
            likelihood_truncation: Length::Px(32.0),
            threshold: 0.35,
            min_edgels_in_band_fraction: 0.02,
            auto_smoothing_sigma: Length::Px(6.0),
            auto_keep_fraction: 0.25,
            auto_shadow_offset: Length::Px(8.0),
            auto_shadow_length: Length::Px(64.0),
            detect_data_region: true,
            backward_pass: false,
            follow_band: false,
            bone: bone::BoneMode::Auto,
            bone_echoes: bone::BoneEchoOptions::default(),
        }
    }
}

impl SegmentOptions {
    /// The defaults with speckle-robust edgels: [`EdgelChaining`] and 1 mm smoothing (the chains need
    /// edges that are continuous over a few columns; at 0.5 mm the speckle breaks them up). It keeps fewer
    /// pixels and more of the steep, faint surface (docs/decisions/0002-segmentation-beyond-the-paper.md).
    pub fn chained() -> Self {
        SegmentOptions {
            smoothing_sigma: Length::Mm(1.0),
            edgel_chaining: Some(EdgelChaining::default()),
            ..Default::default()
        }
    }

    /// Every echoing wall in a band of fixed width in mm (beyond the paper; CLI `--wall-band`):
    /// [`Self::chained`] edgels in two layers (a wall seen through another), the backward pass, and the
    /// paper's 15 px / 32 px taken at 1/6 mm per pixel (the middle of its 0.1-0.2 mm/px): sigma 2.5 mm,
    /// truncation 5.33 mm. At the simulator's 0.2 mm/px the paper's pixels reach 5.8 mm around each wall
    /// and two walls take 32 % of the duck's pixels; this keeps 99.3-99.6 % of its cavity floor's echoes
    /// and 99.8-100 % of its top wall in 26.2-26.4 % (tests/segment_simulated.rs). At finer pixels it is the
    /// wider band: the PLUS spine sweep (0.082 mm/px) keeps 13.8 % of its pixels, 5.4 % with chained
    /// edgels and the paper's pixels.
    pub fn wall_band() -> Self {
        SegmentOptions {
            likelihood_sigma: Length::Mm(15.0 / 6.0),
            likelihood_truncation: Length::Mm(32.0 / 6.0),
            backward_pass: true,
            ..Self::chained()
        }
    }

    /// Checks ranges; the message names the offending option.
    pub fn validate(&self) -> Result<()> {
        let bad = |name: &str, why: &str| {
            Err(Error::InvalidInput(format!("segment option {name}: {why}")))
        };
        let len_ok = |l: Length| match l {
            Length::Px(x) | Length::Mm(x) => x.is_finite() && x >= 0.0,
        };
        if !len_ok(self.smoothing_sigma) {
            return bad("smoothing_sigma", "must be finite and >= 0");
        }
        if !len_ok(self.auto_smoothing_sigma) {
            return bad("auto_smoothing_sigma", "must be finite and >= 0");
        }
        if !len_ok(self.likelihood_sigma)
            || matches!(self.likelihood_sigma, Length::Px(0.0) | Length::Mm(0.0))
        {
            return bad("likelihood_sigma", "must be finite and > 0");
        }
        if !len_ok(self.auto_shadow_offset) || !len_ok(self.auto_shadow_length) {
            return bad(
                "auto_shadow_offset/auto_shadow_length",
                "must be finite and >= 0",
            );
        }
        if !len_ok(self.likelihood_truncation) {
            return bad("likelihood_truncation", "must be finite and >= 0");
        }
        if !(self.edgel_fraction > 0.0 && self.edgel_fraction.is_finite()) {
            return bad("edgel_fraction", "must be > 0");
        }
        if self.edgel_count == Some(0) {
            return bad("edgel_count", "must be >= 1");
        }
        if !(self.min_edgel_relative_strength.is_finite()
            && self.min_edgel_relative_strength >= 0.0)
        {
            return Err(Error::Options {
                kind: crate::OptionsErrorKind::InvalidInput,
                message: crate::Phrase::new("segment option ")
                    .option(crate::OptionName::MinEdgelRelativeStrength)
                    .text(": must be finite and >= 0"),
            });
        }
        for (name, x) in [
            ("min_edgel_gradient", self.min_edgel_gradient),
            ("prior_inside", self.prior_inside),
            ("prior_outside", self.prior_outside),
            ("threshold", self.threshold),
            (
                "min_edgels_in_band_fraction",
                self.min_edgels_in_band_fraction,
            ),
            ("auto_keep_fraction", self.auto_keep_fraction),
        ] {
            if !(x.is_finite() && x >= 0.0) {
                return bad(name, "must be finite and >= 0");
            }
        }
        if self.prior_inside + self.prior_outside < self.threshold {
            return bad("threshold", "is above C1 + C0: no pixel could ever be kept");
        }
        if self.prior_outside >= self.threshold {
            return bad("prior_outside", "C0 >= T would keep every pixel");
        }
        if self.edgel_chaining.is_some_and(|c| c.layers == 0) {
            return bad("edgel_chaining.layers", "must be >= 1");
        }
        if let Err(why) = self.bone_echoes.validate() {
            return bad("bone_echoes", &why);
        }
        Ok(())
    }
}

/// Speckle-robust edgels (beyond the paper). A boundary crosses a column once, so each column offers
/// its strongest candidate; weak candidates (down to `weak_fraction` of the relative floor) are kept
/// when they continue a chain of edgels in neighbouring columns (rows at most `link_rows` apart) that
/// holds at least one edgel above the floor: the faint, steep flanks of a boundary hang on to its strong
/// echo, while speckle edgels, scattered in depth from column to column, rarely form chains. A second
/// wall seen through the first (a hollow organ's far wall) crosses the same columns again: each of
/// `layers - 1` further layers offers the column's next candidate beyond the band around the edgels kept
/// so far, chained under the same floor.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EdgelChaining {
    pub weak_fraction: f64,
    pub link_rows: usize,
    pub min_chain_length: Length,
    /// How many boundaries a column may cross, each chained on its own (a wall seen through another);
    /// a later one must lie farther from the edgels already kept in its column than the band reaches
    /// around them. 1 = one boundary per column.
    #[serde(default = "one_layer")]
    pub layers: usize,
}

/// What a report written before `layers` existed meant.
fn one_layer() -> usize {
    1
}

impl Default for EdgelChaining {
    fn default() -> Self {
        EdgelChaining {
            weak_fraction: 0.3,
            // 4 rather than 3 (0.8 mm at 0.2 mm/px): the steep flanks' edgels jitter by a row or two
            // around the boundary; sphere within 60 degrees of the beam 98.8 % -> 99.7 %, kept pixels
            // 24.6 % -> 26.5 %, the duck unchanged (tests/segment_simulated.rs).
            link_rows: 4,
            min_chain_length: Length::Mm(3.0),
            // 2: the hollow duck's cavity floor, seen through its top wall, keeps 98-99 % of its echoes
            // instead of 30-34 % (tests/segment_simulated.rs); a third layer finds nothing more there.
            layers: 2,
        }
    }
}

/// The band for the first frame of each sweep. From the second sweep on, a given band (mask or
/// polygon) is joined by the band carried from the previous sweep's last frame: a sweep break is a
/// jump of the probe (> 5 mm) or a pause, often within one pass over the same anatomy, where a band
/// drawn on the first frame alone would cut the boundary short (measured in
/// docs/decisions/0002-segmentation-beyond-the-paper.md); the backward pass carries it back the same
/// way. The automatic band is found afresh.
#[derive(Debug, Clone, PartialEq)]
pub enum InitialBand {
    /// A mask of the frame's size, row-major, true = band.
    Mask {
        width: usize,
        height: usize,
        data: Vec<bool>,
    },
    /// A closed polygon in pixel coordinates (u = column, v = row) of the MF-oriented frame.
    Polygon(Vec<[f64; 2]>),
    /// Found automatically: the strongest connected echo structures, dilated into a band.
    Auto,
}

/// Pixel-unit parameters actually used (after mm -> px conversion), reported for reproducibility.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct ResolvedParameters {
    pub pixel_size_mm: Option<f64>,
    pub smoothing_sigma_px: f64,
    pub likelihood_sigma_px: f64,
    pub likelihood_truncation_px: f64,
    pub edgel_count: usize,
    /// Half-width of the band around an edgel that lay inside the carried band.
    pub band_radius_inside_px: f64,
    /// Radius kept around an edgel outside the carried band.
    pub band_radius_outside_px: f64,
}

/// The pixel size that converts the options' mm lengths: the first pose's, or 1 (px = mm) where no length
/// is in mm or there are no poses.
pub(super) fn pixel_size_for_lengths(
    options: &SegmentOptions,
    poses: &PoseResolution,
    pixel_size_mm: Option<f64>,
) -> Result<f64> {
    let needs_mm = [
        options.smoothing_sigma,
        options.likelihood_sigma,
        options.likelihood_truncation,
        options.auto_smoothing_sigma,
        options
            .edgel_chaining
            .map_or(Length::Px(0.0), |c| c.min_chain_length),
    ]
    .iter()
    .any(|l| matches!(l, Length::Mm(_)));
    match pixel_size_mm {
        Some(s) if s.is_finite() && s > 0.0 => Ok(s),
        _ if needs_mm && !poses.poses.is_empty() => Err(Error::InvalidInput(
            "lengths in mm need a pixel size, but the poses give none".into(),
        )),
        _ => Ok(1.0),
    }
}

/// The options in pixels of the frame; M from the clip rectangle's width.
pub(super) fn resolve_parameters(
    options: &SegmentOptions,
    pixel_size_mm: Option<f64>,
    px_size: f64,
    crop_width: usize,
) -> ResolvedParameters {
    let sigma_px = options.likelihood_sigma.to_px(px_size);
    let truncation_px = options.likelihood_truncation.to_px(px_size);
    let (c0, t) = (options.prior_outside, options.threshold);
    // P(e) G(d) + C0 >= T  <=>  d <= sigma sqrt(2 ln(P(e) / (T - C0))), within the truncation.
    let radius_for = |p: f64| {
        if p <= t - c0 {
            0.0
        } else {
            (sigma_px * (2.0 * (p / (t - c0)).ln()).sqrt()).min(truncation_px)
        }
    };
    ResolvedParameters {
        pixel_size_mm,
        smoothing_sigma_px: options.smoothing_sigma.to_px(px_size),
        likelihood_sigma_px: sigma_px,
        likelihood_truncation_px: truncation_px,
        edgel_count: options.edgel_count.unwrap_or_else(|| {
            ((options.edgel_fraction * crop_width as f64).round() as usize).max(1)
        }),
        band_radius_inside_px: radius_for(options.prior_inside),
        band_radius_outside_px: if options.follow_band {
            0.0
        } else {
            radius_for(c0)
        },
    }
}
