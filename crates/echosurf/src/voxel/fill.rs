//! Hole filling (PLUS `vtkPlusFillHolesInVolume`): every voxel no pixel reached gets the value of
//! the first element that succeeds for it, computed from the unfilled volume only (filled voxels
//! never feed other holes), else 0. Parallel over z-slices; each output voxel depends only on the
//! input, so the result does not depend on the thread count.

use rayon::prelude::*;

use super::HoleFillingElement;
use super::paste::{Store, c_cast};
use crate::progress::Progress;

/// The 13 stick directions (one per opposite pair of the 26-neighbourhood), in PLUS's order.
const STICKS: [[i64; 3]; 13] = [
    [1, 0, 0],
    [0, 1, 0],
    [0, 0, 1],
    [1, 1, 0],
    [1, 0, 1],
    [0, 1, 1],
    [1, -1, 0],
    [1, 0, -1],
    [0, 1, -1],
    [1, 1, 1],
    [-1, 1, 1],
    [1, -1, 1],
    [-1, -1, 1],
];

/// An element with its kernel precomputed (f32, as PLUS stores it).
enum Prepared {
    Stick {
        length_limit: i64,
        sticks_to_use: usize,
    },
    Kernel {
        size: i64,
        kernel: Vec<f32>,
        min_ratio: f64,
        weight_by_accumulation: bool,
    },
    NearestNeighbor {
        size: i64,
        min_ratio: f64,
    },
}

fn prepare(e: &HoleFillingElement) -> Prepared {
    match *e {
        HoleFillingElement::Stick {
            length_limit,
            sticks_to_use,
        } => Prepared::Stick {
            length_limit: length_limit as i64,
            sticks_to_use,
        },
        HoleFillingElement::Gaussian {
            size,
            stdev,
            min_ratio,
        }
        | HoleFillingElement::GaussianAccumulation {
            size,
            stdev,
            min_ratio,
        } => Prepared::Kernel {
            size: size as i64,
            kernel: gaussian_kernel(size, stdev as f32),
            min_ratio,
            weight_by_accumulation: matches!(e, HoleFillingElement::GaussianAccumulation { .. }),
        },
        HoleFillingElement::DistanceWeightInverse { size, min_ratio } => Prepared::Kernel {
            size: size as i64,
            kernel: inverse_distance_kernel(size),
            min_ratio,
            weight_by_accumulation: false,
        },
        HoleFillingElement::NearestNeighbor { size, min_ratio } => Prepared::NearestNeighbor {
            size: size as i64,
            min_ratio,
        },
    }
}

/// Normalised 3D Gaussian on a size^3 cube centred on the middle voxel, index z*size^2 + y*size + x.
fn gaussian_kernel(size: usize, stdev: f32) -> Vec<f32> {
    let range = (size as f32 - 1.0) / 2.0;
    let divisor = stdev * stdev * 2.0;
    let term_divisor = ((2.0 * std::f64::consts::PI).powf(1.5) * (stdev as f64).powi(3)) as f32;
    let mut kernel = Vec::with_capacity(size * size * size);
    for z in 0..size {
        for y in 0..size {
            for x in 0..size {
                let d = |c: usize| (c as f64 - range as f64).powi(2) / divisor as f64;
                let e = -(d(x) + d(y) + d(z));
                kernel.push(((1.0f32 / term_divisor) as f64 * e.exp()) as f32);
            }
        }
    }
    kernel
}

/// 1 / distance to the centre (0 at the centre), same layout.
fn inverse_distance_kernel(size: usize) -> Vec<f32> {
    let range = (size as f32 - 1.0) / 2.0;
    let mut kernel = Vec::with_capacity(size * size * size);
    for z in 0..size {
        for y in 0..size {
            for x in 0..size {
                let (dx, dy, dz) = (x as f32 - range, y as f32 - range, z as f32 - range);
                let d = (dx * dx + dy * dy + dz * dz).sqrt();
                kernel.push(if d != 0.0 { (1.0 / d).abs() } else { 0.0 });
            }
        }
    }
    kernel
}

struct Grid<'a, T> {
    values: &'a [T],
    acc: &'a [u16],
    dims: [i64; 3],
    integer: bool,
}

