//! Vertex clustering ("regularisation") that keeps the mesh an oriented 2-manifold.
//!
//! Every raw vertex belongs to one clustering cell (see `rmt::cluster_key`: Voronoi cells of a
//! face-centred cubic lattice slightly coarser than the sampling lattice). Within a cell, vertices are
//! merged by contracting mesh edges joining two of them, one edge at a time, in a fixed order.
//! **The rule**: an edge `uv` is contracted only if
//!
//! 1. it satisfies the *link condition* (Dey, Edelsbrunner et al. 1999):
//!    `Lk(u) ∩ Lk(v) = Lk(uv)`, where links are taken after coning the boundary to a virtual vertex ω
//!    (so a boundary vertex's link contains ω and the edges from ω to its boundary neighbours).
//!    Concretely: the common neighbours of `u` and `v` are exactly the apexes of the (one or two)
//!    triangles on `uv` (plus ω exactly when `uv` is a boundary edge), and no edge lies in both links.
//!    This is necessary and sufficient for the contraction of an edge of a 2-manifold (with boundary) to
//!    give a homeomorphic 2-manifold: it refuses every merge that would create an edge used by three or
//!    more triangles, a pinched vertex (two sheets or two boundary arcs meeting in one point), a
//!    duplicate triangle, or a collapsed tetrahedron/closed-up hole;
//! 2. no triangle kept around `u` and `v` folds over or degenerates when the merged vertex moves to the
//!    cluster's centroid (its normal keeps a positive dot product with the mean normal of the triangles
//!    around `u` and `v` before the merge, and its area stays above a tiny fraction of a cell face).
//!
//! Vertices of one cell that are not joined by an edge (two sheets passing through the cell) are never
//! merged, so refused merges simply leave more than one vertex in that cell. Triangles containing the
//! contracted edge disappear; the others keep their winding, so orientation survives.

use glam::DVec3;
use smallvec::SmallVec;

/// The triangles around one vertex: a raw marching-tetrahedra vertex has at most 12 (two per
/// tetrahedron around its lattice edge), so most lists never leave the inline storage.
type FaceList = SmallVec<[u32; 12]>;

/// The merged mesh: positions (cluster centroids, before projection onto the surface) and triangles.
#[derive(Debug, Default)]
pub(crate) struct ClusteredSurface {
    pub positions: Vec<DVec3>,
    pub triangles: Vec<[u32; 3]>,
    /// For each output vertex, the input vertex it continues (the survivor of its contractions).
    pub input_index: Vec<u32>,
    /// Merges refused by the rule above.
    pub refused_merges: usize,
}

const OMEGA: u32 = u32::MAX;

/// The link of a vertex written out (vertex and edge parts, sorted): the definition the fast test in
/// [`Work::link_condition`] is checked against.
#[cfg(test)]
#[derive(Default)]
struct Link {
    verts: Vec<u32>,
    edges: Vec<(u32, u32)>,
    out_of: Vec<u32>,
    into: Vec<u32>,
}

#[cfg(test)]
impl Link {
    fn clear(&mut self) {
        self.verts.clear();
        self.edges.clear();
        self.out_of.clear();
        self.into.clear();
    }
}

/// Marks of which side of which of two vertices' triangles a neighbour was seen on.
const U_OUT: u8 = 1;
const U_IN: u8 = 2;
const V_OUT: u8 = 4;
const V_IN: u8 = 8;

#[derive(Default)]
struct Scratch {
    /// Per vertex, the marks of the current test (valid where `stamps` equals `epoch`).
    marks: Vec<u8>,
    stamps: Vec<u32>,
    epoch: u32,
    /// Vertices marked in the current test.
    marked: Vec<u32>,
    #[cfg(test)]
    edge_link: Vec<u32>,
    #[cfg(test)]
    lu: Link,
    #[cfg(test)]
    lv: Link,
    /// Decisions checked against the definition: refused, accepted.
    #[cfg(test)]
    checked: [usize; 2],
}

