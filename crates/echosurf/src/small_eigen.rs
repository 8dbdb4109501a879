//! Symmetric eigen-decomposition of small fixed-size matrices (the RBF trend's 4 x 4 Gram matrix).

/// Eigen-decomposition of a symmetric N x N matrix by cyclic Jacobi rotations (deterministic, exact
/// enough for a Gram or covariance matrix). Returns the eigenvalues and the eigenvectors as columns.
pub(crate) fn jacobi_eigen<const N: usize>(mut a: [[f64; N]; N]) -> ([f64; N], [[f64; N]; N]) {
    let mut v = [[0.0; N]; N];
    for (i, row) in v.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    for _sweep in 0..64 {
        let off: f64 = (0..N)
            .flat_map(|i| (0..N).map(move |j| (i, j)))
            .filter(|(i, j)| i != j)
            .map(|(i, j)| a[i][j] * a[i][j])
            .sum();
        let diag: f64 = (0..N).map(|i| a[i][i] * a[i][i]).sum();
        if off <= 1e-30 * diag.max(f64::MIN_POSITIVE) {
            break;
        }
        for p in 0..N {
            for q in p + 1..N {
                if a[p][q] == 0.0 {
                    continue;
                }
                let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let t = if theta == 0.0 { 1.0 } else { t };
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for row in a.iter_mut() {
                    let akp = row[p];
                    let akq = row[q];
                    row[p] = c * akp - s * akq;
                    row[q] = s * akp + c * akq;
                }
                // Each k reads and writes only column k of rows p and q: copies of the rows serve.
                let (row_p, row_q) = (a[p], a[q]);
                for (k, (&apk, &aqk)) in row_p.iter().zip(&row_q).enumerate() {
                    a[p][k] = c * apk - s * aqk;
                    a[q][k] = s * apk + c * aqk;
                }
                for row in v.iter_mut() {
                    let vkp = row[p];
                    let vkq = row[q];
                    row[p] = c * vkp - s * vkq;
                    row[q] = s * vkp + c * vkq;
                }
            }
        }
    }
    (std::array::from_fn(|i| a[i][i]), v)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// Eigenpairs of random symmetric matrices B B^T against faer's dense self-adjoint solver.
    fn check<const N: usize>(seed: u64) {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        for _ in 0..200 {
            let b: [[f64; N]; N] =
                std::array::from_fn(|_| std::array::from_fn(|_| rng.random_range(-1.0..1.0)));
            let m: [[f64; N]; N] = std::array::from_fn(|i| {
                std::array::from_fn(|j| (0..N).map(|k| b[i][k] * b[j][k]).sum())
            });
            let dense = faer::Mat::<f64>::from_fn(N, N, |i, j| m[i][j]);
            let eigen = dense.self_adjoint_eigen(faer::Side::Lower).unwrap();
            let expected = eigen.S().column_vector();
            let (values, vectors) = jacobi_eigen(m);
            let mut order: Vec<usize> = (0..N).collect();
            order.sort_by(|&i, &j| values[i].total_cmp(&values[j]));
            for (rank, &k) in order.iter().enumerate() {
                assert!((values[k] - expected[rank]).abs() < 1e-10, "{values:?}");
                // A distinct eigenvalue's vector agrees up to sign.
                let distinct = (rank == 0 || expected[rank] - expected[rank - 1] > 1e-6)
                    && (rank + 1 == N || expected[rank + 1] - expected[rank] > 1e-6);
                if distinct {
                    let dot: f64 = (0..N).map(|i| vectors[i][k] * eigen.U()[(i, rank)]).sum();
                    assert!(dot.abs() > 1.0 - 1e-9, "{dot}");
                }
            }
        }
    }

    #[test]
    fn jacobi_eigenpairs_match_a_dense_eigensolver() {
        check::<3>(5);
        check::<4>(6);
    }
}
