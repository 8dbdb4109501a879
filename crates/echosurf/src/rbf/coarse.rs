//! Coarse level of the two-level Schwarz preconditioner (Beatson, Light & Billings 2000; Carr et al. 2001).
//!
//! The local (leaf) solves of the restricted additive Schwarz preconditioner only see a few hundred
//! neighbouring samples, so they cannot carry the smooth, global part of the spline: without a coarse
//! level the Krylov iteration count grows with N. The coarse level is a well-spread subset C of the
//! samples (the point nearest each tree node's centroid at the depth where nodes hold about N / |C|
//! samples) with a dense smoothing-spline solve on C, applied *multiplicatively before* the local
//! corrections: `l_C = A_CC^-1 r_C`, `r' = r - (A - wI) E l_C` (the product of the coarse coefficients
//! with every sample, by a treecode over the coarse points), then the local solves act on `r'`.
//!
//! Smoothing on C: the smoothing spline minimises `sum_i (f_i - s(x_i))^2 + rho |s|^2` with `w ~ rho`
//! (ALGORITHMS.md §1); the same function sampled N / |C| times more sparsely has a data term N / |C|
//! times smaller, so the coarse fit uses `w_C = w N / |C|` to stay the same smoother (measured: fewer
//! iterations than `w_C = w` on speckled data, where interpolating every coarse residual is wild).

use faer::Mat;
use faer::linalg::solvers::{PartialPivLu, Solve};
use glam::DVec3;
use rayon::prelude::*;

use super::tree::{InteractionLists, Tree, Treecode, TreecodeParams};
use super::trend::TrendBasis;
use crate::{Error, Result};

/// Leaf size of the treecode over the coarse points: small, because the coarse points are sparse and
/// their near field is summed directly for every fine sample.
const COARSE_LEAF: usize = 16;
/// Relative accuracy of the coarse product: it only has to be a fixed linear map close to the exact one.
const COARSE_PRODUCT_ACCURACY: f64 = 1e-3;

pub(crate) struct CoarseLevel {
    /// Fine-tree positions of the coarse points.
    pub index: Vec<u32>,
    lu: PartialPivLu<f64>,
    rank: usize,
    fine_smoothing: f64,
    treecode: Treecode,
    lists: InteractionLists,
}

impl CoarseLevel {
    /// Coarse level of about `target` points over the fine `tree`, or None when the problem is so small
    /// that the local solves already see most of it.
    pub fn new(tree: &Tree, target: usize, smoothing: f64) -> Result<Option<CoarseLevel>> {
        let n = tree.len();
        if target < 8 || n < 4 * target {
            return Ok(None);
        }
        let index = spread_subset(tree, target);
        let m = index.len();
        let pts: Vec<DVec3> = index.iter().map(|&i| tree.point(i as usize)).collect();
        let basis = TrendBasis::new(&pts);
        let r = basis.rank();
        if m <= r + 4 {
            return Ok(None);
        }
        let u = basis.matrix(&pts);
        let exponent: f64 = std::env::var("CWE").ok().and_then(|v| v.parse().ok()).unwrap_or(1.0);
        let coarse_smoothing = smoothing * (n as f64 / m as f64).powf(exponent);
        let size = m + r;
        let a = Mat::<f64>::from_fn(size, size, |i, j| {
            if i < m && j < m {
                (pts[i] - pts[j]).length() - if i == j { coarse_smoothing } else { 0.0 }
            } else if i < m {
                u[i * r + (j - m)]
            } else if j < m {
                u[j * r + (i - m)]
            } else {
                0.0
            }
        });
        let lu = sequential(|| a.partial_piv_lu());
        let treecode = Treecode::new(
            &pts,
            TreecodeParams {
                leaf_size: COARSE_LEAF,
                theta: std::env::var("CTHETA").ok().and_then(|v| v.parse().ok()).unwrap_or(0.5),
                nodes_per_side: std::env::var("CP").ok().and_then(|v| v.parse().ok()).unwrap_or(6),
            },
        );
        let lists = treecode.interactions(tree);
        let (near, far) = lists.work(&treecode, tree);
        if std::env::var_os("RBF_TRACE").is_some() {
            eprintln!("[coarse] per target {:.0}+{:.0}", near as f64 / n as f64, far as f64 / n as f64);
        }
        let level = CoarseLevel {
            index,
            lu,
            rank: r,
            fine_smoothing: smoothing,
            treecode,
            lists,
        };
        // A singular coarse system shows as non-finite coefficients for a generic right-hand side.
        let probe: Vec<f64> = (0..n).map(|i| ((i * 7919) % 101) as f64 - 50.0).collect();
        if level.solve(&probe).iter().any(|v| !v.is_finite()) {
            return Err(Error::Numerical(
                "singular coarse RBF system in the preconditioner (duplicate points?)".into(),
            ));
        }
        Ok(Some(level))
    }

