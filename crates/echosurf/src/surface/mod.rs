//! Iso-surface extraction: regularised marching tetrahedra (surface-following) and marching cubes.
//!
//! The pipeline of [`extract_surfaces`] for each level: find the lattice cells the surface crosses
//! (`follow`: from seeds, or a full-grid scan), clipped to the region of trust (`trust`); marching
//! tetrahedra in them (`rmt`); merge vertices per clustering cell without breaking the manifold
//! (`clustering`, which documents the rule); move every vertex onto the surface with batched Newton
//! steps along the field gradient, and take normals from the gradient (toward lower values).

mod clustering;
mod crest;
mod follow;
mod lattice;
mod mc;
mod ridge;
mod rmt;
mod sheet;
mod sheet_sums;

/// One bisection step for every active bracket `(t_a, v_a, t_b, v_b)` (parameters and field values
/// less the level at both ends): the midpoint's value `mid_values[m]` replaces the end of its sign.
fn halve_brackets(
    brackets: &mut [Option<(f64, f64, f64, f64)>],
    active: &[usize],
    mid_values: &[f64],
    level: f64,
) {
    for (m, &k) in active.iter().enumerate() {
        let (ta, va, tb, vb) = brackets[k].expect("active");
        let (t, v) = (0.5 * (ta + tb), mid_values[m] - level);
        brackets[k] = Some(if !v.is_finite() || (v <= 0.0) == (va <= 0.0) {
            (t, v, tb, vb)
        } else {
            (ta, va, t, v)
        });
    }
}

#[cfg(test)]
mod tests;

use glam::DVec3;
use rayon::prelude::*;

use crate::mesh::Mesh;

use crate::{Error, Result};
pub use crest::{
    CrestLink, LINK_MAX_ACROSS_MM, LINK_MAX_TURN_DEG, OrientedPoints, PlacedCrest,
    add_linked_crests, keep_pieces_reaching, linked_crest_normals, orient_crests,
};
pub use ridge::{RidgeOptions, RidgeStats, WeakRidge, extend_ridge_sheet, proximal_sheet_on_ridge};
pub use sheet::{SheetOptions, sheet_through_points};

/// A scalar field the surfacer can sample: values and gradients at many points at once (batches let a
/// fast RBF evaluator amortise its tree walks).
pub trait ScalarField: Sync {
    fn values(&self, points: &[DVec3], out: &mut [f64]);
    fn values_and_gradients(&self, points: &[DVec3], values: &mut [f64], gradients: &mut [DVec3]);
    /// Whether NaN marks points where the field is undefined (lattice cells touching one carry no
    /// surface, so a field confined to a region ends there instead of at a fake crossing). For any
    /// other field a NaN is a numerical failure and the extraction stops with an error.
    fn nan_means_undefined(&self) -> bool {
        false
    }
    /// Whether a point's value and gradient are the same whatever batch it is evaluated in (a batched
    /// RBF evaluator's are not, to rounding): then a search may evaluate fewer points per batch and
    /// still find what one batch finds.
    fn values_are_pointwise(&self) -> bool {
        false
    }
}

/// An analytic field from a closure returning (value, gradient) at a point; for tests and phantoms.
pub struct FnField<F: Fn(DVec3) -> (f64, DVec3) + Sync>(pub F);

impl<F: Fn(DVec3) -> (f64, DVec3) + Sync> std::fmt::Debug for FnField<F> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("FnField")
    }
}

impl<F: Fn(DVec3) -> (f64, DVec3) + Sync> ScalarField for FnField<F> {
    fn values(&self, points: &[DVec3], out: &mut [f64]) {
        for (p, o) in points.iter().zip(out.iter_mut()) {
            *o = (self.0)(*p).0;
        }
    }

    fn values_and_gradients(&self, points: &[DVec3], values: &mut [f64], gradients: &mut [DVec3]) {
        for ((p, v), g) in points
            .iter()
            .zip(values.iter_mut())
            .zip(gradients.iter_mut())
        {
            let (value, gradient) = (self.0)(*p);
            *v = value;
            *g = gradient;
        }
    }

    fn values_are_pointwise(&self) -> bool {
        true
    }
}

/// Where to look for the surface.
#[derive(Debug, Clone, Default)]
pub struct SurfaceDomain {
    /// Box (mm) the surface is clipped to (the lattice starts at `bounds_min_mm` and covers the box in
    /// whole cells).
    pub bounds_min_mm: DVec3,
    pub bounds_max_mm: DVec3,
    /// Points near the surface to start surface-following from (e.g. the samples). Empty: full grid.
    pub seeds: Vec<DVec3>,
    /// Data points defining the region of trust: cells whose centre is farther than `trust_distance_mm`
    /// from every one of them produce no surface. Empty: no clipping.
    pub trust_points: Vec<DVec3>,
}

