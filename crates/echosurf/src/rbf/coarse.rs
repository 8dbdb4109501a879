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
//! Smoothing on C: the coarse matrix is the principal submatrix `A_CC - wI` of the fine system (Beatson,
//! Light & Billings 2000). Scaling w by N / |C| (the same smoothing functional on sparser data) was
//! measured worse on speckled 10k samples with |C| = 200: 8 iterations with w, 9 with w sqrt(N/|C|), 11
//! with w N / |C|.

use faer::Mat;
use glam::DVec3;
use rayon::prelude::*;

use super::direct::SequentialLu;
use super::tree::{InteractionLists, Tree, Treecode, TreecodeParams};
use super::trend::TrendBasis;
use crate::{Error, Result};

/// Leaf size of the treecode over the coarse points: small, because the coarse points are sparse and
/// their near field is summed directly for every fine sample.
const COARSE_LEAF: usize = 16;
/// Treecode of the coarse product: it only has to be a fixed linear map close to the exact one. Measured
/// at 10k samples, |C| = 2048: theta 0.5 / 6 nodes 1,975 kernel terms per sample and 10 iterations;
/// theta 0.7 / 4 nodes 1,106 terms and 12 iterations; at 100k it halved the preconditioner's cost.
const COARSE_PRODUCT_THETA: f64 = 0.7;
const COARSE_PRODUCT_NODES: usize = 4;

pub(crate) struct CoarseLevel {
    /// Fine-tree positions of the coarse points.
    pub index: Vec<u32>,
    lu: SequentialLu,
    rank: usize,
    smoothing: f64,
    treecode: Treecode,
    lists: InteractionLists,
}

impl CoarseLevel {
    /// Coarse level of at most `max_points` (and more than a quarter of that) points over the fine
    /// `tree`, or None for tiny problems.
    pub fn new(tree: &Tree, max_points: usize, smoothing: f64) -> Result<Option<CoarseLevel>> {
        let n = tree.len();
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
        let u = basis.matrix(&pts);
        let size = m + r;
        let a = Mat::<f64>::from_fn(size, size, |i, j| {
            if i < m && j < m {
                (pts[i] - pts[j]).length() - if i == j { smoothing } else { 0.0 }
            } else if i < m {
                u[i * r + (j - m)]
            } else if j < m {
                u[j * r + (i - m)]
            } else {
                0.0
            }
        });
        let lu = SequentialLu::new(a);
        let treecode = Treecode::new(
            &pts,
            TreecodeParams {
                leaf_size: COARSE_LEAF,
                theta: COARSE_PRODUCT_THETA,
                nodes_per_side: COARSE_PRODUCT_NODES,
            },
        );
        let lists = treecode.interactions(tree);
        let level = CoarseLevel {
            index,
            lu,
            rank: r,
            smoothing,
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
        self.lu.solve_in_place(rhs.as_mut());
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
            out[i as usize] -= self.smoothing * li;
        }
    }

    pub fn memory_bytes(&self) -> usize {
        let size = self.index.len() + self.rank;
        size * size * 8 + self.treecode.memory_bytes() + self.lists.memory_bytes() + size * 4
    }
}

/// At most `max_points` (and more than a quarter of that) well-spread samples (fine-tree positions): a
/// median-split tree over the samples with leaves of at most `ceil(N / M)` samples, M the largest power
/// of two <= `max_points` (median splits then give at most M leaves), and from each leaf the sample
/// nearest to its centroid. Leaves have equal counts, so the subset follows the sampling density.
pub(crate) fn spread_subset(tree: &Tree, max_points: usize) -> Vec<u32> {
    let m = 1usize << max_points.max(1).ilog2();
    let group = tree.len().div_ceil(m).max(1);
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
        let level = CoarseLevel::new(&tree, 250, w).unwrap().unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(24);
        let r: Vec<f64> = (0..tree.len())
            .map(|_| rng.random_range(-20.0..20.0))
            .collect();
        let got = level.solve(&r);
        let sub: Vec<DVec3> = level
            .index
            .iter()
            .map(|&i| tree.point(i as usize))
            .collect();
        let rhs: Vec<f64> = level.index.iter().map(|&i| r[i as usize]).collect();
        let (want, _) = solve_dense(&sub, &rhs, w, &TrendBasis::new(&sub)).unwrap();
        let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for (a, b) in got.iter().zip(&want) {
            // Two pivoted LUs of the same ~250 x 250 system: agreement to round-off times its condition.
            assert!((a - b).abs() <= 1e-8 * scale, "{a} vs {b}");
        }
    }

    #[test]
    fn coarse_product_matches_the_direct_sum() {
        let (pts, _) = ultrasound_like_samples(4000, 25);
        let tree = Tree::build(&pts, 64);
        let w = 0.5;
        let level = CoarseLevel::new(&tree, 250, w).unwrap().unwrap();
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
            // Chebyshev interpolation with 4 nodes at separation 0.7 errs by about (0.7 / 2)^4 = 1.5 %
            // of a far cluster's absolute contribution.
            assert!((got[i] - exact).abs() <= 0.015 * scale, "{i}");
        }
    }
}
