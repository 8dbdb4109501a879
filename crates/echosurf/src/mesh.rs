//! The triangle mesh shared by the surfacer, the mesh readers and writers, the metrics and the renderer.

use glam::DVec3;
use rayon::prelude::*;

/// An indexed triangle mesh in millimetres (Reference frame). `normals` is either empty or one unit
/// normal per vertex. Triangles wind counter-clockwise seen from the side their normal points to.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Mesh {
    pub vertices: Vec<DVec3>,
    pub normals: Vec<DVec3>,
    pub triangles: Vec<[u32; 3]>,
}

/// Distance from `p` to the segment from `a` to `b`.
fn distance_to_segment(p: DVec3, a: DVec3, b: DVec3) -> f64 {
    let ab = b - a;
    let t = if ab.length_squared() > 0.0 {
        ((p - a).dot(ab) / ab.length_squared()).clamp(0.0, 1.0)
    } else {
        0.0
    };
    p.distance(a + t * ab)
}

/// A mesh's boundary edges as their triangles run them ([`Mesh::bridge_near_pieces`]).
struct DirectedBoundary {
    /// (from, to, triangle), pinched vertices' edges left out.
    edges: Vec<(u32, u32, usize)>,
    /// A boundary vertex's edge out: (to, triangle).
    from: std::collections::HashMap<u32, (u32, usize)>,
    /// A boundary vertex's edge in: (from, triangle).
    to: std::collections::HashMap<u32, (u32, usize)>,
    /// Per vertex: starts or ends more than one boundary edge.
    ambiguous: Vec<bool>,
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

    /// Removes the edge-connected components whose area is below `min_area_mm2` (isolated speckle blobs
    /// and shreds of a surface) and the vertices no triangle uses any more. Returns the triangles removed.
    pub fn remove_small_components(&mut self, min_area_mm2: f64) -> usize {
        let n = self.vertices.len();
        let component = self.triangle_components();
        let mut component_area = vec![0.0f64; self.triangles.len()];
        let valid = |t: &[u32; 3]| t.iter().all(|&i| (i as usize) < n);
        for (f, t) in self.triangles.iter().enumerate() {
            if valid(t) {
                component_area[component[f]] += self.triangle_area_mm2(*t);
            }
        }
        let keep: Vec<bool> = (0..self.triangles.len())
            .map(|f| valid(&self.triangles[f]) && component_area[component[f]] >= min_area_mm2)
            .collect();
        self.retain_triangles(&keep)
    }

    /// Closes every hole whose boundary loop is at most `max_perimeter_mm` long with a fan of triangles
    /// around the mean of the loop's vertices; a component's longest loop is its outer edge and stays
    /// open. Loops through a vertex with two boundary fans are left alone (split pinched vertices
    /// first). For a manifold mesh with consistent winding; returns the holes closed.
    pub fn fill_small_holes(&mut self, max_perimeter_mm: f64) -> usize {
        let n = self.vertices.len();
        let valid = |t: &[u32; 3]| t.iter().all(|&i| (i as usize) < n);
        let mut directed: std::collections::HashMap<(u32, u32), usize> =
            std::collections::HashMap::with_capacity(self.triangles.len() * 3);
        for (f, t) in self.triangles.iter().enumerate().filter(|(_, t)| valid(t)) {
            for k in 0..3 {
                directed.insert((t[k], t[(k + 1) % 3]), f);
            }
        }
        // Boundary edges (no twin), keyed by their start; a vertex starting two is ambiguous.
        let mut next: std::collections::HashMap<u32, (u32, usize)> = Default::default();
        let mut ambiguous = std::collections::HashSet::new();
        let mut boundary: Vec<(u32, u32, usize)> = directed
            .iter()
            .filter(|((a, b), _)| !directed.contains_key(&(*b, *a)))
            .map(|(&(a, b), &f)| (a, b, f))
            .collect();
        boundary.sort_unstable();
        for &(a, b, f) in &boundary {
            if next.insert(a, (b, f)).is_some() {
                ambiguous.insert(a);
            }
        }
        let component = self.triangle_components();
        // Loops: (vertices in boundary order, perimeter, component).
        let mut loops: Vec<(Vec<u32>, f64, usize)> = Vec::new();
        let mut seen = std::collections::HashSet::new();
        for &(start, _, f) in &boundary {
            if seen.contains(&start) {
                continue;
            }
            let (mut cycle, mut perimeter, mut v, mut ok) = (Vec::new(), 0.0, start, true);
            loop {
                if !seen.insert(v) {
                    ok &= v == start;
                    break;
                }
                ok &= !ambiguous.contains(&v);
                cycle.push(v);
                let Some(&(w, _)) = next.get(&v) else {
                    ok = false;
                    break;
                };
                perimeter += self.vertices[v as usize].distance(self.vertices[w as usize]);
                v = w;
            }
            if ok && cycle.len() >= 3 {
                loops.push((cycle, perimeter, component[f]));
            }
        }
        let mut longest: std::collections::HashMap<usize, f64> = Default::default();
        for (_, perimeter, c) in &loops {
            let l = longest.entry(*c).or_insert(0.0);
            *l = l.max(*perimeter);
        }
        let has_normals = self.normals.len() == n;
        let mut filled = 0;
        for (cycle, perimeter, c) in loops {
            if perimeter > max_perimeter_mm || perimeter >= longest[&c] {
                continue;
            }
            let centre = self.vertices.len() as u32;
            let k = cycle.len() as f64;
            self.vertices.push(
                cycle
                    .iter()
                    .map(|&v| self.vertices[v as usize])
                    .sum::<DVec3>()
                    / k,
            );
            if has_normals {
                let normal: DVec3 = cycle.iter().map(|&v| self.normals[v as usize]).sum();
                self.normals.push(normal.normalize_or(DVec3::Z));
            }
            // The loop runs along the existing triangles' edges a -> b; the new ones use b -> a.
            for (i, &a) in cycle.iter().enumerate() {
                let b = cycle[(i + 1) % cycle.len()];
                self.triangles.push([b, a, centre]);
            }
            filled += 1;
        }
        filled
    }