/// Options of the regularised marching tetrahedra.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SurfaceOptions {
    /// Lattice spacing in mm (in `extract`'s options, the user tier's `resolution_mm`).
    #[serde(skip)]
    pub resolution_mm: f64,
    /// Region of trust radius (mm) around `SurfaceDomain::trust_points` (in `extract`'s options,
    /// `Tuning::trust_distance_mm`).
    #[serde(skip)]
    pub trust_distance_mm: f64,
    /// How far (in cells, Chebyshev distance) a seed whose own cell is not crossed looks for the surface.
    pub seed_search_radius_cells: u32,
    /// Size of the clustering cells relative to the lattice: the cells are the Voronoi cells of a
    /// face-centred cubic lattice of volume `2 * factor^3 * resolution^3` each. 1.1 gives about half
    /// the triangles of marching cubes on the same lattice, with well-shaped triangles; larger merges
    /// more (coarser mesh), smaller keeps more of the lattice's detail.
    pub cluster_cell_factor: f64,
    /// Newton steps at most per vertex when putting vertices back on the surface.
    pub max_newton_steps: u32,
    /// A vertex is on the surface when its first-order distance |s(x) - k| / |grad s| is below this.
    pub surface_tolerance_mm: f64,
}

impl Default for SurfaceOptions {
    fn default() -> Self {
        SurfaceOptions {
            resolution_mm: 0.5,
            trust_distance_mm: 3.0,
            seed_search_radius_cells: 2,
            cluster_cell_factor: 1.1,
            max_newton_steps: 8,
            surface_tolerance_mm: 1e-4,
        }
    }
}

/// What one level's extraction did.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct LevelStats {
    pub level: f64,
    /// Lattice cells the surface crosses (inside the region of trust).
    pub crossed_cells: usize,
    pub raw_vertices: usize,
    pub raw_triangles: usize,
    pub vertices: usize,
    pub triangles: usize,
    /// Vertex merges the clustering refused to keep the mesh manifold (or unfolded).
    pub refused_merges: usize,
    /// Triangles still folded over (winding against the field normals) after untangling; 0 normally.
    pub folded_triangles: usize,
    /// Vertices where two pieces of the surface touched and a triangle across the gap joined them
    /// ([`Mesh::join_pinched_fans`]).
    pub joined_pinched_vertices: usize,
    /// Vertices duplicated because trust clipping left two surface pieces touching at them (and they
    /// could not be joined).
    pub split_pinched_vertices: usize,
    /// Vertices Newton did not bring within `surface_tolerance_mm` (then put on the level by bisection).
    pub newton_failed_vertices: usize,
    /// Largest |s - level| at the best point Newton reached, over those vertices (before bisection).
    pub newton_failed_max_error: f64,
    /// Of those, vertices the gradient and axis lines found no bracket for (a fold or saddle of the
    /// field), put on the level by bisecting the lattice edge their vertex was interpolated on.
    pub edge_bisected_vertices: usize,
    /// Vertices that neither Newton nor the bisection fallbacks brought within `surface_tolerance_mm`.
    pub unconverged_vertices: usize,
    /// Output vertices with |s(v) - level| > [`LEVEL_TOLERANCE`] (measured on the final mesh; they
    /// are flagged here, not hidden).
    pub off_level_vertices: usize,
    /// Largest |s(v) - level| over the output vertices (field units: grey levels for a fit).
    pub max_level_error: f64,
}

/// Largest |s(v) - level| (field units; grey levels for an RBF fit) an output vertex may have before it
/// is counted in [`LevelStats::off_level_vertices`].
pub const LEVEL_TOLERANCE: f64 = 0.5;

/// Work counts of one [`extract_surfaces_with_stats`] call, for cost reports.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct SurfaceStats {
    /// Lattice nodes evaluated (shared by all levels).
    pub lattice_nodes_evaluated: usize,
    /// Distinct lattice cells holding a seed (0 in full-grid mode).
    pub seed_cells: usize,
    /// Points passed to `ScalarField::values`.
    pub value_evaluations: usize,
    /// Points passed to `ScalarField::values_and_gradients`.
    pub gradient_evaluations: usize,
    pub levels: Vec<LevelStats>,
}

