//! The triangle mesh shared by the surfacer, the mesh readers and writers, the metrics and the renderer.

use glam::DVec3;

/// An indexed triangle mesh in millimetres (Reference frame). `normals` is either empty or one unit
/// normal per vertex. Triangles wind counter-clockwise seen from the side their normal points to.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Mesh {
    pub vertices: Vec<DVec3>,
    pub normals: Vec<DVec3>,
    pub triangles: Vec<[u32; 3]>,
}

/// Root of `i` in a union-find forest, halving the path on the way.
fn find_root(parent: &mut [usize], mut i: usize) -> usize {
    while parent[i] != i {
        parent[i] = parent[parent[i]];
        i = parent[i];
    }
    i
}

impl Mesh {
    pub fn is_empty(&self) -> bool {
        self.triangles.is_empty()
    }

    /// Total surface area in mm^2.
    pub fn area_mm2(&self) -> f64 {
        self.triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| self.vertices[i as usize]);
                0.5 * (b - a).cross(c - a).length()
            })
            .sum()
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

/// Topological facts about a mesh: what `compare` reports and what the surfacer guarantees.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
pub struct MeshTopology {
    pub vertices_used: usize,
    pub triangles: usize,
    /// Edge-connected components of triangles.
    pub components: usize,
    /// Edges used by exactly one triangle (holes or the mesh's rim).
    pub boundary_edges: usize,
    /// Edges used by three or more triangles.
    pub nonmanifold_edges: usize,
    /// Vertices whose triangles do not form a single fan (pinch points).
    pub nonmanifold_vertices: usize,
    /// Interior edges whose two triangles traverse it in the same direction (inconsistent winding).
    pub misoriented_edges: usize,
    /// Triangles with a repeated vertex index or zero area.
    pub degenerate_triangles: usize,
    /// Triangles with the same vertex set as an earlier one.
    pub duplicate_triangles: usize,
    /// V - E + F over the used vertices.
    pub euler_characteristic: i64,
}

impl MeshTopology {
    /// Every edge shared by at most two triangles, fans single, winding consistent, nothing degenerate.
    pub fn is_oriented_manifold(&self) -> bool {
        self.nonmanifold_edges == 0
            && self.nonmanifold_vertices == 0
            && self.misoriented_edges == 0
            && self.degenerate_triangles == 0
            && self.duplicate_triangles == 0
    }

    /// An oriented manifold without boundary.
    pub fn is_closed_manifold(&self) -> bool {
        self.is_oriented_manifold() && self.boundary_edges == 0
    }
}

impl Mesh {
    /// Computes the mesh's topology in O(F log F).
    pub fn topology(&self) -> MeshTopology {
        use std::collections::HashMap;

        let mut topo = MeshTopology {
            triangles: self.triangles.len(),
            ..Default::default()
        };
        // Undirected edge -> (use count, sum of directions: +1 for a->b with a<b, -1 otherwise).
        let mut edges: HashMap<(u32, u32), (u32, i32)> =
            HashMap::with_capacity(self.triangles.len() * 2);
        let mut seen_faces = std::collections::HashSet::with_capacity(self.triangles.len());
        let mut used = vec![false; self.vertices.len()];
        let mut parent: Vec<usize> = (0..self.triangles.len()).collect();
        let mut first_face_of_edge: HashMap<(u32, u32), usize> = HashMap::new();
        for (f, tri) in self.triangles.iter().enumerate() {
            let [a, b, c] = *tri;
            let in_range = tri.iter().all(|&i| (i as usize) < self.vertices.len());
            if !in_range || a == b || b == c || a == c {
                topo.degenerate_triangles += 1;
                continue;
            }
            let [pa, pb, pc] = tri.map(|i| self.vertices[i as usize]);
            if (pb - pa).cross(pc - pa).length_squared() == 0.0 {
                topo.degenerate_triangles += 1;
            }
            let mut key = [a, b, c];
            key.sort_unstable();
            if !seen_faces.insert(key) {
                topo.duplicate_triangles += 1;
            }
            for &i in tri {
                used[i as usize] = true;
            }
            for (u, v) in [(a, b), (b, c), (c, a)] {
                let (lo, hi, dir) = if u < v { (u, v, 1) } else { (v, u, -1) };
                let e = edges.entry((lo, hi)).or_insert((0, 0));
                e.0 += 1;
                e.1 += dir;
                match first_face_of_edge.get(&(lo, hi)) {
                    Some(&g) => {
                        let (rf, rg) = (find_root(&mut parent, f), find_root(&mut parent, g));
                        if rf != rg {
                            parent[rf] = rg;
                        }
                    }
                    None => {
                        first_face_of_edge.insert((lo, hi), f);
                    }
                }
            }
        }
        for &(count, dir_sum) in edges.values() {
            match count {
                1 => topo.boundary_edges += 1,
                2 if dir_sum != 0 => topo.misoriented_edges += 1,
                2 => {}
                _ => topo.nonmanifold_edges += 1,
            }
        }
        let valid_faces: Vec<usize> = (0..self.triangles.len())
            .filter(|&f| {
                let [a, b, c] = self.triangles[f];
                a != b
                    && b != c
                    && a != c
                    && self.triangles[f]
                        .iter()
                        .all(|&i| (i as usize) < self.vertices.len())
            })
            .collect();
        let mut roots: Vec<usize> = valid_faces
            .iter()
            .map(|&f| find_root(&mut parent, f))
            .collect();
        roots.sort_unstable();
        roots.dedup();
        topo.components = roots.len();
        topo.vertices_used = used.iter().filter(|&&u| u).count();
        topo.nonmanifold_vertices = self.count_pinched_vertices(&valid_faces);
        topo.euler_characteristic =
            topo.vertices_used as i64 - edges.len() as i64 + valid_faces.len() as i64;
        topo
    }

