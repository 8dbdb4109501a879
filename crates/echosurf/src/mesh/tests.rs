#[test]
fn pieces_far_smaller_than_the_largest_are_removed_at_any_scale() {
    // A square of side `k` (area k^2) and two right triangles apart from it, of areas 0.004 and 0.006
    // times the square's: under half a percent of the largest piece goes, whatever the scale; an
    // absolute smallest area still applies on top.
    let mesh = |k: f64| {
        let leg = |share: f64| (2.0 * share).sqrt() * k;
        let (a, b) = (leg(0.004), leg(0.006));
        Mesh {
            vertices: vec![
                DVec3::ZERO,
                DVec3::X * k,
                DVec3::new(k, k, 0.0),
                DVec3::Y * k,
                DVec3::new(3.0 * k, 0.0, 0.0),
                DVec3::new(3.0 * k + a, 0.0, 0.0),
                DVec3::new(3.0 * k, a, 0.0),
                DVec3::new(5.0 * k, 0.0, 0.0),
                DVec3::new(5.0 * k + b, 0.0, 0.0),
                DVec3::new(5.0 * k, b, 0.0),
            ],
            normals: vec![DVec3::Z; 10],
            triangles: vec![[0, 1, 2], [0, 2, 3], [4, 5, 6], [7, 8, 9]],
        }
    };
    for k in [0.1, 1.0, 30.0] {
        let mut m = mesh(k);
        assert_eq!(m.remove_minor_components(0.0, 0.005), 1, "side {k}");
        assert_eq!(m.triangles.len(), 3);
        assert_eq!(m.topology().components, 2);
        // The share alone equals the absolute area it stands for.
        let mut absolute = mesh(k);
        absolute.remove_small_components(0.005 * k * k);
        assert_eq!(absolute, m);
    }
    // Share 0 is the absolute rule; the larger of the two thresholds wins.
    let mut m = mesh(1.0);
    assert_eq!(m.remove_minor_components(0.0, 0.0), 0);
    assert_eq!(m.remove_minor_components(0.01, 0.005), 2);
    assert_eq!(m.topology().components, 1);
    assert_eq!(Mesh::default().remove_minor_components(1.0, 0.5), 0);
}

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