impl SurfaceStats {
    /// All points the field was evaluated at, per output triangle of all levels.
    pub fn evaluations_per_triangle(&self) -> f64 {
        let triangles: usize = self.levels.iter().map(|l| l.triangles).sum();
        (self.value_evaluations + self.gradient_evaluations) as f64 / triangles.max(1) as f64
    }
}

/// One mesh per level, in the order of `levels`; normals point toward lower field values.
pub fn extract_surfaces(
    field: &dyn ScalarField,
    levels: &[f64],
    domain: &SurfaceDomain,
    options: &SurfaceOptions,
) -> Result<Vec<Mesh>> {
    extract_surfaces_with_stats(field, levels, domain, options).map(|(meshes, _)| meshes)
}

/// [`extract_surfaces`] plus what it cost.
pub fn extract_surfaces_with_stats(
    field: &dyn ScalarField,
    levels: &[f64],
    domain: &SurfaceDomain,
    options: &SurfaceOptions,
) -> Result<(Vec<Mesh>, SurfaceStats)> {
    validate(levels, options)?;
    let lattice = lattice::Lattice::new(
        domain.bounds_min_mm,
        domain.bounds_max_mm,
        options.resolution_mm,
    )?;
    let trust = crate::spatial::PointBuckets::new(&domain.trust_points, options.trust_distance_mm);
    let mut counter = lattice::EvalCounter::default();
    let crossed = if domain.seeds.is_empty() {
        follow::full_grid(field, &lattice, levels, trust.as_ref(), &mut counter)?
    } else {
        follow::follow_from_seeds(
            field,
            &lattice,
            levels,
            &domain.seeds,
            options.seed_search_radius_cells,
            trust.as_ref(),
            &mut counter,
        )?
    };
    let mut stats = SurfaceStats {
        lattice_nodes_evaluated: crossed.nodes.len(),
        seed_cells: crossed.seed_cells,
        ..Default::default()
    };
    let mut meshes = Vec::with_capacity(levels.len());
    // Marching tetrahedra and clustering are sequential per level; levels run in parallel (each result
    // depends only on its level, so the order of completion does not matter).
    let h = lattice.spacing_mm;
    let merged_levels: Vec<(rmt::RawSurface, clustering::ClusteredSurface)> = levels
        .par_iter()
        .zip(crossed.per_level.par_iter())
        .map(|(&level, cells)| {
            let raw =
                rmt::march_tetrahedra(&lattice, cells, level, options.cluster_cell_factor, |n| {
                    crossed.nodes.get(n)
                });
            let merged = clustering::cluster_vertices(
                &raw.positions,
                &raw.cluster_keys,
                &raw.triangles,
                h * h,
            );
            (raw, merged)
        })
        .collect();
    for ((&level, cells), (raw, merged)) in levels.iter().zip(&crossed.per_level).zip(merged_levels)
    {
        let mut level_stats = LevelStats {
            level,
            crossed_cells: cells.len(),
            raw_vertices: raw.positions.len(),
            raw_triangles: raw.triangles.len(),
            vertices: merged.positions.len(),
            triangles: merged.triangles.len(),
            refused_merges: merged.refused_merges,
            unconverged_vertices: 0,
            newton_failed_vertices: 0,
            newton_failed_max_error: 0.0,
            edge_bisected_vertices: 0,
            off_level_vertices: 0,
            max_level_error: 0.0,
            joined_pinched_vertices: 0,
            split_pinched_vertices: 0,
            folded_triangles: 0,
        };
        let edges: Vec<(DVec3, DVec3)> = merged
            .input_index
            .iter()
            .map(|&i| raw.edges[i as usize])
            .collect();
        let (mut vertices, mut normals, projection) = project_onto_surface(
            field,
            level,
            merged.positions,
            &edges,
            h,
            options,
            &mut counter,
        );
        level_stats.unconverged_vertices = projection.unconverged;
        level_stats.newton_failed_vertices = projection.newton_failed;
        level_stats.newton_failed_max_error = projection.newton_failed_max_error;
        level_stats.edge_bisected_vertices = projection.edge_bisected;
        level_stats.folded_triangles = untangle(
            field,
            level,
            &mut vertices,
            &mut normals,
            &merged.triangles,
            &edges,
            h,
            options,
            &mut counter,
        );
        finish_normals(&mut normals, &vertices, &merged.triangles);
        let mut mesh = Mesh {
            vertices,
            normals,
            triangles: merged.triangles,
        };
        // Clipping to the region of trust can leave two pieces touching at one vertex: joined across
        // a gap of up to two lattice cells where they continue one another, else split.
        level_stats.joined_pinched_vertices = mesh.join_pinched_fans(2.0 * h);
        level_stats.split_pinched_vertices = mesh.split_pinched_vertices();
        level_stats.vertices = mesh.vertices.len();
        level_stats.triangles = mesh.triangles.len();
        // Independent check of the final vertices (after untangling and pinch repairs).
        let (final_values, _) = lattice::evaluate_gradients(field, &mesh.vertices, &mut counter);
        for v in &final_values {
            let error = (v - level).abs();
            if error.is_nan() || error > LEVEL_TOLERANCE {
                level_stats.off_level_vertices += 1;
            }
            if error.is_finite() {
                level_stats.max_level_error = level_stats.max_level_error.max(error);
            }
        }
        meshes.push(mesh);
        stats.levels.push(level_stats);
    }
    stats.value_evaluations = counter.values;
    stats.gradient_evaluations = counter.gradients;
    Ok((meshes, stats))
}

