//! The whole route from a tracked sequence to surfaces: segment -> samples -> reduce -> fit -> surface,
//! with defaults derived from the data and a report of what every stage did, how long it took and how
//! much memory it needed. The CLI's `extract`, `sample` and `demo` are thin wrappers around this.

use glam::DVec3;

use crate::io::pose::{
    FramePlane, MIN_SWEEP_SPAN_MM, clip_corners_px, frame_corners, sweep_span_mm,
};
use crate::io::{Calibration, PoseResolution, ReferenceChoice, TrackedSequence, resolve_poses};
use crate::mesh::Mesh;
use crate::progress::Progress;
use crate::rbf::{FitOptions, FitReport, RbfModel};
use crate::resources::{StageMeter, StageUsage};
use crate::samples::{
    IntensityLevels, SampleSet, collect_samples_binned_with_cells, estimate_echo_levels,
    estimate_levels, near_echo_flags, priority_decimate, random_decimate,
};
use crate::segment::{
    BandMasks, InitialBand, ResolvedParameters, SegmentOptions, segment_sequence,
};
use crate::surface::{
    RidgeOptions, SheetOptions, SurfaceDomain, SurfaceOptions, SurfaceStats, WeakRidge,
    extend_ridge_sheet, extract_surfaces_with_stats, proximal_sheet_on_ridge, sheet_through_points,
};
use crate::{Error, Result};
use echo_reach::EchoReach;

mod echo_reach;
mod options;
mod voxel_route;

pub use options::{
    CleanupTuning, ExtractConfig, MethodChoice, OptionError, SamplingTuning, Tuning, UserOptions,
};

pub use voxel_route::{VoxelRouteOptions, VoxelRouteReport, smooth_masked_gaussian};

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
    /// shreds. 0 keeps everything; `None`: the sheet's default ([`Sheet::default_min_component_area_mm2`]).
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

/// Smoothing weight `extract` uses unless told otherwise: smooth enough to remove speckle blobs, no
/// smoother than the walls need (measured in docs/decisions/0009-smoothing.md).
pub const DEFAULT_SMOOTHING_MM: f64 = 2.0;

/// Pieces of an iso sheet smaller than this are removed unless told otherwise: speckle blobs
/// (measured in docs/decisions/0015-clean-up-defaults.md).
pub const DEFAULT_MIN_COMPONENT_AREA_MM2: f64 = 5.0;
/// The same for the echo-ridge sheet (measured in docs/decisions/0015-clean-up-defaults.md).
pub const DEFAULT_RIDGE_MIN_COMPONENT_AREA_MM2: f64 = 2.0;

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

/// The sheet drawn for one iso-level, and why.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SheetUsed {
    pub level: f64,
    /// `Iso` or `EchoRidge`.
    pub sheet: Sheet,
    /// Share of the iso-surface's proximal sheet that reached an echo ridge (`None`: not searched,
    /// `--sheet iso`).
    pub ridge_reached_share: Option<f64>,
    /// The lower level whose ridges extended the ridge sheet ([`WeakEchoes`]); `None`: not extended.
    pub weak_ridge_level: Option<f64>,
    /// Farthest a triangle's vertex may lie from an echo (mm; 0: not checked), and the triangles
    /// removed for it ([`Mesh::remove_triangles_not_backed`]).
    pub max_echo_distance_mm: f64,
    pub triangles_far_from_echoes: usize,
    /// Smallest piece kept (mm^2).
    pub min_component_area_mm2: f64,
    /// Least frames whose echoes must back a piece (0: not checked; at most the frames used), and the
    /// pieces removed for it.
    pub min_echo_frames: usize,
    pub pieces_without_echoes: usize,
    /// Widest gap bridged between kept pieces (mm; 0: not bridged), and the seams made across such
    /// gaps ([`Mesh::bridge_near_pieces`]); each joins two pieces into one.
    pub bridge_gap_mm: f64,
    pub bridged_pieces: usize,
    /// Rings peeled off the rims (0: none), and the triangles that went ([`Mesh::trim_rim`]).
    pub trim_rim_rings: usize,
    pub rim_triangles_trimmed: usize,
}

impl SheetUsed {
    /// The iso-surface at `level`, no ridge searched, nothing removed: where every level starts.
    fn iso_surface(level: f64) -> SheetUsed {
        SheetUsed {
            level,
            sheet: Sheet::Iso,
            ridge_reached_share: None,
            weak_ridge_level: None,
            max_echo_distance_mm: 0.0,
            triangles_far_from_echoes: 0,
            min_component_area_mm2: 0.0,
            min_echo_frames: 0,
            pieces_without_echoes: 0,
            bridge_gap_mm: 0.0,
            bridged_pieces: 0,
            trim_rim_rings: 0,
            rim_triangles_trimmed: 0,
        }
    }
}

