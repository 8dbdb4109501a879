//! Phantoms as signed distance functions in mm (negative inside the object's material), with analytic
//! gradients. Composite shapes are small trees of primitives joined by a polynomial smooth minimum whose
//! gradient is the blend of the children's gradients (d smin / d a = h), so no finite differences are used.

use std::path::{Path, PathBuf};

use glam::{DMat3, DVec3};

use super::mesh_sdf::MeshSdf;
use echosurf::mesh::Mesh;
use echosurf::{Error, Result};

/// Which phantom to simulate.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PhantomKind {
    /// Solid sphere, radius 15 mm.
    Sphere,
    /// Solid ellipsoid, semi-axes 25 x 15 x 12 mm.
    Ellipsoid,
    /// Solid torus in the horizontal plane, radii 20 mm (ring) and 7 mm (tube).
    Torus,
    /// Hollow rubber duck (water-filled) with a ~2 mm wall: an outer and an inner surface.
    Duck,
    /// Solid hand lying palm down: palm and five finger capsules.
    Hand,
    /// A vertebra-like bone lying along x: a rounded body with a spinous ridge and two laminae on top.
    /// Meant for the `bone` physics (strong echo, full shadow): its truth is the probe side only.
    Bone,
    /// Any closed triangle mesh (STL/PLY/OBJ, mm), solid.
    Mesh(PathBuf),
}

impl PhantomKind {
    /// Parses `sphere|ellipsoid|torus|duck|hand|bone`, anything else is a mesh path.
    pub fn parse(text: &str) -> PhantomKind {
        match text.to_ascii_lowercase().as_str() {
            "sphere" => PhantomKind::Sphere,
            "ellipsoid" => PhantomKind::Ellipsoid,
            "torus" => PhantomKind::Torus,
            "duck" => PhantomKind::Duck,
            "hand" => PhantomKind::Hand,
            "bone" => PhantomKind::Bone,
            _ => PhantomKind::Mesh(PathBuf::from(text)),
        }
    }

    /// Short name for file contents and messages.
    pub fn name(&self) -> String {
        match self {
            PhantomKind::Sphere => "sphere".into(),
            PhantomKind::Ellipsoid => "ellipsoid".into(),
            PhantomKind::Torus => "torus".into(),
            PhantomKind::Duck => "duck".into(),
            PhantomKind::Hand => "hand".into(),
            PhantomKind::Bone => "bone".into(),
            PhantomKind::Mesh(p) => p.display().to_string(),
        }
    }
}

/// Signed distance and gradient of one closed surface (negative inside).
pub type SurfaceFn = dyn Fn(DVec3) -> (f64, DVec3) + Send + Sync;

/// A phantom's geometry. `distance` is negative inside the material that scatters and attenuates (the duck's
/// rubber wall, the hand's tissue); its zero level is every boundary that echoes, and |distance| is the
/// distance to the nearest true surface (exact for sphere, torus, capsule and mesh; a close first-order
/// estimate for ellipsoids and blends, exact on the zero level).
pub trait Phantom: Send + Sync + std::fmt::Debug {
    fn distance_and_gradient(&self, p: DVec3) -> (f64, DVec3);

    fn distance(&self, p: DVec3) -> f64 {
        self.distance_and_gradient(p).0
    }

    fn gradient(&self, p: DVec3) -> DVec3 {
        self.distance_and_gradient(p).1
    }

    /// Axis-aligned box (mm) containing the material.
    fn bounds(&self) -> (DVec3, DVec3);

    /// The closed true surfaces: (name, signed distance of the region the surface encloses). Their union
    /// is the zero level of `distance`.
    fn surfaces(&self) -> Vec<(String, &SurfaceFn)>;

    /// The true surfaces as meshes when the phantom has them exactly (mesh phantoms); `None` means
    /// "extract the zero level of each `surfaces()` field".
    fn exact_meshes(&self) -> Option<Vec<(String, Mesh)>> {
        None
    }

    /// Whether only the probe side (outward normal with a positive z, toward the probe above) can be
    /// imaged, as on a bone whose shadow hides the rest: its truth and sweeps are that side only.
    fn probe_side_only(&self) -> bool {
        false
    }
}

