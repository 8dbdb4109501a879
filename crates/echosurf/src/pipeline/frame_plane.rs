//! A frame's image plane in the world, for the stages that ask where a point lies relative to the frames
//! (which frame's beam passes nearest, how far an echo reaches out of its plane).

use glam::{DMat4, DVec3};

/// A frame's plane: origin, the world vectors of one pixel along u and v (v: down the beam), the unit
/// normal, and the inverse Gram matrix of (u, v), which projects a world point orthogonally onto the
/// plane in pixel coordinates (whatever the image's third axis in the matrix).
#[derive(Debug, Clone, Copy)]
pub(super) struct FramePlane {
    pub(super) origin: DVec3,
    u: DVec3,
    pub(super) v: DVec3,
    pub(super) normal: DVec3,
    gram_inverse: [[f64; 2]; 2],
}

impl FramePlane {
    pub(super) fn new(image_to_world: DMat4) -> Option<FramePlane> {
        let origin = image_to_world.transform_point3(DVec3::ZERO);
        let u = image_to_world.transform_vector3(DVec3::X);
        let v = image_to_world.transform_vector3(DVec3::Y);
        let normal = u.cross(v).try_normalize()?;
        let (uu, uv, vv) = (u.dot(u), u.dot(v), v.dot(v));
        let det = uu * vv - uv * uv;
        if !(det.is_finite() && det > 0.0 && origin.is_finite()) {
            return None;
        }
        Some(FramePlane {
            origin,
            u,
            v,
            normal,
            gram_inverse: [[vv / det, -uv / det], [-uv / det, uu / det]],
        })
    }

    /// Pixel coordinates of the point's projection onto the plane.
    pub(super) fn pixel_of(&self, p: DVec3) -> [f64; 2] {
        let d = p - self.origin;
        let (a, b) = (self.u.dot(d), self.v.dot(d));
        let g = self.gram_inverse;
        [g[0][0] * a + g[0][1] * b, g[1][0] * a + g[1][1] * b]
    }

    pub(super) fn world_of(&self, pixel: [f64; 2]) -> DVec3 {
        self.origin + self.u * pixel[0] + self.v * pixel[1]
    }
}
