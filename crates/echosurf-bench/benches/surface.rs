//! Surfacing cost on a duck-sized analytic field (until the RBF evaluator lands): a smooth union of
//! ellipsoids (~60 mm long) plus 256 Gaussian bumps, so each evaluation costs about what a small batch of
//! far-field RBF terms would. Reports time, field evaluations per output triangle and mesh size.
//!
//! `cargo bench -p echosurf --bench surface`

use criterion::{Criterion, criterion_group, criterion_main};
use echosurf::surface::{
    FnField, ScalarField, SurfaceDomain, SurfaceOptions, extract_surfaces_with_stats,
};
use glam::DVec3;
use rand::{Rng, SeedableRng};

/// Body, head, neck and beak as ellipsoids (centre, semi-axes in mm).
const ELLIPSOIDS: [(DVec3, DVec3); 4] = [
    (DVec3::new(0.0, 0.0, 0.0), DVec3::new(30.0, 18.0, 14.0)),
    (DVec3::new(22.0, 0.0, 18.0), DVec3::new(10.0, 9.0, 9.0)),
    (DVec3::new(16.0, 0.0, 9.0), DVec3::new(7.0, 6.0, 9.0)),
    (DVec3::new(33.0, 0.0, 17.0), DVec3::new(7.0, 3.5, 2.0)),
];

/// Smooth union (log-sum-exp with sharpness K) of 1 - |A^-1 (x - c)| per ellipsoid, in mm-like units,
/// plus small bumps; higher inside.
struct DuckField {
    bumps: Vec<(DVec3, f64)>,
}

const K: f64 = 0.6;

impl DuckField {
    fn new() -> DuckField {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let bumps = (0..256)
            .map(|_| {
                let c = DVec3::new(
                    rng.random_range(-30.0..40.0),
                    rng.random_range(-18.0..18.0),
                    rng.random_range(-14.0..28.0),
                );
                (c, rng.random_range(-0.4..0.4))
            })
            .collect();
        DuckField { bumps }
    }

    fn eval(&self, p: DVec3) -> (f64, DVec3) {
        let mut sum = 0.0;
        let mut grad = DVec3::ZERO;
        for (c, axes) in ELLIPSOIDS {
            let q = (p - c) / axes;
            let r = q.length().max(1e-12);
            // Distance-like value in mm: (1 - r) times the mean semi-axis.
            let scale = (axes.x + axes.y + axes.z) / 3.0;
            let v = (1.0 - r) * scale;
            let dv = -(q / r) / axes * scale;
            let w = (K * v).exp();
            sum += w;
            grad += w * dv;
        }
        let mut value = sum.ln() / K;
        let mut gradient = grad / sum;
        for &(c, a) in &self.bumps {
            let d = p - c;
            let g = a * (-d.length_squared() / 18.0).exp();
            value += g;
            gradient += -d / 9.0 * g;
        }
        (value, gradient)
    }
}

fn seeds(field: &DuckField) -> Vec<DVec3> {
    // Points near the surface, as the samples would be: rays from the body centre, bisected, jittered.
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
    (0..2000)
        .map(|_| {
            let dir = DVec3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            )
            .normalize();
            let (mut lo, mut hi) = (0.0, 60.0);
            for _ in 0..40 {
                let mid = 0.5 * (lo + hi);
                if field.eval(dir * mid).0 > 0.0 {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            // Samples scatter through the bright band, a few mm either side of the surface.
            dir * (lo + rng.random_range(-3.0..1.0))
        })
        .collect()
}

fn bench_surface(c: &mut Criterion) {
    let duck = DuckField::new();
    let field = FnField(|p| duck.eval(p));
    let seeds = seeds(&duck);
    let domain = SurfaceDomain {
        bounds_min_mm: DVec3::new(-40.0, -30.0, -25.0),
        bounds_max_mm: DVec3::new(50.0, 30.0, 40.0),
        seeds: seeds.clone(),
        trust_points: seeds,
    };
    let options = SurfaceOptions {
        trust_distance_mm: 15.0,
        ..SurfaceOptions::default()
    };
    let field: &dyn ScalarField = &field;
    let (meshes, stats) = extract_surfaces_with_stats(field, &[0.0], &domain, &options).unwrap();
    let topo = meshes[0].topology();
    eprintln!(
        "duck-sized field at 0.5 mm: {} triangles, {} vertices, closed manifold {}, {} lattice nodes, \
         {} value + {} gradient evaluations = {:.2} per triangle; {:?}",
        meshes[0].triangles.len(),
        meshes[0].vertices.len(),
        topo.is_closed_manifold(),
        stats.lattice_nodes_evaluated,
        stats.value_evaluations,
        stats.gradient_evaluations,
        stats.evaluations_per_triangle(),
        stats.levels[0],
    );
    let mut group = c.benchmark_group("surface");
    group.sample_size(10);
    group.bench_function("duck_sized_field_0.5mm", |b| {
        b.iter(|| extract_surfaces_with_stats(field, &[0.0], &domain, &options).unwrap())
    });
    // Two levels (as the duck's outer and inner wall): the lattice is shared, levels cluster in parallel.
    let (meshes2, stats2) =
        extract_surfaces_with_stats(field, &[0.0, 2.0], &domain, &options).unwrap();
    eprintln!(
        "two levels: {:?} triangles, {} lattice nodes, {:.2} evaluations per triangle",
        meshes2
            .iter()
            .map(|m| m.triangles.len())
            .collect::<Vec<_>>(),
        stats2.lattice_nodes_evaluated,
        stats2.evaluations_per_triangle()
    );
    group.bench_function("duck_sized_field_two_levels_0.5mm", |b| {
        b.iter(|| extract_surfaces_with_stats(field, &[0.0, 2.0], &domain, &options).unwrap())
    });
    group.finish();
}

criterion_group!(benches, bench_surface);
criterion_main!(benches);
