//! Coarse level of the two-level Schwarz preconditioner (Beatson, Light & Billings 2000; Carr et al. 2001).
//!
//! The local (leaf) solves of the restricted additive Schwarz preconditioner only see a few hundred
//! neighbouring samples, so they cannot carry the smooth, global part of the spline: without a coarse
//! level the Krylov iteration count grows with N. The coarse level is a well-spread subset C of the
//! samples (the point nearest each tree node's centroid at the depth where nodes hold about N / |C|
//! samples) with a smoothing-spline solve on C (dense up to 2,048 points; above, approximately by C's own
//! two-level Schwarz preconditioner, see [`CoarseConfig`]), applied *multiplicatively before* the local
//! corrections: `l_C = A_CC^-1 r_C`, `r' = r - (A - wI) E l_C` (the product of the coarse coefficients
//! with every sample, by a treecode over the coarse points or, from [`CoarseConfig::fmm_min_points`]
//! samples, by a fast multipole method charged at them), then the local solves act on `r'`.
//!
//! Smoothing on C: the coarse matrix is the principal submatrix `A_CC - wI` of the fine system (Beatson,
//! Light & Billings 2000). Scaling w by N / |C| (the same smoothing functional on sparser data) was
//! measured worse on speckled 10k samples with |C| = 200: 8 iterations with w, 9 with w sqrt(N/|C|), 11
//! with w N / |C|.

use faer::Mat;
use glam::DVec3;
use rayon::prelude::*;

use super::direct::{SequentialLu, saddle_matrix};
use super::fast::{CHEAP_PRODUCT_NODES, CHEAP_PRODUCT_THETA};
use super::fmm::{Fmm, FmmParams};
use super::tree::{InteractionLists, Tree, Treecode, TreecodeParams};
use super::trend::{TrendBasis, project_out};
use crate::{Error, Result};

/// Leaf size of the treecode over the coarse points: small, because the coarse points are sparse and
/// their near field is summed directly for every fine sample.
const COARSE_LEAF: usize = 16;
/// Treecode of the coarse product (theta 0.5, 6 nodes: about 2e-4 of a far cluster's absolute sum). On
/// rough data at w = 0 the coarse coefficients are large and alternate in sign, and a cheaper product
/// (theta 0.7 / 4 nodes) erred enough to stall GMRES; 8 nodes cost more and saved no iteration
/// (docs/decisions/0049-nested-coarse-level.md). The coarse FMM uses the same 6 nodes per side
/// (4 stalled GMRES; docs/decisions/0054-coarse-product-by-fmm.md).
const COARSE_PRODUCT_THETA: f64 = 0.5;
const COARSE_PRODUCT_NODES: usize = 6;

/// Leaf size of the tree over a nested coarse level's points (its subdomains), as the fine tree's.
const NESTED_LEAF: usize = 64;

/// How the coarse levels of the Schwarz preconditioner are built
/// (docs/decisions/0049-nested-coarse-level.md).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct CoarseConfig {
    /// A level over N points gets at most N / `ratio` coarse points (rounded down to a power of two;
    /// see [`CoarseConfig::points_for`]).
    pub ratio: usize,
    /// Coarse levels of at most this many points are factored (a dense LU: `8 |C|^2` bytes and `|C|^3`
    /// time, 34 MB and 0.2 s at 2,048); larger ones are preconditioned by a two-level Schwarz
    /// preconditioner of their own, with the same rule one level down, so the coarse level grows with N.
    pub dense_max_points: usize,
    /// Preconditioned Richardson steps after the first application on a nested (unfactored) level. With
    /// the cheaper coarse product of 0049's first trial, the application alone did not converge at 100k
    /// samples and one step did.
    pub nested_steps: usize,
    /// Over this many fine samples the coarse product is a fast multipole method from the coarse
    /// points ([`COARSE_PRODUCT_NODES`] per side) instead of a treecode over them.
    pub fmm_min_points: usize,
}

