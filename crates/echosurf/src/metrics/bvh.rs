//! Exact point-to-triangle distances (Ericson, Real-Time Collision Detection 5.1.5) and a bounding-volume
//! hierarchy over a mesh's triangles for nearest-triangle queries.
//!
//! The tree is built by median splits along the longest axis of the centroid bounds (depth ~log2(F/4),
//! independent of how triangles are distributed), with leaves of at most [`LEAF_SIZE`] triangles whose
//! corners are copied into leaf order so a query touches contiguous memory. Queries descend the nearer
//! child first and prune boxes farther than the best distance so far; a caller can pass an upper bound
//! (e.g. the distance to the triangle nearest the previous, nearby query point) to prune from the start.

use glam::DVec3;

use crate::mesh::Mesh;

const LEAF_SIZE: usize = 4;

/// The point of triangle `abc` closest to `p`. Degenerate triangles (a zero-length edge or collinear
/// corners) are handled as the union of their edges, so the result is always finite for finite input.
pub fn closest_point_on_triangle(p: DVec3, a: DVec3, b: DVec3, c: DVec3) -> DVec3 {
    let ab = b - a;
    let ac = c - a;
    if ab.cross(ac).length_squared() == 0.0 {
        return closest_on_degenerate(p, a, b, c);
    }
    // Voronoi regions of the vertices, edges and face in turn (Ericson 5.1.5). In every edge region the
    // denominator is that edge's squared length, positive for a non-degenerate triangle.
    let ap = p - a;
    let d1 = ab.dot(ap);
    let d2 = ac.dot(ap);
    if d1 <= 0.0 && d2 <= 0.0 {
        return a;
    }
    let bp = p - b;
    let d3 = ab.dot(bp);
    let d4 = ac.dot(bp);
    if d3 >= 0.0 && d4 <= d3 {
        return b;
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return a + ab * (d1 / (d1 - d3));
    }
    let cp = p - c;
    let d5 = ab.dot(cp);
    let d6 = ac.dot(cp);
    if d6 >= 0.0 && d5 <= d6 {
        return c;
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return a + ac * (d2 / (d2 - d6));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        return b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)));
    }
    let denom = 1.0 / (va + vb + vc);
    a + ab * (vb * denom) + ac * (vc * denom)
}

fn closest_on_segment(p: DVec3, a: DVec3, b: DVec3) -> DVec3 {
    let ab = b - a;
    let len2 = ab.length_squared();
    if len2 == 0.0 {
        return a;
    }
    a + ab * ((p - a).dot(ab) / len2).clamp(0.0, 1.0)
}

fn closest_on_degenerate(p: DVec3, a: DVec3, b: DVec3, c: DVec3) -> DVec3 {
    [
        closest_on_segment(p, a, b),
        closest_on_segment(p, b, c),
        closest_on_segment(p, c, a),
    ]
    .into_iter()
    .min_by(|x, y| {
        (*x - p)
            .length_squared()
            .total_cmp(&(*y - p).length_squared())
    })
    .expect("three candidates")
}

#[derive(Debug, Clone, Copy)]
struct Node {
    lo: DVec3,
    hi: DVec3,
    /// Leaf: first slot. Internal: index of the left child; the right child follows it.
    start: u32,
    /// Triangles in a leaf; 0 for an internal node.
    count: u32,
}

