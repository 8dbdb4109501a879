//! The linear trend `c0 + c.x` and the orthonormal basis of its span on a point set.
//!
//! The trend columns (1, x, y, z) are orthonormalised through the eigen-decomposition of their 4x4 Gram
//! matrix; directions with a tiny eigenvalue (all points on a plane, a line, or one point) are dropped, so
//! degenerate geometry yields a *reduced* trend instead of a singular system.

use glam::DVec3;

/// Relative eigenvalue below which a trend direction counts as absent (coplanar / collinear points).
const RANK_TOLERANCE: f64 = 1e-10;

/// Orthonormal (on the given points) basis of the linear functions that the points can distinguish.
#[derive(Debug, Clone)]
pub(crate) struct TrendBasis {
    pub origin: DVec3,
    pub scale: f64,
    /// Column k of the basis is `u_k(x) = sum_a transform[k][a] * m_a(x)`, with monomials
    /// `m = (1, (x-o).x/scale, (x-o).y/scale, (x-o).z/scale)`.
    pub transform: Vec<[f64; 4]>,
}

impl TrendBasis {
    pub fn new(points: &[DVec3]) -> Self {
        let n = points.len().max(1) as f64;
        let origin = points.iter().fold(DVec3::ZERO, |a, &p| a + p) / n;
        let scale = points
            .iter()
            .map(|p| (*p - origin).abs().max_element())
            .fold(0.0f64, f64::max);
        let scale = if scale > 0.0 { scale } else { 1.0 };
        let mut gram = [[0.0f64; 4]; 4];
        for p in points {
            let m = monomials(*p, origin, scale);
            for a in 0..4 {
                for b in 0..4 {
                    gram[a][b] += m[a] * m[b];
                }
            }
        }
        let (eigenvalues, eigenvectors) = jacobi_eigen(gram);
        let largest = eigenvalues.iter().cloned().fold(0.0, f64::max);
        let mut order: Vec<usize> = (0..4).collect();
        order.sort_by(|&a, &b| eigenvalues[b].total_cmp(&eigenvalues[a]));
        let mut transform = Vec::new();
        for k in order {
            if largest > 0.0 && eigenvalues[k] > RANK_TOLERANCE * largest {
                let s = 1.0 / eigenvalues[k].sqrt();
                transform.push([
                    eigenvectors[0][k] * s,
                    eigenvectors[1][k] * s,
                    eigenvectors[2][k] * s,
                    eigenvectors[3][k] * s,
                ]);
            }
        }
        TrendBasis {
            origin,
            scale,
            transform,
        }
    }

    pub fn rank(&self) -> usize {
        self.transform.len()
    }

    /// Values of all basis functions at `p`.
    pub fn eval(&self, p: DVec3, out: &mut [f64]) {
        let m = monomials(p, self.origin, self.scale);
        for (o, t) in out.iter_mut().zip(&self.transform) {
            *o = t[0] * m[0] + t[1] * m[1] + t[2] * m[2] + t[3] * m[3];
        }
    }

    /// Basis matrix U (row-major, `points.len() x rank`).
    pub fn matrix(&self, points: &[DVec3]) -> Vec<f64> {
        let r = self.rank();
        let mut u = vec![0.0; points.len() * r];
        for (i, p) in points.iter().enumerate() {
            self.eval(*p, &mut u[i * r..(i + 1) * r]);
        }
        u
    }

    /// Converts basis coefficients `d` into `(c0, c)` of `c0 + c.(x - origin)`.
    pub fn to_linear(&self, d: &[f64]) -> (f64, DVec3) {
        let mut a = [0.0; 4];
        for (t, &dk) in self.transform.iter().zip(d) {
            for q in 0..4 {
                a[q] += t[q] * dk;
            }
        }
        (a[0], DVec3::new(a[1], a[2], a[3]) / self.scale)
    }
}

/// `U^T v` for a row-major `U` with `rank` columns, summed in fixed order.
pub(crate) fn trend_coefficients(u: &[f64], rank: usize, v: &[f64]) -> Vec<f64> {
    let mut d = vec![0.0; rank];
    for (i, &vi) in v.iter().enumerate() {
        for k in 0..rank {
            d[k] += u[i * rank + k] * vi;
        }
    }
    d
}

/// `v -= U (U^T v)` for an orthonormal row-major `U` with `rank` columns: `v` projected onto the trend's
/// complement.
pub(crate) fn project_out(v: &mut [f64], u: &[f64], rank: usize) {
    let d = trend_coefficients(u, rank, v);
    for (i, vi) in v.iter_mut().enumerate() {
        for k in 0..rank {
            *vi -= u[i * rank + k] * d[k];
        }
    }
}

