//! Splatting frames into the grid (PLUS `vtkPlusPasteSliceIntoVolume`, double arithmetic).
//!
//! Per frame, the pixel positions in voxel-index space are computed in parallel (rows), then the
//! grid is updated in parallel over z-slabs: each slab applies, in raster order, only the updates
//! that fall inside it. A voxel therefore sees exactly the sequence of updates a single-threaded
//! run would give it, whatever the number of threads.

use glam::DVec3;
use rayon::prelude::*;

use super::{
    Compounding, GridGeometry, Interpolation, PositionArithmetic, ReconstructionStats, VoxelOptions,
};
use crate::io::{PoseResolution, TrackedSequence};
use crate::progress::Progress;
use crate::{Error, Result};

/// Accumulation added by one whole pixel (PLUS `ACCUMULATION_MULTIPLIER`).
pub(super) const ACC_UNIT: u32 = 256;
/// Largest accumulation value (u16).
pub(super) const ACC_MAX: u32 = 65535;
/// Above this a MEAN insertion would overflow (PLUS `ACCUMULATION_THRESHOLD`).
pub(super) const ACC_THRESHOLD: u32 = ACC_MAX - ACC_UNIT;

/// Storage type of voxel values.
pub(super) trait Store: Copy + Send + Sync + Default + 'static {
    fn get(self) -> f64;
    /// Stores an already-typed value (saturating for u8).
    fn put(v: f64) -> Self;
}

impl Store for u8 {
    fn get(self) -> f64 {
        self as f64
    }
    fn put(v: f64) -> Self {
        v as u8
    }
}

impl Store for f32 {
    fn get(self) -> f64 {
        self as f64
    }
    fn put(v: f64) -> Self {
        v as f32
    }
}

/// One in PLUS's fixed-point type (14 fractional bits).
const FIXED_ONE: i64 = 1 << 14;

/// A double in PLUS's fixed point: nearest multiple of 2^-14, ties to even (PLUS adds a magic
/// constant, which rounds the same way).
fn to_fixed(x: f64) -> i64 {
    (x * FIXED_ONE as f64).round_ties_even() as i64
}

/// PLUS's rounding of positions and values: `floor(x + 0.5)`.
#[inline]
pub(super) fn plus_round(x: f64) -> f64 {
    (x + 0.5).floor()
}

/// C's `(T)x` for the stored type: truncation toward zero for integer data.
#[inline]
pub(super) fn c_cast(x: f64, integer: bool) -> f64 {
    if integer { x.trunc() } else { x }
}

/// Allocates a zeroed buffer, turning allocation failure into an error instead of an abort.
pub(super) fn try_zeroed<T: Clone + Default>(n: usize, what: &str) -> Result<Vec<T>> {
    let mut v = Vec::new();
    crate::resources::fallibly(|| v.try_reserve_exact(n)).map_err(|_| {
        Error::ResourceLimit(format!(
            "could not allocate the {what} ({n} voxels); use a coarser spacing"
        ))
    })?;
    v.resize(n, T::default());
    Ok(v)
}

/// Inclusive pixel ranges [x0, x1], [y0, y1] inserted, or None when the clip leaves nothing.
/// PLUS includes the far edge `origin + size` when it lies inside the image.
pub(super) fn clip_ranges(
    width: usize,
    height: usize,
    options: &VoxelOptions,
) -> Option<[usize; 4]> {
    if width == 0 || height == 0 {
        return None;
    }
    let (mut x0, mut x1, mut y0, mut y1) = (0, width - 1, 0, height - 1);
    if let Some(c) = options
        .clip
        .filter(|c| c.size_px[0] > 0 && c.size_px[1] > 0)
    {
        x0 = x0.max(c.origin_px[0]);
        x1 = x1.min(c.origin_px[0].saturating_add(c.size_px[0]));
        y0 = y0.max(c.origin_px[1]);
        y1 = y1.min(c.origin_px[1].saturating_add(c.size_px[1]));
    }
    (x0 <= x1 && y0 <= y1).then_some([x0, x1, y0, y1])
}

/// Bytes one frame's splatting holds at once: its grey levels (f32 per pixel) and its clipped pixels'
/// entries twice (per row, then per slab).
pub(super) fn frame_working_bytes(sequence: &TrackedSequence, options: &VoxelOptions) -> u128 {
    let grey = (sequence.width * sequence.height) as u128 * 4;
    let Some([x0, x1, y0, y1]) = clip_ranges(sequence.width, sequence.height, options) else {
        return grey;
    };
    let entry = match options.interpolation {
        Interpolation::NearestNeighbor => std::mem::size_of::<NnEntry>(),
        Interpolation::Linear => std::mem::size_of::<LinearEntry>(),
    } as u128;
    grey + ((x1 - x0 + 1) * (y1 - y0 + 1)) as u128 * 2 * entry
}

