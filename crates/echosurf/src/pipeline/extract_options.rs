//! What `extract` runs with ([`ExtractOptions`], built from the two tiers in `options.rs`), the
//! sheet choice, and the defaults the stages share.

use super::{
    ExtractConfig, FitOptions, InitialBand, IntensityLevels, ReferenceChoice, SegmentOptions,
    SheetOptions, SurfaceOptions, VoxelRouteOptions,
};
use crate::segment::crests::CrestOptions;

/// Which route turns the frames into a surface.
#[derive(Debug, Clone, PartialEq, Default)]
pub enum Method {
    /// The paper's direct route: segment -> samples -> RBF fit -> surface.
    #[default]
    Rbf,
    /// The PLUS route: voxel volume of all clipped pixels -> optional Gaussian -> marching cubes.
    Voxel(VoxelRouteOptions),
}

/// Which iso-levels to extract.
#[derive(Debug, Clone, PartialEq)]
pub enum IsoLevels {
    /// One level between the background and boundary echo levels of the kept pixels.
    Auto,
    /// These levels (grey levels of the fitted function), one surface each.
    Levels(Vec<f64>),
}

/// Everything `extract` needs besides the data, as the pipeline reads it; built from the two tiers of
/// [`ExtractConfig`] ([`ExtractConfig::to_extract_options`]). The seed, trust distance and memory
/// budget are the fields here: the pipeline hands them to the fit, the surfacer and the voxel route
/// (`fit.seed` and `surface.trust_distance_mm` are overwritten). `Default` is what the CLI uses
/// without options.
#[derive(Debug, Clone)]
pub struct ExtractOptions {
    pub method: Method,
    pub iso: IsoLevels,
    pub init: InitialBand,
    pub segment: SegmentOptions,
    pub reference: ReferenceChoice,
    /// Random decimation target for the samples handed to the fit (the paper: ~10k keeps large features,
    /// ~100k keeps detail).
    pub max_samples: usize,
    pub seed: u64,
    pub fit: FitOptions,
    pub surface: SurfaceOptions,
    /// Region-of-trust radius in mm; `None` derives it from the frame spacing (see [`trust_distance_for`]).
    pub trust_distance_mm: Option<f64>,
    /// Kept pixels are averaged over blocks of about this size (mm, in the image plane) before random
    /// decimation; 0 uses single pixels.
    pub sample_bin_mm: f64,
    /// Echo-priority thinning: samples within this distance (mm, in the image plane) of a sample at least
    /// as bright as the (lowest) iso-level are all kept when the budget allows, the rest of the budget
    /// going to the others at random (see [`priority_decimate`]). `None`: the paper's uniform random
    /// decimation.
    pub echo_margin_mm: Option<f64>,
    /// First, the echo-ridge sheet's triangles farther than this (mm) from every echo are removed
    /// ([`Mesh::remove_triangles_not_backed`]; an echo is a kept sample block at or above the lowest
    /// level the sheet was drawn at, and reaches out of its frame's plane half the gap to the next
    /// frame, unless that gap is wider than the trust distance: [`echo_reach`]): flaps the fitted field
    /// made in gaps of the data. 0 keeps them; the iso sheet is not checked.
    pub max_echo_distance_mm: f64,
    /// Connected pieces of a surface smaller than this (mm^2) are removed: isolated speckle blobs and
    /// shreds. 0 keeps everything; `None`: the sheet's default ([`Sheet::default_min_component_area_mm2`]),
    /// and at the end the pieces under [`MIN_PIECE_SHARE_OF_LARGEST`] of the largest one.
    pub min_component_area_mm2: Option<f64>,
    /// Pieces of a surface that echoes from fewer than this many frames back are removed (see
    /// [`Mesh::remove_components_seen_in_few_frames`]; an echo is a kept sample block at or above the
    /// surface's level within [`ECHO_SUPPORT_RADIUS_MM`]). 0 keeps every piece.
    pub min_echo_frames: usize,
    /// After the two checks above, pieces whose boundaries pass within this distance (mm) of each
    /// other where they continue one another are joined and the seam between them closed
    /// ([`Mesh::bridge_near_pieces`]). 0 joins nothing.
    pub bridge_gap_mm: f64,
    /// Last, this many rings of triangles are peeled off each piece's rim without cutting or removing
    /// a piece ([`Mesh::trim_rim`]): the rims are the least accurate part of a sheet (where its echo
    /// fades). 0, the default, keeps them: a ring costs completeness where walls turn from the beam
    /// (docs/pipeline.md, "Trimming the rims").
    pub trim_rim_rings: usize,
    /// Which surface to output: the iso-surface itself, or one sheet on each echo's ridge.
    pub sheet: Sheet,
    /// How the echo-ridge sheet is smoothed through the ridge points (`Sheet::EchoRidge` only).
    pub echo_sheet: SheetOptions,
    /// How the echo-ridge sheet is extended by weaker echoes (`Sheet::EchoRidge` only).
    pub weak_echoes: WeakEchoes,
    /// How the echo-ridge sheet is extended by the echo crests of the frames (`Sheet::EchoRidge` only).
    pub image_crests: ImageCrests,
    /// Refuse up front when the estimated memory exceeds this (see [`crate::budget`]); `None`: no check.
    pub memory_budget_bytes: Option<u64>,
}

