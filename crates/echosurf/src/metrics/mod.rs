//! Mesh-to-mesh surface distances and topology checks for scoring against ground truth.
//!
//! Both surfaces are sampled by area (a fixed number of points per triangle from a systematic allocation
//! over cumulative area, placed with sqrt-barycentric coordinates from a seeded generator), and every
//! sample's exact distance to the other mesh is found through a [`TriangleBvh`]. Work is split into
//! fixed chunks whose results are concatenated in order, so the numbers do not depend on the thread count.

pub use crate::spatial::{Nearest, TriangleBvh, closest_point_on_triangle};
pub use walls::{WALL_MIN_SHARE, WallJoins};

mod walls;

use glam::DVec3;
use rand::{Rng, SeedableRng};
use rayon::prelude::*;

use crate::mesh::{Mesh, MeshTopology};
use crate::{Error, Result};

/// Distances from the samples of one surface to another surface, in mm.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize)]
pub struct SurfaceDistances {
    pub mean_mm: f64,
    pub rms_mm: f64,
    pub median_mm: f64,
    pub p95_mm: f64,
    /// Largest distance over the area samples and the vertices of the sampled surface.
    pub max_mm: f64,
    /// Area samples the statistics are taken over (equal weights: samples are spread by area).
    pub samples: usize,
}

/// How surfaces are sampled for [`compare_meshes`].
#[derive(Debug, Clone, PartialEq)]
pub struct CompareOptions {
    /// Area samples per mm^2 on each surface (10 gives ~0.3 mm spacing, well below the 1 mm threshold).
    pub samples_per_mm2: f64,
    /// Never fewer samples per surface than this (small meshes), unless the surface has no area.
    pub min_samples: usize,
    /// Never more samples per surface than this (bounds time and memory on large meshes).
    pub max_samples: usize,
    pub seed: u64,
    /// Restricts the TRUTH side (reverse distances, completeness) to the truth triangles marked `true`,
    /// e.g. the swept, beam-facing part; MESH -> TRUTH distances still go to the whole truth. One flag per
    /// truth triangle.
    pub truth_mask: Option<Vec<bool>>,
}

impl Default for CompareOptions {
    fn default() -> Self {
        CompareOptions {
            samples_per_mm2: 10.0,
            min_samples: 20_000,
            max_samples: 1_000_000,
            seed: 0x5eed,
            truth_mask: None,
        }
    }
}

/// A mesh scored against ground truth.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Comparison {
    /// MESH -> TRUTH: how far the extracted surface lies from the truth.
    pub accuracy: SurfaceDistances,
    /// TRUTH (masked part) -> MESH: how far the truth lies from the extracted surface.
    pub reverse: SurfaceDistances,
    /// Share of the (masked) TRUTH area within 1 mm of MESH.
    pub completeness_1mm: f64,
    /// Symmetric Hausdorff distance: the larger of the two directed maxima.
    pub hausdorff_mm: f64,
    pub mesh_topology: MeshTopology,
    pub truth_topology: MeshTopology,
    pub mesh_area_mm2: f64,
    pub truth_area_mm2: f64,
    /// Area of the truth triangles selected by the mask (all of it without one).
    pub truth_compared_area_mm2: f64,
    /// Which of the truth's separate walls (components) the mesh's pieces join.
    pub walls: WallJoins,
}