/// Grey level per pixel of a frame; multi-channel pixels are averaged (rounded for integer data).
fn frame_grey(sequence: &TrackedSequence, frame: usize, integer: bool) -> Vec<f32> {
    let mut grey = sequence.frame_f32(frame);
    if integer && sequence.channels > 1 {
        for g in &mut grey {
            *g = plus_round(*g as f64) as f32;
        }
    }
    grey
}

/// One pixel that lands in the grid: flat voxel index (nearest neighbour) or position in voxel
/// index space (trilinear), with its grey level.
#[derive(Clone, Copy)]
struct NnEntry {
    voxel: u32,
    value: f32,
}

#[derive(Clone, Copy)]
struct LinearEntry {
    position: [f64; 3],
    value: f32,
}

/// Inserts every placed frame (every `skip_interval`-th by frame number, as PLUS does) and returns
/// the values and the accumulation buffer.
pub(super) fn paste_frames<T: Store>(
    sequence: &TrackedSequence,
    poses: &PoseResolution,
    options: &VoxelOptions,
    geometry: &GridGeometry,
    integer: bool,
    stats: &mut ReconstructionStats,
    progress: &dyn Progress,
) -> Result<(Vec<T>, Vec<u16>)> {
    let n = geometry.dims.iter().product::<usize>();
    let mut values: Vec<T> = try_zeroed(n, "voxel values")?;
    let mut accumulation: Vec<u16> = try_zeroed(n, "accumulation buffer")?;
    let world_to_index = super::world_to_index(geometry);
    let dims = geometry.dims.map(|d| d as i64);
    let slice_len = geometry.dims[0] * geometry.dims[1];
    // Several slabs per thread so uneven sweeps still balance; any split gives the same bytes.
    let slab_count = (rayon::current_num_threads() * 4).clamp(1, geometry.dims[2].max(1));
    let slab_depth = geometry.dims[2].div_ceil(slab_count).max(1);
    let chunk_len = (slab_depth * slice_len).max(1);
    let slabs = n.div_ceil(chunk_len);

    let inserted: Vec<_> = poses
        .poses
        .iter()
        .filter(|p| p.frame_index % options.skip_interval == 0)
        .collect();
    stats.frames_skipped = poses.poses.len() - inserted.len();
    let Some([x0, x1, y0, y1]) = clip_ranges(sequence.width, sequence.height, options) else {
        return Ok((values, accumulation));
    };
    let row_len = x1 - x0 + 1;
    let rejection = options.pixel_rejection_threshold;

    progress.start("splatting", inserted.len() as u64);
    for (done, pose) in inserted.iter().enumerate() {
        let m = world_to_index * pose.image_to_world;
        let x_axis = m.x_axis.truncate();
        let y_axis = m.y_axis.truncate();
        let origin = m.w_axis.truncate();
        if !(x_axis.is_finite() && y_axis.is_finite() && origin.is_finite()) {
            return Err(Error::InvalidInput(format!(
                "frame {}: its Image->World matrix is not finite",
                pose.frame_index
            )));
        }
        let grey = frame_grey(sequence, pose.frame_index, integer);
        let width = sequence.width;
        let keep = |v: f32| rejection.is_none_or(|t| v as f64 >= t);
        // PLUS's incremental form: row start = origin + y * yAxis, pixel = row start + x * xAxis;
        // in fixed point every term is an exact multiple of 2^-14.
        let fixed = options.position_arithmetic == PositionArithmetic::FixedPoint14;
        let q = |v: DVec3| -> [i64; 3] { [to_fixed(v.x), to_fixed(v.y), to_fixed(v.z)] };
        let (qx, qy, qo) = (q(x_axis), q(y_axis), q(origin));
        let position = |x: usize, y: usize| -> [f64; 3] {
            if fixed {
                let (xi, yi) = (x as i64, y as i64);
                std::array::from_fn(|a| (qo[a] + yi * qy[a] + xi * qx[a]) as f64 / FIXED_ONE as f64)
            } else {
                let (xf, yf) = (x as f64, y as f64);
                let start = [
                    origin.x + yf * y_axis.x,
                    origin.y + yf * y_axis.y,
                    origin.z + yf * y_axis.z,
                ];
                [
                    start[0] + xf * x_axis.x,
                    start[1] + xf * x_axis.y,
                    start[2] + xf * x_axis.z,
                ]
            }
        };
        let mut overflows = 0u64;
        match options.interpolation {
            Interpolation::NearestNeighbor => {
                let rows: Vec<Vec<NnEntry>> = (y0..=y1)
                    .into_par_iter()
                    .map(|y| {
                        let mut row = Vec::with_capacity(row_len);
                        for x in x0..=x1 {
                            let value = grey[y * width + x];
                            if !keep(value) {
                                continue;
                            }
                            let p = position(x, y);
                            let i = plus_round(p[0]);
                            let j = plus_round(p[1]);
                            let k = plus_round(p[2]);
                            if i < 0.0
                                || j < 0.0
                                || k < 0.0
                                || i >= dims[0] as f64
                                || j >= dims[1] as f64
                                || k >= dims[2] as f64
                            {
                                continue;
                            }
                            let voxel = ((k as usize * geometry.dims[1] + j as usize)
                                * geometry.dims[0]
                                + i as usize) as u32;
                            row.push(NnEntry { voxel, value });
                        }
                        row
                    })
                    .collect();
                // Each slab's pixels, still in raster order.
                let mut buckets: Vec<Vec<NnEntry>> = vec![Vec::new(); slabs];
                for e in rows.into_iter().flatten() {
                    stats.pixels_inserted += 1;
                    buckets[e.voxel as usize / chunk_len].push(e);
                }
                overflows += values
                    .par_chunks_mut(chunk_len)
                    .zip(accumulation.par_chunks_mut(chunk_len))
                    .zip(buckets.par_iter())
                    .enumerate()
                    .map(|(slab, ((vals, accs), bucket))| {
                        let lo = slab * chunk_len;
                        let mut overflow = 0u64;
                        for e in bucket {
                            let v = e.voxel as usize;
                            overflow += insert_nn(
                                &mut vals[v - lo],
                                &mut accs[v - lo],
                                e.value as f64,
                                options.compounding,
                                integer,
                            );
                        }
                        overflow
                    })
                    .sum::<u64>();
            }
            Interpolation::Linear => {
                let rows: Vec<Vec<LinearEntry>> = (y0..=y1)
                    .into_par_iter()
                    .map(|y| {
                        let mut row = Vec::with_capacity(row_len);
                        for x in x0..=x1 {
                            let value = grey[y * width + x];
                            if !keep(value) {
                                continue;
                            }
                            let p = position(x, y);
                            // The 8 corners (floor, and ceil when there is a fraction) must all
                            // be inside, as in PLUS's trilinear bounds check.
                            let inside = (0..3).all(|a| {
                                let f = p[a].floor();
                                let c = if p[a] != f { f + 1.0 } else { f };
                                f >= 0.0 && c <= (dims[a] - 1) as f64
                            });
                            if inside {
                                row.push(LinearEntry { position: p, value });
                            }
                        }
                        row
                    })
                    .collect();
                // Each slab's pixels (a pixel straddling two slabs goes to both), in raster
                // order; insert_linear applies only the corners inside the slab.
                let mut buckets: Vec<Vec<LinearEntry>> = vec![Vec::new(); slabs];
                for e in rows.into_iter().flatten() {
                    stats.pixels_inserted += 1;
                    let z0 = e.position[2].floor() as usize;
                    let z1 = z0 + usize::from(e.position[2] != e.position[2].floor());
                    let (s0, s1) = (z0 / slab_depth, z1 / slab_depth);
                    buckets[s0].push(e);
                    if s1 != s0 {
                        buckets[s1].push(e);
                    }
                }
                let nx = geometry.dims[0];
                let ny = geometry.dims[1];
                // PLUS's fixed-point trilinear arithmetic applies to integer data.
                let fixed_linear = fixed && integer;
                overflows += values
                    .par_chunks_mut(chunk_len)
                    .zip(accumulation.par_chunks_mut(chunk_len))
                    .zip(buckets.par_iter())
                    .enumerate()
                    .map(|(slab, ((vals, accs), bucket))| {
                        let k_lo = slab * slab_depth;
                        let k_hi = k_lo + vals.len() / slice_len.max(1);
                        let mut overflow = 0u64;
                        for e in bucket {
                            overflow += if fixed_linear {
                                insert_linear_fixed(
                                    vals,
                                    accs,
                                    [nx, ny],
                                    (k_lo, k_hi),
                                    e,
                                    options.compounding,
                                )
                            } else {
                                insert_linear(
                                    vals,
                                    accs,
                                    [nx, ny],
                                    (k_lo, k_hi),
                                    e,
                                    options.compounding,
                                    integer,
                                )
                            };
                        }
                        overflow
                    })
                    .sum::<u64>();
            }
        }
        stats.accumulation_overflows += overflows;
        stats.frames_inserted += 1;
        progress.advance(done as u64 + 1);
    }
    progress.finish();
    Ok((values, accumulation))
}

