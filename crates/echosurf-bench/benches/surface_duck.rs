//! Surfacing a real fitted model: the simulated duck sweep (default simulator options), segmented and
//! sampled as `extract` does, 100k samples fitted with the default solver, then one iso-surface at the
//! automatic level and 0.5 mm resolution. Prints the field evaluations per output triangle.
//!
//! `cargo bench -p echosurf --bench surface_duck`

use criterion::{Criterion, criterion_group, criterion_main};
use echosurf::pipeline::{
    ExtractOptions, median_frame_spacing_mm, prepare_samples, surface_domain, trust_distance_for,
};
use echosurf::progress::NoProgress;
use echosurf::resources::StageMeter;
use echosurf::surface::{SurfaceOptions, extract_surfaces_with_stats};
use echosurf_sim::{SimulationOptions, simulate};

fn surface_duck(c: &mut Criterion) {
    let sim = simulate(&SimulationOptions::default(), &NoProgress).expect("simulate duck");
    let options = ExtractOptions::default();
    let mut meter = StageMeter::new(&NoProgress);
    let prepared = prepare_samples(
        &sim.sequence,
        Some(&sim.calibration_written),
        &options,
        &mut meter,
        &NoProgress,
    )
    .expect("samples");
    let values: Vec<f64> = prepared
        .samples
        .intensities
        .iter()
        .map(|&v| v as f64)
        .collect();
    let (model, report) = echosurf::rbf::fit(
        &prepared.samples.positions,
        &values,
        &options.fit,
        &NoProgress,
    )
    .expect("fit");
    let levels = prepared.levels.expect("echo levels");
    let level = [levels.iso as f64];
    let trust = trust_distance_for(median_frame_spacing_mm(&sim.sequence, &prepared.poses));
    let band =
        echosurf::pipeline::SEED_BAND_FRACTION * (levels.boundary - levels.background) as f64;
    let domain = surface_domain(&prepared.samples.positions, &values, &level, band, trust);
    let surface_options = SurfaceOptions {
        trust_distance_mm: trust,
        ..SurfaceOptions::default()
    };
    let (meshes, stats) =
        extract_surfaces_with_stats(&model, &level, &domain, &surface_options).expect("surface");
    eprintln!(
        "duck: {} samples, {} patches, iso {:.1}: {} triangles, {} lattice nodes, {:.2} evaluations per triangle",
        report.merged_points,
        model.patches(),
        level[0],
        meshes[0].triangles.len(),
        stats.lattice_nodes_evaluated,
        stats.evaluations_per_triangle()
    );
    let mut group = c.benchmark_group("surface_duck");
    group.sample_size(10);
    group.bench_function("rbf_100k_0.5mm", |b| {
        b.iter(|| {
            extract_surfaces_with_stats(&model, &level, &domain, &surface_options).expect("surface")
        })
    });
    group.finish();
}

criterion_group!(benches, surface_duck);
criterion_main!(benches);
