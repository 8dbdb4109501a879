//! The biharmonic RBF engine: fit `s(x) = c0 + c.x + sum_i l_i |x - x_i|` to all samples, evaluate it fast.
//!
//! Fitting solves the smoothing-spline system `(A - wI) l + P c = f, P^T l = 0` (`A_ij = |x_i - x_j|`,
//! P the linear trend; ALGORITHMS.md §1: with R(r) = r the smoothing enters with a minus sign so that
//! `-(A - wI)` stays positive definite on `P^T l = 0`). The residual at a sample is `f_i - s(x_i) = -w l_i`.
//! Small problems use a dense LU (the reference). Large ones use, by default, the partition-of-unity
//! method ([`pu`]: local dense fits on overlapping k-d tree patches blended by Wendland weights; O(N)),
//! or on request the global spline via the treecode product inside preconditioned GMRES ([`fast`]).
//! Near-duplicate samples are merged first; coplanar or tiny inputs get a reduced trend.

// Dense linear algebra reads best in index notation.
#![allow(clippy::needless_range_loop)]

mod coarse;
mod direct;
mod fast;
mod fmm;
mod kernel;
mod merge;
mod model;
mod pu;
mod reference;
mod synthetic;
mod tree;
mod trend;

use std::time::Instant;

use glam::DVec3;
use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;

pub(crate) use fast::FMM_MIN_POINTS;
pub use fast::FastBreakdown;
pub use merge::merge_near_duplicates;
pub use model::RbfModel;
pub use pu::{MAX_PATCH_FACTOR, MIN_PATCH_POINTS};
pub use reference::{definition_max_misfit, definition_value};
pub use synthetic::ultrasound_like_samples;

use crate::progress::Progress;
use crate::{Error, OptionName, OptionsErrorKind, Phrase, Result};

/// Which linear solver [`fit`] uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
pub enum SolverChoice {
    /// Dense below [`FitOptions::direct_max_points`] merged points, partition of unity above.
    #[default]
    Auto,
    /// Dense LU, O(N^2) memory, O(N^3) time: the reference.
    Direct,
    /// The *global* spline: treecode + two-level Schwarz-preconditioned GMRES, accurate to the fitting
    /// accuracy but much slower than partition of unity (docs/decisions/0035-figures-from-code-comments.md).
    Fast,
    /// Partition of unity: local dense fits on overlapping patches blended by Wendland weights
    /// (O(N), parallel); not the single global spline, but agrees with it to within the local fit error.
    PartitionOfUnity,
}

/// Parameters of [`fit`]; also the `[tuning.fit]` section of `extract`'s options (the TOML has
/// no smoothing, seed or centre reduction: `extract` takes the first two from its user tier and does
/// not reduce centres).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FitOptions {
    /// Smoothing weight w >= 0, in mm (grey level per grey-level/mm): the fit satisfies
    /// `f_i - s(x_i) = -w l_i`; larger is smoother, w = 0 interpolates, w -> infinity gives the
    /// least-squares linear trend. Sensible values are comparable to the sample spacing or a few times it.
    #[serde(skip)]
    pub smoothing: f64,
    /// Fitting accuracy in grey levels: the solve stops when `max_i |f_i - s(x_i) - w l_i| <= accuracy`
    /// (at w = 0 this is the largest data misfit).
    #[serde(rename = "accuracy_grey")]
    pub accuracy: f64,
    /// Relative accuracy of the fast evaluator (far-field error relative to the sum of absolute
    /// contributions); also used for the products inside the fast solver.
    pub eval_accuracy: f64,
    /// Upper bound on the number of centres; fewer than the samples implies greedy reduction.
    #[serde(skip)]
    pub max_centres: Option<usize>,
    /// Greedy centre reduction (Carr et al. 2001): fit a subset, add the worst-fitted samples, repeat.
    #[serde(skip)]
    pub reduce_centres: bool,
    /// Seed of the random initial subset of the centre reduction.
    #[serde(skip)]
    pub seed: u64,
    /// Samples closer than this (mm) are merged into one, with the mean value.
    pub merge_distance_mm: f64,
    /// `auto`, `direct`, `pu` or `fast` in the TOML.
    #[serde(with = "solver_words")]
    pub solver: SolverChoice,
    /// Largest problem [`SolverChoice::Auto`] solves densely.
    pub direct_max_points: usize,
    /// Krylov iteration budget of the fast solver.
    pub max_iterations: usize,
    /// Partition of unity: samples per k-d tree leaf cell (one local fit per leaf).
    pub pu_leaf_points: usize,
    /// Partition of unity: support expansion per side, relative to the leaf cell's half-size.
    pub pu_overlap: f64,
    /// Partition of unity: minimum support expansion per side (mm).
    pub pu_min_overlap_mm: f64,
}