/// One nearest-neighbour insertion; returns 1 when it saturated the accumulation buffer.
#[inline]
fn insert_nn<T: Store>(
    out: &mut T,
    acc: &mut u16,
    input: f64,
    compounding: Compounding,
    integer: bool,
) -> u64 {
    match compounding {
        Compounding::Mean => {
            let a = *acc as u32;
            if a <= ACC_THRESHOLD {
                let new_a = a + ACC_UNIT;
                // Integer data: C integer division, i.e. truncation (exact in f64 here: the
                // operands are integers far below 2^53 and the divisor below 2^16).
                let mean = (input * ACC_UNIT as f64 + out.get() * a as f64) / new_a as f64;
                *out = T::put(c_cast(mean, integer));
                *acc = new_a.min(ACC_MAX) as u16;
                u64::from(new_a > ACC_THRESHOLD)
            } else {
                // Saturated: PLUS's recursive filter with fixed weights.
                *out = T::put(c_cast(input * 0.99609375 + out.get() * 0.00390625, integer));
                0
            }
        }
        Compounding::Maximum => {
            if out.get() < input {
                *out = T::put(input);
            }
            *acc = ACC_UNIT as u16;
            0
        }
        Compounding::Latest => {
            *out = T::put(input);
            *acc = ACC_UNIT as u16;
            0
        }
    }
}

