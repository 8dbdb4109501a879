//! A smooth sheet through oriented points: the implicit moving-least-squares surface (Kolluri 2008) of
//! points `p_i` with unit normals `n_i`,
//! `f(x) = sum_i w_i(x) (x - p_i) . n_i / sum_i w_i(x)`, with Gaussian weights
//! `w_i = exp(-|x - p_i|^2 / h^2)` cut off at `SUPPORT_RADII` h. Near the points `f` is a signed distance
//! to the local least-squares plane: its zero set averages the points over about `h`, bridges gaps
//! narrower than about twice the reach, and gives one sheet where the points form several close layers
//! facing the same way. Points closer than `h / 2` whose normals agree are summed as one point weighted
//! by their count (the same field to well within the sheet's accuracy, far fewer terms per evaluation
//! where the points are dense). The field is undefined (NaN) farther than `reach_mm` from every given
//! point, so a sheet ends about `reach_mm` past its last point instead of running on along its tangent
//! plane. Gaps between pieces of one sheet are also bridged over up to `bridge_mm` in the sheet's
//! plane: where points lie around a spot on opposite sides and it sits on their common plane (see
//! [`SheetOptions::bridge_mm`]).

use glam::DVec3;
use rayon::prelude::*;

use super::sheet_sums::{LaneSums, SheetPoints, SumShape, Sums, add_run};
use super::{ScalarField, SurfaceDomain, SurfaceOptions, SurfaceStats};
use crate::Result;
use crate::mesh::Mesh;
use crate::spatial::PointBuckets;

/// How [`sheet_through_points`] smooths and closes.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SheetOptions {
    /// `h` of the Gaussian weights (mm): the sheet averages the points over about this distance.
    pub smoothing_mm: f64,
    /// The sheet is defined within this distance of some point (mm).
    pub reach_mm: f64,
    /// Beyond `reach_mm`, the sheet is also defined where points within this distance across their
    /// planes (and within `reach_mm` along their normals) surround the spot (so gaps up to about
    /// `reach_mm + bridge_mm` between points are bridged): their unit directions in
    /// the plane average to at most [`BRIDGE_MAX_IMBALANCE`], so it lies between them rather than past a
    /// rim; and their weighted RMS distance from it along their normals is at most
    /// [`BRIDGE_MAX_RMS_MM`], so it lies on their common plane rather than across a fold or between two
    /// layers. 0: no bridging.
    pub bridge_mm: f64,
    /// Holes whose boundary is at most this long (mm) are closed; 0 keeps them all.
    pub max_hole_perimeter_mm: f64,
}

impl Default for SheetOptions {
    /// Smoothing 0.8 mm, reach 0.75 mm, bridges up to 2 mm on one plane, holes up to 6 mm around closed:
    /// the measurements are in docs/decisions/0004-echo-ridge-sheet.md ("The sheet's defaults").
    fn default() -> Self {
        SheetOptions {
            smoothing_mm: 0.8,
            reach_mm: 0.75,
            max_hole_perimeter_mm: 6.0,
            bridge_mm: 2.0,
        }
    }
}

/// A spot is between points when their unit in-plane directions to it average to at most this (a spot
/// past the straight rim of a sheet sees them over a half-disc: 2 / pi = 0.64).
pub const BRIDGE_MAX_IMBALANCE: f64 = 0.5;

/// ... and on their common plane when its weighted RMS distance from them along their normals is at
/// most this (mm).
pub const BRIDGE_MAX_RMS_MM: f64 = 0.6;

