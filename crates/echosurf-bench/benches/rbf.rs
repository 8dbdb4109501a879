//! RBF engine benchmarks on ultrasound-like samples: fit (partition of unity, global fast solver, dense)
//! and batched evaluation. Large sizes (100k, 1M) are better timed once with
//! `cargo run --release --example rbf_scaling -- 100000 1000000` (SOLVER=fast for the global solver).

use criterion::{Criterion, criterion_group, criterion_main};
use echosurf::progress::NoProgress;
use echosurf::rbf::{FitOptions, SolverChoice, fit, ultrasound_like_samples};

fn bench_rbf(c: &mut Criterion) {
    let mut group = c.benchmark_group("rbf");
    group.sample_size(10);
    let (points, values) = ultrasound_like_samples(10_000, 1);
    let options = FitOptions {
        solver: SolverChoice::Fast,
        ..FitOptions::default()
    };
    group.bench_function("fit_fast_10k", |b| {
        b.iter(|| fit(&points, &values, &options, &NoProgress).expect("fit"))
    });
    let (model, _) = fit(&points, &values, &options, &NoProgress).expect("fit");
    let (probes, _) = ultrasound_like_samples(100_000, 2);
    group.bench_function("eval_values_gradients_100k_at_10k_centres", |b| {
        b.iter(|| model.values_and_gradients(&probes))
    });
    let pu = FitOptions {
        solver: SolverChoice::PartitionOfUnity,
        ..FitOptions::default()
    };
    group.bench_function("fit_pu_10k", |b| {
        b.iter(|| fit(&points, &values, &pu, &NoProgress).expect("fit"))
    });
    let (big, big_values) = ultrasound_like_samples(100_000, 4);
    group.bench_function("fit_pu_100k", |b| {
        b.iter(|| fit(&big, &big_values, &pu, &NoProgress).expect("fit"))
    });
    let (pu_model, _) = fit(&big, &big_values, &pu, &NoProgress).expect("fit");
    group.bench_function("eval_values_gradients_100k_pu_100k", |b| {
        b.iter(|| pu_model.values_and_gradients(&probes))
    });
    let (small, small_values) = ultrasound_like_samples(2_000, 3);
    let direct = FitOptions {
        solver: SolverChoice::Direct,
        ..FitOptions::default()
    };
    group.bench_function("fit_direct_2k", |b| {
        b.iter(|| fit(&small, &small_values, &direct, &NoProgress).expect("fit"))
    });
    group.finish();
}

criterion_group!(benches, bench_rbf);
criterion_main!(benches);
