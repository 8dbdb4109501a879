//! Fast solve of `(A - wI) l + U d = f, U^T l = 0`: right-preconditioned restarted GMRES on the projected
//! system `P (A - wI) P l = P f` (P = I - U U^T, U the orthonormal trend basis), with the treecode product
//! (from [`FMM_MIN_POINTS`] samples the fast multipole method, [`super::fmm`]) and a two-level Schwarz
//! preconditioner (Beatson, Light & Billings 2000):
//! - local level, restricted additive Schwarz: every tree leaf is a subdomain, extended by its nearest
//!   neighbours; a dense local RBF solve (with its own reduced trend) is factored once and only the rows of
//!   the leaf's own points are kept (as f32, to save memory);
//! - coarse level ([`super::coarse`]): a solve on N / 8 well-spread samples, applied before the local
//!   corrections, so the iteration count grows slowly with N. Up to 2,048 points it is factored; a larger
//!   coarse level is preconditioned the same way, recursively (docs/decisions/0049-nested-coarse-level.md).
//!
//! The iteration stops when the system residual `max_i |f_i - s(x_i) + w l_i|` (grey levels; equal to the
//! data misfit at w = 0) is below the fitting accuracy, measured with the accurate treecode product (the
//! model's evaluation accuracy). The Arnoldi products use a cheaper treecode (see [`inner_params`]) when
//! its error on the first solution-like vector is within a few times the accuracy, and the accurate one
//! otherwise.
//!
//! Measured (ultrasound-like samples, w = 1, accuracy 2, eval accuracy 1e-4; 2 shared cores giving about
//! one core's throughput): one-level Schwarz needed 28 iterations / 2.4 s at 10k and 633 s at 100k (issue
//! #5), one accurate product per iteration (32k kernel terms per sample at 100k). Now: 8 iterations /
//! 0.7 s at 10k, 17 iterations / 30-40 s at 100k, where the treecode's products were ~85 % of the time;
//! the FMM products take about a quarter of that (docs/decisions/0053-fmm-product.md).

use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::time::Instant;

use glam::DVec3;
use rayon::prelude::*;

use super::coarse::{CoarseConfig, CoarseLevel};
use super::direct::SequentialLu;
use super::fmm::{Fmm, FmmParams};
use super::tree::{InteractionLists, Tree, Treecode, TreecodeParams, split_by_sizes};
use super::trend::{TrendBasis, project_out, trend_coefficients};
use crate::progress::Progress;
use crate::{Error, Result};

/// Extra neighbours added to each leaf to form its overlapping subdomain, up to
/// [`OVERLAP_REFERENCE_POINTS`] samples. Measured at 10k samples with the coarse level: 48 -> 19
/// iterations, 96 -> 12, 160 -> 6 (100k: 96 -> 28, 160 -> 22 before peeking).
const OVERLAP_POINTS: usize = 160;
/// Above this many samples the overlap grows in proportion to N, so a subdomain keeps its volume as the
/// samples get denser (docs/decisions/0059-subdomains-grow-with-n.md).
const OVERLAP_REFERENCE_POINTS: usize = 100_000;
/// Largest overlap: the local factorisations cost the cube of the subdomain size.
const OVERLAP_MAX_POINTS: usize = 480;
const RESTART: usize = 40;
/// Separation and Chebyshev nodes of the cheap products: the Arnoldi steps' ([`inner_params`]) and the
/// Richardson residual of a nested coarse level.
pub(super) const CHEAP_PRODUCT_THETA: f64 = 0.7;
pub(super) const CHEAP_PRODUCT_NODES: usize = 6;
/// The cheap Arnoldi product is used only when its error on a solution-like vector is at most this many
/// times the fitting accuracy (docs/decisions/0043-arnoldi-product-accuracy.md).
const CHEAP_PRODUCT_MAX_ERROR_RATIO: f64 = 4.0;
/// From this many samples the products use the fast multipole method ([`super::fmm`]), at the
/// treecode's accuracy, for every Arnoldi step; below it, building its translation table costs more
/// than it saves (docs/decisions/0053-fmm-product.md).
pub(crate) const FMM_MIN_POINTS: usize = 20_000;