/// The smooth sheet through `points` with unit `normals` (see the module docs), extracted by the
/// regularised marching tetrahedra from the points as seeds inside `domain`'s box; triangles face the
/// way the normals point. Small holes are closed afterwards ([`Mesh::fill_small_holes`]).
pub fn sheet_through_points(
    points: &[DVec3],
    normals: &[DVec3],
    domain: &SurfaceDomain,
    surface: &SurfaceOptions,
    options: &SheetOptions,
) -> Result<(Mesh, SurfaceStats)> {
    let positive = |mm: f64| mm.is_finite() && mm > 0.0;
    if !(positive(options.smoothing_mm) && positive(options.reach_mm)) {
        return Err(crate::Error::InvalidInput(format!(
            "sheet smoothing and reach must be positive mm, got {} and {}",
            options.smoothing_mm, options.reach_mm
        )));
    }
    if !(options.bridge_mm.is_finite() && options.bridge_mm >= 0.0) {
        return Err(crate::Error::InvalidInput(format!(
            "sheet bridging must be 0 or a positive number of mm, got {}",
            options.bridge_mm
        )));
    }
    let Some(field) = OrientedPointField::new(
        points,
        normals,
        options.smoothing_mm,
        options.reach_mm,
        options.bridge_mm,
    ) else {
        return Ok((Mesh::default(), SurfaceStats::default()));
    };
    let domain = SurfaceDomain {
        bounds_min_mm: domain.bounds_min_mm,
        bounds_max_mm: domain.bounds_max_mm,
        seeds: field.points_in_given_order(),
        trust_points: Vec::new(),
    };
    let (mut meshes, stats) = super::extract_surfaces_with_stats(&field, &[0.0], &domain, surface)?;
    let mut mesh = meshes.remove(0);
    // Extraction winds toward lower values: against the normals.
    for t in &mut mesh.triangles {
        t.swap(1, 2);
    }
    for n in &mut mesh.normals {
        *n = -*n;
    }
    if options.max_hole_perimeter_mm > 0.0 {
        mesh.fill_small_holes(options.max_hole_perimeter_mm);
    }
    Ok((mesh, stats))
}

/// Below this derivative along the mean normal (relative to the mean normal's squared length) the
/// field's gradient is taken as the mean normal itself.
const MIN_SLOPE_ALONG_NORMAL: f64 = 0.1;

/// Weights are cut off at this many `h`: exp(-9) ~ 1e-4 of a point's own weight.
const SUPPORT_RADII: f64 = 3.0;

/// Points in one cell of this many `h` whose normals agree are summed as one point: their mean,
/// weighted by their count. The frames' echo crests lie a pixel apart along every frame, denser than
/// the sheet's smoothing needs, and every evaluation sums over all of them
/// (docs/decisions/0055-merged-sheet-points.md).
const MERGE_CELL_RADII: f64 = 0.5;

/// Points merged into one have normals within this cosine (30 degrees) of its first point's.
const MERGE_MIN_NORMAL_COS: f64 = 0.866;

/// Oriented points merged by [`merge_close_points`].
struct MergedPoints {
    points: Vec<DVec3>,
    /// Unit normals.
    normals: Vec<DVec3>,
    /// How many given points each stands for.
    counts: Vec<f64>,
}

/// `points` (finite) with unit `normals`, merged per cell of `cell_mm`: each point joins the first
/// merged point of its cell whose first normal agrees with its own ([`MERGE_MIN_NORMAL_COS`]), else
/// starts one. The merged points are the means of theirs with the normalised sums of their normals, in
/// the order of their first point. `cell_mm <= 0` keeps every point.
fn merge_close_points(points: &[DVec3], normals: &[DVec3], cell_mm: f64) -> MergedPoints {
    if cell_mm.is_nan() || cell_mm <= 0.0 {
        return MergedPoints {
            points: points.to_vec(),
            normals: normals.to_vec(),
            counts: vec![1.0; points.len()],
        };
    }
    let mut cells: std::collections::HashMap<[i64; 3], Vec<u32>> = Default::default();
    let (mut sums, mut normal_sums, mut firsts) = (Vec::new(), Vec::new(), Vec::<DVec3>::new());
    let mut counts = Vec::new();
    for (&p, &n) in points.iter().zip(normals) {
        let cell = (p / cell_mm).floor().as_i64vec3().to_array();
        let merged = cells.entry(cell).or_default();
        match merged
            .iter()
            .find(|&&k| firsts[k as usize].dot(n) >= MERGE_MIN_NORMAL_COS)
        {
            Some(&k) => {
                let k = k as usize;
                sums[k] += p;
                normal_sums[k] += n;
                counts[k] += 1.0;
            }
            None => {
                merged.push(sums.len() as u32);
                sums.push(p);
                normal_sums.push(n);
                firsts.push(n);
                counts.push(1.0);
            }
        }
    }
    MergedPoints {
        points: sums.iter().zip(&counts).map(|(&s, &c)| s / c).collect(),
        // Normals within 30 degrees of one another do not cancel.
        normals: normal_sums.iter().map(|s| s.normalize()).collect(),
        counts,
    }
}

