//! Black-box fast multipole method (Fong & Darve 2009) for the self product `sum_j q_j |x_i - x_j|`,
//! and for the product from charges at a subset of the points to all of them (the coarse level's,
//! [`Fmm::with_sources`]).
//!
//! The global solver's products evaluate the spline at its own samples, every iteration. The treecode
//! ([`super::tree`]) does that target leaf by source cluster, through up to 8^3 proxies per far cluster,
//! and spends about 18k kernel terms per sample at 100k band pixels (decision 0051). Here both sides
//! are expanded: a uniform octree (every leaf at one depth, empty boxes skipped), tensor Chebyshev
//! interpolation in every box, and box-to-box far-field translations (M2L) that depend only on the
//! boxes' relative position, so they are built once, compressed by an SVD of all of them together and
//! applied as small `rank x rank` products. Near boxes (adjacent leaves) are summed point by point with
//! the crate's kernel loop.
//!
//! |x - y| is homogeneous of degree one, so one set of translations on unit boxes serves every level,
//! scaled by the box size. The leaf depth is chosen by a cost model over the data's own occupancy.

use glam::DVec3;
use rayon::prelude::*;

use super::kernel::{sum_r, sum_r_scatter};
use super::tree::{flatten_lists, split_by_sizes};

/// Interpolation order and SVD cut-off of one FMM.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct FmmParams {
    /// Chebyshev nodes per box side.
    pub nodes_per_side: usize,
    /// Singular values of the stacked translations below this fraction of the largest are dropped.
    pub svd_cutoff: f64,
    /// Leaf depth of the octree; None chooses it by the cost model.
    pub leaf_depth: Option<usize>,
}

impl FmmParams {
    /// The treecode's Chebyshev order per side (clamped to 4-10), and singular values kept down to
    /// 10^-order: about the treecode's error on band pixels (docs/decisions/0053-fmm-product.md).
    pub fn matching(treecode: super::tree::TreecodeParams) -> FmmParams {
        let p = treecode.nodes_per_side.clamp(4, 10);
        FmmParams {
            nodes_per_side: p,
            svd_cutoff: 10f64.powi(-(p as i32)),
            leaf_depth: None,
        }
    }
}

/// Offsets between interacting boxes are in [-3, 3]^3: index `(ox + 3) * 49 + (oy + 3) * 7 + oz + 3`.
const OFFSETS: usize = 343;

/// Target boxes per translation task: their pairs are applied grouped by offset.
const CHUNK: usize = 128;

fn offset_index(o: [i64; 3]) -> usize {
    ((o[0] + 3) * 49 + (o[1] + 3) * 7 + (o[2] + 3)) as usize
}

fn is_far_offset(o: [i64; 3]) -> bool {
    o.iter().any(|c| c.abs() >= 2)
}

/// Nonempty boxes of one octree level, sorted by Morton key.
#[derive(Debug, Clone, Default)]
struct Level {
    keys: Vec<u64>,
    /// Per box: first child in the next level (children are contiguous) and the end of that range.
    child_range: Vec<(u32, u32)>,
    /// Per box: the parent's index in the previous level.
    parent: Vec<u32>,
    /// M2L pairs per chunk of [`CHUNK`] target boxes (CSR): target box, source box, offset index.
    far_offsets: Vec<u32>,
    far: Vec<(u32, u32, u16)>,
}

/// Charged points that are a subset of the FMM's points, grouped by leaf.
#[derive(Debug, Clone)]
struct Sources {
    /// Per leaf box, the range of its sources (CSR).
    leaf_start: Vec<u32>,
    xs: Vec<f64>,
    ys: Vec<f64>,
    zs: Vec<f64>,
    /// Per source (in leaf order), its index in the charges given to [`Fmm::product`].
    charge: Vec<u32>,
}

/// A built FMM over a fixed point set (the points given to [`Fmm::new`], in their order).
#[derive(Debug, Clone)]
pub(crate) struct Fmm {
    p: usize,
    rank: usize,
    /// Points in Morton order, and Morton position -> input index.
    xs: Vec<f64>,
    ys: Vec<f64>,
    zs: Vec<f64>,
    order: Vec<u32>,
    levels: Vec<Level>,
    /// Leaf boxes: point ranges and adjacent leaves (CSR, including the box itself).
    leaf_start: Vec<u32>,
    /// The charged points when they are a subset of the points ([`Fmm::with_sources`]).
    sources: Option<Sources>,
    near_offsets: Vec<u32>,
    near: Vec<u32>,
    /// Self products only (no [`Sources`]): for each entry of `near` joining two different leaves, where
    /// that pair's buffer starts among the pair buffers (the lower-numbered leaf's pass adds the pair's
    /// terms for the higher-numbered leaf's points there), and where each leaf's own pair buffers start
    /// (CSR). Empty with sources.
    near_pair_buffer: Vec<usize>,
    pair_buffer_start: Vec<usize>,
    root_lo: DVec3,
    root_side: f64,
    /// Compression basis, row-major `p^3 x rank`.
    basis: Vec<f64>,
    /// The basis transposed, `rank x p^3` row-major.
    basis_t: Vec<f64>,
    /// Compressed unit translations, `rank x rank` column-major per offset (empty for near offsets).
    m2l: Vec<Vec<f64>>,
    cheb: Cheb,
    /// 1-D child-to-parent interpolation, `[side][parent node * p + child node]`, and its transpose.
    transfer: [Vec<f64>; 2],
    transfer_t: [Vec<f64>; 2],
}

/// Chebyshev points of the first kind on [-1, 1].
fn cheb_points(p: usize) -> Vec<f64> {
    (0..p)
        .map(|m| ((2 * m + 1) as f64 * std::f64::consts::PI / (2 * p) as f64).cos())
        .collect()
}

/// First-kind Chebyshev points on [-1, 1] and their barycentric weights.
#[derive(Debug, Clone)]
struct Cheb {
    nodes: Vec<f64>,
    weights: Vec<f64>,
}

