//! Marching tetrahedra over the cubic lattice (the raw surface before clustering).
//!
//! Every cube is split into the six tetrahedra of the Kuhn (Freudenthal) triangulation around its main
//! diagonal from corner 0 to corner 7: the tetrahedron of axis order (a, b, c) has corners 0, e_a, e_a + e_b
//! and 7. The split is identical in every cube, so neighbouring tetrahedra share faces exactly and every
//! edge joins a node `p` to `p + d` with `d` in {0,1}^3: an edge is named by (`p`, `d`) globally and its
//! vertex is shared by every tetrahedron around it. A value equal to the level counts as below it
//! (a symbolic perturbation), so no vertex falls on a node and the surface of each tetrahedron is a
//! triangle or a quadrilateral with no ambiguous case.

use glam::DVec3;

use super::lattice::{Ijk, Lattice, add, corner_offset};
use crate::spatial::cell_grid::{CellMap, pack_cell, unpack_cell};

/// The Kuhn tetrahedra as cube-corner bitmasks along a monotone path 0 -> 7.
pub(crate) const KUHN_TETS: [[usize; 4]; 6] = [
    [0, 1, 3, 7],
    [0, 1, 5, 7],
    [0, 2, 3, 7],
    [0, 2, 6, 7],
    [0, 4, 5, 7],
    [0, 4, 6, 7],
];

/// Interpolation parameters are kept this far from the nodes so no two edge vertices coincide.
pub(crate) const EDGE_T_MARGIN: f64 = 1e-4;

/// The raw marching-tetrahedra mesh of one level.
#[derive(Debug, Default)]
pub(crate) struct RawSurface {
    /// Linearly interpolated vertex positions (mm).
    pub positions: Vec<DVec3>,
    /// The vertex's clustering cell ([`cluster_key`]).
    pub cluster_keys: Vec<u64>,
    /// The lattice edge (node positions, mm) each vertex was interpolated on: the cached node values
    /// straddle the level, so the field crosses it somewhere on that segment.
    pub edges: Vec<(DVec3, DVec3)>,
    /// Triangles wound counter-clockwise seen from the lower-valued side.
    pub triangles: Vec<[u32; 3]>,
}

fn lattice_direction(d: usize) -> DVec3 {
    let o = corner_offset(d);
    DVec3::new(o[0] as f64, o[1] as f64, o[2] as f64)
}

/// The clustering cell of a point `q` given in clustering-lattice coordinates (lattice coordinates
/// divided by the cluster scale): the Voronoi cell (a rhombic dodecahedron of volume 2 scale^3 h^3) of
/// the nearest point with integer coordinates of even sum (the face-centred cubic lattice). The rhombic
/// dodecahedron is the roundest space-filling cell, which keeps the merged triangles well shaped. The
/// key is offset by one so it stays non-negative at the lattice's lower faces.
pub(crate) fn cluster_key(q: DVec3) -> u64 {
    let mut r = q.round();
    if (r.x + r.y + r.z).rem_euclid(2.0) != 0.0 {
        // Odd sum: move the coordinate that rounded farthest to its other neighbour.
        let err = q - r;
        let axis = if err.x.abs() >= err.y.abs() && err.x.abs() >= err.z.abs() {
            0
        } else if err.y.abs() >= err.z.abs() {
            1
        } else {
            2
        };
        r[axis] += if err[axis] >= 0.0 { 1.0 } else { -1.0 };
    }
    pack_cell([r.x as i32 + 1, r.y as i32 + 1, r.z as i32 + 1])
}

