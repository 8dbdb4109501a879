//! The echo-ridge sheet extended by the echo crests of the frames (`segment::crests`): crests get the
//! normal of the plane through their 3D neighbours, and those linked to the sheet's points (a chain of
//! crests, each within a step of the next, starting near a point) join the points the sheet is drawn
//! through. Hysteresis as in [`super::extend_ridge_sheet`]: a crest is taken as the continuation of a
//! fitted echo, never on its own, so speckle crests away from every wall stay out.

use glam::{DMat3, DVec3};
use rayon::prelude::*;

use crate::mesh::Mesh;
use crate::spatial::PointBuckets;

/// Points with unit normals.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct OrientedPoints {
    pub points: Vec<DVec3>,
    pub normals: Vec<DVec3>,
}

/// Fewest crests (the point itself included) within the radius that give it a normal.
const MIN_NEIGHBOURS: usize = 6;

/// Each point's normal: the direction of least spread (PCA) of the points within `radius_mm`, turned
/// against `beams[i]` (toward the probe, as the ridge sheet's normals point). Points with fewer than
/// [`MIN_NEIGHBOURS`] within reach are dropped.
pub fn orient_by_neighbours(points: &[DVec3], beams: &[DVec3], radius_mm: f64) -> OrientedPoints {
    let Some(grid) = PointBuckets::new(points, radius_mm) else {
        return OrientedPoints::default();
    };
    let oriented: Vec<Option<(DVec3, DVec3)>> = points
        .par_iter()
        .zip(beams)
        .map(|(&p, &beam)| {
            let (mut n, mut sum) = (0usize, DVec3::ZERO);
            grid.visit_within(p, radius_mm, |_, q| {
                n += 1;
                sum += q;
                true
            });
            if n < MIN_NEIGHBOURS {
                return None;
            }
            let mean = sum / n as f64;
            let mut covariance = DMat3::ZERO;
            grid.visit_within(p, radius_mm, |_, q| {
                let d = q - mean;
                covariance += DMat3::from_cols(d * d.x, d * d.y, d * d.z);
                true
            });
            let normal = least_spread_direction(covariance).try_normalize()?;
            Some((
                p,
                if normal.dot(beam) > 0.0 {
                    -normal
                } else {
                    normal
                },
            ))
        })
        .collect();
    let (points, normals) = oriented.into_iter().flatten().unzip();
    OrientedPoints { points, normals }
}

/// The unit eigenvector of the smallest eigenvalue of the symmetric matrix `m`.
pub fn least_spread_direction(m: DMat3) -> DVec3 {
    let (values, vectors) = crate::small_eigen::jacobi_eigen(m.to_cols_array_2d());
    let k = (0..3)
        .min_by(|&i, &j| values[i].total_cmp(&values[j]))
        .unwrap_or(0);
    DVec3::new(vectors[0][k], vectors[1][k], vectors[2][k])
}

/// Which crests the points `seeds` reach: those within `seed_mm` of a seed, and every crest linked to
/// one of those by steps of at most `link_mm` from crest to crest.
pub fn crests_linked_to(
    seeds: &[DVec3],
    crests: &[DVec3],
    seed_mm: f64,
    link_mm: f64,
) -> Vec<bool> {
    let mut reached = vec![false; crests.len()];
    let (Some(near_seeds), Some(links)) = (
        PointBuckets::new(seeds, seed_mm),
        PointBuckets::new(crests, link_mm),
    ) else {
        return reached;
    };
    let starts: Vec<bool> = crests.par_iter().map(|&c| near_seeds.contains(c)).collect();
    let mut stack: Vec<usize> = (0..crests.len()).filter(|&i| starts[i]).collect();
    for &i in &stack {
        reached[i] = true;
    }
    while let Some(i) = stack.pop() {
        links.visit_within(crests[i], link_mm, |j, _| {
            if !reached[j] {
                reached[j] = true;
                stack.push(j);
            }
            true
        });
    }
    reached
}

/// How [`add_linked_crests`] links crests to a sheet's points.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CrestLink {
    /// A crest this close (mm) to one of the points starts a link.
    pub seed_mm: f64,
    /// Longest step (mm) from one linked crest to the next.
    pub link_mm: f64,
}

