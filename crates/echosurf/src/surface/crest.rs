//! The echo-ridge sheet extended by the echo crests of the frames (`segment::crests`): each crest's
//! normal runs across its chain in its frame, tilted by where the neighbouring frames show the wall;
//! the crests linked to the sheet's points (a chain of crests along the wall, each within a step of the
//! next, starting near a point) join the points the sheet is drawn through. Hysteresis as in
//! [`super::extend_ridge_sheet`]: a crest is taken as the continuation of a fitted echo, never on its
//! own, so speckle crests away from every wall stay out.

use glam::DVec3;
use rayon::prelude::*;

use crate::mesh::Mesh;
use crate::spatial::PointBuckets;

/// Points with unit normals.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct OrientedPoints {
    pub points: Vec<DVec3>,
    pub normals: Vec<DVec3>,
}

/// Fewest crests (the crest itself included) within the radius that give it a normal.
const MIN_NEIGHBOURS: usize = 6;

/// A crest placed in world mm, with its frame's geometry there.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlacedCrest {
    pub point: DVec3,
    /// Unit direction of the crest's chain in its frame.
    pub tangent: DVec3,
    /// Unit normal of the frame's plane.
    pub frame_normal: DVec3,
    /// Unit beam direction (away from the probe).
    pub beam: DVec3,
    /// Which frame shows it.
    pub frame: u32,
}

/// Each crest's normal: across its chain within its frame (turned toward the probe), tilted out of the
/// frame by where the other frames' crests within `radius_mm` lie along that direction (per frame, the
/// crest nearest along it; least squares through the crest). The least-spread plane of all the crests
/// around (PCA) is the frame's own plane wherever one frame shows several chains within reach, so the
/// direction within the frame is the chain's. Crests with fewer than [`MIN_NEIGHBOURS`] within reach
/// are dropped.
pub fn orient_crests(crests: &[PlacedCrest], radius_mm: f64) -> OrientedPoints {
    let points: Vec<DVec3> = crests.iter().map(|c| c.point).collect();
    let Some(grid) = PointBuckets::new(&points, radius_mm) else {
        return OrientedPoints::default();
    };
    let oriented: Vec<Option<(DVec3, DVec3)>> = crests
        .par_iter()
        .map(|c| {
            let e = c.frame_normal;
            let mut across = e.cross(c.tangent).try_normalize()?;
            if across.dot(c.beam) > 0.0 {
                across = -across;
            }
            // Per other frame, the crest nearest along `across`: (frame, offset along it, along e).
            let mut nearest: Vec<(u32, f64, f64)> = Vec::new();
            let mut count = 0usize;
            grid.visit_within(c.point, radius_mm, |j, q| {
                count += 1;
                let other = crests[j].frame;
                if other != c.frame {
                    let d = q - c.point;
                    let (a, b) = (d.dot(across), d.dot(e));
                    match nearest.iter_mut().find(|n| n.0 == other) {
                        Some(n) if a.abs() < n.1.abs() => *n = (other, a, b),
                        Some(_) => {}
                        None => nearest.push((other, a, b)),
                    }
                }
                true
            });
            if count < MIN_NEIGHBOURS {
                return None;
            }
            let (ab, bb) = nearest
                .iter()
                .fold((0.0, 0.0), |(ab, bb), &(_, a, b)| (ab + a * b, bb + b * b));
            let slope = if bb > 0.0 { ab / bb } else { 0.0 };
            Some((c.point, (across - e * slope).try_normalize()?))
        })
        .collect();
    let (points, normals) = oriented.into_iter().flatten().unzip();
    OrientedPoints { points, normals }
}

/// A link from one crest (or sheet point) to the next stays within this distance (mm) of the first's
/// tangent plane: a link runs along the wall, not across it to the echoes in front of or behind it.
pub const LINK_MAX_ACROSS_MM: f64 = 0.3;

/// A link turns the normal by at most this angle (degrees): the wall runs on smoothly.
pub const LINK_MAX_TURN_DEG: f64 = 30.0;

