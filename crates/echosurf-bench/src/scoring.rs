//! `echosurf bench`: the direct RBF route against the voxel route on the same data, scored against
//! ground truth, and the fit's cost against the number of samples.
//!
//! Scoring ([`score_mesh`]): accuracy = MESH -> TRUTH distances over the whole truth; completeness = share
//! of the *swept, beam-facing* truth within 1 mm of the mesh. A truth triangle counts as swept and
//! beam-facing when its centroid projects inside some frame's (clipped) image within
//! `max(1.5 mm, median frame spacing)` of the image plane, and its normal is within 60 degrees of that
//! frame's beam axis (either sign: the front and back walls of a specular boundary both echo, side walls
//! beyond 60 degrees do not, cos^12 falls to 2e-4 there). No route can be asked to find what was never
//! imaged. A second score counts only the truth within [`STRONG_ECHO_DEG`] (30 degrees) of the beam,
//! where the simulated specular echo is strong (from about 40 degrees on it is below the object's own
//! speckle, so the 60-degree share includes walls no echo shows).

pub mod svg;

use glam::{DMat4, DVec3};

use crate::io::pose::FramePlane;
use crate::io::{Calibration, ClipRect, TrackedSequence, resolve_poses};
use crate::mesh::Mesh;
use crate::metrics::{CompareOptions, compare_meshes, triangle_map};
use crate::pipeline::{ExtractOptions, IsoLevels, Method, Sheet, VoxelRouteOptions, extract};
use crate::progress::{NoProgress, Progress};
use crate::simulate::{PhantomKind, SimulationOptions, TrackingErrors, simulate};
use crate::{Error, Result};

/// Speckle / noise level of a simulated case.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub enum NoiseLevel {
    /// Noise floor 6 dB lower, half the surface roughness, half the tracker noise.
    Low,
    /// The simulator's defaults.
    Default,
    /// Noise floor 8 dB higher, 1.5x roughness, brighter water speckle (+4 dB), 3x tracker noise.
    High,
}

impl NoiseLevel {
    pub const ALL: [NoiseLevel; 3] = [NoiseLevel::Low, NoiseLevel::Default, NoiseLevel::High];

    pub fn name(self) -> &'static str {
        match self {
            NoiseLevel::Low => "low",
            NoiseLevel::Default => "default",
            NoiseLevel::High => "high",
        }
    }

    /// Applies this level to simulation options (acoustics and tracking errors).
    pub fn apply(self, options: &mut SimulationOptions) {
        let defaults = TrackingErrors::default();
        match self {
            NoiseLevel::Default => {}
            NoiseLevel::Low => {
                options.acoustics.noise_db -= 6.0;
                options.acoustics.roughness *= 0.5;
                options.errors.tracker_noise_mm = 0.5 * defaults.tracker_noise_mm;
                options.errors.tracker_noise_deg = 0.5 * defaults.tracker_noise_deg;
            }
            NoiseLevel::High => {
                options.acoustics.noise_db += 8.0;
                options.acoustics.roughness *= 1.5;
                options.acoustics.water.scatter_db += 4.0;
                options.errors.tracker_noise_mm = 3.0 * defaults.tracker_noise_mm;
                options.errors.tracker_noise_deg = 3.0 * defaults.tracker_noise_deg;
            }
        }
    }
}

/// A sequence with its calibration and ground truth.
#[derive(Debug, Clone)]
pub struct BenchCase {
    pub name: String,
    pub sequence: TrackedSequence,
    pub calibration: Calibration,
    /// All true surfaces merged into one mesh.
    pub truth: Mesh,
    /// Where every used frame's image really was (Image -> World), for the completeness mask.
    pub true_image_to_world: Vec<DMat4>,
}

/// Settings of a benchmark run.
#[derive(Debug, Clone)]
pub struct BenchOptions {
    /// Small images and few frames: a CI-sized run.
    pub quick: bool,
    /// Iso-level for both routes; `Auto` = each route's own automatic level.
    pub iso: IsoLevels,
    /// RBF route's decimation target.
    pub max_samples: usize,
    pub voxel: VoxelRouteOptions,
    pub seed: u64,
}

impl Default for BenchOptions {
    fn default() -> Self {
        BenchOptions {
            quick: false,
            iso: IsoLevels::Auto,
            max_samples: 100_000,
            voxel: VoxelRouteOptions::default(),
            seed: 1,
        }
    }
}

