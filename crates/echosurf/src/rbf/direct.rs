//! Dense solvers: the global reference solve (faer LU of the saddle system) and the small local solves
//! used by the Schwarz preconditioner (own LU, sequential and therefore deterministic inside rayon).

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::lu::partial_pivoting::{factor, solve};
use faer::perm::PermRef;
use faer::{Mat, MatMut, Par};
use glam::DVec3;

use super::trend::TrendBasis;
use crate::{Error, Result};

/// The saddle matrix `[[A - wI, U], [U^T, 0]]` of `points` (A the |x - y| kernel, U the trend basis).
pub(crate) fn saddle_matrix(points: &[DVec3], smoothing: f64, basis: &TrendBasis) -> Mat<f64> {
    let n = points.len();
    let r = basis.rank();
    let u = basis.matrix(points);
    Mat::<f64>::from_fn(n + r, n + r, |i, j| {
        if i < n && j < n {
            (points[i] - points[j]).length() - if i == j { smoothing } else { 0.0 }
        } else if i < n {
            u[i * r + (j - n)]
        } else if j < n {
            u[j * r + (i - n)]
        } else {
            0.0
        }
    })
}

/// Solves `[A - wI, U; U^T, 0] [l; d] = [f; 0]` densely. Returns (l, d) with d the trend-basis coefficients.
pub(crate) fn solve_dense(
    points: &[DVec3],
    values: &[f64],
    smoothing: f64,
    basis: &TrendBasis,
) -> Result<(Vec<f64>, Vec<f64>)> {
    let n = points.len();
    let size = n + basis.rank();
    let m = saddle_matrix(points, smoothing, basis);
    let mut rhs = Mat::<f64>::from_fn(size, 1, |i, _| if i < n { values[i] } else { 0.0 });
    SequentialLu::new(m).solve_in_place(rhs.as_mut());
    let solution: Vec<f64> = (0..size).map(|i| rhs[(i, 0)]).collect();
    if solution.iter().any(|v| !v.is_finite()) {
        return Err(Error::Numerical(format!(
            "dense RBF solve of {n} points produced non-finite coefficients (singular system; \
             merge duplicate points or increase smoothing)"
        )));
    }
    Ok((solution[..n].to_vec(), solution[n..].to_vec()))
}

/// LU factors with partial pivoting of a square matrix, computed and applied by faer's kernels with
/// `Par::Seq` passed explicitly: parallel kernels split work by thread count, which changes rounding,
/// and a fit must be bit-identical on any number of threads (and must not touch faer's global setting,
/// which another fit in the same process may be using).
pub(crate) struct SequentialLu {
    /// L (unit diagonal, strictly below it) and U (on and above the diagonal) in one matrix.
    factors: Mat<f64>,
    row_perm: Vec<usize>,
    row_perm_inverse: Vec<usize>,
}

impl SequentialLu {
    /// Factors the square matrix `a` in place.
    pub fn new(mut a: Mat<f64>) -> Self {
        let n = a.nrows();
        assert_eq!(n, a.ncols(), "LU of a non-square matrix");
        let mut row_perm = vec![0usize; n];
        let mut row_perm_inverse = vec![0usize; n];
        let params = Default::default();
        let mut buffer = MemBuffer::new(factor::lu_in_place_scratch::<usize, f64>(
            n,
            n,
            Par::Seq,
            params,
        ));
        factor::lu_in_place(
            a.as_mut(),
            &mut row_perm,
            &mut row_perm_inverse,
            Par::Seq,
            MemStack::new(&mut buffer),
            params,
        );
        Self {
            factors: a,
            row_perm,
            row_perm_inverse,
        }
    }

    /// As [`SequentialLu::new`], or None when a pivot is zero or within round-off of the largest entry
    /// (the rule of [`lu_solve`]).
    pub fn new_nonsingular(a: Mat<f64>) -> Option<Self> {
        let mut scale = 0.0f64;
        for j in 0..a.ncols() {
            for i in 0..a.nrows() {
                scale = scale.max(a[(i, j)].abs());
            }
        }
        let lu = Self::new(a);
        let tiny = (1e-15 * scale * f64::EPSILON).max(1e-300);
        (0..lu.factors.nrows())
            .all(|k| lu.factors[(k, k)].abs() > tiny)
            .then_some(lu)
    }