    pub fn len(&self) -> usize {
        self.index.len()
    }

    /// Coarse coefficients for the fine (tree-ordered) residual `r`, in `index` order.
    pub fn solve(&self, r: &[f64]) -> Vec<f64> {
        let m = self.index.len();
        let mut rhs = Mat::<f64>::from_fn(m + self.rank, 1, |i, _| {
            if i < m {
                r[self.index[i] as usize]
            } else {
                0.0
            }
        });
        sequential(|| self.lu.solve_in_place(rhs.as_mut()));
        (0..m).map(|i| rhs[(i, 0)]).collect()
    }

    /// `out = (A - wI) E l` on every fine sample (tree order), `E` placing the coarse coefficients `l`
    /// at their samples.
    pub fn product(&self, tree: &Tree, l: &[f64], out: &mut [f64]) {
        let q = self.treecode.tree.to_tree_order(l);
        let proxies = self.treecode.upward(&q);
        self.treecode
            .evaluate(tree, &self.lists, &q, &proxies, out, None);
        for (&i, &li) in self.index.iter().zip(l) {
            out[i as usize] -= self.fine_smoothing * li;
        }
    }

    pub fn memory_bytes(&self) -> usize {
        let size = self.index.len() + self.rank;
        size * size * 8 + self.treecode.memory_bytes() + self.lists.memory_bytes() + size * 4
    }
}

/// Runs `f` with faer's parallelism off: its blocked kernels split work by thread count, which changes
/// rounding, and fits must be bit-identical on any number of threads.
fn sequential<T>(f: impl FnOnce() -> T) -> T {
    let previous = faer::get_global_parallelism();
    faer::set_global_parallelism(faer::Par::Seq);
    let out = f();
    faer::set_global_parallelism(previous);
    out
}

/// About `target` well-spread samples (fine-tree positions): a median-split tree over the samples with
/// leaves of at most `N / target` samples, and from each leaf the sample nearest to its centroid. Median
/// splits give leaves of equal counts, so the subset follows the sampling density.
fn spread_subset(tree: &Tree, target: usize) -> Vec<u32> {
    let group = tree.len().div_ceil(target.max(1)).max(1);
    let points: Vec<DVec3> = (0..tree.len()).map(|i| tree.point(i)).collect();
    let selection = Tree::build(&points, group);
    let mut index: Vec<u32> = selection
        .leaves
        .par_iter()
        .filter_map(|&ni| {
            let node = &selection.nodes[ni as usize];
            if node.len() == 0 {
                return None;
            }
            let range = node.start as usize..node.end as usize;
            let centroid = range
                .clone()
                .fold(DVec3::ZERO, |a, i| a + selection.point(i))
                / node.len() as f64;
            let mut best = (f64::INFINITY, node.start as usize);
            for i in range {
                let d = (selection.point(i) - centroid).length_squared();
                if d < best.0 {
                    best = (d, i);
                }
            }
            Some(selection.order[best.1])
        })
        .collect();
    index.sort_unstable();
    index
}