/// A node of an analytic SDF tree.
#[derive(Debug, Clone)]
pub enum Sdf {
    Sphere {
        center: DVec3,
        radius: f64,
    },
    /// Ellipsoid with semi-axes `radii` along the columns of `rotation` (local -> world).
    Ellipsoid {
        center: DVec3,
        radii: DVec3,
        rotation: DMat3,
    },
    /// Torus around `axis` through `center`.
    Torus {
        center: DVec3,
        axis: DVec3,
        major: f64,
        minor: f64,
    },
    Capsule {
        a: DVec3,
        b: DVec3,
        radius: f64,
    },
    /// Polynomial smooth union with blend radius `k` mm.
    SmoothUnion(Box<Sdf>, Box<Sdf>, f64),
}

impl Sdf {
    pub fn eval(&self, p: DVec3) -> (f64, DVec3) {
        match self {
            Sdf::Sphere { center, radius } => {
                let d = p - *center;
                let len = d.length();
                let g = if len > 1e-12 { d / len } else { DVec3::Z };
                (len - radius, g)
            }
            Sdf::Ellipsoid {
                center,
                radii,
                rotation,
            } => {
                let q = rotation.transpose() * (p - *center);
                let (d, g_local) = ellipsoid_local(q, *radii);
                (d, *rotation * g_local)
            }
            Sdf::Torus {
                center,
                axis,
                major,
                minor,
            } => {
                let d = p - *center;
                let h = d.dot(*axis);
                let radial = d - *axis * h;
                let r = radial.length();
                let ring_dir = if r > 1e-12 {
                    radial / r
                } else {
                    axis.any_orthonormal_vector()
                };
                let to_tube = d - ring_dir * *major;
                let len = to_tube.length();
                let g = if len > 1e-12 { to_tube / len } else { *axis };
                (len - minor, g)
            }
            Sdf::Capsule { a, b, radius } => {
                let ab = *b - *a;
                let t = ((p - *a).dot(ab) / ab.length_squared()).clamp(0.0, 1.0);
                let d = p - (*a + ab * t);
                let len = d.length();
                let g = if len > 1e-12 { d / len } else { DVec3::Z };
                (len - radius, g)
            }
            Sdf::SmoothUnion(left, right, k) => {
                let (a, ga) = left.eval(p);
                // Children far from the blend zone cannot change the result: skip the other branch's
                // gradient work only when cheap bounds allow it is not worth the complexity here.
                let (b, gb) = right.eval(p);
                smooth_min(a, ga, b, gb, *k)
            }
        }
    }

    /// A conservative axis-aligned box of the negative region.
    pub fn bounds(&self) -> (DVec3, DVec3) {
        match self {
            Sdf::Sphere { center, radius } => (*center - *radius, *center + *radius),
            Sdf::Ellipsoid {
                center,
                radii,
                rotation,
            } => {
                // Half-extent along world axis i: |R_i . r| over the rotated semi-axes.
                let m = *rotation;
                let ext = DVec3::new(
                    (DVec3::new(m.x_axis.x, m.y_axis.x, m.z_axis.x) * *radii).length(),
                    (DVec3::new(m.x_axis.y, m.y_axis.y, m.z_axis.y) * *radii).length(),
                    (DVec3::new(m.x_axis.z, m.y_axis.z, m.z_axis.z) * *radii).length(),
                );
                (*center - ext, *center + ext)
            }
            Sdf::Torus {
                center,
                major,
                minor,
                ..
            } => {
                let r = major + minor;
                (*center - r, *center + r)
            }
            Sdf::Capsule { a, b, radius } => (a.min(*b) - *radius, a.max(*b) + *radius),
            Sdf::SmoothUnion(l, r, k) => {
                let (l0, l1) = l.bounds();
                let (r0, r1) = r.bounds();
                // The blend can bulge by at most k/4 beyond either child.
                (l0.min(r0) - k * 0.25, l1.max(r1) + k * 0.25)
            }
        }
    }

    fn union(self, other: Sdf, k: f64) -> Sdf {
        Sdf::SmoothUnion(Box::new(self), Box::new(other), k)
    }
}