impl Node {
    fn distance_squared(&self, p: DVec3) -> f64 {
        let d = (self.lo - p).max(p - self.hi).max(DVec3::ZERO);
        d.length_squared()
    }
}

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
    nodes: Vec<Node>,
    /// Corners of the triangles in leaf order.
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
        let mut items: Vec<(DVec3, u32)> = mesh
            .triangles
            .iter()
            .enumerate()
            .filter(|&(i, t)| t.iter().all(|&v| (v as usize) < n) && keep(i))
            .map(|(i, t)| {
                let [a, b, c] = t.map(|v| mesh.vertices[v as usize]);
                ((a + b + c) / 3.0, i as u32)
            })
            .collect();
        let mut bvh = TriangleBvh::default();
        if items.is_empty() {
            return bvh;
        }
        bvh.nodes.reserve(2 * items.len() / LEAF_SIZE + 1);
        bvh.nodes.push(Node {
            lo: DVec3::ZERO,
            hi: DVec3::ZERO,
            start: 0,
            count: 0,
        });
        bvh.build(mesh, &mut items, 0, 0);
        bvh.ids = items.iter().map(|&(_, i)| i).collect();
        bvh.slot_of_triangle = vec![u32::MAX; mesh.triangles.len()];
        for (slot, &i) in bvh.ids.iter().enumerate() {
            bvh.slot_of_triangle[i as usize] = slot as u32;
        }
        bvh.corners = bvh
            .ids
            .iter()
            .map(|&i| mesh.triangles[i as usize].map(|v| mesh.vertices[v as usize]))
            .collect();
        bvh
    }

    fn build(&mut self, mesh: &Mesh, items: &mut [(DVec3, u32)], offset: usize, node: usize) {
        let (mut lo, mut hi) = (DVec3::INFINITY, DVec3::NEG_INFINITY);
        let (mut clo, mut chi) = (DVec3::INFINITY, DVec3::NEG_INFINITY);
        for &(centroid, i) in items.iter() {
            for v in mesh.triangles[i as usize] {
                let p = mesh.vertices[v as usize];
                lo = lo.min(p);
                hi = hi.max(p);
            }
            clo = clo.min(centroid);
            chi = chi.max(centroid);
        }
        if items.len() <= LEAF_SIZE {
            self.nodes[node] = Node {
                lo,
                hi,
                start: offset as u32,
                count: items.len() as u32,
            };
            return;
        }
        let extent = chi - clo;
        let axis = if extent.x >= extent.y && extent.x >= extent.z {
            0
        } else if extent.y >= extent.z {
            1
        } else {
            2
        };
        let mid = items.len() / 2;
        // Ties broken by triangle index so the tree does not depend on the selection algorithm's whims.
        items.select_nth_unstable_by(mid, |x, y| {
            x.0[axis].total_cmp(&y.0[axis]).then(x.1.cmp(&y.1))
        });
        let left = self.nodes.len();
        let placeholder = self.nodes[node];
        self.nodes.push(placeholder);
        self.nodes.push(placeholder);
        self.nodes[node] = Node {
            lo,
            hi,
            start: left as u32,
            count: 0,
        };
        let (first, second) = items.split_at_mut(mid);
        self.build(mesh, first, offset, left);
        self.build(mesh, second, offset + mid, left + 1);
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
        let root = self.nodes.first()?;
        let mut best_d2 = f64::INFINITY;
        let mut best_slot = usize::MAX;
        let mut best_point = DVec3::ZERO;
        if let Some(slot) = hint.and_then(|h| self.slot_of(h)) {
            let [a, b, c] = self.corners[slot];
            let q = closest_point_on_triangle(p, a, b, c);
            best_d2 = (q - p).length_squared();
            best_slot = slot;
            best_point = q;
        }
        let mut stack: Vec<(u32, f64)> = Vec::with_capacity(64);
        stack.push((0, root.distance_squared(p)));
        while let Some((index, box_d2)) = stack.pop() {
            if box_d2 >= best_d2 {
                continue;
            }
            let node = &self.nodes[index as usize];
            if node.count > 0 {
                let start = node.start as usize;
                for slot in start..start + node.count as usize {
                    let [a, b, c] = self.corners[slot];
                    let q = closest_point_on_triangle(p, a, b, c);
                    let d2 = (q - p).length_squared();
                    // Ties go to the lower slot, so the answer does not depend on the visiting order.
                    if d2 < best_d2 || (d2 == best_d2 && slot < best_slot) {
                        best_d2 = d2;
                        best_slot = slot;
                        best_point = q;
                    }
                }
            } else {
                let left = node.start;
                let dl = self.nodes[left as usize].distance_squared(p);
                let dr = self.nodes[left as usize + 1].distance_squared(p);
                // Nearer child popped first.
                let (near, far) = if dl <= dr {
                    ((left, dl), (left + 1, dr))
                } else {
                    ((left + 1, dr), (left, dl))
                };
                if far.1 < best_d2 {
                    stack.push(far);
                }
                if near.1 < best_d2 {
                    stack.push(near);
                }
            }
        }
        (best_slot != usize::MAX).then(|| Nearest {
            distance_mm: best_d2.sqrt(),
            triangle: self.ids[best_slot],
            point: best_point,
        })
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

    /// Reference: the minimum over a dense sampling of the triangle (barycentric grid) - independent of
    /// Ericson's region logic. With n steps the grid spacing is |edge|/n, so the sampled minimum exceeds the
    /// exact one by at most that spacing.
    fn brute_force_distance(p: DVec3, a: DVec3, b: DVec3, c: DVec3, n: usize) -> f64 {
        let mut best = f64::INFINITY;
        for i in 0..=n {
            for j in 0..=n - i {
                let (u, v) = (i as f64 / n as f64, j as f64 / n as f64);
                let q = a + (b - a) * u + (c - a) * v;
                best = best.min((q - p).length());
            }
        }
        best
    }

    #[test]
    fn closest_point_matches_dense_sampling_in_every_region() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let mut r = |s: f64| {
            DVec3::new(
                rng.random_range(-s..s),
                rng.random_range(-s..s),
                rng.random_range(-s..s),
            )
        };
        for _ in 0..300 {
            let (a, b, c, p) = (r(1.0), r(1.0), r(1.0), r(2.0));
            let q = closest_point_on_triangle(p, a, b, c);
            let exact = (q - p).length();
            let n = 200;
            let spacing = [(b - a).length(), (c - a).length(), (c - b).length()]
                .into_iter()
                .fold(0.0, f64::max)
                / n as f64;
            let sampled = brute_force_distance(p, a, b, c, n);
            assert!(
                exact <= sampled + 1e-12,
                "exact {exact} above sampled {sampled}"
            );
            assert!(sampled - exact <= spacing, "{sampled} vs {exact}");
            // The answer lies on the triangle's plane within its bounds.
            let normal = (b - a).cross(c - a).normalize();
            assert!((q - a).dot(normal).abs() < 1e-12);
        }
    }

    #[test]
    fn degenerate_triangles_use_their_edges() {
        let p = DVec3::new(0.5, 1.0, 0.0);
        let (a, b) = (DVec3::ZERO, DVec3::X);
        // Collinear, repeated corner, and a point triangle.
        assert_eq!(
            closest_point_on_triangle(p, a, b, DVec3::X * 0.5),
            DVec3::X * 0.5
        );
        assert_eq!(closest_point_on_triangle(p, a, a, b), DVec3::X * 0.5);
        assert_eq!(closest_point_on_triangle(p, b, b, b), b);
    }
}
