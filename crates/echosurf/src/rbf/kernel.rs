//! The inner sums of every evaluation: `sum_j q_j |t - s_j|` and its gradient, on SoA centres.
//!
//! These loops are where evaluation spends its time (a partition-of-unity point visits a few hundred
//! centres), and the x86-64 baseline (SSE2) runs only two square roots per instruction. So each sum is
//! written once over [`LANES`] independent accumulators (centre j goes to lane `j % LANES`, the tail to
//! lane 0, the lanes reduced in one fixed tree) and run with AVX-512 or AVX2 square roots when the CPU has
//! them, else as plain scalar code. Every variant performs the same IEEE operations in the same order
//! (square root and division are correctly rounded; nothing is fused), so results are bit-identical on
//! every machine whatever the instruction set.

// The crate's unsafe code is here and in surface/sheet_sums.rs: calling the instruction-set variants
// after the runtime check, and their unaligned vector loads and stores, each bounded by the block
// arithmetic next to it.
#![allow(unsafe_code)]

use glam::DVec3;

/// Accumulator lanes: one AVX-512 register of f64, two AVX2 registers.
const LANES: usize = 8;

/// Charged centres as SoA slices of equal length: x, y, z and charge.
pub(crate) type Charges<'a> = (&'a [f64], &'a [f64], &'a [f64], &'a [f64]);

/// `sum_j q_j |t - s_j|`.
#[inline]
pub(crate) fn sum_r(t: DVec3, sx: &[f64], sy: &[f64], sz: &[f64], q: &[f64]) -> f64 {
    let n = q.len();
    let (sx, sy, sz) = (&sx[..n], &sy[..n], &sz[..n]);
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f") {
            // SAFETY: the CPU supports AVX-512F (checked above); slices have equal lengths.
            return unsafe { x86::sum_r_avx512(t, sx, sy, sz, q) };
        }
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2 (checked above); slices have equal lengths.
            return unsafe { x86::sum_r_avx2(t, sx, sy, sz, q) };
        }
    }
    sum_r_scalar(t, sx, sy, sz, q)
}

/// Value and gradient (with respect to t) of `sum_j q_j |t - s_j|`; the gradient of |t - s| at t = s is
/// taken as zero (the kernel's subgradient there).
#[inline]
pub(crate) fn sum_r_grad(t: DVec3, sx: &[f64], sy: &[f64], sz: &[f64], q: &[f64]) -> (f64, DVec3) {
    let n = q.len();
    let (sx, sy, sz) = (&sx[..n], &sy[..n], &sz[..n]);
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f") {
            // SAFETY: as in `sum_r`.
            return unsafe { x86::sum_r_grad_avx512(t, sx, sy, sz, q) };
        }
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: as in `sum_r`.
            return unsafe { x86::sum_r_grad_avx2(t, sx, sy, sz, q) };
        }
    }
    sum_r_grad_scalar(t, sx, sy, sz, q)
}

/// `sum_j q_j |t - s_j|`, as [`sum_r`] to the bit, while adding `q_t |t - s_j|` to `scatter[j]`: the
/// kernel is symmetric, so one pass over a pair of point sets serves both directions (the FMM's near
/// field) with half the square roots.
#[inline]
pub(crate) fn sum_r_scatter(
    t: DVec3,
    (sx, sy, sz, q): Charges<'_>,
    q_t: f64,
    scatter: &mut [f64],
) -> f64 {
    let n = q.len();
    let (sx, sy, sz, scatter) = (&sx[..n], &sy[..n], &sz[..n], &mut scatter[..n]);
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f") {
            // SAFETY: the CPU supports AVX-512F (checked above); slices have equal lengths.
            return unsafe { x86::sum_r_scatter_avx512(t, (sx, sy, sz, q), q_t, scatter) };
        }
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2 (checked above); slices have equal lengths.
            return unsafe { x86::sum_r_scatter_avx2(t, (sx, sy, sz, q), q_t, scatter) };
        }
    }
    sum_r_scatter_scalar(t, (sx, sy, sz, q), q_t, scatter)
}