/// Polynomial smooth minimum (Quilez): exact min where |a - b| >= k, a rounded fillet of radius ~k
/// between. Its derivative with respect to `a` is h, with respect to `b` is 1 - h.
pub fn smooth_min(a: f64, ga: DVec3, b: f64, gb: DVec3, k: f64) -> (f64, DVec3) {
    if k <= 0.0 {
        return if a < b { (a, ga) } else { (b, gb) };
    }
    let h = (0.5 + 0.5 * (b - a) / k).clamp(0.0, 1.0);
    let d = b + h * (a - b) - k * h * (1.0 - h);
    (d, ga * h + gb * (1.0 - h))
}

/// Ellipsoid distance estimate k0 (k0 - 1) / k1 with k0 = |q / r|, k1 = |q / r^2| (Quilez): exact on the
/// surface and along the axes, within a few percent near the surface; gradient by the quotient rule.
fn ellipsoid_local(q: DVec3, r: DVec3) -> (f64, DVec3) {
    let qr = q / r;
    let qr2 = qr / r;
    let k0 = qr.length();
    let k1 = qr2.length();
    if k1 < 1e-12 {
        let rmin = r.min_element();
        return (-rmin, DVec3::Z);
    }
    let d = k0 * (k0 - 1.0) / k1;
    let grad_k0 = qr2 / k0;
    let grad_k1 = (qr2 / (r * r)) / k1;
    let g = ((2.0 * k0 - 1.0) * grad_k0 * k1 - k0 * (k0 - 1.0) * grad_k1) / (k1 * k1);
    (d, g)
}

fn rotation_y(deg: f64) -> DMat3 {
    DMat3::from_rotation_y(deg.to_radians())
}

/// A solid analytic phantom: one closed surface.
pub struct SolidPhantom {
    name: String,
    sdf: Sdf,
    eval: Box<SurfaceFn>,
}

impl SolidPhantom {
    pub fn new(name: &str, sdf: Sdf) -> Self {
        let tree = sdf.clone();
        SolidPhantom {
            name: name.into(),
            sdf,
            eval: Box::new(move |p| tree.eval(p)),
        }
    }
}

impl std::fmt::Debug for SolidPhantom {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SolidPhantom")
            .field("name", &self.name)
            .field("sdf", &self.sdf)
            .finish()
    }
}

impl std::fmt::Debug for ShellPhantom {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ShellPhantom")
            .field("bounds", &self.bounds)
            .field("wall_mm", &self.wall_mm)
            .finish()
    }
}

impl Phantom for SolidPhantom {
    fn distance_and_gradient(&self, p: DVec3) -> (f64, DVec3) {
        self.sdf.eval(p)
    }

    fn bounds(&self) -> (DVec3, DVec3) {
        self.sdf.bounds()
    }

    fn surfaces(&self) -> Vec<(String, &SurfaceFn)> {
        vec![(self.name.clone(), &*self.eval as &SurfaceFn)]
    }
}

/// A solid seen from above only (a bone): the solid's geometry, the probe side's truth.
#[derive(Debug)]
pub struct ProbeSidePhantom(pub SolidPhantom);

impl Phantom for ProbeSidePhantom {
    fn distance_and_gradient(&self, p: DVec3) -> (f64, DVec3) {
        self.0.distance_and_gradient(p)
    }

    fn bounds(&self) -> (DVec3, DVec3) {
        self.0.bounds()
    }

    fn surfaces(&self) -> Vec<(String, &SurfaceFn)> {
        self.0.surfaces()
    }

    fn probe_side_only(&self) -> bool {
        true
    }
}

/// A hollow object: material between the outer surface and its inward offset by `wall_mm`.
pub struct ShellPhantom {
    outer: Box<SurfaceFn>,
    inner: Box<SurfaceFn>,
    bounds: (DVec3, DVec3),
    pub wall_mm: f64,
}