/// The beam direction of the frame nearest a point (among frames whose image the point projects into).
struct FrameBeams {
    /// Each frame's plane and unit beam direction (the image's +v axis).
    frames: Vec<(FramePlane, DVec3)>,
    width: f64,
    height: f64,
    max_distance_mm: f64,
}

impl FrameBeams {
    fn new(sequence: &TrackedSequence, poses: &PoseResolution, max_distance_mm: f64) -> Self {
        FrameBeams {
            frames: poses
                .poses
                .iter()
                .filter_map(|p| {
                    let plane = FramePlane::new(p.image_to_world)?;
                    Some((plane, plane.v.try_normalize()?))
                })
                .collect(),
            width: sequence.width.saturating_sub(1) as f64,
            height: sequence.height.saturating_sub(1) as f64,
            max_distance_mm,
        }
    }

    fn beam_at(&self, x: DVec3) -> Option<DVec3> {
        let mut best: Option<(f64, DVec3)> = None;
        for (plane, beam) in &self.frames {
            let [u, v] = plane.pixel_of(x);
            if !(u >= 0.0 && u <= self.width && v >= 0.0 && v <= self.height) {
                continue;
            }
            let distance = x.distance(plane.world_of([u, v]));
            if distance <= self.max_distance_mm && best.is_none_or(|(d, _)| distance < d) {
                best = Some((distance, *beam));
            }
        }
        best.map(|(_, b)| b)
    }
}

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

/// One extracted surface.
#[derive(Debug, Clone)]
pub struct ExtractedSurface {
    pub level: f64,
    pub mesh: Mesh,
}

/// Counts per stage.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct StageCounts {
    pub frames: usize,
    pub frames_used: usize,
    /// Pixels of the frames used.
    pub pixels: usize,
    /// Pixels inside the bands.
    pub kept_pixels: usize,
    /// Samples after block averaging (before decimation).
    pub binned_samples: usize,
    /// Binned samples near an echo (see [`ExtractOptions::echo_margin_mm`]); 0 with uniform thinning.
    pub near_echo_samples: usize,
    /// Samples handed to the fit after thinning.
    pub samples: usize,
    pub centres: usize,
    /// Triangles per surface, in level order.
    pub triangles: Vec<usize>,
    /// The sweep was segmented as bone (`segment::bone`): bands around bone echoes, fitted against
    /// each echo's own contrast.
    pub bone_sweep: bool,
}

/// Parameters actually used, defaults resolved.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct UsedParameters {
    pub iso_levels: Vec<f64>,
    pub iso_auto: bool,
    pub smoothing_mm: f64,
    pub accuracy_grey: f64,
    pub eval_accuracy: f64,
    pub max_samples: usize,
    pub seed: u64,
    pub resolution_mm: f64,
    pub trust_distance_mm: f64,
    pub world_frame: String,
    pub pixel_size_mm: [f64; 2],
    pub median_frame_spacing_mm: Option<f64>,
    pub sample_bin_mm: f64,
    /// `None`: uniform random thinning.
    pub echo_margin_mm: Option<f64>,
    /// As asked; what each level got is in [`ExtractReport::sheets`].
    pub sheet: Sheet,
    /// As asked; `None`: each sheet's default ([`Sheet::default_min_component_area_mm2`]).
    pub min_component_area_mm2: Option<f64>,
    /// `None` when the route did not segment (voxel route with explicit iso-levels).
    pub segment: Option<ResolvedParameters>,
}

/// What `extract` did: the `--report` JSON.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ExtractReport {
    /// `rbf` or `voxel`.
    pub method: String,
    pub parameters: UsedParameters,
    /// Echo levels of the kept pixels (background, boundary, suggested iso).
    pub levels: Option<IntensityLevels>,
    pub counts: StageCounts,
    /// The RBF route's fit and surfacer work (`None` on the voxel route).
    pub fit: Option<FitReport>,
    pub surface: Option<SurfaceStats>,
    /// The sheet drawn for each level.
    pub sheets: Vec<SheetUsed>,
    /// The voxel route's volume and marching cubes (`None` on the RBF route).
    pub voxel: Option<VoxelRouteReport>,
    pub stages: Vec<StageUsage>,
    pub total_seconds: f64,
    pub peak_rss_bytes: Option<u64>,
    pub warnings: Vec<String>,
}

/// Everything `extract` produced.
#[derive(Debug)]
pub struct ExtractOutput {
    pub surfaces: Vec<ExtractedSurface>,
    /// The fitted model (RBF route only).
    pub model: Option<RbfModel>,
    pub samples: SampleSet,
    /// The outline of every used frame's image (or clip rectangle) in the world, for preview overlays.
    pub frame_outlines: Vec<[DVec3; 2]>,
    pub report: ExtractReport,
}