    /// Per vertex, whether it lies within `reach_mm` of a vertex flagged in `seeds` (one per vertex)
    /// along the mesh's edges (shortest path, Dijkstra). Growing along edges rather than through space
    /// keeps the growth on the surface it starts from: a nearby sheet that is not connected to a seed
    /// stays out.
    pub fn within_reach_along_edges(&self, seeds: &[bool], reach_mm: f64) -> Vec<bool> {
        let n = self.vertices.len();
        let neighbours = edge_neighbours(n, &self.triangles);
        // Non-negative f64 bit patterns order like the values, so the heap can hold them as u64.
        let mut distance = vec![f64::INFINITY; n];
        let mut heap = std::collections::BinaryHeap::new();
        for (i, _) in seeds.iter().enumerate().take(n).filter(|(_, s)| **s) {
            distance[i] = 0.0;
            heap.push(std::cmp::Reverse((0u64, i)));
        }
        while let Some(std::cmp::Reverse((bits, i))) = heap.pop() {
            let d = f64::from_bits(bits);
            if d > distance[i] {
                continue;
            }
            for &j in &neighbours[i] {
                let j = j as usize;
                let through = d + self.vertices[i].distance(self.vertices[j]);
                if through <= reach_mm && through < distance[j] {
                    distance[j] = through;
                    heap.push(std::cmp::Reverse((through.to_bits(), j)));
                }
            }
        }
        distance.iter().map(|d| d.is_finite()).collect()
    }

    /// Removes the triangles with a vertex no echo backs (`backed`; the pipeline's test allows for the
    /// gaps between frames): in a gap of the data (outside the kept band, in a shadow) the fitted field
    /// can overshoot into a ridge that nothing echoed, and the sheet drawn through it is a flap hanging
    /// off the wall. A surface is only as good as the echoes near it. Where two kept fans then touch at
    /// one vertex, each gets its own copy of it (the mesh stays manifold). Returns the triangles removed.
    pub fn remove_triangles_not_backed(&mut self, backed: impl Fn(DVec3) -> bool + Sync) -> usize {
        if self.triangles.is_empty() {
            return 0;
        }
        let backed: Vec<bool> = self.vertices.par_iter().map(|&v| backed(v)).collect();
        let keep: Vec<bool> = self
            .triangles
            .iter()
            .map(|t| {
                t.iter()
                    .all(|&i| backed.get(i as usize).copied().unwrap_or(false))
            })
            .collect();
        let removed = self.retain_triangles(&keep);
        if removed > 0 {
            self.split_pinched_vertices();
        }
        removed
    }

    /// Removes the edge-connected components that fewer than `min_frames` frames back: a frame backs a
    /// component when one of its echoes (`echoes[k]`, seen in frame `echo_frames[k]`) lies within
    /// `radius_mm` of one of the component's vertices (for a surfacer's mesh, whose vertices lie a
    /// lattice cell apart, about the distance to the surface). A wall is seen again and again as the probe
    /// passes over it; a piece that one frame's speckle (or none: an overshoot of the fitted field)
    /// made is not. Returns the components removed.
    pub fn remove_components_seen_in_few_frames(
        &mut self,
        echoes: &[DVec3],
        echo_frames: &[u32],
        radius_mm: f64,
        min_frames: usize,
    ) -> usize {
        if min_frames == 0 || self.triangles.is_empty() {
            return 0;
        }
        let n = self.vertices.len();
        let component = self.triangle_components();
        let mut vertex_component = vec![usize::MAX; n];
        for (f, t) in self.triangles.iter().enumerate() {
            for &i in t.iter().filter(|&&i| (i as usize) < n) {
                vertex_component[i as usize] = component[f];
            }
        }
        let mut frames_seen: std::collections::HashMap<usize, Vec<u32>> =
            std::collections::HashMap::new();
        if let Some(buckets) = crate::spatial::PointBuckets::new(echoes, radius_mm) {
            for (v, &c) in self.vertices.iter().zip(&vertex_component) {
                if c == usize::MAX {
                    continue;
                }
                let seen = frames_seen.entry(c).or_default();
                if seen.len() >= min_frames {
                    continue;
                }
                buckets.visit_within(*v, radius_mm, &mut |k, _| {
                    // An echo without a frame (slices of unequal length) backs nothing.
                    let Some(&frame) = echo_frames.get(k) else {
                        return true;
                    };
                    if let Err(at) = seen.binary_search(&frame) {
                        seen.insert(at, frame);
                    }
                    seen.len() < min_frames
                });
            }
        }
        let backed = |c: usize| frames_seen.get(&c).is_some_and(|s| s.len() >= min_frames);
        let mut removed: Vec<usize> = component.iter().copied().filter(|&c| !backed(c)).collect();
        removed.sort_unstable();
        removed.dedup();
        let keep: Vec<bool> = component.iter().map(|&c| backed(c)).collect();
        self.retain_triangles(&keep);
        removed.len()
    }

