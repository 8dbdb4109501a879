//! Frames simulated per second at 256 x 200 px (the duck's top sweep, default acoustics), on all cores.
//! Run: `cargo bench -p echosurf --bench simulate`.

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use echosurf::progress::NoProgress;
use echosurf_sim::{PhantomKind, SimulationOptions, simulate_sweeps};

fn frames_per_second(c: &mut Criterion) {
    let mut group = c.benchmark_group("simulate");
    group.sample_size(10);
    for phantom in [PhantomKind::Duck, PhantomKind::Hand] {
        let options = SimulationOptions {
            phantom: phantom.clone(),
            frames_per_sweep: 40,
            sweeps: Some(3),
            ..Default::default()
        };
        group.throughput(Throughput::Elements(120));
        group.bench_function(format!("{}_120_frames_256x200", phantom.name()), |b| {
            b.iter(|| simulate_sweeps(&options, &NoProgress).unwrap())
        });
    }
    group.finish();
}

criterion_group!(benches, frames_per_second);
criterion_main!(benches);
