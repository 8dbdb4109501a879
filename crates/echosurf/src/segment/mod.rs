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
pub mod filters;
mod init;
mod preview;
#[doc(hidden)]
pub mod synthetic;

use std::collections::BTreeSet;

use glam::DMat4;

pub use init::{find_echo_structures, rasterize_polygon};
pub use preview::{default_preview_frames, write_band_preview, write_frame_png};

use crate::io::{ClipRect, PixelData, PoseResolution, TrackedFrame, TrackedSequence};
use crate::progress::Progress;
use crate::{Error, Result};

pub use filters::EdgePolarity;
use filters::{
    Edgel, EdgelSelection, gaussian_taps, smooth, squared_distance_capped, strongest_column_edgels,
};

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
    /// edges that are continuous over a few columns; at 0.5 mm the speckle breaks them up). On simulated
    /// sweeps this halves the kept pixels (sphere: 50.8 % -> 26.5 %) and keeps more of the steep, faint
    /// surface (95.9 % -> 99.7 % within 60 degrees of the beam).
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
/// drawn on the first frame alone would cut the boundary short (simulated duck, one pass of 24 frames
/// that the 5 mm rule splits into six: visible surface within 45 degrees kept 98.1 % -> 99.5 %); the
/// backward pass carries it back the same way. The automatic band is found afresh.
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

/// The kept pixels of every frame of a sequence.
#[derive(Debug, Clone, PartialEq)]
pub struct BandMasks {
    pub width: usize,
    pub height: usize,
    /// One mask per sequence frame, row-major, 255 = kept, 0 = dropped (all 0 for frames without a pose).
    pub masks: Vec<Vec<u8>>,
    /// Lost bands, re-initialisations, frames where nothing was found; each names its frame index.
    pub warnings: Vec<String>,
    /// Sequence frame indices where the band was (re-)initialised: sweep starts and recoveries.
    pub initialised_frames: Vec<usize>,
    /// Frame metadata (poses, timestamps) of the sequence, so the masks can be written as a PLUS file.
    pub frames: Vec<TrackedFrame>,
    /// Orientation written with the masks (MF plus the third letter of the source, if any).
    pub orientation: String,
    pub parameters: ResolvedParameters,
    /// The sweep was segmented as bone ([`bone`]): each band is the bone echo's surface.
    pub bone_sweep: bool,
    /// For a bone sweep, per frame and per column of the full frame, the column's bone echo (row in
    /// the full frame); empty otherwise.
    pub bone_echoes: Vec<Vec<Option<bone::BoneEcho>>>,
}

impl BandMasks {
    /// Number of kept pixels in frame `index`.
    pub fn kept_count(&self, index: usize) -> usize {
        self.masks[index].iter().filter(|&&m| m != 0).count()
    }

    /// Fraction of all pixels of all frames that are kept.
    pub fn kept_fraction(&self) -> f64 {
        let total = self.width * self.height * self.masks.len();
        if total == 0 {
            return 0.0;
        }
        let kept: usize = (0..self.masks.len()).map(|i| self.kept_count(i)).sum();
        kept as f64 / total as f64
    }

    /// The masks as a PLUS sequence (MET_UCHAR, same W x H x N and per-frame fields as the source).
    pub fn to_sequence(&self) -> TrackedSequence {
        let mut pixels = Vec::with_capacity(self.width * self.height * self.masks.len());
        for m in &self.masks {
            pixels.extend_from_slice(m);
        }
        TrackedSequence {
            width: self.width,
            height: self.height,
            channels: 1,
            orientation: self.orientation.clone(),
            frames: self.frames.clone(),
            pixels: PixelData::U8(pixels),
            header: Default::default(),
        }
    }
}

/// Pixel size (mm) of a frame's Image->World matrix: mean length of its first two columns.
fn pixel_size_of(image_to_world: &DMat4) -> f64 {
    0.5 * (image_to_world.x_axis.truncate().length() + image_to_world.y_axis.truncate().length())
}

/// The clip rectangle intersected with the frame; `None` if it leaves nothing.
/// A clip rectangle that reaches beyond the frames is cut to them, and said so: it usually means a
/// calibration made for another image size, whose pixel size and origin are then wrong too.
fn clip_beyond_frame_warning(
    clip: Option<ClipRect>,
    width: usize,
    height: usize,
) -> Option<String> {
    let clip = clip.filter(|c| !c.fits(width, height))?;
    Some(format!(
        "the clip rectangle ({}) reaches beyond the {width} x {height} px frames and is cut to them: \
         is the calibration for this image size?",
        clip.describe()
    ))
}

fn effective_clip(clip: Option<ClipRect>, width: usize, height: usize) -> Option<ClipRect> {
    let c = clip.unwrap_or(ClipRect {
        origin_px: [0, 0],
        size_px: [width, height],
    });
    let u0 = c.origin_px[0].min(width);
    let v0 = c.origin_px[1].min(height);
    let u1 = c.origin_px[0].saturating_add(c.size_px[0]).min(width);
    let v1 = c.origin_px[1].saturating_add(c.size_px[1]).min(height);
    (u1 > u0 && v1 > v0).then_some(ClipRect {
        origin_px: [u0, v0],
        size_px: [u1 - u0, v1 - v0],
    })
}

