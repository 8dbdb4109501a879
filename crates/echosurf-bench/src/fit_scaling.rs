//! The fit's cost against the number of samples: fit and evaluation times of ultrasound-like samples,
//! or of a sweep's band pixels.

use echosurf::rbf::{FastBreakdown, FitOptions, SolverChoice, fit, ultrasound_like_samples};
use glam::DVec3;

use crate::band_pixels::random_subset;

/// Where the fit-scaling samples come from.
#[derive(Debug, Clone, Copy)]
pub enum ScalingSamples<'a> {
    /// [`ultrasound_like_samples`] of each size; the evaluation points are another draw.
    Synthetic,
    /// Random subsets of a sweep's band pixels ([`crate::all_band_pixels`]); the evaluation points
    /// are another subset. Sizes beyond the pixels there are are skipped.
    BandPixels {
        name: &'a str,
        points: &'a [DVec3],
        values: &'a [f64],
    },
}

impl ScalingSamples<'_> {
    fn name(&self) -> &str {
        match self {
            ScalingSamples::Synthetic => "synthetic",
            ScalingSamples::BandPixels { name, .. } => name,
        }
    }

    /// `n` samples and their values, or None when there are fewer.
    fn draw(&self, n: usize, seed: u64) -> Option<(Vec<DVec3>, Vec<f64>)> {
        match self {
            ScalingSamples::Synthetic => Some(ultrasound_like_samples(n, seed)),
            ScalingSamples::BandPixels { points, values, .. } => {
                (points.len() >= n).then(|| random_subset(points, values, n, seed))
            }
        }
    }
}

/// One row of [`bench_fit_scaling`].
#[derive(Debug, Clone, serde::Serialize)]
pub struct ScalingRow {
    /// "synthetic", or the name of the sweep whose band pixels were fitted.
    pub samples_from: String,
    pub samples: usize,
    pub fit_seconds: f64,
    pub iterations: usize,
    pub max_residual: f64,
    pub rms_residual: f64,
    pub solver: SolverChoice,
    /// Partition-of-unity patches (0 for global solvers).
    pub patches: usize,
    pub mean_patch_points: f64,
    /// Time to evaluate values and gradients at `samples` fresh points.
    pub eval_seconds: f64,
    pub solver_bytes_per_sample: f64,
    /// Time breakdown of the global fast solver (None for the other solvers).
    pub fast_breakdown: Option<FastBreakdown>,
}

/// Fits `source`'s samples of each size with `options` and times fit and evaluation.
pub fn bench_fit_scaling(
    sizes: &[usize],
    options: &FitOptions,
    seed: u64,
    source: ScalingSamples,
) -> echosurf::Result<Vec<ScalingRow>> {
    let mut rows = Vec::new();
    for &n in sizes {
        let Some((points, values)) = source.draw(n, seed) else {
            continue;
        };
        let (model, report) = fit(&points, &values, options, &echosurf::progress::NoProgress)?;
        let (probes, _) = source
            .draw(n, seed.wrapping_add(1))
            .expect("as many samples as the fit's");
        let start = std::time::Instant::now();
        let (v, _) = model.values_and_gradients(&probes);
        let eval_seconds = start.elapsed().as_secs_f64();
        debug_assert_eq!(v.len(), n);
        rows.push(ScalingRow {
            samples_from: source.name().to_string(),
            samples: n,
            fit_seconds: report.fit_seconds,
            iterations: report.iterations,
            max_residual: report.max_residual,
            rms_residual: report.rms_residual,
            solver: report.solver,
            patches: report.patches,
            mean_patch_points: report.mean_patch_points,
            eval_seconds,
            solver_bytes_per_sample: report.solver_bytes as f64 / n as f64,
            fast_breakdown: report.fast_breakdown,
        });
    }
    Ok(rows)
}

/// The sample counts of the fit-scaling run up to `max` (1k, 3k, 10k, 30k, 100k, ...).
pub fn fit_sizes(max: usize) -> Vec<usize> {
    let mut sizes = Vec::new();
    let mut decade = 1_000usize;
    while decade <= max {
        sizes.push(decade);
        if 3 * decade <= max {
            sizes.push(3 * decade);
        }
        decade = match decade.checked_mul(10) {
            Some(d) => d,
            None => break,
        };
    }
    sizes
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fit_sizes_are_one_three_per_decade() {
        assert_eq!(
            fit_sizes(100_000),
            vec![1_000, 3_000, 10_000, 30_000, 100_000]
        );
        assert_eq!(fit_sizes(3_000), vec![1_000, 3_000]);
        assert!(fit_sizes(999).is_empty());
    }
}
