//! Joining a mesh's pieces: across pinched vertices, across narrow gaps between rims, and splitting
//! the pinches that cannot be joined.

use super::{DVec3, Mesh, find_root};

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

impl Mesh {
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
            buckets.visit_within(midpoints[i], max_gap_mm, |j, _| {
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
}