impl Scratch {
    /// Starts a test over a mesh of `vertices` vertices: every mark cleared.
    fn begin(&mut self, vertices: usize) {
        if self.stamps.len() < vertices {
            self.stamps.resize(vertices, 0);
            self.marks.resize(vertices, 0);
        }
        self.epoch = self.epoch.wrapping_add(1);
        if self.epoch == 0 {
            self.stamps.fill(0);
            self.epoch = 1;
        }
        self.marked.clear();
    }

    fn mark(&mut self, x: u32, bit: u8) {
        let i = x as usize;
        if self.stamps[i] != self.epoch {
            self.stamps[i] = self.epoch;
            self.marks[i] = 0;
            self.marked.push(x);
        }
        self.marks[i] |= bit;
    }

    fn marks_of(&self, x: u32) -> u8 {
        if self.stamps[x as usize] == self.epoch {
            self.marks[x as usize]
        } else {
            0
        }
    }
}

/// Whether marks `m` say the vertex lies on a boundary edge of the vertex whose marks are `out | into`
/// (an edge to it in one direction only).
fn on_boundary_edge(m: u8, out: u8, into: u8) -> bool {
    let both = m & (out | into);
    both == out || both == into
}

struct Work {
    pos_sum: Vec<DVec3>,
    weight: Vec<f64>,
    faces: Vec<[u32; 3]>,
    face_alive: Vec<bool>,
    vertex_faces: Vec<FaceList>,
    min_area2: f64,
}

impl Work {
    fn position(&self, v: u32) -> DVec3 {
        self.pos_sum[v as usize] / self.weight[v as usize]
    }

    /// The other two vertices of face `f` in its winding order after `x` (the directed edges x -> p
    /// and q -> x).
    fn after(&self, f: u32, x: u32) -> (u32, u32) {
        let t = self.faces[f as usize];
        let i = t
            .iter()
            .position(|&v| v == x)
            .expect("face lists its vertex");
        (t[(i + 1) % 3], t[(i + 2) % 3])
    }

    fn adjacent(&self, a: u32, b: u32) -> bool {
        self.vertex_faces[a as usize]
            .iter()
            .any(|&f| self.faces[f as usize].contains(&b))
    }

    /// Vertex part (sorted neighbours, plus ω if on the boundary) and edge part (sorted pairs) of Lk(x),
    /// into `out` (buffers reused across calls: this runs for every candidate merge).
    #[cfg(test)]
    fn link(&self, x: u32, out: &mut Link) {
        out.clear();
        for &f in &self.vertex_faces[x as usize] {
            let (p, q) = self.after(f, x);
            out.verts.push(p);
            out.verts.push(q);
            out.edges.push((p.min(q), p.max(q)));
            // Directed edges out of and into x: a boundary edge appears in one direction only.
            out.out_of.push(p);
            out.into.push(q);
        }
        out.out_of.sort_unstable();
        out.into.sort_unstable();
        let mut boundary = false;
        for &p in &out.out_of {
            if out.into.binary_search(&p).is_err() {
                boundary = true;
                out.edges.push((p, OMEGA));
            }
        }
        for &q in &out.into {
            if out.out_of.binary_search(&q).is_err() {
                boundary = true;
                out.edges.push((q, OMEGA));
            }
        }
        if boundary {
            out.verts.push(OMEGA);
        }
        out.verts.sort_unstable();
        out.verts.dedup();
        out.edges.sort_unstable();
        out.edges.dedup();
    }

    /// The link condition by its definition: both links written out and compared.
    #[cfg(test)]
    fn link_condition_by_links(&self, u: u32, v: u32, scratch: &mut Scratch) -> bool {
        let edge_link = &mut scratch.edge_link;
        edge_link.clear();
        let mut uses = 0;
        for &f in &self.vertex_faces[u as usize] {
            let t = self.faces[f as usize];
            if t.contains(&v) {
                uses += 1;
                edge_link.extend(t.iter().copied().filter(|&w| w != u && w != v));
            }
        }
        if uses == 0 || uses > 2 {
            return false;
        }
        if uses == 1 {
            edge_link.push(OMEGA);
        }
        edge_link.sort_unstable();
        self.link(u, &mut scratch.lu);
        self.link(v, &mut scratch.lv);
        let (lu, lv) = (&scratch.lu, &scratch.lv);
        let mut common = lu
            .verts
            .iter()
            .filter(|x| lv.verts.binary_search(x).is_ok());
        // Common neighbours must equal the apexes of the edge's triangles (both sorted).
        for w in scratch.edge_link.iter() {
            if common.next() != Some(w) {
                return false;
            }
        }
        if common.next().is_some() {
            return false;
        }
        !lu.edges.iter().any(|e| lv.edges.binary_search(e).is_ok())
    }