impl Cheb {
    fn new(p: usize) -> Cheb {
        Cheb {
            nodes: cheb_points(p),
            weights: (0..p)
                .map(|m| {
                    let sign = if m % 2 == 0 { 1.0 } else { -1.0 };
                    sign * ((2 * m + 1) as f64 * std::f64::consts::PI / (2 * p) as f64).sin()
                })
                .collect(),
        }
    }

    /// Lagrange basis values at `x` (barycentric form).
    fn basis(&self, x: f64, out: &mut [f64]) {
        let mut total = 0.0;
        for (m, (&node, &w)) in self.nodes.iter().zip(&self.weights).enumerate() {
            let d = x - node;
            if d == 0.0 {
                out.fill(0.0);
                out[m] = 1.0;
                return;
            }
            out[m] = w / d;
            total += out[m];
        }
        let inv = 1.0 / total;
        for o in out.iter_mut() {
            *o *= inv;
        }
    }
}

fn spread(v: u64) -> u64 {
    let mut x = v & 0x1f_ffff;
    x = (x | (x << 32)) & 0x1f00000000ffff;
    x = (x | (x << 16)) & 0x1f0000ff0000ff;
    x = (x | (x << 8)) & 0x100f00f00f00f00f;
    x = (x | (x << 4)) & 0x10c30c30c30c30c3;
    x = (x | (x << 2)) & 0x1249249249249249;
    x
}

fn compact(v: u64) -> u64 {
    let mut x = v & 0x1249249249249249;
    x = (x ^ (x >> 2)) & 0x10c30c30c30c30c3;
    x = (x ^ (x >> 4)) & 0x100f00f00f00f00f;
    x = (x ^ (x >> 8)) & 0x1f0000ff0000ff;
    x = (x ^ (x >> 16)) & 0x1f00000000ffff;
    x = (x ^ (x >> 32)) & 0x1f_ffff;
    x
}

fn morton(c: [u64; 3]) -> u64 {
    (spread(c[0]) << 2) | (spread(c[1]) << 1) | spread(c[2])
}

fn coords(key: u64) -> [i64; 3] {
    [
        compact(key >> 2) as i64,
        compact(key >> 1) as i64,
        compact(key) as i64,
    ]
}

/// Morton key of the leaf at `depth` holding `x`, in the cube of side `side` from `root_lo`.
fn cell_key(x: DVec3, root_lo: DVec3, side: f64, depth: usize) -> u64 {
    let cells = 1u64 << depth;
    let c = ((x - root_lo) / side * cells as f64).floor();
    let clamp = |v: f64| (v.max(0.0) as u64).min(cells - 1);
    morton([clamp(c.x), clamp(c.y), clamp(c.z)])
}

/// Deepest leaf level considered (21 bits per axis fit a 64-bit key; far more than any sweep needs).
const MAX_DEPTH: usize = 16;

impl Fmm {
    /// The self product over `points`: every point is charged ([`Fmm::product`]).
    pub fn new(points: &[DVec3], params: FmmParams) -> Fmm {
        Self::build(points, None, params)
    }

    /// Products from charges at `sources` (indices into `points`) to every point: the coarse level's
    /// coefficients evaluated at every sample. [`Fmm::product`] then takes one charge per source, in
    /// the order of `sources`.
    pub fn with_sources(points: &[DVec3], sources: &[u32], params: FmmParams) -> Fmm {
        Self::build(points, Some(sources), params)
    }