/// The implicit surface of oriented points (see the module docs).
pub(crate) struct OrientedPointField {
    /// The points in `grid`'s bucket order ([`PointBuckets::sorted_points`]), so that
    /// [`OrientedPointField::at`] reads each run of neighbours as slices.
    grid: PointBuckets,
    /// The same points with their unit normals and how many given points each stands for
    /// ([`merge_close_points`]), as the SoA slices the sums read.
    soa: SheetPoints,
    /// The given (unmerged) points, for whether `x` lies within reach of one: merging must not pull
    /// the sheet's rims in.
    reach_grid: PointBuckets,
    /// The weights' width and support and the bridging test's reach and bridge, squared.
    shape: SumShape,
}

impl OrientedPointField {
    /// `None` without a finite point with a unit normal. `smoothing_mm` is `h`; `reach_mm` and
    /// `bridge_mm` (each at most the support `3 h`) bound where the field is defined.
    pub fn new(
        points: &[DVec3],
        normals: &[DVec3],
        smoothing_mm: f64,
        reach_mm: f64,
        bridge_mm: f64,
    ) -> Option<OrientedPointField> {
        let (points, normals): (Vec<DVec3>, Vec<DVec3>) = points
            .iter()
            .zip(normals)
            .filter_map(|(&p, n)| Some((p, n.try_normalize()?)).filter(|_| p.is_finite()))
            .unzip();
        Self::with_merge_cell(
            &points,
            &normals,
            smoothing_mm,
            reach_mm,
            bridge_mm,
            MERGE_CELL_RADII * smoothing_mm,
        )
    }

    /// As [`OrientedPointField::new`] for finite `points` with unit `normals`, merged per cell of
    /// `merge_cell_mm` ([`merge_close_points`]; 0: not merged).
    fn with_merge_cell(
        points: &[DVec3],
        normals: &[DVec3],
        smoothing_mm: f64,
        reach_mm: f64,
        bridge_mm: f64,
        merge_cell_mm: f64,
    ) -> Option<OrientedPointField> {
        let support = SUPPORT_RADII * smoothing_mm;
        let reach_mm = reach_mm.min(support);
        // Every point is finite, so the grids keep them all.
        let reach_grid = PointBuckets::new(points, reach_mm)?;
        let merged = merge_close_points(points, normals, merge_cell_mm);
        let grid = PointBuckets::new(&merged.points, support)?;
        let order = grid.original_indices();
        let normals: Vec<DVec3> = order.iter().map(|&i| merged.normals[i as usize]).collect();
        let counts: Vec<f64> = order.iter().map(|&i| merged.counts[i as usize]).collect();
        let soa = SheetPoints::new(grid.sorted_points(), &normals, &counts);
        let bridge_mm = bridge_mm.min(support);
        Some(OrientedPointField {
            grid,
            soa,
            reach_grid,
            shape: SumShape {
                inv_h2: 1.0 / (smoothing_mm * smoothing_mm),
                support2: support.powi(2),
                reach2: reach_mm * reach_mm,
                bridge2: bridge_mm * bridge_mm,
            },
        })
    }