/// Which crests the oriented points `seeds` reach, each with its normal turned to agree with the point
/// it was reached from: the crests within `seed_mm` of a seed (turned as the nearest such seed), then
/// every crest linked to one of those by steps of at most `link_mm` from crest to crest (turned as the
/// crest before it). Every step stays within [`LINK_MAX_ACROSS_MM`] of the tangent plane of the point
/// it starts from and turns the normal by at most [`LINK_MAX_TURN_DEG`]. Turned along the links, the
/// sheet keeps one side even where a wall runs along the beam (no side faces the probe). `None`: not
/// reached.
pub fn linked_crest_normals(
    seeds: &OrientedPoints,
    crests: &OrientedPoints,
    seed_mm: f64,
    link_mm: f64,
) -> Vec<Option<DVec3>> {
    let mut reached: Vec<Option<DVec3>> = vec![None; crests.points.len()];
    let (Some(near_seeds), Some(links)) = (
        PointBuckets::new(&seeds.points, seed_mm),
        PointBuckets::new(&crests.points, link_mm),
    ) else {
        return reached;
    };
    let min_cos = LINK_MAX_TURN_DEG.to_radians().cos();
    // The normal `n` of a crest at `q` seen from a point `p` with normal `from`, turned to agree with
    // it; `None` when the step leaves `p`'s tangent plane or turns too far.
    let step = |p: DVec3, from: DVec3, q: DVec3, n: DVec3| {
        let turn = n.dot(from);
        ((q - p).dot(from).abs() <= LINK_MAX_ACROSS_MM && turn.abs() >= min_cos)
            .then(|| if turn < 0.0 { -n } else { n })
    };
    let starts: Vec<Option<DVec3>> = crests
        .points
        .par_iter()
        .zip(&crests.normals)
        .map(|(&c, &n)| {
            let mut nearest: Option<(f64, usize, DVec3)> = None;
            near_seeds.visit_within(c, seed_mm, |j, q| {
                let d2 = q.distance_squared(c);
                if let Some(turned) = seeds.normals.get(j).and_then(|&s| step(q, s, c, n))
                    && nearest.is_none_or(|(best, k, _)| d2 < best || (d2 == best && j < k))
                {
                    nearest = Some((d2, j, turned));
                }
                true
            });
            nearest.map(|(_, _, turned)| turned)
        })
        .collect();
    let mut stack: Vec<usize> = Vec::new();
    for (i, start) in starts.into_iter().enumerate() {
        if start.is_some() {
            reached[i] = start;
            stack.push(i);
        }
    }
    while let Some(i) = stack.pop() {
        let (Some(from), p) = (reached[i], crests.points[i]) else {
            continue;
        };
        links.visit_within(p, link_mm, |j, q| {
            if reached[j].is_none()
                && let Some(turned) = step(p, from, q, crests.normals[j])
            {
                reached[j] = Some(turned);
                stack.push(j);
            }
            true
        });
    }
    reached
}

/// How [`add_linked_crests`] links crests to a sheet's points.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CrestLink {
    /// A crest this close (mm) to one of the points starts a link.
    pub seed_mm: f64,
    /// Longest step (mm) from one linked crest to the next.
    pub link_mm: f64,
}

/// Adds to `sheet_points` (the oriented points a sheet is drawn through, normals toward the probe) the
/// crests linked to them, turned as they link ([`linked_crest_normals`]); returns how many. Points
/// without normals take none.
pub fn add_linked_crests(
    sheet_points: &mut OrientedPoints,
    crests: &OrientedPoints,
    link: CrestLink,
) -> usize {
    if sheet_points.points.is_empty() || sheet_points.normals.len() != sheet_points.points.len() {
        return 0;
    }
    let linked = linked_crest_normals(sheet_points, crests, link.seed_mm, link.link_mm);
    let before = sheet_points.points.len();
    for (p, n) in crests.points.iter().zip(linked) {
        if let Some(n) = n {
            sheet_points.points.push(*p);
            sheet_points.normals.push(n);
        }
    }
    sheet_points.points.len() - before
}