fn validate(levels: &[f64], options: &SurfaceOptions) -> Result<()> {
    if let Some(l) = levels.iter().find(|l| !l.is_finite()) {
        return Err(Error::InvalidInput(format!("iso-level {l} is not finite")));
    }
    if !(options.trust_distance_mm.is_finite() && options.trust_distance_mm > 0.0) {
        return Err(Error::InvalidInput(format!(
            "trust distance must be a positive number of mm, got {}",
            options.trust_distance_mm
        )));
    }
    if !(options.cluster_cell_factor.is_finite()
        && (0.5..=4.0).contains(&options.cluster_cell_factor))
    {
        return Err(Error::InvalidInput(format!(
            "cluster cell factor must lie in 0.5..=4, got {}",
            options.cluster_cell_factor
        )));
    }
    if options.seed_search_radius_cells > 16 {
        return Err(Error::InvalidInput(format!(
            "seed search radius {} cells is more than 16",
            options.seed_search_radius_cells
        )));
    }
    if !(options.surface_tolerance_mm.is_finite() && options.surface_tolerance_mm > 0.0) {
        return Err(Error::InvalidInput(format!(
            "surface tolerance must be a positive number of mm, got {}",
            options.surface_tolerance_mm
        )));
    }
    Ok(())
}

/// Newton steps along the gradient toward s(x) = level, all pending vertices in one batch per step.
/// A step is capped at one lattice spacing (the vertex starts within about a cell of the surface, so a
/// longer step means a poor gradient). On a rough field (an interpolating fit of speckle) Newton can
/// wander or cycle; such a vertex restarts from the best point Newton visited and is put on the level by
/// bisection along its gradient line ([`bisect_onto_level`]); where that finds no bracket (a fold or
/// saddle of the field near the vertex), by bisection of the lattice edge its marching-tetrahedra vertex
/// came from (`edges[i]`, whose end values straddle the level). Returns positions, unit normals toward
/// lower values (the mesh's face normals where the gradient vanishes) and what happened.
fn project_onto_surface(
    field: &dyn ScalarField,
    level: f64,
    mut positions: Vec<DVec3>,
    edges: &[(DVec3, DVec3)],
    spacing_mm: f64,
    options: &SurfaceOptions,
    counter: &mut lattice::EvalCounter,
) -> (Vec<DVec3>, Vec<DVec3>, Projection) {
    let mut normals = vec![DVec3::ZERO; positions.len()];
    let mut best: Vec<(f64, DVec3)> = positions.iter().map(|&p| (f64::INFINITY, p)).collect();
    let mut pending: Vec<u32> = (0..positions.len() as u32).collect();
    let mut failed: Vec<u32> = Vec::new();
    let mut steps = 0;
    while !pending.is_empty() {
        let points: Vec<DVec3> = pending.iter().map(|&i| positions[i as usize]).collect();
        let (values, gradients) = lattice::evaluate_gradients(field, &points, counter);
        let last = steps == options.max_newton_steps;
        let mut still = Vec::new();
        for (k, &i) in pending.iter().enumerate() {
            let (s, g) = (values[k], gradients[k]);
            let g2 = g.length_squared();
            normals[i as usize] = -g;
            if !(s.is_finite() && g2.is_finite() && g2 > 0.0) {
                failed.push(i);
                continue;
            }
            let residual = s - level;
            if residual.abs() < best[i as usize].0 {
                best[i as usize] = (residual.abs(), positions[i as usize]);
            }
            if residual.abs() <= options.surface_tolerance_mm * g2.sqrt() {
                continue;
            }
            if last {
                failed.push(i);
                continue;
            }
            let step = -residual * g / g2;
            let len = step.length();
            positions[i as usize] += if len > spacing_mm {
                step * (spacing_mm / len)
            } else {
                step
            };
            still.push(i);
        }
        pending = still;
        if last {
            break;
        }
        steps += 1;
    }
    let mut outcome = Projection {
        newton_failed: failed.len(),
        ..Projection::default()
    };
    if !failed.is_empty() {
        failed.sort_unstable();
        outcome.newton_failed_max_error = failed
            .iter()
            .map(|&i| best[i as usize].0)
            .fold(0.0, f64::max);
        let starts: Vec<DVec3> = failed
            .iter()
            .map(|&i| {
                let (r, p) = best[i as usize];
                if r.is_finite() {
                    p
                } else {
                    positions[i as usize]
                }
            })
            .collect();
        let (moved, values, gradients) =
            bisect_onto_level(field, level, &starts, spacing_mm, counter);
        let mut missed = Vec::new();
        for (k, &i) in failed.iter().enumerate() {
            positions[i as usize] = moved[k];
            normals[i as usize] = -gradients[k];
            let g = gradients[k].length();
            let miss = (values[k] - level).abs();
            if miss.is_nan() || miss > options.surface_tolerance_mm * g {
                missed.push((i, miss));
            }
        }
        if !missed.is_empty() {
            outcome.edge_bisected = missed.len();
            let segments: Vec<(DVec3, DVec3)> =
                missed.iter().map(|&(i, _)| edges[i as usize]).collect();
            let on_edge = bisect_edges(field, level, &segments, counter);
            for (&(i, miss), found) in missed.iter().zip(on_edge) {
                match found {
                    Some((p, v, g))
                        if (v - level).abs() <= options.surface_tolerance_mm * g.length()
                            || miss.is_nan()
                            || (v - level).abs() < miss =>
                    {
                        positions[i as usize] = p;
                        normals[i as usize] = -g;
                        let now = (v - level).abs();
                        if now.is_nan() || now > options.surface_tolerance_mm * g.length() {
                            outcome.unconverged += 1;
                        }
                    }
                    _ => outcome.unconverged += 1,
                }
            }
        }
    }
    (positions, normals, outcome)
}