    /// Peels up to `rings` rings of triangles off the rim (the edges with one triangle) without changing
    /// the topology: no piece is cut, pinched or removed. The rim of a surface is where its echo fades
    /// and the least accurate part of it. Per ring, in triangle order, a triangle with a rim edge goes if
    /// its third vertex is not on the rim (an ear of one edge: the rim moves in past that vertex) or if
    /// it has two rim edges (a corner: its tip vertex goes); a triangle that would cut a neck (third
    /// vertex already on the rim) or whose removal would delete a piece (three rim edges) stays. Returns
    /// the triangles removed.
    pub fn trim_rim(&mut self, rings: usize) -> usize {
        use std::collections::HashMap;
        let n = self.vertices.len();
        if rings == 0
            || self
                .triangles
                .iter()
                .any(|t| t.iter().any(|&i| i as usize >= n))
        {
            return 0;
        }
        let key = |a: u32, b: u32| (a.min(b), a.max(b));
        let edges_of = |t: [u32; 3]| [(t[0], t[1], t[2]), (t[1], t[2], t[0]), (t[2], t[0], t[1])];
        // Triangles per edge, and rim edges per vertex, kept current as triangles go.
        let mut per_edge: HashMap<(u32, u32), u32> =
            HashMap::with_capacity(self.triangles.len() * 2);
        for &t in &self.triangles {
            for (a, b, _) in edges_of(t) {
                *per_edge.entry(key(a, b)).or_default() += 1;
            }
        }
        let mut rim_edges_at = vec![0u32; n];
        for (&(a, b), &count) in &per_edge {
            if count == 1 {
                rim_edges_at[a as usize] += 1;
                rim_edges_at[b as usize] += 1;
            }
        }
        let mut keep = vec![true; self.triangles.len()];
        let mut removed = 0;
        for _ in 0..rings {
            let ring: Vec<usize> = (0..self.triangles.len())
                .filter(|&f| {
                    keep[f]
                        && edges_of(self.triangles[f])
                            .iter()
                            .any(|&(a, b, _)| per_edge[&key(a, b)] == 1)
                })
                .collect();
            let before = removed;
            for f in ring {
                let t = self.triangles[f];
                let rim: Vec<(u32, u32, u32)> = edges_of(t)
                    .into_iter()
                    .filter(|&(a, b, _)| per_edge[&key(a, b)] == 1)
                    .collect();
                let peelable = match rim.as_slice() {
                    [(_, _, opposite)] => rim_edges_at[*opposite as usize] == 0,
                    [_, _] => true,
                    _ => false,
                };
                if !peelable {
                    continue;
                }
                keep[f] = false;
                removed += 1;
                for (a, b, _) in edges_of(t) {
                    let count = per_edge
                        .get_mut(&key(a, b))
                        .expect("edge of a kept triangle");
                    *count -= 1;
                    // 2 -> 1: the edge joins the rim; 1 -> 0: it leaves with the triangle.
                    for v in [a, b] {
                        match *count {
                            1 => rim_edges_at[v as usize] += 1,
                            0 => rim_edges_at[v as usize] -= 1,
                            _ => {}
                        }
                    }
                }
            }
            if removed == before {
                break;
            }
        }
        self.retain_triangles(&keep);
        removed
    }

