//! Which of the truth's walls a mesh joins: a hollow phantom's outer and inner surfaces are separate
//! components of its truth, and one sheet per wall means no piece of the mesh runs from one to another.

use super::Nearest;
use crate::mesh::Mesh;

/// A piece counts as lying on a wall when at least this share of its vertices do.
pub const WALL_MIN_SHARE: f64 = 0.1;

/// How a mesh joins the truth's walls (its edge-connected components). Each mesh vertex lies on the
/// wall of its nearest truth triangle.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
pub struct WallJoins {
    /// Edge-connected components of the truth.
    pub truth_walls: usize,
    /// Mesh edges from a vertex on one wall to a vertex on another.
    pub edges_across_walls: usize,
    /// Mesh pieces with at least [`WALL_MIN_SHARE`] of their vertices on each of two or more walls.
    pub pieces_on_several_walls: usize,
}

/// [`WallJoins`] of `mesh` against `truth`, given each mesh vertex's nearest truth triangle (`None`:
/// unused vertex). Meshes are validated by the caller (indices in range).
pub(super) fn wall_joins(
    mesh: &Mesh,
    truth: &Mesh,
    vertex_nearest: &[Option<Nearest>],
) -> WallJoins {
    // Truth components, numbered densely in order of first triangle.
    let component = truth.triangle_components();
    let mut dense = vec![usize::MAX; component.len()];
    let mut truth_walls = 0;
    let wall_of_triangle: Vec<usize> = component
        .iter()
        .map(|&c| {
            if dense[c] == usize::MAX {
                dense[c] = truth_walls;
                truth_walls += 1;
            }
            dense[c]
        })
        .collect();
    let wall: Vec<Option<usize>> = vertex_nearest
        .iter()
        .map(|n| n.map(|n| wall_of_triangle[n.triangle as usize]))
        .collect();
    let mut edges: Vec<(u32, u32)> = mesh
        .triangles
        .iter()
        .flat_map(|t| [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])])
        .map(|(a, b)| (a.min(b), a.max(b)))
        .collect();
    edges.sort_unstable();
    edges.dedup();
    let edges_across_walls = edges
        .iter()
        .filter(
            |&&(a, b)| matches!((wall[a as usize], wall[b as usize]), (Some(x), Some(y)) if x != y),
        )
        .count();
    // Per mesh piece, its vertices on each wall.
    let piece = mesh.triangle_components();
    let mut piece_of_vertex = vec![usize::MAX; mesh.vertices.len()];
    for (t, &p) in mesh.triangles.iter().zip(&piece) {
        for &i in t {
            piece_of_vertex[i as usize] = p;
        }
    }
    let mut on: Vec<(usize, usize)> = piece_of_vertex
        .iter()
        .zip(&wall)
        .filter_map(|(&p, w)| Some((p, (*w)?)).filter(|_| p != usize::MAX))
        .collect();
    on.sort_unstable();
    let mut pieces_on_several_walls = 0;
    for run in on.chunk_by(|a, b| a.0 == b.0) {
        let counts: Vec<usize> = run.chunk_by(|a, b| a.1 == b.1).map(|w| w.len()).collect();
        let walls = counts
            .iter()
            .filter(|&&c| c as f64 >= WALL_MIN_SHARE * run.len() as f64)
            .count();
        if walls >= 2 {
            pieces_on_several_walls += 1;
        }
    }
    WallJoins {
        truth_walls,
        edges_across_walls,
        pieces_on_several_walls,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec3;

    /// A flat square grid of `n` x `n` cells over [0, size]^2 at height z, as its own mesh.
    fn square(z: f64, size: f64, n: u32) -> Mesh {
        let mut mesh = Mesh::default();
        for j in 0..=n {
            for i in 0..=n {
                let (x, y) = (size * i as f64 / n as f64, size * j as f64 / n as f64);
                mesh.vertices.push(DVec3::new(x, y, z));
                mesh.normals.push(DVec3::Z);
            }
        }
        let at = |i: u32, j: u32| j * (n + 1) + i;
        for j in 0..n {
            for i in 0..n {
                mesh.triangles
                    .push([at(i, j), at(i + 1, j), at(i + 1, j + 1)]);
                mesh.triangles
                    .push([at(i, j), at(i + 1, j + 1), at(i, j + 1)]);
            }
        }
        mesh
    }

    fn joined(parts: &[Mesh]) -> Mesh {
        let mut out = Mesh::default();
        for p in parts {
            let base = out.vertices.len() as u32;
            out.vertices.extend(&p.vertices);
            out.normals.extend(&p.normals);
            out.triangles
                .extend(p.triangles.iter().map(|t| t.map(|i| i + base)));
        }
        out
    }

    #[test]
    fn a_sheet_per_wall_joins_nothing_and_a_fold_between_them_is_counted() {
        // Truth: two walls 2 mm apart (z = 0 and z = 2), 10 mm square each.
        let truth = joined(&[square(0.0, 10.0, 4), square(2.0, 10.0, 4)]);
        let bvh = super::super::TriangleBvh::new(&truth);
        let wall_joins =
            |m: &Mesh| wall_joins(m, &truth, &super::super::used_vertex_nearest(m, &bvh));
        // One sheet on each wall, a little off it: two pieces, nothing joined.
        let apart = joined(&[square(0.2, 10.0, 5), square(1.8, 10.0, 5)]);
        assert_eq!(
            wall_joins(&apart),
            WallJoins {
                truth_walls: 2,
                edges_across_walls: 0,
                pieces_on_several_walls: 0,
            }
        );
        // A fold: a strip in the plane x = 5 from z = 0.2 up to z = 1.8 in 4 rows (z 0.2, 0.6, 1.0+,
        // 1.4, 1.8; the middle row just above 1, so it lies on the upper wall), 3 columns along y: the
        // edges from the row at 0.6 to the row above 1 cross, 3 + 2 of them (rungs and diagonals).
        let mut fold = Mesh::default();
        let rows = [0.2, 0.6, 1.05, 1.4, 1.8];
        for &z in &rows {
            for k in 0..3 {
                fold.vertices.push(DVec3::new(5.0, 2.0 + 2.0 * k as f64, z));
                fold.normals.push(DVec3::X);
            }
        }
        for r in 0..rows.len() as u32 - 1 {
            for k in 0..2 {
                let a = r * 3 + k;
                fold.triangles.push([a, a + 1, a + 4]);
                fold.triangles.push([a, a + 4, a + 3]);
            }
        }
        let joins = wall_joins(&fold);
        assert_eq!(joins.truth_walls, 2);
        assert_eq!(joins.edges_across_walls, 5);
        assert_eq!(joins.pieces_on_several_walls, 1);
        // The fold beside the two sheets: still one piece on several walls.
        let all = joined(&[apart, fold]);
        assert_eq!(wall_joins(&all).pieces_on_several_walls, 1);
    }
}