impl ShellPhantom {
    pub fn new(outer: Sdf, wall_mm: f64) -> Self {
        let bounds = outer.bounds();
        let (o, i) = (outer.clone(), outer);
        ShellPhantom {
            outer: Box::new(move |p| o.eval(p)),
            // The cavity is where the outer distance is below -wall: its SDF is outer + wall.
            inner: Box::new(move |p| {
                let (d, g) = i.eval(p);
                (d + wall_mm, g)
            }),
            bounds,
            wall_mm,
        }
    }
}

impl Phantom for ShellPhantom {
    fn distance_and_gradient(&self, p: DVec3) -> (f64, DVec3) {
        let (d, g) = (self.outer)(p);
        // max(outer, -inner): negative only inside the wall.
        let inner = -(d + self.wall_mm);
        if d >= inner { (d, g) } else { (inner, -g) }
    }

    fn bounds(&self) -> (DVec3, DVec3) {
        self.bounds
    }

    fn surfaces(&self) -> Vec<(String, &SurfaceFn)> {
        vec![
            ("outer".into(), &*self.outer as &SurfaceFn),
            ("inner".into(), &*self.inner as &SurfaceFn),
        ]
    }
}

/// The duck's outer surface (mm, z up, floating with the body centred at the origin, head toward +x):
/// body, head, beak, tail and two wings blended smoothly. About 64 x 40 x 44 mm.
pub fn duck_outer() -> Sdf {
    let body = Sdf::Ellipsoid {
        center: DVec3::ZERO,
        radii: DVec3::new(26.0, 18.0, 14.0),
        rotation: DMat3::IDENTITY,
    };
    let head = Sdf::Sphere {
        center: DVec3::new(17.0, 0.0, 20.0),
        radius: 11.0,
    };
    let beak = Sdf::Ellipsoid {
        center: DVec3::new(29.0, 0.0, 17.5),
        radii: DVec3::new(8.0, 6.5, 3.8),
        rotation: rotation_y(8.0),
    };
    let tail = Sdf::Ellipsoid {
        center: DVec3::new(-24.0, 0.0, 7.0),
        radii: DVec3::new(9.0, 7.0, 4.5),
        rotation: rotation_y(-35.0),
    };
    let wing = |side: f64| Sdf::Ellipsoid {
        center: DVec3::new(-3.0, side * 15.5, 4.0),
        radii: DVec3::new(14.0, 4.5, 7.5),
        rotation: DMat3::from_rotation_x(side * 12f64.to_radians()) * rotation_y(-10.0),
    };
    body.union(head, 7.0)
        .union(beak, 3.0)
        .union(tail, 5.0)
        .union(wing(1.0), 4.0)
        .union(wing(-1.0), 4.0)
}

/// Wall thickness of the duck (mm).
pub const DUCK_WALL_MM: f64 = 2.0;

/// A hand lying palm down (mm, z up, fingers toward +x): a flattened palm and five finger capsules.
pub fn hand() -> Sdf {
    let palm = Sdf::Ellipsoid {
        center: DVec3::ZERO,
        radii: DVec3::new(42.0, 38.0, 13.0),
        rotation: DMat3::IDENTITY,
    };
    // (base y, length, radius, splay in degrees) for index, middle, ring, little finger.
    let fingers: [(f64, f64, f64, f64); 4] = [
        (24.0, 72.0, 8.5, 6.0),
        (8.0, 80.0, 8.8, 1.0),
        (-8.0, 74.0, 8.4, -4.0),
        (-24.0, 60.0, 7.6, -10.0),
    ];
    let mut sdf = palm;
    for (y, length, radius, splay) in fingers {
        let a = DVec3::new(34.0, y, 1.0);
        let dir = DVec3::new(
            f64::cos(splay.to_radians()),
            f64::sin(splay.to_radians()),
            -0.05,
        );
        sdf = sdf.union(
            Sdf::Capsule {
                a,
                b: a + dir.normalize() * length,
                radius,
            },
            6.0,
        );
    }
    let thumb = Sdf::Capsule {
        a: DVec3::new(5.0, 34.0, -2.0),
        b: DVec3::new(38.0, 62.0, -1.0),
        radius: 10.0,
    };
    sdf.union(thumb, 8.0)
}

