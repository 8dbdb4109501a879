//! A bounding-volume hierarchy over a mesh's triangles for exact nearest-triangle queries (the
//! comparison's distances, the simulator's signed distance to a mesh phantom).
//!
//! A [`BoxTree`] over the triangles' boxes, split at their centroids, with the corners copied into slot
//! order so a query touches contiguous memory. Queries descend the nearer child first and prune boxes
//! farther than the best distance so far; a caller can pass a hint (the triangle nearest a previous,
//! nearby query point) to prune from the start.

use glam::DVec3;

use super::box_tree::BoxTree;
use super::triangle::{TriangleFeature, closest_feature_on_triangle, closest_point_on_triangle};
use crate::mesh::Mesh;

/// The triangle nearest a query point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Nearest {
    pub distance_mm: f64,
    /// Index into the mesh's `triangles`.
    pub triangle: u32,
    /// Closest point on that triangle.
    pub point: DVec3,
}

/// A BVH over the triangles of one mesh, for exact nearest-triangle queries.
#[derive(Debug, Clone, Default)]
pub struct TriangleBvh {
    tree: BoxTree,
    /// Corners of the triangles in slot order.
    corners: Vec<[DVec3; 3]>,
    /// Original triangle index of each slot.
    ids: Vec<u32>,
    /// Slot of each original triangle, `u32::MAX` if not in the tree.
    slot_of_triangle: Vec<u32>,
}

impl TriangleBvh {
    /// Builds the tree over the triangles of `mesh` whose indices are in range (others are skipped).
    pub fn new(mesh: &Mesh) -> Self {
        Self::with_filter(mesh, |_| true)
    }

    /// Builds the tree over the valid triangles for which `keep(triangle_index)` holds.
    pub fn with_filter(mesh: &Mesh, keep: impl Fn(usize) -> bool) -> Self {
        let n = mesh.vertices.len();
        let kept: Vec<u32> = mesh
            .triangles
            .iter()
            .enumerate()
            .filter(|&(i, t)| t.iter().all(|&v| (v as usize) < n) && keep(i))
            .map(|(i, _)| i as u32)
            .collect();
        if kept.is_empty() {
            return TriangleBvh::default();
        }
        let corners_of = |i: u32| mesh.triangles[i as usize].map(|v| mesh.vertices[v as usize]);
        let (centroids, bounds): (Vec<DVec3>, Vec<(DVec3, DVec3)>) = kept
            .iter()
            .map(|&i| {
                let [a, b, c] = corners_of(i);
                ((a + b + c) / 3.0, (a.min(b).min(c), a.max(b).max(c)))
            })
            .unzip();
        let tree = BoxTree::new(&centroids, &bounds);
        let ids: Vec<u32> = tree.order().iter().map(|&k| kept[k as usize]).collect();
        let mut slot_of_triangle = vec![u32::MAX; mesh.triangles.len()];
        for (slot, &i) in ids.iter().enumerate() {
            slot_of_triangle[i as usize] = slot as u32;
        }
        let corners = ids.iter().map(|&i| corners_of(i)).collect();
        TriangleBvh {
            tree,
            corners,
            ids,
            slot_of_triangle,
        }
    }