/// The samples of a sequence and what it took to get them (shared by `extract` and `sample`).
#[derive(Debug)]
pub struct PreparedSamples {
    pub poses: PoseResolution,
    pub masks: BandMasks,
    /// All kept pixels as samples.
    pub all: SampleSet,
    /// The decimated set handed to the fit.
    pub samples: SampleSet,
    pub levels: Option<IntensityLevels>,
    pub counts: StageCounts,
    pub pixel_size_mm: [f64; 2],
}

/// The first stage of both routes: refuses a sequence without images and resolves every frame's pose.
pub(crate) fn place_frames(
    sequence: &TrackedSequence,
    calibration: Option<&Calibration>,
    options: &ExtractOptions,
    meter: &mut StageMeter,
) -> Result<PoseResolution> {
    if sequence.is_tracking_only() {
        return Err(Error::InvalidInput(
            "the sequence has no images (tracking only): nothing to extract a surface from".into(),
        ));
    }
    let poses = meter.stage("poses", || {
        resolve_poses(
            sequence,
            calibration,
            options.reference,
            std::path::Path::new("<sequence>"),
        )
    })?;
    let span_mm = sweep_span_mm(sequence.width, sequence.height, &poses.poses);
    if let Some(mm) = span_mm.filter(|&mm| mm < MIN_SWEEP_SPAN_MM) {
        return Err(Error::InvalidInput(format!(
            "all {} placed frames lie within {mm:.2} mm of one plane: the probe was not swept (or its \
             poses do not change), so the frames hold no volume to extract a surface from",
            poses.poses.len()
        )));
    }
    Ok(poses)
}

/// Places the frames, segments the bands and turns kept pixels into (decimated) samples.
pub fn prepare_samples(
    sequence: &TrackedSequence,
    calibration: Option<&Calibration>,
    options: &ExtractOptions,
    meter: &mut StageMeter,
    progress: &dyn Progress,
) -> Result<PreparedSamples> {
    let poses = place_frames(sequence, calibration, options, meter)?;
    let clip = calibration.and_then(|c| c.clip);
    let masks = meter.stage("segment", || {
        segment_sequence(
            sequence,
            &poses,
            clip,
            &options.init,
            &options.segment,
            progress,
        )
    })?;
    prepare_samples_from_masks(sequence, calibration, options, meter, poses, masks)
}

/// [`prepare_samples`] after the segmentation: the kept pixels of `masks` (one per frame of
/// `sequence`) as (decimated) samples. `live` segments frames as they arrive and calls this.
pub fn prepare_samples_from_masks(
    sequence: &TrackedSequence,
    calibration: Option<&Calibration>,
    options: &ExtractOptions,
    meter: &mut StageMeter,
    poses: PoseResolution,
    masks: BandMasks,
) -> Result<PreparedSamples> {
    let pixel_size_mm = calibration
        .map(|c| c.pixel_size_mm())
        .unwrap_or([f64::NAN, f64::NAN]);
    let bin_px = sample_bin_px(options.sample_bin_mm, pixel_size_mm);
    if let Some(budget) = options.memory_budget_bytes {
        let counts = crate::budget::SegmentedCounts {
            frame_pixels: (poses.poses.len() * sequence.width * sequence.height) as u64,
            kept_pixels: poses
                .poses
                .iter()
                .map(|p| masks.kept_count(p.frame_index) as u64)
                .sum(),
            bin_px,
            bone_sweep: masks.bone_sweep,
        };
        crate::budget::check_extract_budget_after_segmentation(
            counts,
            fit_plan(options),
            budget,
            meter.observer(),
        )?;
    }
    // A bone band is fitted against each echo's own contrast (see `segment::bone`).
    let normalised = masks.bone_sweep.then(|| {
        let px = masks.parameters.pixel_size_mm.unwrap_or(1.0);
        let b = &options.segment.bone_echoes;
        let core = [b.band_above_mm, b.band_below_mm].map(|mm| (mm / px).round() as usize);
        crate::segment::bone::contrast_normalised(sequence, &masks.masks, &masks.bone_echoes, core)
    });
    let sampled = normalised.as_ref().unwrap_or(sequence);
    let (all, cells) = meter.stage("samples", || {
        collect_samples_binned_with_cells(sampled, &poses, &masks, bin_px)
    });
    if all.is_empty() {
        return Err(Error::InvalidInput(
            "segmentation kept no pixels: no samples to fit (check the initial band or the clip rectangle)"
                .into(),
        ));
    }
    let levels =
        estimate_echo_levels(sampled, &poses, &masks).or_else(|| estimate_levels(&all.intensities));
    let (samples, near_echo_samples) =
        meter.stage("decimate", || match (options.echo_margin_mm, levels) {
            (Some(margin_mm), Some(l)) if all.len() > options.max_samples => {
                let echo_level = l.background + ECHO_LEVEL_FRACTION * (l.boundary - l.background);
                let radius = echo_margin_cells(margin_mm, bin_px, pixel_size_mm);
                let flags = near_echo_flags(&all, &cells, echo_level, radius);
                let max_flagged = (ECHO_BUDGET_SHARE * options.max_samples as f64) as usize;
                let near = flags.iter().filter(|&&f| f).count();
                let thinned =
                    priority_decimate(&all, &flags, options.max_samples, max_flagged, options.seed);
                (thinned, near)
            }
            _ => (random_decimate(&all, options.max_samples, options.seed), 0),
        });
    let counts = StageCounts {
        frames: sequence.frames.len(),
        frames_used: poses.poses.len(),
        pixels: poses.poses.len() * sequence.width * sequence.height,
        kept_pixels: poses
            .poses
            .iter()
            .map(|p| masks.kept_count(p.frame_index))
            .sum(),
        binned_samples: all.len(),
        near_echo_samples,
        samples: samples.len(),
        bone_sweep: masks.bone_sweep,
        ..Default::default()
    };
    Ok(PreparedSamples {
        poses,
        masks,
        all,
        samples,
        levels,
        counts,
        pixel_size_mm,
    })
}

