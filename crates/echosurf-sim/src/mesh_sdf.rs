//! Signed distance to a closed triangle mesh: nearest triangle through a bounding-volume hierarchy, sign from
//! the angle-weighted pseudo-normal of the nearest feature (face, edge or vertex; Baerentzen & Aanaes 2005),
//! which is exact for any closed, consistently oriented 2-manifold.

use std::collections::HashMap;

use glam::DVec3;

use echosurf::mesh::Mesh;

/// Which part of a triangle the closest point lies on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Feature {
    Face,
    /// Edge i runs from vertex i to vertex (i + 1) % 3.
    Edge(u8),
    Vertex(u8),
}

#[derive(Debug, Clone, Copy)]
struct Node {
    lo: DVec3,
    hi: DVec3,
    /// Leaf: first triangle in `order` and count; inner: `first` is the left child (right = left + 1
    /// is not assumed: `right` holds it).
    first: u32,
    count: u32,
    right: u32,
}

/// A closed mesh prepared for signed-distance queries.
#[derive(Debug)]
pub struct MeshSdf {
    mesh: Mesh,
    order: Vec<u32>,
    nodes: Vec<Node>,
    face_normals: Vec<DVec3>,
    /// Per triangle, per edge: the sum of the two adjacent face normals.
    edge_normals: Vec<[DVec3; 3]>,
    vertex_normals: Vec<DVec3>,
    bounds: (DVec3, DVec3),
}

const LEAF_SIZE: usize = 4;

impl MeshSdf {
    /// Fails (with a message) unless the mesh is a closed, consistently oriented 2-manifold. Meshes wound
    /// inside-out (negative volume) are flipped.
    pub fn new(mut mesh: Mesh) -> Result<Self, String> {
        let topology = mesh.topology();
        if mesh.triangles.is_empty() || !topology.is_closed_manifold() {
            return Err(format!(
                "a mesh phantom must be a closed, consistently oriented 2-manifold ({topology:?})"
            ));
        }
        if !mesh.vertices.iter().all(|v| v.is_finite()) {
            return Err("mesh has non-finite vertex coordinates".into());
        }
        let volume: f64 = mesh
            .triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| mesh.vertices[i as usize]);
                a.dot(b.cross(c)) / 6.0
            })
            .sum();
        if volume < 0.0 {
            for t in &mut mesh.triangles {
                t.swap(1, 2);
            }
        }
        mesh.normals.clear();
        let tri = |t: &[u32; 3]| t.map(|i| mesh.vertices[i as usize]);
        let face_normals: Vec<DVec3> = mesh
            .triangles
            .iter()
            .map(|t| {
                let [a, b, c] = tri(t);
                (b - a).cross(c - a).normalize_or_zero()
            })
            .collect();
        let mut vertex_normals = vec![DVec3::ZERO; mesh.vertices.len()];
        let mut edge_sum: HashMap<(u32, u32), DVec3> = HashMap::new();
        for (f, t) in mesh.triangles.iter().enumerate() {
            let p = tri(t);
            for i in 0..3 {
                let (a, b, c) = (p[i], p[(i + 1) % 3], p[(i + 2) % 3]);
                let angle = (b - a).angle_between(c - a);
                vertex_normals[t[i] as usize] += face_normals[f] * angle;
                let (u, v) = (t[i].min(t[(i + 1) % 3]), t[i].max(t[(i + 1) % 3]));
                *edge_sum.entry((u, v)).or_insert(DVec3::ZERO) += face_normals[f];
            }
        }
        let edge_normals = mesh
            .triangles
            .iter()
            .map(|t| {
                std::array::from_fn(|i| {
                    let (u, v) = (t[i].min(t[(i + 1) % 3]), t[i].max(t[(i + 1) % 3]));
                    edge_sum[&(u, v)]
                })
            })
            .collect();
        let bounds = mesh.bounds().unwrap_or((DVec3::ZERO, DVec3::ZERO));
        let mut sdf = MeshSdf {
            order: (0..mesh.triangles.len() as u32).collect(),
            mesh,
            nodes: Vec::new(),
            face_normals,
            edge_normals,
            vertex_normals,
            bounds,
        };
        let n = sdf.order.len();
        sdf.build(0, n);
        Ok(sdf)
    }

    pub fn mesh(&self) -> &Mesh {
        &self.mesh
    }

    fn triangle(&self, f: usize) -> [DVec3; 3] {
        self.mesh.triangles[f].map(|i| self.mesh.vertices[i as usize])
    }

    /// Builds the node for order[start..end] (median split on the longest axis of centroids); returns its
    /// index.
    fn build(&mut self, start: usize, end: usize) -> u32 {
        let mut lo = DVec3::splat(f64::INFINITY);
        let mut hi = DVec3::splat(f64::NEG_INFINITY);
        let mut clo = lo;
        let mut chi = hi;
        for &f in &self.order[start..end] {
            let t = self.triangle(f as usize);
            for v in t {
                lo = lo.min(v);
                hi = hi.max(v);
            }
            let c = (t[0] + t[1] + t[2]) / 3.0;
            clo = clo.min(c);
            chi = chi.max(c);
        }
        let index = self.nodes.len() as u32;
        self.nodes.push(Node {
            lo,
            hi,
            first: start as u32,
            count: (end - start) as u32,
            right: 0,
        });
        if end - start > LEAF_SIZE {
            let extent = chi - clo;
            let axis = if extent.x >= extent.y && extent.x >= extent.z {
                0
            } else if extent.y >= extent.z {
                1
            } else {
                2
            };
            let mid = (start + end) / 2;
            let vertices = &self.mesh.vertices;
            let triangles = &self.mesh.triangles;
            let key = |f: &u32| {
                let t = triangles[*f as usize];
                (vertices[t[0] as usize] + vertices[t[1] as usize] + vertices[t[2] as usize])[axis]
            };
            self.order[start..end]
                .select_nth_unstable_by(mid - start, |a, b| key(a).total_cmp(&key(b)));
            let left = self.build(start, mid);
            let right = self.build(mid, end);
            self.nodes[index as usize].first = left;
            self.nodes[index as usize].count = 0;
            self.nodes[index as usize].right = right;
        }
        index
    }

    /// Nearest triangle, closest point and feature.
    fn nearest(&self, p: DVec3) -> (usize, DVec3, Feature, f64) {
        let mut best = (0usize, DVec3::ZERO, Feature::Face, f64::INFINITY);
        let mut stack: Vec<u32> = Vec::with_capacity(64);
        stack.push(0);
        while let Some(n) = stack.pop() {
            let node = self.nodes[n as usize];
            if box_distance_sq(p, node.lo, node.hi) >= best.3 {
                continue;
            }
            if node.count > 0 {
                for &f in &self.order[node.first as usize..(node.first + node.count) as usize] {
                    let [a, b, c] = self.triangle(f as usize);
                    let (q, feature) = closest_point_on_triangle(p, a, b, c);
                    let d2 = (p - q).length_squared();
                    if d2 < best.3 {
                        best = (f as usize, q, feature, d2);
                    }
                }
            } else {
                let (l, r) = (node.first, node.right);
                let dl = box_distance_sq(p, self.nodes[l as usize].lo, self.nodes[l as usize].hi);
                let dr = box_distance_sq(p, self.nodes[r as usize].lo, self.nodes[r as usize].hi);
                // Visit the nearer child first (pushed last).
                if dl < dr {
                    stack.push(r);
                    stack.push(l);
                } else {
                    stack.push(l);
                    stack.push(r);
                }
            }
        }
        best
    }
}