    /// The link condition of the module documentation, `Lk(u) ∩ Lk(v) = Lk(uv)`, without writing the
    /// links out. The common neighbours of u and v include the apexes of the triangles on uv, so the
    /// vertex part holds when the apexes are distinct, no other vertex is common, and ω is common (both
    /// are boundary vertices) exactly when uv is a boundary edge. Then every common edge joins two of
    /// those: the two apexes (a triangle u a0 a1 and a triangle v a0 a1) or the one apex and ω (u a0
    /// and v a0 both boundary edges).
    fn link_condition(&self, u: u32, v: u32, scratch: &mut Scratch) -> bool {
        let mut apexes = [OMEGA; 2];
        let mut uses = 0;
        for &f in &self.vertex_faces[u as usize] {
            let t = self.faces[f as usize];
            if t.contains(&v) {
                for w in t.into_iter().filter(|&w| w != u && w != v) {
                    if uses == 2 {
                        return false;
                    }
                    apexes[uses] = w;
                    uses += 1;
                }
            }
        }
        if uses == 0 || uses == 2 && apexes[0] == apexes[1] {
            return false;
        }
        scratch.begin(self.pos_sum.len());
        for (x, out, into) in [(u, U_OUT, U_IN), (v, V_OUT, V_IN)] {
            for &f in &self.vertex_faces[x as usize] {
                let (p, q) = self.after(f, x);
                scratch.mark(p, out);
                scratch.mark(q, into);
            }
        }
        let (mut common, mut u_boundary, mut v_boundary) = (0, false, false);
        for &x in &scratch.marked {
            let m = scratch.marks[x as usize];
            let (of_u, of_v) = (m & (U_OUT | U_IN) != 0, m & (V_OUT | V_IN) != 0);
            common += usize::from(of_u && of_v);
            u_boundary |= of_u && on_boundary_edge(m, U_OUT, U_IN);
            v_boundary |= of_v && on_boundary_edge(m, V_OUT, V_IN);
        }
        if common != uses || (uses == 1) != (u_boundary && v_boundary) {
            return false;
        }
        if uses == 1 {
            let m = scratch.marks_of(apexes[0]);
            !(on_boundary_edge(m, U_OUT, U_IN) && on_boundary_edge(m, V_OUT, V_IN))
        } else {
            let has_triangle_with = |x: u32| {
                self.vertex_faces[x as usize].iter().any(|&f| {
                    let t = self.faces[f as usize];
                    t.contains(&apexes[0]) && t.contains(&apexes[1])
                })
            };
            !(has_triangle_with(u) && has_triangle_with(v))
        }
    }

    /// Rule 2: the surviving triangles around u and v neither fold over nor degenerate at the new
    /// position. "Fold" is judged against the area-weighted mean normal of all triangles around u and v
    /// before the merge (the raw slivers' own normals are too noisy to compare with).
    fn keeps_shape(&self, u: u32, v: u32, new_position: DVec3) -> bool {
        let mut mean_normal = DVec3::ZERO;
        for &x in &[u, v] {
            for &f in &self.vertex_faces[x as usize] {
                let t = self.faces[f as usize].map(|w| self.position(w));
                mean_normal += (t[1] - t[0]).cross(t[2] - t[0]);
            }
        }
        for &x in &[u, v] {
            for &f in &self.vertex_faces[x as usize] {
                let t = self.faces[f as usize];
                if t.contains(&u) && t.contains(&v) {
                    continue;
                }
                let after = t.map(|w| {
                    if w == u || w == v {
                        new_position
                    } else {
                        self.position(w)
                    }
                });
                let n_after = (after[1] - after[0]).cross(after[2] - after[0]);
                if n_after.dot(mean_normal) <= 0.0 || n_after.length_squared() <= self.min_area2 {
                    return false;
                }
            }
        }
        true
    }