/// Scores `mesh` against `truth`. Errors if either has no area to sample, the mask has the wrong length
/// or selects nothing, or a mesh has non-finite vertices or indices out of range.
pub fn compare_meshes(mesh: &Mesh, truth: &Mesh, options: &CompareOptions) -> Result<Comparison> {
    validate(mesh, "mesh")?;
    validate(truth, "truth")?;
    if !(options.samples_per_mm2 > 0.0 && options.samples_per_mm2.is_finite()) {
        return Err(Error::InvalidInput(format!(
            "samples per mm^2 must be positive, got {}",
            options.samples_per_mm2
        )));
    }
    if options.max_samples == 0 {
        return Err(Error::InvalidInput("max samples must be at least 1".into()));
    }
    let truth_selected: Vec<bool> = match &options.truth_mask {
        Some(mask) if mask.len() != truth.triangles.len() => {
            return Err(Error::InvalidInput(format!(
                "truth mask has {} flags for {} truth triangles",
                mask.len(),
                truth.triangles.len()
            )));
        }
        Some(mask) => mask.clone(),
        None => vec![true; truth.triangles.len()],
    };
    let all_mesh = vec![true; mesh.triangles.len()];

    let ((mesh_bvh, truth_bvh), (mesh_topology, truth_topology)) = rayon::join(
        || rayon::join(|| TriangleBvh::new(mesh), || TriangleBvh::new(truth)),
        || rayon::join(|| mesh.topology(), || truth.topology()),
    );

    let mesh_samples = sample_surface(mesh, &all_mesh, options, options.seed)?;
    let truth_samples =
        sample_surface(truth, &truth_selected, options, options.seed ^ 0x7275_7468)?;
    if mesh_samples.points.is_empty() {
        return Err(Error::InvalidInput("mesh has no area to sample".into()));
    }
    if truth_samples.points.is_empty() {
        return Err(Error::InvalidInput(
            "truth (within the mask) has no area to sample".into(),
        ));
    }

    let forward = distances_to(&truth_bvh, &mesh_samples.points);
    let backward = distances_to(&mesh_bvh, &truth_samples.points);
    // Each mesh vertex's nearest truth triangle: its distance bounds the accuracy's max, its triangle
    // puts the vertex on a wall ([`WallJoins`]).
    let mesh_vertex_nearest = used_vertex_nearest(mesh, &truth_bvh);
    let truth_vertices = used_vertices(truth, &truth_selected);
    let forward_vertex_max = mesh_vertex_nearest
        .iter()
        .flatten()
        .map(|n| n.distance_mm)
        .fold(0.0, f64::max);
    let backward_vertex_max = max_of(&distances_to(&mesh_bvh, &truth_vertices));

    let within = backward.iter().filter(|&&d| d <= 1.0).count();
    let accuracy = summarise(&forward, forward_vertex_max);
    let reverse = summarise(&backward, backward_vertex_max);
    Ok(Comparison {
        accuracy,
        reverse,
        completeness_1mm: within as f64 / backward.len() as f64,
        hausdorff_mm: accuracy.max_mm.max(reverse.max_mm),
        mesh_topology,
        truth_topology,
        mesh_area_mm2: mesh_samples.area_mm2,
        truth_area_mm2: truth.area_mm2(),
        truth_compared_area_mm2: truth_samples.area_mm2,
        walls: walls::wall_joins(mesh, truth, &mesh_vertex_nearest),
    })
}

/// One flag per triangle of `mesh`: `keep(centroid, unit normal)`, e.g. to build
/// [`CompareOptions::truth_mask`] from "swept and facing the beam". Degenerate triangles (no normal) and
/// triangles with indices out of range get `false`.
pub fn triangle_mask(mesh: &Mesh, keep: impl Fn(DVec3, DVec3) -> bool) -> Vec<bool> {
    triangle_map(mesh, false, keep)
}

/// One value per triangle of `mesh`: `f(centroid, unit normal)`; `invalid` for degenerate triangles
/// (no normal) and triangles with indices out of range.
pub fn triangle_map<T: Copy>(mesh: &Mesh, invalid: T, f: impl Fn(DVec3, DVec3) -> T) -> Vec<T> {
    let n = mesh.vertices.len();
    mesh.triangles
        .iter()
        .map(|t| {
            if t.iter().any(|&i| i as usize >= n) {
                return invalid;
            }
            let [a, b, c] = t.map(|i| mesh.vertices[i as usize]);
            match (b - a).cross(c - a).try_normalize() {
                Some(normal) => f((a + b + c) / 3.0, normal),
                None => invalid,
            }
        })
        .collect()
}

