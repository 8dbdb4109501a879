//! Which truth a sweep imaged, to score a mesh on.
//!
//! Scoring (as [`run_case`](crate::run_case) does): accuracy = MESH -> TRUTH distances over the whole truth; completeness = share
//! of the *swept, beam-facing* truth within 1 mm of the mesh. A truth triangle counts as swept and
//! beam-facing when its centroid projects inside some frame's (clipped) image within
//! `max(1.5 mm, median frame spacing)` of the image plane, and its normal is within 60 degrees of that
//! frame's beam axis (either sign: the front and back walls of a specular boundary both echo, side walls
//! beyond 60 degrees do not, cos^12 falls to 2e-4 there). No route can be asked to find what was never
//! imaged. A second score counts only the truth within [`STRONG_ECHO_DEG`] (30 degrees) of the beam,
//! where the simulated specular echo is strong (from about 40 degrees on it is below the object's own
//! speckle, so the 60-degree share includes walls no echo shows).

use glam::{DMat4, DVec3};

use echosurf::io::ClipRect;
use echosurf::io::pose::FramePlane;
use echosurf::mesh::Mesh;
use echosurf::metrics::{CompareOptions, compare_meshes, triangle_map};
use echosurf::{Error, Result};

use crate::patches::{
    MIN_PATCH_AREA_MM2, PatchCoverage, PatchDetail, patch_count, patch_details, patches_of,
};

/// Swept, beam-facing truth triangles (see the module docs), `side` facing the beam within
/// `max_angle_deg`. The beam runs along the image's +v axis.
#[allow(clippy::too_many_arguments)]
pub fn swept_beam_facing_mask(
    truth: &Mesh,
    image_to_world: &[DMat4],
    width: usize,
    height: usize,
    clip: Option<ClipRect>,
    max_plane_distance_mm: f64,
    side: FacingSide,
    max_angle_deg: f64,
) -> Vec<bool> {
    let cosines = swept_beam_cosines(
        truth,
        image_to_world,
        width,
        height,
        clip,
        max_plane_distance_mm,
        side,
    );
    facing_within(&cosines, max_angle_deg)
}

/// Which side of a wall counts as facing the beam.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum FacingSide {
    /// Either side: the wall's normal along or against the beam (a specular boundary echoes from
    /// both sides where the beam reaches it).
    Either,
    /// The side facing the probe: the outward normal against the beam (needs outward normals, as on a
    /// closed truth mesh).
    Probe,
}

/// Per truth triangle, the largest |cos| between its normal and the beam of a frame that sweeps it (its
/// centroid projects into the frame's clipped image within `max_plane_distance_mm` of the plane);
/// `-inf` where no frame does. With [`FacingSide::Probe`], the largest `-cos` instead (the outward
/// normal against the beam), so a wall seen only from behind scores below zero. One pass over the
/// frames serves every angle ([`facing_within`]).
pub fn swept_beam_cosines(
    truth: &Mesh,
    image_to_world: &[DMat4],
    width: usize,
    height: usize,
    clip: Option<ClipRect>,
    max_plane_distance_mm: f64,
    side: FacingSide,
) -> Vec<f64> {
    let (u0, v0, u1, v1) =
        match clip.and_then(|c| echosurf::io::pose::clip_corners_px(width, height, &c)) {
            Some([a, b, c, d]) => (a, b, c, d),
            None => (0.0, 0.0, width as f64 - 1.0, height as f64 - 1.0),
        };
    // Per frame: its plane and the unit beam direction.
    let frames: Vec<(FramePlane, DVec3)> = image_to_world
        .iter()
        .filter_map(|&m| {
            let plane = FramePlane::new(m)?;
            Some((plane, plane.v.try_normalize()?))
        })
        .collect();
    triangle_map(truth, f64::NEG_INFINITY, |centroid, triangle_normal| {
        if !triangle_normal.is_finite() {
            return f64::NEG_INFINITY;
        }
        frames
            .iter()
            .filter(|(plane, _)| {
                let [u, v] = plane.pixel_of(centroid);
                if !(u >= u0 && u <= u1 && v >= v0 && v <= v1) {
                    return false;
                }
                (centroid - plane.world_of([u, v])).dot(plane.normal).abs() <= max_plane_distance_mm
            })
            .map(|(_, beam)| {
                let cos = triangle_normal.dot(*beam);
                match side {
                    FacingSide::Either => cos.abs(),
                    FacingSide::Probe => -cos,
                }
            })
            .fold(f64::NEG_INFINITY, f64::max)
    })
}

/// The triangles of [`swept_beam_cosines`] facing a sweeping frame's beam within `max_angle_deg`.
pub fn facing_within(cosines: &[f64], max_angle_deg: f64) -> Vec<bool> {
    let cos_limit = max_angle_deg.to_radians().cos();
    cosines.iter().map(|&c| c >= cos_limit).collect()
}