/// Where the global fast solver spent its time (wall-clock seconds) and how often.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct FastBreakdown {
    /// Treecodes, interaction lists and the preconditioner (local and coarse factorisations).
    pub setup_seconds: f64,
    pub coarse_points: usize,
    /// Points of each coarse level, largest first: all but the last are preconditioned themselves
    /// rather than factored (levels over 2,048 points).
    pub coarse_level_points: Vec<usize>,
    /// Products with the accurate treecode (one per true-residual check).
    pub accurate_products: usize,
    pub accurate_product_seconds: f64,
    /// Products with the cheap inner treecode: one to measure its error, then one per GMRES iteration
    /// unless that error was too large ([`FastBreakdown::accurate_arnoldi`]).
    pub inner_products: usize,
    pub inner_product_seconds: f64,
    pub preconditioner_applications: usize,
    pub preconditioner_seconds: f64,
    /// Whether the Arnoldi steps used the accurate product (the cheap one erred by too much).
    pub accurate_arnoldi: bool,
}

/// Call count and accumulated time of one operation.
#[derive(Default)]
struct Counter {
    nanos: AtomicU64,
    calls: AtomicU64,
}

impl Counter {
    fn time<T>(&self, f: impl FnOnce() -> T) -> T {
        let start = Instant::now();
        let out = f();
        self.nanos
            .fetch_add(start.elapsed().as_nanos() as u64, Relaxed);
        self.calls.fetch_add(1, Relaxed);
        out
    }
    fn seconds(&self) -> f64 {
        self.nanos.load(Relaxed) as f64 * 1e-9
    }
    fn calls(&self) -> usize {
        self.calls.load(Relaxed) as usize
    }
}

/// The assembled fast system, in tree order.
pub(crate) struct FastSystem {
    /// The samples' tree: their order, the subdomains and, below [`FMM_MIN_POINTS`], the product.
    pub treecode: Treecode,
    accurate_product: AccurateProduct,
    /// Cheaper, less accurate product for the Arnoldi steps (same tree, so the same point order).
    inner: Option<(Treecode, InteractionLists)>,
    smoothing: f64,
    /// Trend basis values, row-major `n x rank`, tree order.
    u: Vec<f64>,
    rank: usize,
    precond: Schwarz,
    setup_seconds: f64,
    accurate: Counter,
    inner_counter: Counter,
    precond_counter: Counter,
}

impl std::fmt::Debug for FastSystem {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FastSystem").finish_non_exhaustive()
    }
}

pub(super) struct Schwarz {
    /// Per leaf: domain points (tree positions) and the `inner x domain` rows of the local inverse.
    domains: Vec<(Vec<u32>, Vec<f32>)>,
    leaf_sizes: Vec<usize>,
    coarse: Option<CoarseLevel>,
}

/// How the accurate product `(A - wI) l` is computed.
enum AccurateProduct {
    /// Target leaves against the treecode's clusters, through these interaction lists.
    Treecode(InteractionLists),
    /// The fast multipole method over the same samples (tree order as its input order).
    Fmm(Box<Fmm>),
}

/// The first Arnoldi step, computed while checking the cheap product ([`FastSystem::first_step`]).
struct FirstStep {
    z: Vec<f64>,
    /// `(A - wI) z` by the product the Arnoldi steps use.
    product: Vec<f64>,
    accurate_arnoldi: bool,
}

/// Outcome of an iterative solve.
#[derive(Debug, Clone)]
pub(crate) struct Solution {
    /// Coefficients in input order.
    pub coefficients: Vec<f64>,
    /// Trend-basis coefficients.
    pub trend: Vec<f64>,
    pub iterations: usize,
    pub max_residual: f64,
    pub rms_residual: f64,
    pub breakdown: FastBreakdown,
    /// Most Krylov basis vectors held at once (each `8 N` bytes).
    pub krylov_vectors: usize,
}

