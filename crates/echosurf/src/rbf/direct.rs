//! Dense solvers: the global reference solve (faer LU of the saddle system) and the small local solves
//! used by the Schwarz preconditioner (own LU, sequential and therefore deterministic inside rayon).

use faer::Mat;
use faer::linalg::solvers::Solve;
use glam::DVec3;

use super::trend::TrendBasis;
use crate::{Error, Result};

/// Solves `[A - wI, U; U^T, 0] [l; d] = [f; 0]` densely. Returns (l, d) with d the trend-basis coefficients.
pub(crate) fn solve_dense(
    points: &[DVec3],
    values: &[f64],
    smoothing: f64,
    basis: &TrendBasis,
) -> Result<(Vec<f64>, Vec<f64>)> {
    let n = points.len();
    let r = basis.rank();
    let u = basis.matrix(points);
    let size = n + r;
    let m = Mat::<f64>::from_fn(size, size, |i, j| {
        if i < n && j < n {
            (points[i] - points[j]).length() - if i == j { smoothing } else { 0.0 }
        } else if i < n {
            u[i * r + (j - n)]
        } else if j < n {
            u[j * r + (i - n)]
        } else {
            0.0
        }
    });
    let mut rhs = Mat::<f64>::from_fn(size, 1, |i, _| if i < n { values[i] } else { 0.0 });
    // faer's blocked LU splits its work by thread count when it runs in parallel, which changes the
    // rounding of the result: run it sequentially so a fit is bit-identical on 1 or many threads (the
    // dense path is only used up to a few thousand points, where this costs well under a second).
    let previous = faer::get_global_parallelism();
    faer::set_global_parallelism(faer::Par::Seq);
    let lu = m.partial_piv_lu();
    lu.solve_in_place(rhs.as_mut());
    faer::set_global_parallelism(previous);
    let solution: Vec<f64> = (0..size).map(|i| rhs[(i, 0)]).collect();
    if solution.iter().any(|v| !v.is_finite()) {
        return Err(Error::Numerical(format!(
            "dense RBF solve of {n} points produced non-finite coefficients (singular system; \
             merge duplicate points or increase smoothing)"
        )));
    }
    Ok((solution[..n].to_vec(), solution[n..].to_vec()))
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
}