/// Distance from each point to the nearest triangle of `mesh` (mm), in input order; `f64::INFINITY` for
/// every point if the mesh has no triangles. Builds a [`TriangleBvh`]; keep one yourself for repeated
/// queries against the same mesh.
pub fn point_to_mesh_distances(points: &[DVec3], mesh: &Mesh) -> Vec<f64> {
    distances_to(&TriangleBvh::new(mesh), points)
}

/// Colour of a distance on an error map: blue at 0, through cyan, green and yellow, to red at
/// `scale_mm` and beyond (a non-finite distance, nothing to measure to, is grey).
pub fn distance_colour(distance_mm: f64, scale_mm: f64) -> [u8; 3] {
    const STOPS: [[f64; 3]; 5] = [
        [40.0, 70.0, 200.0],
        [40.0, 170.0, 220.0],
        [70.0, 190.0, 90.0],
        [240.0, 200.0, 40.0],
        [215.0, 40.0, 40.0],
    ];
    if !distance_mm.is_finite() {
        return [128, 128, 128];
    }
    let t = if scale_mm > 0.0 {
        (distance_mm / scale_mm).clamp(0.0, 1.0) * (STOPS.len() - 1) as f64
    } else {
        (STOPS.len() - 1) as f64
    };
    let k = (t.floor() as usize).min(STOPS.len() - 2);
    let f = t - k as f64;
    std::array::from_fn(|c| (STOPS[k][c] * (1.0 - f) + STOPS[k + 1][c] * f).round() as u8)
}

/// An error map: each vertex of `mesh`'s distance to the nearest triangle of `to` (mm) and its
/// [`distance_colour`] on `scale_mm`.
pub fn vertex_distance_map(mesh: &Mesh, to: &Mesh, scale_mm: f64) -> (Vec<f64>, Vec<[u8; 3]>) {
    let distances = point_to_mesh_distances(&mesh.vertices, to);
    let colours = distances
        .iter()
        .map(|&d| distance_colour(d, scale_mm))
        .collect();
    (distances, colours)
}

/// Chunk size for parallel work: results are concatenated per chunk in order (deterministic).
const CHUNK: usize = 4096;

fn distances_to(bvh: &TriangleBvh, points: &[DVec3]) -> Vec<f64> {
    nearest_to(bvh, points)
        .into_iter()
        .map(|n| n.map_or(f64::INFINITY, |n| n.distance_mm))
        .collect()
}

/// Each point's nearest triangle of `bvh` (`None` for every point of an empty one), in input order.
fn nearest_to(bvh: &TriangleBvh, points: &[DVec3]) -> Vec<Option<Nearest>> {
    if bvh.is_empty() {
        return vec![None; points.len()];
    }
    points
        .par_chunks(CHUNK)
        .flat_map_iter(|chunk| {
            // Consecutive points are usually close (same triangle), so the previous answer is a tight
            // first bound. The hint only speeds up pruning; the minimum found is the same.
            let mut hint = None;
            chunk
                .iter()
                .map(move |&p| {
                    let n = bvh.nearest_with_hint(p, hint);
                    hint = n.map(|n| n.triangle).or(hint);
                    n
                })
                .collect::<Vec<_>>()
        })
        .collect()
}

/// Per vertex of `mesh`, its nearest triangle of `bvh`; `None` for vertices no triangle uses.
fn used_vertex_nearest(mesh: &Mesh, bvh: &TriangleBvh) -> Vec<Option<Nearest>> {
    let used = used_flags(mesh, &vec![true; mesh.triangles.len()]);
    let indices: Vec<usize> = (0..used.len()).filter(|&i| used[i]).collect();
    let points: Vec<DVec3> = indices.iter().map(|&i| mesh.vertices[i]).collect();
    let mut nearest = vec![None; mesh.vertices.len()];
    for (i, n) in indices.into_iter().zip(nearest_to(bvh, &points)) {
        nearest[i] = n;
    }
    nearest
}

