//! Removing what no echo backs from a mesh: small or unechoed pieces, far triangles, rim rings, and
//! closing small holes.

use super::{DVec3, Mesh, edge_neighbours};
use rayon::prelude::*;

impl Mesh {
    /// Removes the edge-connected components whose area is below `min_area_mm2` (isolated speckle blobs
    /// and shreds of a surface) and the vertices no triangle uses any more. Returns the triangles removed.
    pub fn remove_small_components(&mut self, min_area_mm2: f64) -> usize {
        self.remove_components_below(min_area_mm2, 0.0).1
    }

    /// Removes the components smaller than `min_area_mm2` or than `min_share_of_largest` of the largest
    /// component's area, as [`Mesh::remove_small_components`]: specks far smaller than the structure
    /// the mesh shows, whatever its size. Returns the pieces removed.
    pub fn remove_minor_components(
        &mut self,
        min_area_mm2: f64,
        min_share_of_largest: f64,
    ) -> usize {
        self.remove_components_below(min_area_mm2, min_share_of_largest)
            .0
    }

    /// (pieces, triangles) removed by [`Mesh::remove_minor_components`].
    fn remove_components_below(
        &mut self,
        min_area_mm2: f64,
        min_share_of_largest: f64,
    ) -> (usize, usize) {
        let n = self.vertices.len();
        let component = self.triangle_components();
        let mut component_area = vec![0.0f64; self.triangles.len()];
        let valid = |t: &[u32; 3]| t.iter().all(|&i| (i as usize) < n);
        for (f, t) in self.triangles.iter().enumerate() {
            if valid(t) {
                component_area[component[f]] += self.triangle_area_mm2(*t);
            }
        }
        let largest = component_area.iter().fold(0.0f64, |a, &b| a.max(b));
        let min_area_mm2 = min_area_mm2.max(min_share_of_largest * largest);
        let keep: Vec<bool> = (0..self.triangles.len())
            .map(|f| valid(&self.triangles[f]) && component_area[component[f]] >= min_area_mm2)
            .collect();
        let mut removed_piece = vec![false; self.triangles.len()];
        for (f, &k) in keep.iter().enumerate() {
            if !k {
                removed_piece[component[f]] = true;
            }
        }
        let pieces = removed_piece.iter().filter(|&&r| r).count();
        (pieces, self.retain_triangles(&keep))
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
                buckets.visit_within(*v, radius_mm, |k, _| {
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
}