    /// Removes the edge-connected components whose area is below `min_area_mm2` (isolated speckle blobs
    /// and shreds of a surface) and the vertices no triangle uses any more. Returns the triangles removed.
    pub fn remove_small_components(&mut self, min_area_mm2: f64) -> usize {
        let n = self.vertices.len();
        let faces = self.triangles.len();
        let mut parent: Vec<usize> = (0..faces).collect();
        let mut first_face_of_edge: std::collections::HashMap<(u32, u32), usize> =
            std::collections::HashMap::with_capacity(faces * 2);
        let mut area = vec![0.0f64; faces];
        for (f, t) in self.triangles.iter().enumerate() {
            if t.iter().any(|&i| i as usize >= n) {
                continue;
            }
            let [a, b, c] = t.map(|i| self.vertices[i as usize]);
            area[f] = 0.5 * (b - a).cross(c - a).length();
            for k in 0..3 {
                let (x, y) = (t[k], t[(k + 1) % 3]);
                let key = (x.min(y), x.max(y));
                match first_face_of_edge.get(&key) {
                    Some(&g) => {
                        let (rf, rg) = (find_root(&mut parent, f), find_root(&mut parent, g));
                        if rf != rg {
                            parent[rf.max(rg)] = rf.min(rg);
                        }
                    }
                    None => {
                        first_face_of_edge.insert(key, f);
                    }
                }
            }
        }
        let mut component_area = vec![0.0f64; faces];
        for (f, a) in area.iter().enumerate() {
            let r = find_root(&mut parent, f);
            component_area[r] += a;
        }
        let keep: Vec<bool> = (0..faces)
            .map(|f| {
                let r = find_root(&mut parent, f);
                self.triangles[f].iter().all(|&i| (i as usize) < n)
                    && component_area[r] >= min_area_mm2
            })
            .collect();
        let removed = keep.iter().filter(|&&k| !k).count();
        if removed == 0 {
            return 0;
        }
        let mut index = vec![u32::MAX; n];
        let mut vertices = Vec::new();
        let mut normals = Vec::new();
        let has_normals = self.normals.len() == n;
        let mut triangles = Vec::with_capacity(faces - removed);
        for (f, t) in self.triangles.iter().enumerate() {
            if !keep[f] {
                continue;
            }
            triangles.push(t.map(|i| {
                let i = i as usize;
                if index[i] == u32::MAX {
                    index[i] = vertices.len() as u32;
                    vertices.push(self.vertices[i]);
                    if has_normals {
                        normals.push(self.normals[i]);
                    }
                }
                index[i]
            }));
        }
        self.vertices = vertices;
        self.normals = normals;
        self.triangles = triangles;
        removed
    }

