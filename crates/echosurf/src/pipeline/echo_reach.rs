//! Which points of a surface some echo backs, allowing for the gaps between frames.
//!
//! An echo is seen in one frame's plane; the space between that frame and the next one on either side
//! was never imaged, and a wall crossing it is backed by the echoes of the frames around it. A plain
//! distance (a point within D of an echo) therefore fails in the middle of every gap wider than 2D:
//! at a sweep's fringe, where a freehand sweep's frames thin out, it cut a finger of the simulated hand
//! in two. Here each echo stands for the space out of its plane up to half the gap to the nearest frame
//! on that side whose image covers the same spot (at most a cap), and a point is backed when it lies
//! within D of an echo in the plane and within D of that slab across it. Beyond a sweep's last frame
//! nothing was imaged, so there the distance is the plain one; so it is across a gap wider than twice
//! the cap (a break in the sweep).

use crate::io::PoseResolution;
use crate::io::pose::FramePlane;
use crate::spatial::PointBuckets;
use glam::DVec3;
use rayon::prelude::*;

/// Frames whose normals differ by more than this do not bound each other's gaps (their line-plane
/// intersections run off to infinity): cos 60 degrees.
const MIN_NORMAL_COSINE: f64 = 0.5;

/// Gaps are measured on a grid of this many pixels per frame: the gap varies smoothly over a frame
/// (the probe tilts), and a 256 x 200 frame then takes 17 x 14 probes.
const GAP_GRID_STEP_PX: usize = 16;

/// Below this the two frames are one (a paused probe repeats its frame): no gap between them.
const SAME_PLANE_MM: f64 = 0.01;

/// Kept echoes and how far out of its frame's plane each one reaches on either side.
pub(crate) struct EchoReach {
    max_distance_mm: f64,
    /// The echoes bucketed at `max_distance_mm` (the plain test, most points pass it) and at
    /// `max_distance_mm` + the largest reach (the test across a gap).
    near: Option<PointBuckets>,
    far: Option<PointBuckets>,
    largest_reach_mm: f64,
    /// Per echo: its frame's unit normal, and the reach along +normal and -normal.
    normals: Vec<DVec3>,
    reach_mm: Vec<[f64; 2]>,
}

impl EchoReach {
    /// `echoes[k]` was seen in frame `echo_frames[k]` (a sequence frame index, as in
    /// `SampleSet::frame_of_sample`); frames of `width` x `height` pixels placed by `poses`. Each echo
    /// reaches half the gap to the nearest covering frame on each side, at most `reach_cap_mm`; none on
    /// a side with no covering frame within twice that.
    pub(crate) fn new(
        echoes: &[DVec3],
        echo_frames: &[u32],
        poses: &PoseResolution,
        frame_size_px: [usize; 2],
        max_distance_mm: f64,
        reach_cap_mm: f64,
    ) -> EchoReach {
        let [width, height] = frame_size_px;
        let planes: Vec<Option<FramePlane>> = poses
            .poses
            .iter()
            .map(|p| FramePlane::new(p.image_to_world))
            .collect();
        let max_frame = poses.poses.iter().map(|p| p.frame_index).max();
        let mut pose_of_frame = vec![usize::MAX; max_frame.map_or(0, |m| m + 1)];
        for (k, p) in poses.poses.iter().enumerate() {
            pose_of_frame[p.frame_index] = k;
        }
        let grid = GapGrid::new(width, height);
        let cap = if reach_cap_mm.is_finite() {
            reach_cap_mm.max(0.0)
        } else {
            0.0
        };
        // Frames farther apart than their half-diagonals and the gap searched cannot bound each other.
        let bounds: Vec<Option<(DVec3, f64)>> = planes
            .iter()
            .map(|plane| {
                plane.map(|p| {
                    let far = [
                        (width.saturating_sub(1)) as f64,
                        (height.saturating_sub(1)) as f64,
                    ];
                    let centre = p.world_of([0.5 * far[0], 0.5 * far[1]]);
                    (centre, centre.distance(p.origin))
                })
            })
            .collect();
        let frame_gaps: Vec<Vec<[f64; 2]>> = (0..planes.len())
            .into_par_iter()
            .map(|f| {
                let near: Vec<FramePlane> = match bounds[f] {
                    Some((centre, radius)) => planes
                        .iter()
                        .zip(&bounds)
                        .enumerate()
                        .filter_map(|(g, (plane, b))| {
                            let (c, r) = (*b)?;
                            (g != f && c.distance(centre) <= radius + r + 2.0 * cap)
                                .then_some((*plane)?)
                        })
                        .collect(),
                    None => Vec::new(),
                };
                grid.half_gaps(planes[f], &near, [width, height], cap)
            })
            .collect();
        let mut normals = Vec::with_capacity(echoes.len());
        let mut reach_mm = Vec::with_capacity(echoes.len());
        for (&p, &frame) in echoes.iter().zip(echo_frames) {
            let pose = pose_of_frame
                .get(frame as usize)
                .copied()
                .unwrap_or(usize::MAX);
            match planes.get(pose).copied().flatten() {
                Some(plane) => {
                    normals.push(plane.normal);
                    reach_mm.push(frame_gaps[pose][grid.node_of(plane.pixel_of(p))]);
                }
                None => {
                    normals.push(DVec3::Z);
                    reach_mm.push([0.0, 0.0]);
                }
            }
        }
        let largest_reach_mm = reach_mm
            .iter()
            .flat_map(|r| r.iter().copied())
            .fold(0.0, f64::max);
        let usable = max_distance_mm.is_finite() && max_distance_mm > 0.0;
        EchoReach {
            max_distance_mm,
            near: usable
                .then(|| PointBuckets::new(echoes, max_distance_mm))
                .flatten(),
            far: (usable && largest_reach_mm > 0.0)
                .then(|| PointBuckets::new(echoes, max_distance_mm + largest_reach_mm))
                .flatten(),
            largest_reach_mm,
            normals,
            reach_mm,
        }
    }