impl Default for CoarseConfig {
    fn default() -> Self {
        CoarseConfig {
            ratio: 8,
            dense_max_points: 2048,
            nested_steps: 1,
            fmm_min_points: super::fast::FMM_MIN_POINTS,
        }
    }
}

impl CoarseConfig {
    /// Most coarse points for a level over `n` points: N / `ratio`, and at most `ratio` times
    /// `dense_max_points`, so that a nested level's own coarse level is always factored. Deeper nesting
    /// (16,384 points over 4,096 nested over 1,024 factored) did not converge at 100k samples.
    pub fn points_for(&self, n: usize) -> usize {
        let ratio = self.ratio.max(2);
        (n / ratio).min(ratio * self.dense_max_points)
    }
}

/// How the coarse system is solved.
enum CoarseSolver {
    /// Exactly: LU factors of the saddle matrix with its trend rows (`rank` of them).
    Dense { lu: SequentialLu, rank: usize },
    /// Approximately, by the coarse points' own preconditioner ([`NestedSolver`]).
    Nested(Box<NestedSolver>),
}

/// Approximate solve of a coarse level too large to factor: one application of the coarse points' own
/// Schwarz preconditioner, then `steps` preconditioned Richardson steps, all on the trend's complement.
/// A fixed number of steps keeps it a fixed linear map, so the outer GMRES needs no flexible variant.
struct NestedSolver {
    /// Treecode over the coarse points (its tree orders them) for the residual of the Richardson steps.
    treecode: Treecode,
    lists: InteractionLists,
    /// Orthonormal trend basis at the coarse points (tree order, row-major `m x rank`).
    u: Vec<f64>,
    rank: usize,
    schwarz: super::fast::Schwarz,
    smoothing: f64,
    steps: usize,
}

pub(crate) struct CoarseLevel {
    /// Fine-tree positions of the coarse points.
    pub index: Vec<u32>,
    solver: CoarseSolver,
    smoothing: f64,
    product: CoarseProduct,
}

/// How the coarse coefficients are evaluated at every fine sample.
enum CoarseProduct {
    /// Fine leaves against a treecode over the coarse points.
    Treecode(Box<(Treecode, InteractionLists)>),
    /// A fast multipole method over the fine samples, charged at the coarse points only.
    Fmm(Box<Fmm>),
}

