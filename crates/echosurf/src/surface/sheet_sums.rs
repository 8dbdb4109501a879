//! The weighted sums of the oriented-point sheet's field ([`super::sheet`]) over runs of points,
//! four points at a time.
//!
//! Every evaluation of the sheet's field visits a few hundred points and takes a Gaussian weight of
//! each; in scalar code with the C library's `exp` and a branch per point, that was most of the time
//! of drawing a sheet. Here the points are SoA slices, every point of a run goes to lane `j % 4` of
//! the accumulators (a run's last partial block padded with weightless points far away), and the
//! weight's exponential is a fixed polynomial of plain IEEE additions and multiplications. The same
//! operations run in the same order with AVX2 or as scalar code, so results are bit-identical on
//! every machine whatever the instruction set.

// Calling the AVX2 variant after the runtime check, and its unaligned loads, each bounded by the
// block arithmetic next to it.
#![allow(unsafe_code)]

use glam::DVec3;

/// Accumulator lanes: one AVX2 register of f64.
const LANES: usize = 4;

/// Oriented points as SoA slices of one length: position, unit normal and how many given points each
/// stands for.
#[derive(Debug, Clone)]
pub(super) struct SheetPoints {
    x: Vec<f64>,
    y: Vec<f64>,
    z: Vec<f64>,
    nx: Vec<f64>,
    ny: Vec<f64>,
    nz: Vec<f64>,
    count: Vec<f64>,
}

impl SheetPoints {
    pub(super) fn new(points: &[DVec3], normals: &[DVec3], counts: &[f64]) -> SheetPoints {
        SheetPoints {
            x: points.iter().map(|p| p.x).collect(),
            y: points.iter().map(|p| p.y).collect(),
            z: points.iter().map(|p| p.z).collect(),
            nx: normals.iter().map(|n| n.x).collect(),
            ny: normals.iter().map(|n| n.y).collect(),
            nz: normals.iter().map(|n| n.z).collect(),
            count: counts.to_vec(),
        }
    }

    /// The slices of the points `run`.
    fn slices(&self, run: std::ops::Range<usize>) -> Slices<'_> {
        [
            &self.x[run.clone()],
            &self.y[run.clone()],
            &self.z[run.clone()],
            &self.nx[run.clone()],
            &self.ny[run.clone()],
            &self.nz[run.clone()],
            &self.count[run],
        ]
    }
}

/// The shape of the weights and of the bridging test, squared distances in mm^2.
#[derive(Debug, Clone, Copy)]
pub(super) struct SumShape {
    /// 1 / h^2.
    pub(super) inv_h2: f64,
    /// Points farther than the support weigh nothing.
    pub(super) support2: f64,
    /// A point may bridge to `x` when `x` lies within reach of its plane ...
    pub(super) reach2: f64,
    /// ... and within this of it across its normal.
    pub(super) bridge2: f64,
}

/// The sums over the points within the support of `x`, with `w_i = count_i exp(-|d_i|^2 / h^2)`,
/// `d_i = x - p_i` and `a_i = d_i . n_i`.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(super) struct Sums {
    /// `sum w_i`.
    pub(super) weight: f64,
    /// `sum w_i a_i`.
    pub(super) value: f64,
    /// `sum w_i a_i^2`.
    pub(super) value2: f64,
    /// `sum w_i n_i`.
    pub(super) normal: DVec3,
    /// `sum w_i a_i d_i`.
    pub(super) along_offsets: DVec3,
    /// `sum w_i d_i`.
    pub(super) offsets: DVec3,
    /// Over the points that could bridge to `x` (within reach of its plane, within the bridge across
    /// it): `sum count_i u_i`, `u_i` the unit direction from the point to `x` in its plane ...
    pub(super) around: DVec3,
    /// ... and `sum count_i`. Both zero unless asked for.
    pub(super) bridging: f64,
}

/// Per-lane sums, in the order of [`Sums`]'s fields (vectors as x, y, z).
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct LaneSums([[f64; LANES]; 16]);