/// Parameters of the inner (Arnoldi) product: separation 0.7 and at most 6 Chebyshev nodes per side.
/// Measured on 10k ultrasound-like samples (relative to the exact product of realistic coefficients):
/// theta 0.5 / 8 nodes (the default accuracy 1e-4) errs by 0.007 grey levels at 32k kernel terms per
/// target at 100k samples; theta 0.7 / 6 nodes errs by ~1.5 grey levels at 10k terms. The inner error
/// only slows convergence slightly (10k: 7 -> 10 iterations), because every convergence decision uses the
/// accurate product. Cheaper choices cost more than they save at 100k samples: theta 0.85 / 6 nodes 28
/// iterations, 0.7 / 5 27, 0.6 / 5 17 at the same time (0.7 / 6: 17). None when the accurate product is
/// already at least as cheap.
pub(crate) fn inner_params(outer: TreecodeParams) -> Option<TreecodeParams> {
    let inner = TreecodeParams {
        theta: outer.theta.max(CHEAP_PRODUCT_THETA),
        nodes_per_side: outer.nodes_per_side.min(CHEAP_PRODUCT_NODES),
        ..outer
    };
    (inner != outer).then_some(inner)
}

impl FastSystem {
    pub fn new(
        points: &[DVec3],
        smoothing: f64,
        basis: &TrendBasis,
        params: TreecodeParams,
    ) -> Result<FastSystem> {
        Self::with_levels(
            points,
            smoothing,
            basis,
            params,
            Some(CoarseConfig::default()),
            FMM_MIN_POINTS,
        )
    }

    /// As [`FastSystem::new`] with the coarse levels built by `coarse` (None drops them: one-level
    /// Schwarz, for tests) and the FMM products (the system's and the coarse level's) from
    /// `fmm_min_points` samples.
    pub fn with_levels(
        points: &[DVec3],
        smoothing: f64,
        basis: &TrendBasis,
        params: TreecodeParams,
        coarse: Option<CoarseConfig>,
        fmm_min_points: usize,
    ) -> Result<FastSystem> {
        let start = Instant::now();
        let treecode = Treecode::new(points, params);
        let use_fmm = points.len() >= fmm_min_points;
        let lists = (!use_fmm).then(|| treecode.interactions(&treecode.tree));
        let inner = inner_params(params).filter(|_| !use_fmm).map(|p| {
            let tc = Treecode::new(points, p);
            // Same points and leaf size: the same median splits, so the same order.
            debug_assert_eq!(tc.tree.order, treecode.tree.order);
            let lists = tc.interactions(&tc.tree);
            (tc, lists)
        });
        let tree_points = treecode.tree.points();
        let u = basis.matrix(&tree_points);
        let coarse = coarse.map(|c| CoarseConfig {
            fmm_min_points,
            ..c
        });
        let precond = Schwarz::new(&treecode.tree, smoothing, coarse.as_ref())?;
        let accurate_product = match lists {
            Some(lists) => AccurateProduct::Treecode(lists),
            None => AccurateProduct::Fmm(Box::new(Fmm::new(
                &tree_points,
                FmmParams::matching(params),
            ))),
        };
        Ok(FastSystem {
            treecode,
            accurate_product,
            inner,
            smoothing,
            u,
            rank: basis.rank(),
            precond,
            setup_seconds: start.elapsed().as_secs_f64(),
            accurate: Counter::default(),
            inner_counter: Counter::default(),
            precond_counter: Counter::default(),
        })
    }

    fn breakdown(&self, accurate_arnoldi: bool) -> FastBreakdown {
        FastBreakdown {
            accurate_arnoldi,
            setup_seconds: self.setup_seconds,
            coarse_points: self.precond.coarse.as_ref().map_or(0, |c| c.len()),
            coarse_level_points: self.precond.coarse_level_sizes(),
            accurate_products: self.accurate.calls(),
            accurate_product_seconds: self.accurate.seconds(),
            inner_products: self.inner_counter.calls(),
            inner_product_seconds: self.inner_counter.seconds(),
            preconditioner_applications: self.precond_counter.calls(),
            preconditioner_seconds: self.precond_counter.seconds(),
        }
    }