impl Default for FitOptions {
    fn default() -> Self {
        FitOptions {
            smoothing: 1.0,
            accuracy: 2.0,
            eval_accuracy: 1e-4,
            max_centres: None,
            reduce_centres: false,
            seed: 0,
            merge_distance_mm: 0.01,
            solver: SolverChoice::Auto,
            direct_max_points: 2000,
            max_iterations: 1000,
            pu_leaf_points: 64,
            pu_overlap: 0.5,
            pu_min_overlap_mm: 0.5,
        }
    }
}

crate::serde_forms::word_serde!(solver_words, SolverChoice, [
    "auto" => SolverChoice::Auto,
    "direct" => SolverChoice::Direct,
    "pu" => SolverChoice::PartitionOfUnity,
    "fast" => SolverChoice::Fast,
]);

/// What [`fit`] did.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct FitReport {
    pub input_points: usize,
    /// Samples after near-duplicate merging.
    pub merged_points: usize,
    /// Centres of the global spline; for partition of unity the total of local centres (sum of patch
    /// sizes, so samples in overlaps count once per patch).
    pub centres: usize,
    /// Partition-of-unity patches (0 for the global solvers).
    pub patches: usize,
    /// Mean samples per partition-of-unity patch (0 for the global solvers).
    pub mean_patch_points: f64,
    /// Krylov iterations summed over all solves (0 for the direct solver).
    pub iterations: usize,
    /// Greedy reduction rounds (0 without reduction).
    pub reduction_rounds: usize,
    /// Largest system residual `|f_i - s(x_i) - w l_i|` over the centres (grey levels). Partition of unity
    /// has no single system: there it is the measured data misfit `|f_i - s(x_i)|` of the blended model
    /// over all (merged) samples, which includes the smoothing misfit.
    pub max_residual: f64,
    pub rms_residual: f64,
    /// Largest and rms data misfit `|f_i - s(x_i)|` of the final model over the (merged) samples, grey
    /// levels: at w > 0 the smoothing's intended misfit; far above the speckle it says the samples
    /// contradict each other (frames placed wrongly, e.g. a calibration of another probe).
    pub max_data_misfit: f64,
    pub rms_data_misfit: f64,
    /// Number of linear-trend directions kept (4 normally; 3 for coplanar samples, ...); for partition of
    /// unity the smallest over the local fits.
    pub trend_rank: usize,
    pub solver: SolverChoice,
    pub smoothing: f64,
    pub fit_seconds: f64,
    /// Bytes held by the largest solver structure (treecode, lists, preconditioner, Krylov basis; for
    /// partition of unity the model plus one dense local system per thread).
    pub solver_bytes: usize,
    /// Time and call counts of the global fast solver's parts (last solve; None for other solvers).
    pub fast_breakdown: Option<FastBreakdown>,
}