/// One trilinear insertion restricted to the slab's z range [k_lo, k_hi); returns the number of
/// voxels whose accumulation saturated.
fn insert_linear<T: Store>(
    vals: &mut [T],
    accs: &mut [u16],
    [nx, ny]: [usize; 2],
    (k_lo, k_hi): (usize, usize),
    e: &LinearEntry,
    compounding: Compounding,
    integer: bool,
) -> u64 {
    let p = e.position;
    let f0 = [p[0].floor(), p[1].floor(), p[2].floor()];
    let fr = [p[0] - f0[0], p[1] - f0[1], p[2] - f0[2]];
    let i0 = [f0[0] as usize, f0[1] as usize, f0[2] as usize];
    let i1 = [
        i0[0] + usize::from(fr[0] != 0.0),
        i0[1] + usize::from(fr[1] != 0.0),
        i0[2] + usize::from(fr[2] != 0.0),
    ];
    if i1[2] < k_lo || i0[2] >= k_hi {
        return 0;
    }
    let (fx, fy, fz) = (fr[0], fr[1], fr[2]);
    let (rx, ry, rz) = (1.0 - fx, 1.0 - fy, 1.0 - fz);
    let (ryrz, ryfz, fyrz, fyfz) = (ry * rz, ry * fz, fy * rz, fy * fz);
    // Corner j: bit 2 = x1, bit 1 = y1, bit 0 = z1 (PLUS's order and weights).
    let weights = [
        rx * ryrz,
        rx * ryfz,
        rx * fyrz,
        rx * fyfz,
        fx * ryrz,
        fx * ryfz,
        fx * fyrz,
        fx * fyfz,
    ];
    let input = e.value as f64;
    let mut overflow = 0;
    for j in (0..8).rev() {
        let f = weights[j];
        if f == 0.0 {
            continue;
        }
        let i = if j & 4 != 0 { i1[0] } else { i0[0] };
        let jj = if j & 2 != 0 { i1[1] } else { i0[1] };
        let k = if j & 1 != 0 { i1[2] } else { i0[2] };
        if k < k_lo || k >= k_hi {
            continue;
        }
        let v = ((k - k_lo) * ny + jj) * nx + i;
        let out = &mut vals[v];
        let acc = &mut accs[v];
        let old_acc = *acc as f64;
        let mut a = old_acc;
        match compounding {
            Compounding::Maximum => {
                // Only the voxels carrying a real share of the pixel (PLUS: weight >= 1/8).
                if f >= 0.125 && input > out.get() {
                    *out = T::put(input);
                    a = f * ACC_UNIT as f64;
                }
            }
            Compounding::Latest => {
                if f >= 0.125 {
                    *out = T::put(input);
                    a = f * ACC_UNIT as f64;
                }
            }
            Compounding::Mean => {
                let r = old_acc / ACC_UNIT as f64;
                let sum = f + r;
                let mean = (f * input + r * out.get()) / sum;
                *out = T::put(if integer { plus_round(mean) } else { mean });
                a = sum * ACC_UNIT as f64;
            }
        }
        if a > ACC_THRESHOLD as f64 && old_acc <= ACC_THRESHOLD as f64 {
            overflow += 1;
        }
        *acc = if a < ACC_MAX as f64 {
            plus_round(a) as u16
        } else {
            ACC_MAX as u16
        };
    }
    overflow
}