/// Bisection steps on a lattice edge (length at most sqrt(3) spacings): the bracket shrinks below 1e-14
/// of it.
const EDGE_BISECTION_STEPS: usize = 48;

/// For each segment whose end values straddle `level`: the point of the bracket bisection ends on
/// (the end of the last bracket nearer the level), with its value and gradient; None where the ends do
/// not straddle it (the field changed since the lattice was evaluated: not expected).
fn bisect_edges(
    field: &dyn ScalarField,
    level: f64,
    segments: &[(DVec3, DVec3)],
    counter: &mut lattice::EvalCounter,
) -> Vec<Option<(DVec3, f64, DVec3)>> {
    let ends: Vec<DVec3> = segments.iter().flat_map(|&(a, b)| [a, b]).collect();
    let (ev, _) = lattice::evaluate_gradients(field, &ends, counter);
    // Bracket (t_a, value_a, t_b, value_b) along a -> b, values minus the level.
    let mut brackets: Vec<Option<(f64, f64, f64, f64)>> = (0..segments.len())
        .map(|k| {
            let (a, b) = (ev[2 * k] - level, ev[2 * k + 1] - level);
            (a.is_finite() && b.is_finite() && (a <= 0.0) != (b <= 0.0)).then_some((0.0, a, 1.0, b))
        })
        .collect();
    let active: Vec<usize> = (0..segments.len())
        .filter(|&k| brackets[k].is_some())
        .collect();
    let at = |k: usize, t: f64| segments[k].0 + (segments[k].1 - segments[k].0) * t;
    for _ in 0..EDGE_BISECTION_STEPS {
        if active.is_empty() {
            break;
        }
        let mids: Vec<DVec3> = active
            .iter()
            .map(|&k| {
                let (ta, _, tb, _) = brackets[k].expect("active");
                at(k, 0.5 * (ta + tb))
            })
            .collect();
        let (mv, _) = lattice::evaluate_gradients(field, &mids, counter);
        halve_brackets(&mut brackets, &active, &mv, level);
    }
    let finals: Vec<DVec3> = active
        .iter()
        .map(|&k| {
            let (ta, va, tb, vb) = brackets[k].expect("active");
            at(k, if va.abs() <= vb.abs() { ta } else { tb })
        })
        .collect();
    let (values, gradients) = lattice::evaluate_gradients(field, &finals, counter);
    let mut out = vec![None; segments.len()];
    for (m, &k) in active.iter().enumerate() {
        out[k] = Some((finals[m], values[m], gradients[m]));
    }
    out
}