    /// The (merged) points in the order of their first given point (less those it dropped).
    fn points_in_given_order(&self) -> Vec<DVec3> {
        let mut points = vec![DVec3::ZERO; self.grid.sorted_points().len()];
        for (&p, &i) in self
            .grid
            .sorted_points()
            .iter()
            .zip(self.grid.original_indices())
        {
            points[i as usize] = p;
        }
        points
    }

    /// Value and the gradient's part along the mean normal at `x` (see
    /// [`OrientedPointField::values_and_gradients`]); NaN beyond reach. Sums over the points
    /// within the support in the grid's visiting order ([`PointBuckets::visit_within`]'s).
    fn at(&self, x: DVec3) -> (f64, DVec3) {
        let shape = self.shape;
        let inv_h2 = shape.inv_h2;
        let within_reach = self.reach_grid.contains(x);
        // Beyond reach, the points that could bridge to `x` are summed too.
        let mut lanes = LaneSums::default();
        self.grid.runs_around(x, |run| {
            add_run(x, &self.soa, run, shape, !within_reach, &mut lanes);
            true
        });
        let Sums {
            weight,
            value,
            value2,
            normal,
            along_offsets: weighted_along_offsets,
            offsets: weighted_offsets,
            around,
            bridging,
        } = lanes.reduce();
        let bridged = || {
            bridging >= 2.0
                && around.length() <= BRIDGE_MAX_IMBALANCE * bridging
                && value2 <= BRIDGE_MAX_RMS_MM * BRIDGE_MAX_RMS_MM * weight
        };
        if weight <= 0.0 || !(within_reach || bridged()) {
            return (f64::NAN, DVec3::NAN);
        }
        // The field's derivative along the mean normal, from d/dx of value / weight with
        // d w_i / dx = -2 w_i d_i / h^2.
        let f = value / weight;
        let mean_normal = normal / weight;
        let gradient =
            (normal - 2.0 * inv_h2 * (weighted_along_offsets - f * weighted_offsets)) / weight;
        let m2 = mean_normal.length_squared();
        let slope = gradient.dot(mean_normal);
        if slope > MIN_SLOPE_ALONG_NORMAL * m2 {
            (f, mean_normal * (slope / m2))
        } else {
            (f, mean_normal)
        }
    }
}

impl ScalarField for OrientedPointField {
    fn values(&self, points: &[DVec3], out: &mut [f64]) {
        out.par_iter_mut()
            .zip(points.par_iter())
            .for_each(|(o, &p)| *o = self.at(p).0);
    }

    /// The gradient's part along the weighted mean normal `m`: `m (grad f . m) / |m|^2`. Newton steps
    /// then move across the sheet along the points' normals (as the mean normal alone did) at the rate
    /// the field really changes there, which the mean normal alone misjudges where the points spread
    /// across the sheet (slow convergence); the full gradient also tilts along the sheet (less
    /// accurate meshes). Where the field does not rise along `m`, `m` itself. Measured in
    /// docs/decisions/0041-sheet-field-gradient.md.
    fn values_and_gradients(&self, points: &[DVec3], values: &mut [f64], gradients: &mut [DVec3]) {
        values
            .par_iter_mut()
            .zip(gradients.par_iter_mut())
            .zip(points.par_iter())
            .for_each(|((v, g), &p)| (*v, *g) = self.at(p));
    }

    fn nan_means_undefined(&self) -> bool {
        true
    }