    /// The preconditioner `M^-1 r`, projected onto the trend's complement.
    fn precondition(&self, r: &[f64], z: &mut [f64]) {
        self.precond_counter
            .time(|| self.precond.apply(&self.treecode.tree, r, z));
        self.project(z);
    }

    fn len(&self) -> usize {
        self.treecode.tree.len()
    }

    /// `(A - wI) l` for tree-ordered `l`, accurate product.
    fn apply(&self, l: &[f64], out: &mut [f64]) {
        self.accurate.time(|| match &self.accurate_product {
            AccurateProduct::Treecode(lists) => {
                product(&self.treecode, lists, self.smoothing, l, out)
            }
            AccurateProduct::Fmm(fmm) => {
                fmm.product(l, out);
                subtract_smoothing(self.smoothing, l, out);
            }
        });
    }

    /// `(A - wI) l` with the inner (cheap) product, or the accurate one without an inner treecode.
    fn apply_inner(&self, l: &[f64], out: &mut [f64]) {
        match &self.inner {
            Some((tc, lists)) => self
                .inner_counter
                .time(|| product(tc, lists, self.smoothing, l, out)),
            None => self.apply(l, out),
        }
    }

    /// `U^T v`, summed in fixed order.
    fn trend_coefficients(&self, v: &[f64]) -> Vec<f64> {
        trend_coefficients(&self.u, self.rank, v)
    }

    fn project(&self, v: &mut [f64]) {
        project_out(v, &self.u, self.rank);
    }

    /// The first Arnoldi step's preconditioned vector `z = M^-1 e` (`e` the initial residual) and its
    /// product, plus whether the cheap product errs on it by more than
    /// [`CHEAP_PRODUCT_MAX_ERROR_RATIO`] times the accuracy. Rough data at w = 0 has large, alternating
    /// coefficients; GMRES on such a product stalls near its error and crawls by restarts, so then every
    /// Arnoldi step uses the accurate product. `z` solves the system approximately, so it is the kind of
    /// vector whose product error limits the solve; the check costs one product of the other kind.
    fn first_step(&self, e: &[f64], accuracy: f64) -> FirstStep {
        let n = self.len();
        let mut z = vec![0.0; n];
        self.precondition(e, &mut z);
        let mut accurate = vec![0.0; n];
        self.apply(&z, &mut accurate);
        let Some((tc, lists)) = &self.inner else {
            return FirstStep {
                z,
                product: accurate,
                accurate_arnoldi: true,
            };
        };
        let mut cheap = vec![0.0; n];
        self.inner_counter
            .time(|| product(tc, lists, self.smoothing, &z, &mut cheap));
        // NaN-propagating maximum, unlike f64::max.
        let error = accurate.iter().zip(&cheap).fold(0.0f64, |m, (a, b)| {
            let d = (a - b).abs();
            if d.is_nan() || d > m { d } else { m }
        });
        // A NaN error (a non-finite product) also selects the accurate product.
        let accurate_arnoldi = error.is_nan() || error > CHEAP_PRODUCT_MAX_ERROR_RATIO * accuracy;
        FirstStep {
            z,
            product: if accurate_arnoldi { accurate } else { cheap },
            accurate_arnoldi,
        }
    }