    /// Replaces `rhs` (n rows) by the solution of `A x = rhs`.
    pub fn solve_in_place(&self, rhs: MatMut<'_, f64>) {
        let n = self.factors.nrows();
        let perm = PermRef::new_checked(&self.row_perm, &self.row_perm_inverse, n);
        let mut buffer = MemBuffer::new(solve::solve_in_place_scratch::<usize, f64>(
            n,
            rhs.ncols(),
            Par::Seq,
        ));
        solve::solve_in_place(
            self.factors.as_ref(),
            self.factors.as_ref(),
            perm,
            rhs,
            Par::Seq,
            MemStack::new(&mut buffer),
        );
    }
}

/// In-place LU with partial pivoting of the row-major `n x n` matrix `a`, then solves for the row-major
/// `n x nrhs` right-hand sides `b`. Returns false if a pivot is zero.
pub(crate) fn lu_solve(a: &mut [f64], n: usize, b: &mut [f64], nrhs: usize) -> bool {
    let mut scale = 0.0f64;
    for v in a.iter() {
        scale = scale.max(v.abs());
    }
    for k in 0..n {
        let mut p = k;
        let mut best = a[k * n + k].abs();
        for i in k + 1..n {
            let v = a[i * n + k].abs();
            if v > best {
                best = v;
                p = i;
            }
        }
        if best <= 1e-300 || best <= 1e-15 * scale * f64::EPSILON {
            return false;
        }
        if p != k {
            for j in 0..n {
                a.swap(k * n + j, p * n + j);
            }
            for j in 0..nrhs {
                b.swap(k * nrhs + j, p * nrhs + j);
            }
        }
        let pivot = a[k * n + k];
        let (upper, lower) = a.split_at_mut((k + 1) * n);
        let row_k = &upper[k * n..(k + 1) * n];
        let (bu, bl) = b.split_at_mut((k + 1) * nrhs);
        let b_k = &bu[k * nrhs..(k + 1) * nrhs];
        for i in 0..n - k - 1 {
            let row = &mut lower[i * n..(i + 1) * n];
            let f = row[k] / pivot;
            if f == 0.0 {
                continue;
            }
            row[k] = f;
            for j in k + 1..n {
                row[j] -= f * row_k[j];
            }
            let brow = &mut bl[i * nrhs..(i + 1) * nrhs];
            for j in 0..nrhs {
                brow[j] -= f * b_k[j];
            }
        }
    }
    for k in (0..n).rev() {
        let pivot = a[k * n + k];
        for j in 0..nrhs {
            let mut s = b[k * nrhs + j];
            for i in k + 1..n {
                s -= a[k * n + i] * b[i * nrhs + j];
            }
            b[k * nrhs + j] = s / pivot;
        }
    }
    true
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn small_lu_solves_a_pivoting_system() {
        let mut a = vec![0.0, 2.0, 1.0, 1.0, 1.0, 0.0, 3.0, 0.0, 1.0];
        let x = [1.0, -2.0, 0.5];
        let b0: Vec<f64> = (0..3)
            .map(|i| (0..3).map(|j| a[i * 3 + j] * x[j]).sum())
            .collect();
        let mut b = b0.clone();
        assert!(lu_solve(&mut a, 3, &mut b, 1));
        for i in 0..3 {
            assert!((b[i] - x[i]).abs() < 1e-12);
        }
        let mut singular = vec![1.0, 2.0, 2.0, 4.0];
        let mut rhs = vec![1.0, 1.0];
        assert!(!lu_solve(&mut singular, 2, &mut rhs, 1));
    }

    #[test]
    fn checked_blocked_lu_solves_or_refuses_as_the_small_lu_does() {
        let a = [0.0, 2.0, 1.0, 1.0, 1.0, 0.0, 3.0, 0.0, 1.0];
        let x = [1.0, -2.0, 0.5];
        let lu = SequentialLu::new_nonsingular(Mat::from_fn(3, 3, |i, j| a[i * 3 + j]))
            .expect("regular");
        let mut b = Mat::from_fn(3, 1, |i, _| (0..3).map(|j| a[i * 3 + j] * x[j]).sum());
        lu.solve_in_place(b.as_mut());
        for (i, xi) in x.iter().enumerate() {
            assert!((b[(i, 0)] - xi).abs() < 1e-12);
        }
        // Two equal rows (two coincident samples in an RBF matrix).
        let singular = Mat::from_fn(3, 3, |i, j| {
            [1.0, 2.0, 3.0, 1.0, 2.0, 3.0, 0.0, 1.0, 5.0][i.min(2) * 3 + j]
        });
        assert!(SequentialLu::new_nonsingular(singular).is_none());
    }
}