/// What the memory budget reads of `options` (see [`crate::budget::FitPlan`]).
pub fn fit_plan(options: &ExtractOptions) -> crate::budget::FitPlan<'_> {
    crate::budget::FitPlan {
        max_samples: options.max_samples,
        fit: &options.fit,
    }
}

/// Block size in pixels for [`ExtractOptions::sample_bin_mm`]: the nearest whole number of pixels along
/// each image axis, at least 1 (1 without a known pixel size).
pub fn sample_bin_px(bin_mm: f64, pixel_size_mm: [f64; 2]) -> [usize; 2] {
    pixel_size_mm.map(|p| {
        if bin_mm > 0.0 && p.is_finite() && p > 0.0 {
            ((bin_mm / p).round() as usize).clamp(1, 64)
        } else {
            1
        }
    })
}

/// [`ExtractOptions::echo_margin_mm`] in sample blocks along each image axis (at least 1 block; a
/// 1 mm guess per pixel without a known pixel size).
pub fn echo_margin_cells(
    margin_mm: f64,
    bin_px: [usize; 2],
    pixel_size_mm: [f64; 2],
) -> [usize; 2] {
    [0, 1].map(|a| {
        let block_mm = bin_px[a] as f64 * pixel_size_mm[a];
        let block_mm = if block_mm.is_finite() && block_mm > 0.0 {
            block_mm
        } else {
            bin_px[a] as f64
        };
        ((margin_mm / block_mm).ceil() as usize).clamp(1, 1024)
    })
}

/// Region-of-trust radius from the data: three frame spacings (so the surface bridges the gaps between
/// frames and the missing steep walls between neighbouring echoes), at least 2 mm and at most 10 mm.
pub fn trust_distance_for(median_frame_spacing_mm: Option<f64>) -> f64 {
    match median_frame_spacing_mm {
        Some(s) if s.is_finite() && s > 0.0 => (3.0 * s).clamp(2.0, 10.0),
        _ => 3.0,
    }
}

/// Median distance between the image centres of consecutive used frames.
pub fn median_frame_spacing_mm(sequence: &TrackedSequence, poses: &PoseResolution) -> Option<f64> {
    let centres: Vec<DVec3> = poses
        .poses
        .iter()
        .map(|p| crate::io::pose::image_centre(sequence, p))
        .collect();
    let mut steps: Vec<f64> = centres
        .windows(2)
        .map(|w| w[0].distance(w[1]))
        .filter(|d| d.is_finite() && *d > 1e-6)
        .collect();
    if steps.is_empty() {
        return None;
    }
    steps.sort_by(f64::total_cmp);
    Some(steps[steps.len() / 2])
}

/// Checks requested iso-levels against the range of the fitted data: a level outside it has no surface.
fn check_levels(levels: &[f64], samples: &SampleSet) -> Result<()> {
    let (lo, hi) = samples
        .intensities
        .iter()
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), &x| {
            (a.min(x), b.max(x))
        });
    for &level in levels {
        if !level.is_finite() {
            return Err(Error::InvalidInput(format!(
                "iso-level {level} is not a number"
            )));
        }
        if level <= lo as f64 || level >= hi as f64 {
            return Err(Error::Options {
                kind: crate::OptionsErrorKind::InvalidInput,
                message: crate::Phrase::new(format!(
                    "iso-level {level} is outside the grey levels of the kept pixels ({lo} to {hi}): \
                     it would give no surface; set "
                ))
                .option(crate::OptionName::IsoLevels)
                .text(" to auto or a level in that range"),
            });
        }
    }
    Ok(())
}