    fn build(points: &[DVec3], sources: Option<&[u32]>, params: FmmParams) -> Fmm {
        let p = params.nodes_per_side.clamp(2, 10);
        let (lo, hi) = points.iter().fold(
            (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
            |(lo, hi), &x| (lo.min(x), hi.max(x)),
        );
        let (lo, hi) = if points.is_empty() {
            (DVec3::ZERO, DVec3::ONE)
        } else {
            (lo, hi)
        };
        let side = (hi - lo).max_element().max(1e-9) * (1.0 + 1e-9);
        let centre = (lo + hi) * 0.5;
        let root_lo = centre - DVec3::splat(side * 0.5);
        let (basis, rank, m2l) = compressed_translations(p, params.svd_cutoff);
        let leaf_depth = match params.leaf_depth {
            Some(d) => d.clamp(2, MAX_DEPTH),
            None => {
                let source_points: Option<Vec<DVec3>> =
                    sources.map(|s| s.iter().map(|&i| points[i as usize]).collect());
                let source_points = source_points.as_deref().unwrap_or(points);
                let pairs_summed_once = sources.is_none();
                choose_leaf_depth(
                    points,
                    source_points,
                    (root_lo, side),
                    (p, rank),
                    pairs_summed_once,
                )
            }
        };
        let mut keyed: Vec<(u64, u32)> = points
            .iter()
            .enumerate()
            .map(|(i, &x)| (cell_key(x, root_lo, side, leaf_depth), i as u32))
            .collect();
        keyed.sort_unstable();
        let order: Vec<u32> = keyed.iter().map(|k| k.1).collect();
        let xs = order.iter().map(|&i| points[i as usize].x).collect();
        let ys = order.iter().map(|&i| points[i as usize].y).collect();
        let zs = order.iter().map(|&i| points[i as usize].z).collect();

        // Leaf boxes and their point ranges.
        let mut leaf_keys = Vec::new();
        let mut leaf_start = Vec::new();
        for (i, &(k, _)) in keyed.iter().enumerate() {
            if leaf_keys.last() != Some(&k) {
                leaf_keys.push(k);
                leaf_start.push(i as u32);
            }
        }
        leaf_start.push(keyed.len() as u32);
        let sources = sources.map(|subset| {
            let mut position = vec![0u32; points.len()];
            for (k, &(_, i)) in keyed.iter().enumerate() {
                position[i as usize] = k as u32;
            }
            let mut placed: Vec<(u32, u32)> = subset
                .iter()
                .enumerate()
                .map(|(c, &i)| (position[i as usize], c as u32))
                .collect();
            placed.sort_unstable();
            let mut start = Vec::with_capacity(leaf_start.len());
            let mut next = 0;
            for &first in &leaf_start {
                while next < placed.len() && placed[next].0 < first {
                    next += 1;
                }
                start.push(next as u32);
            }
            let at = |k: u32| points[keyed[k as usize].1 as usize];
            Sources {
                leaf_start: start,
                xs: placed.iter().map(|&(k, _)| at(k).x).collect(),
                ys: placed.iter().map(|&(k, _)| at(k).y).collect(),
                zs: placed.iter().map(|&(k, _)| at(k).z).collect(),
                charge: placed.iter().map(|&(_, c)| c).collect(),
            }
        });

        // Levels, leaf upwards.
        let mut levels: Vec<Level> = vec![Level::default(); leaf_depth + 1];
        levels[leaf_depth].keys = leaf_keys;
        for l in (0..leaf_depth).rev() {
            let child_keys = &levels[l + 1].keys;
            let mut keys = Vec::new();
            let mut ranges = Vec::new();
            let mut parent = Vec::with_capacity(child_keys.len());
            for (ci, &ck) in child_keys.iter().enumerate() {
                let pk = ck >> 3;
                if keys.last() != Some(&pk) {
                    keys.push(pk);
                    ranges.push((ci as u32, ci as u32));
                }
                ranges.last_mut().expect("pushed").1 = ci as u32 + 1;
                parent.push(keys.len() as u32 - 1);
            }
            levels[l + 1].parent = parent;
            levels[l].keys = keys;
            levels[l].child_range = ranges;
        }

        // Interaction lists: children of the parent's neighbours that are not adjacent.
        for l in 2..=leaf_depth {
            let (upper, lower) = levels.split_at_mut(l);
            let parent_level = &upper[l - 1];
            let level = &mut lower[0];
            let lists: Vec<Vec<(u32, u16)>> = (0..level.keys.len())
                .into_par_iter()
                .map(|b| {
                    let cb = coords(level.keys[b]);
                    let pb = coords(parent_level.keys[level.parent[b] as usize]);
                    let mut list = Vec::new();
                    for_each_neighbour(&parent_level.keys, pb, |pn| {
                        let (s, e) = parent_level.child_range[pn];
                        for c in s..e {
                            let cc = coords(level.keys[c as usize]);
                            let o = [cb[0] - cc[0], cb[1] - cc[1], cb[2] - cc[2]];
                            if is_far_offset(o) {
                                list.push((c, offset_index(o) as u16));
                            }
                        }
                    });
                    list
                })
                .collect();
            let chunks: Vec<Vec<(u32, u32, u16)>> = lists
                .par_chunks(CHUNK)
                .enumerate()
                .map(|(ci, boxes)| {
                    let mut pairs: Vec<(u32, u32, u16)> = boxes
                        .iter()
                        .enumerate()
                        .flat_map(|(bl, list)| {
                            list.iter()
                                .map(move |&(c, o)| ((ci * CHUNK + bl) as u32, c, o))
                        })
                        .collect();
                    // Grouped by translation, so each stays in cache across the chunk.
                    pairs.sort_unstable_by_key(|&(t, c, o)| (o, t, c));
                    pairs
                })
                .collect();
            let (offsets, entries) = flatten_lists(chunks);
            level.far_offsets = offsets;
            level.far = entries;
        }
        let leaf_level = &levels[leaf_depth];
        let near_lists: Vec<Vec<u32>> = (0..leaf_level.keys.len())
            .into_par_iter()
            .map(|b| {
                let mut list = Vec::new();
                for_each_neighbour(&leaf_level.keys, coords(leaf_level.keys[b]), |n| {
                    list.push(n as u32)
                });
                list
            })
            .collect();
        let (near_offsets, near) = flatten_lists(near_lists);
        let (near_pair_buffer, pair_buffer_start) = if sources.is_none() {
            pair_buffers(&leaf_start, &near_offsets, &near)
        } else {
            (Vec::new(), Vec::new())
        };

        let cheb = Cheb::new(p);
        let transfer = [-1.0, 1.0].map(|s: f64| {
            let mut t = vec![0.0; p * p];
            let mut w = vec![0.0; p];
            for k in 0..p {
                cheb.basis(0.5 * cheb.nodes[k] + 0.5 * s, &mut w);
                for m in 0..p {
                    t[m * p + k] = w[m];
                }
            }
            t
        });
        let transfer_t = transfer
            .clone()
            .map(|t| (0..p * p).map(|i| t[(i % p) * p + i / p]).collect());
        let p3 = p * p * p;
        let basis_t = (0..rank * p3)
            .map(|i| basis[(i % p3) * rank + i / p3])
            .collect();
        Fmm {
            p,
            rank,
            basis_t,
            xs,
            ys,
            zs,
            order,
            levels,
            leaf_start,
            sources,
            near_offsets,
            near,
            near_pair_buffer,
            pair_buffer_start,
            root_lo,
            root_side: side,
            basis,
            m2l,
            cheb,
            transfer,
            transfer_t,
        }
    }

    pub fn len(&self) -> usize {
        self.order.len()
    }

    /// Leaf depth, nonempty leaves, translation pairs and near point pairs.
    #[cfg(test)]
    pub fn shape(&self) -> (usize, usize, usize, usize) {
        let leaf = self.levels.len() - 1;
        let pairs = self.levels.iter().map(|l| l.far.len()).sum();
        let mut near_pairs = 0usize;
        for b in 0..self.levels[leaf].keys.len() {
            let n = (self.leaf_start[b + 1] - self.leaf_start[b]) as usize;
            for &c in &self.near[self.near_offsets[b] as usize..self.near_offsets[b + 1] as usize] {
                near_pairs +=
                    n * (self.leaf_start[c as usize + 1] - self.leaf_start[c as usize]) as usize;
            }
        }
        (leaf, self.levels[leaf].keys.len(), pairs, near_pairs)
    }

    /// Half-width of a box at level `l`.
    fn half_width(&self, l: usize) -> f64 {
        self.root_side / (1u64 << l) as f64 * 0.5
    }

    fn box_centre(&self, l: usize, key: u64) -> DVec3 {
        let c = coords(key);
        let h = self.half_width(l);
        self.root_lo
            + DVec3::new(c[0] as f64, c[1] as f64, c[2] as f64) * (2.0 * h)
            + DVec3::splat(h)
    }

    /// The 1-D interpolation weights of `x` in the box of centre `c` and half-width `h`, per axis.
    fn point_weights(&self, x: DVec3, c: DVec3, h: f64, w: &mut [Vec<f64>; 3]) {
        let u = (x - c) / h;
        self.cheb.basis(u.x, &mut w[0]);
        self.cheb.basis(u.y, &mut w[1]);
        self.cheb.basis(u.z, &mut w[2]);
    }

    /// `out_i = sum_j q_j |x_i - y_j|` at every point `x_i` (input order), the charges `q_j` at every
    /// point (input order) or, built [`Fmm::with_sources`], at the sources (their order).
    pub fn product(&self, q_in: &[f64], out: &mut [f64]) {
        let n = self.len();
        let p3 = self.p * self.p * self.p;
        // Charges and their positions in Morton order, ranges per leaf.
        let (q, start, xs, ys, zs) = match &self.sources {
            None => (
                self.order
                    .iter()
                    .map(|&i| q_in[i as usize])
                    .collect::<Vec<f64>>(),
                self.leaf_start.as_slice(),
                self.xs.as_slice(),
                self.ys.as_slice(),
                self.zs.as_slice(),
            ),
            Some(s) => (
                s.charge.iter().map(|&c| q_in[c as usize]).collect(),
                s.leaf_start.as_slice(),
                s.xs.as_slice(),
                s.ys.as_slice(),
                s.zs.as_slice(),
            ),
        };
        let leaf = self.levels.len() - 1;

        // Upward pass: multipole (interpolation-node charges) per box.
        let mut multipole: Vec<Vec<f64>> = vec![Vec::new(); leaf + 1];
        multipole[leaf] = vec![0.0; self.levels[leaf].keys.len() * p3];
        {
            let h = self.half_width(leaf);
            let keys = &self.levels[leaf].keys;
            multipole[leaf]
                .par_chunks_mut(p3)
                .enumerate()
                .for_each(|(b, m)| {
                    let c = self.box_centre(leaf, keys[b]);
                    let mut w = [vec![0.0; self.p], vec![0.0; self.p], vec![0.0; self.p]];
                    for i in start[b] as usize..start[b + 1] as usize {
                        self.point_weights(DVec3::new(xs[i], ys[i], zs[i]), c, h, &mut w);
                        tensor_accumulate(&w, q[i], m);
                    }
                });
        }
        for l in (2..leaf).rev() {
            let (upper, lower) = multipole.split_at_mut(l + 1);
            let children = &lower[0];
            let level = &self.levels[l];
            let next = &self.levels[l + 1];
            upper[l] = vec![0.0; level.keys.len() * p3];
            upper[l].par_chunks_mut(p3).enumerate().for_each(|(b, m)| {
                let mut scratch = vec![0.0; 2 * p3];
                let (s, e) = level.child_range[b];
                for c in s..e {
                    let side = child_side(next.keys[c as usize]);
                    let child = &children[c as usize * p3..(c as usize + 1) * p3];
                    self.transfer_up(side, child, m, &mut scratch);
                }
            });
        }
        // Compressed multipoles.
        let k = self.rank;
        let compressed: Vec<Vec<f64>> = multipole
            .iter()
            .map(|m| {
                let mut out = vec![0.0; m.len() / p3 * k];
                out.par_chunks_mut(k.max(1))
                    .zip(m.par_chunks(p3))
                    .for_each(|(c, m)| {
                        for (node, &mv) in m.iter().enumerate() {
                            let row = &self.basis[node * k..(node + 1) * k];
                            for (cj, &u) in c.iter_mut().zip(row) {
                                *cj += u * mv;
                            }
                        }
                    });
                out
            })
            .collect();

        // Translations and the downward pass: local (node potentials) per box.
        let mut local: Vec<Vec<f64>> = vec![Vec::new(); leaf + 1];
        for l in 2..=leaf {
            let level = &self.levels[l];
            let scale = self.half_width(l);
            let mut loc = vec![0.0; level.keys.len() * p3];
            let parent_local = &local[l - 1];
            let far = &level.far;
            let compressed_l = &compressed[l];
            loc.par_chunks_mut(CHUNK * p3)
                .enumerate()
                .for_each(|(ci, out)| {
                    let first = ci * CHUNK;
                    let mut acc = vec![0.0; out.len() / p3 * k];
                    let pairs =
                        &far[level.far_offsets[ci] as usize..level.far_offsets[ci + 1] as usize];
                    let mut gathered = Vec::new();
                    let mut translated = Vec::new();
                    for group in pairs.chunk_by(|a, b| a.2 == b.2) {
                        let m = group.len();
                        gathered.clear();
                        for &(_, c, _) in group {
                            gathered.extend_from_slice(
                                &compressed_l[c as usize * k..(c as usize + 1) * k],
                            );
                        }
                        translated.clear();
                        translated.resize(k * m, 0.0);
                        faer::linalg::matmul::matmul(
                            faer::MatMut::from_column_major_slice_mut(&mut translated, k, m),
                            faer::Accum::Replace,
                            faer::MatRef::from_column_major_slice(
                                &self.m2l[group[0].2 as usize],
                                k,
                                k,
                            ),
                            faer::MatRef::from_column_major_slice(&gathered, k, m),
                            1.0,
                            faer::Par::Seq,
                        );
                        for (&(t, _, _), d) in group.iter().zip(translated.chunks_exact(k)) {
                            let a =
                                &mut acc[(t as usize - first) * k..(t as usize - first + 1) * k];
                            for (ai, &dv) in a.iter_mut().zip(d) {
                                *ai += dv;
                            }
                        }
                    }
                    let mut scratch = vec![0.0; 2 * p3];
                    for (bl, out_b) in out.chunks_mut(p3).enumerate() {
                        let b = first + bl;
                        for (j, &aj) in acc[bl * k..(bl + 1) * k].iter().enumerate() {
                            let column = &self.basis_t[j * p3..(j + 1) * p3];
                            for (o, &u) in out_b.iter_mut().zip(column) {
                                *o += u * aj;
                            }
                        }
                        for o in out_b.iter_mut() {
                            *o *= scale;
                        }
                        if l > 2 {
                            let parent = level.parent[b] as usize;
                            self.transfer_down(
                                child_side(level.keys[b]),
                                &parent_local[parent * p3..(parent + 1) * p3],
                                out_b,
                                &mut scratch,
                            );
                        }
                    }
                });
            local[l] = loc;
        }

        // Leaves: local expansion plus the near field, point by point.
        let h = self.half_width(leaf);
        let keys = &self.levels[leaf].keys;
        let sizes: Vec<usize> = (0..keys.len())
            .map(|b| (self.leaf_start[b + 1] - self.leaf_start[b]) as usize)
            .collect();
        let mut values = vec![0.0; n];
        let leaf_local = &local[leaf];
        // Leaf `b`'s values: far field, then the near leaves in list order. With pair buffers (self
        // products), summing a near leaf numbered above `b` also leaves the terms of `b`'s points for
        // that leaf in their pair's buffer, and a near leaf numbered below `b` is left to its own pass.
        let leaf_values = |b: usize, vals: &mut [f64], mut pairs: Option<&mut [f64]>| {
            let c = self.box_centre(leaf, keys[b]);
            let mut w = [vec![0.0; self.p], vec![0.0; self.p], vec![0.0; self.p]];
            let first = self.leaf_start[b] as usize;
            // The leaf depth is at least 2, so every leaf has a local expansion.
            let loc = &leaf_local[b * p3..(b + 1) * p3];
            let near_range = self.near_offsets[b] as usize..self.near_offsets[b + 1] as usize;
            let near = &self.near[near_range.clone()];
            // With pair buffers, the leaf's own pairs are summed once too: point `i` takes the terms
            // of the points after it and leaves its own term for them in `own`.
            let mut own = vec![0.0; if pairs.is_some() { vals.len() } else { 0 }];
            for (i, v) in (first..).zip(vals.iter_mut()) {
                let x = DVec3::new(self.xs[i], self.ys[i], self.zs[i]);
                self.point_weights(x, c, h, &mut w);
                let mut s = tensor_dot(&w, loc);
                for (k, &nb) in near_range.clone().zip(near) {
                    let r = start[nb as usize] as usize..start[nb as usize + 1] as usize;
                    if r.is_empty() {
                        continue;
                    }
                    let Some(buffers) = pairs.as_deref_mut() else {
                        s += sum_r(x, &xs[r.clone()], &ys[r.clone()], &zs[r.clone()], &q[r]);
                        continue;
                    };
                    let (nb, r) = (nb as usize, if nb as usize == b { i + 1..r.end } else { r });
                    let sources = (
                        &xs[r.clone()],
                        &ys[r.clone()],
                        &zs[r.clone()],
                        &q[r.clone()],
                    );
                    if nb == b {
                        s += sum_r_scatter(x, sources, q[i], &mut own[i + 1 - first..]);
                    } else if nb > b {
                        let at = self.near_pair_buffer[k] - self.pair_buffer_start[b];
                        s += sum_r_scatter(x, sources, q[i], &mut buffers[at..at + r.len()]);
                    }
                }
                *v = s;
            }
            for (v, o) in vals.iter_mut().zip(&own) {
                *v += o;
            }
        };
        if self.pair_buffer_start.is_empty() {
            let chunks = split_by_sizes(&mut values, &sizes);
            chunks
                .into_par_iter()
                .enumerate()
                .for_each(|(b, vals)| leaf_values(b, vals, None));
        } else {
            // Each pair of adjacent leaves is summed once: the lower-numbered leaf's pass puts the
            // pair's terms for the other leaf's points in the pair's buffer, and each leaf then adds
            // its buffers from lower-numbered leaves, in its near list's order.
            let starts = &self.pair_buffer_start;
            let mut buffers = vec![0.0; starts[starts.len() - 1]];
            let buffer_sizes: Vec<usize> = starts.windows(2).map(|w| w[1] - w[0]).collect();
            split_by_sizes(&mut values, &sizes)
                .into_par_iter()
                .zip(split_by_sizes(&mut buffers, &buffer_sizes))
                .enumerate()
                .for_each(|(b, (vals, pairs))| leaf_values(b, vals, Some(pairs)));
            let buffers = &buffers;
            split_by_sizes(&mut values, &sizes)
                .into_par_iter()
                .enumerate()
                .for_each(|(b, vals)| {
                    let near_range =
                        self.near_offsets[b] as usize..self.near_offsets[b + 1] as usize;
                    for k in near_range {
                        if (self.near[k] as usize) < b {
                            let at = self.near_pair_buffer[k];
                            let len = vals.len();
                            for (v, &t) in vals.iter_mut().zip(&buffers[at..at + len]) {
                                *v += t;
                            }
                        }
                    }
                });
        }
        for (&i, &v) in self.order.iter().zip(&values) {
            out[i as usize] = v;
        }
    }

    /// Adds the child's node charges, interpolated to the parent's nodes, to `parent`.
    fn transfer_up(
        &self,
        side: [usize; 3],
        child: &[f64],
        parent: &mut [f64],
        scratch: &mut [f64],
    ) {
        let t = side.map(|s| self.transfer[s].as_slice());
        tensor_apply(self.p, t, child, parent, scratch);
    }

    /// Adds the parent's node potentials, interpolated to the child's nodes, to `child` (the
    /// transpose of [`Fmm::transfer_up`]).
    fn transfer_down(
        &self,
        side: [usize; 3],
        parent: &[f64],
        child: &mut [f64],
        scratch: &mut [f64],
    ) {
        let t = side.map(|s| self.transfer_t[s].as_slice());
        tensor_apply(self.p, t, parent, child, scratch);
    }

    /// Bytes held (for the memory budget), not counting one product's temporaries.
    pub fn memory_bytes(&self) -> usize {
        let boxes: usize = self.levels.iter().map(|l| l.keys.len()).sum();
        let pairs: usize = self.levels.iter().map(|l| l.far.len()).sum();
        let sources = self
            .sources
            .as_ref()
            .map_or(0, |s| s.charge.len() * (3 * 8 + 4) + s.leaf_start.len() * 4);
        self.len() * (3 * 8 + 4)
            + sources
            + boxes * (8 + 8 + 4 + 4)
            + pairs * 8
            + self.near.len() * 4
            + (self.near_pair_buffer.len() + self.pair_buffer_start.len()) * 8
            + self.m2l.iter().map(|m| m.len() * 8).sum::<usize>()
            + self.basis.len() * 8
    }

    /// Bytes one product allocates: node charges and potentials per box, compressed, the values and
    /// the near field's pair buffers.
    pub fn product_bytes(&self) -> usize {
        let boxes: usize = self.levels.iter().map(|l| l.keys.len()).sum();
        let p3 = self.p * self.p * self.p;
        let pair_buffers = self.pair_buffer_start.last().copied().unwrap_or(0);
        boxes * (2 * p3 + self.rank) * 8 + self.len() * 16 + pair_buffers * 8
    }
}

/// `out[a, b, c] += sum M_x[a][i] M_y[b][j] M_z[c][k] input[i, j, k]` for `p x p` row-major matrices
/// `m`, one axis at a time (z, then y, then x); `scratch` holds `2 p^3`.
fn tensor_apply(p: usize, m: [&[f64]; 3], input: &[f64], out: &mut [f64], scratch: &mut [f64]) {
    let (a, b) = scratch.split_at_mut(p * p * p);
    for i in 0..p * p {
        for c in 0..p {
            let row = &m[2][c * p..(c + 1) * p];
            a[i * p + c] = row
                .iter()
                .zip(&input[i * p..(i + 1) * p])
                .map(|(x, y)| x * y)
                .sum();
        }
    }
    for i in 0..p {
        for r in 0..p {
            let row = &m[1][r * p..(r + 1) * p];
            for c in 0..p {
                b[(i * p + r) * p + c] = (0..p).map(|j| row[j] * a[(i * p + j) * p + c]).sum();
            }
        }
    }
    for r in 0..p {
        let row = &m[0][r * p..(r + 1) * p];
        for j in 0..p * p {
            out[r * p * p + j] += (0..p).map(|i| row[i] * b[i * p * p + j]).sum::<f64>();
        }
    }
}

/// Which half of its parent a box is in, per axis (0 lower, 1 upper).
fn child_side(key: u64) -> [usize; 3] {
    [
        ((key >> 2) & 1) as usize,
        ((key >> 1) & 1) as usize,
        (key & 1) as usize,
    ]
}

fn tensor_accumulate(w: &[Vec<f64>; 3], q: f64, out: &mut [f64]) {
    let mut k = 0;
    for &a in &w[0] {
        let qa = q * a;
        for &b in &w[1] {
            let qab = qa * b;
            for &c in &w[2] {
                out[k] += qab * c;
                k += 1;
            }
        }
    }
}

fn tensor_dot(w: &[Vec<f64>; 3], values: &[f64]) -> f64 {
    let mut k = 0;
    let mut total = 0.0;
    for &a in &w[0] {
        let mut sa = 0.0;
        for &b in &w[1] {
            let mut sb = 0.0;
            for &c in &w[2] {
                sb += c * values[k];
                k += 1;
            }
            sa += b * sb;
        }
        total += a * sa;
    }
    total
}

/// Calls `f` with the index of every nonempty box (in sorted `keys`) adjacent to or equal to `c`.
fn for_each_neighbour(keys: &[u64], c: [i64; 3], mut f: impl FnMut(usize)) {
    for dx in -1..=1 {
        for dy in -1..=1 {
            for dz in -1..=1 {
                let n = [c[0] + dx, c[1] + dy, c[2] + dz];
                if n.iter().any(|&v| v < 0) {
                    continue;
                }
                let key = morton([n[0] as u64, n[1] as u64, n[2] as u64]);
                if let Ok(i) = keys.binary_search(&key) {
                    f(i);
                }
            }
        }
    }
}

/// For a self product: per entry of the near lists (CSR `near_offsets`, `near`) that joins two
/// different leaves, the start of that pair's buffer (as many values as the higher-numbered leaf has
/// points), the buffers ordered by their lower-numbered leaf, and the start of each leaf's buffers.
fn pair_buffers(
    leaf_start: &[u32],
    near_offsets: &[u32],
    near: &[u32],
) -> (Vec<usize>, Vec<usize>) {
    let leaves = near_offsets.len() - 1;
    let points = |b: usize| (leaf_start[b + 1] - leaf_start[b]) as usize;
    let entries = |b: usize| near_offsets[b] as usize..near_offsets[b + 1] as usize;
    let mut at = vec![usize::MAX; near.len()];
    let mut starts = Vec::with_capacity(leaves + 1);
    let mut total = 0usize;
    for a in 0..leaves {
        starts.push(total);
        for k in entries(a) {
            let b = near[k] as usize;
            if b > a {
                at[k] = total;
                total += points(b);
            }
        }
    }
    starts.push(total);
    for b in 0..leaves {
        for k in entries(b) {
            let a = near[k] as usize;
            if a < b {
                // Adjacency is symmetric, so `b` is in `a`'s list.
                let upper = entries(a)
                    .find(|&j| near[j] as usize == b)
                    .expect("adjacent leaves list each other");
                at[k] = at[upper];
            }
        }
    }
    (at, starts)
}

/// The leaf depth with the least estimated cost of a product from `sources` to `points` (an octree of
/// cube `(root_lo, side)`, `(p, rank)` the expansions): near point pairs, each summed once for both
/// of its points when `pairs_summed_once` (the self product), plus far-field work.
fn choose_leaf_depth(
    points: &[DVec3],
    sources: &[DVec3],
    (root_lo, side): (DVec3, f64),
    (p, rank): (usize, usize),
    pairs_summed_once: bool,
) -> usize {
    let p3 = (p * p * p) as f64;
    let occupied = |points: &[DVec3], depth: usize| {
        let mut keys: Vec<u64> = points
            .iter()
            .map(|&x| cell_key(x, root_lo, side, depth))
            .collect();
        keys.sort_unstable();
        let mut boxes: Vec<(u64, usize)> = Vec::new();
        for k in keys {
            match boxes.last_mut() {
                Some((key, n)) if *key == k => *n += 1,
                _ => boxes.push((k, 1)),
            }
        }
        boxes
    };
    let mut best = (f64::INFINITY, 2usize);
    for depth in 2..=MAX_DEPTH {
        let boxes = occupied(points, depth);
        let source_boxes = occupied(sources, depth);
        let source_keys: Vec<u64> = source_boxes.iter().map(|b| b.0).collect();
        let mut near_pairs = 0.0;
        for &(key, n) in &boxes {
            for_each_neighbour(&source_keys, coords(key), |i| {
                near_pairs += (n * source_boxes[i].1) as f64;
            });
        }
        if pairs_summed_once {
            near_pairs *= 0.5;
        }
        // In units of a near pair: each box (over all levels, ~1.15 per leaf) takes ~100 translations of
        // rank^2 multiply-adds, at about a tenth of a near pair each (docs/decisions/0058).
        let far = boxes.len() as f64 * 1.15 * 100.0 * (rank * rank) as f64 * 0.1;
        let cost = near_pairs + far + (points.len() + sources.len()) as f64 * p3;
        if cost < best.0 {
            best = (cost, depth);
        }
        if boxes.len() * 4 > points.len() {
            break;
        }
    }
    best.1
}

/// The SVD basis of all far-field translations between unit boxes, and each translation compressed.
fn compressed_translations(p: usize, cutoff: f64) -> (Vec<f64>, usize, Vec<Vec<f64>>) {
    let p3 = p * p * p;
    let nodes = cheb_points(p);
    let grid: Vec<DVec3> = (0..p3)
        .map(|i| DVec3::new(nodes[i / (p * p)], nodes[(i / p) % p], nodes[i % p]))
        .collect();
    let far: Vec<[i64; 3]> = (0..OFFSETS as i64)
        .map(|i| [i / 49 - 3, (i / 7) % 7 - 3, i % 7 - 3])
        .filter(|&o| is_far_offset(o))
        .collect();
    // Boxes of half-width 1: target node x_m, source node y_k + 2o (o = target - source).
    let kernel = |o: [i64; 3]| {
        let shift = DVec3::new(o[0] as f64, o[1] as f64, o[2] as f64) * 2.0;
        faer::Mat::<f64>::from_fn(p3, p3, |m, k| (grid[m] - grid[k] + shift).length())
    };
    // Gram matrix of the stacked translations, summed over fixed groups so the result does not depend on
    // the thread count.
    // The nearest offsets (one box between the boxes) have the slowest-decaying spectra; the basis
    // they span also holds the farther ones' (checked against direct sums in the tests).
    let nearest: Vec<[i64; 3]> = far
        .iter()
        .copied()
        .filter(|o| o.iter().all(|c| c.abs() <= 2))
        .collect();
    let groups: Vec<faer::Mat<f64>> = nearest
        .par_chunks(8)
        .map(|chunk| {
            let mut g = faer::Mat::<f64>::zeros(p3, p3);
            for &o in chunk {
                let k = kernel(o);
                faer::linalg::matmul::matmul(
                    g.as_mut(),
                    faer::Accum::Add,
                    k.as_ref(),
                    k.transpose(),
                    1.0,
                    faer::Par::Seq,
                );
            }
            g
        })
        .collect();
    let mut gram = faer::Mat::<f64>::zeros(p3, p3);
    for g in &groups {
        gram += g;
    }
    let eigen = gram
        .self_adjoint_eigen(faer::Side::Lower)
        .expect("symmetric eigendecomposition of a finite matrix");
    let values = eigen.S().column_vector();
    let mut idx: Vec<usize> = (0..p3).collect();
    idx.sort_by(|&a, &b| values[b].total_cmp(&values[a]));
    let largest = values[idx[0]].max(0.0).sqrt();
    let rank = idx
        .iter()
        .take_while(|&&i| values[i].max(0.0).sqrt() > cutoff * largest)
        .count()
        .max(1);
    let vectors = eigen.U();
    let mut basis = vec![0.0; p3 * rank];
    for m in 0..p3 {
        for (j, &i) in idx[..rank].iter().enumerate() {
            basis[m * rank + j] = vectors[(m, i)];
        }
    }
    let u = faer::Mat::<f64>::from_fn(p3, rank, |m, j| basis[m * rank + j]);
    let mut m2l = vec![Vec::new(); OFFSETS];
    // K_{-o} = K_o^T (the kernel is symmetric and the node grid is the same in every box), so
    // C_{-o} = C_o^T: half of the translations are transposes.
    let half: Vec<[i64; 3]> = far
        .iter()
        .copied()
        .filter(|&o| offset_index(o) > offset_index([-o[0], -o[1], -o[2]]))
        .collect();
    let compressed: Vec<([i64; 3], Vec<f64>)> = half
        .par_iter()
        .map(|&o| {
            let k = kernel(o);
            let c = u.transpose() * &k * &u;
            let mut column_major = vec![0.0; rank * rank];
            for a in 0..rank {
                for b in 0..rank {
                    column_major[b * rank + a] = c[(a, b)];
                }
            }
            (o, column_major)
        })
        .collect();
    for (o, c) in compressed {
        let mut transposed = vec![0.0; rank * rank];
        for a in 0..rank {
            for b in 0..rank {
                transposed[a * rank + b] = c[b * rank + a];
            }
        }
        m2l[offset_index(o)] = c;
        m2l[offset_index([-o[0], -o[1], -o[2]])] = transposed;
    }
    (basis, rank, m2l)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn frame_like(n: usize, seed: u64) -> Vec<DVec3> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        (0..n)
            .map(|i| {
                let tilt = (i % 23) as f64 * 0.07;
                let u: f64 = rng.random_range(0.0..40.0);
                let v: f64 = rng.random_range(0.0..30.0);
                DVec3::new(u, v * tilt.cos(), v * tilt.sin() + (i % 23) as f64 * 0.8)
            })
            .collect()
    }