fn box_distance_sq(p: DVec3, lo: DVec3, hi: DVec3) -> f64 {
    let d = (lo - p).max(DVec3::ZERO).max(p - hi);
    d.length_squared()
}

/// Ericson, Real-Time Collision Detection 5.1.5, also reporting the Voronoi region.
fn closest_point_on_triangle(p: DVec3, a: DVec3, b: DVec3, c: DVec3) -> (DVec3, Feature) {
    let ab = b - a;
    let ac = c - a;
    let ap = p - a;
    let d1 = ab.dot(ap);
    let d2 = ac.dot(ap);
    if d1 <= 0.0 && d2 <= 0.0 {
        return (a, Feature::Vertex(0));
    }
    let bp = p - b;
    let d3 = ab.dot(bp);
    let d4 = ac.dot(bp);
    if d3 >= 0.0 && d4 <= d3 {
        return (b, Feature::Vertex(1));
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        let v = d1 / (d1 - d3);
        return (a + ab * v, Feature::Edge(0));
    }
    let cp = p - c;
    let d5 = ab.dot(cp);
    let d6 = ac.dot(cp);
    if d6 >= 0.0 && d5 <= d6 {
        return (c, Feature::Vertex(2));
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        let w = d2 / (d2 - d6);
        return (a + ac * w, Feature::Edge(2));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        let w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        return (b + (c - b) * w, Feature::Edge(1));
    }
    let denom = 1.0 / (va + vb + vc);
    let v = vb * denom;
    let w = vc * denom;
    (a + ab * v + ac * w, Feature::Face)
}