/// Simulation settings of a benchmark phantom: the simulator's defaults, or in quick mode 128 x 100 px
/// at 0.4 mm and 20 frames per sweep.
pub fn simulation_options(
    phantom: PhantomKind,
    noise: NoiseLevel,
    quick: bool,
    seed: u64,
) -> SimulationOptions {
    let mut options = SimulationOptions {
        phantom,
        seed,
        ..SimulationOptions::default()
    };
    if quick {
        options.frames_per_sweep = 20;
        options.width_px = 128;
        options.height_px = 100;
        options.pixel_size_mm = 0.4;
        options.truth_resolution_mm = 1.0;
    }
    noise.apply(&mut options);
    options
}

/// Simulates one benchmark case.
pub fn simulated_case(
    phantom: PhantomKind,
    noise: NoiseLevel,
    quick: bool,
    seed: u64,
) -> Result<BenchCase> {
    let name = format!("{} / {}", phantom.name(), noise.name());
    let options = simulation_options(phantom, noise, quick, seed);
    let sim = simulate(&options, &NoProgress)?;
    Ok(BenchCase {
        name,
        sequence: sim.sequence,
        calibration: sim.calibration_written,
        truth: crate::simulate::merged_truth(&sim.truth),
        true_image_to_world: sim.true_image_to_world,
    })
}

/// A user case: the recorded poses stand in for the true ones in the completeness mask.
pub fn user_case(
    name: String,
    sequence: TrackedSequence,
    calibration: Calibration,
    truth: Mesh,
) -> Result<BenchCase> {
    let poses = resolve_poses(
        &sequence,
        Some(&calibration),
        crate::io::ReferenceChoice::Auto,
        std::path::Path::new(&name),
    )?;
    let true_image_to_world = poses.poses.iter().map(|p| p.image_to_world).collect();
    Ok(BenchCase {
        name,
        sequence,
        calibration,
        truth,
        true_image_to_world,
    })
}

/// Swept, beam-facing truth triangles (see the module docs), `side` facing the beam within
/// `max_angle_deg`. The beam runs along the image's +v axis.
#[allow(clippy::too_many_arguments)]
pub fn swept_beam_facing_mask(
    truth: &Mesh,
    image_to_world: &[DMat4],
    width: usize,
    height: usize,
    clip: Option<ClipRect>,
    max_plane_distance_mm: f64,
    side: FacingSide,
    max_angle_deg: f64,
) -> Vec<bool> {
    let cosines = swept_beam_cosines(
        truth,
        image_to_world,
        width,
        height,
        clip,
        max_plane_distance_mm,
        side,
    );
    facing_within(&cosines, max_angle_deg)
}

/// Which side of a wall counts as facing the beam.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum FacingSide {
    /// Either side: the wall's normal along or against the beam (a specular boundary echoes from
    /// both sides where the beam reaches it).
    Either,
    /// The side facing the probe: the outward normal against the beam (needs outward normals, as on a
    /// closed truth mesh).
    Probe,
}

/// Area share (0..=1) of the mesh's largest edge-connected piece: how dominant one sheet is. `None` for
/// a mesh without area.
pub fn largest_piece_area_share(mesh: &Mesh) -> Option<f64> {
    let n = mesh.vertices.len();
    let component = mesh.triangle_components();
    let mut area = vec![0.0f64; mesh.triangles.len()];
    for (f, t) in mesh.triangles.iter().enumerate() {
        if t.iter().all(|&i| (i as usize) < n) {
            area[component[f]] += mesh.triangle_area_mm2(*t);
        }
    }
    let total: f64 = area.iter().sum();
    let largest = area.iter().copied().fold(0.0, f64::max);
    (total > 0.0).then(|| largest / total)
}