    /// Solves for input-ordered `values`, stopping when the max residual is below `accuracy`.
    /// `initial` (input order) warm-starts the iteration.
    ///
    /// Restarted GMRES, right-preconditioned. The Arnoldi products use the cheap inner treecode where it
    /// is close enough (see [`FastSystem::first_step`]); the residual that decides
    /// convergence always uses the accurate one. When the GMRES estimate of the rms
    /// residual reaches the current target, the iterate is formed and its true residual measured
    /// ("peek"): converged -> done; otherwise the rms target is lowered (the max norm lags the rms) and
    /// the same Krylov space is extended, unless the true residual has drifted from the estimate (the
    /// inner product's error dominates), in which case the cycle restarts from the true residual (a step
    /// of iterative refinement). Peeking instead of restarting keeps the Krylov space, so fewer
    /// iterations are needed (docs/decisions/0035-figures-from-code-comments.md).
    pub fn solve(
        &self,
        values: &[f64],
        accuracy: f64,
        max_iterations: usize,
        initial: Option<&[f64]>,
        progress: &dyn Progress,
    ) -> Result<Solution> {
        let n = self.len();
        let sqrt_n = (n as f64).sqrt();
        let f = self.treecode.tree.to_tree_order(values);
        let mut x = match initial {
            Some(init) => {
                let mut x = self.treecode.tree.to_tree_order(init);
                self.project(&mut x);
                x
            }
            None => vec![0.0; n],
        };
        // `work` holds (A - wI) x of the latest true residual (for the trend at the end).
        let mut work = vec![0.0; n];
        // True residual e = P (f - (A - wI) x): with d = U^T (f - (A - wI) x) it is the system residual.
        let residual = |x: &[f64], work: &mut Vec<f64>| -> Vec<f64> {
            if x.iter().all(|&v| v == 0.0) {
                work.fill(0.0); // a cold start needs no product
            } else {
                self.apply(x, work);
            }
            let mut e: Vec<f64> = f.iter().zip(work.iter()).map(|(a, b)| a - b).collect();
            self.project(&mut e);
            e
        };
        let mut e = residual(&x, &mut work);
        let mut iterations = 0;
        let mut krylov_vectors = 0;
        let mut max_abs = max_norm(&e);
        // Peek at the true residual once the GMRES estimate (rms) falls below this.
        // The max norm runs ~3-6x the rms on speckled data: a first target of accuracy / 5 saves a
        // peek (an accurate product) at 10k and 100k samples without changing the iterate.
        let mut check_rms = accuracy * 0.2;
        let mut z = vec![0.0; n];
        let mut w = vec![0.0; n];
        let mut first = (max_abs > accuracy).then(|| self.first_step(&e, accuracy));
        let accurate_arnoldi = first.as_ref().is_some_and(|f| f.accurate_arnoldi);
        progress.start("fit: iterations", max_iterations as u64);
        'cycles: while max_abs > accuracy {
            if iterations >= max_iterations {
                progress.finish();
                return Err(Error::Numerical(format!(
                    "RBF solve did not reach the fitting accuracy {accuracy} in {max_iterations} \
                     iterations (max residual {max_abs:.4}); raise the accuracy or the smoothing"
                )));
            }
            let beta = norm(&e);
            let mut basis: Vec<Vec<f64>> = vec![e.iter().map(|v| v / beta).collect()];
            let mut h: Vec<Vec<f64>> = Vec::new(); // column j has j + 2 entries
            let mut cs: Vec<(f64, f64)> = Vec::new();
            let mut g = vec![beta];
            let mut k = 0;
            loop {
                if let Some(step) = first.take() {
                    // basis[0] = e / beta: the check's vector and product, scaled.
                    for ((zi, wi), (a, b)) in z
                        .iter_mut()
                        .zip(w.iter_mut())
                        .zip(step.z.iter().zip(&step.product))
                    {
                        *zi = a / beta;
                        *wi = b / beta;
                    }
                } else {
                    self.precondition(&basis[k], &mut z);
                    if accurate_arnoldi {
                        self.apply(&z, &mut w);
                    } else {
                        self.apply_inner(&z, &mut w);
                    }
                }
                self.project(&mut w);
                let mut col = vec![0.0; k + 2];
                // Modified Gram-Schmidt, twice for stability with this many vectors.
                for _pass in 0..2 {
                    for (j, vj) in basis.iter().enumerate() {
                        let c = dot(&w, vj);
                        col[j] += c;
                        axpy(-c, vj, &mut w);
                    }
                }
                let hn = norm(&w);
                col[k + 1] = hn;
                for (j, &(c, s)) in cs.iter().enumerate() {
                    let (a, b) = (col[j], col[j + 1]);
                    col[j] = c * a + s * b;
                    col[j + 1] = -s * a + c * b;
                }
                let (a, b) = (col[k], col[k + 1]);
                let rho = a.hypot(b);
                let (c, s) = if rho == 0.0 {
                    (1.0, 0.0)
                } else {
                    (a / rho, b / rho)
                };
                col[k] = rho;
                col[k + 1] = 0.0;
                cs.push((c, s));
                let gk = g[k];
                g[k] = c * gk;
                g.push(-s * gk);
                h.push(col);
                iterations += 1;
                k += 1;
                progress.advance(iterations as u64);
                let estimate_rms = g[k].abs() / sqrt_n;
                let cycle_over = hn == 0.0 || k >= RESTART || iterations >= max_iterations;
                if cycle_over || estimate_rms <= check_rms {
                    // Form the iterate x + M^-1 V y and measure its true residual.
                    let y = back_substitute(&h, &g, k);
                    let mut combo = vec![0.0; n];
                    for (j, vj) in basis.iter().take(k).enumerate() {
                        axpy(y[j], vj, &mut combo);
                    }
                    self.precondition(&combo, &mut z);
                    let mut x_try = x.clone();
                    axpy(1.0, &z, &mut x_try);
                    let e_try = residual(&x_try, &mut work);
                    let max_try = max_norm(&e_try);
                    if !max_try.is_finite() {
                        progress.finish();
                        return Err(Error::Numerical(
                            "RBF solve diverged (non-finite residual)".into(),
                        ));
                    }
                    let rms_try = norm(&e_try) / sqrt_n;
                    if max_try > accuracy && rms_try <= check_rms {
                        // The max norm lags the rms: ask for a proportionally smaller rms next time.
                        check_rms = rms_try * (accuracy / max_try).min(0.5);
                    } else if max_try > accuracy {
                        check_rms *= 0.5;
                    }
                    let drifted = rms_try > 2.0 * estimate_rms;
                    if max_try <= accuracy || cycle_over || drifted {
                        x = x_try;
                        e = e_try;
                        max_abs = max_try;
                        continue 'cycles;
                    }
                    // Keep extending this Krylov space from the cycle's start `x`; `work` is
                    // recomputed by the next peek.
                }
                basis.push(w.iter().map(|v| v / hn).collect());
                krylov_vectors = krylov_vectors.max(basis.len());
            }
        }
        progress.finish();
        // Trend: d = U^T (f - (A - wI) x); `work` holds (A - wI) x from the last residual.
        let rest: Vec<f64> = f.iter().zip(&work).map(|(a, b)| a - b).collect();
        let trend = self.trend_coefficients(&rest);
        let rms_residual = norm(&e) / sqrt_n;
        Ok(Solution {
            coefficients: self.treecode.tree.to_input_order(&x),
            trend,
            iterations,
            max_residual: max_abs,
            rms_residual,
            breakdown: self.breakdown(accurate_arnoldi),
            krylov_vectors: krylov_vectors.max(1),
        })
    }

    pub fn memory_bytes(&self) -> usize {
        self.treecode.memory_bytes()
            + match &self.accurate_product {
                AccurateProduct::Treecode(lists) => lists.memory_bytes(),
                AccurateProduct::Fmm(fmm) => fmm.memory_bytes() + fmm.product_bytes(),
            }
            + self.u.len() * 8
            + self.precond.memory_bytes()
            + self
                .inner
                .as_ref()
                .map_or(0, |(tc, lists)| tc.memory_bytes() + lists.memory_bytes())
    }
}

