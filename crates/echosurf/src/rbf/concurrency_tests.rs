//! Fits running at the same time in one process give the same bytes as the same fits run one after
//! another: the solvers pass their parallelism to faer explicitly and change no process-wide setting.

use super::synthetic::ultrasound_like_samples;
use super::*;
use crate::progress::NoProgress;

/// How often each thread repeats its dense fit: the old code's save-toggle-restore of faer's global
/// parallelism only showed when one thread restored the setting while the other was factoring, which
/// two threads repeating dense fits of different sizes reach within a few rounds.
const DENSE_REPEATS: usize = 8;

/// Every bit of what a model is: its evaluations at fixed probe points and, for a global spline, its
/// centres, coefficients and trend.
fn fingerprint(model: &RbfModel) -> Vec<u64> {
    let probes: Vec<DVec3> = (0..400)
        .map(|i| {
            let t = i as f64;
            DVec3::new(
                -35.0 + (t * 0.37) % 70.0,
                -25.0 + (t * 0.61) % 50.0,
                -20.0 + (t * 0.13) % 40.0,
            )
        })
        .collect();
    let mut bits: Vec<u64> = model.values(&probes).iter().map(|v| v.to_bits()).collect();
    if !model.is_partition_of_unity() {
        bits.extend(model.coefficients().iter().map(|v| v.to_bits()));
        bits.extend(
            model
                .centres()
                .iter()
                .flat_map(|c| c.to_array())
                .map(f64::to_bits),
        );
        let (c, g, h) = model.trend();
        bits.push(c.to_bits());
        bits.extend(
            g.to_array()
                .iter()
                .chain(&h.to_array())
                .map(|v| v.to_bits()),
        );
    }
    bits
}

fn fit_fingerprint(points: &[DVec3], values: &[f64], solver: SolverChoice) -> Vec<u64> {
    let options = FitOptions {
        solver,
        merge_distance_mm: 0.0,
        ..FitOptions::default()
    };
    let (model, report) = fit(points, values, &options, &NoProgress).unwrap();
    assert_eq!(report.solver, solver);
    fingerprint(&model)
}

/// One thread's samples: a dense problem of `dense_points` (large enough for faer's blocked LU), one
/// for the fast solver (whose coarse level is a dense LU) and one for the partition of unity.
struct Case {
    dense: (Vec<DVec3>, Vec<f64>),
    fast: (Vec<DVec3>, Vec<f64>),
    pu: (Vec<DVec3>, Vec<f64>),
}

impl Case {
    fn new(dense_points: usize, seed: u64) -> Self {
        Case {
            dense: ultrasound_like_samples(dense_points, seed),
            fast: ultrasound_like_samples(2000, seed + 100),
            pu: ultrasound_like_samples(4000, seed + 200),
        }
    }

    /// Fingerprints of the dense fit `dense_repeats` times, then of the fast and the PU fit.
    fn run(&self, dense_repeats: usize) -> Vec<(&'static str, Vec<u64>)> {
        let mut out: Vec<_> = (0..dense_repeats)
            .map(|_| {
                let (p, v) = &self.dense;
                ("direct", fit_fingerprint(p, v, SolverChoice::Direct))
            })
            .collect();
        let (p, v) = &self.fast;
        out.push(("fast", fit_fingerprint(p, v, SolverChoice::Fast)));
        let (p, v) = &self.pu;
        out.push((
            "partition of unity",
            fit_fingerprint(p, v, SolverChoice::PartitionOfUnity),
        ));
        out
    }
}

#[test]
fn concurrent_fits_give_the_bytes_of_sequential_fits() {
    let cases = [Case::new(500, 11), Case::new(800, 12)];
    let sequential: Vec<_> = cases.iter().map(|c| c.run(1)).collect();
    let barrier = std::sync::Barrier::new(cases.len());
    std::thread::scope(|scope| {
        let workers: Vec<_> = cases
            .iter()
            .map(|case| {
                let barrier = &barrier;
                scope.spawn(move || {
                    barrier.wait();
                    case.run(DENSE_REPEATS)
                })
            })
            .collect();
        for (worker, reference) in workers.into_iter().zip(&sequential) {
            let fits = worker.join().unwrap();
            for (round, (name, bits)) in fits.iter().enumerate() {
                let expected = reference.iter().find(|(n, _)| n == name).unwrap();
                assert!(
                    bits == &expected.1,
                    "{name} fit (result {round}): concurrent bytes differ from sequential"
                );
            }
        }
    });
}