/// Seeds for surface-following: samples whose grey level is near some iso-level (they sit close to the
/// surface), spread over the data by a deterministic stride, at most `max` of them.
fn surface_seeds(
    points: &[DVec3],
    values: &[f64],
    levels: &[f64],
    band: f64,
    max: usize,
) -> Vec<DVec3> {
    let near: Vec<DVec3> = points
        .iter()
        .zip(values)
        .filter(|(_, v)| levels.iter().any(|&k| (**v - k).abs() <= band))
        .map(|(p, _)| *p)
        .collect();
    let stride = near.len().div_ceil(max.max(1)).max(1);
    near.into_iter().step_by(stride).collect()
}

/// At most this many seeds start the surface-following. Measured on the simulated duck (100k samples):
/// 5,000 seeds from a band of 0.1 x (boundary - background) around the level give the same completeness
/// (29.7% vs 30.0%) as 20,000, with 16.8 instead of 28.9 field evaluations per triangle (surface 0.45 s
/// instead of 1.26 s); every separate piece of surface still gets seeds because they are spread evenly.
pub const MAX_SURFACE_SEEDS: usize = 5_000;

/// Width of the seed band as a fraction of (boundary - background) echo levels.
pub const SEED_BAND_FRACTION: f64 = 0.1;

/// The surfacer's domain around data points: their box grown by the trust distance, seeds from the
/// points whose value lies within `seed_band` of a level, the points themselves as the region of trust.
pub fn surface_domain(
    points: &[DVec3],
    values: &[f64],
    levels: &[f64],
    seed_band: f64,
    trust_distance_mm: f64,
) -> SurfaceDomain {
    let (lo, hi) = bounds(points);
    let margin = DVec3::splat(trust_distance_mm);
    SurfaceDomain {
        bounds_min_mm: lo - margin,
        bounds_max_mm: hi + margin,
        seeds: surface_seeds(
            points,
            values,
            levels,
            seed_band.max(1.0),
            MAX_SURFACE_SEEDS,
        ),
        trust_points: points.to_vec(),
    }
}

/// Frame outlines (clip rectangle if any, else the image border) as world line segments.
pub fn frame_outlines(
    sequence: &TrackedSequence,
    poses: &PoseResolution,
    calibration: Option<&Calibration>,
) -> Vec<[DVec3; 2]> {
    let clip = calibration
        .and_then(|c| c.clip)
        .and_then(|c| clip_corners_px(sequence.width, sequence.height, &c));
    poses
        .poses
        .iter()
        .flat_map(|p| {
            let corners = match clip {
                Some([u0, v0, u1, v1]) => [(u0, v0), (u1, v0), (u1, v1), (u0, v1)]
                    .map(|(u, v)| p.image_to_world.transform_point3(DVec3::new(u, v, 0.0))),
                None => {
                    // frame_corners lists (0,0), (u,0), (0,v), (u,v): reorder into a cycle.
                    let [a, b, c, d] = frame_corners(sequence, p);
                    [a, b, d, c]
                }
            };
            (0..4).map(move |i| [corners[i], corners[(i + 1) % 4]])
        })
        .collect()
}

/// Fits whose rms data misfit exceeds this fraction of the samples' grey range are implausible.
pub const IMPLAUSIBLE_MISFIT_FRACTION: f64 = 0.1;

/// A warning when the fit's rms data misfit `|f_i - s(x_i)|` is more than
/// [`IMPLAUSIBLE_MISFIT_FRACTION`] of the samples' grey range: the smoothing cannot explain that much,
/// the samples contradict each other where frames cross (a wrong calibration or tracking is the usual
/// reason).
pub fn implausible_fit_warning(report: &crate::rbf::FitReport, values: &[f64]) -> Option<String> {
    let (lo, hi) = values
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
    let range = hi - lo;
    (range > 0.0 && report.rms_data_misfit > IMPLAUSIBLE_MISFIT_FRACTION * range).then(|| {
        format!(
            "the fit misses the samples by {:.1} grey rms (max {:.1}) at smoothing {} mm, more than \
             {:.0} % of their grey range {:.0}-{:.0}: crossing frames disagree, most often because \
             the calibration (or tracking) does not belong to this sweep",
            report.rms_data_misfit,
            report.max_data_misfit,
            report.smoothing,
            100.0 * IMPLAUSIBLE_MISFIT_FRACTION,
            lo,
            hi
        )
    })
}