impl Schwarz {
    /// The preconditioner of the system on `tree`'s points: a subdomain per leaf, and with `coarse` the
    /// coarse level (itself preconditioned this way when it is too large to factor).
    pub(super) fn new(
        tree: &Tree,
        smoothing: f64,
        coarse: Option<&CoarseConfig>,
    ) -> Result<Schwarz> {
        let n = tree.len();
        let overlap = overlap_points(n);
        let leaves = &tree.leaves;
        let domains: Vec<Option<(Vec<u32>, Vec<f32>)>> = leaves
            .par_iter()
            .map(|&li| {
                let leaf = &tree.nodes[li as usize];
                let inner: Vec<u32> = (leaf.start..leaf.end).collect();
                let centroid = inner
                    .iter()
                    .fold(DVec3::ZERO, |a, &i| a + tree.point(i as usize))
                    / inner.len().max(1) as f64;
                let want = (inner.len() + overlap).min(n);
                let mut domain = inner.clone();
                for j in tree.nearest(centroid, want) {
                    if domain.len() >= want {
                        break;
                    }
                    if j < leaf.start || j >= leaf.end {
                        domain.push(j);
                    }
                }
                local_inverse_rows(tree, &domain, inner.len(), smoothing).map(|b| (domain, b))
            })
            .collect();
        let mut out = Vec::with_capacity(domains.len());
        for d in domains {
            out.push(d.ok_or_else(|| {
                Error::Numerical(
                    "singular local RBF system in the preconditioner (duplicate points?)".into(),
                )
            })?);
        }
        let leaf_sizes = leaves
            .iter()
            .map(|&l| tree.nodes[l as usize].len())
            .collect();
        let coarse = match coarse {
            Some(config) => CoarseLevel::new(tree, config, smoothing)?,
            None => None,
        };
        Ok(Schwarz {
            domains: out,
            leaf_sizes,
            coarse,
        })
    }