/// Median distance between the origins of consecutive frames.
pub fn median_spacing(frames: &[DMat4]) -> Option<f64> {
    let mut d: Vec<f64> = frames
        .windows(2)
        .map(|w| w[0].w_axis.truncate().distance(w[1].w_axis.truncate()))
        .filter(|d| d.is_finite() && *d > 1e-6)
        .collect();
    d.sort_by(f64::total_cmp);
    d.get(d.len() / 2).copied()
}

/// Walls within this angle of the beam return a strong specular echo in the simulator (cos^12: at least
/// 18 % of normal incidence); the benchmark also scores completeness on them alone.
pub const STRONG_ECHO_DEG: f64 = 30.0;

/// The benchmark also scores the truth whose outward side faces the probe within this angle of a
/// sweeping beam ([`FacingSide::Probe`]): the walls every sweep shows with a strong echo from the
/// side the sound arrives at (the far side of a solid object lies in its shadow). 20 degrees is where
/// the simulator's specular echo (cos^12) is still half of normal incidence, the usual -6 dB edge
/// (cos^12 of 20 degrees = 0.47, -6.5 dB; of 25 degrees 0.31, of 30 degrees 0.18): the pipeline
/// issue's "beam-facing truth", which names no angle, is read here.
pub const PROBE_FACING_DEG: f64 = 20.0;

/// The swept truth that faces the beam within an angle, and how a mesh covers it: completeness within
/// 1 mm and the mesh's pieces per echoing patch ([`PatchCoverage`]). For any sweep whose truth lies in
/// the same world frame as its poses (`compare --sequence`), from [`SweptFacingTruth::score`].
#[derive(Debug, Clone, serde::Serialize)]
pub struct SweptFacingScore {
    pub max_angle_deg: f64,
    pub side: FacingSide,
    /// A truth triangle counts as swept within this distance of a frame's plane: the median frame
    /// spacing, at least 1.5 mm (as the benchmark).
    pub plane_distance_mm: f64,
    pub truth_area_mm2: f64,
    pub completeness_1mm: f64,
    /// Connected patches (at least [`MIN_PATCH_AREA_MM2`]) of that truth.
    pub truth_patches: usize,
    pub patch_coverage: PatchCoverage,
    /// Each patch and the pieces over it.
    pub patches: Vec<PatchDetail>,
}

/// The part of a truth that the frames sweep and whose chosen side faces their beam within an angle,
/// with its patches: found once per sweep and truth, then [`SweptFacingTruth::score`] for each mesh.
#[derive(Debug, Clone)]
pub struct SweptFacingTruth {
    max_angle_deg: f64,
    side: FacingSide,
    plane_distance_mm: f64,
    mask: Vec<bool>,
    patches: Mesh,
}

impl SweptFacingTruth {
    /// The triangles of `truth` that the frames `image_to_world` (of `width` x `height` px, `clip`ped)
    /// sweep and whose `side` faces their beam within `max_angle_deg`; an error if there are none.
    pub fn new(
        truth: &Mesh,
        image_to_world: &[DMat4],
        width: usize,
        height: usize,
        clip: Option<ClipRect>,
        side: FacingSide,
        max_angle_deg: f64,
    ) -> Result<SweptFacingTruth> {
        if !(max_angle_deg > 0.0 && max_angle_deg <= 90.0) {
            return Err(Error::InvalidInput(format!(
                "facing angle must be in (0, 90] degrees, got {max_angle_deg}"
            )));
        }
        let plane_distance_mm = median_spacing(image_to_world).unwrap_or(1.5).max(1.5);
        let mask = swept_beam_facing_mask(
            truth,
            image_to_world,
            width,
            height,
            clip,
            plane_distance_mm,
            side,
            max_angle_deg,
        );
        if !mask.iter().any(|&m| m) {
            return Err(Error::InvalidInput(format!(
                "no truth triangle is swept by a frame and faces its beam within {max_angle_deg} \
                 degrees (do the truth and the sequence share a world frame?)"
            )));
        }
        let patches = patches_of(truth, &mask, MIN_PATCH_AREA_MM2);
        Ok(SweptFacingTruth {
            max_angle_deg,
            side,
            plane_distance_mm,
            mask,
            patches,
        })
    }

    /// This part of `truth` (the mesh the selection was made of): its selected triangles.
    pub fn selected(&self, truth: &Mesh) -> Mesh {
        let mut part = truth.clone();
        part.retain_triangles(&self.mask);
        part
    }

