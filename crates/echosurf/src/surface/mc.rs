//! Classic marching cubes with a case table generated from one face rule, so it is consistent.
//!
//! For each of the 256 corner sign patterns the table is built on the cube's surface: on each face the
//! edge crossings are paired into segments, and on an ambiguous face (high corners diagonally opposite)
//! the high corners are always separated. The rule looks only at the face's own four corners, so the two
//! cubes sharing a face draw the same segments and the surface is watertight. Segments chain into closed
//! loops (every crossed edge lies on two faces), and each loop is fanned into triangles. A value equal to
//! the level counts as below it.

use std::sync::OnceLock;

use glam::DVec3;

use super::rmt::EDGE_T_MARGIN;
use crate::mesh::Mesh;
use crate::spatial::cell_grid::CellMap;
use crate::{Error, Result};

/// The 12 cube edges as corner pairs (corner bits: x = 1, y = 2, z = 4), lower corner first.
const EDGES: [(usize, usize); 12] = [
    (0, 1),
    (2, 3),
    (4, 5),
    (6, 7),
    (0, 2),
    (1, 3),
    (4, 6),
    (5, 7),
    (0, 4),
    (1, 5),
    (2, 6),
    (3, 7),
];

fn edge_index(a: usize, b: usize) -> usize {
    let (a, b) = (a.min(b), a.max(b));
    EDGES.iter().position(|&e| e == (a, b)).expect("cube edge")
}

/// The six faces, corners counter-clockwise seen from outside the cube.
fn faces() -> [[usize; 4]; 6] {
    let mut out = [[0; 4]; 6];
    for axis in 0..3 {
        let (b, c) = ((axis + 1) % 3, (axis + 2) % 3);
        for side in 0..2 {
            let corner = |u: usize, v: usize| (side << axis) | (u << b) | (v << c);
            // (0,0) (1,0) (1,1) (0,1) in (b, c) is counter-clockwise seen from +axis (e_b x e_c = e_axis).
            let ccw = [corner(0, 0), corner(1, 0), corner(1, 1), corner(0, 1)];
            out[axis * 2 + side] = if side == 1 {
                ccw
            } else {
                [ccw[0], ccw[3], ccw[2], ccw[1]]
            };
        }
    }
    out
}

/// Per case: triangles as triples of cube-edge indices.
fn case_table() -> &'static Vec<Vec<[u8; 3]>> {
    static TABLE: OnceLock<Vec<Vec<[u8; 3]>>> = OnceLock::new();
    TABLE.get_or_init(|| (0..256).map(triangulate_case).collect())
}

fn triangulate_case(case: usize) -> Vec<[u8; 3]> {
    let high = |c: usize| (case >> c) & 1 == 1;
    // next[e] = the crossing that follows crossing e along its loop.
    let mut next = [usize::MAX; 12];
    for face in faces() {
        // Crossings in counter-clockwise order; a crossing entering the high region (low -> high) starts
        // a segment that ends at the next crossing leaving it, which puts the low side on the loop's left
        // seen from outside; the fan then faces the low side.
        let mut crossings: Vec<(usize, bool)> = Vec::new(); // (edge, entering high)
        for i in 0..4 {
            let (a, b) = (face[i], face[(i + 1) % 4]);
            if high(a) != high(b) {
                crossings.push((edge_index(a, b), high(b)));
            }
        }
        match crossings.len() {
            0 => {}
            2 => {
                let (enter, exit) = if crossings[0].1 {
                    (crossings[0].0, crossings[1].0)
                } else {
                    (crossings[1].0, crossings[0].0)
                };
                next[enter] = exit;
            }
            4 => {
                // Ambiguous face: pair each entering crossing with the exit right after it, which cuts
                // off each high corner on its own.
                for i in 0..4 {
                    if crossings[i].1 {
                        next[crossings[i].0] = crossings[(i + 1) % 4].0;
                    }
                }
            }
            _ => unreachable!("a face has an even number of crossings"),
        }
    }
    let mut triangles = Vec::new();
    let mut done = [false; 12];
    for start in 0..12 {
        if next[start] == usize::MAX || done[start] {
            continue;
        }
        let mut lp = vec![start];
        done[start] = true;
        let mut e = next[start];
        while e != start {
            lp.push(e);
            done[e] = true;
            e = next[e];
        }
        for i in 1..lp.len() - 1 {
            triangles.push([lp[0] as u8, lp[i] as u8, lp[i + 1] as u8]);
        }
    }
    triangles
}