/// The whole pipeline on an in-memory sequence.
pub fn extract(
    sequence: &TrackedSequence,
    calibration: Option<&Calibration>,
    options: &ExtractOptions,
    progress: &dyn Progress,
) -> Result<ExtractOutput> {
    if let Method::Voxel(route) = &options.method {
        return voxel_route::extract_voxel(sequence, calibration, options, route, progress);
    }
    if let Some(budget) = options.memory_budget_bytes {
        crate::budget::check_extract_budget(sequence, budget, progress)?;
    }
    let mut meter = StageMeter::new(progress);
    let prepared = prepare_samples(sequence, calibration, options, &mut meter, progress)?;
    extract_from_prepared(sequence, calibration, options, meter, prepared, progress)
}

/// [`extract`] on bands segmented elsewhere (`masks`: one per frame of `sequence`, as
/// [`segment_sequence`] makes them): `live` segments each frame once, as it arrives, and refits
/// from here. The RBF route only; no memory budget check.
pub fn extract_with_masks(
    sequence: &TrackedSequence,
    calibration: Option<&Calibration>,
    options: &ExtractOptions,
    masks: BandMasks,
    progress: &dyn Progress,
) -> Result<ExtractOutput> {
    if masks.masks.len() != sequence.frames.len() {
        return Err(Error::InvalidInput(format!(
            "{} band masks for {} frames",
            masks.masks.len(),
            sequence.frames.len()
        )));
    }
    let mut meter = StageMeter::new(progress);
    let poses = place_frames(sequence, calibration, options, &mut meter)?;
    let prepared =
        prepare_samples_from_masks(sequence, calibration, options, &mut meter, poses, masks)?;
    extract_from_prepared(sequence, calibration, options, meter, prepared, progress)
}

/// The RBF route after the samples: fit, surface, sheets and pieces, and the report.
fn extract_from_prepared(
    sequence: &TrackedSequence,
    calibration: Option<&Calibration>,
    options: &ExtractOptions,
    mut meter: StageMeter,
    prepared: PreparedSamples,
    progress: &dyn Progress,
) -> Result<ExtractOutput> {
    let mut warnings = prepared.masks.warnings.clone();

    let (levels, iso_auto) = match &options.iso {
        IsoLevels::Auto => {
            let l = prepared.levels.ok_or_else(|| {
                Error::InvalidInput(
                    "cannot choose an iso-level automatically: the kept pixels all have one grey level".into(),
                )
            })?;
            (vec![l.iso as f64], true)
        }
        IsoLevels::Levels(v) if v.is_empty() => {
            return Err(Error::InvalidInput("no iso-level given".into()));
        }
        IsoLevels::Levels(v) => (v.clone(), false),
    };
    check_levels(&levels, &prepared.samples)?;

    let positions = &prepared.samples.positions;
    let values: Vec<f64> = prepared
        .samples
        .intensities
        .iter()
        .map(|&v| v as f64)
        .collect();
    let (model, fit_report) = meter.stage("fit", || {
        let fit_options = FitOptions {
            seed: options.seed,
            ..options.fit.clone()
        };
        crate::rbf::fit(positions, &values, &fit_options, progress)
    })?;
    if let Some(w) = implausible_fit_warning(&fit_report, &values) {
        warnings.push(w);
    }

    let spacing = median_frame_spacing_mm(sequence, &prepared.poses);
    let trust_distance_mm = options
        .trust_distance_mm
        .unwrap_or_else(|| trust_distance_for(spacing));
    let seed_band = match prepared.levels {
        Some(l) => SEED_BAND_FRACTION * (l.boundary - l.background).abs() as f64,
        None => 10.0,
    };
    let domain = surface_domain(positions, &values, &levels, seed_band, trust_distance_mm);
    let surface_options = SurfaceOptions {
        trust_distance_mm,
        ..options.surface.clone()
    };
    if let Some(budget) = options.memory_budget_bytes {
        crate::budget::check_surface_budget(
            domain.seeds.len() as u64,
            surface_options.resolution_mm,
            budget,
            progress,
        )?;
    }
    let (mut meshes, surface_stats) = meter.stage("surface", || {
        extract_surfaces_with_stats(&model, &levels, &domain, &surface_options)
    })?;
    for l in &surface_stats.levels {
        if l.off_level_vertices > 0 {
            warnings.push(format!(
                "iso-level {}: {} of {} vertices could not be put within {} grey of the level (worst \
                 {:.2}); they are kept and counted in the report (surface.levels.off_level_vertices)",
                l.level,
                l.off_level_vertices,
                l.vertices,
                crate::surface::LEVEL_TOLERANCE,
                l.max_level_error
            ));
        }
    }
    let mut sheets: Vec<SheetUsed> = levels
        .iter()
        .map(|&level| SheetUsed::iso_surface(level))
        .collect();
    if options.sheet != Sheet::Iso {
        let beams = FrameBeams::new(sequence, &prepared.poses, trust_distance_mm);
        let ridge = RidgeInputs {
            model: &model,
            beams: &beams,
            domain: &domain,
            surface_options: &surface_options,
            levels: prepared.levels,
            bone_sweep: prepared.counts.bone_sweep,
        };
        meter.stage("ridge", || {
            move_onto_echo_ridges(&mut meshes, &mut sheets, &ridge, options)
        })?;
    }
    meter.stage("pieces", || {
        remove_and_join_pieces(
            &mut meshes,
            &mut sheets,
            &prepared,
            [sequence.width, sequence.height],
            trust_distance_mm,
            options,
        )
    });
    for (used, mesh) in sheets.iter().zip(&meshes) {
        if mesh.is_empty() && used.pieces_without_echoes > 0 {
            warnings.push(format!(
                "iso-level {}: every piece of surface ({}) was echoed by fewer than {} frames and removed \
                 (tuning.cleanup.min_echo_frames = 0 keeps them)",
                used.level, used.pieces_without_echoes, used.min_echo_frames
            ));
        } else if mesh.is_empty() {
            warnings.push(format!(
                "iso-level {}: no surface found inside the region of trust",
                used.level
            ));
        }
    }

    let mut counts = prepared.counts.clone();
    counts.centres = fit_report.centres;
    counts.triangles = meshes.iter().map(|m| m.triangles.len()).collect();
    let report = ExtractReport {
        method: "rbf".into(),
        parameters: UsedParameters {
            iso_levels: levels.clone(),
            iso_auto,
            smoothing_mm: options.fit.smoothing,
            accuracy_grey: options.fit.accuracy,
            eval_accuracy: options.fit.eval_accuracy,
            max_samples: options.max_samples,
            seed: options.seed,
            resolution_mm: surface_options.resolution_mm,
            trust_distance_mm,
            world_frame: prepared.poses.world_frame.clone(),
            pixel_size_mm: prepared.pixel_size_mm,
            median_frame_spacing_mm: spacing,
            sample_bin_mm: options.sample_bin_mm,
            echo_margin_mm: options.echo_margin_mm,
            sheet: options.sheet,
            min_component_area_mm2: options.min_component_area_mm2,
            segment: Some(prepared.masks.parameters),
        },
        levels: prepared.levels,
        counts,
        fit: Some(fit_report),
        surface: Some(surface_stats),
        sheets,
        voxel: None,
        total_seconds: meter.total_seconds(),
        peak_rss_bytes: meter.peak_rss_bytes(),
        stages: meter.stages,
        warnings,
    };
    let frame_outlines = frame_outlines(sequence, &prepared.poses, calibration);
    Ok(ExtractOutput {
        surfaces: levels
            .into_iter()
            .zip(meshes)
            .map(|(level, mesh)| ExtractedSurface { level, mesh })
            .collect(),
        model: Some(model),
        samples: prepared.samples,
        frame_outlines,
        report,
    })
}

