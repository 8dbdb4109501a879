//! What a mesh's connectivity is: its topology counts (manifold, closed, oriented) and its
//! edge-connected pieces.

use super::{Mesh, find_root};

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

    /// The edge-connected component of every triangle, as the smallest triangle index in it
    /// (triangles with an out-of-range vertex are components of their own).
    pub fn triangle_components(&self) -> Vec<usize> {
        let n = self.vertices.len();
        let faces = self.triangles.len();
        let mut parent: Vec<usize> = (0..faces).collect();
        let mut first_face_of_edge: std::collections::HashMap<(u32, u32), usize> =
            std::collections::HashMap::with_capacity(faces * 2);
        for (f, t) in self.triangles.iter().enumerate() {
            if t.iter().any(|&i| i as usize >= n) {
                continue;
            }
            for k in 0..3 {
                let (x, y) = (t[k], t[(k + 1) % 3]);
                match first_face_of_edge.entry((x.min(y), x.max(y))) {
                    std::collections::hash_map::Entry::Occupied(e) => {
                        let (rf, rg) =
                            (find_root(&mut parent, f), find_root(&mut parent, *e.get()));
                        if rf != rg {
                            parent[rf.max(rg)] = rf.min(rg);
                        }
                    }
                    std::collections::hash_map::Entry::Vacant(e) => {
                        e.insert(f);
                    }
                }
            }
        }
        (0..faces).map(|f| find_root(&mut parent, f)).collect()
    }

    /// For every vertex, the triangles incident to it (faces with an index out of range are skipped).
    pub(super) fn incident_triangles(&self) -> Vec<Vec<u32>> {
        let n = self.vertices.len();
        let mut incident: Vec<Vec<u32>> = vec![Vec::new(); n];
        for (f, t) in self.triangles.iter().enumerate() {
            if t.iter().all(|&i| (i as usize) < n) {
                for &i in t {
                    incident[i as usize].push(f as u32);
                }
            }
        }
        incident
    }

    /// Groups the triangles `faces` around vertex `v` into fans (triangles sharing an edge at `v` belong
    /// to one fan): for each face, the index (into `faces`) of its fan's root; the roots, sorted.
    pub(super) fn fans_around(&self, v: u32, faces: &[u32]) -> (Vec<usize>, Vec<usize>) {
        let mut parent: Vec<usize> = (0..faces.len()).collect();
        let mut by_neighbour: Vec<(u32, usize)> = Vec::new();
        for (k, &f) in faces.iter().enumerate() {
            for &x in &self.triangles[f as usize] {
                if x != v {
                    by_neighbour.push((x, k));
                }
            }
        }
        by_neighbour.sort_unstable();
        for pair in by_neighbour.windows(2) {
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
        let mut fans = roots.clone();
        fans.sort_unstable();
        fans.dedup();
        (roots, fans)
    }

    /// Vertices whose incident triangles form more than one fan: the link (opposite edges) of such a
    /// vertex falls apart into several pieces.
    pub(super) fn count_pinched_vertices(&self, faces: &[usize]) -> usize {
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