    /// Gives every fan of triangles around a pinched vertex its own copy of the vertex, so a mesh whose
    /// edges are manifold becomes a manifold (with boundary). Pinches arise where clipping to the region
    /// of trust cuts a surface so that two pieces touch at a single vertex. Returns how many vertices
    /// were added.
    pub fn split_pinched_vertices(&mut self) -> usize {
        let n = self.vertices.len();
        let mut incident: Vec<Vec<u32>> = vec![Vec::new(); n];
        for (f, t) in self.triangles.iter().enumerate() {
            for &i in t {
                if (i as usize) < n {
                    incident[i as usize].push(f as u32);
                }
            }
        }
        let mut added = 0;
        let mut parent: Vec<usize> = Vec::new();
        let mut first_by_neighbour: Vec<(u32, usize)> = Vec::new();
        for (v, faces) in incident.iter().enumerate() {
            if faces.len() < 2 {
                continue;
            }
            parent.clear();
            parent.extend(0..faces.len());
            // Triangles around v sharing an edge (v, x) belong to one fan.
            first_by_neighbour.clear();
            for (k, &f) in faces.iter().enumerate() {
                for &x in &self.triangles[f as usize] {
                    if x as usize != v {
                        first_by_neighbour.push((x, k));
                    }
                }
            }
            first_by_neighbour.sort_unstable();
            for pair in first_by_neighbour.windows(2) {
                if pair[0].0 == pair[1].0 {
                    let (a, b) = (
                        find_root(&mut parent, pair[0].1),
                        find_root(&mut parent, pair[1].1),
                    );
                    if a != b {
                        parent[a.max(b)] = a.min(b);
                    }
                }
            }
            let roots: Vec<usize> = (0..faces.len())
                .map(|k| find_root(&mut parent, k))
                .collect();
            let mut fans: Vec<usize> = roots.clone();
            fans.sort_unstable();
            fans.dedup();
            // The fan holding the first incident triangle keeps v; every other fan gets a copy.
            for &fan in fans.iter().skip(1) {
                let copy = self.vertices.len() as u32;
                self.vertices.push(self.vertices[v]);
                if self.normals.len() == n + added {
                    self.normals.push(self.normals[v]);
                }
                added += 1;
                for (k, &f) in faces.iter().enumerate() {
                    if roots[k] == fan {
                        for i in self.triangles[f as usize].iter_mut() {
                            if *i as usize == v {
                                *i = copy;
                            }
                        }
                    }
                }
            }
        }
        if self.normals.len() != self.vertices.len() && !self.normals.is_empty() {
            self.normals.clear();
        }
        added
    }

    /// Vertices whose incident triangles form more than one fan: the link (opposite edges) of such a
    /// vertex falls apart into several pieces.
    fn count_pinched_vertices(&self, faces: &[usize]) -> usize {
        let mut link: Vec<Vec<(u32, u32)>> = vec![Vec::new(); self.vertices.len()];
        for &f in faces {
            let [a, b, c] = self.triangles[f];
            link[a as usize].push((b, c));
            link[b as usize].push((c, a));
            link[c as usize].push((a, b));
        }
        let mut pinched = 0;
        let mut ids: Vec<u32> = Vec::new();
        let mut parent: Vec<usize> = Vec::new();
        for edges in link.iter().filter(|e| e.len() > 1) {
            ids.clear();
            for &(u, v) in edges {
                ids.push(u);
                ids.push(v);
            }
            ids.sort_unstable();
            ids.dedup();
            parent.clear();
            parent.extend(0..ids.len());
            let idx = |x: u32| ids.binary_search(&x).unwrap_or(0);
            let mut pieces = ids.len();
            for &(u, v) in edges {
                let (ru, rv) = (
                    find_root(&mut parent, idx(u)),
                    find_root(&mut parent, idx(v)),
                );
                if ru != rv {
                    parent[ru] = rv;
                    pieces -= 1;
                }
            }
            if pieces > 1 {
                pinched += 1;
            }
        }
        pinched
    }
}

#[cfg(test)]
mod tests {