/// See [`super::marching_cubes`].
pub(crate) fn marching_cubes(
    values: &[f32],
    dims: [usize; 3],
    origin_mm: DVec3,
    spacing_mm: DVec3,
    level: f64,
) -> Result<Mesh> {
    let expected = dims.iter().try_fold(1usize, |acc, &d| acc.checked_mul(d));
    if expected != Some(values.len()) {
        return Err(Error::InvalidInput(format!(
            "marching cubes: grid {}x{}x{} does not match {} values",
            dims[0],
            dims[1],
            dims[2],
            values.len()
        )));
    }
    if dims.iter().any(|&d| d >= 1 << 20) {
        return Err(Error::InvalidInput(format!(
            "marching cubes: grid {dims:?} has an axis of 2^20 or more nodes"
        )));
    }
    if !(origin_mm.is_finite() && spacing_mm.is_finite() && spacing_mm.min_element() > 0.0) {
        return Err(Error::InvalidInput(format!(
            "marching cubes: origin {origin_mm} and spacing {spacing_mm} must be finite, spacing positive"
        )));
    }
    if !level.is_finite() {
        return Err(Error::InvalidInput(format!(
            "marching cubes: level {level} is not finite"
        )));
    }
    let mut mesh = Mesh::default();
    if dims.iter().any(|&d| d < 2) {
        return Ok(mesh);
    }
    let table = case_table();
    let index = |i: usize, j: usize, k: usize| i + dims[0] * (j + dims[1] * k);
    let mut edge_vertex: CellMap<u32> = CellMap::default();
    let mut gradients: Vec<DVec3> = Vec::new();
    for k in 0..dims[2] - 1 {
        for j in 0..dims[1] - 1 {
            for i in 0..dims[0] - 1 {
                let corner = |c: usize| (i + (c & 1), j + ((c >> 1) & 1), k + ((c >> 2) & 1));
                let value = |c: usize| {
                    let (x, y, z) = corner(c);
                    values[index(x, y, z)] as f64
                };
                let mut case = 0;
                for c in 0..8 {
                    let v = value(c);
                    // NaN counts as below, like "not inside".
                    if v > level {
                        case |= 1 << c;
                    }
                }
                if case == 0 || case == 255 {
                    continue;
                }
                let mut vertex_of_edge = [u32::MAX; 12];
                for tri in &table[case] {
                    let ids = tri.map(|e| {
                        let e = e as usize;
                        if vertex_of_edge[e] == u32::MAX {
                            let (a, b) = EDGES[e];
                            let (ax, ay, az) = corner(a);
                            let key =
                                (index(ax, ay, az) as u64) << 2 | (b - a).trailing_zeros() as u64;
                            vertex_of_edge[e] = *edge_vertex.entry(key).or_insert_with(|| {
                                let (va, vb) = (value(a), value(b));
                                let t = ((level - va) / (vb - va))
                                    .clamp(EDGE_T_MARGIN, 1.0 - EDGE_T_MARGIN);
                                let t = if t.is_finite() { t } else { 0.5 };
                                let (bx, by, bz) = corner(b);
                                let pa = DVec3::new(ax as f64, ay as f64, az as f64);
                                let pb = DVec3::new(bx as f64, by as f64, bz as f64);
                                mesh.vertices
                                    .push(origin_mm + (pa + (pb - pa) * t) * spacing_mm);
                                gradients.push(
                                    central_gradient(values, dims, (ax, ay, az), (bx, by, bz), t)
                                        / spacing_mm,
                                );
                                (mesh.vertices.len() - 1) as u32
                            });
                        }
                        vertex_of_edge[e]
                    });
                    mesh.triangles.push(ids);
                }
            }
        }
    }
    // Normals toward lower values; a vanishing gradient falls back to the area-weighted face normal.
    let mut face_normals = vec![DVec3::ZERO; mesh.vertices.len()];
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|i| mesh.vertices[i as usize]);
        let n = (b - a).cross(c - a);
        for &i in t {
            face_normals[i as usize] += n;
        }
    }
    mesh.normals = gradients
        .iter()
        .zip(&face_normals)
        .map(|(g, f)| {
            (-*g)
                .try_normalize()
                .or(f.try_normalize())
                .unwrap_or(DVec3::Z)
        })
        .collect();
    Ok(mesh)
}

/// Central-difference gradient (per grid step) at parameter t between two neighbouring nodes.
fn central_gradient(
    values: &[f32],
    dims: [usize; 3],
    a: (usize, usize, usize),
    b: (usize, usize, usize),
    t: f64,
) -> DVec3 {
    let at = |p: (usize, usize, usize)| {
        let p = [p.0, p.1, p.2];
        let mut g = DVec3::ZERO;
        for axis in 0..3 {
            let mut lo = p;
            let mut hi = p;
            lo[axis] = p[axis].saturating_sub(1);
            hi[axis] = (p[axis] + 1).min(dims[axis] - 1);
            let v = |q: [usize; 3]| values[q[0] + dims[0] * (q[1] + dims[1] * q[2])] as f64;
            g[axis] = (v(hi) - v(lo)) / (hi[axis] - lo[axis]).max(1) as f64;
        }
        g
    };
    at(a) * (1.0 - t) + at(b) * t
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn faces_are_counter_clockwise_from_outside() {
        let p = |c: usize| DVec3::new((c & 1) as f64, ((c >> 1) & 1) as f64, ((c >> 2) & 1) as f64);
        for f in faces() {
            let n = (p(f[1]) - p(f[0])).cross(p(f[2]) - p(f[1]));
            let centre = f.iter().map(|&c| p(c)).sum::<DVec3>() / 4.0;
            assert!(n.dot(centre - DVec3::splat(0.5)) > 0.0, "{f:?}");
        }
    }

    #[test]
    fn every_case_closes_into_loops() {
        // Each crossed edge is used by the table exactly as often as a closed fan needs: the loops
        // cover every crossed edge, and complementary cases mirror the number of triangles only where no
        // face is ambiguous.
        for case in 1..255usize {
            let tris = &case_table()[case];
            let crossed: Vec<usize> = (0..12)
                .filter(|&e| ((case >> EDGES[e].0) & 1) != ((case >> EDGES[e].1) & 1))
                .collect();
            let mut used: Vec<usize> = tris.iter().flatten().map(|&e| e as usize).collect();
            used.sort_unstable();
            used.dedup();
            assert_eq!(used, crossed, "case {case}");
        }
    }
}
