//! Drawing the oriented-point sheet (`sheet_through_points`, the ridge route's sheets) through a
//! duck-body-sized shell of 60,000 points with normals, jittered across the shell as echo ridges are:
//! about as many points as the sheet drawn through the independent duck's ridges and crests
//! (docs/decisions/0061-sheet-sums-four-at-a-time.md).
//!
//! `cargo bench -p echosurf-bench --bench sheet`

use criterion::{Criterion, criterion_group, criterion_main};
use echosurf::surface::{SheetOptions, SurfaceDomain, SurfaceOptions, sheet_through_points};
use glam::DVec3;
use rand::{Rng, SeedableRng};

/// Semi-axes (mm) of the shell: the demo duck's body.
const SEMI_AXES: DVec3 = DVec3::new(30.0, 18.0, 14.0);

/// `n` points spread over the ellipsoid (a Fibonacci lattice on the unit sphere, stretched), each moved
/// up to 0.15 mm along its normal, with the ellipsoid's outward unit normals.
fn shell(n: usize, seed: u64) -> (Vec<DVec3>, Vec<DVec3>) {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    (0..n)
        .map(|i| {
            let z = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
            let r = (1.0 - z * z).sqrt();
            let a = golden * i as f64;
            let on = DVec3::new(r * a.cos(), r * a.sin(), z) * SEMI_AXES;
            let normal = (on / (SEMI_AXES * SEMI_AXES)).normalize();
            let jitter: f64 = rng.random::<f64>() * 0.3 - 0.15;
            (on + normal * jitter, normal)
        })
        .unzip()
}

fn bench_sheet(c: &mut Criterion) {
    let (points, normals) = shell(60_000, 7);
    let domain = SurfaceDomain {
        bounds_min_mm: -SEMI_AXES - 5.0,
        bounds_max_mm: SEMI_AXES + 5.0,
        seeds: Vec::new(),
        trust_points: Vec::new(),
    };
    let surface = SurfaceOptions::default();
    let options = SheetOptions::default();
    let (mesh, stats) =
        sheet_through_points(&points, &normals, &domain, &surface, &options).unwrap();
    eprintln!(
        "sheet through {} points: {} triangles, {} value + {} gradient evaluations",
        points.len(),
        mesh.triangles.len(),
        stats.value_evaluations,
        stats.gradient_evaluations,
    );
    let mut group = c.benchmark_group("sheet");
    group.sample_size(10);
    group.bench_function("shell_60k_points_0.5mm", |b| {
        b.iter(|| sheet_through_points(&points, &normals, &domain, &surface, &options).unwrap())
    });
    group.finish();
}

criterion_group!(benches, bench_sheet);
criterion_main!(benches);