    #[test]
    fn product_is_identical_on_one_and_two_threads() {
        let points = frame_like(9_000, 8);
        let q: Vec<f64> = (0..points.len())
            .map(|i| ((i * 7919) % 201) as f64 - 100.0)
            .collect();
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                let fmm = Fmm::new(
                    &points,
                    FmmParams {
                        nodes_per_side: 6,
                        svd_cutoff: 1e-6,
                        leaf_depth: Some(4),
                    },
                );
                let mut out = vec![0.0; points.len()];
                fmm.product(&q, &mut out);
                out.iter().map(|v| v.to_bits()).collect::<Vec<u64>>()
            })
        };
        assert_eq!(run(1), run(2));
    }

    #[test]
    fn products_from_a_subset_of_sources_match_direct_sums() {
        // Every 9th point charged, as a coarse level is; its cost model picks its own depth.
        let points = frame_like(12_000, 6);
        let sources: Vec<u32> = (0..points.len() as u32).step_by(9).collect();
        let mut rng = ChaCha8Rng::seed_from_u64(10);
        let q: Vec<f64> = sources
            .iter()
            .map(|_| rng.random_range(-1.0..1.0))
            .collect();
        let fmm = Fmm::with_sources(
            &points,
            &sources,
            FmmParams {
                nodes_per_side: 6,
                svd_cutoff: 1e-6,
                leaf_depth: None,
            },
        );
        let mut out = vec![0.0; points.len()];
        fmm.product(&q, &mut out);
        let mut worst: f64 = 0.0;
        for (i, &t) in points.iter().enumerate().step_by(29) {
            let (mut exact, mut scale) = (0.0, 0.0);
            for (&j, &c) in sources.iter().zip(&q) {
                let r = (t - points[j as usize]).length();
                exact += c * r;
                scale += c.abs() * r;
            }
            worst = worst.max((out[i] - exact).abs() / scale);
        }
        // As the self product at p = 6 (1.5e-7 there).
        assert!(worst <= 2e-6, "worst relative error {worst}");
        // The same charges placed on every point, the others zero: the self product's result.
        let mut full = vec![0.0; points.len()];
        for (&j, &c) in sources.iter().zip(&q) {
            full[j as usize] = c;
        }
        let depth = fmm.levels.len() - 1;
        let whole = Fmm::new(
            &points,
            FmmParams {
                nodes_per_side: 6,
                svd_cutoff: 1e-6,
                leaf_depth: Some(depth),
            },
        );
        let mut want = vec![0.0; points.len()];
        whole.product(&full, &mut want);
        for (a, b) in out.iter().zip(&want) {
            assert!((a - b).abs() <= 1e-9 * b.abs().max(1.0), "{a} vs {b}");
        }
    }

    #[test]
    fn morton_round_trips() {
        for c in [[0u64, 0, 0], [1, 2, 3], [2_000_000, 5, 1_048_575]] {
            let k = morton(c);
            assert_eq!(coords(k), c.map(|v| v as i64));
        }
    }

    #[test]
    fn fmm_matches_direct_sums() {
        let points = frame_like(12_000, 5);
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let q: Vec<f64> = (0..points.len())
            .map(|_| rng.random_range(-1.0..1.0))
            .collect();
        // Errors measured: 1.6e-5, 1.5e-7, 2.4e-9; depth 5 runs translations and transfers over
        // four levels.
        for (p, cutoff, depth, tol) in [
            (4, 1e-4, None, 1e-4),
            (6, 1e-6, None, 2e-6),
            (6, 1e-6, Some(5), 2e-6),
            (8, 1e-8, None, 2e-8),
        ] {
            let fmm = Fmm::new(
                &points,
                FmmParams {
                    nodes_per_side: p,
                    svd_cutoff: cutoff,
                    leaf_depth: depth,
                },
            );
            assert!(fmm.shape().2 > 0, "no translations at p {p}");
            let mut out = vec![0.0; points.len()];
            fmm.product(&q, &mut out);
            let mut worst: f64 = 0.0;
            for i in (0..points.len()).step_by(37) {
                let t = points[i];
                let mut exact = 0.0;
                let mut scale = 0.0;
                for (y, &c) in points.iter().zip(&q) {
                    let r = (t - *y).length();
                    exact += c * r;
                    scale += c.abs() * r;
                }
                worst = worst.max((out[i] - exact).abs() / scale);
            }
            eprintln!(
                "p {p} rank {} shape {:?} worst {worst:e}",
                fmm.rank,
                fmm.shape()
            );
            assert!(worst <= tol, "p {p}: worst relative error {worst}");
        }
    }
}