fn monomials(p: DVec3, origin: DVec3, scale: f64) -> [f64; 4] {
    let q = (p - origin) / scale;
    [1.0, q.x, q.y, q.z]
}

/// Eigen-decomposition of a symmetric 4x4 matrix by cyclic Jacobi rotations (deterministic, exact enough
/// for a Gram matrix). Returns eigenvalues and eigenvectors as columns.
fn jacobi_eigen(mut a: [[f64; 4]; 4]) -> ([f64; 4], [[f64; 4]; 4]) {
    let mut v = [[0.0; 4]; 4];
    for (i, row) in v.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    for _sweep in 0..64 {
        let off: f64 = (0..4)
            .flat_map(|i| (0..4).map(move |j| (i, j)))
            .filter(|(i, j)| i != j)
            .map(|(i, j)| a[i][j] * a[i][j])
            .sum();
        let diag: f64 = (0..4).map(|i| a[i][i] * a[i][i]).sum();
        if off <= 1e-30 * diag.max(f64::MIN_POSITIVE) {
            break;
        }
        for p in 0..4 {
            for q in p + 1..4 {
                if a[p][q] == 0.0 {
                    continue;
                }
                let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let t = if theta == 0.0 { 1.0 } else { t };
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for k in 0..4 {
                    let akp = a[k][p];
                    let akq = a[k][q];
                    a[k][p] = c * akp - s * akq;
                    a[k][q] = s * akp + c * akq;
                }
                for k in 0..4 {
                    let apk = a[p][k];
                    let aqk = a[q][k];
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
    ([a[0][0], a[1][1], a[2][2], a[3][3]], v)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn jacobi_eigenpairs_match_a_dense_eigensolver() {
        // Random symmetric B B^T against faer's dense self-adjoint solver.
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(6);
        for _ in 0..200 {
            let b: [[f64; 4]; 4] =
                std::array::from_fn(|_| std::array::from_fn(|_| rng.random_range(-1.0..1.0)));
            let m: [[f64; 4]; 4] = std::array::from_fn(|i| {
                std::array::from_fn(|j| (0..4).map(|k| b[i][k] * b[j][k]).sum())
            });
            let dense = faer::Mat::<f64>::from_fn(4, 4, |i, j| m[i][j]);
            let eigen = dense.self_adjoint_eigen(faer::Side::Lower).unwrap();
            let expected = eigen.S().column_vector();
            let (values, vectors) = jacobi_eigen(m);
            let mut order: Vec<usize> = (0..4).collect();
            order.sort_by(|&i, &j| values[i].total_cmp(&values[j]));
            for (rank, &k) in order.iter().enumerate() {
                assert!((values[k] - expected[rank]).abs() < 1e-10, "{values:?}");
                // A distinct eigenvalue's vector agrees up to sign.
                let distinct = (rank == 0 || expected[rank] - expected[rank - 1] > 1e-6)
                    && (rank + 1 == 4 || expected[rank + 1] - expected[rank] > 1e-6);
                if distinct {
                    let dot: f64 = (0..4).map(|i| vectors[i][k] * eigen.U()[(i, rank)]).sum();
                    assert!(dot.abs() > 1.0 - 1e-9, "{dot}");
                }
            }
        }
    }

    #[test]
    fn basis_is_orthonormal_and_rank_detects_coplanar_points() {
        let pts: Vec<DVec3> = (0..50)
            .map(|i| DVec3::new((i % 7) as f64, (i / 7) as f64 * 0.5, (i * 13 % 5) as f64))
            .collect();
        let b = TrendBasis::new(&pts);
        assert_eq!(b.rank(), 4);
        let u = b.matrix(&pts);
        for a in 0..4 {
            for c in 0..4 {
                let dot: f64 = (0..pts.len()).map(|i| u[i * 4 + a] * u[i * 4 + c]).sum();
                let expected = if a == c { 1.0 } else { 0.0 };
                assert!((dot - expected).abs() < 1e-10, "{a} {c} {dot}");
            }
        }
        let flat: Vec<DVec3> = pts.iter().map(|p| DVec3::new(p.x, p.y, 2.0)).collect();
        assert_eq!(TrendBasis::new(&flat).rank(), 3);
        assert_eq!(TrendBasis::new(&[DVec3::ONE]).rank(), 1);
        assert_eq!(TrendBasis::new(&[DVec3::ONE, DVec3::ZERO]).rank(), 2);
    }
}
