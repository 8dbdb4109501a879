//! `compare_meshes` on two ~100k-triangle tori (different tessellations, 0.2 mm apart) and the raw
//! nearest-triangle query rate of the BVH.

use criterion::{Criterion, criterion_group, criterion_main};
use echosurf::metrics::shapes::torus;
use echosurf::metrics::{CompareOptions, compare_meshes, point_to_mesh_distances};
use glam::DVec3;

fn bench(c: &mut Criterion) {
    let mesh = torus(30.0, 10.0, 250, 200); // 100,000 triangles, 11,800 mm^2
    let truth = torus(30.0, 10.2, 240, 210); // 100,800 triangles
    let mut group = c.benchmark_group("metrics");
    group.sample_size(10);
    let options = CompareOptions::default();
    group.bench_function("compare_100k_tris_default", |b| {
        b.iter(|| compare_meshes(&mesh, &truth, &options).unwrap())
    });
    let points: Vec<DVec3> = mesh.vertices.iter().map(|v| *v * 1.01).collect();
    group.bench_function("point_to_mesh_50k_points_100k_tris", |b| {
        b.iter(|| point_to_mesh_distances(&points, &truth))
    });
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