/// Adds to `sheet_points` (the oriented points a sheet is drawn through, normals toward the probe) the
/// crests linked to them ([`crests_linked_to`]); returns how many. Points without normals take none.
pub fn add_linked_crests(
    sheet_points: &mut OrientedPoints,
    crests: &OrientedPoints,
    link: CrestLink,
) -> usize {
    if sheet_points.points.is_empty() || sheet_points.normals.len() != sheet_points.points.len() {
        return 0;
    }
    let linked = crests_linked_to(
        &sheet_points.points,
        &crests.points,
        link.seed_mm,
        link.link_mm,
    );
    let before = sheet_points.points.len();
    for ((p, n), _) in crests
        .points
        .iter()
        .zip(&crests.normals)
        .zip(&linked)
        .filter(|(_, l)| **l)
    {
        sheet_points.points.push(*p);
        sheet_points.normals.push(*n);
    }
    sheet_points.points.len() - before
}

/// Removes the pieces of `mesh` in which fewer than `min_share` of the triangles have a vertex within
/// `reach_mm` of an anchor (0: pieces with none): a sheet drawn through a ridge sheet's points and
/// crests keeps the pieces that continue the ridge sheet, not crumbs drawn through crests alone.
/// Returns the triangles removed.
pub fn keep_pieces_reaching(
    mesh: &mut Mesh,
    anchors: &[DVec3],
    reach_mm: f64,
    min_share: f64,
) -> usize {
    let Some(near) = PointBuckets::new(anchors, reach_mm) else {
        let removed = mesh.triangles.len();
        mesh.retain_triangles(&vec![false; removed]);
        return removed;
    };
    let components = mesh.triangle_components();
    let (mut anchored, mut total) = (
        vec![0usize; components.len()],
        vec![0usize; components.len()],
    );
    for (f, t) in mesh.triangles.iter().enumerate() {
        total[components[f]] += 1;
        if t.iter().any(|&i| {
            mesh.vertices
                .get(i as usize)
                .is_some_and(|&v| near.contains(v))
        }) {
            anchored[components[f]] += 1;
        }
    }
    let keep: Vec<bool> = components
        .iter()
        .map(|&c| anchored[c] > 0 && anchored[c] as f64 >= min_share * total[c] as f64)
        .collect();
    mesh.retain_triangles(&keep)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::surface::{SheetOptions, SurfaceDomain, SurfaceOptions, sheet_through_points};
    use rand::{Rng, SeedableRng};

    #[test]
    fn the_least_spread_direction_matches_a_dense_eigensolver() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        for _ in 0..200 {
            let b = DMat3::from_cols_array(&std::array::from_fn(|_| rng.random_range(-1.0..1.0)));
            let m = b * b.transpose();
            let dense = faer::Mat::<f64>::from_fn(3, 3, |i, j| m.col(j)[i]);
            let eigen = dense.self_adjoint_eigen(faer::Side::Lower).unwrap();
            // faer sorts eigenvalues ascending: column 0 is the smallest one's vector.
            let u = eigen.U();
            let expected = DVec3::new(u[(0, 0)], u[(1, 0)], u[(2, 0)]);
            let got = least_spread_direction(m);
            let values = eigen.S().column_vector();
            if values[1] - values[0] < 1e-6 {
                continue; // a repeated smallest eigenvalue has no single direction
            }
            assert!(
                got.dot(expected).abs() > 1.0 - 1e-9,
                "{got} against {expected} for {m}"
            );
        }
    }

    /// Points on the plane through the origin with normal `n`, on a 0.2 mm grid within `r` mm.
    fn plane_points(n: DVec3, centre: DVec3, r: f64) -> Vec<DVec3> {
        let a = n.any_orthonormal_vector();
        let b = n.cross(a);
        let k = (r / 0.2) as i32;
        (-k..=k)
            .flat_map(|i| {
                (-k..=k).map(move |j| centre + a * (i as f64 * 0.2) + b * (j as f64 * 0.2))
            })
            .collect()
    }

    #[test]
    fn crest_normals_are_their_plane_s_normal_turned_toward_the_probe() {
        let n = DVec3::new(0.3, -0.2, 0.9).normalize();
        let points = plane_points(n, DVec3::ZERO, 2.0);
        let beam = DVec3::NEG_Z; // the probe above: normals must point up
        let beams = vec![beam; points.len()];
        let oriented = orient_by_neighbours(&points, &beams, 1.2);
        assert_eq!(oriented.points.len(), points.len());
        for normal in &oriented.normals {
            assert!(normal.dot(n) > 1.0 - 1e-9, "{normal} against {n}");
        }
        // A lone point has no neighbours to fit a plane to: dropped.
        let lone = orient_by_neighbours(&[DVec3::ZERO], &[beam], 1.2);
        assert!(lone.points.is_empty());
    }

    #[test]
    fn only_crests_linked_to_the_sheet_extend_it() {
        // The sheet: a flat patch in z = 0 over x < 0. Crests: the same plane continued over
        // 0 <= x < 4 (linked), and a patch 3 mm below it (not linked: no crest within a step).
        let sheet_points: Vec<DVec3> = plane_points(DVec3::Z, DVec3::new(-2.0, 0.0, 0.0), 2.0);
        let domain = SurfaceDomain {
            bounds_min_mm: DVec3::new(-6.0, -4.0, -6.0),
            bounds_max_mm: DVec3::new(6.0, 4.0, 3.0),
            seeds: Vec::new(),
            trust_points: Vec::new(),
        };
        let surface = SurfaceOptions {
            resolution_mm: 0.25,
            ..SurfaceOptions::default()
        };
        let (sheet, _) = sheet_through_points(
            &sheet_points,
            &vec![DVec3::Z; sheet_points.len()],
            &domain,
            &surface,
            &SheetOptions::default(),
        )
        .unwrap();
        assert!(sheet.vertices.iter().all(|v| v.x < 0.9));
        let mut crest_points = plane_points(DVec3::Z, DVec3::new(2.0, 0.0, 0.0), 2.0);
        crest_points.retain(|p| p.x >= 0.0);
        let far = plane_points(DVec3::Z, DVec3::new(2.0, 0.0, -3.0), 1.0);
        let all: Vec<DVec3> = crest_points.iter().chain(&far).copied().collect();
        let crests = OrientedPoints {
            normals: vec![DVec3::Z; all.len()],
            points: all,
        };
        let link = CrestLink {
            seed_mm: 0.75,
            link_mm: 0.6,
        };
        let linked = crests_linked_to(&sheet.vertices, &crests.points, link.seed_mm, link.link_mm);
        assert!(linked[..crest_points.len()].iter().all(|&l| l));
        assert!(linked[crest_points.len()..].iter().all(|&l| !l));
        let mut points = OrientedPoints {
            points: sheet.vertices.clone(),
            normals: sheet.normals.clone(),
        };
        let count = add_linked_crests(&mut points, &crests, link);
        assert_eq!(count, crest_points.len());
        let (extended, _) = sheet_through_points(
            &points.points,
            &points.normals,
            &domain,
            &surface,
            &SheetOptions::default(),
        )
        .unwrap();
        // The sheet now runs over the linked crests, stays on the plane, and never reaches the far patch.
        assert!(extended.vertices.iter().any(|v| v.x > 3.5));
        assert!(
            extended.vertices.iter().all(|v| v.z.abs() < 0.05),
            "off the plane"
        );
        // A piece drawn through the far patch alone (as a sheet through all the crests would) does not
        // reach the ridge sheet: removed; the extended sheet stays.
        let (mut with_far, _) = sheet_through_points(
            &[points.points.clone(), far.clone()].concat(),
            &vec![DVec3::Z; points.points.len() + far.len()],
            &domain,
            &surface,
            &SheetOptions::default(),
        )
        .unwrap();
        assert_eq!(with_far.topology().components, 2);
        let removed = keep_pieces_reaching(&mut with_far, &sheet.vertices, link.seed_mm, 0.0);
        assert!(removed > 0);
        assert_eq!(with_far.topology().components, 1);
        assert!(with_far.vertices.iter().all(|v| v.z.abs() < 0.05));
        assert_eq!(extended.topology().components, 1);
    }
}
