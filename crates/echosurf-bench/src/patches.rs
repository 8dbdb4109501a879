//! The truth's echoing patches and how a mesh's pieces lie over them.

use glam::DVec3;

use echosurf::mesh::Mesh;

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

/// Truth patches smaller than this (mm^2) are not counted in
/// [`RouteResult::truth_patches_strong_echo`](crate::RouteResult::truth_patches_strong_echo) (slivers
/// where a wall's angle to the beam hovers around the limit); the ridge sheet's default smallest piece.
pub const MIN_PATCH_AREA_MM2: f64 = echosurf::pipeline::DEFAULT_RIDGE_MIN_COMPONENT_AREA_MM2;

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
    let bvh = echosurf::metrics::TriangleBvh::new(mesh);
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

#[cfg(test)]
mod tests {
    use super::*;

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
}
