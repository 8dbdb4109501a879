//! The triangle mesh shared by the surfacer, the mesh readers and writers, the metrics and the renderer.

use glam::DVec3;

mod cleanup;
mod joins;
mod topology;

pub use topology::MeshTopology;

/// An indexed triangle mesh in millimetres (Reference frame). `normals` is either empty or one unit
/// normal per vertex. Triangles wind counter-clockwise seen from the side their normal points to.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Mesh {
    pub vertices: Vec<DVec3>,
    pub normals: Vec<DVec3>,
    pub triangles: Vec<[u32; 3]>,
}

/// Root of `i` in a union-find forest, halving the path on the way.
pub(super) fn find_root(parent: &mut [usize], mut i: usize) -> usize {
    while parent[i] != i {
        parent[i] = parent[parent[i]];
        i = parent[i];
    }
    i
}

impl Mesh {
    /// All of `meshes` in one mesh (vertices renumbered); normals only if every part has them.
    pub fn merged<'a>(meshes: impl IntoIterator<Item = &'a Mesh>) -> Mesh {
        let mut out = Mesh::default();
        let mut all_normals = true;
        for m in meshes {
            let base = out.vertices.len() as u32;
            out.vertices.extend(&m.vertices);
            all_normals &= m.normals.len() == m.vertices.len();
            out.normals.extend(&m.normals);
            out.triangles
                .extend(m.triangles.iter().map(|t| t.map(|i| i + base)));
        }
        if !all_normals {
            out.normals.clear();
        }
        out
    }

    pub fn is_empty(&self) -> bool {
        self.triangles.is_empty()
    }

    /// Total surface area in mm^2.
    pub fn area_mm2(&self) -> f64 {
        self.triangles
            .iter()
            .map(|&t| self.triangle_area_mm2(t))
            .sum()
    }

    /// Area of triangle `t` (vertex indices into this mesh) in mm^2.
    pub fn triangle_area_mm2(&self, t: [u32; 3]) -> f64 {
        let [a, b, c] = t.map(|i| self.vertices[i as usize]);
        0.5 * (b - a).cross(c - a).length()
    }

    /// Axis-aligned bounds of the vertices, `None` for a mesh without vertices.
    pub fn bounds(&self) -> Option<(DVec3, DVec3)> {
        let first = *self.vertices.first()?;
        Some(
            self.vertices
                .iter()
                .fold((first, first), |(lo, hi), v| (lo.min(*v), hi.max(*v))),
        )
    }
}

impl Mesh {
    /// Unit normal of a triangle by the right-hand rule, zero for a degenerate one.
    pub(crate) fn triangle_unit_normal(&self, t: [u32; 3]) -> DVec3 {
        let [a, b, c] = t.map(|i| self.vertices[i as usize]);
        (b - a).cross(c - a).normalize_or_zero()
    }
}

/// Per vertex (of `vertex_count`), the vertices it shares a triangle edge with, once per triangle edge
/// (an inner edge lists each end twice), in triangle order; triangles with an out-of-range vertex are
/// skipped.
pub(crate) fn edge_neighbours(vertex_count: usize, triangles: &[[u32; 3]]) -> Vec<Vec<u32>> {
    let mut neighbours: Vec<Vec<u32>> = vec![Vec::new(); vertex_count];
    for t in triangles
        .iter()
        .filter(|t| t.iter().all(|&i| (i as usize) < vertex_count))
    {
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            neighbours[a as usize].push(b);
            neighbours[b as usize].push(a);
        }
    }
    neighbours
}

#[cfg(test)]
mod tests;