    /// How `mesh` covers this part of `truth` (the mesh the selection was made of).
    pub fn score(
        &self,
        mesh: &Mesh,
        truth: &Mesh,
        compare: &CompareOptions,
    ) -> Result<SweptFacingScore> {
        let comparison = compare_meshes(
            mesh,
            truth,
            &CompareOptions {
                truth_mask: Some(self.mask.clone()),
                ..compare.clone()
            },
        )?;
        let (patch_coverage, patches) = patch_details(mesh, &self.patches, MIN_PATCH_AREA_MM2);
        Ok(SweptFacingScore {
            max_angle_deg: self.max_angle_deg,
            side: self.side,
            plane_distance_mm: self.plane_distance_mm,
            truth_area_mm2: comparison.truth_compared_area_mm2,
            completeness_1mm: comparison.completeness_1mm,
            truth_patches: patch_count(&self.patches),
            patch_coverage,
            patches,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use echosurf::metrics::shapes::icosphere;

    /// A sphere of radius 10 mm at the origin and one 81 x 81 px frame through its centre: image x ->
    /// world x, image y (depth) -> world -z (the beam), 0.5 mm pixels, image top at z = 20.
    fn sphere_and_frame() -> (Mesh, DMat4) {
        let frame = DMat4::from_cols(
            glam::DVec4::new(0.5, 0.0, 0.0, 0.0),
            glam::DVec4::new(0.0, 0.0, -0.5, 0.0),
            glam::DVec4::new(0.0, 1.0, 0.0, 0.0),
            glam::DVec4::new(-20.0, 0.0, 20.0, 1.0),
        );
        (icosphere(DVec3::ZERO, 10.0, 4), frame)
    }

    /// One frame through the centre of a sphere, beam along -z: only the top and bottom caps within
    /// 60 degrees of the beam axis and inside the image count.
    #[test]
    fn mask_keeps_the_swept_caps_facing_the_beam() {
        let (sphere, frame) = sphere_and_frame();
        let mask = swept_beam_facing_mask(
            &sphere,
            &[frame],
            81,
            81,
            None,
            1.5,
            FacingSide::Either,
            60.0,
        );
        let kept: Vec<usize> = (0..mask.len()).filter(|&i| mask[i]).collect();
        assert!(!kept.is_empty());
        for &i in &kept {
            let c = sphere.triangles[i]
                .map(|v| sphere.vertices[v as usize])
                .iter()
                .sum::<DVec3>()
                / 3.0;
            assert!(c.y.abs() <= 1.5 + 1e-9, "off the plane: {c}");
            assert!(c.z.abs() / c.length() >= 0.45, "not facing the beam: {c}");
        }
        // The equator at x = +-10 (normal across the beam) is not kept.
        let side_kept = kept.iter().any(|&i| {
            let c = sphere.vertices[sphere.triangles[i][0] as usize];
            c.x.abs() > 9.5
        });
        assert!(!side_kept);
        // The frame sweeps a strip over the top cap and one under the bottom cap: two patches.
        assert_eq!(patch_count(&patches_of(&sphere, &mask, 0.5)), 2);
        assert_eq!(patch_count(&patches_of(&sphere, &mask, 1e6)), 0);
    }

    /// The same frame, scored per side: the probe (above, beam along -z) faces only the top cap's
    /// outward normals. A mesh of the sphere's upper half covers the top strip whole and misses the
    /// bottom one, so it is complete on the probe side and about half complete on either side.
    #[test]
    fn swept_facing_truth_counts_the_side_facing_the_probe() {
        let (sphere, frame) = sphere_and_frame();
        let mut upper = sphere.clone();
        let keep: Vec<bool> = upper
            .triangles
            .iter()
            .map(|t| t.iter().all(|&v| upper.vertices[v as usize].z > -0.5))
            .collect();
        upper.retain_triangles(&keep);
        let score_on = |mesh: &Mesh, frame: DMat4, side, angle_deg| {
            SweptFacingTruth::new(&sphere, &[frame], 81, 81, None, side, angle_deg)?.score(
                mesh,
                &sphere,
                &CompareOptions::default(),
            )
        };
        let score = |mesh: &Mesh, side| score_on(mesh, frame, side, 60.0).unwrap();
        let probe = score(&upper, FacingSide::Probe);
        let either = score(&upper, FacingSide::Either);
        assert_eq!(probe.truth_patches, 1);
        assert_eq!(either.truth_patches, 2);
        assert!((either.truth_area_mm2 / probe.truth_area_mm2 - 2.0).abs() < 0.1);
        assert!(probe.completeness_1mm > 0.999, "{probe:?}");
        assert!((either.completeness_1mm - 0.5).abs() < 0.05, "{either:?}");
        let whole_one = PatchCoverage {
            whole: 1,
            split: 0,
            missed: 0,
        };
        assert_eq!(probe.patch_coverage, whole_one);
        assert_eq!(
            either.patch_coverage,
            PatchCoverage {
                missed: 1,
                ..whole_one
            }
        );
        // The whole sphere covers both strips; a frame 100 mm away sweeps nothing, and a bad angle is
        // refused.
        assert_eq!(score(&sphere, FacingSide::Either).patch_coverage.whole, 2);
        let far = DMat4::from_translation(DVec3::new(0.0, 100.0, 0.0)) * frame;
        assert!(score_on(&sphere, far, FacingSide::Either, 60.0).is_err());
        assert!(score_on(&sphere, frame, FacingSide::Either, 0.0).is_err());
    }
}