/// What the ridge stage reads: the fitted field, the beam at each point, where the surface may go.
struct RidgeInputs<'a> {
    model: &'a RbfModel,
    beams: &'a FrameBeams,
    domain: &'a SurfaceDomain,
    surface_options: &'a SurfaceOptions,
    levels: Option<IntensityLevels>,
    /// A bone sweep's echoes are one-sided ridges (a shadow below): `Sheet::Auto` draws the ridge sheet.
    bone_sweep: bool,
}

/// Replaces each level's iso-surface by one sheet on its echoes' ridges, extended by the ridges of the
/// weaker echoes that continue them (`--sheet ridge`; with `--sheet auto`, only where enough of the
/// iso-surface's probe side reached a ridge).
fn move_onto_echo_ridges(
    meshes: &mut [Mesh],
    sheets: &mut [SheetUsed],
    inputs: &RidgeInputs,
    options: &ExtractOptions,
) -> Result<()> {
    let beam = |x: DVec3| inputs.beams.beam_at(x);
    for (mesh, used) in meshes.iter_mut().zip(sheets) {
        let (ridge, stats) =
            proximal_sheet_on_ridge(mesh, inputs.model, &beam, &RidgeOptions::default());
        used.ridge_reached_share = Some(stats.reached_share());
        if options.sheet == Sheet::Auto
            && !inputs.bone_sweep
            && stats.reached_share() < AUTO_RIDGE_MIN_REACHED_SHARE
        {
            continue;
        }
        let (mut sheet, _) = sheet_through_points(
            &ridge.vertices,
            &ridge.normals,
            inputs.domain,
            inputs.surface_options,
            &options.echo_sheet,
        )?;
        if let Some(weak_level) = options.weak_echoes.level_below(used.level, inputs.levels) {
            let weak = WeakRidge {
                strong_level: used.level,
                weak_level,
                reach_mm: options.weak_echoes.reach_mm,
                min_seed_area_mm2: options.min_component_area_for(Sheet::EchoRidge),
            };
            sheet = extend_ridge_sheet(
                sheet,
                inputs.model,
                &beam,
                inputs.domain,
                inputs.surface_options,
                &options.echo_sheet,
                &weak,
            )?;
            used.weak_ridge_level = Some(weak_level);
        }
        *mesh = sheet;
        used.sheet = Sheet::EchoRidge;
    }
    Ok(())
}