/// Marching tetrahedra over `cells` (packed keys, sorted: vertex numbering follows this order).
/// `value_at` returns the cached lattice value of a node.
pub(crate) fn march_tetrahedra(
    lattice: &Lattice,
    cells: &[u64],
    level: f64,
    cluster_scale: f64,
    value_at: impl Fn(Ijk) -> f64,
) -> RawSurface {
    let mut raw = RawSurface::default();
    let mut edge_vertex: CellMap<u32> = CellMap::default();
    edge_vertex.reserve(cells.len() * 3);
    for &cell_key in cells {
        let cell = unpack_cell(cell_key);
        let corners: [Ijk; 8] = std::array::from_fn(|c| add(cell, corner_offset(c)));
        let values: [f64; 8] = std::array::from_fn(|c| value_at(corners[c]));
        if values.iter().any(|v| v.is_nan()) {
            // The field is undefined at a corner (see `ScalarField::nan_means_undefined`).
            continue;
        }
        let high: [bool; 8] = std::array::from_fn(|c| values[c] > level);
        if high.iter().all(|&h| h) || high.iter().all(|&h| !h) {
            continue;
        }
        for tet in KUHN_TETS {
            let n_high = tet.iter().filter(|&&c| high[c]).count();
            if n_high == 0 || n_high == 4 {
                continue;
            }
            // The vertex on the tetrahedron edge between corners a and b (a < b as bitmasks, so b - a
            // is the edge direction and a the lower node).
            let mut vertex = |a: usize, b: usize| -> u32 {
                let (a, b) = if a < b { (a, b) } else { (b, a) };
                let key = pack_cell(corners[a]) << 3 | (b - a) as u64;
                *edge_vertex.entry(key).or_insert_with(|| {
                    let (va, vb) = (values[a], values[b]);
                    let t = ((level - va) / (vb - va)).clamp(EDGE_T_MARGIN, 1.0 - EDGE_T_MARGIN);
                    let pa = lattice.node_position(corners[a]);
                    let pb = lattice.node_position(corners[b]);
                    raw.positions.push(pa + (pb - pa) * t);
                    raw.edges.push((pa, pb));
                    let q = DVec3::new(
                        corners[a][0] as f64,
                        corners[a][1] as f64,
                        corners[a][2] as f64,
                    ) + lattice_direction(b - a) * t;
                    raw.cluster_keys.push(cluster_key(q / cluster_scale));
                    (raw.positions.len() - 1) as u32
                })
            };
            // Orientation is decided on edge midpoints: the surface of a tetrahedron under linear
            // interpolation is a planar section whose orientation does not depend on where along the
            // edges it cuts, and midpoint triangles are never degenerate.
            let corner_point = |c: usize| {
                let o = corner_offset(c);
                DVec3::new(o[0] as f64, o[1] as f64, o[2] as f64)
            };
            let (mut high_sum, mut low_sum) = (DVec3::ZERO, DVec3::ZERO);
            for &c in &tet {
                if high[c] {
                    high_sum += corner_point(c);
                } else {
                    low_sum += corner_point(c);
                }
            }
            let toward_low = low_sum / (4 - n_high) as f64 - high_sum / n_high as f64;
            let emit = |e: [(usize, usize); 3], raw_tris: &mut Vec<[u32; 3]>, ids: [u32; 3]| {
                let m = e.map(|(a, b)| (corner_point(a) + corner_point(b)) * 0.5);
                let normal = (m[1] - m[0]).cross(m[2] - m[0]);
                raw_tris.push(if normal.dot(toward_low) > 0.0 {
                    ids
                } else {
                    [ids[0], ids[2], ids[1]]
                });
            };
            // The tetrahedron's corners above the level, then those below (in corner order).
            let (mut highs, mut lows) = ([0usize; 4], [0usize; 4]);
            let (mut n_highs, mut n_lows) = (0, 0);
            for &c in &tet {
                if high[c] {
                    highs[n_highs] = c;
                    n_highs += 1;
                } else {
                    lows[n_lows] = c;
                    n_lows += 1;
                }
            }
            match n_high {
                1 | 3 => {
                    let (apex, base) = if n_high == 1 {
                        (highs[0], [lows[0], lows[1], lows[2]])
                    } else {
                        (lows[0], [highs[0], highs[1], highs[2]])
                    };
                    let e = base.map(|b| (apex, b));
                    let ids = e.map(|(a, b)| vertex(a, b));
                    emit(e, &mut raw.triangles, ids);
                }
                _ => {
                    // Quadrilateral ac - ad - bd - bc, split along ac - bd.
                    let (a, b, c, d) = (highs[0], highs[1], lows[0], lows[1]);
                    let quad = [(a, c), (a, d), (b, d), (b, c)];
                    let ids = quad.map(|(x, y)| vertex(x, y));
                    emit(
                        [quad[0], quad[1], quad[2]],
                        &mut raw.triangles,
                        [ids[0], ids[1], ids[2]],
                    );
                    emit(
                        [quad[0], quad[2], quad[3]],
                        &mut raw.triangles,
                        [ids[0], ids[2], ids[3]],
                    );
                }
            }
        }
    }
    raw
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cluster_key_is_the_nearest_even_node() {
        for q in [
            DVec3::new(0.2, 0.1, 0.0),
            DVec3::new(0.6, 0.45, 0.1),
            DVec3::new(2.9, 1.2, 3.4),
            DVec3::new(0.0, 0.0, 0.9),
        ] {
            let mut best = (f64::INFINITY, [0i32; 3]);
            for x in -1..5 {
                for y in -1..5 {
                    for z in -1..5 {
                        let d = q.distance(DVec3::new(x as f64, y as f64, z as f64));
                        if (x + y + z) % 2 == 0 && d < best.0 {
                            best = (d, [x + 1, y + 1, z + 1]);
                        }
                    }
                }
            }
            assert_eq!(cluster_key(q), pack_cell(best.1), "{q}");
        }
    }

    #[test]
    fn kuhn_tetrahedra_tile_the_cube() {
        // Volumes sum to the cube's and every tetrahedron follows a monotone corner path.
        let p = |c: usize| {
            let o = corner_offset(c);
            DVec3::new(o[0] as f64, o[1] as f64, o[2] as f64)
        };
        let mut volume = 0.0;
        for t in KUHN_TETS {
            for w in t.windows(2) {
                assert_eq!(w[0] & w[1], w[0], "edge {w:?} is not monotone");
                assert_eq!((w[1] - w[0]).count_ones(), 1);
            }
            volume += (p(t[1]) - p(t[0]))
                .cross(p(t[2]) - p(t[0]))
                .dot(p(t[3]) - p(t[0]))
                .abs()
                / 6.0;
        }
        assert!((volume - 1.0).abs() < 1e-12);
    }
}
