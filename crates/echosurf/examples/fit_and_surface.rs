//! Fits the biharmonic RBF to samples of an analytic field around a sphere, surfaces the fit at the
//! sphere's level and prints how far the surface lies from the true sphere (an independent reference):
//! `cargo run --release -p echosurf --example fit_and_surface [-- SAMPLES]` (default 3000).

use echosurf::progress::NoProgress;
use echosurf::rbf::{self, FitOptions};
use echosurf::surface::{self, SurfaceDomain, SurfaceOptions};
use glam::DVec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const RADIUS_MM: f64 = 10.0;
/// Samples lie within this distance of the sphere, as band pixels lie around a boundary.
const SHELL_HALF_WIDTH_MM: f64 = 3.0;

/// The field sampled: signed distance to the sphere, positive inside (grey-level-like: brighter in).
fn sphere_field(p: DVec3) -> f64 {
    RADIUS_MM - p.length()
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let count: usize = match std::env::args().nth(1) {
        Some(text) => text.parse()?,
        None => 3000,
    };
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let points: Vec<DVec3> = (0..count)
        .map(|_| {
            let direction = loop {
                let v = DVec3::new(
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                );
                let length = v.length();
                if length > 0.1 && length <= 1.0 {
                    break v / length;
                }
            };
            let radius = RADIUS_MM + rng.random_range(-SHELL_HALF_WIDTH_MM..SHELL_HALF_WIDTH_MM);
            direction * radius
        })
        .collect();
    let values: Vec<f64> = points.iter().map(|&p| sphere_field(p)).collect();

    // Interpolate (w = 0): the samples are exact, so there is no speckle to smooth away.
    let options = FitOptions {
        smoothing: 0.0,
        accuracy: 1e-3,
        ..FitOptions::default()
    };
    let (model, report) = rbf::fit(&points, &values, &options, &NoProgress)?;
    println!(
        "fit: {} samples, solver {:?}, {} patches, max data misfit {:.2e}, {:.2} s",
        report.merged_points,
        report.solver,
        report.patches,
        report.max_data_misfit,
        report.fit_seconds
    );

    let reach = RADIUS_MM + SHELL_HALF_WIDTH_MM + 1.0;
    let domain = SurfaceDomain {
        bounds_min_mm: DVec3::splat(-reach),
        bounds_max_mm: DVec3::splat(reach),
        seeds: points.clone(),
        trust_points: points,
    };
    let surface_options = SurfaceOptions {
        resolution_mm: 0.5,
        ..SurfaceOptions::default()
    };
    let meshes = surface::extract_surfaces(&model, &[0.0], &domain, &surface_options)?;
    let mesh = &meshes[0];

    let distances: Vec<f64> = mesh
        .vertices
        .iter()
        .map(|v| (v.length() - RADIUS_MM).abs())
        .collect();
    let mean = distances.iter().sum::<f64>() / distances.len().max(1) as f64;
    let max = distances.iter().fold(0.0_f64, |m, &d| m.max(d));
    let topology = mesh.topology();
    println!(
        "surface: {} triangles, {} pieces, closed manifold: {}; area {:.1} mm^2 (sphere {:.1})",
        topology.triangles,
        topology.components,
        topology.is_closed_manifold(),
        mesh.area_mm2(),
        4.0 * std::f64::consts::PI * RADIUS_MM * RADIUS_MM
    );
    println!("distance of the vertices to the true sphere: mean {mean:.4} mm, max {max:.4} mm");
    Ok(())
}