impl<T: Store> Grid<'_, T> {
    #[inline]
    fn index(&self, p: [i64; 3]) -> Option<usize> {
        if (0..3).all(|a| p[a] >= 0 && p[a] < self.dims[a]) {
            Some(((p[2] * self.dims[1] + p[1]) * self.dims[0] + p[0]) as usize)
        } else {
            None
        }
    }

    /// PLUS's stick rule: on each of the 13 lines through the hole, the nearest hit voxel forward
    /// and backward (the two together within `length_limit`); the shortest sticks win, each
    /// valued by PLUS's interpolation weights.
    fn stick(&self, p: [i64; 3], length_limit: i64, sticks_to_use: usize) -> Option<f64> {
        let mut weights = [0.0f64; 13];
        let mut values = [0.0f64; 13];
        for (s, d) in STICKS.iter().enumerate() {
            let find = |sign: i64, limit: i64| -> Option<(i64, f64)> {
                let mut q = p;
                let mut j = 1;
                while j < limit {
                    for a in 0..3 {
                        q[a] += sign * d[a];
                    }
                    let idx = self.index(q)?;
                    if self.acc[idx] != 0 {
                        return Some((j, self.values[idx].get()));
                    }
                    j += 1;
                }
                None
            };
            let Some((fwd, fwd_val)) = find(1, length_limit) else {
                continue;
            };
            let Some((rvs, rvs_val)) = find(-1, length_limit - fwd) else {
                continue;
            };
            let total = (fwd + rvs + 1) as f64;
            let weight_fwd = (rvs + 1) as f64 / total;
            let weight_rvs = 1.0 - weight_fwd;
            let length = ((d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) as f64).sqrt();
            weights[s] = 1.0 / (total * length);
            values[s] = c_cast(weight_rvs * rvs_val + weight_fwd * fwd_val, self.integer);
        }
        let mut used = 0;
        let (mut sum, mut sum_w) = (0.0, 0.0);
        while used < sticks_to_use {
            let max_w = weights.iter().copied().fold(0.0, f64::max);
            if max_w == 0.0 {
                break;
            }
            for s in 0..13 {
                if weights[s] == max_w {
                    sum += values[s] * weights[s];
                    sum_w += weights[s];
                    used += 1;
                    weights[s] = 0.0;
                }
            }
        }
        (sum_w != 0.0).then(|| c_cast(sum / sum_w, self.integer))
    }

    /// Kernel-weighted mean of the hit voxels in the cube (x outer, z inner, as PLUS sums).
    fn kernel(
        &self,
        p: [i64; 3],
        size: i64,
        kernel: &[f32],
        min_ratio: f64,
        weight_by_accumulation: bool,
    ) -> Option<f64> {
        let range = (size - 1) / 2;
        let (mut sum, mut sum_w, mut known) = (0.0f64, 0.0f64, 0usize);
        for x in p[0] - range..=p[0] + range {
            for y in p[1] - range..=p[1] + range {
                for z in p[2] - range..=p[2] + range {
                    let Some(idx) = self.index([x, y, z]) else {
                        continue;
                    };
                    let a = self.acc[idx];
                    if a == 0 {
                        continue;
                    }
                    let k = (size * size * (z - p[2] + range)
                        + size * (y - p[1] + range)
                        + (x - p[0] + range)) as usize;
                    let mut w = kernel[k] as f64;
                    if weight_by_accumulation {
                        w *= a as f64;
                    }
                    sum += self.values[idx].get() * w;
                    sum_w += w;
                    known += 1;
                }
            }
        }
        if sum_w == 0.0 || (known as f64 / (size * size * size) as f64) <= min_ratio {
            return None;
        }
        Some(c_cast(sum / sum_w, self.integer))
    }

    /// Mean of the hit voxels in the smallest cube shell (radius 1.. (size-1)/2) holding any.
    fn nearest(&self, p: [i64; 3], size: i64, min_ratio: f64) -> Option<f64> {
        let max_range = (size - 1) / 2;
        for range in 1..=max_range {
            let (mut sum, mut count) = (0.0f64, 0usize);
            for x in p[0] - range..=p[0] + range {
                for y in p[1] - range..=p[1] + range {
                    for z in p[2] - range..=p[2] + range {
                        if let Some(idx) = self.index([x, y, z])
                            && self.acc[idx] != 0
                        {
                            sum += self.values[idx].get();
                            count += 1;
                        }
                    }
                }
            }
            if count > 0 {
                if (count as f64 / (size * size * size) as f64) > min_ratio {
                    return Some(c_cast(sum / count as f64, self.integer));
                }
                return None;
            }
        }
        None
    }
}

/// Fills the holes; returns the filled volume and how many holes got a value.
pub(super) fn fill_holes<T: Store>(
    values: &[T],
    acc: &[u16],
    dims: [usize; 3],
    hole_filling: &super::HoleFilling,
    integer: bool,
    progress: &dyn Progress,
) -> (Vec<T>, usize) {
    let elements: Vec<Prepared> = hole_filling.elements.iter().map(prepare).collect();
    let grid = Grid {
        values,
        acc,
        dims: dims.map(|d| d as i64),
        integer,
    };
    let slice_len = (dims[0] * dims[1]).max(1);
    let mut out = values.to_vec();
    progress.start("filling holes", dims[2] as u64);
    let done = std::sync::atomic::AtomicU64::new(0);
    let filled: usize = out
        .par_chunks_mut(slice_len)
        .enumerate()
        .map(|(k, slice)| {
            let mut filled = 0;
            for (offset, v) in slice.iter_mut().enumerate() {
                let idx = k * slice_len + offset;
                if acc[idx] != 0 {
                    continue;
                }
                let p = [
                    (offset % dims[0]) as i64,
                    (offset / dims[0]) as i64,
                    k as i64,
                ];
                let result = elements.iter().find_map(|e| match e {
                    Prepared::Stick {
                        length_limit,
                        sticks_to_use,
                    } => grid.stick(p, *length_limit, *sticks_to_use),
                    Prepared::Kernel {
                        size,
                        kernel,
                        min_ratio,
                        weight_by_accumulation,
                    } => grid.kernel(p, *size, kernel, *min_ratio, *weight_by_accumulation),
                    Prepared::NearestNeighbor { size, min_ratio } => {
                        grid.nearest(p, *size, *min_ratio)
                    }
                });
                *v = T::put(result.unwrap_or(0.0));
                filled += usize::from(result.is_some());
            }
            let n = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
            progress.advance(n);
            filled
        })
        .sum();
    progress.finish();
    (out, filled)
}