fn validate(mesh: &Mesh, what: &str) -> Result<()> {
    if u32::try_from(mesh.triangles.len()).is_err() {
        return Err(Error::InvalidInput(format!(
            "{what} has too many triangles"
        )));
    }
    if let Some(i) = mesh.vertices.iter().position(|v| !v.is_finite()) {
        return Err(Error::InvalidInput(format!(
            "{what} vertex {i} is not finite"
        )));
    }
    let n = mesh.vertices.len();
    if let Some(t) = mesh
        .triangles
        .iter()
        .position(|t| t.iter().any(|&i| i as usize >= n))
    {
        return Err(Error::InvalidInput(format!(
            "{what} triangle {t} indexes past its {n} vertices"
        )));
    }
    Ok(())
}

struct Samples {
    points: Vec<DVec3>,
    area_mm2: f64,
}

/// Area-proportional samples on the selected triangles. Triangle `i` gets
/// `floor(N * A_end / A) - floor(N * A_start / A)` points (cumulative areas), so counts follow the area
/// exactly on aggregate with no random count noise; positions use sqrt-barycentric coordinates, uniform
/// over the triangle, from a generator seeded per chunk of triangles.
fn sample_surface(
    mesh: &Mesh,
    selected: &[bool],
    options: &CompareOptions,
    seed: u64,
) -> Result<Samples> {
    let areas: Vec<f64> = mesh
        .triangles
        .iter()
        .zip(selected)
        .map(|(&t, &s)| if s { mesh.triangle_area_mm2(t) } else { 0.0 })
        .collect();
    let total: f64 = areas.iter().sum();
    if total <= 0.0 || !total.is_finite() {
        return Ok(Samples {
            points: Vec::new(),
            area_mm2: 0.0,
        });
    }
    let wanted = (total * options.samples_per_mm2).ceil();
    let count = (wanted.max(options.min_samples as f64) as usize).clamp(1, options.max_samples);
    let scale = count as f64 / total;
    let mut cumulative = 0.0;
    let mut starts = Vec::with_capacity(areas.len() + 1);
    starts.push(0usize);
    for &a in &areas {
        cumulative += a;
        starts.push(((cumulative * scale).floor() as usize).min(count));
    }
    *starts.last_mut().expect("non-empty") = count;

    let tri_chunks: Vec<usize> = (0..mesh.triangles.len()).step_by(CHUNK).collect();
    let points: Vec<DVec3> = tri_chunks
        .par_iter()
        .enumerate()
        .flat_map_iter(|(chunk_index, &first)| {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
            rng.set_stream(chunk_index as u64);
            let last = (first + CHUNK).min(mesh.triangles.len());
            let mut out = Vec::with_capacity(starts[last] - starts[first]);
            for t in first..last {
                let [a, b, c] = mesh.triangles[t].map(|i| mesh.vertices[i as usize]);
                for _ in starts[t]..starts[t + 1] {
                    let s = rng.random::<f64>().sqrt();
                    let r2 = rng.random::<f64>();
                    out.push(a * (1.0 - s) + b * (s * (1.0 - r2)) + c * (s * r2));
                }
            }
            out
        })
        .collect();
    Ok(Samples {
        points,
        area_mm2: total,
    })
}

fn used_vertices(mesh: &Mesh, selected: &[bool]) -> Vec<DVec3> {
    mesh.vertices
        .iter()
        .zip(&used_flags(mesh, selected))
        .filter(|(_, u)| **u)
        .map(|(v, _)| *v)
        .collect()
}

/// Per vertex of `mesh`: whether a triangle marked in `selected` uses it.
fn used_flags(mesh: &Mesh, selected: &[bool]) -> Vec<bool> {
    let mut used = vec![false; mesh.vertices.len()];
    for (t, _) in mesh.triangles.iter().zip(selected).filter(|(_, s)| **s) {
        for &i in t {
            used[i as usize] = true;
        }
    }
    used
}

fn max_of(values: &[f64]) -> f64 {
    values.iter().copied().fold(0.0, f64::max)
}