/// Removes the pieces of `mesh` in which fewer than `min_share` of the triangles have a vertex within
/// `reach_mm` of an anchor (0: pieces with none): a sheet drawn through a ridge sheet's points and
/// crests keeps the pieces that continue the ridge sheet, not crumbs drawn through crests alone.
/// Returns the triangles removed.
pub fn keep_pieces_reaching(
    mesh: &mut Mesh,
    anchors: &[DVec3],
    reach_mm: f64,
    min_share: f64,
) -> usize {
    let Some(near) = PointBuckets::new(anchors, reach_mm) else {
        let removed = mesh.triangles.len();
        mesh.retain_triangles(&vec![false; removed]);
        return removed;
    };
    let components = mesh.triangle_components();
    // Each vertex looked up once (a vertex is shared by about six triangles).
    let near_vertex: Vec<bool> = mesh
        .vertices
        .par_iter()
        .map(|&v| near.contains(v))
        .collect();
    let (mut anchored, mut total) = (
        vec![0usize; components.len()],
        vec![0usize; components.len()],
    );
    for (f, t) in mesh.triangles.iter().enumerate() {
        total[components[f]] += 1;
        if t.iter()
            .any(|&i| near_vertex.get(i as usize).copied().unwrap_or(false))
        {
            anchored[components[f]] += 1;
        }
    }
    let keep: Vec<bool> = components
        .iter()
        .map(|&c| anchored[c] > 0 && anchored[c] as f64 >= min_share * total[c] as f64)
        .collect();
    mesh.retain_triangles(&keep)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::surface::{SheetOptions, SurfaceDomain, SurfaceOptions, sheet_through_points};

    /// Points on the plane through the origin with normal `n`, on a 0.2 mm grid within `r` mm.
    fn plane_points(n: DVec3, centre: DVec3, r: f64) -> Vec<DVec3> {
        let a = n.any_orthonormal_vector();
        let b = n.cross(a);
        let k = (r / 0.2) as i32;
        (-k..=k)
            .flat_map(|i| {
                (-k..=k).map(move |j| centre + a * (i as f64 * 0.2) + b * (j as f64 * 0.2))
            })
            .collect()
    }

    /// Crests of a wall through the origin with normal `n` (toward the probe, which looks along -z)
    /// seen by frames x = 0.5 k (|k| <= 4, frame normal +x): each frame's chain every 0.2 mm along the
    /// wall's line in the frame, and a second chain `stack_mm` deeper (another echo behind the wall).
    fn wall_crests(n: DVec3, stack_mm: f64) -> Vec<PlacedCrest> {
        let tangent = DVec3::X.cross(n).normalize();
        let mut crests = Vec::new();
        for k in -4..=4 {
            let x = 0.5 * k as f64;
            // The wall's point of the frame on its z axis: n . (x, 0, z) = 0.
            let on_axis = DVec3::new(x, 0.0, -n.x * x / n.z);
            for depth in [0.0, stack_mm] {
                for i in -15..=15 {
                    crests.push(PlacedCrest {
                        point: on_axis + tangent * (0.2 * i as f64) - DVec3::Z * depth,
                        tangent,
                        frame_normal: DVec3::X,
                        beam: DVec3::NEG_Z,
                        frame: (k + 4) as u32,
                    });
                }
            }
        }
        crests
    }

    #[test]
    fn crest_normals_follow_the_chain_and_the_neighbouring_frames_toward_the_probe() {
        // Tilted across the frames (out of plane, 14 degrees) and within them, with a second echo
        // 1.5 mm behind the wall in every frame: each crest gets the wall's normal. (Per frame the
        // crest nearest along the in-frame normal is taken: a wall tilted so far that, within the
        // radius, it moves by more than half its distance to the echo behind it would take that echo.)
        let n = DVec3::new(0.25, 0.3, 1.0).normalize();
        let crests = wall_crests(n, 1.5);
        let oriented = orient_crests(&crests, 2.5);
        assert_eq!(oriented.points.len(), crests.len());
        for ((p, normal), c) in oriented.points.iter().zip(&oriented.normals).zip(&crests) {
            assert_eq!(*p, c.point);
            // Both echoes are planes with normal n (the sweep's end frames see neighbours on one side).
            assert!(normal.dot(n) > 1.0 - 1e-9, "{normal} against {n} at {p}");
        }
        // Without other frames the normal is the chain's across direction in its frame (no tilt).
        let one_frame: Vec<PlacedCrest> = crests.iter().filter(|c| c.frame == 4).copied().collect();
        let flat = orient_crests(&one_frame, 2.5);
        let across = DVec3::X.cross(one_frame[0].tangent).normalize();
        assert!(
            flat.normals
                .iter()
                .all(|m| m.dot(across).abs() > 1.0 - 1e-9)
        );
        // A lone crest has no neighbours: dropped.
        assert!(orient_crests(&crests[..1], 2.5).points.is_empty());
    }

    #[test]
    fn only_crests_linked_to_the_sheet_extend_it() {
        // The sheet: a flat patch in z = 0 over x < 0. Crests: the same plane continued over
        // 0 <= x < 4 (linked), and a patch 3 mm below it (not linked: no crest within a step).
        let sheet_points: Vec<DVec3> = plane_points(DVec3::Z, DVec3::new(-2.0, 0.0, 0.0), 2.0);
        let domain = SurfaceDomain {
            bounds_min_mm: DVec3::new(-6.0, -4.0, -6.0),
            bounds_max_mm: DVec3::new(6.0, 4.0, 3.0),
            seeds: Vec::new(),
            trust_points: Vec::new(),
        };
        let surface = SurfaceOptions {
            resolution_mm: 0.25,
            ..SurfaceOptions::default()
        };
        let (sheet, _) = sheet_through_points(
            &sheet_points,
            &vec![DVec3::Z; sheet_points.len()],
            &domain,
            &surface,
            &SheetOptions::default(),
        )
        .unwrap();
        assert!(sheet.vertices.iter().all(|v| v.x < 0.9));
        let mut crest_points = plane_points(DVec3::Z, DVec3::new(2.0, 0.0, 0.0), 2.0);
        crest_points.retain(|p| p.x >= 0.0);
        let far = plane_points(DVec3::Z, DVec3::new(2.0, 0.0, -3.0), 1.0);
        let all: Vec<DVec3> = crest_points.iter().chain(&far).copied().collect();
        let crests = OrientedPoints {
            normals: vec![DVec3::Z; all.len()],
            points: all,
        };
        let link = CrestLink {
            seed_mm: 0.75,
            link_mm: 0.6,
        };
        let mut points = OrientedPoints {
            points: sheet.vertices.clone(),
            normals: sheet.normals.clone(),
        };
        let linked = linked_crest_normals(&points, &crests, link.seed_mm, link.link_mm);
        assert!(linked[..crest_points.len()].iter().all(|l| l.is_some()));
        assert!(linked[crest_points.len()..].iter().all(|l| l.is_none()));
        // A link runs along the wall: an echo 0.4 mm behind the continued plane (within a step, but
        // across it) and crests turned 45 degrees are not reached; normals given the other way round
        // are turned as the sheet's.
        let behind = plane_points(DVec3::Z, DVec3::new(2.0, 0.0, -0.4), 2.0);
        let turned = plane_points(DVec3::Z, DVec3::new(2.0, 0.0, 0.0), 2.0);
        let tilted = DVec3::new(1.0, 0.0, 1.0).normalize();
        let mixed = OrientedPoints {
            points: [crest_points.clone(), behind.clone(), turned.clone()].concat(),
            normals: [
                vec![DVec3::NEG_Z; crest_points.len()],
                vec![DVec3::Z; behind.len()],
                vec![tilted; turned.len()],
            ]
            .concat(),
        };
        let reached = linked_crest_normals(&points, &mixed, link.seed_mm, link.link_mm);
        let (along, rest) = reached.split_at(crest_points.len());
        assert!(
            along.iter().all(|n| *n == Some(DVec3::Z)),
            "turned as the sheet"
        );
        assert!(rest.iter().all(|n| n.is_none()));
        let count = add_linked_crests(&mut points, &crests, link);
        assert_eq!(count, crest_points.len());
        let (extended, _) = sheet_through_points(
            &points.points,
            &points.normals,
            &domain,
            &surface,
            &SheetOptions::default(),
        )
        .unwrap();
        // The sheet now runs over the linked crests, stays on the plane, and never reaches the far patch.
        assert!(extended.vertices.iter().any(|v| v.x > 3.5));
        assert!(
            extended.vertices.iter().all(|v| v.z.abs() < 0.05),
            "off the plane"
        );
        // A piece drawn through the far patch alone (as a sheet through all the crests would) does not
        // reach the ridge sheet: removed; the extended sheet stays.
        let (mut with_far, _) = sheet_through_points(
            &[points.points.clone(), far.clone()].concat(),
            &vec![DVec3::Z; points.points.len() + far.len()],
            &domain,
            &surface,
            &SheetOptions::default(),
        )
        .unwrap();
        assert_eq!(with_far.topology().components, 2);
        let removed = keep_pieces_reaching(&mut with_far, &sheet.vertices, link.seed_mm, 0.0);
        assert!(removed > 0);
        assert_eq!(with_far.topology().components, 1);
        assert!(with_far.vertices.iter().all(|v| v.z.abs() < 0.05));
        assert_eq!(extended.topology().components, 1);
    }
}