/// The fixed reduction of the lanes, shared by every variant.
#[inline(always)]
fn reduce(a: &[f64; LANES]) -> f64 {
    ((a[0] + a[1]) + (a[2] + a[3])) + ((a[4] + a[5]) + (a[6] + a[7]))
}

#[inline(always)]
fn term_r(t: DVec3, sx: f64, sy: f64, sz: f64) -> (f64, f64, f64, f64) {
    let dx = t.x - sx;
    let dy = t.y - sy;
    let dz = t.z - sz;
    (dx, dy, dz, (dx * dx + dy * dy + dz * dz).sqrt())
}

/// Adds centres `from..n` (the part no full block of lanes covers) to lane 0, in order.
#[inline(always)]
fn tail_r(t: DVec3, sx: &[f64], sy: &[f64], sz: &[f64], q: &[f64], from: usize, acc: &mut f64) {
    for j in from..q.len() {
        let (_, _, _, r) = term_r(t, sx[j], sy[j], sz[j]);
        *acc += q[j] * r;
    }
}

#[inline(always)]
fn tail_r_grad(
    t: DVec3,
    (sx, sy, sz, q): (&[f64], &[f64], &[f64], &[f64]),
    from: usize,
    acc: [&mut f64; 4],
) {
    let [v, gx, gy, gz] = acc;
    for j in from..q.len() {
        let (dx, dy, dz, r) = term_r(t, sx[j], sy[j], sz[j]);
        let inv = if r > 0.0 { q[j] / r } else { 0.0 };
        *v += q[j] * r;
        *gx += inv * dx;
        *gy += inv * dy;
        *gz += inv * dz;
    }
}

fn sum_r_scalar(t: DVec3, sx: &[f64], sy: &[f64], sz: &[f64], q: &[f64]) -> f64 {
    let mut acc = [0.0f64; LANES];
    let blocks = q.len() / LANES;
    for b in 0..blocks {
        for (l, a) in acc.iter_mut().enumerate() {
            let j = b * LANES + l;
            let (_, _, _, r) = term_r(t, sx[j], sy[j], sz[j]);
            *a += q[j] * r;
        }
    }
    tail_r(t, sx, sy, sz, q, blocks * LANES, &mut acc[0]);
    reduce(&acc)
}

/// Adds `q_t |t - s_j|` for centres `from..n` to `scatter` and `q_j |t - s_j|` to lane 0, in order.
#[inline(always)]
fn tail_r_scatter(
    t: DVec3,
    (sx, sy, sz, q): Charges<'_>,
    q_t: f64,
    scatter: &mut [f64],
    from: usize,
    acc: &mut f64,
) {
    for j in from..q.len() {
        let (_, _, _, r) = term_r(t, sx[j], sy[j], sz[j]);
        *acc += q[j] * r;
        scatter[j] += q_t * r;
    }
}

fn sum_r_scatter_scalar(
    t: DVec3,
    (sx, sy, sz, q): Charges<'_>,
    q_t: f64,
    scatter: &mut [f64],
) -> f64 {
    let mut acc = [0.0f64; LANES];
    let blocks = q.len() / LANES;
    for b in 0..blocks {
        for (l, a) in acc.iter_mut().enumerate() {
            let j = b * LANES + l;
            let (_, _, _, r) = term_r(t, sx[j], sy[j], sz[j]);
            *a += q[j] * r;
            scatter[j] += q_t * r;
        }
    }
    tail_r_scatter(
        t,
        (sx, sy, sz, q),
        q_t,
        scatter,
        blocks * LANES,
        &mut acc[0],
    );
    reduce(&acc)
}