    #[test]
    fn small_components_are_removed_with_their_vertices() {
        // A unit square (two triangles, area 1) and a small triangle (area 0.005) apart from it.
        let mut mesh = Mesh {
            vertices: vec![
                DVec3::ZERO,
                DVec3::X,
                DVec3::new(1.0, 1.0, 0.0),
                DVec3::Y,
                DVec3::new(5.0, 0.0, 0.0),
                DVec3::new(5.1, 0.0, 0.0),
                DVec3::new(5.0, 0.1, 0.0),
            ],
            normals: vec![DVec3::Z; 7],
            triangles: vec![[0, 1, 2], [0, 2, 3], [4, 5, 6]],
        };
        assert_eq!(mesh.topology().components, 2);
        assert_eq!(mesh.clone().remove_small_components(0.001), 0);
        assert_eq!(mesh.remove_small_components(0.5), 1);
        assert_eq!(mesh.triangles, vec![[0, 1, 2], [0, 2, 3]]);
        assert_eq!((mesh.vertices.len(), mesh.normals.len()), (4, 4));
        // Below the square's area, nothing is left.
        assert_eq!(mesh.remove_small_components(1.5), 2);
        assert!(mesh.is_empty() && mesh.vertices.is_empty());
    }

    use super::*;

    fn tetrahedron() -> Mesh {
        Mesh {
            vertices: vec![DVec3::ZERO, DVec3::X, DVec3::Y, DVec3::Z],
            normals: vec![],
            // Outward-facing, counter-clockwise seen from outside.
            triangles: vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
        }
    }

    #[test]
    fn closed_tetrahedron_is_a_sphere() {
        let t = tetrahedron().topology();
        assert!(t.is_closed_manifold(), "{t:?}");
        assert_eq!(t.euler_characteristic, 2);
        assert_eq!(t.components, 1);
    }

    #[test]
    fn flipped_face_is_misoriented_and_missing_face_is_boundary() {
        let mut m = tetrahedron();
        m.triangles[3] = [1, 3, 2];
        let t = m.topology();
        assert_eq!(t.misoriented_edges, 3);
        m.triangles.pop();
        let t = m.topology();
        assert_eq!(t.boundary_edges, 3);
        assert!(!t.is_closed_manifold());
    }

    #[test]
    fn two_tetrahedra_sharing_a_vertex_pinch_it() {
        let mut m = tetrahedron();
        let offset = m.vertices.len() as u32;
        // Second tetrahedron sharing vertex 3 only.
        m.vertices.extend([
            DVec3::new(0.0, 0.0, 2.0),
            DVec3::new(1.0, 0.0, 2.0),
            DVec3::new(0.0, 1.0, 2.0),
        ]);
        let (a, b, c, d) = (3, offset, offset + 1, offset + 2);
        m.triangles
            .extend([[a, c, b], [a, b, d], [a, d, c], [b, c, d]]);
        let t = m.topology();
        assert_eq!(t.nonmanifold_vertices, 1);
        assert_eq!(t.components, 2);
        assert!(!t.is_oriented_manifold());
    }

    #[test]
    fn degenerate_and_duplicate_faces_are_counted() {
        let mut m = tetrahedron();
        m.triangles.push([0, 0, 1]);
        m.triangles.push([2, 1, 0]);
        let t = m.topology();
        assert_eq!(t.degenerate_triangles, 1);
        assert_eq!(t.duplicate_triangles, 1);
    }

    #[test]
    fn splitting_pinched_vertices_makes_a_manifold() {
        let mut m = tetrahedron();
        let offset = m.vertices.len() as u32;
        m.vertices.extend([
            DVec3::new(0.0, 0.0, 2.0),
            DVec3::new(1.0, 0.0, 2.0),
            DVec3::new(0.0, 1.0, 2.0),
        ]);
        let (a, b, c, d) = (3, offset, offset + 1, offset + 2);
        m.triangles
            .extend([[a, c, b], [a, b, d], [a, d, c], [b, c, d]]);
        m.normals = vec![DVec3::Z; m.vertices.len()];
        assert_eq!(m.split_pinched_vertices(), 1);
        let t = m.topology();
        assert!(t.is_closed_manifold(), "{t:?}");
        assert_eq!(t.components, 2);
        assert_eq!(t.euler_characteristic, 4);
        assert_eq!(m.normals.len(), m.vertices.len());
        // A manifold is left alone.
        assert_eq!(m.split_pinched_vertices(), 0);
    }
}