/// Mean, RMS, median, p95 (nearest rank) and max; sums run in input order for reproducibility.
fn summarise(distances: &[f64], extra_max: f64) -> SurfaceDistances {
    if distances.is_empty() {
        return SurfaceDistances::default();
    }
    let n = distances.len() as f64;
    let mean = distances.iter().sum::<f64>() / n;
    let rms = (distances.iter().map(|d| d * d).sum::<f64>() / n).sqrt();
    let mut sorted = distances.to_vec();
    sorted.par_sort_unstable_by(f64::total_cmp);
    let rank = |q: f64| sorted[((q * n).ceil() as usize).clamp(1, sorted.len()) - 1];
    SurfaceDistances {
        mean_mm: mean,
        rms_mm: rms,
        median_mm: rank(0.5),
        p95_mm: rank(0.95),
        max_mm: sorted[sorted.len() - 1].max(extra_max),
        samples: distances.len(),
    }
}

/// Closed analytic reference meshes for tests, benchmarks and demos (known area, distances, topology).
pub mod shapes {
    use super::*;
    use std::collections::HashMap;

    /// An icosphere: the icosahedron with each triangle split in four `subdivisions` times, vertices
    /// pushed to the sphere. Outward counter-clockwise winding, closed, vertex normals set.
    pub fn icosphere(centre: DVec3, radius: f64, subdivisions: u32) -> Mesh {
        let t = (1.0 + 5f64.sqrt()) / 2.0;
        let mut vertices: Vec<DVec3> = [
            (-1.0, t, 0.0),
            (1.0, t, 0.0),
            (-1.0, -t, 0.0),
            (1.0, -t, 0.0),
            (0.0, -1.0, t),
            (0.0, 1.0, t),
            (0.0, -1.0, -t),
            (0.0, 1.0, -t),
            (t, 0.0, -1.0),
            (t, 0.0, 1.0),
            (-t, 0.0, -1.0),
            (-t, 0.0, 1.0),
        ]
        .iter()
        .map(|&(x, y, z)| DVec3::new(x, y, z).normalize())
        .collect();
        let mut triangles: Vec<[u32; 3]> = vec![
            [0, 11, 5],
            [0, 5, 1],
            [0, 1, 7],
            [0, 7, 10],
            [0, 10, 11],
            [1, 5, 9],
            [5, 11, 4],
            [11, 10, 2],
            [10, 7, 6],
            [7, 1, 8],
            [3, 9, 4],
            [3, 4, 2],
            [3, 2, 6],
            [3, 6, 8],
            [3, 8, 9],
            [4, 9, 5],
            [2, 4, 11],
            [6, 2, 10],
            [8, 6, 7],
            [9, 8, 1],
        ];
        for _ in 0..subdivisions {
            let mut midpoint: HashMap<(u32, u32), u32> = HashMap::new();
            let mut mid = |a: u32, b: u32, vertices: &mut Vec<DVec3>| {
                *midpoint.entry((a.min(b), a.max(b))).or_insert_with(|| {
                    vertices
                        .push(((vertices[a as usize] + vertices[b as usize]) / 2.0).normalize());
                    (vertices.len() - 1) as u32
                })
            };
            let mut next = Vec::with_capacity(triangles.len() * 4);
            for &[a, b, c] in &triangles {
                let ab = mid(a, b, &mut vertices);
                let bc = mid(b, c, &mut vertices);
                let ca = mid(c, a, &mut vertices);
                next.extend([[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
            }
            triangles = next;
        }
        Mesh {
            normals: vertices.clone(),
            vertices: vertices.iter().map(|&v| centre + v * radius).collect(),
            triangles,
        }
    }

    /// A torus around z (major radius `big`, tube radius `small`), closed, outward winding, normals set.
    pub fn torus(big: f64, small: f64, around: u32, tube: u32) -> Mesh {
        let mut mesh = Mesh::default();
        for i in 0..around {
            let u = i as f64 / around as f64 * std::f64::consts::TAU;
            for j in 0..tube {
                let v = j as f64 / tube as f64 * std::f64::consts::TAU;
                let dir = DVec3::new(u.cos(), u.sin(), 0.0);
                let normal = dir * v.cos() + DVec3::Z * v.sin();
                mesh.vertices.push(dir * big + normal * small);
                mesh.normals.push(normal);
            }
        }
        let id = |i: u32, j: u32| (i % around) * tube + (j % tube);
        for i in 0..around {
            for j in 0..tube {
                let (a, b, c, d) = (id(i, j), id(i + 1, j), id(i + 1, j + 1), id(i, j + 1));
                mesh.triangles.push([a, b, c]);
                mesh.triangles.push([a, c, d]);
            }
        }
        mesh
    }
}

#[cfg(test)]
mod tests {
    use super::shapes::icosphere;
    use super::*;

    fn fast_options() -> CompareOptions {
        CompareOptions {
            samples_per_mm2: 2.0,
            min_samples: 5_000,
            max_samples: 50_000,
            ..Default::default()
        }
    }

    #[test]
    fn identical_meshes_are_zero_apart_and_complete() {
        let sphere = icosphere(DVec3::new(1.0, 2.0, 3.0), 10.0, 3);
        let c = compare_meshes(&sphere, &sphere, &fast_options()).unwrap();
        // Samples lie on the triangles; the only error is rounding in the barycentric combination.
        assert!(c.hausdorff_mm < 1e-12, "{c:?}");
        assert_eq!(c.completeness_1mm, 1.0);
        assert!(c.mesh_topology.is_closed_manifold());
        assert_eq!(c.mesh_topology.euler_characteristic, 2);
        assert!(c.accuracy.samples >= 5_000);
    }

    #[test]
    fn concentric_spheres_are_half_a_millimetre_apart() {
        let (r, gap) = (10.0, 0.5);
        let level = 4;
        let inner = icosphere(DVec3::ZERO, r, level);
        let outer = icosphere(DVec3::ZERO, r + gap, level);
        // Faceting: a flat triangle lies inside its sphere by at most the sagitta of its circumscribed
        // circle, R - sqrt(R^2 - rc^2). Bound rc by the longest edge (rc <= edge for any triangle with
        // angles <= 90 deg; the icosphere's are near-equilateral, rc ~ edge/sqrt(3)).
        let longest_edge = |m: &Mesh| {
            m.triangles
                .iter()
                .flat_map(|t| {
                    let [a, b, c] = t.map(|i| m.vertices[i as usize]);
                    [(a - b).length(), (b - c).length(), (c - a).length()]
                })
                .fold(0.0, f64::max)
        };
        let sagitta = |rr: f64, e: f64| rr - (rr * rr - e * e).sqrt();
        let tol_inner = sagitta(r, longest_edge(&inner));
        let tol_outer = sagitta(r + gap, longest_edge(&outer));
        let tol = tol_inner + tol_outer;
        assert!(tol < 0.1, "test mesh too coarse: {tol}");
        let c = compare_meshes(&inner, &outer, &fast_options()).unwrap();
        for d in [c.accuracy, c.reverse] {
            assert!((d.mean_mm - gap).abs() <= tol, "{d:?} tol {tol}");
            assert!(d.max_mm <= gap + tol && d.max_mm >= gap - tol, "{d:?}");
            assert!(d.p95_mm >= d.median_mm && d.max_mm >= d.p95_mm);
        }
        assert_eq!(c.completeness_1mm, 1.0);
        // 1.5 mm apart: nothing within 1 mm.
        let far = icosphere(DVec3::ZERO, r + 1.5, level);
        let c = compare_meshes(&inner, &far, &fast_options()).unwrap();
        assert_eq!(c.completeness_1mm, 0.0);
        assert!((c.hausdorff_mm - 1.5).abs() <= tol, "{c:?}");
    }

    #[test]
    fn error_map_colours_each_vertex_by_its_distance() {
        // Vertices of a sphere 0.5 mm outside another: each lies 0.5 mm from it, less the inner
        // mesh's faceting (its sagitta) and never more.
        let (r, gap) = (10.0, 0.5);
        let inner = icosphere(DVec3::ZERO, r, 4);
        let outer = icosphere(DVec3::ZERO, r + gap, 4);
        let (distances, colours) = vertex_distance_map(&outer, &inner, 1.0);
        assert_eq!(
            (distances.len(), colours.len()),
            (outer.vertices.len(), outer.vertices.len())
        );
        for (&d, &c) in distances.iter().zip(&colours) {
            assert!((gap - 1e-9..gap + 0.05).contains(&d), "{d}");
            assert_eq!(c, distance_colour(d, 1.0));
        }
        // The ramp: blue at 0, green half-way, red at the scale and beyond, grey for no distance.
        assert_eq!(distance_colour(0.0, 1.0), [40, 70, 200]);
        assert_eq!(distance_colour(0.5, 1.0), [70, 190, 90]);
        assert_eq!(distance_colour(1.0, 1.0), [215, 40, 40]);
        assert_eq!(distance_colour(7.0, 1.0), [215, 40, 40]);
        assert_eq!(distance_colour(f64::INFINITY, 1.0), [128, 128, 128]);
        assert_eq!(distance_colour(0.25, 0.5), distance_colour(0.5, 1.0));
        // Red grows and blue falls from the middle of the scale on.
        let ramp: Vec<[u8; 3]> = (0..=20)
            .map(|k| distance_colour(k as f64 * 0.05, 1.0))
            .collect();
        for w in ramp[10..].windows(2) {
            assert!(w[1][2] <= w[0][2], "{ramp:?}");
        }
        for w in ramp[..16].windows(2) {
            assert!(w[1][0] >= w[0][0], "{ramp:?}");
        }
    }

    #[test]
    fn a_sub_patch_covers_its_share_of_the_truth() {
        let sphere = icosphere(DVec3::ZERO, 10.0, 4);
        // The cap z > 4: area share (R - 4) / 2R = 0.3 exactly for a sphere (Archimedes); the faceted
        // cut deviates by the triangles straddling z = 4, and the 1 mm band adds the rim's neighbourhood.
        let cap_flags: Vec<bool> = sphere
            .triangles
            .iter()
            .map(|t| t.iter().all(|&i| sphere.vertices[i as usize].z > 4.0))
            .collect();
        // The same cap through the public helper: centroid above the cut and normal pointing up-ish.
        let by_helper = triangle_mask(&sphere, |centroid, normal| {
            centroid.z > 4.0 && normal.z > 0.0
        });
        let agree = cap_flags
            .iter()
            .zip(&by_helper)
            .filter(|(a, b)| a == b)
            .count();
        assert!(agree as f64 > 0.97 * cap_flags.len() as f64, "{agree}");
        let cap = Mesh {
            vertices: sphere.vertices.clone(),
            normals: vec![],
            triangles: sphere
                .triangles
                .iter()
                .zip(&cap_flags)
                .filter(|(_, k)| **k)
                .map(|(t, _)| *t)
                .collect(),
        };
        let cap_area: f64 = cap.area_mm2();
        let share = cap_area / sphere.area_mm2();
        let c = compare_meshes(&cap, &sphere, &fast_options()).unwrap();
        // Truth within 1 mm of the cap: the cap itself plus a rim band of geodesic width ~1 mm, whose area
        // is ~ circumference * 1 mm. Sampling noise at 5k+ samples: ~0.007 (binomial).
        let rim_radius = (100.0f64 - 16.0).sqrt();
        let band_share = std::f64::consts::TAU * rim_radius * 1.0 / sphere.area_mm2();
        assert!(
            c.completeness_1mm > share && c.completeness_1mm < share + band_share + 0.03,
            "completeness {} cap share {share} band {band_share}",
            c.completeness_1mm
        );
        assert!(c.accuracy.max_mm < 1e-9, "the cap lies on the truth");
        assert!(c.mesh_topology.boundary_edges > 0);

        // Masking the truth to the cap's own triangles makes it complete again.
        let masked = CompareOptions {
            truth_mask: Some(cap_flags),
            ..fast_options()
        };
        let c = compare_meshes(&cap, &sphere, &masked).unwrap();
        assert_eq!(c.completeness_1mm, 1.0);
        assert!((c.truth_compared_area_mm2 - cap_area).abs() < 1e-9 * cap_area);
    }

    #[test]
    fn nested_tori_are_their_tube_gap_apart() {
        // Non-convex, genus 1: tubes of radius 3 and 3.3 around the same circle are 0.3 mm apart.
        // Faceting: around the big circle (radius up to 13.3, 128 steps) and the tube (48 steps) the
        // chords sag by at most r(1 - cos(pi/n)) each: 13.3 * 3.0e-4 + 3.3 * 2.1e-3 < 0.012 per mesh.
        let inner = super::shapes::torus(10.0, 3.0, 128, 48);
        let outer = super::shapes::torus(10.0, 3.3, 128, 48);
        let topo = inner.topology();
        assert!(topo.is_closed_manifold());
        assert_eq!(topo.euler_characteristic, 0);
        let c = compare_meshes(&inner, &outer, &fast_options()).unwrap();
        let tol = 0.024;
        for d in [c.accuracy, c.reverse] {
            assert!(
                (d.mean_mm - 0.3).abs() < tol && (d.max_mm - 0.3).abs() < tol,
                "{d:?}"
            );
        }
        assert_eq!(c.completeness_1mm, 1.0);
    }

    #[test]
    fn results_do_not_depend_on_thread_count() {
        let a = icosphere(DVec3::ZERO, 10.0, 3);
        let b = icosphere(DVec3::new(0.3, 0.0, 0.1), 10.2, 2);
        let run = |threads| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| compare_meshes(&a, &b, &fast_options()).unwrap())
        };
        assert_eq!(run(1), run(3));
    }

    #[test]
    fn point_distances_match_brute_force() {
        let mesh = icosphere(DVec3::ZERO, 5.0, 2);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let points: Vec<DVec3> = (0..500)
            .map(|_| {
                DVec3::new(
                    rng.random_range(-8.0..8.0),
                    rng.random_range(-8.0..8.0),
                    rng.random_range(-8.0..8.0),
                )
            })
            .collect();
        let fast = point_to_mesh_distances(&points, &mesh);
        for (p, d) in points.iter().zip(&fast) {
            let brute = mesh
                .triangles
                .iter()
                .map(|t| {
                    let [a, b, c] = t.map(|i| mesh.vertices[i as usize]);
                    (closest_point_on_triangle(*p, a, b, c) - *p).length()
                })
                .fold(f64::INFINITY, f64::min);
            assert_eq!(*d, brute);
        }
        assert_eq!(
            point_to_mesh_distances(&points[..2], &Mesh::default()),
            vec![f64::INFINITY; 2]
        );
    }

    #[test]
    fn bad_inputs_are_errors() {
        let sphere = icosphere(DVec3::ZERO, 1.0, 1);
        let empty = Mesh::default();
        assert!(compare_meshes(&empty, &sphere, &fast_options()).is_err());
        assert!(compare_meshes(&sphere, &empty, &fast_options()).is_err());
        let wrong_mask = CompareOptions {
            truth_mask: Some(vec![true; 3]),
            ..fast_options()
        };
        assert!(compare_meshes(&sphere, &sphere, &wrong_mask).is_err());
        let nothing = CompareOptions {
            truth_mask: Some(vec![false; sphere.triangles.len()]),
            ..fast_options()
        };
        assert!(compare_meshes(&sphere, &sphere, &nothing).is_err());
        let mut broken = sphere.clone();
        broken.triangles.push([0, 1, 9999]);
        assert!(compare_meshes(&broken, &sphere, &fast_options()).is_err());
    }
}