/// Fits the smoothing biharmonic spline to `values` at `points` (see [`FitOptions`]).
pub fn fit(
    points: &[DVec3],
    values: &[f64],
    options: &FitOptions,
    progress: &dyn Progress,
) -> Result<(RbfModel, FitReport)> {
    let start = Instant::now();
    validate(points, values, options)?;
    let (pts, vals) = merge_near_duplicates(points, values, options.merge_distance_mm);
    let reduce = options.reduce_centres || options.max_centres.is_some_and(|m| m < pts.len());
    let mut report = FitReport {
        input_points: points.len(),
        merged_points: pts.len(),
        centres: 0,
        patches: 0,
        mean_patch_points: 0.0,
        iterations: 0,
        reduction_rounds: 0,
        max_residual: 0.0,
        rms_residual: 0.0,
        max_data_misfit: 0.0,
        rms_data_misfit: 0.0,
        trend_rank: 0,
        solver: options.solver,
        smoothing: options.smoothing,
        fit_seconds: 0.0,
        solver_bytes: 0,
        fast_breakdown: None,
    };
    let model = if reduce {
        let model = greedy_reduction(&pts, &vals, options, progress, &mut report)?;
        let fitted = model.values(&pts);
        let misfit: Vec<f64> = fitted.iter().zip(&vals).map(|(s, f)| f - s).collect();
        report.max_data_misfit = misfit.iter().fold(0.0, |m, e| m.max(e.abs()));
        report.rms_data_misfit =
            (misfit.iter().map(|e| e * e).sum::<f64>() / misfit.len() as f64).sqrt();
        model
    } else {
        let sub = solve_subset(&pts, &vals, options, None, progress)?;
        absorb(&mut report, &sub);
        if sub.solver == SolverChoice::PartitionOfUnity {
            (report.max_data_misfit, report.rms_data_misfit) = sub.data_misfit;
        } else {
            // Measured afresh from the final model (its own evaluator), not the solver's vectors.
            let [max_r, rms_r, max_m, rms_m] =
                global_system_residual(&sub.model, &pts, &vals, options.smoothing);
            (report.max_residual, report.rms_residual) = (max_r, rms_r);
            (report.max_data_misfit, report.rms_data_misfit) = (max_m, rms_m);
        }
        if report.max_residual.is_nan() || report.max_residual > options.accuracy {
            return Err(Error::Options {
                kind: OptionsErrorKind::Numerical,
                message: Phrase::new(format!(
                    "RBF fit ({:?} solver, {} samples, smoothing {} mm): the largest system residual \
                     |f_i - s(x_i) + w l_i| of the fitted model is {:.4} grey levels, above the \
                     requested accuracy {}; ",
                    sub.solver,
                    pts.len(),
                    options.smoothing,
                    report.max_residual,
                    options.accuracy,
                ))
                .then(accuracy_advice(sub.solver)),
            });
        }
        sub.model
    };
    report.centres = model.coefficients().len();
    report.patches = model.patches();
    if report.patches > 0 {
        report.mean_patch_points = report.centres as f64 / report.patches as f64;
    }
    report.fit_seconds = start.elapsed().as_secs_f64();
    Ok((model, report))
}

/// What to change when a solver misses the accuracy.
fn accuracy_advice(solver: SolverChoice) -> Phrase {
    use OptionName::{FitAccuracy, FitSmoothing, FitSolver};
    let raise_both = Phrase::new("raise ")
        .option(FitAccuracy)
        .text(" or ")
        .option(FitSmoothing);
    match solver {
        SolverChoice::PartitionOfUnity => raise_both
            .text(", or set ")
            .option(FitSolver)
            .text(" to fast (the global spline)"),
        SolverChoice::Fast => {
            raise_both.text(" (the model's evaluation error is part of the figure)")
        }
        _ => Phrase::new("raise ")
            .option(FitSmoothing)
            .text(" (near-coincident samples with different values) or ")
            .option(FitAccuracy),
    }
}

/// `[max, rms]` over the samples of the system residual `|f_i - s(x_i) + w l_i|`, then `[max, rms]` of
/// the data misfit `|f_i - s(x_i)|`, for a global model whose centres are `pts`, with `s` the model's
/// own evaluation.
fn global_system_residual(model: &RbfModel, pts: &[DVec3], vals: &[f64], w: f64) -> [f64; 4] {
    let fitted = model.values(pts);
    let (mut max_r, mut sum_sq, mut max_m, mut misfit_sq) = (0.0f64, 0.0, 0.0f64, 0.0);
    for ((s, f), l) in fitted.iter().zip(vals).zip(model.coefficients()) {
        let e = f - s + w * l;
        max_r = max_r.max(e.abs());
        sum_sq += e * e;
        max_m = max_m.max((f - s).abs());
        misfit_sq += (f - s) * (f - s);
    }
    if !max_r.is_finite() {
        max_r = f64::INFINITY;
    }
    let n = pts.len() as f64;
    [max_r, (sum_sq / n).sqrt(), max_m, (misfit_sq / n).sqrt()]
}