    /// Keeps the triangles whose flag in `keep` (one per triangle) is set, and the vertices they use
    /// (renumbered in order of first use). Returns the triangles removed.
    pub fn retain_triangles(&mut self, keep: &[bool]) -> usize {
        let n = self.vertices.len();
        let faces = self.triangles.len();
        let removed = (0..faces)
            .filter(|&f| !keep.get(f).copied().unwrap_or(false))
            .count();
        if removed == 0 {
            return 0;
        }
        let mut index = vec![u32::MAX; n];
        let mut vertices = Vec::new();
        let mut normals = Vec::new();
        let has_normals = self.normals.len() == n;
        let mut triangles = Vec::with_capacity(faces - removed);
        for (f, t) in self.triangles.iter().enumerate() {
            if !keep[f] || t.iter().any(|&i| i as usize >= n) {
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

    /// For every vertex, the triangles incident to it (faces with an index out of range are skipped).
    fn incident_triangles(&self) -> Vec<Vec<u32>> {
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
    fn fans_around(&self, v: u32, faces: &[u32]) -> (Vec<usize>, Vec<usize>) {
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

    /// Joins the two fans of a vertex where two pieces of a surface touch at that vertex alone: one
    /// triangle across the narrower of the two wedges between the fans (from one fan's boundary edge
    /// at the vertex to the other's), where that triangle's far edge is at most `max_gap_mm` long and
    /// it faces the way both fans do (which must agree). The pieces then form one surface, joined
    /// along edges, instead of two that touch at a point; a pinch that does not qualify (three or more
    /// fans, a closed fan, a wide or folded wedge) is left for [`Mesh::split_pinched_vertices`].
    /// Returns how many vertices were joined. No vertex is added or moved.
    pub fn join_pinched_fans(&mut self, max_gap_mm: f64) -> usize {
        let n = self.vertices.len();
        let incident = self.incident_triangles();
        // Vertices a join has used: their fans change, so they are not considered again in this pass.
        let mut used = vec![false; n];
        let mut added = Vec::new();
        for v in 0..n {
            let faces = &incident[v];
            if used[v] || faces.len() < 2 {
                continue;
            }
            let (roots, fans) = self.fans_around(v as u32, faces);
            if fans.len() != 2 {
                continue;
            }
            // Per fan: its one boundary edge out of v (v -> out) and one into v (into -> v), and its
            // area-weighted normal.
            let open_fan = |fan: usize| -> Option<(u32, u32, DVec3)> {
                let (mut outs, mut ins, mut normal) = (Vec::new(), Vec::new(), DVec3::ZERO);
                for (k, &f) in faces.iter().enumerate() {
                    if roots[k] != fan {
                        continue;
                    }
                    let t = self.triangles[f as usize];
                    let i = t.iter().position(|&x| x as usize == v)?;
                    outs.push(t[(i + 1) % 3]);
                    ins.push(t[(i + 2) % 3]);
                    let [a, b, c] = t.map(|x| self.vertices[x as usize]);
                    normal += (b - a).cross(c - a);
                }
                let out: Vec<u32> = outs.iter().copied().filter(|x| !ins.contains(x)).collect();
                let into: Vec<u32> = ins.iter().copied().filter(|x| !outs.contains(x)).collect();
                (out.len() == 1 && into.len() == 1).then(|| (out[0], into[0], normal))
            };
            let (Some((a_out, a_in, na)), Some((b_out, b_in, nb))) =
                (open_fan(fans[0]), open_fan(fans[1]))
            else {
                continue;
            };
            if na.normalize_or_zero().dot(nb.normalize_or_zero()) < 0.5 {
                continue;
            }
            let p = |i: u32| self.vertices[i as usize];
            // (a_out, v, b_in) closes the wedge from A's outgoing boundary to B's incoming one; (b_out,
            // v, a_in) the other wedge. Both keep the winding: each shares a boundary edge of each fan,
            // traversed the other way.
            let mut candidates = [
                (p(a_out).distance(p(b_in)), [a_out, v as u32, b_in]),
                (p(b_out).distance(p(a_in)), [b_out, v as u32, a_in]),
            ];
            candidates.sort_by(|x, y| x.0.total_cmp(&y.0));
            for (gap, t) in candidates {
                let (x, y) = (t[0], t[2]);
                // Written so that a NaN gap or bound never joins.
                let narrow = gap <= max_gap_mm;
                if !narrow || x == y || used[x as usize] || used[y as usize] {
                    continue;
                }
                // The far edge must be new, or the join would make it non-manifold.
                if incident[x as usize]
                    .iter()
                    .any(|&f| self.triangles[f as usize].contains(&y))
                {
                    continue;
                }
                let [a, b, c] = t.map(p);
                let nt = (b - a).cross(c - a);
                if nt.length() <= 1e-12 || nt.dot(na) <= 0.0 || nt.dot(nb) <= 0.0 {
                    continue;
                }
                added.push(t);
                for i in t {
                    used[i as usize] = true;
                }
                break;
            }
        }
        let joined = added.len();
        self.triangles.extend(added);
        joined
    }

    /// Joins pieces of a surface whose boundaries pass within `max_gap_mm` of each other where they
    /// continue one another, and closes the seam between them. A bridge starts at the narrowest pair
    /// of facing boundary edges of two different pieces (a0 -> a1 on one, b0 -> b1 on the other, a0
    /// near b1 and a1 near b0) with a quad of two triangles, and is zipped along both boundaries from
    /// there (one triangle at a time, taking the shorter new edge, as contour stitching does) while
    /// the vertex each triangle takes lies within `max_gap_mm` of the other boundary. Every triangle
    /// must face the way both pieces do there (normals' dot at least 0.5): a gap across the tangent
    /// plane (a second wall beneath) cannot be bridged, since the quad would stand at right angles to
    /// both pieces. The narrowest gaps go first, and a pair of pieces (or of groups already bridged)
    /// is bridged once, along one seam, so no handle is made. The new triangles traverse each
    /// boundary edge they close the other way and extend single fans, so an oriented manifold stays
    /// one; no vertex is added or moved. A gap bound that is not a positive finite distance bridges
    /// nothing. Returns the bridges made.
    pub fn bridge_near_pieces(&mut self, max_gap_mm: f64) -> usize {
        // Written so that a NaN bound bridges nothing.
        if !(max_gap_mm > 0.0 && max_gap_mm.is_finite()) || self.triangles.is_empty() {
            return 0;
        }
        let boundary = self.directed_boundary();
        let component = self.triangle_components();
        let candidates = self.bridge_quads(&boundary, &component, max_gap_mm);
        let mut group: Vec<usize> = (0..self.triangles.len()).collect();
        let mut used = boundary.ambiguous.clone();
        let mut added: Vec<[u32; 3]> = Vec::new();
        let mut bridges = 0;
        for (_, i, j, quad) in candidates {
            let (a0, a1, fa) = boundary.edges[i];
            let (b0, b1, fb) = boundary.edges[j];
            let (ga, gb) = (
                find_root(&mut group, component[fa]),
                find_root(&mut group, component[fb]),
            );
            if ga == gb || [a0, a1, b0, b1].iter().any(|&v| used[v as usize]) {
                continue;
            }
            group[ga.max(gb)] = ga.min(gb);
            for v in [a0, a1, b0, b1] {
                used[v as usize] = true;
            }
            added.extend(quad);
            bridges += 1;
            // Zip on from each side of the quad. Towards a1: the front is the new edge b0 -> a1; the
            // next triangle runs a1 -> b0 and closes either the first piece's boundary edge out of
            // a1 or the second's into b0. Towards a0: the front a0 -> b1, the next triangle runs
            // b1 -> a0 and closes the first piece's edge into a0 or the second's out of b1.
            for (front, last) in [((a1, b0), quad[1]), ((b1, a0), quad[0])] {
                self.zip_seam(&boundary, front, last, max_gap_mm, &mut used, &mut added);
            }
        }
        self.triangles.extend(added);
        bridges
    }

    /// The boundary edges (used by one triangle) as their triangle runs them, in triangle order, with
    /// each boundary vertex's edge out and edge in. A vertex starting or ending two of them (a pinch)
    /// is marked ambiguous and its edges are left out.
    fn directed_boundary(&self) -> DirectedBoundary {
        let n = self.vertices.len();
        let valid = |t: &[u32; 3]| t.iter().all(|&i| (i as usize) < n);
        let mut undirected: std::collections::HashMap<(u32, u32), usize> =
            std::collections::HashMap::with_capacity(self.triangles.len() * 3);
        for t in self.triangles.iter().filter(|t| valid(t)) {
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                *undirected.entry((a.min(b), a.max(b))).or_default() += 1;
            }
        }
        let mut boundary = DirectedBoundary {
            edges: Vec::new(),
            from: Default::default(),
            to: Default::default(),
            ambiguous: vec![false; n],
        };
        for (f, t) in self.triangles.iter().enumerate().filter(|(_, t)| valid(t)) {
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                if a != b && undirected[&(a.min(b), a.max(b))] == 1 {
                    boundary.edges.push((a, b, f));
                    boundary.ambiguous[a as usize] |= boundary.from.insert(a, (b, f)).is_some();
                    boundary.ambiguous[b as usize] |= boundary.to.insert(b, (a, f)).is_some();
                }
            }
        }
        let ambiguous = &boundary.ambiguous;
        boundary
            .edges
            .retain(|&(a, b, _)| !ambiguous[a as usize] && !ambiguous[b as usize]);
        boundary
    }

    /// Unit normal of a triangle by the right-hand rule, zero for a degenerate one.
    pub(crate) fn triangle_unit_normal(&self, t: [u32; 3]) -> DVec3 {
        let [a, b, c] = t.map(|i| self.vertices[i as usize]);
        (b - a).cross(c - a).normalize_or_zero()
    }

    /// Every quad that could start a bridge, narrowest first: (summed gap, edge i, edge j, the quad's
    /// two triangles) for each pair of boundary edges i -> j of different pieces that face each other
    /// within `max_gap_mm` at both ends, with pieces and quad all facing alike.
    fn bridge_quads(
        &self,
        boundary: &DirectedBoundary,
        component: &[usize],
        max_gap_mm: f64,
    ) -> Vec<(f64, usize, usize, [[u32; 3]; 2])> {
        let p = |i: u32| self.vertices[i as usize];
        let edges = &boundary.edges;
        let midpoints: Vec<DVec3> = edges.iter().map(|&(a, b, _)| 0.5 * (p(a) + p(b))).collect();
        let Some(buckets) = crate::spatial::PointBuckets::new(&midpoints, max_gap_mm) else {
            return Vec::new();
        };
        let mut candidates = Vec::new();
        for (i, &(a0, a1, fa)) in edges.iter().enumerate() {
            let na = self.triangle_unit_normal(self.triangles[fa]);
            buckets.visit_within(midpoints[i], max_gap_mm, &mut |j, _| {
                let (b0, b1, fb) = edges[j];
                // Each pair once; the condition below is symmetric in the two edges.
                if j <= i || component[fa] == component[fb] {
                    return true;
                }
                let (gap_a0, gap_a1) = (p(a0).distance(p(b1)), p(a1).distance(p(b0)));
                if !(gap_a0 <= max_gap_mm && gap_a1 <= max_gap_mm) {
                    return true;
                }
                let nb = self.triangle_unit_normal(self.triangles[fb]);
                if na.dot(nb) < 0.5 {
                    return true;
                }
                // The quad a1 -> a0 -> b1 -> b0, cut along its shorter diagonal if that faces right.
                let along_a1_b1 = [[a1, a0, b1], [a1, b1, b0]];
                let along_a0_b0 = [[a0, b1, b0], [a0, b0, a1]];
                let mut cuts = [
                    (p(a1).distance(p(b1)), along_a1_b1),
                    (p(a0).distance(p(b0)), along_a0_b0),
                ];
                cuts.sort_by(|x, y| x.0.total_cmp(&y.0));
                let faces_alike = |t: [u32; 3]| {
                    let nt = self.triangle_unit_normal(t);
                    nt.dot(na) >= 0.5 && nt.dot(nb) >= 0.5
                };
                if let Some((_, quad)) = cuts
                    .into_iter()
                    .find(|(_, quad)| quad.iter().all(|&t| faces_alike(t)))
                {
                    candidates.push((gap_a0 + gap_a1, i, j, quad));
                }
                true
            });
        }
        candidates.sort_by(|x, y| x.0.total_cmp(&y.0).then((x.1, x.2).cmp(&(y.1, y.2))));
        candidates
    }

    /// Zips a seam on from its front edge `y -> x` (the edge of the last triangle laid, `last`): `x`
    /// advances along its piece's boundary edges (out of x), `y` against them (into y), every new
    /// triangle runs x -> y -> (the vertex taken), and the zip stops where neither next vertex lies
    /// within `max_gap_mm` of the other side's front or the triangle would not face alike.
    fn zip_seam(
        &self,
        boundary: &DirectedBoundary,
        (mut x, mut y): (u32, u32),
        last: [u32; 3],
        max_gap_mm: f64,
        used: &mut [bool],
        added: &mut Vec<[u32; 3]>,
    ) {
        let p = |i: u32| self.vertices[i as usize];
        let mut previous = self.triangle_unit_normal(last);
        for _ in 0..boundary.edges.len() {
            let next_x = boundary.from.get(&x).copied();
            let next_y = boundary.to.get(&y).copied();
            // Distance from a vertex to the other side's front: its edge on from the front vertex
            // (or the vertex alone at the end of a boundary).
            let to_front = |v: u32, front: u32, on: Option<(u32, usize)>| match on {
                Some((w, _)) => distance_to_segment(p(v), p(front), p(w)),
                None => p(v).distance(p(front)),
            };
            // (new triangle, new edge's length, the vertex it takes, the triangle whose boundary edge
            // it closes, whether x advances)
            let mut options: Vec<([u32; 3], f64, u32, usize, bool)> = Vec::new();
            if let Some((v, f)) = next_x
                && to_front(v, y, next_y) <= max_gap_mm
            {
                options.push(([x, y, v], p(v).distance(p(y)), v, f, true));
            }
            if let Some((v, f)) = next_y
                && to_front(v, x, next_x) <= max_gap_mm
            {
                options.push(([x, y, v], p(v).distance(p(x)), v, f, false));
            }
            options.retain(|&(t, _, v, f, _)| {
                let nt = self.triangle_unit_normal(t);
                !used[v as usize]
                    && nt.dot(previous) >= 0.5
                    && nt.dot(self.triangle_unit_normal(self.triangles[f])) >= 0.5
            });
            options.sort_by(|u, w| u.1.total_cmp(&w.1));
            let Some(&(t, _, v, _, advances_x)) = options.first() else {
                break;
            };
            added.push(t);
            used[v as usize] = true;
            previous = self.triangle_unit_normal(t);
            if advances_x {
                x = v;
            } else {
                y = v;
            }
        }
    }

    /// Gives every fan of triangles around a pinched vertex its own copy of the vertex, so a mesh whose
    /// edges are manifold becomes a manifold (with boundary). Pinches arise where clipping to the region
    /// of trust cuts a surface so that two pieces touch at a single vertex. Returns how many vertices
    /// were added.
    pub fn split_pinched_vertices(&mut self) -> usize {
        let n = self.vertices.len();
        let incident = self.incident_triangles();
        let mut added = 0;
        for (v, faces) in incident.iter().enumerate() {
            if faces.len() < 2 {
                continue;
            }
            let (roots, fans) = self.fans_around(v as u32, faces);
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

    #[test]
    fn pieces_that_too_few_frames_echo_are_removed() {
        // Square A at the origin, square B 10 mm away.
        let square = |x: f64| {
            [
                DVec3::new(x, 0.0, 0.0),
                DVec3::new(x + 1.0, 0.0, 0.0),
                DVec3::new(x + 1.0, 1.0, 0.0),
                DVec3::new(x, 1.0, 0.0),
            ]
        };
        let mesh = Mesh {
            vertices: [square(0.0), square(10.0)].concat(),
            normals: Vec::new(),
            triangles: vec![[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]],
        };
        // A: echoes from frames 1, 2, 3 within 0.5 mm of a vertex (frame 2 twice; distances are taken
        // to vertices, which the surfacer places a lattice cell apart). B: many echoes, all from frame 5,
        // and one from frame 6 just beyond the radius. Far from both: frames 7, 8, 9.
        let echoes = [
            (DVec3::new(0.2, 0.2, 0.4), 1),
            (DVec3::new(0.9, 0.1, -0.3), 2),
            (DVec3::new(0.1, 0.9, 0.1), 2),
            (DVec3::new(1.3, 1.0, 0.0), 3),
            (DVec3::new(10.5, 0.5, 0.2), 5),
            (DVec3::new(10.2, 0.9, -0.2), 5),
            (DVec3::new(11.0, 1.0, 0.45), 5),
            (DVec3::new(11.0, 1.0, 0.51), 6),
            (DVec3::new(5.0, 5.0, 0.0), 7),
            (DVec3::new(5.0, 5.0, 0.0), 8),
            (DVec3::new(5.0, 5.0, 0.0), 9),
        ];
        let (points, frames): (Vec<DVec3>, Vec<u32>) = echoes.into_iter().unzip();
        let remove = |min_frames: usize| {
            let mut m = mesh.clone();
            let removed = m.remove_components_seen_in_few_frames(&points, &frames, 0.5, min_frames);
            (removed, m)
        };
        assert_eq!(remove(0).0, 0);
        let (removed, one) = remove(1);
        assert_eq!((removed, one.triangles.len()), (0, 4));
        // B has one frame within reach: two frames leave only A.
        let (removed, kept) = remove(2);
        assert_eq!(removed, 1);
        assert_eq!(kept.vertices, square(0.0).to_vec());
        assert_eq!(kept.triangles, vec![[0, 1, 2], [0, 2, 3]]);
        assert_eq!(remove(3).0, 1);
        // A has three frames: four remove everything.
        let (removed, none) = remove(4);
        assert_eq!(removed, 2);
        assert!(none.is_empty());
        // No echoes at all: no piece is backed.
        let mut m = mesh.clone();
        assert_eq!(m.remove_components_seen_in_few_frames(&[], &[], 0.5, 1), 2);
    }

    /// A `k` x `k` grid of unit squares in z = 0 (two triangles each, facing +z) without the squares
    /// listed in `holes` (as (column, row)).
    fn grid_with_holes(k: u32, holes: &[(u32, u32)]) -> Mesh {
        let mut mesh = Mesh::default();
        for j in 0..=k {
            for i in 0..=k {
                mesh.vertices.push(DVec3::new(i as f64, j as f64, 0.0));
                mesh.normals.push(DVec3::Z);
            }
        }
        let at = |i: u32, j: u32| j * (k + 1) + i;
        for j in 0..k {
            for i in 0..k {
                if !holes.contains(&(i, j)) {
                    let (a, b, c, d) = (at(i, j), at(i + 1, j), at(i + 1, j + 1), at(i, j + 1));
                    mesh.triangles.push([a, b, c]);
                    mesh.triangles.push([a, c, d]);
                }
            }
        }
        mesh
    }

    /// Within `max_distance_mm` of one of `echoes`.
    fn near_any(echoes: &[DVec3], max_distance_mm: f64) -> impl Fn(DVec3) -> bool + Sync {
        let buckets = crate::spatial::PointBuckets::new(echoes, max_distance_mm);
        move |v| buckets.as_ref().is_some_and(|b| b.contains(v))
    }

    #[test]
    fn triangles_far_from_every_echo_are_removed() {
        // Echoes 0.3 mm above the left half of a 10 x 10 grid (x <= 5), none over the right half.
        let mut echoes = Vec::new();
        for i in 0..=10 {
            for j in 0..=20 {
                echoes.push(DVec3::new(i as f64 * 0.5, j as f64 * 0.5, 0.3));
            }
        }
        let grid = grid_with_holes(10, &[]);
        // Within 2 mm: the vertices at x <= 6 (x = 7 is sqrt(4.09) mm away), so 6 of the 10 columns of
        // squares stay.
        let mut mesh = grid.clone();
        assert_eq!(mesh.remove_triangles_not_backed(near_any(&echoes, 2.0)), 80);
        assert_eq!(mesh.triangles.len(), 120);
        assert!(mesh.vertices.iter().all(|v| v.x <= 6.0));
        assert_eq!(mesh.vertices.len(), 7 * 11);
        // A reach past the far edge keeps everything; no echoes at all back nothing.
        let mut all = grid.clone();
        assert_eq!(all.remove_triangles_not_backed(near_any(&echoes, 5.1)), 0);
        assert_eq!(all.remove_triangles_not_backed(near_any(&[], 1.0)), 200);
        assert!(all.is_empty());
    }

    #[test]
    fn removing_triangles_far_from_echoes_leaves_no_pinch() {
        // An open fan of four triangles around the origin; the middle two share the vertex x, which
        // no echo backs. Without them the outer two touch at the origin only, which each then holds
        // a copy of.
        let x = DVec3::new(-0.2, 1.5, 0.0);
        let mut mesh = Mesh {
            vertices: vec![
                DVec3::ZERO,
                DVec3::new(1.0, 0.0, 0.0),
                DVec3::new(1.0, 1.0, 0.0),
                x,
                DVec3::new(-1.0, 0.0, 0.0),
                DVec3::new(-1.0, -1.0, 0.0),
            ],
            normals: Vec::new(),
            triangles: vec![[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 5]],
        };
        assert_eq!(mesh.topology().nonmanifold_vertices, 0);
        let echoes: Vec<DVec3> = mesh.vertices.iter().copied().filter(|&v| v != x).collect();
        assert_eq!(mesh.remove_triangles_not_backed(near_any(&echoes, 0.5)), 2);
        let topology = mesh.topology();
        assert_eq!(topology.nonmanifold_vertices, 0, "{topology:?}");
        assert_eq!(topology.components, 2);
        assert_eq!(mesh.vertices.len(), 6);
        assert_eq!(
            mesh.vertices.iter().filter(|&&v| v == DVec3::ZERO).count(),
            2
        );
    }

    #[test]
    fn small_holes_are_closed_and_the_outer_edge_is_not() {
        // Two one-square holes (perimeter 4) and one three-square hole (perimeter 8) in a 6 x 6 grid.
        let mut mesh = grid_with_holes(6, &[(1, 1), (4, 1), (1, 4), (2, 4), (3, 4)]);
        let before = mesh.topology();
        assert!(before.is_oriented_manifold() && before.boundary_edges == 24 + 4 + 4 + 8);
        let area = mesh.area_mm2();
        assert_eq!(mesh.fill_small_holes(5.0), 2);
        let after = mesh.topology();
        assert!(after.is_oriented_manifold(), "{after:?}");
        assert_eq!(after.boundary_edges, 24 + 8);
        assert!((mesh.area_mm2() - area - 2.0).abs() < 1e-12);
        assert_eq!(mesh.normals.len(), mesh.vertices.len());
        // The new triangles face the same way as the old ones.
        for t in &mesh.triangles {
            let [a, b, c] = t.map(|i| mesh.vertices[i as usize]);
            assert!((b - a).cross(c - a).z > 0.0);
        }
        // A larger limit closes the long hole too, never the outer edge (perimeter 24).
        assert_eq!(mesh.fill_small_holes(100.0), 1);
        assert_eq!(mesh.topology().boundary_edges, 24);
        assert!((mesh.area_mm2() - 36.0).abs() < 1e-12);
        assert_eq!(mesh.fill_small_holes(100.0), 0);
    }

    #[test]
    fn trimming_the_rim_peels_rings_and_never_cuts_or_removes_a_piece() {
        // A 6 x 6 grid: the first ring takes the 20 edge squares' rim triangles and the corners' tips.
        let mut grid = grid_with_holes(6, &[]);
        let before = grid.topology();
        let removed = grid.trim_rim(1);
        let after = grid.topology();
        assert!(removed > 0 && after.is_oriented_manifold(), "{after:?}");
        assert_eq!(
            (after.components, after.euler_characteristic),
            (before.components, before.euler_characteristic)
        );
        assert_eq!(grid.triangles.len(), 72 - removed);
        assert_eq!(grid.normals.len(), grid.vertices.len());
        // A ring is the triangles on the rim when it starts: on this triangulation one of each
        // edge square's two, so the old outer vertices go with the second ring (the other triangle,
        // then a corner with two rim edges), but for the few a neck-check keeps.
        let mut twice = grid_with_holes(6, &[]);
        twice.trim_rim(2);
        assert_eq!(twice.topology().euler_characteristic, 1);
        let on_old_edge = twice
            .vertices
            .iter()
            .filter(|v| v.x == 0.0 || v.y == 0.0 || v.x == 6.0 || v.y == 6.0)
            .count();
        assert!(
            on_old_edge < 24 / 2,
            "{on_old_edge} of 24 outer vertices left"
        );
        // More rings keep peeling, never past one piece.
        let mut deep = grid_with_holes(6, &[]);
        deep.trim_rim(50);
        let t = deep.topology();
        assert!(
            t.components == 1 && t.euler_characteristic == 1 && t.triangles >= 1,
            "{t:?}"
        );

        // Two squares joined by a strip one square wide: the strip's rim triangles each have their
        // third vertex on the other rim, so it stays, and the piece stays one.
        let dumbbell = {
            let mut holes = Vec::new();
            for j in 0..7 {
                for i in 0..7 {
                    let in_left = i < 3 && (2..5).contains(&j);
                    let in_right = i >= 4 && (2..5).contains(&j);
                    let in_neck = i == 3 && j == 3;
                    if !(in_left || in_right || in_neck) {
                        holes.push((i, j));
                    }
                }
            }
            grid_with_holes(7, &holes)
        };
        let mut m = dumbbell.clone();
        assert_eq!(m.topology().components, 1);
        m.trim_rim(3);
        let t = m.topology();
        assert_eq!((t.components, t.euler_characteristic), (1, 1), "{t:?}");
        assert!(m.triangles.len() < dumbbell.triangles.len());

        // A lone triangle is never removed, and zero rings change nothing.
        let mut lone = Mesh {
            vertices: vec![DVec3::ZERO, DVec3::X, DVec3::Y],
            normals: vec![],
            triangles: vec![[0, 1, 2]],
        };
        assert_eq!(lone.trim_rim(5), 0);
        let mut same = dumbbell.clone();
        assert_eq!(same.trim_rim(0), 0);
        assert_eq!(same, dumbbell);
    }

    #[test]
    fn reach_along_edges_is_a_shortest_path_on_the_surface() {
        // A 6 x 6 unit grid with a wall of missing squares at column 2, rows 0-4: from the seed at
        // (0, 0), vertex (3, 0) lies 3 mm away in space but 11.8 mm along the edges, around the wall's
        // end at row 5: two square diagonals to (2, 2), up to (2, 5), across, and down to (3, 0).
        let holes: Vec<(u32, u32)> = (0..5).map(|j| (2, j)).collect();
        let mesh = grid_with_holes(6, &holes);
        let at = |i: usize, j: usize| j * 7 + i;
        let mut seeds = vec![false; mesh.vertices.len()];
        seeds[at(0, 0)] = true;
        let reach = |mm: f64| mesh.within_reach_along_edges(&seeds, mm);
        // Straight along the bottom row: exactly 2 mm to (2, 0), which the wall's left edge still holds.
        assert!(reach(2.0)[at(2, 0)] && !reach(1.999)[at(2, 0)]);
        // The diagonal of a square (the grid's triangles split them along (i, j) -> (i + 1, j + 1)).
        assert!(reach(2f64.sqrt())[at(1, 1)] && !reach(1.414)[at(1, 1)]);
        // Across the wall: only along the path around it.
        let around = 2.0 * 2f64.sqrt() + 3.0 + 1.0 + 5.0;
        assert!(!reach(around - 1e-6)[at(3, 0)] && reach(around + 1e-9)[at(3, 0)]);
        // Only seeds at zero reach; nothing at all without seeds.
        assert_eq!(reach(0.0).iter().filter(|&&k| k).count(), 1);
        assert!(
            !mesh
                .within_reach_along_edges(&vec![false; mesh.vertices.len()], 100.0)
                .contains(&true)
        );
    }

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

    /// Two flat fans around the origin (normal +z), one over 0-90 degrees and one over 120-210, so
    /// they touch at the origin alone; `tilt` turns the second about the x axis.
    fn two_fans_touching_at_a_vertex(tilt_deg: f64) -> Mesh {
        let rot = glam::DQuat::from_rotation_x(tilt_deg.to_radians());
        let at = |deg: f64, second: bool| {
            let p = DVec3::new(deg.to_radians().cos(), deg.to_radians().sin(), 0.0);
            if second { rot * p } else { p }
        };
        let vertices = vec![
            DVec3::ZERO,
            at(0.0, false),
            at(45.0, false),
            at(90.0, false),
            at(120.0, true),
            at(165.0, true),
            at(210.0, true),
        ];
        Mesh {
            vertices,
            normals: vec![],
            triangles: vec![[0, 1, 2], [0, 2, 3], [0, 4, 5], [0, 5, 6]],
        }
    }

    /// A flat strip of `cells` x 1 unit squares over x in [0, cells], y in [y0, y0 + 1], z = 0, wound
    /// counter-clockwise seen from +z, with every vertex mapped by `place`.
    fn strip(cells: u32, y0: f64, place: impl Fn(DVec3) -> DVec3) -> Mesh {
        let mut m = Mesh::default();
        for i in 0..=cells {
            for j in 0..2 {
                m.vertices
                    .push(place(DVec3::new(i as f64, y0 + j as f64, 0.0)));
            }
        }
        for i in 0..cells {
            let (a, b, c, d) = (2 * i, 2 * i + 2, 2 * i + 3, 2 * i + 1);
            m.triangles.push([a, b, c]);
            m.triangles.push([a, c, d]);
        }
        m
    }

    #[test]
    fn pieces_side_by_side_are_bridged_and_the_seam_closed() {
        // Two strips 4 units long, 0.5 apart, in one plane.
        let pair = |place: &dyn Fn(DVec3) -> DVec3| {
            Mesh::merged([&strip(4, 0.0, |p| p), &strip(4, 1.5, place)])
        };
        let mut m = pair(&|p| p);
        let before = m.area_mm2();
        assert_eq!(m.topology().components, 2);
        // A gap wider than the bound is left.
        assert_eq!(m.clone().bridge_near_pieces(0.4), 0);
        assert_eq!(m.bridge_near_pieces(0.6), 1);
        let t = m.topology();
        assert!(t.is_oriented_manifold(), "{t:?}");
        // One disc (no handle), and the whole 4 x 0.5 seam is closed.
        assert_eq!((t.components, t.euler_characteristic), (1, 1));
        assert!(
            (m.area_mm2() - before - 4.0 * 0.5).abs() < 1e-9,
            "{}",
            m.area_mm2()
        );
        // Bridged once: nothing left to join.
        assert_eq!(m.bridge_near_pieces(0.6), 0);

        // A second layer 0.5 beneath the first (the gap runs along the normal) is not bridged.
        let mut stacked = Mesh::merged([
            &strip(4, 0.0, |p| p),
            &strip(4, 0.0, |p| p - DVec3::Z * 0.5),
        ]);
        assert_eq!(stacked.bridge_near_pieces(2.0), 0);
        // Nor is a strip turned 90 degrees about the seam (a wall meeting the first at right angles).
        let turned = |p: DVec3| DVec3::new(p.x, 1.5, p.y - 1.5);
        let mut corner = pair(&turned);
        assert_eq!(corner.bridge_near_pieces(2.0), 0);
        // A strip running the other way round (facing -z) is not either.
        let flipped = |p: DVec3| DVec3::new(p.x, 4.0 - p.y, 0.0);
        let mut facing_away = pair(&flipped);
        assert_eq!(facing_away.bridge_near_pieces(2.0), 0);
        // A NaN or infinite bound bridges nothing.
        assert_eq!(pair(&|p| p).bridge_near_pieces(f64::NAN), 0);
        assert_eq!(pair(&|p| p).bridge_near_pieces(f64::INFINITY), 0);
    }

    #[test]
    fn pinched_fans_are_joined_across_the_narrow_wedge() {
        let mut m = two_fans_touching_at_a_vertex(0.0);
        let t = m.topology();
        assert_eq!((t.components, t.nonmanifold_vertices), (2, 1));
        // The wedge from 90 to 120 degrees is 2 sin(15 deg) = 0.52 wide, the other 1.93.
        assert_eq!(m.clone().join_pinched_fans(0.5), 0);
        assert_eq!(m.join_pinched_fans(0.6), 1);
        assert_eq!(m.triangles.last(), Some(&[4, 0, 3]));
        let t = m.topology();
        assert!(t.is_oriented_manifold(), "{t:?}");
        assert_eq!((t.components, t.nonmanifold_vertices), (1, 0));
        // Joined once, nothing is pinched any more.
        assert_eq!(m.join_pinched_fans(0.6), 0);
        assert_eq!(m.split_pinched_vertices(), 0);
        // Fans that do not continue one another (the second turned 90 degrees) are not joined.
        let mut folded = two_fans_touching_at_a_vertex(90.0);
        assert_eq!(folded.join_pinched_fans(10.0), 0);
        assert_eq!(folded.split_pinched_vertices(), 1);
        assert_eq!(folded.topology().components, 2);
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