    /// Contracts v into u.
    fn contract(&mut self, u: u32, v: u32) {
        let (moved_sum, moved_weight) = (self.pos_sum[v as usize], self.weight[v as usize]);
        self.pos_sum[u as usize] += moved_sum;
        self.weight[u as usize] += moved_weight;
        let v_faces = std::mem::take(&mut self.vertex_faces[v as usize]);
        for f in v_faces {
            let t = self.faces[f as usize];
            if t.contains(&u) {
                self.face_alive[f as usize] = false;
                for w in t {
                    if w != v {
                        self.vertex_faces[w as usize].retain(|g| *g != f);
                    }
                }
            } else {
                for w in self.faces[f as usize].iter_mut() {
                    if *w == v {
                        *w = u;
                    }
                }
                self.vertex_faces[u as usize].push(f);
            }
        }
    }
}

/// Merges the raw vertices cluster by cluster (clusters in key order, vertices in index order, so the
/// result is deterministic) under the manifold-preserving rule of the module documentation.
/// `cell_area_mm2` scales the degeneracy threshold.
pub(crate) fn cluster_vertices(
    positions: &[DVec3],
    cluster_keys: &[u64],
    triangles: &[[u32; 3]],
    cell_area_mm2: f64,
) -> ClusteredSurface {
    let mut scratch = GroupScratch::default();
    cluster_vertices_with(
        positions,
        cluster_keys,
        triangles,
        cell_area_mm2,
        &mut scratch,
    )
}

/// [`cluster_vertices`] with the caller's buffers (the tests read what they counted).
fn cluster_vertices_with(
    positions: &[DVec3],
    cluster_keys: &[u64],
    triangles: &[[u32; 3]],
    cell_area_mm2: f64,
    scratch: &mut GroupScratch,
) -> ClusteredSurface {
    let n = positions.len();
    let mut work = Work {
        pos_sum: positions.to_vec(),
        weight: vec![1.0; n],
        faces: triangles.to_vec(),
        face_alive: vec![true; triangles.len()],
        vertex_faces: vec![FaceList::new(); n],
        // |cross|^2 = (2 * area)^2; refuse areas below 1e-6 of a cell face.
        min_area2: (2e-6 * cell_area_mm2).powi(2),
    };
    for (f, t) in triangles.iter().enumerate() {
        for &v in t {
            work.vertex_faces[v as usize].push(f as u32);
        }
    }
    let mut order: Vec<u32> = (0..n as u32).collect();
    order.sort_unstable_by_key(|&v| (cluster_keys[v as usize], v));
    let refused = order
        .chunk_by(|&a, &b| cluster_keys[a as usize] == cluster_keys[b as usize])
        .filter(|group| group.len() >= 2)
        .map(|group| cluster_group(&mut work, group, scratch))
        .sum();
    // Compact: surviving triangles in their original order, vertices in raw index order.
    let mut new_index = vec![u32::MAX; n];
    let mut used = vec![false; n];
    for (f, t) in work.faces.iter().enumerate() {
        if work.face_alive[f] {
            for &v in t {
                used[v as usize] = true;
            }
        }
    }
    let mut out = ClusteredSurface {
        refused_merges: refused,
        ..Default::default()
    };
    for v in 0..n {
        if used[v] {
            new_index[v] = out.positions.len() as u32;
            out.positions.push(work.position(v as u32));
            out.input_index.push(v as u32);
        }
    }
    out.triangles = work
        .faces
        .iter()
        .zip(&work.face_alive)
        .filter(|(_, alive)| **alive)
        .map(|(t, _)| t.map(|v| new_index[v as usize]))
        .collect();
    out
}