/// Per truth triangle, the largest |cos| between its normal and the beam of a frame that sweeps it (its
/// centroid projects into the frame's clipped image within `max_plane_distance_mm` of the plane);
/// `-inf` where no frame does. With [`FacingSide::Probe`], the largest `-cos` instead (the outward
/// normal against the beam), so a wall seen only from behind scores below zero. One pass over the
/// frames serves every angle ([`facing_within`]).
pub fn swept_beam_cosines(
    truth: &Mesh,
    image_to_world: &[DMat4],
    width: usize,
    height: usize,
    clip: Option<ClipRect>,
    max_plane_distance_mm: f64,
    side: FacingSide,
) -> Vec<f64> {
    let (u0, v0, u1, v1) =
        match clip.and_then(|c| crate::io::pose::clip_corners_px(width, height, &c)) {
            Some([a, b, c, d]) => (a, b, c, d),
            None => (0.0, 0.0, width as f64 - 1.0, height as f64 - 1.0),
        };
    // Per frame: its plane and the unit beam direction.
    let frames: Vec<(FramePlane, DVec3)> = image_to_world
        .iter()
        .filter_map(|&m| {
            let plane = FramePlane::new(m)?;
            Some((plane, plane.v.try_normalize()?))
        })
        .collect();
    triangle_map(truth, f64::NEG_INFINITY, |centroid, triangle_normal| {
        if !triangle_normal.is_finite() {
            return f64::NEG_INFINITY;
        }
        frames
            .iter()
            .filter(|(plane, _)| {
                let [u, v] = plane.pixel_of(centroid);
                if !(u >= u0 && u <= u1 && v >= v0 && v <= v1) {
                    return false;
                }
                (centroid - plane.world_of([u, v])).dot(plane.normal).abs() <= max_plane_distance_mm
            })
            .map(|(_, beam)| {
                let cos = triangle_normal.dot(*beam);
                match side {
                    FacingSide::Either => cos.abs(),
                    FacingSide::Probe => -cos,
                }
            })
            .fold(f64::NEG_INFINITY, f64::max)
    })
}

/// The triangles of [`swept_beam_cosines`] facing a sweeping frame's beam within `max_angle_deg`.
pub fn facing_within(cosines: &[f64], max_angle_deg: f64) -> Vec<bool> {
    let cos_limit = max_angle_deg.to_radians().cos();
    cosines.iter().map(|&c| c >= cos_limit).collect()
}

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

/// Median distance between the origins of consecutive frames.
pub fn median_spacing(frames: &[DMat4]) -> Option<f64> {
    let mut d: Vec<f64> = frames
        .windows(2)
        .map(|w| w[0].w_axis.truncate().distance(w[1].w_axis.truncate()))
        .filter(|d| d.is_finite() && *d > 1e-6)
        .collect();
    d.sort_by(f64::total_cmp);
    d.get(d.len() / 2).copied()
}

/// Walls within this angle of the beam return a strong specular echo in the simulator (cos^12: at least
/// 18 % of normal incidence); the benchmark also scores completeness on them alone.
pub const STRONG_ECHO_DEG: f64 = 30.0;

/// The benchmark also scores the truth whose outward side faces the probe within this angle of a
/// sweeping beam ([`FacingSide::Probe`]): the walls every sweep shows with a strong echo from the
/// side the sound arrives at (the far side of a solid object lies in its shadow). 20 degrees is where
/// the simulator's specular echo (cos^12) is still half of normal incidence, the usual -6 dB edge
/// (cos^12 of 20 degrees = 0.47, -6.5 dB; of 25 degrees 0.31, of 30 degrees 0.18): the pipeline
/// issue's "beam-facing truth", which names no angle, is read here.
pub const PROBE_FACING_DEG: f64 = 20.0;

/// Truth patches smaller than this (mm^2) are not counted in [`RouteResult::truth_patches_strong_echo`]
/// (slivers where a wall's angle to the beam hovers around the limit); the ridge sheet's default
/// smallest piece.
pub const MIN_PATCH_AREA_MM2: f64 = crate::pipeline::DEFAULT_RIDGE_MIN_COMPONENT_AREA_MM2;

/// The triangles of `mesh` flagged in `mask`, without the connected patches smaller than
/// `min_area_mm2`.
pub fn patches_of(mesh: &Mesh, mask: &[bool], min_area_mm2: f64) -> Mesh {
    let mut patches = mesh.clone();
    patches.retain_triangles(mask);
    patches.remove_small_components(min_area_mm2);
    patches
}

/// Connected pieces of `patches` (from [`patches_of`]).
pub fn patch_count(patches: &Mesh) -> usize {
    if patches.is_empty() {
        0
    } else {
        patches.topology().components
    }
}