const WEIGHT: usize = 0;
const VALUE: usize = 1;
const VALUE2: usize = 2;
const NORMAL: usize = 3;
const ALONG_OFFSETS: usize = 6;
const OFFSETS: usize = 9;
const AROUND: usize = 12;
const BRIDGING: usize = 15;

impl LaneSums {
    /// The lanes reduced in one fixed tree.
    pub(super) fn reduce(&self) -> Sums {
        let r = |k: usize| {
            let a = &self.0[k];
            (a[0] + a[1]) + (a[2] + a[3])
        };
        let v = |k: usize| DVec3::new(r(k), r(k + 1), r(k + 2));
        Sums {
            weight: r(WEIGHT),
            value: r(VALUE),
            value2: r(VALUE2),
            normal: v(NORMAL),
            along_offsets: v(ALONG_OFFSETS),
            offsets: v(OFFSETS),
            around: v(AROUND),
            bridging: r(BRIDGING),
        }
    }
}

/// Adds the points `run` of `points` to `sums` for the field at `x`; the bridging sums only when
/// `bridging` (they cost a square root and a division per point).
pub(super) fn add_run(
    x: DVec3,
    points: &SheetPoints,
    run: std::ops::Range<usize>,
    shape: SumShape,
    bridging: bool,
    sums: &mut LaneSums,
) {
    let slices = points.slices(run);
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2 (checked above); the slices have one length.
            unsafe {
                if bridging {
                    x86::add_run_avx2::<true>(x, slices, shape, sums);
                } else {
                    x86::add_run_avx2::<false>(x, slices, shape, sums);
                }
            }
            return;
        }
    }
    if bridging {
        add_run_scalar::<true>(x, slices, shape, sums);
    } else {
        add_run_scalar::<false>(x, slices, shape, sums);
    }
}

/// The SoA slices of a run: x, y, z, nx, ny, nz, count.
type Slices<'a> = [&'a [f64]; 7];

/// A run's last partial block: the points from `from` (fewer than [`LANES`]), the rest of the block
/// far from `x` with no count and no normal (outside any support, they add zeros).
fn padded_tail(x: DVec3, s: Slices<'_>, from: usize) -> [[f64; LANES]; 7] {
    let far = [x.x + 1.0e6, x.y, x.z, 0.0, 0.0, 0.0, 0.0];
    let mut block = [[0.0; LANES]; 7];
    for (k, column) in block.iter_mut().enumerate() {
        for (l, value) in column.iter_mut().enumerate() {
            *value = s[k].get(from + l).copied().unwrap_or(far[k]);
        }
    }
    block
}

/// `exp(-t)` for `t >= 0`, to a few ulp; arguments beyond 700 are taken as 700. `2^k` times the
/// degree-13 Taylor polynomial of `exp(r)`, `r = -t - k ln 2` within ln 2 / 2 of zero.
#[inline(always)]
fn exp_neg_scalar(t: f64) -> f64 {
    let x = 0.0 - t.min(700.0);
    let k = (x * std::f64::consts::LOG2_E).round_ties_even();
    let r = (x - k * LN2_HI) - k * LN2_LO;
    // Estrin's scheme: pairs, then pairs of pairs, so the chain of dependent operations is short.
    let c = &EXP_TAYLOR;
    let (r2, pair) = (r * r, |k: usize| c[k] + c[k + 1] * r);
    let r4 = r2 * r2;
    let low = (pair(0) + pair(2) * r2) + (pair(4) + pair(6) * r2) * r4;
    let high = (pair(8) + pair(10) * r2) + pair(12) * r4;
    let p = low + high * (r4 * r4);
    let scale = f64::from_bits((k + EXPONENT_MAGIC).to_bits() << 52);
    p * scale
}

/// ln 2 split so that `k * LN2_HI` is exact for the `k` of [`exp_neg_scalar`].
const LN2_HI: f64 = f64::from_bits(0x3fe6_2e42_fee0_0000);
const LN2_LO: f64 = f64::from_bits(0x3dea_39ef_3579_3c76);