// `simulate::phantom` implements its `Phantom` trait over these, so this module does not depend on it.
impl MeshSdf {
    /// Signed distance (mm, negative inside) to the mesh at `p` and its gradient.
    pub(crate) fn signed_distance_and_gradient(&self, p: DVec3) -> (f64, DVec3) {
        let (f, q, feature, d2) = self.nearest(p);
        let normal = match feature {
            Feature::Face => self.face_normals[f],
            Feature::Edge(i) => self.edge_normals[f][i as usize],
            Feature::Vertex(i) => self.vertex_normals[self.mesh.triangles[f][i as usize] as usize],
        };
        let offset = p - q;
        let sign = if offset.dot(normal) < 0.0 { -1.0 } else { 1.0 };
        let d = d2.sqrt();
        let g = if d > 1e-12 {
            offset / d * sign
        } else {
            self.face_normals[f]
        };
        (sign * d, g)
    }

    /// Bounding box (min, max corners, mm) of the mesh.
    pub(crate) fn bounding_box(&self) -> (DVec3, DVec3) {
        self.bounds
    }

    /// The mesh itself with its vertex normals: the phantom's exact truth.
    pub(crate) fn exact_mesh(&self) -> Mesh {
        let mut mesh = self.mesh.clone();
        mesh.normals = self
            .vertex_normals
            .iter()
            .map(|n| n.normalize_or_zero())
            .collect();
        mesh
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::phantom::Phantom;

    /// A UV sphere of radius r: closed, outward-wound.
    pub(crate) fn uv_sphere(r: f64, rings: u32, segments: u32) -> Mesh {
        let mut vertices = vec![DVec3::new(0.0, 0.0, r)];
        for i in 1..rings {
            let theta = std::f64::consts::PI * i as f64 / rings as f64;
            for j in 0..segments {
                let phi = 2.0 * std::f64::consts::PI * j as f64 / segments as f64;
                vertices.push(
                    r * DVec3::new(
                        theta.sin() * phi.cos(),
                        theta.sin() * phi.sin(),
                        theta.cos(),
                    ),
                );
            }
        }
        vertices.push(DVec3::new(0.0, 0.0, -r));
        let south = vertices.len() as u32 - 1;
        let ring = |i: u32, j: u32| 1 + (i - 1) * segments + (j % segments);
        let mut triangles = Vec::new();
        for j in 0..segments {
            triangles.push([0, ring(1, j), ring(1, j + 1)]);
            triangles.push([south, ring(rings - 1, j + 1), ring(rings - 1, j)]);
        }
        for i in 1..rings - 1 {
            for j in 0..segments {
                triangles.push([ring(i, j), ring(i + 1, j), ring(i + 1, j + 1)]);
                triangles.push([ring(i, j), ring(i + 1, j + 1), ring(i, j + 1)]);
            }
        }
        Mesh {
            vertices,
            normals: vec![],
            triangles,
        }
    }

    #[test]
    fn sphere_mesh_distance_matches_analytic_within_faceting() {
        let r = 10.0;
        let mesh = uv_sphere(r, 48, 96);
        assert!(mesh.topology().is_closed_manifold());
        let sdf = MeshSdf::new(mesh).unwrap();
        // Faceting error of a 48 x 96 UV sphere: a face centre sits r (1 - cos(a)) inside the sphere with a
        // the half-diagonal angle of a cell, ~sqrt(2) pi / 96, i.e. 0.011 mm at r = 10; allow 0.015 mm.
        for i in 0..200 {
            let t = i as f64 * 0.731;
            let dir = DVec3::new(
                t.sin() * (2.0 * t).cos(),
                t.cos(),
                t.sin() * (2.0 * t).sin(),
            )
            .normalize();
            let radius = 2.0 + 0.1 * i as f64;
            let (d, g) = sdf.distance_and_gradient(dir * radius);
            assert!((d - (radius - r)).abs() < 0.015, "r {radius}: {d}");
            if (radius - r).abs() > 0.5 {
                assert!(g.dot(dir) > 0.99, "{g} vs {dir}");
            }
        }
    }

    #[test]
    fn inside_out_mesh_is_flipped_and_open_mesh_rejected() {
        let mut mesh = uv_sphere(5.0, 8, 16);
        for t in &mut mesh.triangles {
            t.swap(1, 2);
        }
        let sdf = MeshSdf::new(mesh.clone()).unwrap();
        assert!(sdf.distance(DVec3::ZERO) < 0.0);
        mesh.triangles.pop();
        assert!(MeshSdf::new(mesh).is_err());
    }
}
