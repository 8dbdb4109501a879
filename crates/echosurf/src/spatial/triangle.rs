//! The point of a triangle closest to a query point (Ericson, Real-Time Collision Detection 5.1.5), and
//! which feature (face, edge or corner) it lies on.

use glam::DVec3;

/// Which part of a triangle `abc` (corners 0, 1, 2) a closest point lies on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TriangleFeature {
    Face,
    /// Edge i runs from corner i to corner (i + 1) % 3.
    Edge(u8),
    Vertex(u8),
}

/// The point of triangle `abc` closest to `p`. Degenerate triangles (a zero-length edge or collinear
/// corners) are handled as the union of their edges, so the result is always finite for finite input.
#[inline]
pub fn closest_point_on_triangle(p: DVec3, a: DVec3, b: DVec3, c: DVec3) -> DVec3 {
    closest_feature_on_triangle(p, a, b, c).0
}

/// As [`closest_point_on_triangle`], also naming the feature the point lies on (the Voronoi region of
/// `p`); for a degenerate triangle, the nearest of its edges (the first on a tie).
#[inline]
pub fn closest_feature_on_triangle(
    p: DVec3,
    a: DVec3,
    b: DVec3,
    c: DVec3,
) -> (DVec3, TriangleFeature) {
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
        return (a, TriangleFeature::Vertex(0));
    }
    let bp = p - b;
    let d3 = ab.dot(bp);
    let d4 = ac.dot(bp);
    if d3 >= 0.0 && d4 <= d3 {
        return (b, TriangleFeature::Vertex(1));
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return (a + ab * (d1 / (d1 - d3)), TriangleFeature::Edge(0));
    }
    let cp = p - c;
    let d5 = ab.dot(cp);
    let d6 = ac.dot(cp);
    if d6 >= 0.0 && d5 <= d6 {
        return (c, TriangleFeature::Vertex(2));
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return (a + ac * (d2 / (d2 - d6)), TriangleFeature::Edge(2));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        return (
            b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6))),
            TriangleFeature::Edge(1),
        );
    }
    let denom = 1.0 / (va + vb + vc);
    (
        a + ab * (vb * denom) + ac * (vc * denom),
        TriangleFeature::Face,
    )
}

fn closest_on_segment(p: DVec3, a: DVec3, b: DVec3) -> DVec3 {
    let ab = b - a;
    let len2 = ab.length_squared();
    if len2 == 0.0 {
        return a;
    }
    a + ab * ((p - a).dot(ab) / len2).clamp(0.0, 1.0)
}

#[cold]
fn closest_on_degenerate(p: DVec3, a: DVec3, b: DVec3, c: DVec3) -> (DVec3, TriangleFeature) {
    let candidates = [
        closest_on_segment(p, a, b),
        closest_on_segment(p, b, c),
        closest_on_segment(p, c, a),
    ];
    let mut best = 0;
    for i in 1..3 {
        let d = (candidates[i] - p).length_squared();
        if d.total_cmp(&(candidates[best] - p).length_squared())
            .is_lt()
        {
            best = i;
        }
    }
    (candidates[best], TriangleFeature::Edge(best as u8))
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

    #[test]
    fn feature_names_where_the_point_lies() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        let mut r = |s: f64| {
            DVec3::new(
                rng.random_range(-s..s),
                rng.random_range(-s..s),
                rng.random_range(-s..s),
            )
        };
        let mut seen = [0usize; 3];
        for _ in 0..3000 {
            let corners = [r(1.0), r(1.0), r(1.0)];
            let p = r(2.0);
            let [a, b, c] = corners;
            let (q, feature) = closest_feature_on_triangle(p, a, b, c);
            assert_eq!(q, closest_point_on_triangle(p, a, b, c));
            let scale = 1e-9;
            match feature {
                TriangleFeature::Vertex(i) => {
                    seen[0] += 1;
                    assert_eq!(q, corners[i as usize]);
                }
                TriangleFeature::Edge(i) => {
                    seen[1] += 1;
                    let (u, v) = (corners[i as usize], corners[(i as usize + 1) % 3]);
                    // On the segment: the distances to its ends add up to its length.
                    assert!((q.distance(u) + q.distance(v) - u.distance(v)).abs() < scale);
                    // p - q is perpendicular to the edge (an interior edge point).
                    assert!((p - q).dot(v - u).abs() < scale);
                }
                TriangleFeature::Face => {
                    seen[2] += 1;
                    // p - q is along the normal, and q has positive barycentric coordinates.
                    let n = (b - a).cross(c - a);
                    assert!((p - q).cross(n).length() < scale * n.length());
                    for i in 0..3 {
                        let (u, v, w) = (corners[i], corners[(i + 1) % 3], corners[(i + 2) % 3]);
                        assert!((v - u).cross(q - u).dot(n) >= 0.0, "{w}");
                    }
                }
            }
        }
        assert!(seen.iter().all(|&k| k > 100), "{seen:?}");
        // A degenerate (collinear) triangle answers on an edge.
        let (q, f) = closest_feature_on_triangle(DVec3::Y, DVec3::ZERO, DVec3::X, DVec3::X * 2.0);
        assert_eq!((q, f), (DVec3::ZERO, TriangleFeature::Edge(0)));
    }
}