/// What [`project_onto_surface`] did.
#[derive(Debug, Default, Clone, Copy)]
struct Projection {
    newton_failed: usize,
    /// Vertices the gradient/axis bisection left off the level, bisected on their lattice edge.
    edge_bisected: usize,
    newton_failed_max_error: f64,
    unconverged: usize,
}

/// Offsets (in lattice spacings) along the gradient line where [`bisect_onto_level`] looks for a sign
/// change of `s - level`, nearest first.
const BRACKET_OFFSETS: [f64; 10] = [0.25, -0.25, 0.5, -0.5, 1.0, -1.0, 1.5, -1.5, 2.0, -2.0];
/// The brackets [`bisect_onto_level`] tries, nearest first (over all lines, the gradient line first at
/// equal distance): bracket `j` ends at `BRACKET_OFFSETS[j]` and starts at the nearer offset on the
/// same side, `BRACKET_OFFSETS[j - 2]`, or at the start point itself for the first two.
fn bracket_near_end(j: usize) -> Option<usize> {
    j.checked_sub(2)
}
/// Bisection steps: the bracket (at most 2 spacings) shrinks below 1e-9 spacings.
const BISECTION_STEPS: usize = 32;

/// Search lines of [`bisect_onto_level`] besides the gradient's: the lattice axes.
const AXIS_LINES: [DVec3; 3] = [DVec3::X, DVec3::Y, DVec3::Z];
/// Search lines per start: the gradient's and the axes.
const SEARCH_LINES: usize = 1 + AXIS_LINES.len();

/// For each start point: the nearest sign change of `s - level` along the line through it in the
/// direction of its gradient, else along a lattice axis (within two lattice spacings), then bisection of
/// that bracket; where no bracket is found the start point is kept. Returns positions, values and
/// gradients there.
fn bisect_onto_level(
    field: &dyn ScalarField,
    level: f64,
    starts: &[DVec3],
    spacing_mm: f64,
    counter: &mut lattice::EvalCounter,
) -> (Vec<DVec3>, Vec<f64>, Vec<DVec3>) {
    let (v0, g0) = lattice::evaluate_gradients(field, starts, counter);
    let line = |k: usize, d: usize| -> DVec3 {
        if d == 0 {
            let n = g0[k].normalize_or_zero();
            if n == DVec3::ZERO { DVec3::Z } else { n }
        } else {
            AXIS_LINES[d - 1]
        }
    };
    let search = BracketSearch {
        field,
        level,
        starts,
        start_values: &v0,
        line: &line,
        spacing_mm,
    };
    let found = if field.values_are_pointwise() {
        search.nearest_first(counter)
    } else {
        search.in_one_batch(counter)
    };
    // Per start: its search line and bracket (t_a, value_a, t_b, value_b) in spacings, or None.
    let directions: Vec<DVec3> = (0..starts.len())
        .map(|k| line(k, found[k].map_or(0, |(d, _)| d)))
        .collect();
    let mut brackets: Vec<Option<(f64, f64, f64, f64)>> =
        found.iter().map(|f| f.map(|(_, b)| b)).collect();
    let active: Vec<usize> = (0..starts.len())
        .filter(|&k| brackets[k].is_some())
        .collect();
    for _ in 0..BISECTION_STEPS {
        if active.is_empty() {
            break;
        }
        let mids: Vec<DVec3> = active
            .iter()
            .map(|&k| {
                let (ta, _, tb, _) = brackets[k].expect("active");
                starts[k] + directions[k] * (0.5 * (ta + tb) * spacing_mm)
            })
            .collect();
        let (mv, _) = lattice::evaluate_gradients(field, &mids, counter);
        halve_brackets(&mut brackets, &active, &mv, level);
    }
    let finals: Vec<DVec3> = (0..starts.len())
        .map(|k| match brackets[k] {
            Some((ta, va, tb, vb)) => {
                let t = if va.abs() <= vb.abs() { ta } else { tb };
                starts[k] + directions[k] * (t * spacing_mm)
            }
            None => starts[k],
        })
        .collect();
    let (values, gradients) = lattice::evaluate_gradients(field, &finals, counter);
    (finals, values, gradients)
}