/// How a surface's pieces lie over the truth's patches (those of [`patches_of`]): a patch is whole
/// when exactly one piece of the mesh comes within 1 mm of at least `min_area_mm2` of it, split when two
/// or more do, missed when none does. This is the pipeline issue's "at most one mesh component per true
/// wall", read per echoing patch of a wall.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct PatchCoverage {
    pub whole: usize,
    pub split: usize,
    pub missed: usize,
}

/// [`PatchCoverage`] of `mesh` over `patches` (from [`patches_of`] with the same `min_area_mm2`). Each
/// truth triangle's area goes to the piece holding the mesh triangle nearest its centroid (within 1 mm).
pub fn patch_coverage(mesh: &Mesh, patches: &Mesh, min_area_mm2: f64) -> PatchCoverage {
    patch_details(mesh, patches, min_area_mm2).0
}

/// One truth patch and the mesh's pieces over it (see [`PatchCoverage`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct PatchDetail {
    pub area_mm2: f64,
    /// Area-weighted centroid of the patch (mm, the truth's frame).
    pub centroid_mm: [f64; 3],
    /// Area of the patch farther than 1 mm from every piece.
    pub missed_mm2: f64,
    /// The pieces within 1 mm of it, largest share first: (piece, area of the patch it covers). A piece
    /// is numbered by its first triangle in the mesh, from 0.
    pub pieces: Vec<(usize, f64)>,
    /// Pieces covering at least the smallest patch area: 0 missed, 1 whole, more split.
    pub counted_pieces: usize,
}

/// [`patch_coverage`] with the detail of every patch, in the order of the patches' first triangles.
pub fn patch_details(
    mesh: &Mesh,
    patches: &Mesh,
    min_area_mm2: f64,
) -> (PatchCoverage, Vec<PatchDetail>) {
    use rayon::prelude::*;
    let dense = |components: Vec<usize>| -> Vec<usize> {
        let mut number = std::collections::BTreeMap::new();
        components
            .iter()
            .map(|&c| {
                let next = number.len();
                *number.entry(c).or_insert(next)
            })
            .collect()
    };
    let patch_of = dense(patches.triangle_components());
    let piece_of = dense(mesh.triangle_components());
    let bvh = crate::metrics::TriangleBvh::new(mesh);
    let nearest_piece: Vec<Option<usize>> = patches
        .triangles
        .par_iter()
        .map(|t| {
            let [a, b, c] = t.map(|i| patches.vertices[i as usize]);
            bvh.nearest((a + b + c) / 3.0)
                .filter(|n| n.distance_mm <= 1.0)
                .map(|n| piece_of[n.triangle as usize])
        })
        .collect();
    let count = patch_of.iter().max().map_or(0, |&m| m + 1);
    let mut details = vec![
        PatchDetail {
            area_mm2: 0.0,
            centroid_mm: [0.0; 3],
            missed_mm2: 0.0,
            pieces: Vec::new(),
            counted_pieces: 0,
        };
        count
    ];
    let mut weighted_centre = vec![DVec3::ZERO; count];
    // Covered area per (patch, piece), in a sorted map so the result does not depend on hashing.
    let mut covered: std::collections::BTreeMap<(usize, usize), f64> = Default::default();
    for (f, piece) in nearest_piece.iter().enumerate() {
        let t = patches.triangles[f];
        let area = patches.triangle_area_mm2(t);
        let patch = patch_of[f];
        details[patch].area_mm2 += area;
        weighted_centre[patch] += area
            * t.map(|i| patches.vertices[i as usize])
                .iter()
                .sum::<DVec3>()
            / 3.0;
        match piece {
            Some(piece) => *covered.entry((patch, *piece)).or_default() += area,
            None => details[patch].missed_mm2 += area,
        }
    }
    for (&(patch, piece), &area) in &covered {
        details[patch].pieces.push((piece, area));
        if area >= min_area_mm2 {
            details[patch].counted_pieces += 1;
        }
    }
    let mut coverage = PatchCoverage::default();
    for (detail, centre) in details.iter_mut().zip(weighted_centre) {
        detail
            .pieces
            .sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
        if detail.area_mm2 > 0.0 {
            detail.centroid_mm = (centre / detail.area_mm2).to_array();
        }
        match detail.counted_pieces {
            0 => coverage.missed += 1,
            1 => coverage.whole += 1,
            _ => coverage.split += 1,
        }
    }
    (coverage, details)
}