impl Default for ExtractOptions {
    /// The defaults of [`ExtractConfig`] (where every default lives) with the automatic first band.
    fn default() -> Self {
        ExtractConfig::default().to_extract_options(InitialBand::Auto)
    }
}

impl ExtractOptions {
    /// Smallest piece kept of `sheet` (the sheet actually drawn): the user's, or the sheet's default.
    pub fn min_component_area_for(&self, sheet: Sheet) -> f64 {
        self.min_component_area_mm2
            .unwrap_or(sheet.default_min_component_area_mm2())
    }

    /// The share of the largest piece's area under which a piece is removed: [`MIN_PIECE_SHARE_OF_LARGEST`]
    /// with the default smallest piece, 0 when one is given.
    pub fn min_piece_share_of_largest(&self) -> f64 {
        if self.min_component_area_mm2.is_none() {
            MIN_PIECE_SHARE_OF_LARGEST
        } else {
            0.0
        }
    }
}

/// Hysteresis for the echo-ridge sheet ([`extend_ridge_sheet`]): the ridges of weaker echoes, whose
/// peak passes a lower level but not the iso-level, are added where they continue a strong echo's
/// ridge. They fill the sheet between frames (where the fitted echo's peak sags) and along walls
/// turning from the beam; a weak echo is never taken on its own.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct WeakEchoes {
    /// The lower level lies this fraction of the way from the iso-level down to the background level
    /// (of the kept pixels); 0 turns the extension off.
    pub level_fraction: f64,
    /// How far (mm, along the lower level's ridge sheet) a weak ridge point may lie from a strong one.
    pub reach_mm: f64,
}

impl Default for WeakEchoes {
    /// The lower level 0.3 of the way to the background, reached within 1.5 mm of a strong ridge
    /// (measured in docs/decisions/0004-echo-ridge-sheet.md, "The weaker echoes' defaults").
    fn default() -> Self {
        WeakEchoes {
            level_fraction: 0.3,
            reach_mm: 1.5,
        }
    }
}

impl WeakEchoes {
    /// The lower level for iso-level `level`, or `None` when the extension is off or the background is
    /// unknown or not below `level`.
    pub fn level_below(&self, level: f64, levels: Option<IntensityLevels>) -> Option<f64> {
        let background = levels?.background as f64;
        (self.level_fraction > 0.0 && level > background)
            .then_some(level - self.level_fraction * (level - background))
    }
}

/// The echo-ridge sheet extended by the echo crests found in the frames themselves
/// ([`crate::segment::crests`]): crests linked to the sheet, crest to crest, are drawn into it
/// ([`crate::surface::add_linked_crests`]). The fitted field flattens faint echoes where walls turn
/// from the beam; the frames still show them there. On by default since each crest's normal follows
/// its chain and links run along the wall (docs/decisions/0045-crest-normals-along-the-chain.md; the
/// method in 0044). Never used for bone sweeps, whose band is already the bone echo of each column.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ImageCrests {
    /// Extend the ridge sheet by the frames' crests.
    pub enabled: bool,
    /// Longest step (mm) from one linked crest to the next.
    pub link_mm: f64,
    /// Crests this close (mm) to the sheet start the links; pieces of the redrawn sheet are kept
    /// where they lie this close to it ([`super::CRESTS_MIN_ANCHORED_SHARE`]).
    pub seed_mm: f64,
    /// A crest's normal is tilted out of its frame by the other frames' crests within this distance
    /// (mm); crests with too few crests this near are dropped.
    pub normal_radius_mm: f64,
    /// Which maxima along the beam are crests.
    pub crest: CrestOptions,
}

impl Default for ImageCrests {
    /// On; the lengths measured on both generators and the real sweeps in docs/decisions/0044 and
    /// 0045.
    fn default() -> Self {
        ImageCrests {
            enabled: true,
            link_mm: 0.6,
            seed_mm: 0.75,
            normal_radius_mm: 2.5,
            crest: CrestOptions::default(),
        }
    }
}

/// Smoothing weight `extract` uses unless told otherwise: smooth enough to remove speckle blobs, no
/// smoother than the walls need (measured in docs/decisions/0009-smoothing.md).
pub const DEFAULT_SMOOTHING_MM: f64 = 2.0;