/// The bracket search of [`bisect_onto_level`]: the start points, their values and search lines.
struct BracketSearch<'a> {
    field: &'a dyn ScalarField,
    level: f64,
    starts: &'a [DVec3],
    start_values: &'a [f64],
    /// The search line `d` (0: the gradient's) of start `k`.
    line: &'a dyn Fn(usize, usize) -> DVec3,
    spacing_mm: f64,
}

/// Per start: the search line and bracket `(t_a, value_a, t_b, value_b)` (in spacings, values less
/// the level) found, if any.
type Brackets = Vec<Option<(usize, (f64, f64, f64, f64))>>;

impl BracketSearch<'_> {
    /// The probe of start `k` on line `d` at `BRACKET_OFFSETS[j]`.
    fn probe(&self, k: usize, d: usize, j: usize) -> DVec3 {
        self.starts[k] + (self.line)(k, d) * (BRACKET_OFFSETS[j] * self.spacing_mm)
    }

    /// Where `probes` holds start `k`'s probe values (`SEARCH_LINES` lines of `BRACKET_OFFSETS` each):
    /// the first of the brackets `pairs` (see [`bracket_near_end`]), on the first line, whose ends
    /// straddle the level.
    fn first_bracket(
        &self,
        k: usize,
        probes: &[f64],
        pairs: std::ops::Range<usize>,
    ) -> Option<(usize, (f64, f64, f64, f64))> {
        for j in pairs {
            for d in 0..SEARCH_LINES {
                let on_line = &probes[d * BRACKET_OFFSETS.len()..(d + 1) * BRACKET_OFFSETS.len()];
                let (ta, a) = match bracket_near_end(j) {
                    None => (0.0, self.start_values[k] - self.level),
                    Some(i) => (BRACKET_OFFSETS[i], on_line[i] - self.level),
                };
                let (tb, b) = (BRACKET_OFFSETS[j], on_line[j] - self.level);
                if a.is_finite() && b.is_finite() && (a <= 0.0) != (b <= 0.0) {
                    return Some((d, (ta, a, tb, b)));
                }
            }
        }
        None
    }

    /// Every probe of every start in one batch (a batched field's values depend on the batch, so
    /// this keeps them as they were measured).
    fn in_one_batch(&self, counter: &mut lattice::EvalCounter) -> Brackets {
        let per_start = SEARCH_LINES * BRACKET_OFFSETS.len();
        let probes: Vec<DVec3> = (0..self.starts.len())
            .flat_map(|k| {
                (0..SEARCH_LINES)
                    .flat_map(move |d| (0..BRACKET_OFFSETS.len()).map(move |j| self.probe(k, d, j)))
            })
            .collect();
        let (pv, _) = lattice::evaluate_gradients(self.field, &probes, counter);
        (0..self.starts.len())
            .map(|k| {
                let own = &pv[k * per_start..(k + 1) * per_start];
                self.first_bracket(k, own, 0..BRACKET_OFFSETS.len())
            })
            .collect()
    }

    /// The same brackets for a pointwise field, evaluating the probes two offsets (the far ends of the
    /// next two brackets) at a time and only for the starts still without a bracket: most find one at
    /// the nearest offsets.
    fn nearest_first(&self, counter: &mut lattice::EvalCounter) -> Brackets {
        let per_start = SEARCH_LINES * BRACKET_OFFSETS.len();
        let mut pv = vec![f64::NAN; self.starts.len() * per_start];
        let mut found: Brackets = vec![None; self.starts.len()];
        let mut pending: Vec<usize> = (0..self.starts.len()).collect();
        for round in (0..BRACKET_OFFSETS.len()).step_by(2) {
            if pending.is_empty() {
                break;
            }
            let (lo, hi) = (round, (round + 2).min(BRACKET_OFFSETS.len()));
            let slots: Vec<(usize, usize, usize)> = pending
                .iter()
                .flat_map(|&k| {
                    (0..SEARCH_LINES).flat_map(move |d| (lo..hi).map(move |j| (k, d, j)))
                })
                .collect();
            let probes: Vec<DVec3> = slots.iter().map(|&(k, d, j)| self.probe(k, d, j)).collect();
            let (values, _) = lattice::evaluate_gradients(self.field, &probes, counter);
            for (&(k, d, j), &v) in slots.iter().zip(&values) {
                pv[k * per_start + d * BRACKET_OFFSETS.len() + j] = v;
            }
            pending.retain(|&k| {
                let own = &pv[k * per_start..(k + 1) * per_start];
                found[k] = self.first_bracket(k, own, lo..hi);
                found[k].is_none()
            });
        }
        found
    }
}

/// Rounds of untangling after projection.
const UNTANGLE_ROUNDS: usize = 3;