fn validate(points: &[DVec3], values: &[f64], options: &FitOptions) -> Result<()> {
    if points.len() != values.len() {
        return Err(Error::InvalidInput(format!(
            "RBF fit: {} points but {} values",
            points.len(),
            values.len()
        )));
    }
    if points.is_empty() {
        return Err(Error::InvalidInput("RBF fit: no samples".into()));
    }
    if let Some(i) = points.iter().position(|p| !p.is_finite()) {
        return Err(Error::InvalidInput(format!(
            "RBF fit: sample {i} has a non-finite position {:?}",
            points[i]
        )));
    }
    if let Some(i) = values.iter().position(|v| !v.is_finite()) {
        return Err(Error::InvalidInput(format!(
            "RBF fit: sample {i} has a non-finite value {}",
            values[i]
        )));
    }
    let bad =
        |what: &str, v: f64| Error::InvalidInput(format!("RBF fit: {what} {v} is out of range"));
    if !(options.smoothing >= 0.0 && options.smoothing.is_finite()) {
        return Err(bad("smoothing", options.smoothing));
    }
    if !(options.accuracy > 0.0 && options.accuracy.is_finite()) {
        return Err(bad("accuracy (grey levels, > 0)", options.accuracy));
    }
    if !(options.eval_accuracy > 0.0 && options.eval_accuracy <= 0.1) {
        return Err(bad(
            "eval accuracy (relative, in (0, 0.1])",
            options.eval_accuracy,
        ));
    }
    if !(options.merge_distance_mm >= 0.0 && options.merge_distance_mm.is_finite()) {
        return Err(bad("merge distance", options.merge_distance_mm));
    }
    if options.pu_leaf_points < 1 || options.pu_leaf_points > 100_000 {
        return Err(bad(
            "partition-of-unity leaf size (samples, 1..=100000)",
            options.pu_leaf_points as f64,
        ));
    }
    if !(options.pu_overlap > 0.0 && options.pu_overlap <= 10.0) {
        return Err(bad(
            "partition-of-unity overlap (relative, in (0, 10])",
            options.pu_overlap,
        ));
    }
    if !(options.pu_min_overlap_mm > 0.0 && options.pu_min_overlap_mm.is_finite()) {
        return Err(bad(
            "partition-of-unity minimum overlap (mm, > 0)",
            options.pu_min_overlap_mm,
        ));
    }
    if options.max_centres == Some(0) {
        return Err(Error::InvalidInput(
            "RBF fit: max centres must be at least 1".into(),
        ));
    }
    Ok(())
}

fn absorb(report: &mut FitReport, sub: &SubsetFit) {
    report.iterations += sub.iterations;
    report.max_residual = sub.max_residual;
    report.rms_residual = sub.rms_residual;
    report.trend_rank = sub.trend_rank;
    report.solver = sub.solver;
    report.solver_bytes = report.solver_bytes.max(sub.solver_bytes);
    report.fast_breakdown = sub.fast_breakdown.clone();
}

struct SubsetFit {
    model: RbfModel,
    iterations: usize,
    max_residual: f64,
    rms_residual: f64,
    trend_rank: usize,
    solver: SolverChoice,
    solver_bytes: usize,
    fast_breakdown: Option<FastBreakdown>,
    /// Partition of unity: (max, rms) data misfit measured with the residuals; unused otherwise.
    data_misfit: (f64, f64),
}