/// PLUS's fixed-point product (`fixed::fast_multiply`): rounded, 14 fractional bits.
#[inline]
fn fixed_mul(a: i64, b: i64) -> i64 {
    (a * b + FIXED_ONE / 2) >> 14
}

/// PLUS's fixed-point rounding to an integer (`fixed::round`).
#[inline]
fn fixed_round(a: i64) -> i64 {
    (a + FIXED_ONE / 2) >> 14
}

/// One trilinear insertion with PLUS's `Optimization="FULL"` arithmetic for integer data: the
/// fraction, the corner weights, the running mean and the accumulation all in 14-bit fixed point.
/// Same contract as [`insert_linear`].
fn insert_linear_fixed<T: Store>(
    vals: &mut [T],
    accs: &mut [u16],
    [nx, ny]: [usize; 2],
    (k_lo, k_hi): (usize, usize),
    e: &LinearEntry,
    compounding: Compounding,
) -> u64 {
    // Positions were computed as exact multiples of 2^-14.
    let p = e.position.map(|x| (x * FIXED_ONE as f64) as i64);
    let fl = p.map(|x| x >> 14);
    let fr = [
        p[0] - (fl[0] << 14),
        p[1] - (fl[1] << 14),
        p[2] - (fl[2] << 14),
    ];
    let i0 = fl.map(|x| x as usize);
    let i1 = [
        i0[0] + usize::from(fr[0] != 0),
        i0[1] + usize::from(fr[1] != 0),
        i0[2] + usize::from(fr[2] != 0),
    ];
    if i1[2] < k_lo || i0[2] >= k_hi {
        return 0;
    }
    let (fx, fy, fz) = (fr[0], fr[1], fr[2]);
    let (rx, ry, rz) = (FIXED_ONE - fx, FIXED_ONE - fy, FIXED_ONE - fz);
    let (ryrz, ryfz, fyrz, fyfz) = (
        fixed_mul(ry, rz),
        fixed_mul(ry, fz),
        fixed_mul(fy, rz),
        fixed_mul(fy, fz),
    );
    let weights = [
        fixed_mul(rx, ryrz),
        fixed_mul(rx, ryfz),
        fixed_mul(rx, fyrz),
        fixed_mul(rx, fyfz),
        fixed_mul(fx, ryrz),
        fixed_mul(fx, ryfz),
        fixed_mul(fx, fyrz),
        fixed_mul(fx, fyfz),
    ];
    let input = e.value as i64;
    let unit = ACC_UNIT as i64;
    let min_weight = FIXED_ONE / 8;
    let mut overflow = 0;
    for j in (0..8).rev() {
        let f = weights[j];
        if f == 0 {
            continue;
        }
        let i = if j & 4 != 0 { i1[0] } else { i0[0] };
        let jj = if j & 2 != 0 { i1[1] } else { i0[1] };
        let k = if j & 1 != 0 { i1[2] } else { i0[2] };
        if k < k_lo || k >= k_hi {
            continue;
        }
        let v = ((k - k_lo) * ny + jj) * nx + i;
        let out = &mut vals[v];
        let acc = &mut accs[v];
        let old_acc = *acc as i64;
        let mut a = old_acc << 14;
        let current = out.get() as i64;
        match compounding {
            Compounding::Maximum => {
                if f >= min_weight && input > current {
                    *out = T::put(input as f64);
                    a = f * unit;
                }
            }
            Compounding::Latest => {
                if f >= min_weight {
                    *out = T::put(input as f64);
                    a = f * unit;
                }
            }
            Compounding::Mean => {
                // r = acc / 256 in fixed point is exactly acc * 64.
                let r = old_acc * (FIXED_ONE / unit);
                let sum = f + r;
                let numerator = f * input + r * current;
                let quotient =
                    (numerator as f64 / sum as f64 * FIXED_ONE as f64).round_ties_even() as i64;
                *out = T::put(fixed_round(quotient) as f64);
                a = sum * unit;
            }
        }
        if a > (ACC_THRESHOLD as i64) << 14 && old_acc <= ACC_THRESHOLD as i64 {
            overflow += 1;
        }
        *acc = if a < (ACC_MAX as i64) << 14 {
            fixed_round(a) as u16
        } else {
            ACC_MAX as u16
        };
    }
    overflow
}