    /// Whether an echo backs `p`: within the distance of it in its plane, and of its slab across.
    pub(crate) fn backs(&self, p: DVec3) -> bool {
        if self.near.as_ref().is_some_and(|b| b.contains(p)) {
            return true;
        }
        let Some(far) = &self.far else {
            return false;
        };
        let d2 = self.max_distance_mm * self.max_distance_mm;
        let mut backed = false;
        far.visit_within(
            p,
            self.max_distance_mm + self.largest_reach_mm,
            |k, echo| {
                let d = p - echo;
                let along = d.dot(self.normals[k]);
                let in_plane2 = (d.length_squared() - along * along).max(0.0);
                let reach = self.reach_mm[k][usize::from(along < 0.0)];
                let across = (along.abs() - reach).max(0.0);
                backed = in_plane2 + across * across <= d2;
                !backed
            },
        );
        backed
    }
}

/// Grid nodes over a frame at which the gaps to the neighbouring frames are measured (a sampling grid
/// over one frame's pixels, not a spatial index: the echo queries go through [`PointBuckets`]).
struct GapGrid {
    us: Vec<f64>,
    vs: Vec<f64>,
}

impl GapGrid {
    fn new(width: usize, height: usize) -> GapGrid {
        let axis = |n: usize| -> Vec<f64> {
            let last = n.saturating_sub(1);
            let mut nodes: Vec<f64> = (0..=last)
                .step_by(GAP_GRID_STEP_PX)
                .map(|x| x as f64)
                .collect();
            if !last.is_multiple_of(GAP_GRID_STEP_PX) {
                nodes.push(last as f64);
            }
            nodes
        };
        GapGrid {
            us: axis(width),
            vs: axis(height),
        }
    }

    fn node_of(&self, pixel: [f64; 2]) -> usize {
        let nearest = |nodes: &[f64], x: f64| {
            let i = (x / GAP_GRID_STEP_PX as f64).round();
            (if i.is_finite() {
                i.max(0.0) as usize
            } else {
                0
            })
            .min(nodes.len() - 1)
        };
        nearest(&self.vs, pixel[1]) * self.us.len() + nearest(&self.us, pixel[0])
    }