/// A vertebra-like bone (mm, z up, along x): a rounded body 56 mm long, radius 8 mm, with a spinous
/// ridge rising 7 mm above it and two laminae to the sides, blended smoothly. About 56 x 34 x 22 mm.
pub fn bone() -> Sdf {
    let body = Sdf::Capsule {
        a: DVec3::new(-20.0, 0.0, -3.0),
        b: DVec3::new(20.0, 0.0, -3.0),
        radius: 8.0,
    };
    let ridge = Sdf::Ellipsoid {
        center: DVec3::new(0.0, 0.0, 5.0),
        radii: DVec3::new(22.0, 3.5, 7.0),
        rotation: DMat3::IDENTITY,
    };
    let lamina = |side: f64| Sdf::Ellipsoid {
        center: DVec3::new(0.0, side * 11.0, -1.0),
        radii: DVec3::new(16.0, 6.0, 3.5),
        rotation: DMat3::from_rotation_x(side * -15f64.to_radians()),
    };
    body.union(ridge, 4.0)
        .union(lamina(1.0), 3.0)
        .union(lamina(-1.0), 3.0)
}

/// Builds the phantom; mesh phantoms are read from their file (which must hold a closed manifold).
pub fn build_phantom(kind: &PhantomKind) -> Result<Box<dyn Phantom>> {
    Ok(match kind {
        PhantomKind::Sphere => Box::new(SolidPhantom::new(
            "sphere",
            Sdf::Sphere {
                center: DVec3::ZERO,
                radius: 15.0,
            },
        )),
        PhantomKind::Ellipsoid => Box::new(SolidPhantom::new(
            "ellipsoid",
            Sdf::Ellipsoid {
                center: DVec3::ZERO,
                radii: DVec3::new(25.0, 15.0, 12.0),
                rotation: DMat3::IDENTITY,
            },
        )),
        PhantomKind::Torus => Box::new(SolidPhantom::new(
            "torus",
            Sdf::Torus {
                center: DVec3::ZERO,
                axis: DVec3::Z,
                major: 20.0,
                minor: 7.0,
            },
        )),
        PhantomKind::Duck => Box::new(ShellPhantom::new(duck_outer(), DUCK_WALL_MM)),
        PhantomKind::Hand => Box::new(SolidPhantom::new("hand", hand())),
        PhantomKind::Bone => Box::new(ProbeSidePhantom(SolidPhantom::new("bone", bone()))),
        PhantomKind::Mesh(path) => Box::new(mesh_phantom(path)?),
    })
}

/// Signed distance (mm) of a phantom as a plain closure: |value| is the distance to the nearest true surface.
pub fn phantom_sdf(kind: &PhantomKind) -> Result<impl Fn(DVec3) -> f64 + Send + Sync> {
    let phantom = build_phantom(kind)?;
    Ok(move |p: DVec3| phantom.distance(p))
}

impl Phantom for MeshSdf {
    fn distance_and_gradient(&self, p: DVec3) -> (f64, DVec3) {
        self.signed_distance_and_gradient(p)
    }

    fn bounds(&self) -> (DVec3, DVec3) {
        self.bounding_box()
    }

    fn surfaces(&self) -> Vec<(String, &SurfaceFn)> {
        Vec::new()
    }

    fn exact_meshes(&self) -> Option<Vec<(String, Mesh)>> {
        Some(vec![("mesh".into(), self.exact_mesh())])
    }
}