    /// Bytes held: the local inverse rows and the coarse levels.
    pub(super) fn memory_bytes(&self) -> usize {
        self.domains
            .iter()
            .map(|(d, b)| d.len() * 4 + b.len() * 4)
            .sum::<usize>()
            + self.coarse.as_ref().map_or(0, |c| c.memory_bytes())
    }

    /// Points of each coarse level, largest first (empty without one).
    pub(super) fn coarse_level_sizes(&self) -> Vec<usize> {
        self.coarse.as_ref().map_or(Vec::new(), |c| c.level_sizes())
    }

    /// Two-level application: coarse solve, residual update, then the local corrections.
    pub(super) fn apply(&self, tree: &Tree, r: &[f64], z: &mut [f64]) {
        match &self.coarse {
            None => self.apply_local(r, z),
            Some(coarse) => {
                let lc = coarse.solve(r);
                let mut rest = vec![0.0; r.len()];
                coarse.product(tree, &lc, &mut rest);
                rest.par_chunks_mut(4096)
                    .zip(r.par_chunks(4096))
                    .for_each(|(a, b)| {
                        for (ai, bi) in a.iter_mut().zip(b) {
                            *ai = bi - *ai;
                        }
                    });
                self.apply_local(&rest, z);
                for (&i, &l) in coarse.index.iter().zip(&lc) {
                    z[i as usize] += l;
                }
            }
        }
    }

    fn apply_local(&self, r: &[f64], z: &mut [f64]) {
        let chunks = split_by_sizes(z, &self.leaf_sizes);
        chunks
            .into_par_iter()
            .zip(self.domains.par_iter())
            .for_each(|(out, (domain, b))| {
                let m = domain.len();
                let local: Vec<f64> = domain.iter().map(|&j| r[j as usize]).collect();
                for (i, o) in out.iter_mut().enumerate() {
                    let row = &b[i * m..(i + 1) * m];
                    let mut s = 0.0;
                    for (bij, lj) in row.iter().zip(&local) {
                        s += *bij as f64 * lj;
                    }
                    *o = s;
                }
            });
    }
}