/// Per-frame working state, reused from frame to frame (no per-frame or per-pixel allocation in the loop
/// once the buffers have their size).
#[derive(Debug, Default)]
struct Workspace {
    grey: Vec<f32>,
    tmp: Vec<f32>,
    smoothed: Vec<f32>,
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
struct Propagator {
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

/// The pixel size that converts the options' mm lengths: the first pose's, or 1 (px = mm) where no length
/// is in mm or there are no poses.
fn pixel_size_for_lengths(
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
fn resolve_parameters(
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

impl Propagator {
    fn new(
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
struct BandPropagation<'a> {
    sequence: &'a TrackedSequence,
    clip: ClipRect,
    propagator: Propagator,
    ws: Workspace,
    /// The band carried into the next frame (after a frame: that frame's band).
    prior: Vec<bool>,
    band: Vec<bool>,
    masks: Vec<Vec<u8>>,
    warnings: Vec<String>,
    initialised_frames: Vec<usize>,
}

impl BandPropagation<'_> {
    /// One frame of the forward pass; `k` is its position in the sweep (0: the initial band, `given`, or
    /// the automatic one).
    fn forward(&mut self, k: usize, frame: usize, given: Option<&[bool]>) {
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
    fn backward(&mut self, frames: &[(usize, usize)], carried: Option<&[bool]>) {
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

/// The bounding box, inside `clip`, of the pixels that are non-zero in any of up to 16 frames spread over
/// the posed frames; `None` if all are zero.
pub fn data_region(
    sequence: &TrackedSequence,
    poses: &PoseResolution,
    clip: ClipRect,
) -> Option<ClipRect> {
    let n = poses.poses.len();
    if n == 0 {
        return Some(clip);
    }
    let picks: BTreeSet<usize> = (0..n.min(16))
        .map(|k| poses.poses[k * n / n.min(16)].frame_index)
        .collect();
    let [u0, v0] = clip.origin_px;
    let [cw, ch] = clip.size_px;
    let (mut umin, mut umax, mut vmin, mut vmax) = (usize::MAX, 0, usize::MAX, 0);
    let mut grey = Vec::new();
    for f in picks {
        load_grey_crop(sequence, f, clip, &mut grey);
        for v in 0..ch {
            let row = &grey[v * cw..(v + 1) * cw];
            if let Some(first) = row.iter().position(|&x| x != 0.0) {
                let last = row.iter().rposition(|&x| x != 0.0).unwrap_or(first);
                umin = umin.min(first);
                umax = umax.max(last);
                vmin = vmin.min(v);
                vmax = vmax.max(v);
            }
        }
    }
    (umin <= umax).then(|| ClipRect {
        origin_px: [u0 + umin, v0 + vmin],
        size_px: [umax - umin + 1, vmax - vmin + 1],
    })
}

/// `out = max(0, s(u, v) - mean of s over rows v+offset .. v+offset+length of the same column)`, zero
/// where the window leaves the image entirely.
fn shadow_contrast(
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

/// Grey levels (channels averaged) of the clip rectangle of frame `index`.
fn load_grey_crop(sequence: &TrackedSequence, index: usize, clip: ClipRect, out: &mut Vec<f32>) {
    let (w, c) = (sequence.width, sequence.channels.max(1));
    let [u0, v0] = clip.origin_px;
    let [cw, ch] = clip.size_px;
    out.clear();
    out.reserve(cw * ch);
    let base = index * sequence.frame_len();
    match (&sequence.pixels, c) {
        (PixelData::U8(data), 1) => {
            for v in v0..v0 + ch {
                let row = base + v * w + u0;
                out.extend(data[row..row + cw].iter().map(|&x| x as f32));
            }
        }
        _ => {
            for v in v0..v0 + ch {
                for u in u0..u0 + cw {
                    out.push(sequence.pixel_f32(index, u, v));
                }
            }
        }
    }
}

fn crop_bool(full: &[bool], width: usize, clip: ClipRect) -> Vec<bool> {
    let [u0, v0] = clip.origin_px;
    let [cw, ch] = clip.size_px;
    let mut out = Vec::with_capacity(cw * ch);
    for v in v0..v0 + ch {
        out.extend_from_slice(&full[v * width + u0..v * width + u0 + cw]);
    }
    out
}

/// Loads frame `frame` (cropped to `clip`) into `ws.grey` and its smoothed copy into `ws.smoothed`.
fn load_smoothed(
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

/// The band a mask keeps, cropped to `clip`.
fn band_from_mask(mask: &[u8], clip: ClipRect, width: usize, band: &mut Vec<bool>) {
    let [u0, v0] = clip.origin_px;
    let [cw, ch] = clip.size_px;
    band.clear();
    for r in 0..ch {
        let row = (v0 + r) * width + u0;
        band.extend(mask[row..row + cw].iter().map(|&m| m != 0));
    }
}

/// Sets to 255 the pixels of `mask` that `band` keeps (a union with what is there: masks start empty,
/// and the backward pass adds to the forward pass's).
fn add_to_mask(band: &[bool], clip: ClipRect, width: usize, mask: &mut [u8]) {
    let [u0, v0] = clip.origin_px;
    let [cw, ch] = clip.size_px;
    for r in 0..ch {
        let dst = &mut mask[(v0 + r) * width + u0..(v0 + r) * width + u0 + cw];
        for (d, &b) in dst.iter_mut().zip(&band[r * cw..(r + 1) * cw]) {
            if b {
                *d = 255;
            }
        }
    }
}

#[cfg(test)]
mod tests;
