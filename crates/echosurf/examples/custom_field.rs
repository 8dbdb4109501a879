//! Surfaces a user-defined implicit field: a torus, given by value and gradient through the
//! [`ScalarField`] trait, extracted by regularised marching tetrahedra over the whole grid; prints the
//! mesh's topology and its area against the analytic one, then writes it if a path is given:
//! `cargo run --release -p echosurf --example custom_field [-- torus.ply]`

use std::path::Path;

use echosurf::io;
use echosurf::surface::{self, ScalarField, SurfaceDomain, SurfaceOptions};
use glam::DVec3;

/// A torus about the z axis: `(sqrt(x^2 + y^2) - R)^2 + z^2 - r^2`, negative inside.
#[derive(Debug)]
struct Torus {
    ring_radius_mm: f64,
    tube_radius_mm: f64,
}

impl Torus {
    fn value_and_gradient(&self, p: DVec3) -> (f64, DVec3) {
        let rho = (p.x * p.x + p.y * p.y).sqrt();
        let off_ring = rho - self.ring_radius_mm;
        let value = off_ring * off_ring + p.z * p.z - self.tube_radius_mm * self.tube_radius_mm;
        // d/dx (rho - R)^2 = 2 (rho - R) x / rho; on the axis (rho = 0) take the limit along x.
        let radial = if rho > 0.0 { off_ring / rho } else { 0.0 };
        let gradient = DVec3::new(2.0 * radial * p.x, 2.0 * radial * p.y, 2.0 * p.z);
        (value, gradient)
    }
}

/// The surfacer asks for values (and gradients) of whole batches of points at once. (For a closure
/// returning `(value, gradient)`, `surface::FnField(|p| ...)` implements this trait for you.)
impl ScalarField for Torus {
    fn values(&self, points: &[DVec3], out: &mut [f64]) {
        for (p, o) in points.iter().zip(out.iter_mut()) {
            *o = self.value_and_gradient(*p).0;
        }
    }

    fn values_and_gradients(&self, points: &[DVec3], values: &mut [f64], gradients: &mut [DVec3]) {
        for ((p, v), g) in points
            .iter()
            .zip(values.iter_mut())
            .zip(gradients.iter_mut())
        {
            (*v, *g) = self.value_and_gradient(*p);
        }
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let torus = Torus {
        ring_radius_mm: 12.0,
        tube_radius_mm: 4.0,
    };
    let half_width = torus.ring_radius_mm + torus.tube_radius_mm + 1.0;
    let half_height = torus.tube_radius_mm + 1.0;
    // No seeds and no trust points: scan the whole grid, clip nothing.
    let domain = SurfaceDomain {
        bounds_min_mm: DVec3::new(-half_width, -half_width, -half_height),
        bounds_max_mm: DVec3::new(half_width, half_width, half_height),
        ..SurfaceDomain::default()
    };
    let options = SurfaceOptions {
        resolution_mm: 0.5,
        ..SurfaceOptions::default()
    };
    let (meshes, stats) = surface::extract_surfaces_with_stats(&torus, &[0.0], &domain, &options)?;
    let mesh = &meshes[0];

    let topology = mesh.topology();
    let genus = (2 - topology.euler_characteristic) / 2;
    let area_true =
        4.0 * std::f64::consts::PI.powi(2) * torus.ring_radius_mm * torus.tube_radius_mm;
    println!(
        "{} triangles, {} piece(s), closed manifold: {}, genus {genus} (a torus: 1)",
        topology.triangles,
        topology.components,
        topology.is_closed_manifold()
    );
    println!(
        "area {:.1} mm^2 against {area_true:.1} mm^2 ({:+.2} %); {} field evaluations",
        mesh.area_mm2(),
        100.0 * (mesh.area_mm2() / area_true - 1.0),
        stats.value_evaluations + stats.gradient_evaluations
    );
    if let Some(out) = std::env::args_os().nth(1) {
        io::write_mesh(Path::new(&out), mesh)?;
        println!("written to {}", Path::new(&out).display());
    }
    Ok(())
}