/// Neighbours added to each leaf's subdomain for a system over `n` points: [`OVERLAP_POINTS`] up to
/// [`OVERLAP_REFERENCE_POINTS`], then in proportion to `n`, at most [`OVERLAP_MAX_POINTS`].
pub(super) fn overlap_points(n: usize) -> usize {
    let scaled = (OVERLAP_POINTS as u128 * n as u128 / OVERLAP_REFERENCE_POINTS as u128) as usize;
    scaled.clamp(OVERLAP_POINTS, OVERLAP_MAX_POINTS)
}

/// Rows (for the first `inner` domain points) of the inverse of the local saddle matrix, restricted to the
/// point columns. The matrix is symmetric, so these rows are the solutions for unit right-hand sides.
fn local_inverse_rows(
    tree: &super::tree::Tree,
    domain: &[u32],
    inner: usize,
    smoothing: f64,
) -> Option<Vec<f32>> {
    let pts: Vec<DVec3> = domain.iter().map(|&i| tree.point(i as usize)).collect();
    let basis = TrendBasis::new(&pts);
    let m = pts.len();
    let r = basis.rank();
    let u = basis.matrix(&pts);
    let size = m + r;
    let a = faer::Mat::<f64>::from_fn(size, size, |i, j| match (i < m, j < m) {
        (true, true) => (pts[i] - pts[j]).length() - if i == j { smoothing } else { 0.0 },
        (true, false) => u[i * r + j - m],
        (false, true) => u[j * r + i - m],
        (false, false) => 0.0,
    });
    // Blocked LU (faer, sequential: each leaf is one parallel task); the unit right-hand sides of the
    // leaf's own points.
    let lu = SequentialLu::new_nonsingular(a)?;
    let mut b = faer::Mat::<f64>::from_fn(size, inner, |i, j| if i == j { 1.0 } else { 0.0 });
    lu.solve_in_place(b.as_mut());
    let mut rows = vec![0.0f32; inner * m];
    for i in 0..inner {
        for j in 0..m {
            rows[i * m + j] = b[(j, i)] as f32;
        }
    }
    rows.iter().all(|v| v.is_finite()).then_some(rows)
}

/// Solves the `k x k` upper-triangular GMRES system `H y = g` (column-stored `h`).
fn back_substitute(h: &[Vec<f64>], g: &[f64], k: usize) -> Vec<f64> {
    let mut y = vec![0.0; k];
    for i in (0..k).rev() {
        let mut s = g[i];
        for j in i + 1..k {
            s -= h[j][i] * y[j];
        }
        y[i] = if h[i][i] != 0.0 { s / h[i][i] } else { 0.0 };
    }
    y
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    // Fixed-order chunked sum: parallel, yet independent of the thread count.
    a.par_chunks(4096)
        .zip(b.par_chunks(4096))
        .map(|(x, y)| x.iter().zip(y).map(|(p, q)| p * q).sum::<f64>())
        .collect::<Vec<f64>>()
        .iter()
        .sum()
}

fn norm(a: &[f64]) -> f64 {
    dot(a, a).sqrt()
}

fn max_norm(a: &[f64]) -> f64 {
    a.iter().fold(0.0f64, |m, v| m.max(v.abs()))
}

fn axpy(alpha: f64, x: &[f64], y: &mut [f64]) {
    y.par_chunks_mut(4096)
        .zip(x.par_chunks(4096))
        .for_each(|(yc, xc)| {
            for (yi, xi) in yc.iter_mut().zip(xc) {
                *yi += alpha * xi;
            }
        });
}

/// `out = (A - wI) l` with treecode `tc`.
pub(super) fn product(
    tc: &Treecode,
    lists: &InteractionLists,
    smoothing: f64,
    l: &[f64],
    out: &mut [f64],
) {
    let proxies = tc.upward(l);
    tc.evaluate(&tc.tree, lists, l, &proxies, out, None);
    subtract_smoothing(smoothing, l, out);
}

/// `out -= w l`: the smoothing term of `(A - wI) l`.
fn subtract_smoothing(smoothing: f64, l: &[f64], out: &mut [f64]) {
    for (o, &li) in out.iter_mut().zip(l) {
        *o -= smoothing * li;
    }
}