/// `2^52 + 1023`: `k + EXPONENT_MAGIC` holds `k + 1023` in its low mantissa bits, which shifted up
/// by 52 are the bits of `2^k`.
const EXPONENT_MAGIC: f64 = 4_503_599_627_371_519.0;

/// 1/0!, 1/1!, ..., 1/13!: the Taylor coefficients of `exp` at zero.
const EXP_TAYLOR: [f64; 14] = [
    1.0,
    1.0,
    0.5,
    1.0 / 6.0,
    1.0 / 24.0,
    1.0 / 120.0,
    1.0 / 720.0,
    1.0 / 5_040.0,
    1.0 / 40_320.0,
    1.0 / 362_880.0,
    1.0 / 3_628_800.0,
    1.0 / 39_916_800.0,
    1.0 / 479_001_600.0,
    1.0 / 6_227_020_800.0,
];

/// [`add_run`] as scalar code, lane by lane in the vector variant's operation order.
fn add_run_scalar<const BRIDGING_SUMS: bool>(
    x: DVec3,
    s: Slices<'_>,
    shape: SumShape,
    sums: &mut LaneSums,
) {
    let n = s[0].len();
    let full = n - n % LANES;
    let mut j = 0;
    while j < full {
        let block: [[f64; LANES]; 7] =
            std::array::from_fn(|k| std::array::from_fn(|l| s[k][j + l]));
        add_block_scalar::<BRIDGING_SUMS>(x, &block, shape, sums);
        j += LANES;
    }
    if full < n {
        add_block_scalar::<BRIDGING_SUMS>(x, &padded_tail(x, s, full), shape, sums);
    }
}