fn mesh_phantom(path: &Path) -> Result<MeshSdf> {
    let mesh = echosurf::io::read_mesh(path)?;
    MeshSdf::new(mesh)
        .map_err(|message| Error::format(path, echosurf::FormatProblem::BadValue, message))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Central differences of the distance agree with the analytic gradient (to 1e-5: the step is 1e-5 mm
    /// and the fields are smooth away from kinks).
    fn check_gradient(phantom: &dyn Phantom, points: &[DVec3]) {
        let h = 1e-5;
        for &p in points {
            let g = phantom.gradient(p);
            let fd = DVec3::new(
                phantom.distance(p + DVec3::X * h) - phantom.distance(p - DVec3::X * h),
                phantom.distance(p + DVec3::Y * h) - phantom.distance(p - DVec3::Y * h),
                phantom.distance(p + DVec3::Z * h) - phantom.distance(p - DVec3::Z * h),
            ) / (2.0 * h);
            assert!((g - fd).length() < 1e-5, "at {p}: analytic {g} vs fd {fd}");
        }
    }

    fn test_points() -> Vec<DVec3> {
        let mut pts = Vec::new();
        for i in 0..7 {
            for j in 0..7 {
                pts.push(DVec3::new(
                    -33.0 + 11.3 * i as f64,
                    -29.0 + 9.1 * j as f64,
                    -7.3 + 4.7 * ((i + j) % 5) as f64,
                ));
            }
        }
        pts
    }

    #[test]
    fn analytic_gradients_match_finite_differences() {
        for kind in [
            PhantomKind::Sphere,
            PhantomKind::Ellipsoid,
            PhantomKind::Torus,
            PhantomKind::Duck,
            PhantomKind::Hand,
            PhantomKind::Bone,
        ] {
            let phantom = build_phantom(&kind).unwrap();
            check_gradient(phantom.as_ref(), &test_points());
        }
    }

    #[test]
    fn primitives_are_exact_distances() {
        let sphere = build_phantom(&PhantomKind::Sphere).unwrap();
        assert!((sphere.distance(DVec3::new(0.0, 20.0, 0.0)) - 5.0).abs() < 1e-12);
        let torus = build_phantom(&PhantomKind::Torus).unwrap();
        assert!((torus.distance(DVec3::new(20.0, 0.0, 10.0)) - 3.0).abs() < 1e-12);
        assert!((torus.distance(DVec3::ZERO) - 13.0).abs() < 1e-12);
        // Ellipsoid estimate is exact along the axes.
        let e = build_phantom(&PhantomKind::Ellipsoid).unwrap();
        assert!((e.distance(DVec3::new(30.0, 0.0, 0.0)) - 5.0).abs() < 1e-9);
        assert!((e.distance(DVec3::new(0.0, 0.0, 10.0)) + 2.0).abs() < 1e-9);
    }

    #[test]
    fn duck_wall_is_two_mm_thick_and_hollow() {
        let duck = build_phantom(&PhantomKind::Duck).unwrap();
        // Straight down through the top of the body at x = -8 (no head or wing there).
        let mut inside = Vec::new();
        let mut z = 40.0;
        let mut prev = duck.distance(DVec3::new(-8.0, 0.0, z));
        while z > -30.0 {
            z -= 0.01;
            let d = duck.distance(DVec3::new(-8.0, 0.0, z));
            if (d < 0.0) != (prev < 0.0) {
                inside.push(z);
            }
            prev = d;
        }
        // Four crossings: top outer, top inner, bottom inner, bottom outer.
        assert_eq!(inside.len(), 4, "{inside:?}");
        let top_wall = inside[0] - inside[1];
        let bottom_wall = inside[2] - inside[3];
        // The ellipsoid estimate near the top pole is almost exact: wall within 0.1 mm of 2 mm.
        assert!((top_wall - DUCK_WALL_MM).abs() < 0.1, "{top_wall}");
        assert!((bottom_wall - DUCK_WALL_MM).abs() < 0.1, "{bottom_wall}");
        assert_eq!(duck.surfaces().len(), 2);
    }

    #[test]
    fn bounds_contain_the_material() {
        for kind in [
            PhantomKind::Duck,
            PhantomKind::Hand,
            PhantomKind::Torus,
            PhantomKind::Bone,
        ] {
            let phantom = build_phantom(&kind).unwrap();
            let (lo, hi) = phantom.bounds();
            let size = hi - lo;
            for i in 0..30 {
                for j in 0..30 {
                    for k in 0..30 {
                        let p = lo - size * 0.1
                            + size * 1.2 * DVec3::new(i as f64, j as f64, k as f64) / 29.0;
                        let outside = p.cmplt(lo).any() || p.cmpgt(hi).any();
                        if outside {
                            assert!(phantom.distance(p) > 0.0, "{kind:?} material at {p}");
                        }
                    }
                }
            }
        }
    }
}