/// Removes the triangles far from every echo, then small pieces, then pieces too few frames echo, then
/// joins the pieces left that continue one another across small gaps, then (if asked) trims the rims.
fn remove_and_join_pieces(
    meshes: &mut [Mesh],
    sheets: &mut [SheetUsed],
    prepared: &PreparedSamples,
    frame_size_px: [usize; 2],
    trust_distance_mm: f64,
    options: &ExtractOptions,
) {
    for (mesh, used) in meshes.iter_mut().zip(sheets) {
        // The ridge sheet only: it claims to lie on echoes. The iso sheet wraps a thick bright
        // structure where the fitted field stays above the level beyond the kept band (the real spine
        // sweep: a third of its triangles lie farther than 2.5 mm from a kept block that bright).
        if used.sheet == Sheet::EchoRidge
            && options.max_echo_distance_mm.is_finite()
            && options.max_echo_distance_mm > 0.0
        {
            // The weak echoes' ridges extend the sheet: they back it too.
            let (echoes, frames) =
                kept_echoes(prepared, used.weak_ridge_level.unwrap_or(used.level));
            let reach = EchoReach::new(
                &echoes,
                &frames,
                &prepared.poses,
                frame_size_px,
                options.max_echo_distance_mm,
                0.5 * trust_distance_mm,
            );
            used.max_echo_distance_mm = options.max_echo_distance_mm;
            used.triangles_far_from_echoes = mesh.remove_triangles_not_backed(|v| reach.backs(v));
        }
        used.min_component_area_mm2 = options.min_component_area_for(used.sheet);
        if used.min_component_area_mm2 > 0.0 {
            mesh.remove_small_components(used.min_component_area_mm2);
        }
        // A recording of fewer frames cannot show a wall more often than it has frames.
        used.min_echo_frames = options.min_echo_frames.min(prepared.counts.frames_used);
        if used.min_echo_frames > 0 {
            let (echoes, frames) = kept_echoes(prepared, used.level);
            used.pieces_without_echoes = mesh.remove_components_seen_in_few_frames(
                &echoes,
                &frames,
                ECHO_SUPPORT_RADIUS_MM,
                used.min_echo_frames,
            );
        }
        // Only pieces that passed both checks are bridged: a crumb next to a wall stays a crumb.
        if options.bridge_gap_mm.is_finite() && options.bridge_gap_mm > 0.0 {
            used.bridge_gap_mm = options.bridge_gap_mm;
            used.bridged_pieces = mesh.bridge_near_pieces(options.bridge_gap_mm);
        }
        if options.trim_rim_rings > 0 {
            used.trim_rim_rings = options.trim_rim_rings;
            used.rim_triangles_trimmed = mesh.trim_rim(options.trim_rim_rings);
        }
    }
}

/// The kept blocks at or above `level` (positions, and the frame each came from): all of them, not just
/// the fitted samples, so that the checks on a surface do not depend on the sample budget.
fn kept_echoes(prepared: &PreparedSamples, level: f64) -> (Vec<DVec3>, Vec<u32>) {
    let all = &prepared.all;
    all.positions
        .iter()
        .zip(&all.intensities)
        .zip(&all.frame_of_sample)
        .filter(|((_, value), _)| **value as f64 >= level)
        .map(|((&p, _), &f)| (p, f))
        .unzip()
}

fn bounds(points: &[DVec3]) -> (DVec3, DVec3) {
    points.iter().fold(
        (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
        |(lo, hi), p| (lo.min(*p), hi.max(*p)),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_weak_level_lies_between_the_background_and_the_iso_level() {
        let levels = IntensityLevels {
            background: 15.0,
            boundary: 90.0,
            strong_echo: 130.0,
            iso: 37.5,
        };
        let weak = WeakEchoes::default();
        // The demo's duck: 37.5 - 0.3 x (37.5 - 15) = 30.75.
        assert_eq!(weak.level_below(37.5, Some(levels)), Some(30.75));
        // Off, no background known, or a user level at or below the background: no extension.
        let off = WeakEchoes {
            level_fraction: 0.0,
            ..weak.clone()
        };
        assert_eq!(off.level_below(37.5, Some(levels)), None);
        assert_eq!(weak.level_below(37.5, None), None);
        assert_eq!(weak.level_below(15.0, Some(levels)), None);
        assert_eq!(weak.level_below(10.0, Some(levels)), None);
    }
}
