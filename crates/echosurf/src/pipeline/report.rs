//! What `extract` returns: the surfaces and the report of every stage.

use super::{
    DVec3, FitReport, IntensityLevels, Mesh, RbfModel, ResolvedParameters, SampleSet, Sheet,
    StageUsage, SurfaceStats, VoxelRouteReport,
};

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
    /// Echo crests of the frames drawn into the ridge sheet ([`ImageCrests`]); 0: none, or not enabled.
    pub crests_linked: usize,
    /// Farthest a triangle's vertex may lie from an echo (mm; 0: not checked), and the triangles
    /// removed for it ([`Mesh::remove_triangles_not_backed`]).
    pub max_echo_distance_mm: f64,
    pub triangles_far_from_echoes: usize,
    /// Smallest piece kept (mm^2); and as a share of the largest piece (0: not applied), with the
    /// pieces removed for it.
    pub min_component_area_mm2: f64,
    pub min_piece_share_of_largest: f64,
    pub minor_pieces_removed: usize,
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
    pub(super) fn iso_surface(level: f64) -> SheetUsed {
        SheetUsed {
            level,
            sheet: Sheet::Iso,
            ridge_reached_share: None,
            weak_ridge_level: None,
            crests_linked: 0,
            max_echo_distance_mm: 0.0,
            triangles_far_from_echoes: 0,
            min_component_area_mm2: 0.0,
            min_piece_share_of_largest: 0.0,
            minor_pieces_removed: 0,
            min_echo_frames: 0,
            pieces_without_echoes: 0,
            bridge_gap_mm: 0.0,
            bridged_pieces: 0,
            trim_rim_rings: 0,
            rim_triangles_trimmed: 0,
        }
    }
}

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