/// The swept truth that faces the beam within an angle, and how a mesh covers it: completeness within
/// 1 mm and the mesh's pieces per echoing patch ([`PatchCoverage`]). For any sweep whose truth lies in
/// the same world frame as its poses (`compare --sequence`), from [`SweptFacingTruth::score`].
#[derive(Debug, Clone, serde::Serialize)]
pub struct SweptFacingScore {
    pub max_angle_deg: f64,
    pub side: FacingSide,
    /// A truth triangle counts as swept within this distance of a frame's plane: the median frame
    /// spacing, at least 1.5 mm (as the benchmark).
    pub plane_distance_mm: f64,
    pub truth_area_mm2: f64,
    pub completeness_1mm: f64,
    /// Connected patches (at least [`MIN_PATCH_AREA_MM2`]) of that truth.
    pub truth_patches: usize,
    pub patch_coverage: PatchCoverage,
    /// Each patch and the pieces over it.
    pub patches: Vec<PatchDetail>,
}

/// The part of a truth that the frames sweep and whose chosen side faces their beam within an angle,
/// with its patches: found once per sweep and truth, then [`SweptFacingTruth::score`] for each mesh.
#[derive(Debug, Clone)]
pub struct SweptFacingTruth {
    max_angle_deg: f64,
    side: FacingSide,
    plane_distance_mm: f64,
    mask: Vec<bool>,
    patches: Mesh,
}

impl SweptFacingTruth {
    /// The triangles of `truth` that the frames `image_to_world` (of `width` x `height` px, `clip`ped)
    /// sweep and whose `side` faces their beam within `max_angle_deg`; an error if there are none.
    pub fn new(
        truth: &Mesh,
        image_to_world: &[DMat4],
        width: usize,
        height: usize,
        clip: Option<ClipRect>,
        side: FacingSide,
        max_angle_deg: f64,
    ) -> Result<SweptFacingTruth> {
        if !(max_angle_deg > 0.0 && max_angle_deg <= 90.0) {
            return Err(Error::InvalidInput(format!(
                "facing angle must be in (0, 90] degrees, got {max_angle_deg}"
            )));
        }
        let plane_distance_mm = median_spacing(image_to_world).unwrap_or(1.5).max(1.5);
        let mask = swept_beam_facing_mask(
            truth,
            image_to_world,
            width,
            height,
            clip,
            plane_distance_mm,
            side,
            max_angle_deg,
        );
        if !mask.iter().any(|&m| m) {
            return Err(Error::InvalidInput(format!(
                "no truth triangle is swept by a frame and faces its beam within {max_angle_deg} \
                 degrees (do the truth and the sequence share a world frame?)"
            )));
        }
        let patches = patches_of(truth, &mask, MIN_PATCH_AREA_MM2);
        Ok(SweptFacingTruth {
            max_angle_deg,
            side,
            plane_distance_mm,
            mask,
            patches,
        })
    }