    fn values_are_pointwise(&self) -> bool {
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plane_points_give_the_signed_distance_to_the_plane() {
        // Points on z = 1 every 0.3 mm, normals +z: f(x) = z - 1 near them, NaN beyond reach.
        let mut points = Vec::new();
        for i in -20..=20 {
            for j in -20..=20 {
                points.push(DVec3::new(i as f64 * 0.3, j as f64 * 0.3, 1.0));
            }
        }
        let normals = vec![DVec3::Z; points.len()];
        let field = OrientedPointField::new(&points, &normals, 0.5, 1.0, 0.0).unwrap();
        assert_eq!(field.grid.sorted_points().len(), points.len());
        assert_eq!(field.points_in_given_order(), points);
        let mut v = [0.0; 3];
        let mut g = [DVec3::ZERO; 3];
        let probes = [
            DVec3::new(0.1, 0.2, 1.4),
            DVec3::new(-1.0, 0.5, 0.3),
            DVec3::new(0.0, 0.0, 2.5),
        ];
        field.values_and_gradients(&probes, &mut v, &mut g);
        assert!(
            (v[0] - 0.4).abs() < 1e-12 && (v[1] + 0.7).abs() < 1e-12,
            "{v:?}"
        );
        assert!(g[0].distance(DVec3::Z) < 1e-12);
        assert!(
            v[2].is_nan(),
            "1.5 mm from every point is beyond the 1 mm reach"
        );
    }

    #[test]
    fn the_gradient_is_the_derivative_along_the_mean_normal() {
        // Points on a sphere of radius 3 mm with outward normals, jittered off it so that the points'
        // planes disagree: the returned gradient points along the weighted mean normal (summed here
        // from the definition) with the length of the value's central difference along it.
        let mut points = Vec::new();
        let mut normals = Vec::new();
        for i in 0..40 {
            for j in 0..20 {
                let (a, b) = (i as f64 * 0.157, 0.1 + j as f64 * 0.15);
                let n = DVec3::new(b.sin() * a.cos(), b.sin() * a.sin(), b.cos());
                let jitter = 0.15 * ((7 * i + 3 * j) % 5) as f64 / 4.0 - 0.075;
                points.push(n * (3.0 + jitter));
                normals.push((n + DVec3::new(jitter, -jitter, 0.5 * jitter)).normalize());
            }
        }
        let h = 0.8;
        // Unmerged: the mean normal below sums the given points.
        let field =
            OrientedPointField::with_merge_cell(&points, &normals, h, 1.5, 0.0, 0.0).unwrap();
        let e = 1e-6;
        let mut rescaled = 0;
        for probe in [
            DVec3::new(0.3, 0.2, 3.2),
            DVec3::new(1.5, -1.0, 2.2),
            DVec3::new(-2.0, 1.1, 1.6),
            DVec3::new(2.6, 0.4, 0.9),
        ] {
            let (_, g) = field.at(probe);
            let (mut weight, mut normal) = (0.0, DVec3::ZERO);
            for (p, n) in points.iter().zip(&normals) {
                let d2 = probe.distance_squared(*p);
                if d2 <= (SUPPORT_RADII * h).powi(2) {
                    let w = (-d2 / (h * h)).exp();
                    weight += w;
                    normal += w * *n;
                }
            }
            let mean_normal = normal / weight;
            let u = mean_normal.normalize();
            assert!(
                g.normalize().distance(u) < 1e-9,
                "at {probe}: {g} against {mean_normal}"
            );
            let slope = (field.at(probe + u * e).0 - field.at(probe - u * e).0) / (2.0 * e);
            assert!(
                (g.length() - slope).abs() < 1e-6,
                "at {probe}: |{g}| against {slope}"
            );
            if (g.length() - mean_normal.length()).abs() > 1e-3 {
                rescaled += 1;
            }
        }
        assert!(
            rescaled >= 2,
            "the probes do not tell the slope from the mean normal's length"
        );
    }

    #[test]
    fn close_points_with_agreeing_normals_merge_into_their_mean() {
        let tilted = DVec3::new(0.3, 0.0, 1.0).normalize();
        let points = [
            DVec3::new(0.1, 0.1, 0.1),
            DVec3::new(0.3, 0.2, 0.1),
            // Same cell, normal opposite: a point of its own.
            DVec3::new(0.2, 0.2, 0.2),
            // Next cell.
            DVec3::new(0.45, 0.1, 0.1),
            // Same cell as the first, normal 17 degrees off: merged.
            DVec3::new(0.2, 0.3, 0.3),
        ];
        let normals = [DVec3::Z, DVec3::Z, DVec3::NEG_Z, DVec3::Z, tilted];
        let merged = merge_close_points(&points, &normals, 0.4);
        assert_eq!(merged.counts, vec![3.0, 1.0, 1.0]);
        let mean = (points[0] + points[1] + points[4]) / 3.0;
        assert!(merged.points[0].distance(mean) < 1e-15);
        assert!(merged.normals[0].distance((2.0 * DVec3::Z + tilted).normalize()) < 1e-15);
        assert_eq!(&merged.points[1..], &[points[2], points[3]]);
        assert_eq!(&merged.normals[1..], &[DVec3::NEG_Z, DVec3::Z]);
        let kept = merge_close_points(&points, &normals, 0.0);
        assert_eq!(kept.points, points.to_vec());
        assert_eq!(kept.counts, vec![1.0; 5]);
    }

    #[test]
    fn merged_points_give_the_field_of_all_points_and_end_where_they_end() {
        // A jittered cap of a 6 mm sphere (up to 50 degrees from its pole) sampled every ~0.1 mm, with
        // outward normals tilted by up to 5 degrees: merging leaves a fraction of the points, the same
        // values to a few micrometres and the same NaN beyond the cap's rim.
        let (mut points, mut normals) = (Vec::new(), Vec::new());
        let (radius, step_mm) = (6.0, 0.1);
        for i in 0..53 {
            let polar = i as f64 * step_mm / radius;
            let ring =
                ((std::f64::consts::TAU * polar.sin() * radius / step_mm).round() as usize).max(1);
            for j in 0..ring {
                let azimuth = j as f64 / ring as f64 * std::f64::consts::TAU;
                let n = DVec3::new(
                    polar.sin() * azimuth.cos(),
                    polar.sin() * azimuth.sin(),
                    polar.cos(),
                );
                let k = (i * 31 + j * 17) % 13;
                let jitter = 0.02 * (k as f64 / 6.0 - 1.0);
                let tilt = DVec3::new(0.17 * (k as f64 / 12.0 - 0.5), 0.0, 0.0);
                points.push(n * (radius + jitter));
                normals.push((n + tilt).normalize());
            }
        }
        let all =
            OrientedPointField::with_merge_cell(&points, &normals, 0.8, 0.75, 2.0, 0.0).unwrap();
        let merged = OrientedPointField::new(&points, &normals, 0.8, 0.75, 2.0).unwrap();
        let kept = merged.grid.sorted_points().len();
        assert_eq!(all.grid.sorted_points().len(), points.len());
        assert!(
            kept * 3 < points.len(),
            "{kept} of {} points left",
            points.len()
        );
        let (mut compared, mut undefined) = (0, 0);
        for a in 0..40 {
            for r in [-0.6, -0.2, 0.0, 0.3, 0.7, 1.2] {
                let polar = 0.05 + a as f64 * 0.025;
                let probe = DVec3::new(polar.sin(), 0.3 * polar.sin(), polar.cos()).normalize()
                    * (radius + r);
                let (v_all, g_all) = all.at(probe);
                let (v, g) = merged.at(probe);
                assert_eq!(
                    v_all.is_nan(),
                    v.is_nan(),
                    "at {probe} ({v_all} against {v})"
                );
                if v.is_nan() {
                    undefined += 1;
                    continue;
                }
                compared += 1;
                assert!((v - v_all).abs() < 0.005, "at {probe}: {v} against {v_all}");
                assert!(g.distance(g_all) < 0.02, "at {probe}: {g} against {g_all}");
            }
        }
        assert!(compared > 100 && undefined > 20, "{compared} {undefined}");
    }

    #[test]
    fn two_close_layers_give_one_sheet_between_them() {
        // Layers at z = 0 and z = 0.3 facing the same way: the zero set lies midway.
        let mut points = Vec::new();
        for i in -10..=10 {
            for j in -10..=10 {
                for z in [0.0, 0.3] {
                    points.push(DVec3::new(i as f64 * 0.25, j as f64 * 0.25, z));
                }
            }
        }
        let normals = vec![DVec3::NEG_Z; points.len()];
        let field = OrientedPointField::new(&points, &normals, 0.6, 1.0, 0.0).unwrap();
        let mut v = [0.0; 1];
        field.values(&[DVec3::new(0.2, -0.1, 0.15)], &mut v);
        assert!(v[0].abs() < 1e-12, "{v:?}");
        assert!(OrientedPointField::new(&[], &[], 0.5, 1.0, 0.0).is_none());
    }

    #[test]
    fn the_sheet_bridges_gaps_closes_holes_and_faces_the_normals() {
        // Points every 0.3 mm on the tilted plane z = 0.2 x over 12 x 12 mm, normals toward +z (the
        // probe), with a 1 mm wide strip missing across the whole plane and a 0.8 mm hole.
        let up = DVec3::new(-0.2, 0.0, 1.0).normalize();
        let (points, normals) = grid_points(|x, y| {
            let in_strip = (y - 1.0).abs() < 0.5;
            let in_hole = DVec3::new(x + 3.0, y + 3.0, 0.0).length() < 0.4;
            (!(in_strip || in_hole)).then_some((0.2 * x, up))
        });
        let (domain, surface) = lattice();
        let (mesh, _) = sheet_through_points(
            &points,
            &normals,
            &domain,
            &surface,
            &SheetOptions::default(),
        )
        .unwrap();
        let topo = mesh.topology();
        assert_eq!(topo.components, 1, "{topo:?}");
        assert!(topo.is_oriented_manifold(), "{topo:?}");
        // On the plane (to the lattice's and the weights' precision) and across the strip.
        for v in &mesh.vertices {
            let off_plane = (v.z - 0.2 * v.x).abs() / (1.0f64 + 0.04).sqrt();
            assert!(off_plane < 0.01, "{v} is {off_plane} mm off the plane");
        }
        assert!(
            mesh.vertices
                .iter()
                .any(|v| (v.y - 1.0).abs() < 0.1 && v.x.abs() < 1.0)
        );
        // The sheet ends within the reach of the outermost points (6 mm + 0.75 mm).
        assert!(
            mesh.vertices
                .iter()
                .all(|v| v.x.abs().max(v.y.abs()) < 6.0 + 0.8)
        );
        // Faces toward the normals, and the only boundary left is the outer edge.
        for t in &mesh.triangles {
            let [a, b, c] = t.map(|i| mesh.vertices[i as usize]);
            assert!((b - a).cross(c - a).dot(up) > 0.0);
        }
        let mut open = mesh.clone();
        assert_eq!(open.fill_small_holes(1e9), 0, "only the outer edge is open");
        // Without points there is no sheet; bad options are refused.
        let (empty, _) =
            sheet_through_points(&[], &[], &domain, &surface, &SheetOptions::default()).unwrap();
        assert!(empty.is_empty());
        let bad = SheetOptions {
            reach_mm: 0.0,
            ..SheetOptions::default()
        };
        assert!(sheet_through_points(&points, &normals, &domain, &surface, &bad).is_err());
        let bad = SheetOptions {
            bridge_mm: -1.0,
            ..SheetOptions::default()
        };
        assert!(sheet_through_points(&points, &normals, &domain, &surface, &bad).is_err());
    }

    /// Points every 0.3 mm over x, y in [-6, 6] mm, at height and with the normal `at(x, y)` gives
    /// (`None`: no point there).
    fn grid_points(at: impl Fn(f64, f64) -> Option<(f64, DVec3)>) -> (Vec<DVec3>, Vec<DVec3>) {
        let (mut points, mut normals) = (Vec::new(), Vec::new());
        for i in -20..=20 {
            for j in -20..=20 {
                let (x, y) = (i as f64 * 0.3, j as f64 * 0.3);
                if let Some((z, n)) = at(x, y) {
                    points.push(DVec3::new(x, y, z));
                    normals.push(n);
                }
            }
        }
        (points, normals)
    }

    /// The box and lattice the sheet tests extract in.
    fn lattice() -> (SurfaceDomain, SurfaceOptions) {
        let domain = SurfaceDomain {
            bounds_min_mm: DVec3::splat(-10.0),
            bounds_max_mm: DVec3::splat(10.0),
            ..SurfaceDomain::default()
        };
        let surface = SurfaceOptions {
            resolution_mm: 0.25,
            ..SurfaceOptions::default()
        };
        (domain, surface)
    }

    /// The sheet with `bridge_mm` through the grid points on `z = surface(x)` where `keep(x)`, with
    /// normals `normal(x)`.
    fn sheet_over(
        surface: impl Fn(f64) -> f64,
        normal: impl Fn(f64) -> DVec3,
        keep: impl Fn(f64) -> bool,
        bridge_mm: f64,
    ) -> Mesh {
        let (points, normals) = grid_points(|x, _| keep(x).then(|| (surface(x), normal(x))));
        let (domain, surface) = lattice();
        let options = SheetOptions {
            bridge_mm,
            ..SheetOptions::default()
        };
        sheet_through_points(&points, &normals, &domain, &surface, &options)
            .unwrap()
            .0
    }

    #[test]
    fn bridging_joins_pieces_of_one_plane_but_not_across_a_fold_or_a_step() {
        // A plane with a strip missing, its points 2.4 mm apart across it: beyond the reach (gaps up to
        // 1.5 mm), within bridging (a spot just past one rim's reach sees the other rim at 1.65 mm).
        let flat = |bridge| sheet_over(|_| 1.0, |_| DVec3::Z, |x: f64| x.abs() > 1.0, bridge);
        let apart = flat(0.0);
        assert_eq!(apart.topology().components, 2);
        let joined = flat(2.0);
        assert_eq!(joined.topology().components, 1);
        assert!(joined.vertices.iter().all(|v| (v.z - 1.0).abs() < 0.01));
        assert!(joined.vertices.iter().any(|v| v.x.abs() < 0.2));
        // A 90-degree fold (z = |x|) with the same strip missing around its crease: a bridge would cut
        // the corner (a chord 0.7 mm off the surface); the points are not on one plane there, so the
        // two pieces stay apart and on the surface.
        let fold = sheet_over(
            f64::abs,
            |x| DVec3::new(-x.signum(), 0.0, 1.0).normalize(),
            |x: f64| x.abs() > 1.0,
            2.0,
        );
        assert_eq!(fold.topology().components, 2, "{:?}", fold.topology());
        let off = fold
            .vertices
            .iter()
            .map(|v| (v.z - v.x.abs()).abs() / 2f64.sqrt())
            .fold(0.0, f64::max);
        assert!(off < 0.3, "{off} mm off the fold");
        // A step: the two sides 1.3 mm apart in height. A spot midway lies within the reach of both
        // planes along their normals (0.65 mm) and between them across, but 0.65 mm off both (more than
        // BRIDGE_MAX_RMS_MM): not on a common plane, so no ramp is bridged there.
        let (points, normals) = grid_points(|x, _| {
            (x.abs() > 1.0).then_some((if x < 0.0 { 0.0 } else { 1.3 }, DVec3::Z))
        });
        let step = OrientedPointField::new(&points, &normals, 0.8, 0.75, 2.0).unwrap();
        assert!(step.at(DVec3::new(0.0, 0.0, 0.65)).0.is_nan());
        let level: Vec<DVec3> = points.iter().map(|p| DVec3::new(p.x, p.y, 0.0)).collect();
        let flat = OrientedPointField::new(&level, &normals, 0.8, 0.75, 2.0).unwrap();
        assert!(flat.at(DVec3::new(0.0, 0.0, 0.0)).0.abs() < 1e-9);
    }
}