    /// Number of triangles in the tree.
    pub fn len(&self) -> usize {
        self.ids.len()
    }

    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }

    /// The nearest triangle to `p`, `None` for an empty tree.
    pub fn nearest(&self, p: DVec3) -> Option<Nearest> {
        self.nearest_with_hint(p, None)
    }

    /// As [`Self::nearest`], first trying triangle `hint` (an original triangle index, e.g. the answer for a
    /// nearby point) to get a tight bound before descending.
    pub fn nearest_with_hint(&self, p: DVec3, hint: Option<u32>) -> Option<Nearest> {
        let eval = |slot: usize| {
            let [a, b, c] = self.corners[slot];
            let q = closest_point_on_triangle(p, a, b, c);
            ((q - p).length_squared(), q)
        };
        let known = hint.and_then(|h| self.slot_of(h)).map(|slot| {
            let (d2, q) = eval(slot);
            (slot, d2, q)
        });
        let (slot, d2, point) = self.tree.nearest(p, known, eval)?;
        Some(Nearest {
            distance_mm: d2.sqrt(),
            triangle: self.ids[slot],
            point,
        })
    }

    /// As [`Self::nearest`], also naming the feature of the triangle the closest point lies on (for a
    /// signed distance by pseudo-normals).
    pub fn nearest_feature(&self, p: DVec3) -> Option<(Nearest, TriangleFeature)> {
        let (slot, d2, (point, feature)) = self.tree.nearest(p, None, |slot| {
            let [a, b, c] = self.corners[slot];
            let (q, feature) = closest_feature_on_triangle(p, a, b, c);
            ((q - p).length_squared(), (q, feature))
        })?;
        let nearest = Nearest {
            distance_mm: d2.sqrt(),
            triangle: self.ids[slot],
            point,
        };
        Some((nearest, feature))
    }

    fn slot_of(&self, triangle: u32) -> Option<usize> {
        match self.slot_of_triangle.get(triangle as usize) {
            Some(&slot) if slot != u32::MAX => Some(slot as usize),
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// Random triangles of varied size and shape, some sharing corners (as in a mesh), some degenerate,
    /// and one with an out-of-range index (skipped).
    fn random_mesh(triangles: usize, seed: u64) -> Mesh {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let vertices: Vec<DVec3> = (0..triangles)
            .map(|_| DVec3::new(rng.random(), rng.random(), rng.random()) * 40.0)
            .collect();
        let n = vertices.len() as u32;
        let mut tris: Vec<[u32; 3]> = (0..triangles)
            .map(|i| {
                let a = i as u32;
                [
                    a,
                    (a + 1 + rng.random_range(0..3)) % n,
                    rng.random_range(0..n),
                ]
            })
            .collect();
        tris.push([0, 0, 1]);
        tris.push([0, 1, n + 5]);
        Mesh {
            vertices,
            normals: vec![],
            triangles: tris,
        }
    }

    fn brute_nearest(mesh: &Mesh, p: DVec3, keep: impl Fn(usize) -> bool) -> Option<(f64, u32)> {
        let n = mesh.vertices.len();
        mesh.triangles
            .iter()
            .enumerate()
            .filter(|&(i, t)| t.iter().all(|&v| (v as usize) < n) && keep(i))
            .map(|(i, t)| {
                let [a, b, c] = t.map(|v| mesh.vertices[v as usize]);
                (closest_point_on_triangle(p, a, b, c).distance(p), i as u32)
            })
            .min_by(|x, y| x.0.total_cmp(&y.0))
    }

    #[test]
    fn nearest_matches_brute_force_with_hints_and_filters() {
        let mesh = random_mesh(400, 1);
        let bvh = TriangleBvh::new(&mesh);
        assert_eq!(bvh.len(), mesh.triangles.len() - 1);
        let odd = TriangleBvh::with_filter(&mesh, |i| i % 2 == 1);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2);
        for k in 0..1500 {
            let p =
                DVec3::new(rng.random(), rng.random(), rng.random()) * 60.0 - DVec3::splat(10.0);
            let (d, _) = brute_nearest(&mesh, p, |_| true).unwrap();
            let got = bvh.nearest(p).unwrap();
            assert_eq!(got.distance_mm, d, "{p}");
            let [a, b, c] =
                mesh.triangles[got.triangle as usize].map(|v| mesh.vertices[v as usize]);
            assert_eq!(got.point, closest_point_on_triangle(p, a, b, c));
            // A hint (any triangle) changes nothing but the work done.
            let hinted = bvh.nearest_with_hint(p, Some(k % 400)).unwrap();
            assert_eq!(hinted.distance_mm, d);
            // The feature query finds the same triangle and point.
            let (nearest, feature) = bvh.nearest_feature(p).unwrap();
            assert_eq!(nearest, got);
            assert_eq!(
                closest_feature_on_triangle(p, a, b, c),
                (got.point, feature)
            );
            let (d_odd, _) = brute_nearest(&mesh, p, |i| i % 2 == 1).unwrap();
            let got_odd = odd.nearest(p).unwrap();
            assert_eq!(got_odd.distance_mm, d_odd);
            assert_eq!(got_odd.triangle % 2, 1);
        }
    }

    #[test]
    fn empty_and_invalid_meshes_answer_none() {
        let empty = TriangleBvh::new(&Mesh::default());
        assert!(empty.is_empty());
        assert!(empty.nearest(DVec3::ZERO).is_none());
        assert!(empty.nearest_feature(DVec3::ZERO).is_none());
        let mesh = Mesh {
            vertices: vec![DVec3::ZERO],
            normals: vec![],
            triangles: vec![[0, 1, 2]],
        };
        assert!(TriangleBvh::new(&mesh).nearest(DVec3::ONE).is_none());
        // A hint outside the tree is ignored.
        let mesh = random_mesh(10, 3);
        let bvh = TriangleBvh::new(&mesh);
        assert_eq!(
            bvh.nearest_with_hint(DVec3::ONE, Some(10_000)),
            bvh.nearest(DVec3::ONE)
        );
    }
}