fn sum_r_grad_scalar(t: DVec3, sx: &[f64], sy: &[f64], sz: &[f64], q: &[f64]) -> (f64, DVec3) {
    let mut v = [0.0f64; LANES];
    let mut gx = [0.0f64; LANES];
    let mut gy = [0.0f64; LANES];
    let mut gz = [0.0f64; LANES];
    let blocks = q.len() / LANES;
    for b in 0..blocks {
        for l in 0..LANES {
            let j = b * LANES + l;
            let (dx, dy, dz, r) = term_r(t, sx[j], sy[j], sz[j]);
            let inv = if r > 0.0 { q[j] / r } else { 0.0 };
            v[l] += q[j] * r;
            gx[l] += inv * dx;
            gy[l] += inv * dy;
            gz[l] += inv * dz;
        }
    }
    tail_r_grad(
        t,
        (sx, sy, sz, q),
        blocks * LANES,
        [&mut v[0], &mut gx[0], &mut gy[0], &mut gz[0]],
    );
    (
        reduce(&v),
        DVec3::new(reduce(&gx), reduce(&gy), reduce(&gz)),
    )
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::{Charges, LANES, reduce, tail_r, tail_r_grad, tail_r_scatter};
    use glam::DVec3;
    use std::arch::x86_64::*;

    /// The offsets `t - s_j`, distances and charges of the 8 centres from `j`, with `t` broadcast: the
    /// block every AVX-512 sum starts from.
    ///
    /// # Safety
    /// The CPU must support AVX-512F; `j + 8` must not exceed the length of any slice.
    #[target_feature(enable = "avx512f")]
    #[inline]
    unsafe fn offsets_avx512(
        [tx, ty, tz]: [__m512d; 3],
        (sx, sy, sz, q): Charges<'_>,
        j: usize,
    ) -> ([__m512d; 3], __m512d, __m512d) {
        // SAFETY: j + 8 <= len for every slice (the caller's contract).
        let (x, y, z, w) = unsafe {
            (
                _mm512_loadu_pd(sx.as_ptr().add(j)),
                _mm512_loadu_pd(sy.as_ptr().add(j)),
                _mm512_loadu_pd(sz.as_ptr().add(j)),
                _mm512_loadu_pd(q.as_ptr().add(j)),
            )
        };
        let dx = _mm512_sub_pd(tx, x);
        let dy = _mm512_sub_pd(ty, y);
        let dz = _mm512_sub_pd(tz, z);
        let d2 = _mm512_add_pd(
            _mm512_add_pd(_mm512_mul_pd(dx, dx), _mm512_mul_pd(dy, dy)),
            _mm512_mul_pd(dz, dz),
        );
        ([dx, dy, dz], _mm512_sqrt_pd(d2), w)
    }

    /// [`offsets_avx512`] for the 4 centres from `j`, with AVX2.
    ///
    /// # Safety
    /// The CPU must support AVX2; `j + 4` must not exceed the length of any slice.
    #[target_feature(enable = "avx2")]
    #[inline]
    unsafe fn offsets_avx2(
        [tx, ty, tz]: [__m256d; 3],
        (sx, sy, sz, q): Charges<'_>,
        j: usize,
    ) -> ([__m256d; 3], __m256d, __m256d) {
        // SAFETY: j + 4 <= len for every slice (the caller's contract).
        let (x, y, z, w) = unsafe {
            (
                _mm256_loadu_pd(sx.as_ptr().add(j)),
                _mm256_loadu_pd(sy.as_ptr().add(j)),
                _mm256_loadu_pd(sz.as_ptr().add(j)),
                _mm256_loadu_pd(q.as_ptr().add(j)),
            )
        };
        let dx = _mm256_sub_pd(tx, x);
        let dy = _mm256_sub_pd(ty, y);
        let dz = _mm256_sub_pd(tz, z);
        let d2 = _mm256_add_pd(
            _mm256_add_pd(_mm256_mul_pd(dx, dx), _mm256_mul_pd(dy, dy)),
            _mm256_mul_pd(dz, dz),
        );
        ([dx, dy, dz], _mm256_sqrt_pd(d2), w)
    }

    /// # Safety
    /// The CPU must support AVX-512F; all slices must have `q.len()` elements.
    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn sum_r_avx512(
        t: DVec3,
        sx: &[f64],
        sy: &[f64],
        sz: &[f64],
        q: &[f64],
    ) -> f64 {
        let (tx, ty, tz) = (
            _mm512_set1_pd(t.x),
            _mm512_set1_pd(t.y),
            _mm512_set1_pd(t.z),
        );
        let mut acc = _mm512_setzero_pd();
        let blocks = q.len() / LANES;
        for b in 0..blocks {
            let j = b * LANES;
            // SAFETY: j + LANES <= len for every slice.
            let (_, r, w) = unsafe { offsets_avx512([tx, ty, tz], (sx, sy, sz, q), j) };
            acc = _mm512_add_pd(acc, _mm512_mul_pd(w, r));
        }
        let mut lanes = [0.0f64; LANES];
        // SAFETY: `lanes` holds 8 f64.
        unsafe { _mm512_storeu_pd(lanes.as_mut_ptr(), acc) };
        tail_r(t, sx, sy, sz, q, blocks * LANES, &mut lanes[0]);
        reduce(&lanes)
    }

    /// # Safety
    /// The CPU must support AVX-512F; all slices (and `scatter`) must have `q.len()` elements.
    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn sum_r_scatter_avx512(
        t: DVec3,
        (sx, sy, sz, q): Charges<'_>,
        q_t: f64,
        scatter: &mut [f64],
    ) -> f64 {
        let (tx, ty, tz) = (
            _mm512_set1_pd(t.x),
            _mm512_set1_pd(t.y),
            _mm512_set1_pd(t.z),
        );
        let qt = _mm512_set1_pd(q_t);
        let mut acc = _mm512_setzero_pd();
        let blocks = q.len() / LANES;
        for b in 0..blocks {
            let j = b * LANES;
            // SAFETY: j + LANES <= len for every slice.
            let ((_, r, w), s) = unsafe {
                (
                    offsets_avx512([tx, ty, tz], (sx, sy, sz, q), j),
                    _mm512_loadu_pd(scatter.as_ptr().add(j)),
                )
            };
            acc = _mm512_add_pd(acc, _mm512_mul_pd(w, r));
            // SAFETY: j + LANES <= len of `scatter`.
            unsafe {
                _mm512_storeu_pd(
                    scatter.as_mut_ptr().add(j),
                    _mm512_add_pd(s, _mm512_mul_pd(qt, r)),
                )
            };
        }
        let mut lanes = [0.0f64; LANES];
        // SAFETY: `lanes` holds 8 f64.
        unsafe { _mm512_storeu_pd(lanes.as_mut_ptr(), acc) };
        tail_r_scatter(
            t,
            (sx, sy, sz, q),
            q_t,
            scatter,
            blocks * LANES,
            &mut lanes[0],
        );
        reduce(&lanes)
    }

    /// # Safety
    /// The CPU must support AVX2; all slices (and `scatter`) must have `q.len()` elements.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn sum_r_scatter_avx2(
        t: DVec3,
        (sx, sy, sz, q): Charges<'_>,
        q_t: f64,
        scatter: &mut [f64],
    ) -> f64 {
        let (tx, ty, tz) = (
            _mm256_set1_pd(t.x),
            _mm256_set1_pd(t.y),
            _mm256_set1_pd(t.z),
        );
        let qt = _mm256_set1_pd(q_t);
        let mut acc = [_mm256_setzero_pd(); 2];
        let blocks = q.len() / LANES;
        for b in 0..blocks {
            for (h, a) in acc.iter_mut().enumerate() {
                let j = b * LANES + 4 * h;
                // SAFETY: j + 4 <= len for every slice.
                let ((_, r, w), s) = unsafe {
                    (
                        offsets_avx2([tx, ty, tz], (sx, sy, sz, q), j),
                        _mm256_loadu_pd(scatter.as_ptr().add(j)),
                    )
                };
                *a = _mm256_add_pd(*a, _mm256_mul_pd(w, r));
                // SAFETY: j + 4 <= len of `scatter`.
                unsafe {
                    _mm256_storeu_pd(
                        scatter.as_mut_ptr().add(j),
                        _mm256_add_pd(s, _mm256_mul_pd(qt, r)),
                    )
                };
            }
        }
        let mut lanes = [0.0f64; LANES];
        // SAFETY: `lanes` holds 8 f64.
        unsafe {
            _mm256_storeu_pd(lanes.as_mut_ptr(), acc[0]);
            _mm256_storeu_pd(lanes.as_mut_ptr().add(4), acc[1]);
        }
        tail_r_scatter(
            t,
            (sx, sy, sz, q),
            q_t,
            scatter,
            blocks * LANES,
            &mut lanes[0],
        );
        reduce(&lanes)
    }

    /// # Safety
    /// The CPU must support AVX2; all slices must have `q.len()` elements.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn sum_r_avx2(
        t: DVec3,
        sx: &[f64],
        sy: &[f64],
        sz: &[f64],
        q: &[f64],
    ) -> f64 {
        let (tx, ty, tz) = (
            _mm256_set1_pd(t.x),
            _mm256_set1_pd(t.y),
            _mm256_set1_pd(t.z),
        );
        let mut acc = [_mm256_setzero_pd(); 2];
        let blocks = q.len() / LANES;
        for b in 0..blocks {
            for (h, a) in acc.iter_mut().enumerate() {
                let j = b * LANES + 4 * h;
                // SAFETY: j + 4 <= len for every slice.
                let (_, r, w) = unsafe { offsets_avx2([tx, ty, tz], (sx, sy, sz, q), j) };
                *a = _mm256_add_pd(*a, _mm256_mul_pd(w, r));
            }
        }
        let mut lanes = [0.0f64; LANES];
        // SAFETY: `lanes` holds 8 f64.
        unsafe {
            _mm256_storeu_pd(lanes.as_mut_ptr(), acc[0]);
            _mm256_storeu_pd(lanes.as_mut_ptr().add(4), acc[1]);
        }
        tail_r(t, sx, sy, sz, q, blocks * LANES, &mut lanes[0]);
        reduce(&lanes)
    }

    /// # Safety
    /// The CPU must support AVX-512F; all slices must have `q.len()` elements.
    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn sum_r_grad_avx512(
        t: DVec3,
        sx: &[f64],
        sy: &[f64],
        sz: &[f64],
        q: &[f64],
    ) -> (f64, DVec3) {
        let (tx, ty, tz) = (
            _mm512_set1_pd(t.x),
            _mm512_set1_pd(t.y),
            _mm512_set1_pd(t.z),
        );
        let zero = _mm512_setzero_pd();
        let (mut v, mut gx, mut gy, mut gz) = (zero, zero, zero, zero);
        let blocks = q.len() / LANES;
        for b in 0..blocks {
            let j = b * LANES;
            // SAFETY: j + LANES <= len for every slice.
            let ([dx, dy, dz], r, w) = unsafe { offsets_avx512([tx, ty, tz], (sx, sy, sz, q), j) };
            let positive = _mm512_cmp_pd_mask::<_CMP_GT_OQ>(r, zero);
            let inv = _mm512_maskz_div_pd(positive, w, r);
            v = _mm512_add_pd(v, _mm512_mul_pd(w, r));
            gx = _mm512_add_pd(gx, _mm512_mul_pd(inv, dx));
            gy = _mm512_add_pd(gy, _mm512_mul_pd(inv, dy));
            gz = _mm512_add_pd(gz, _mm512_mul_pd(inv, dz));
        }
        let mut lanes = [[0.0f64; LANES]; 4];
        for (out, reg) in lanes.iter_mut().zip([v, gx, gy, gz]) {
            // SAFETY: each row holds 8 f64.
            unsafe { _mm512_storeu_pd(out.as_mut_ptr(), reg) };
        }
        let [lv, lx, ly, lz] = &mut lanes;
        tail_r_grad(
            t,
            (sx, sy, sz, q),
            blocks * LANES,
            [&mut lv[0], &mut lx[0], &mut ly[0], &mut lz[0]],
        );
        (reduce(lv), DVec3::new(reduce(lx), reduce(ly), reduce(lz)))
    }

    /// # Safety
    /// The CPU must support AVX2; all slices must have `q.len()` elements.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn sum_r_grad_avx2(
        t: DVec3,
        sx: &[f64],
        sy: &[f64],
        sz: &[f64],
        q: &[f64],
    ) -> (f64, DVec3) {
        let (tx, ty, tz) = (
            _mm256_set1_pd(t.x),
            _mm256_set1_pd(t.y),
            _mm256_set1_pd(t.z),
        );
        let zero = _mm256_setzero_pd();
        let mut acc = [[zero; 4]; 2];
        let blocks = q.len() / LANES;
        for b in 0..blocks {
            for (h, [v, gx, gy, gz]) in acc.iter_mut().enumerate() {
                let j = b * LANES + 4 * h;
                // SAFETY: j + 4 <= len for every slice.
                let ([dx, dy, dz], r, w) =
                    unsafe { offsets_avx2([tx, ty, tz], (sx, sy, sz, q), j) };
                let positive = _mm256_cmp_pd::<_CMP_GT_OQ>(r, zero);
                let inv = _mm256_and_pd(_mm256_div_pd(w, r), positive);
                *v = _mm256_add_pd(*v, _mm256_mul_pd(w, r));
                *gx = _mm256_add_pd(*gx, _mm256_mul_pd(inv, dx));
                *gy = _mm256_add_pd(*gy, _mm256_mul_pd(inv, dy));
                *gz = _mm256_add_pd(*gz, _mm256_mul_pd(inv, dz));
            }
        }
        let mut lanes = [[0.0f64; LANES]; 4];
        for (k, out) in lanes.iter_mut().enumerate() {
            // SAFETY: each row holds 8 f64.
            unsafe {
                _mm256_storeu_pd(out.as_mut_ptr(), acc[0][k]);
                _mm256_storeu_pd(out.as_mut_ptr().add(4), acc[1][k]);
            }
        }
        let [lv, lx, ly, lz] = &mut lanes;
        tail_r_grad(
            t,
            (sx, sy, sz, q),
            blocks * LANES,
            [&mut lv[0], &mut lx[0], &mut ly[0], &mut lz[0]],
        );
        (reduce(lv), DVec3::new(reduce(lx), reduce(ly), reduce(lz)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Centres with exact hits (r = 0), a tail that no block covers, and values of mixed sign.
    fn case(n: usize) -> (DVec3, [Vec<f64>; 4]) {
        let t = DVec3::new(0.3, -1.7, 2.25);
        let mut c = [Vec::new(), Vec::new(), Vec::new(), Vec::new()];
        for j in 0..n {
            let a = j as f64;
            let (x, y, z) = if j % 11 == 3 {
                (t.x, t.y, t.z)
            } else {
                ((a * 0.37).sin() * 5.0, (a * 0.11).cos() * 4.0, a * 0.013)
            };
            c[0].push(x);
            c[1].push(y);
            c[2].push(z);
            c[3].push(((a * 1.3).sin() - 0.2) * 7.0);
        }
        (t, c)
    }

    /// Every instruction set must give the scalar lanes' bits exactly (the determinism promise), and
    /// the sums must agree with a naive sum to rounding (the lanes only reorder the additions).
    #[test]
    fn all_variants_are_bit_identical_and_match_a_naive_sum() {
        for n in [0, 1, 7, 8, 9, 64, 203] {
            let (t, [sx, sy, sz, q]) = case(n);
            let scalar = sum_r_scalar(t, &sx, &sy, &sz, &q);
            let (gv, g) = sum_r_grad_scalar(t, &sx, &sy, &sz, &q);
            assert_eq!(scalar.to_bits(), sum_r(t, &sx, &sy, &sz, &q).to_bits());
            let (dv, dg) = sum_r_grad(t, &sx, &sy, &sz, &q);
            assert_eq!(
                (gv.to_bits(), g.to_array().map(f64::to_bits)),
                (dv.to_bits(), dg.to_array().map(f64::to_bits))
            );
            assert_eq!(
                gv.to_bits(),
                scalar.to_bits(),
                "value with and without gradient"
            );
            #[cfg(target_arch = "x86_64")]
            {
                if std::arch::is_x86_feature_detected!("avx2") {
                    // SAFETY: AVX2 present; equal lengths.
                    let (v2, g2) = unsafe { x86::sum_r_grad_avx2(t, &sx, &sy, &sz, &q) };
                    let s2 = unsafe { x86::sum_r_avx2(t, &sx, &sy, &sz, &q) };
                    assert_eq!(s2.to_bits(), scalar.to_bits());
                    assert_eq!(
                        (v2.to_bits(), g2.to_array().map(f64::to_bits)),
                        (gv.to_bits(), g.to_array().map(f64::to_bits))
                    );
                }
                if std::arch::is_x86_feature_detected!("avx512f") {
                    // SAFETY: AVX-512F present; equal lengths.
                    let (v5, g5) = unsafe { x86::sum_r_grad_avx512(t, &sx, &sy, &sz, &q) };
                    let s5 = unsafe { x86::sum_r_avx512(t, &sx, &sy, &sz, &q) };
                    assert_eq!(s5.to_bits(), scalar.to_bits());
                    assert_eq!(
                        (v5.to_bits(), g5.to_array().map(f64::to_bits)),
                        (gv.to_bits(), g.to_array().map(f64::to_bits))
                    );
                }
            }
            let mut naive = 0.0;
            let mut naive_g = DVec3::ZERO;
            let mut scale = 0.0;
            for j in 0..n {
                let d = t - DVec3::new(sx[j], sy[j], sz[j]);
                naive += q[j] * d.length();
                scale += (q[j] * d.length()).abs() + q[j].abs();
                if d.length() > 0.0 {
                    naive_g += d * (q[j] / d.length());
                }
            }
            // Reordering n additions changes the result by at most ~n ulp of the absolute sum.
            let tol = 1e-14 * (scale + 1.0) * (n as f64 + 1.0);
            assert!((scalar - naive).abs() <= tol, "{n}: {scalar} vs {naive}");
            assert!((g - naive_g).length() <= tol, "{n}: {g} vs {naive_g}");
        }
    }

    /// The scattering sum returns `sum_r`'s bits on every instruction set, and adds `q_t |t - s_j|` to
    /// every `scatter[j]` with the same bits on every instruction set (the FMM's near field relies on
    /// both for its determinism).
    #[test]
    fn scatter_variants_are_bit_identical_and_add_the_transposed_terms() {
        for n in [0, 1, 7, 8, 9, 64, 203] {
            let (t, [sx, sy, sz, q]) = case(n);
            let q_t = -2.75;
            let start: Vec<f64> = (0..n).map(|j| (j as f64 * 0.7).cos()).collect();
            let mut scalar_out = start.clone();
            let sum = sum_r_scatter_scalar(t, (&sx, &sy, &sz, &q), q_t, &mut scalar_out);
            assert_eq!(sum.to_bits(), sum_r_scalar(t, &sx, &sy, &sz, &q).to_bits());
            for j in 0..n {
                let r = (t - DVec3::new(sx[j], sy[j], sz[j])).length();
                let expected = start[j] + q_t * r;
                assert!(
                    (scalar_out[j] - expected).abs() <= 1e-13 * (expected.abs() + 1.0),
                    "{n}/{j}: {} vs {expected}",
                    scalar_out[j]
                );
            }
            let mut dispatched = start.clone();
            let s = sum_r_scatter(t, (&sx, &sy, &sz, &q), q_t, &mut dispatched);
            assert_eq!(s.to_bits(), sum.to_bits());
            assert_eq!(
                dispatched.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                scalar_out.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
            );
            #[cfg(target_arch = "x86_64")]
            {
                type Variant = unsafe fn(DVec3, Charges<'_>, f64, &mut [f64]) -> f64;
                let mut variants: Vec<Variant> = Vec::new();
                if std::arch::is_x86_feature_detected!("avx2") {
                    variants.push(x86::sum_r_scatter_avx2);
                }
                if std::arch::is_x86_feature_detected!("avx512f") {
                    variants.push(x86::sum_r_scatter_avx512);
                }
                for variant in variants {
                    let mut out = start.clone();
                    // SAFETY: the variant's instruction set is present; equal lengths.
                    let v = unsafe { variant(t, (&sx, &sy, &sz, &q), q_t, &mut out) };
                    assert_eq!(v.to_bits(), sum.to_bits());
                    assert_eq!(
                        out.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                        scalar_out.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
                    );
                }
            }
        }
    }
}