impl CoarseLevel {
    /// Coarse level of at most `config.points_for(N)` (and more than a quarter of that) points over the
    /// fine `tree`, or None for tiny problems.
    pub fn new(tree: &Tree, config: &CoarseConfig, smoothing: f64) -> Result<Option<CoarseLevel>> {
        let n = tree.len();
        let max_points = config.points_for(n);
        if max_points < 8 || n < 4 * max_points {
            return Ok(None);
        }
        let index = spread_subset(tree, max_points);
        let m = index.len();
        let pts: Vec<DVec3> = index.iter().map(|&i| tree.point(i as usize)).collect();
        let basis = TrendBasis::new(&pts);
        let r = basis.rank();
        if m <= r + 4 {
            return Ok(None);
        }
        let solver = if m <= config.dense_max_points {
            CoarseSolver::Dense {
                lu: SequentialLu::new(saddle_matrix(&pts, smoothing, &basis)),
                rank: r,
            }
        } else {
            let treecode = Treecode::new(
                &pts,
                TreecodeParams {
                    leaf_size: NESTED_LEAF,
                    // The cheap product: it only has to keep the Richardson steps a fixed linear map.
                    theta: CHEAP_PRODUCT_THETA,
                    nodes_per_side: CHEAP_PRODUCT_NODES,
                },
            );
            let lists = treecode.interactions(&treecode.tree);
            let tree_points = treecode.tree.points();
            let u = basis.matrix(&tree_points);
            let schwarz = super::fast::Schwarz::new(&treecode.tree, smoothing, Some(config))?;
            CoarseSolver::Nested(Box::new(NestedSolver {
                treecode,
                lists,
                u,
                rank: r,
                schwarz,
                smoothing,
                steps: config.nested_steps,
            }))
        };
        let product = if n >= config.fmm_min_points {
            let fine = tree.points();
            let params = FmmParams {
                nodes_per_side: COARSE_PRODUCT_NODES,
                svd_cutoff: 10f64.powi(-(COARSE_PRODUCT_NODES as i32)),
                leaf_depth: None,
            };
            CoarseProduct::Fmm(Box::new(Fmm::with_sources(&fine, &index, params)))
        } else {
            let treecode = Treecode::new(
                &pts,
                TreecodeParams {
                    leaf_size: COARSE_LEAF,
                    theta: COARSE_PRODUCT_THETA,
                    nodes_per_side: COARSE_PRODUCT_NODES,
                },
            );
            let lists = treecode.interactions(tree);
            CoarseProduct::Treecode(Box::new((treecode, lists)))
        };
        let level = CoarseLevel {
            index,
            solver,
            smoothing,
            product,
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
        match &self.solver {
            CoarseSolver::Dense { lu, rank } => {
                let mut rhs = Mat::<f64>::from_fn(m + rank, 1, |i, _| {
                    if i < m {
                        r[self.index[i] as usize]
                    } else {
                        0.0
                    }
                });
                lu.solve_in_place(rhs.as_mut());
                (0..m).map(|i| rhs[(i, 0)]).collect()
            }
            CoarseSolver::Nested(nested) => {
                let tree = &nested.treecode.tree;
                let restricted: Vec<f64> = self.index.iter().map(|&i| r[i as usize]).collect();
                let z = nested.solve(tree.to_tree_order(&restricted));
                tree.to_input_order(&z)
            }
        }
    }

    /// Points of this coarse level and of the levels below it, largest first.
    pub fn level_sizes(&self) -> Vec<usize> {
        let mut sizes = vec![self.index.len()];
        if let CoarseSolver::Nested(nested) = &self.solver {
            sizes.extend(nested.schwarz.coarse_level_sizes());
        }
        sizes
    }

    /// `out = (A - wI) E l` on every fine sample (tree order), `E` placing the coarse coefficients `l`
    /// at their samples.
    pub fn product(&self, tree: &Tree, l: &[f64], out: &mut [f64]) {
        match &self.product {
            CoarseProduct::Treecode(product) => {
                let (treecode, lists) = &**product;
                let q = treecode.tree.to_tree_order(l);
                let proxies = treecode.upward(&q);
                treecode.evaluate(tree, lists, &q, &proxies, out, None);
            }
            CoarseProduct::Fmm(fmm) => fmm.product(l, out),
        }
        for (&i, &li) in self.index.iter().zip(l) {
            out[i as usize] -= self.smoothing * li;
        }
    }

    pub fn memory_bytes(&self) -> usize {
        let solver = match &self.solver {
            CoarseSolver::Dense { rank, .. } => (self.index.len() + rank).pow(2) * 8,
            CoarseSolver::Nested(nested) => {
                nested.treecode.memory_bytes()
                    + nested.lists.memory_bytes()
                    + nested.u.len() * 8
                    + nested.schwarz.memory_bytes()
            }
        };
        let product = match &self.product {
            CoarseProduct::Treecode(product) => product.0.memory_bytes() + product.1.memory_bytes(),
            CoarseProduct::Fmm(fmm) => fmm.memory_bytes() + fmm.product_bytes(),
        };
        solver + product + self.index.len() * 4
    }
}

impl NestedSolver {
    /// Tree-ordered coefficients for the tree-ordered right-hand side `rhs`.
    fn solve(&self, mut rhs: Vec<f64>) -> Vec<f64> {
        let tree = &self.treecode.tree;
        let m = rhs.len();
        let project = |v: &mut [f64]| project_out(v, &self.u, self.rank);
        project(&mut rhs);
        let mut z = vec![0.0; m];
        self.schwarz.apply(tree, &rhs, &mut z);
        project(&mut z);
        let (mut az, mut dz) = (vec![0.0; m], vec![0.0; m]);
        for _ in 0..self.steps {
            super::fast::product(&self.treecode, &self.lists, self.smoothing, &z, &mut az);
            let mut res: Vec<f64> = rhs.iter().zip(&az).map(|(a, b)| a - b).collect();
            project(&mut res);
            self.schwarz.apply(tree, &res, &mut dz);
            project(&mut dz);
            for (zi, d) in z.iter_mut().zip(&dz) {
                *zi += d;
            }
        }
        z
    }
}

/// At most `max_points` (and more than a quarter of that) well-spread samples (fine-tree positions): a
/// median-split tree over the samples with leaves of at most `ceil(N / M)` samples, M the largest power
/// of two <= `max_points` (median splits then give at most M leaves), and from each leaf the sample
/// nearest to its centroid. Leaves have equal counts, so the subset follows the sampling density.
pub(crate) fn spread_subset(tree: &Tree, max_points: usize) -> Vec<u32> {
    let m = 1usize << max_points.max(1).ilog2();
    let group = tree.len().div_ceil(m).max(1);
    let points = tree.points();
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rbf::direct::solve_dense;
    use crate::rbf::ultrasound_like_samples;
    use rand::seq::SliceRandom;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn covering_radius(points: &[DVec3], subset: &[DVec3]) -> f64 {
        points.iter().fold(0.0f64, |worst, p| {
            let nearest = subset
                .iter()
                .map(|c| (*c - *p).length())
                .fold(f64::INFINITY, f64::min);
            worst.max(nearest)
        })
    }

    /// The dense solve on `level`'s points of the fine residual `r` restricted to them.
    fn dense_solve_on_level(tree: &Tree, level: &CoarseLevel, r: &[f64], w: f64) -> Vec<f64> {
        let sub: Vec<DVec3> = level
            .index
            .iter()
            .map(|&i| tree.point(i as usize))
            .collect();
        let rhs: Vec<f64> = level.index.iter().map(|&i| r[i as usize]).collect();
        solve_dense(&sub, &rhs, w, &TrendBasis::new(&sub))
            .unwrap()
            .0
    }

    /// At most N / 16 coarse points (250 of 4,000: 128 after rounding to a power of two), factored.
    fn ratio_16() -> CoarseConfig {
        CoarseConfig {
            ratio: 16,
            ..CoarseConfig::default()
        }
    }

    #[test]
    fn spread_subset_is_bounded_distinct_and_covers_better_than_random() {
        let (pts, _) = ultrasound_like_samples(6000, 21);
        let tree = Tree::build(&pts, 64);
        let index = spread_subset(&tree, 300);
        assert!(index.len() > 75 && index.len() <= 300, "{}", index.len());
        assert!(index.windows(2).all(|w| w[0] < w[1]), "sorted and distinct");
        let chosen: Vec<DVec3> = index.iter().map(|&i| tree.point(i as usize)).collect();
        let mut order: Vec<usize> = (0..pts.len()).collect();
        order.shuffle(&mut ChaCha8Rng::seed_from_u64(22));
        let random: Vec<DVec3> = order[..index.len()].iter().map(|&i| pts[i]).collect();
        let (spread, rand) = (
            covering_radius(&pts, &chosen),
            covering_radius(&pts, &random),
        );
        assert!(spread < rand, "spread {spread} mm vs random {rand} mm");
    }

    #[test]
    fn coarse_solve_equals_the_dense_solve_on_the_subset() {
        let (pts, _) = ultrasound_like_samples(4000, 23);
        let tree = Tree::build(&pts, 64);
        let w = 0.7;
        let level = CoarseLevel::new(&tree, &ratio_16(), w).unwrap().unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(24);
        let r: Vec<f64> = (0..tree.len())
            .map(|_| rng.random_range(-20.0..20.0))
            .collect();
        let got = level.solve(&r);
        let want = dense_solve_on_level(&tree, &level, &r, w);
        let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for (a, b) in got.iter().zip(&want) {
            // Two pivoted LUs of the same ~250 x 250 system: agreement to round-off times its condition.
            assert!((a - b).abs() <= 1e-8 * scale, "{a} vs {b}");
        }
    }

    #[test]
    fn coarse_product_matches_the_direct_sum() {
        // By the treecode over the coarse points, and by the FMM charged at them.
        for fmm_min_points in [usize::MAX, 0] {
            coarse_product_matches_the_direct_sum_with(CoarseConfig {
                fmm_min_points,
                ..ratio_16()
            });
        }
    }

    fn coarse_product_matches_the_direct_sum_with(config: CoarseConfig) {
        let (pts, _) = ultrasound_like_samples(4000, 25);
        let tree = Tree::build(&pts, 64);
        let w = 0.5;
        let level = CoarseLevel::new(&tree, &config, w).unwrap().unwrap();
        assert_eq!(
            matches!(level.product, CoarseProduct::Fmm(_)),
            config.fmm_min_points == 0
        );
        let mut rng = ChaCha8Rng::seed_from_u64(26);
        let l: Vec<f64> = (0..level.len())
            .map(|_| rng.random_range(-1.0..1.0))
            .collect();
        let mut got = vec![0.0; tree.len()];
        level.product(&tree, &l, &mut got);
        let coarse: Vec<DVec3> = level
            .index
            .iter()
            .map(|&i| tree.point(i as usize))
            .collect();
        for i in (0..tree.len()).step_by(7) {
            let x = tree.point(i);
            let mut exact = 0.0;
            let mut scale = 0.0;
            for (k, c) in coarse.iter().enumerate() {
                exact += l[k] * (x - *c).length();
                scale += l[k].abs() * (x - *c).length();
                if level.index[k] as usize == i {
                    exact -= w * l[k];
                }
            }
            // Chebyshev interpolation with 6 nodes at separation 0.5 errs by about (0.5 / 2)^6 = 2.4e-4
            // of a far cluster's absolute contribution.
            assert!((got[i] - exact).abs() <= 1e-3 * scale, "{i}");
        }
    }

    /// A coarse level too large to factor is solved approximately by its own two-level Schwarz
    /// preconditioner plus Richardson steps: every step must bring it closer to the dense solve on the
    /// same subset, and four steps close to it.
    #[test]
    fn nested_coarse_solve_converges_to_the_dense_solve_with_its_steps() {
        let (pts, _) = ultrasound_like_samples(8000, 27);
        let tree = Tree::build(&pts, 64);
        let w = 0.5;
        let nested = |steps| CoarseConfig {
            ratio: 8,
            dense_max_points: 128,
            nested_steps: steps,
            ..CoarseConfig::default()
        };
        let mut rng = ChaCha8Rng::seed_from_u64(28);
        let r: Vec<f64> = (0..tree.len())
            .map(|_| rng.random_range(-20.0..20.0))
            .collect();
        let mut want = Vec::new();
        let mut errors = Vec::new();
        for steps in [0, 1, 4] {
            let level = CoarseLevel::new(&tree, &nested(steps), w).unwrap().unwrap();
            // 1,000 points rounded to 512 (nested), its own coarse level 64 (factored).
            assert_eq!(level.level_sizes(), vec![512, 64]);
            if want.is_empty() {
                want = dense_solve_on_level(&tree, &level, &r, w);
            }
            let got = level.solve(&r);
            let diff: f64 = got.iter().zip(&want).map(|(a, b)| (a - b).powi(2)).sum();
            let norm: f64 = want.iter().map(|b| b * b).sum();
            errors.push((diff / norm).sqrt());
        }
        assert!(
            errors[0] > errors[1] && errors[1] > errors[2] && errors[2] < 1e-4,
            "relative errors after 0 / 1 / 4 steps: {errors:?}"
        );
    }
}