    /// Half the gap along the frame's normal (+, -) from each node to the nearest of `others` whose
    /// image covers the crossing point, at most `cap`; 0 on a side with no such frame within `2 cap`.
    fn half_gaps(
        &self,
        own: Option<FramePlane>,
        others: &[FramePlane],
        [width, height]: [usize; 2],
        cap: f64,
    ) -> Vec<[f64; 2]> {
        let mut gaps = vec![[0.0; 2]; self.us.len() * self.vs.len()];
        let Some(own) = own else {
            return gaps;
        };
        let (w, h) = (
            width.saturating_sub(1) as f64,
            height.saturating_sub(1) as f64,
        );
        for (node, gap) in gaps.iter_mut().enumerate() {
            let p = own.world_of([self.us[node % self.us.len()], self.vs[node / self.us.len()]]);
            // The nearest covering frame's distance on each side, if within 2 cap.
            let mut nearest: [Option<f64>; 2] = [None; 2];
            for other in others {
                let cosine = other.normal.dot(own.normal);
                if cosine.abs() < MIN_NORMAL_COSINE {
                    continue;
                }
                let t = other.normal.dot(other.origin - p) / cosine;
                let side = usize::from(t < 0.0);
                let closer = nearest[side].is_none_or(|n| t.abs() < n);
                if !(t.abs() >= SAME_PLANE_MM && t.abs() <= 2.0 * cap && closer) {
                    continue;
                }
                let [a, b] = other.pixel_of(p + own.normal * t);
                if a >= 0.0 && a <= w && b >= 0.0 && b <= h {
                    nearest[side] = Some(t.abs());
                }
            }
            *gap = nearest.map(|t| t.map_or(0.0, |t| 0.5 * t));
        }
        gaps
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::FramePose;
    use glam::DMat4;

    /// Frames of 11 x 11 px at 1 mm/px in the planes x = `xs[k]`, u along y and v along z (the beam).
    fn frames_at(xs: &[f64]) -> PoseResolution {
        PoseResolution {
            poses: xs
                .iter()
                .enumerate()
                .map(|(k, &x)| FramePose {
                    frame_index: k,
                    image_to_world: DMat4::from_cols(
                        glam::DVec4::new(0.0, 1.0, 0.0, 0.0),
                        glam::DVec4::new(0.0, 0.0, 1.0, 0.0),
                        glam::DVec4::new(1.0, 0.0, 0.0, 0.0),
                        glam::DVec4::new(x, 0.0, 0.0, 1.0),
                    ),
                })
                .collect(),
            skipped: Vec::new(),
            world_frame: "Reference".into(),
        }
    }

    /// An echo line across each frame at depth z = 5 mm.
    fn echo_lines(xs: &[f64]) -> (Vec<DVec3>, Vec<u32>) {
        let mut echoes = Vec::new();
        let mut frames = Vec::new();
        for (k, &x) in xs.iter().enumerate() {
            for y in 0..=10 {
                echoes.push(DVec3::new(x, y as f64, 5.0));
                frames.push(k as u32);
            }
        }
        (echoes, frames)
    }

    /// The echo lines of frames at `xs`, backing points within `distance_mm`, reaching at most `cap_mm`.
    fn reach_over(xs: &[f64], distance_mm: f64, cap_mm: f64) -> EchoReach {
        let (echoes, frames) = echo_lines(xs);
        EchoReach::new(
            &echoes,
            &frames,
            &frames_at(xs),
            [11, 11],
            distance_mm,
            cap_mm,
        )
    }

    #[test]
    fn an_echo_backs_half_the_gap_to_the_next_frame() {
        // Frames at x = 0, 6 and 8 mm: between 0 and 6 each echo reaches 3 mm; 6 reaches 1 mm towards 8.
        let reach = reach_over(&[0.0, 6.0, 8.0], 2.0, 5.0);
        // Mid-gap on the wall: 3 mm from either frame's echoes, backed through their slabs.
        assert!(reach.backs(DVec3::new(3.0, 5.0, 5.0)));
        // Mid-gap but 2.5 mm off the wall in the plane: not backed (the plain test would not either).
        assert!(!reach.backs(DVec3::new(3.0, 5.0, 7.5)));
        // Within the distance in the plane (1.5 mm) and of the slab: backed.
        assert!(reach.backs(DVec3::new(3.0, 5.0, 6.5)));
        // Beyond the last frame nothing was imaged: the plain distance, 2 mm.
        assert!(reach.backs(DVec3::new(9.9, 5.0, 5.0)));
        assert!(!reach.backs(DVec3::new(10.1, 5.0, 5.0)));
        // Behind the first frame too.
        assert!(!reach.backs(DVec3::new(-2.1, 5.0, 5.0)));
    }

    #[test]
    fn a_frame_that_does_not_cover_the_spot_bounds_no_gap() {
        // The second frame 6 mm on but 20 mm aside: nothing was imaged beside the first one's echoes.
        let (echoes, frames) = echo_lines(&[0.0]);
        let mut poses = frames_at(&[0.0, 6.0]);
        poses.poses[1].image_to_world.w_axis.y = 20.0;
        let reach = EchoReach::new(&echoes, &frames, &poses, [11, 11], 2.0, 5.0);
        assert!(reach.backs(DVec3::new(1.9, 5.0, 5.0)));
        assert!(!reach.backs(DVec3::new(3.0, 5.0, 5.0)));
        // Where it does cover (aside by 5 mm only: it images y 5-15), the echoes at y 5-10 reach 3 mm.
        poses.poses[1].image_to_world.w_axis.y = 5.0;
        let reach = EchoReach::new(&echoes, &frames, &poses, [11, 11], 2.0, 5.0);
        assert!(reach.backs(DVec3::new(3.0, 8.0, 5.0)));
    }

    #[test]
    fn a_gap_wider_than_twice_the_cap_is_a_break() {
        let xs = [0.0, 12.0];
        // Cap 6: each frame reaches 6 mm, the middle is backed.
        let wide = reach_over(&xs, 2.0, 6.0);
        assert!(wide.backs(DVec3::new(6.0, 5.0, 5.0)));
        // Cap 5.9: the gap is a break in the sweep, each frame an edge: the plain 2 mm.
        let broken = reach_over(&xs, 2.0, 5.9);
        assert!(broken.backs(DVec3::new(1.9, 5.0, 5.0)));
        assert!(!broken.backs(DVec3::new(2.1, 5.0, 5.0)));
        // No distance: nothing is backed.
        let off = reach_over(&xs, 0.0, 6.0);
        assert!(!off.backs(DVec3::new(0.0, 5.0, 5.0)));
    }

    #[test]
    fn a_repeated_frame_is_no_gap() {
        // A paused probe: two frames in one plane, then one 6 mm on. The pause must not shrink the reach.
        let reach = reach_over(&[0.0, 0.0, 6.0], 2.0, 5.0);
        assert!(reach.backs(DVec3::new(3.0, 5.0, 5.0)));
    }
}