    /// How `mesh` covers this part of `truth` (the mesh the selection was made of).
    pub fn score(
        &self,
        mesh: &Mesh,
        truth: &Mesh,
        compare: &CompareOptions,
    ) -> Result<SweptFacingScore> {
        let comparison = compare_meshes(
            mesh,
            truth,
            &CompareOptions {
                truth_mask: Some(self.mask.clone()),
                ..compare.clone()
            },
        )?;
        let (patch_coverage, patches) = patch_details(mesh, &self.patches, MIN_PATCH_AREA_MM2);
        Ok(SweptFacingScore {
            max_angle_deg: self.max_angle_deg,
            side: self.side,
            plane_distance_mm: self.plane_distance_mm,
            truth_area_mm2: comparison.truth_compared_area_mm2,
            completeness_1mm: comparison.completeness_1mm,
            truth_patches: patch_count(&self.patches),
            patch_coverage,
            patches,
        })
    }
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
        let baseline = crate::resources::current_rss_bytes();
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

fn mb(bytes: Option<u64>) -> String {
    bytes.map_or_else(|| "n/a".into(), |b| format!("{:.0}", b as f64 / 1e6))
}

/// The results as a markdown table, one row per case and route.
pub fn markdown_table(results: &[RouteResult]) -> String {
    let mut out = String::from(
        "| case | route | iso | accuracy mean (mm) | accuracy p95 (mm) | completeness (1 mm) | completeness, <= 30 deg (1 mm) | components | truth patches, <= 30 deg | patches whole / split / missed | probe side <= 20 deg: completeness; patches whole / split / missed of n | triangles | time (s) | peak extra memory (MB) |\n\
         |---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n",
    );
    for r in results {
        let note = r
            .error
            .as_deref()
            .map(|e| format!(" ({e})"))
            .unwrap_or_default();
        out.push_str(&format!(
            "| {} | {}{} | {:.1} | {:.2} | {:.2} | {:.1} % | {:.1} % | {} | {} | {} / {} / {} | {} | {} | {:.2} | {} |\n",
            r.case,
            r.route,
            note,
            r.iso,
            r.accuracy_mean_mm,
            r.accuracy_p95_mm,
            100.0 * r.completeness_1mm,
            100.0 * r.completeness_strong_echo_1mm,
            r.components,
            r.truth_patches_strong_echo,
            r.patch_coverage.whole,
            r.patch_coverage.split,
            r.patch_coverage.missed,
            r.probe_facing.as_ref().map_or_else(
                || "n/a".to_string(),
                |p| format!(
                    "{:.1} %; {} / {} / {} of {}",
                    100.0 * p.completeness_1mm,
                    p.patch_coverage.whole,
                    p.patch_coverage.split,
                    p.patch_coverage.missed,
                    p.truth_patches
                )
            ),
            r.triangles,
            r.seconds,
            mb(r.peak_extra_bytes),
        ));
    }
    out
}

/// Accuracy (mean, mm) against time (s), one series per route.
pub fn accuracy_vs_time_plot(results: &[RouteResult]) -> svg::Plot {
    let series = ROUTES
        .iter()
        .map(|(route, _)| route)
        .map(|route| svg::Series {
            name: format!("{route} route"),
            points: results
                .iter()
                .filter(|r| r.route == *route)
                .map(|r| (r.seconds, r.accuracy_mean_mm))
                .collect(),
            connect: false,
        })
        .collect();
    svg::Plot {
        title: "Accuracy against time, all cases".into(),
        x_label: "time (s, log)".into(),
        y_label: "mean distance mesh -> truth (mm)".into(),
        x_log: true,
        y_log: false,
        series,
    }
}

/// Fit time against the number of samples, log-log.
pub fn fit_scaling_plot(rows: &[crate::rbf::ScalingRow]) -> svg::Plot {
    svg::Plot {
        title: "RBF fit time against samples (ultrasound-like data)".into(),
        x_label: "samples".into(),
        y_label: "seconds".into(),
        x_log: true,
        y_log: true,
        series: vec![
            svg::Series {
                name: "fit".into(),
                points: rows
                    .iter()
                    .map(|r| (r.samples as f64, r.fit_seconds))
                    .collect(),
                connect: true,
            },
            svg::Series {
                name: "evaluate N points".into(),
                points: rows
                    .iter()
                    .map(|r| (r.samples as f64, r.eval_seconds))
                    .collect(),
                connect: true,
            },
        ],
    }
}

/// The sample counts of the fit-scaling run up to `max` (1k, 3k, 10k, 30k, 100k, ...).
pub fn fit_sizes(max: usize) -> Vec<usize> {
    let mut sizes = Vec::new();
    let mut decade = 1_000usize;
    while decade <= max {
        sizes.push(decade);
        if 3 * decade <= max {
            sizes.push(3 * decade);
        }
        decade = match decade.checked_mul(10) {
            Some(d) => d,
            None => break,
        };
    }
    sizes
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::metrics::shapes::icosphere;

    /// `nx` x `ny` unit squares in the plane z = `z`, from (`x0`, 0).
    fn squares(x0: f64, z: f64, nx: u32, ny: u32) -> Mesh {
        let mut mesh = Mesh::default();
        for j in 0..=ny {
            for i in 0..=nx {
                mesh.vertices.push(DVec3::new(x0 + i as f64, j as f64, z));
            }
        }
        let at = |i: u32, j: u32| j * (nx + 1) + i;
        for j in 0..ny {
            for i in 0..nx {
                mesh.triangles
                    .push([at(i, j), at(i + 1, j), at(i + 1, j + 1)]);
                mesh.triangles
                    .push([at(i, j), at(i + 1, j + 1), at(i, j + 1)]);
            }
        }
        mesh
    }

    #[test]
    fn largest_piece_share_of_two_squares() {
        // Two separate unit-area squares scaled 1 and 2: areas 1 and 4 mm^2, share 4 / 5.
        let square = |x0: f64, size: f64, base: u32| {
            let v = vec![
                DVec3::new(x0, 0.0, 0.0),
                DVec3::new(x0 + size, 0.0, 0.0),
                DVec3::new(x0 + size, size, 0.0),
                DVec3::new(x0, size, 0.0),
            ];
            let t = vec![[base, base + 1, base + 2], [base, base + 2, base + 3]];
            (v, t)
        };
        let (mut vertices, mut triangles) = square(0.0, 1.0, 0);
        let (v2, t2) = square(5.0, 2.0, 4);
        vertices.extend(v2);
        triangles.extend(t2);
        let mesh = Mesh {
            vertices,
            triangles,
            ..Default::default()
        };
        let share = largest_piece_area_share(&mesh).unwrap();
        assert!((share - 0.8).abs() < 1e-12, "{share}");
        assert_eq!(largest_piece_area_share(&Mesh::default()), None);
    }

    #[test]
    fn patch_coverage_counts_the_pieces_over_each_patch() {
        // Three 4 x 4 mm patches of truth.
        let truth = Mesh::merged([
            &squares(0.0, 0.0, 4, 4),
            &squares(10.0, 0.0, 4, 4),
            &squares(20.0, 0.0, 4, 4),
        ]);
        let all = vec![true; truth.triangles.len()];
        // The first patch under one piece (0.5 mm above it) and a 1 mm^2 crumb (0.45 mm above it: nearest
        // only to the 1 mm^2 of truth under it, too little to count);
        // the second under two pieces of 2 x 4 mm; the third under nothing within 1 mm (2 mm above).
        let mesh = Mesh::merged([
            &squares(0.0, 0.5, 4, 4),
            &squares(0.0, 0.45, 1, 1),
            &squares(10.0, 0.5, 2, 4),
            &squares(12.0, 0.5, 2, 4),
            &squares(20.0, 2.0, 4, 4),
        ]);
        let (coverage, details) = patch_details(&mesh, &patches_of(&truth, &all, 2.0), 2.0);
        assert_eq!(
            coverage,
            PatchCoverage {
                whole: 1,
                split: 1,
                missed: 1
            }
        );
        assert_eq!(
            coverage,
            patch_coverage(&mesh, &patches_of(&truth, &all, 2.0), 2.0)
        );
        // Per patch: area, centre, the pieces over it (largest share first; pieces numbered by their
        // first triangle: 0 the big one, 1 the crumb, 2 and 3 the halves, 4 the one too high).
        let patch = |x: f64, missed_mm2: f64, pieces: Vec<(usize, f64)>, counted_pieces: usize| {
            PatchDetail {
                area_mm2: 16.0,
                centroid_mm: [x, 2.0, 0.0],
                missed_mm2,
                pieces,
                counted_pieces,
            }
        };
        assert_eq!(
            details,
            vec![
                patch(2.0, 0.0, vec![(0, 15.0), (1, 1.0)], 1),
                patch(12.0, 0.0, vec![(2, 8.0), (3, 8.0)], 2),
                patch(22.0, 16.0, vec![], 0),
            ]
        );
        // Patches below the smallest area are not counted at all; a mask removes the others.
        assert_eq!(
            patch_coverage(&mesh, &patches_of(&truth, &all, 20.0), 20.0),
            PatchCoverage::default()
        );
        let first_only: Vec<bool> = (0..truth.triangles.len()).map(|f| f < 32).collect();
        assert_eq!(
            patch_coverage(&mesh, &patches_of(&truth, &first_only, 2.0), 2.0),
            PatchCoverage {
                whole: 1,
                split: 0,
                missed: 0
            }
        );
    }

    #[test]
    fn fit_sizes_are_one_three_per_decade() {
        assert_eq!(
            fit_sizes(100_000),
            vec![1_000, 3_000, 10_000, 30_000, 100_000]
        );
        assert_eq!(fit_sizes(3_000), vec![1_000, 3_000]);
        assert!(fit_sizes(999).is_empty());
    }

    /// A sphere of radius 10 mm at the origin and one 81 x 81 px frame through its centre: image x ->
    /// world x, image y (depth) -> world -z (the beam), 0.5 mm pixels, image top at z = 20.
    fn sphere_and_frame() -> (Mesh, DMat4) {
        let frame = DMat4::from_cols(
            glam::DVec4::new(0.5, 0.0, 0.0, 0.0),
            glam::DVec4::new(0.0, 0.0, -0.5, 0.0),
            glam::DVec4::new(0.0, 1.0, 0.0, 0.0),
            glam::DVec4::new(-20.0, 0.0, 20.0, 1.0),
        );
        (icosphere(DVec3::ZERO, 10.0, 4), frame)
    }

    /// One frame through the centre of a sphere, beam along -z: only the top and bottom caps within
    /// 60 degrees of the beam axis and inside the image count.
    #[test]
    fn mask_keeps_the_swept_caps_facing_the_beam() {
        let (sphere, frame) = sphere_and_frame();
        let mask = swept_beam_facing_mask(
            &sphere,
            &[frame],
            81,
            81,
            None,
            1.5,
            FacingSide::Either,
            60.0,
        );
        let kept: Vec<usize> = (0..mask.len()).filter(|&i| mask[i]).collect();
        assert!(!kept.is_empty());
        for &i in &kept {
            let c = sphere.triangles[i]
                .map(|v| sphere.vertices[v as usize])
                .iter()
                .sum::<DVec3>()
                / 3.0;
            assert!(c.y.abs() <= 1.5 + 1e-9, "off the plane: {c}");
            assert!(c.z.abs() / c.length() >= 0.45, "not facing the beam: {c}");
        }
        // The equator at x = +-10 (normal across the beam) is not kept.
        let side_kept = kept.iter().any(|&i| {
            let c = sphere.vertices[sphere.triangles[i][0] as usize];
            c.x.abs() > 9.5
        });
        assert!(!side_kept);
        // The frame sweeps a strip over the top cap and one under the bottom cap: two patches.
        assert_eq!(patch_count(&patches_of(&sphere, &mask, 0.5)), 2);
        assert_eq!(patch_count(&patches_of(&sphere, &mask, 1e6)), 0);
    }

    /// The same frame, scored per side: the probe (above, beam along -z) faces only the top cap's
    /// outward normals. A mesh of the sphere's upper half covers the top strip whole and misses the
    /// bottom one, so it is complete on the probe side and about half complete on either side.
    #[test]
    fn swept_facing_truth_counts_the_side_facing_the_probe() {
        let (sphere, frame) = sphere_and_frame();
        let mut upper = sphere.clone();
        let keep: Vec<bool> = upper
            .triangles
            .iter()
            .map(|t| t.iter().all(|&v| upper.vertices[v as usize].z > -0.5))
            .collect();
        upper.retain_triangles(&keep);
        let score_on = |mesh: &Mesh, frame: DMat4, side, angle_deg| {
            SweptFacingTruth::new(&sphere, &[frame], 81, 81, None, side, angle_deg)?.score(
                mesh,
                &sphere,
                &CompareOptions::default(),
            )
        };
        let score = |mesh: &Mesh, side| score_on(mesh, frame, side, 60.0).unwrap();
        let probe = score(&upper, FacingSide::Probe);
        let either = score(&upper, FacingSide::Either);
        assert_eq!(probe.truth_patches, 1);
        assert_eq!(either.truth_patches, 2);
        assert!((either.truth_area_mm2 / probe.truth_area_mm2 - 2.0).abs() < 0.1);
        assert!(probe.completeness_1mm > 0.999, "{probe:?}");
        assert!((either.completeness_1mm - 0.5).abs() < 0.05, "{either:?}");
        let whole_one = PatchCoverage {
            whole: 1,
            split: 0,
            missed: 0,
        };
        assert_eq!(probe.patch_coverage, whole_one);
        assert_eq!(
            either.patch_coverage,
            PatchCoverage {
                missed: 1,
                ..whole_one
            }
        );
        // The whole sphere covers both strips; a frame 100 mm away sweeps nothing, and a bad angle is
        // refused.
        assert_eq!(score(&sphere, FacingSide::Either).patch_coverage.whole, 2);
        let far = DMat4::from_translation(DVec3::new(0.0, 100.0, 0.0)) * frame;
        assert!(score_on(&sphere, far, FacingSide::Either, 60.0).is_err());
        assert!(score_on(&sphere, frame, FacingSide::Either, 0.0).is_err());
    }
}
