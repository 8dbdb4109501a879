//! One benchmark run: every route on a case, each scored against the truth.

use echosurf::mesh::Mesh;
use echosurf::metrics::{CompareOptions, compare_meshes};
use echosurf::pipeline::{ExtractOptions, Method, Sheet, extract};
use echosurf::progress::Progress;
use echosurf::{Error, Result};

use crate::case::{BenchCase, BenchOptions};
use crate::patches::{MIN_PATCH_AREA_MM2, PatchCoverage, patch_count, patch_coverage, patches_of};
use crate::scoring::{
    FacingSide, PROBE_FACING_DEG, STRONG_ECHO_DEG, SweptFacingScore, SweptFacingTruth,
    facing_within, median_spacing, swept_beam_cosines,
};

/// One route on one case.
#[derive(Debug, Clone, serde::Serialize)]
pub struct RouteResult {
    pub case: String,
    pub route: String,
    pub iso: f64,
    pub triangles: usize,
    pub components: usize,
    /// Connected patches (of at least [`MIN_PATCH_AREA_MM2`]) of the truth within [`STRONG_ECHO_DEG`]
    /// of a sweeping frame's beam: the pieces a surface of the echoing walls can at best come in (the
    /// parts of a wall between them face the beam too steeply to echo). Same for every route of a case.
    pub truth_patches_strong_echo: usize,
    /// How the mesh's pieces lie over those patches.
    pub patch_coverage: PatchCoverage,
    /// MESH -> TRUTH (mm); NaN when the route produced no surface.
    pub accuracy_mean_mm: f64,
    pub accuracy_p95_mm: f64,
    /// Share of the swept, beam-facing truth within 1 mm of the mesh.
    pub completeness_1mm: f64,
    /// The same for truth facing the beam within [`STRONG_ECHO_DEG`] (NaN when there is none).
    pub completeness_strong_echo_1mm: f64,
    /// The truth facing the probe within [`PROBE_FACING_DEG`] of a sweeping beam: completeness and
    /// pieces per patch (`None` when the route produced no surface or no truth faces the probe so).
    pub probe_facing: Option<SweptFacingScore>,
    pub seconds: f64,
    /// Peak resident memory during the route above the resident memory at its start.
    pub peak_extra_bytes: Option<u64>,
    pub error: Option<String>,
}

/// The routes compared, with the sheet each outputs: the RBF route's iso-surface (the paper's and
/// `extract`'s default), its echo-ridge sheet (`--sheet ridge`), and the voxel route.
pub const ROUTES: [(&str, Sheet); 3] = [
    ("rbf", Sheet::Iso),
    ("rbf-ridge", Sheet::EchoRidge),
    ("voxel", Sheet::Iso),
];

/// Runs every route on `case` and scores them; `observer` hears each pipeline stage (and measures its peak memory,
/// if it does: the CLI's does).
pub fn run_case(
    case: &BenchCase,
    options: &BenchOptions,
    observer: &dyn Progress,
) -> Result<Vec<RouteResult>> {
    let plane_distance = median_spacing(&case.true_image_to_world)
        .unwrap_or(1.5)
        .max(1.5);
    let cosines = swept_beam_cosines(
        &case.truth,
        &case.true_image_to_world,
        case.sequence.width,
        case.sequence.height,
        case.calibration.clip,
        plane_distance,
        FacingSide::Either,
    );
    let mask = facing_within(&cosines, 60.0);
    if !mask.iter().any(|&m| m) {
        return Err(Error::InvalidInput(format!(
            "{}: no truth triangle is swept and beam-facing (do the truth and the sequence share a frame?)",
            case.name
        )));
    }
    let strong_mask = facing_within(&cosines, STRONG_ECHO_DEG);
    // No truth facing the probe so is not a failure of a route: that column stays empty.
    let probe_facing = SweptFacingTruth::new(
        &case.truth,
        &case.true_image_to_world,
        case.sequence.width,
        case.sequence.height,
        case.calibration.clip,
        FacingSide::Probe,
        PROBE_FACING_DEG,
    )
    .ok();
    // The patches once per case, for their count and for every route's coverage of them.
    let patches = patches_of(&case.truth, &strong_mask, MIN_PATCH_AREA_MM2);
    let truth_patches = patch_count(&patches);
    let compare = CompareOptions {
        samples_per_mm2: if options.quick { 2.0 } else { 5.0 },
        min_samples: if options.quick { 2_000 } else { 20_000 },
        max_samples: 300_000,
        seed: options.seed,
        truth_mask: Some(mask),
    };
    let compare_strong = strong_mask.iter().any(|&m| m).then(|| CompareOptions {
        truth_mask: Some(strong_mask),
        ..compare.clone()
    });
    let mut results = Vec::new();
    for (route, method, sheet) in ROUTES.map(|(route, sheet)| {
        let method = if route == "voxel" {
            Method::Voxel(options.voxel.clone())
        } else {
            Method::Rbf
        };
        (route, method, sheet)
    }) {
        let extract_options = ExtractOptions {
            method,
            sheet,
            iso: options.iso.clone(),
            max_samples: options.max_samples,
            seed: options.seed,
            ..ExtractOptions::default()
        };
        let baseline = echosurf::resources::current_rss_bytes();
        let start = std::time::Instant::now();
        let outcome = extract(
            &case.sequence,
            Some(&case.calibration),
            &extract_options,
            observer,
        );
        let seconds = start.elapsed().as_secs_f64();
        let mut result = RouteResult {
            case: case.name.clone(),
            route: route.into(),
            iso: f64::NAN,
            triangles: 0,
            components: 0,
            truth_patches_strong_echo: truth_patches,
            patch_coverage: PatchCoverage::default(),
            accuracy_mean_mm: f64::NAN,
            accuracy_p95_mm: f64::NAN,
            completeness_1mm: 0.0,
            completeness_strong_echo_1mm: f64::NAN,
            probe_facing: None,
            seconds,
            peak_extra_bytes: None,
            error: None,
        };
        match outcome {
            Err(e) => result.error = Some(e.to_string()),
            Ok(output) => {
                result.peak_extra_bytes = output
                    .report
                    .peak_rss_bytes
                    .zip(baseline)
                    .map(|(p, b)| p.saturating_sub(b));
                result.iso = output.surfaces.first().map_or(f64::NAN, |s| s.level);
                let mesh = Mesh::merged(output.surfaces.iter().map(|s| &s.mesh));
                result.triangles = mesh.triangles.len();
                if mesh.is_empty() {
                    result.error = Some("no surface".into());
                } else {
                    match compare_meshes(&mesh, &case.truth, &compare) {
                        Ok(c) => {
                            result.components = c.mesh_topology.components;
                            result.accuracy_mean_mm = c.accuracy.mean_mm;
                            result.accuracy_p95_mm = c.accuracy.p95_mm;
                            result.completeness_1mm = c.completeness_1mm;
                        }
                        Err(e) => result.error = Some(e.to_string()),
                    }
                    result.patch_coverage = patch_coverage(&mesh, &patches, MIN_PATCH_AREA_MM2);
                    if let Some(strong) = &compare_strong {
                        match compare_meshes(&mesh, &case.truth, strong) {
                            Ok(c) => result.completeness_strong_echo_1mm = c.completeness_1mm,
                            Err(e) => result.error = Some(e.to_string()),
                        }
                    }
                    result.probe_facing = probe_facing
                        .as_ref()
                        .and_then(|truth| truth.score(&mesh, &case.truth, &compare).ok());
                }
            }
        }
        results.push(result);
    }
    Ok(results)
}