/// Solves the full system on `pts` (every point a centre).
fn solve_subset(
    pts: &[DVec3],
    vals: &[f64],
    options: &FitOptions,
    initial: Option<&[f64]>,
    progress: &dyn Progress,
) -> Result<SubsetFit> {
    let n = pts.len();
    let solver = match options.solver {
        SolverChoice::Auto if n <= options.direct_max_points => SolverChoice::Direct,
        SolverChoice::Auto => SolverChoice::PartitionOfUnity,
        s => s,
    };
    if solver == SolverChoice::PartitionOfUnity {
        return solve_partition_of_unity(pts, vals, options, progress);
    }
    let basis = trend::TrendBasis::new(pts);
    let mut fast_breakdown = None;
    let (coefficients, d, iterations, max_residual, rms_residual, solver_bytes) =
        if n <= basis.rank() {
            // No room for RBF terms: the (reduced) trend interpolates.
            let u = basis.matrix(pts);
            let r = basis.rank();
            let d: Vec<f64> = (0..r)
                .map(|k| (0..n).map(|i| u[i * r + k] * vals[i]).sum())
                .collect();
            (vec![0.0; n], d, 0, 0.0, 0.0, 0)
        } else if solver == SolverChoice::Direct {
            check_dense_memory(n + basis.rank())?;
            // One LU, no intermediate progress to report: a spinner.
            progress.start("fit: dense solve", 0);
            let (l, d) = direct::solve_dense(pts, vals, options.smoothing, &basis)?;
            progress.finish();
            let (max_r, rms_r) = dense_residual(pts, vals, &l, &d, &basis, options.smoothing);
            let bytes = (n + 4) * (n + 4) * 8;
            (l, d, 0, max_r, rms_r, bytes)
        } else {
            let params = tree::TreecodeParams::for_accuracy(options.eval_accuracy);
            let system = fast::FastSystem::new(pts, options.smoothing, &basis, params)?;
            let sol = system.solve(
                vals,
                options.accuracy,
                options.max_iterations,
                initial,
                progress,
            )?;
            // Krylov basis plus the work vectors alive at a peek (x, f, work, e, z, w, combo, x_try, e_try).
            let bytes = system.memory_bytes() + (sol.krylov_vectors + 9) * n * 8;
            fast_breakdown = Some(sol.breakdown);
            (
                sol.coefficients,
                sol.trend,
                sol.iterations,
                sol.max_residual,
                sol.rms_residual,
                bytes,
            )
        };
    let (constant, linear) = basis.to_linear(&d);
    let model = RbfModel::new(
        pts.to_vec(),
        coefficients,
        basis.origin,
        constant,
        linear,
        options.smoothing,
        options.eval_accuracy,
    );
    Ok(SubsetFit {
        model,
        iterations,
        max_residual,
        rms_residual,
        trend_rank: basis.rank(),
        solver,
        solver_bytes,
        fast_breakdown,
        data_misfit: (0.0, 0.0),
    })
}

/// Bytes the dense solve holds: the saddle matrix and faer's LU copy of it, `2 (n + r)^2` f64.
pub fn dense_solve_bytes(size: usize) -> u128 {
    2 * (size as u128) * (size as u128) * 8
}

/// Refuses a dense solve that would not fit the memory budget (half the machine's memory).
fn check_dense_memory(size: usize) -> Result<()> {
    let needed = dense_solve_bytes(size);
    let budget = crate::resources::default_memory_budget_bytes();
    if needed > u128::from(budget) {
        return Err(Error::OverBudget {
            needed_bytes: needed.min(u128::from(u64::MAX)) as u64,
            budget_bytes: budget,
            budget_option: None,
            message: Phrase::new(format!(
                "dense RBF solve of {size} unknowns needs {:.1} GB (two {size} x {size} f64 matrices), \
                 more than the {:.1} GB memory budget (half the machine's memory); set ",
                needed as f64 / 1e9,
                budget as f64 / 1e9
            ))
            .option(OptionName::FitSolver)
            .text(" to pu or fast, or fit fewer samples"),
        });
    }
    Ok(())
}

fn solve_partition_of_unity(
    pts: &[DVec3],
    vals: &[f64],
    options: &FitOptions,
    progress: &dyn Progress,
) -> Result<SubsetFit> {
    let params = pu::PuParams {
        leaf_points: options.pu_leaf_points,
        overlap: options.pu_overlap,
        min_overlap_mm: options.pu_min_overlap_mm,
    };
    let (pu_model, stats) = pu::fit_pu(
        pts,
        vals,
        options.smoothing,
        options.eval_accuracy,
        params,
        progress,
    )?;
    let size = stats.max_patch_points + 4;
    let solver_bytes =
        pu_model.memory_bytes() + rayon::current_num_threads() * size * (size + 1) * 8;
    let model = RbfModel::from_partition_of_unity(pu_model);
    if stats.foreign_weighted_samples > 0 {
        return Err(Error::Options {
            kind: OptionsErrorKind::Numerical,
            message: Phrase::new(format!(
                "partition-of-unity fit: {} samples are weighted by patches not fitted to them (a bug \
                 in the partition; set ",
                stats.foreign_weighted_samples
            ))
            .option(OptionName::FitSolver)
            .text(" to fast)"),
        });
    }
    Ok(SubsetFit {
        model,
        iterations: 0,
        max_residual: stats.max_residual,
        rms_residual: stats.rms_residual,
        trend_rank: stats.min_trend_rank,
        solver: SolverChoice::PartitionOfUnity,
        solver_bytes,
        fast_breakdown: None,
        data_misfit: (stats.max_data_misfit, stats.rms_data_misfit),
    })
}