/// Projection can fold a triangle over its neighbours (its winding normal then opposes the field
/// normals at its corners). Each round moves the vertices of folded triangles to the centroid of their
/// neighbours and projects them back onto the surface. Returns the triangles still folded.
#[allow(clippy::too_many_arguments)]
fn untangle(
    field: &dyn ScalarField,
    level: f64,
    vertices: &mut [DVec3],
    normals: &mut [DVec3],
    triangles: &[[u32; 3]],
    edges: &[(DVec3, DVec3)],
    spacing_mm: f64,
    options: &SurfaceOptions,
    counter: &mut lattice::EvalCounter,
) -> usize {
    let folded = |vertices: &[DVec3], normals: &[DVec3]| -> Vec<usize> {
        (0..triangles.len())
            .filter(|&f| {
                let t = triangles[f];
                let [a, b, c] = t.map(|i| vertices[i as usize]);
                let field_normal: DVec3 = t.iter().map(|&i| normals[i as usize]).sum();
                (b - a).cross(c - a).dot(field_normal) <= 0.0
            })
            .collect()
    };
    let mut bad = folded(vertices, normals);
    if bad.is_empty() {
        return 0;
    }
    let mut neighbours: Vec<Vec<u32>> = vec![Vec::new(); vertices.len()];
    for t in triangles {
        for k in 0..3 {
            neighbours[t[k] as usize].push(t[(k + 1) % 3]);
            neighbours[t[k] as usize].push(t[(k + 2) % 3]);
        }
    }
    for _ in 0..UNTANGLE_ROUNDS {
        let mut moved: Vec<u32> = bad.iter().flat_map(|&f| triangles[f]).collect();
        moved.sort_unstable();
        moved.dedup();
        let starts: Vec<DVec3> = moved
            .iter()
            .map(|&v| {
                let n = &neighbours[v as usize];
                n.iter().map(|&w| vertices[w as usize]).sum::<DVec3>() / n.len().max(1) as f64
            })
            .collect();
        let moved_edges: Vec<(DVec3, DVec3)> = moved.iter().map(|&v| edges[v as usize]).collect();
        let (positions, new_normals, _) = project_onto_surface(
            field,
            level,
            starts,
            &moved_edges,
            spacing_mm,
            options,
            counter,
        );
        // A move that would leave the vertex farther off the level than it is stays undone: a folded
        // triangle is counted, an off-level vertex would break the surface's contract.
        let (old_values, _) = lattice::evaluate_gradients(
            field,
            &moved
                .iter()
                .map(|&v| vertices[v as usize])
                .collect::<Vec<_>>(),
            counter,
        );
        let (new_values, _) = lattice::evaluate_gradients(field, &positions, counter);
        for (k, &v) in moved.iter().enumerate() {
            let (was, now) = ((old_values[k] - level).abs(), (new_values[k] - level).abs());
            if now.is_nan() || (now > LEVEL_TOLERANCE && now > was) {
                continue;
            }
            vertices[v as usize] = positions[k];
            normals[v as usize] = new_normals[k];
        }
        bad = folded(vertices, normals);
        if bad.is_empty() {
            break;
        }
    }
    bad.len()
}

/// Unit normals from the field gradient; where it vanishes, the area-weighted normal of the faces.
fn finish_normals(gradient_normals: &mut [DVec3], positions: &[DVec3], triangles: &[[u32; 3]]) {
    let mut face_sum = vec![DVec3::ZERO; positions.len()];
    for t in triangles {
        let [a, b, c] = t.map(|i| positions[i as usize]);
        let n = (b - a).cross(c - a);
        for &i in t {
            face_sum[i as usize] += n;
        }
    }
    for (n, f) in gradient_normals.iter_mut().zip(&face_sum) {
        *n = n
            .try_normalize()
            .filter(|n| n.is_finite())
            .or(f.try_normalize())
            .unwrap_or(DVec3::Z);
    }
}

/// Classic marching cubes on a regular grid: `values[x + dims[0] * (y + dims[1] * z)]`, node (i, j, k) at
/// `origin_mm + (i, j, k) * spacing_mm`; normals point toward lower values (central differences).
/// Watertight: closed wherever the surface closes inside the grid (see `mc` for the face rule).
pub fn marching_cubes(
    values: &[f32],
    dims: [usize; 3],
    origin_mm: DVec3,
    spacing_mm: DVec3,
    level: f64,
) -> Result<Mesh> {
    mc::marching_cubes(values, dims, origin_mm, spacing_mm, level)
}