/// Reused buffers of one group's merging.
#[derive(Default)]
struct GroupScratch {
    link: Scratch,
    members: Vec<u32>,
    blocked: Vec<(u32, u32)>,
}

/// Merges the vertices of one cluster (`group`, in index order); returns the merges refused.
fn cluster_group(work: &mut Work, group: &[u32], scratch: &mut GroupScratch) -> usize {
    let GroupScratch {
        link,
        members,
        blocked,
    } = scratch;
    members.clear();
    members.extend_from_slice(group);
    blocked.clear();
    // Passes over all pairs until one merges nothing (a merge can make a refused pair acceptable or
    // join two vertices that were not adjacent before).
    loop {
        let mut merged_any = false;
        let mut i = 0;
        while i < members.len() {
            let mut j = i + 1;
            while j < members.len() {
                let (u, v) = (members[i], members[j]);
                if work.adjacent(u, v) {
                    let new_position = (work.pos_sum[u as usize] + work.pos_sum[v as usize])
                        / (work.weight[u as usize] + work.weight[v as usize]);
                    let linked = work.link_condition(u, v, link);
                    #[cfg(test)]
                    assert_eq!(
                        linked,
                        work.link_condition_by_links(u, v, link),
                        "the link condition's fast test disagrees with its definition on {u}-{v}"
                    );
                    #[cfg(test)]
                    {
                        link.checked[usize::from(linked)] += 1;
                    }
                    if linked && work.keeps_shape(u, v, new_position) {
                        work.contract(u, v);
                        members.remove(j);
                        merged_any = true;
                        continue;
                    } else if !blocked.contains(&(u, v)) {
                        blocked.push((u, v));
                    }
                }
                j += 1;
            }
            i += 1;
        }
        if !merged_any {
            break;
        }
    }
    // A pair refused at some point but later merged through another contraction is not a refusal.
    blocked
        .iter()
        .filter(|(u, v)| members.contains(u) && members.contains(v) && work.adjacent(*u, *v))
        .count()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::Mesh;

    fn topo(c: &ClusteredSurface) -> crate::mesh::MeshTopology {
        Mesh {
            vertices: c.positions.clone(),
            normals: vec![],
            triangles: c.triangles.clone(),
        }
        .topology()
    }

    /// The raw marching-tetrahedra surface of a bumpy sphere cut open by the lattice's box (so it has
    /// a boundary), clustered: every link-condition decision is checked against the definition (in
    /// `cluster_group`), and both answers occur often.
    #[test]
    fn the_fast_link_condition_decides_as_the_written_out_links_do() {
        use crate::spatial::cell_grid::pack_cell;
        use crate::surface::lattice::Lattice;
        use crate::surface::rmt::march_tetrahedra;
        let lattice = Lattice::new(DVec3::splat(-3.6), DVec3::new(2.1, 3.6, 3.6), 0.25).unwrap();
        let value = |n: [i32; 3]| {
            let p = lattice.node_position(n);
            p.length() - 3.0 + 0.35 * (7.0 * p.x).sin() * (5.0 * p.y).sin() * (6.0 * p.z).sin()
        };
        let mut cells = Vec::new();
        for k in 0..lattice.cells[2] {
            for j in 0..lattice.cells[1] {
                for i in 0..lattice.cells[0] {
                    cells.push(pack_cell([i, j, k]));
                }
            }
        }
        cells.sort_unstable();
        for factor in [1.1, 1.6] {
            let raw = march_tetrahedra(&lattice, &cells, 0.0, factor, value);
            let mut scratch = GroupScratch::default();
            let c = cluster_vertices_with(
                &raw.positions,
                &raw.cluster_keys,
                &raw.triangles,
                0.0625,
                &mut scratch,
            );
            let [no, yes] = scratch.link.checked;
            assert!(
                no >= 50 && yes >= 1000,
                "factor {factor}: {no} refused, {yes} accepted"
            );
            let t = topo(&c);
            assert!(t.is_oriented_manifold() && t.boundary_edges > 0, "{t:?}");
        }
    }

    /// An octahedron: contracting any edge would leave a tetrahedron-like shape; one edge is fine, but
    /// the link condition must refuse collapsing the result into a doubled triangle.
    #[test]
    fn refuses_to_collapse_a_tetrahedron() {
        let positions = vec![DVec3::ZERO, DVec3::X, DVec3::Y, DVec3::Z];
        let triangles = vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]];
        // All four vertices in one cluster: any contraction of a tetrahedron violates the link condition.
        let c = cluster_vertices(&positions, &[0; 4], &triangles, 1.0);
        assert_eq!(c.triangles.len(), 4);
        assert!(c.refused_merges > 0);
        let t = topo(&c);
        assert!(
            t.is_closed_manifold() && t.euler_characteristic == 2,
            "{t:?}"
        );
    }

    /// Two sheets through one cluster cell, joined by a strip elsewhere: merging across would pinch.
    #[test]
    fn keeps_two_sheets_in_one_cell_apart() {
        // Two parallel square strips (z = 0 and z = 0.2) with vertices 0..4 and 4..8; vertices 1 and 5
        // sit in the same cluster but no edge joins them, so they must survive as two vertices.
        let mut positions = Vec::new();
        for z in [0.0, 0.2] {
            positions.extend([
                DVec3::new(0.0, 0.0, z),
                DVec3::new(1.0, 0.0, z),
                DVec3::new(1.0, 1.0, z),
                DVec3::new(0.0, 1.0, z),
            ]);
        }
        let triangles = vec![[0, 1, 2], [0, 2, 3], [4, 6, 5], [4, 7, 6]];
        let keys = [0, 9, 1, 2, 3, 9, 4, 5];
        let c = cluster_vertices(&positions, &keys, &triangles, 1.0);
        assert_eq!(c.positions.len(), 8);
        assert_eq!(c.triangles.len(), 4);
    }

    /// A boundary fan: merging two boundary vertices across an interior edge would pinch the fan's
    /// centre into two boundary arcs; the link condition (with ω) refuses it.
    #[test]
    fn refuses_boundary_pinch() {
        // Strip of two triangles sharing edge 1-2: 0-1-2, 1-3-2. Vertices 0 and 3 are not adjacent; 1 and
        // 2 are both boundary vertices joined by the interior edge 1-2.
        let positions = vec![
            DVec3::new(0.0, 0.0, 0.0),
            DVec3::new(1.0, 0.0, 0.0),
            DVec3::new(0.0, 1.0, 0.0),
            DVec3::new(1.0, 1.0, 0.0),
        ];
        let triangles = vec![[0, 1, 2], [1, 3, 2]];
        let c = cluster_vertices(&positions, &[0, 5, 5, 1], &triangles, 1.0);
        assert_eq!(
            c.triangles.len(),
            2,
            "contracting 1-2 would leave two triangles sharing only a vertex"
        );
        assert_eq!(c.refused_merges, 1);
        assert!(topo(&c).is_oriented_manifold());
    }

    /// Contracting an interior edge of a fan removes its two triangles and keeps the manifold.
    #[test]
    fn contracts_interior_edge() {
        // Hexagon fan around vertex 0, plus vertex 1 on the rim merged into 0.
        let mut positions = vec![DVec3::ZERO];
        for k in 0..6 {
            let a = k as f64 * std::f64::consts::PI / 3.0;
            positions.push(DVec3::new(a.cos(), a.sin(), 0.0));
        }
        let triangles: Vec<[u32; 3]> = (0..6).map(|k| [0, 1 + k, 1 + (k + 1) % 6]).collect();
        let mut keys: Vec<u64> = (10..17).collect();
        keys[1] = 10;
        let c = cluster_vertices(&positions, &keys, &triangles, 1.0);
        // Vertex 1 is a boundary vertex and 0 is interior: allowed, removes triangles 0-1-2 and 0-6-1.
        assert_eq!(c.triangles.len(), 4);
        assert_eq!(c.refused_merges, 0);
        assert!(topo(&c).is_oriented_manifold());
    }
}