#[inline(always)]
fn add_block_scalar<const BRIDGING_SUMS: bool>(
    x: DVec3,
    b: &[[f64; LANES]; 7],
    shape: SumShape,
    sums: &mut LaneSums,
) {
    let offsets: [[f64; 3]; LANES] =
        std::array::from_fn(|l| [x.x - b[0][l], x.y - b[1][l], x.z - b[2][l]]);
    let squared: [f64; LANES] = offsets.map(|d| (d[0] * d[0] + d[1] * d[1]) + d[2] * d[2]);
    // Most blocks of a run lie wholly beyond the support: they add nothing.
    if !squared.iter().any(|&d2| d2 <= shape.support2) {
        return;
    }
    let a = &mut sums.0;
    for l in 0..LANES {
        let (d, d2) = (offsets[l], squared[l]);
        let n = [b[3][l], b[4][l], b[5][l]];
        let count = b[6][l];
        let inside = d2 <= shape.support2;
        let along = (d[0] * n[0] + d[1] * n[1]) + d[2] * n[2];
        let e = exp_neg_scalar(d2 * shape.inv_h2);
        let w = if inside { count * e } else { 0.0 };
        let wa = w * along;
        a[WEIGHT][l] += w;
        a[VALUE][l] += wa;
        a[VALUE2][l] += wa * along;
        for k in 0..3 {
            a[NORMAL + k][l] += w * n[k];
            a[ALONG_OFFSETS + k][l] += wa * d[k];
            a[OFFSETS + k][l] += w * d[k];
        }
        if BRIDGING_SUMS {
            let across = [
                d[0] - n[0] * along,
                d[1] - n[1] * along,
                d[2] - n[2] * along,
            ];
            let a2 = (across[0] * across[0] + across[1] * across[1]) + across[2] * across[2];
            let inv = 1.0 / a2.sqrt();
            let bridges =
                inside && along * along <= shape.reach2 && a2 <= shape.bridge2 && a2 > 0.0;
            let c = if bridges { count } else { 0.0 };
            for k in 0..3 {
                a[AROUND + k][l] += c * (across[k] * inv);
            }
            a[BRIDGING][l] += c;
        }
    }
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::*;
    use std::arch::x86_64::*;

    /// [`exp_neg_scalar`] on four lanes, the same operations in the same order.
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[target_feature(enable = "avx2")]
    #[inline]
    unsafe fn exp_neg_avx2(t: __m256d) -> __m256d {
        let x = _mm256_sub_pd(_mm256_setzero_pd(), _mm256_min_pd(t, _mm256_set1_pd(700.0)));
        let k = _mm256_round_pd::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(
            _mm256_mul_pd(x, _mm256_set1_pd(std::f64::consts::LOG2_E)),
        );
        let r = _mm256_sub_pd(
            _mm256_sub_pd(x, _mm256_mul_pd(k, _mm256_set1_pd(LN2_HI))),
            _mm256_mul_pd(k, _mm256_set1_pd(LN2_LO)),
        );
        let (add, mul, c) = (_mm256_add_pd, _mm256_mul_pd, |k: usize| {
            _mm256_set1_pd(EXP_TAYLOR[k])
        });
        let (r2, pair) = (mul(r, r), |k: usize| add(c(k), mul(c(k + 1), r)));
        let r4 = mul(r2, r2);
        let low = add(
            add(pair(0), mul(pair(2), r2)),
            mul(add(pair(4), mul(pair(6), r2)), r4),
        );
        let high = add(add(pair(8), mul(pair(10), r2)), mul(pair(12), r4));
        let p = add(low, mul(high, mul(r4, r4)));
        let bits = _mm256_castpd_si256(_mm256_add_pd(k, _mm256_set1_pd(EXPONENT_MAGIC)));
        let scale = _mm256_castsi256_pd(_mm256_slli_epi64::<52>(bits));
        _mm256_mul_pd(p, scale)
    }

    /// [`add_run`] with AVX2.
    ///
    /// # Safety
    /// The CPU must support AVX2; the slices must have one length.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn add_run_avx2<const BRIDGING_SUMS: bool>(
        x: DVec3,
        s: Slices<'_>,
        shape: SumShape,
        sums: &mut LaneSums,
    ) {
        let n = s[0].len();
        let full = n - n % LANES;
        let mut acc = [_mm256_setzero_pd(); 16];
        for (a, lanes) in acc.iter_mut().zip(&sums.0) {
            // SAFETY: each lane array holds LANES = 4 f64.
            *a = unsafe { _mm256_loadu_pd(lanes.as_ptr()) };
        }
        let mut block = [_mm256_setzero_pd(); 7];
        let mut j = 0;
        while j < full {
            for (b, column) in block.iter_mut().zip(&s) {
                // SAFETY: j + LANES <= full <= the length of every slice.
                *b = unsafe { _mm256_loadu_pd(column.as_ptr().add(j)) };
            }
            // SAFETY: AVX2 is supported (the caller's contract).
            unsafe { add_block_avx2::<BRIDGING_SUMS>(x, &block, shape, &mut acc) };
            j += LANES;
        }
        if full < n {
            let tail = padded_tail(x, s, full);
            for (b, column) in block.iter_mut().zip(&tail) {
                // SAFETY: each padded column holds LANES = 4 f64.
                *b = unsafe { _mm256_loadu_pd(column.as_ptr()) };
            }
            // SAFETY: as above.
            unsafe { add_block_avx2::<BRIDGING_SUMS>(x, &block, shape, &mut acc) };
        }
        for (k, a) in acc.iter().enumerate() {
            // SAFETY: each lane array holds LANES = 4 f64.
            unsafe { _mm256_storeu_pd(sums.0[k].as_mut_ptr(), *a) };
        }
    }

    /// # Safety
    /// The CPU must support AVX2.
    #[target_feature(enable = "avx2")]
    #[inline]
    unsafe fn add_block_avx2<const BRIDGING_SUMS: bool>(
        x: DVec3,
        b: &[__m256d; 7],
        shape: SumShape,
        a: &mut [__m256d; 16],
    ) {
        let (add, sub, mul) = (_mm256_add_pd, _mm256_sub_pd, _mm256_mul_pd);
        let d = [
            sub(_mm256_set1_pd(x.x), b[0]),
            sub(_mm256_set1_pd(x.y), b[1]),
            sub(_mm256_set1_pd(x.z), b[2]),
        ];
        let n = [b[3], b[4], b[5]];
        let count = b[6];
        let d2 = add(add(mul(d[0], d[0]), mul(d[1], d[1])), mul(d[2], d[2]));
        let inside = _mm256_cmp_pd::<_CMP_LE_OQ>(d2, _mm256_set1_pd(shape.support2));
        if _mm256_movemask_pd(inside) == 0 {
            return;
        }
        let along = add(add(mul(d[0], n[0]), mul(d[1], n[1])), mul(d[2], n[2]));
        // SAFETY: AVX2 is supported (the caller's contract).
        let e = unsafe { exp_neg_avx2(mul(d2, _mm256_set1_pd(shape.inv_h2))) };
        let w = _mm256_and_pd(mul(count, e), inside);
        let wa = mul(w, along);
        a[WEIGHT] = add(a[WEIGHT], w);
        a[VALUE] = add(a[VALUE], wa);
        a[VALUE2] = add(a[VALUE2], mul(wa, along));
        for k in 0..3 {
            a[NORMAL + k] = add(a[NORMAL + k], mul(w, n[k]));
            a[ALONG_OFFSETS + k] = add(a[ALONG_OFFSETS + k], mul(wa, d[k]));
            a[OFFSETS + k] = add(a[OFFSETS + k], mul(w, d[k]));
        }
        if BRIDGING_SUMS {
            let across = [
                sub(d[0], mul(n[0], along)),
                sub(d[1], mul(n[1], along)),
                sub(d[2], mul(n[2], along)),
            ];
            let a2 = add(
                add(mul(across[0], across[0]), mul(across[1], across[1])),
                mul(across[2], across[2]),
            );
            let inv = _mm256_div_pd(_mm256_set1_pd(1.0), _mm256_sqrt_pd(a2));
            let bridges = _mm256_and_pd(
                _mm256_and_pd(
                    inside,
                    _mm256_cmp_pd::<_CMP_LE_OQ>(mul(along, along), _mm256_set1_pd(shape.reach2)),
                ),
                _mm256_and_pd(
                    _mm256_cmp_pd::<_CMP_LE_OQ>(a2, _mm256_set1_pd(shape.bridge2)),
                    _mm256_cmp_pd::<_CMP_GT_OQ>(a2, _mm256_setzero_pd()),
                ),
            );
            let c = _mm256_and_pd(count, bridges);
            for k in 0..3 {
                a[AROUND + k] = add(a[AROUND + k], mul(c, mul(across[k], inv)));
            }
            a[BRIDGING] = add(a[BRIDGING], c);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[test]
    fn the_exponential_is_within_a_few_ulp_of_the_library_one() {
        for i in 0..=20_000 {
            let t = i as f64 * 9.5e-4;
            let (ours, exact) = (exp_neg_scalar(t), (-t).exp());
            assert!(
                (ours - exact).abs() <= 4.0 * f64::EPSILON * exact,
                "exp(-{t}): {ours} against {exact}"
            );
        }
        assert_eq!(exp_neg_scalar(0.0), 1.0);
        assert!(exp_neg_scalar(1.0e9) > 0.0 && exp_neg_scalar(1.0e9) < 1.0e-300);
    }

    /// Points around the origin within a few mm, normals of any direction.
    fn random_points(n: usize, seed: u64) -> (Vec<DVec3>, Vec<DVec3>, Vec<f64>) {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut unit = || DVec3::new(rng.random(), rng.random(), rng.random());
        let points: Vec<DVec3> = (0..n).map(|_| unit() * 5.0 - 2.5).collect();
        let normals: Vec<DVec3> = (0..n).map(|_| (unit() - 0.5).normalize()).collect();
        let counts: Vec<f64> = (0..n).map(|i| 1.0 + (i % 3) as f64).collect();
        (points, normals, counts)
    }

    /// The sums written out point by point from their definitions, with the library's `exp`.
    fn reference(x: DVec3, p: &[DVec3], n: &[DVec3], c: &[f64], shape: SumShape) -> Sums {
        let mut s = Sums::default();
        for i in 0..p.len() {
            let d = x - p[i];
            if d.length_squared() > shape.support2 {
                continue;
            }
            let along = d.dot(n[i]);
            let w = c[i] * (-d.length_squared() * shape.inv_h2).exp();
            s.weight += w;
            s.value += w * along;
            s.value2 += w * along * along;
            s.normal += w * n[i];
            s.along_offsets += w * along * d;
            s.offsets += w * d;
            let across = d - n[i] * along;
            if along * along <= shape.reach2
                && across.length_squared() <= shape.bridge2
                && let Some(u) = across.try_normalize()
            {
                s.around += c[i] * u;
                s.bridging += c[i];
            }
        }
        s
    }

    fn shape() -> SumShape {
        SumShape {
            inv_h2: 1.0 / 0.64,
            support2: 2.4 * 2.4,
            reach2: 0.75 * 0.75,
            bridge2: 4.0,
        }
    }

    #[test]
    fn sums_over_runs_match_the_definition() {
        let (p, n, c) = random_points(103, 5);
        let points = SheetPoints::new(&p, &n, &c);
        let mut bridged_somewhere = false;
        for q in [DVec3::ZERO, DVec3::new(0.3, -1.1, 0.8), DVec3::splat(2.0)] {
            let mut lanes = LaneSums::default();
            // Runs of every length modulo four.
            for run in [0..10, 10..11, 11..50, 50..103] {
                add_run(q, &points, run, shape(), true, &mut lanes);
            }
            let (ours, exact) = (lanes.reduce(), reference(q, &p, &n, &c, shape()));
            assert_eq!(ours.bridging, exact.bridging, "at {q}");
            bridged_somewhere |= exact.bridging > 0.0;
            let scale = exact.weight.max(1.0);
            let close = |a: f64, b: f64| (a - b).abs() <= 1e-12 * scale;
            assert!(close(ours.weight, exact.weight) && exact.weight > 0.0);
            assert!(close(ours.value, exact.value) && close(ours.value2, exact.value2));
            for (a, b) in [
                (ours.normal, exact.normal),
                (ours.along_offsets, exact.along_offsets),
                (ours.offsets, exact.offsets),
                (ours.around, exact.around),
            ] {
                assert!(a.distance(b) <= 1e-12 * scale, "{a} against {b} at {q}");
            }
            // Without the bridging sums, the others are the same to the bit.
            let mut plain = LaneSums::default();
            for run in [0..10, 10..11, 11..50, 50..103] {
                add_run(q, &points, run, shape(), false, &mut plain);
            }
            let plain = plain.reduce();
            assert_eq!((plain.around, plain.bridging), (DVec3::ZERO, 0.0));
            assert_eq!(
                Sums {
                    around: ours.around,
                    bridging: ours.bridging,
                    ..plain
                },
                ours
            );
        }
        assert!(bridged_somewhere, "the bridging sums are checked somewhere");
    }

    #[test]
    fn the_scalar_code_gives_the_vector_codes_bits() {
        let (p, n, c) = random_points(77, 9);
        let points = SheetPoints::new(&p, &n, &c);
        for q in [DVec3::new(0.1, 0.2, -0.4), DVec3::new(-1.7, 0.9, 1.3)] {
            for bridging in [false, true] {
                let mut dispatched = LaneSums::default();
                let mut scalar = LaneSums::default();
                for run in [0..13, 13..14, 14..77] {
                    add_run(q, &points, run.clone(), shape(), bridging, &mut dispatched);
                    let slices = points.slices(run);
                    if bridging {
                        add_run_scalar::<true>(q, slices, shape(), &mut scalar);
                    } else {
                        add_run_scalar::<false>(q, slices, shape(), &mut scalar);
                    }
                }
                let bits = |s: &LaneSums| s.0.map(|lane| lane.map(f64::to_bits));
                assert_eq!(
                    bits(&dispatched),
                    bits(&scalar),
                    "at {q}, bridging {bridging}"
                );
            }
        }
    }
}
