//! `extract` end to end on the 9.2 M-pixel, 180-frame simulated duck sweep (the demo's data: 256 x 200
//! pixels, 3 sweeps): segment -> samples -> 100k-sample fit -> surface, with the defaults. Prints the
//! per-stage times of one run (the `--report` stages), then times whole runs (issue target: <= 8 s on
//! 2 cores).
//!
//! `cargo bench -p echosurf --bench extract`

use criterion::{Criterion, criterion_group, criterion_main};
use echosurf::pipeline::{ExtractOptions, extract};
use echosurf::progress::NoProgress;
use echosurf_sim::{SimulationOptions, simulate};

fn extract_duck(c: &mut Criterion) {
    let sim = simulate(&SimulationOptions::default(), &NoProgress).expect("simulate duck");
    let pixels = sim.sequence.frames.len() * sim.sequence.width * sim.sequence.height;
    let options = ExtractOptions::default();
    let run = || {
        extract(
            &sim.sequence,
            Some(&sim.calibration_written),
            &options,
            &NoProgress,
        )
        .expect("extract")
    };
    let output = run();
    let stages: Vec<String> = output
        .report
        .stages
        .iter()
        .map(|s| format!("{} {:.2} s", s.stage, s.seconds))
        .collect();
    eprintln!(
        "duck: {} frames, {:.1} M pixels, {} samples, {} triangles; total {:.2} s ({})",
        sim.sequence.frames.len(),
        pixels as f64 / 1e6,
        output.report.counts.samples,
        output.report.counts.triangles.iter().sum::<usize>(),
        output.report.total_seconds,
        stages.join(", ")
    );
    let mut group = c.benchmark_group("extract");
    group.sample_size(10);
    group.bench_function("duck_9.2M_pixels_180_frames", |b| b.iter(run));
    group.finish();
}

criterion_group!(benches, extract_duck);
criterion_main!(benches);