fn dense_residual(
    pts: &[DVec3],
    vals: &[f64],
    l: &[f64],
    d: &[f64],
    basis: &trend::TrendBasis,
    w: f64,
) -> (f64, f64) {
    let r = basis.rank();
    let mut ub = vec![0.0; r];
    let mut max_r: f64 = 0.0;
    let mut sum_sq = 0.0;
    for i in 0..pts.len() {
        let mut s = -w * l[i];
        for (p, lj) in pts.iter().zip(l) {
            s += lj * (pts[i] - *p).length();
        }
        basis.eval(pts[i], &mut ub);
        s += ub.iter().zip(d).map(|(a, b)| a * b).sum::<f64>();
        let e = vals[i] - s;
        max_r = max_r.max(e.abs());
        sum_sq += e * e;
    }
    (max_r, (sum_sq / pts.len() as f64).sqrt())
}

/// Carr et al. (2001): start from a random 2 % subset, refit, add the worst-fitted samples in batches.
fn greedy_reduction(
    pts: &[DVec3],
    vals: &[f64],
    options: &FitOptions,
    progress: &dyn Progress,
    report: &mut FitReport,
) -> Result<RbfModel> {
    let n = pts.len();
    let budget = options.max_centres.unwrap_or(n).min(n);
    let mut order: Vec<usize> = (0..n).collect();
    order.shuffle(&mut ChaCha8Rng::seed_from_u64(options.seed));
    let initial = (n / 50).max(500.min(n)).min(budget);
    let mut selected: Vec<usize> = order[..initial].to_vec();
    selected.sort_unstable();
    let mut is_centre = vec![false; n];
    for &i in &selected {
        is_centre[i] = true;
    }
    let mut previous: Option<(Vec<usize>, Vec<f64>)> = None;
    loop {
        report.reduction_rounds += 1;
        let sub_pts: Vec<DVec3> = selected.iter().map(|&i| pts[i]).collect();
        let sub_vals: Vec<f64> = selected.iter().map(|&i| vals[i]).collect();
        // Warm start: old coefficients where the centre already existed.
        let warm = previous.as_ref().map(|(idx, coef)| {
            let mut w = vec![0.0; selected.len()];
            let mut k = 0;
            for (j, &s) in selected.iter().enumerate() {
                while k < idx.len() && idx[k] < s {
                    k += 1;
                }
                if k < idx.len() && idx[k] == s {
                    w[j] = coef[k];
                }
            }
            w
        });
        let sub = solve_subset(&sub_pts, &sub_vals, options, warm.as_deref(), progress)?;
        absorb(report, &sub);
        if selected.len() >= budget {
            return Ok(sub.model);
        }
        // Non-centres must fit as well as the centres do (accuracy plus the smoothing misfit w|l|).
        let smoothing_misfit = sub
            .model
            .coefficients()
            .iter()
            .fold(0.0f64, |m, l| m.max((options.smoothing * l).abs()));
        let threshold = options.accuracy + smoothing_misfit;
        let others: Vec<usize> = (0..n).filter(|&i| !is_centre[i]).collect();
        let other_pts: Vec<DVec3> = others.iter().map(|&i| pts[i]).collect();
        let fitted = sub.model.values(&other_pts);
        let mut bad: Vec<(f64, usize)> = others
            .iter()
            .zip(&fitted)
            .map(|(&i, s)| ((vals[i] - s).abs(), i))
            .filter(|(e, _)| *e > threshold)
            .collect();
        if bad.is_empty() {
            return Ok(sub.model);
        }
        bad.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
        let batch = (selected.len() / 2).max(100).min(budget - selected.len());
        for &(_, i) in bad.iter().take(batch) {
            is_centre[i] = true;
        }
        previous = Some((selected, sub.model.coefficients().to_vec()));
        selected = (0..n).filter(|&i| is_centre[i]).collect();
    }
}

#[cfg(test)]
mod concurrency_tests;
#[cfg(test)]
mod pu_tests;
#[cfg(test)]
mod tests;