/// Pieces of an iso sheet smaller than this are removed unless told otherwise: speckle blobs
/// (measured in docs/decisions/0015-clean-up-defaults.md).
pub const DEFAULT_MIN_COMPONENT_AREA_MM2: f64 = 5.0;

/// The same for the echo-ridge sheet (measured in docs/decisions/0015-clean-up-defaults.md).
pub const DEFAULT_RIDGE_MIN_COMPONENT_AREA_MM2: f64 = 2.0;

/// Unless a smallest piece is given, pieces under this share of the largest piece's area are removed
/// too: a point scatterer's speck beside an organ (measured in
/// docs/decisions/0048-pieces-relative-to-the-largest.md).
pub const MIN_PIECE_SHARE_OF_LARGEST: f64 = 0.005;

/// The surface `extract` outputs for each level.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub enum Sheet {
    /// The iso-surface `s(x) = k` (the paper's): around a thin echo, a sheath of two sheets, each a few
    /// tenths of a millimetre off the boundary.
    Iso,
    /// One open sheet per echo, on its ridge: the iso-surface's proximal sheet (where the field rises
    /// along the beam) is moved along the beam onto the ridge ([`proximal_sheet_on_ridge`]), which
    /// leaves a mosaic of pieces (the ridge steps from frame to frame where a wall is tilted along the
    /// sweep); a smooth sheet is then drawn through the moved vertices ([`sheet_through_points`],
    /// [`ExtractOptions::echo_sheet`]) and its small holes closed.
    EchoRidge,
    /// Per level, the echo-ridge sheet when the echoes are thin ridges, the iso-surface otherwise: the
    /// ridge sheet is taken when at least [`AUTO_RIDGE_MIN_REACHED_SHARE`] of the iso-surface's proximal
    /// sheet found the field's maximum along the beam within reach ([`RidgeStats::reached_share`]),
    /// and always on a bone sweep (its echoes are one-sided ridges over a shadow).
    Auto,
}

impl Sheet {
    /// Smallest piece kept unless told otherwise (of the sheet actually drawn: `Auto` resolves to one of
    /// the others first).
    pub fn default_min_component_area_mm2(self) -> f64 {
        match self {
            Sheet::Iso | Sheet::Auto => DEFAULT_MIN_COMPONENT_AREA_MM2,
            Sheet::EchoRidge => DEFAULT_RIDGE_MIN_COMPONENT_AREA_MM2,
        }
    }
}

/// `Sheet::Auto` draws the ridge sheet when at least this share of the proximal sheet reached a ridge.
/// It separates the thin-echo recordings from the real spine's ragged sheath (measured in
/// docs/decisions/0007-choosing-the-sheet-per-level.md).
pub const AUTO_RIDGE_MIN_REACHED_SHARE: f64 = 0.8;

/// How many frames' echoes must back a piece of surface by default (see
/// [`ExtractOptions::min_echo_frames`]).
pub const DEFAULT_MIN_ECHO_FRAMES: usize = 3;

/// Default [`ExtractOptions::max_echo_distance_mm`], in the frame's plane and beyond the echoes'
/// reach across it (measured in docs/decisions/0015-clean-up-defaults.md).
pub const DEFAULT_MAX_ECHO_DISTANCE_MM: f64 = 1.5;

/// An echo backs a piece of surface within this distance of one of its vertices: about a speckle cell
/// plus the fit's smoothing, well inside the distance to another wall.
pub const ECHO_SUPPORT_RADIUS_MM: f64 = 1.0;

/// Kept pieces whose boundaries pass within this distance (mm) of each other, facing each other and
/// facing alike, are joined by default (see [`ExtractOptions::bridge_gap_mm`]): the echo-ridge sheet
/// itself bridges gaps of this size between echo points that lie on one plane
/// ([`SheetOptions::bridge_mm`]), so a gap this narrow between two pieces that continue one another
/// is not evidence of two walls (measured in docs/decisions/0015-clean-up-defaults.md).
pub const DEFAULT_BRIDGE_GAP_MM: f64 = 2.0;

/// Echo-priority margin `extract` uses unless told otherwise (see [`ExtractOptions::echo_margin_mm`]).
pub const DEFAULT_ECHO_MARGIN_MM: f64 = 1.0;

/// A sample block is an echo when its grey level is at least this far from the background to the
/// boundary level. Lower (the iso-level, 0.3) also flags the object's own speckle: half the band.
pub const ECHO_LEVEL_FRACTION: f32 = 0.85;

/// Share of the sample budget echo-priority thinning may give to the samples near echoes; the rest
/// pins the background (with all of it there, the fit bulges into spurious surfaces where the
/// background has no samples).
pub const ECHO_BUDGET_SHARE: f64 = 0.5;
