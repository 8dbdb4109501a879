//! Point trees and the kernel-independent treecode for `sum_j q_j |x - y_j|`.
//!
//! Tree: binary splits of the tight bounding box at the median of its longest side, until a node holds at most
//! `leaf_size` points. Splitting by count (not by fixed size) suits ultrasound samples, which are dense inside
//! frame planes and sparse between them.
//!
//! Far field: barycentric Lagrange treecode (Wang, Krasny & Tlupova 2020). A source cluster is replaced by
//! proxy charges on a tensor Chebyshev grid over its box (charges = sum of Lagrange weights times the source
//! charges, computed bottom-up from the children's proxies); a target leaf interacts with a cluster through
//! its proxies when the cluster is well separated (`r_cluster <= theta * (distance - r_leaf)`), and with the
//! points themselves otherwise. The kernel only needs to be evaluated, so gradients come for free. The grid
//! uses fewer nodes along thin box sides (a cluster inside one frame plane is flat), with the count chosen so
//! each side's interpolation error matches the longest side's.
//!
//! This tree is the treecode's cluster tree (tight boxes that carry interpolation proxies and interaction
//! lists), not a query index; the crate's query indexes are in [`crate::spatial`].

use glam::DVec3;

pub(crate) use super::kernel::{sum_r, sum_r_grad};
use rayon::prelude::*;

/// Accuracy/speed parameters of the treecode.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct TreecodeParams {
    /// Separation ratio: a cluster of radius r is far from a leaf when r <= theta * (distance - leaf radius).
    pub theta: f64,
    /// Chebyshev nodes per side along a cluster's longest side.
    pub nodes_per_side: usize,
    pub leaf_size: usize,
}

impl TreecodeParams {
    /// Parameters for a relative far-field accuracy `eps` (kernel-sum relative error). The error of a
    /// Chebyshev interpolation of |x - y| over a box of half-width a at distance d decays like (a / 2d)^n;
    /// the table below was calibrated against direct sums (see tests), with theta fixed at 0.5.
    pub fn for_accuracy(eps: f64) -> Self {
        let eps = eps.clamp(1e-12, 1e-1);
        let theta: f64 = 0.5;
        // (theta/2)^n <= eps  ->  n = ln(eps)/ln(theta/2); one node extra for the constant.
        let n = (eps.ln() / (theta / 2.0).ln()).ceil() as usize + 1;
        TreecodeParams {
            theta,
            nodes_per_side: n.clamp(2, 12),
            leaf_size: 64,
        }
    }
}

#[derive(Debug, Clone, Copy)]
pub(crate) struct Node {
    pub start: u32,
    pub end: u32,
    /// Children are `first_child` and `first_child + 1`; 0 means leaf.
    pub first_child: u32,
    pub depth: u32,
    pub lo: DVec3,
    pub hi: DVec3,
}

impl Node {
    pub fn len(&self) -> usize {
        (self.end - self.start) as usize
    }
    pub fn is_leaf(&self) -> bool {
        self.first_child == 0
    }
    pub fn centre(&self) -> DVec3 {
        (self.lo + self.hi) * 0.5
    }
    pub fn radius(&self) -> f64 {
        (self.hi - self.lo).length() * 0.5
    }
}

/// Points reordered so every node is a contiguous range; coordinates stored as separate arrays.
#[derive(Debug, Clone)]
pub(crate) struct Tree {
    pub xs: Vec<f64>,
    pub ys: Vec<f64>,
    pub zs: Vec<f64>,
    /// Tree position -> index in the input slice.
    pub order: Vec<u32>,
    pub nodes: Vec<Node>,
    /// Leaf node indices in increasing `start` order.
    pub leaves: Vec<u32>,
}

impl Tree {
    pub fn build(points: &[DVec3], leaf_size: usize) -> Tree {
        let leaf_size = leaf_size.max(1);
        let mut order: Vec<u32> = (0..points.len() as u32).collect();
        let mut nodes = vec![Node {
            start: 0,
            end: points.len() as u32,
            first_child: 0,
            depth: 0,
            lo: DVec3::ZERO,
            hi: DVec3::ZERO,
        }];
        let mut stack = vec![0usize];
        while let Some(ni) = stack.pop() {
            let node = nodes[ni];
            let range = &mut order[node.start as usize..node.end as usize];
            let (lo, hi) = bounds(points, range);
            nodes[ni].lo = lo;
            nodes[ni].hi = hi;
            if range.len() <= leaf_size {
                continue;
            }
            let extent = hi - lo;
            let axis = if extent.x >= extent.y && extent.x >= extent.z {
                0
            } else if extent.y >= extent.z {
                1
            } else {
                2
            };
            let mid = range.len() / 2;
            range.select_nth_unstable_by(mid, |&a, &b| {
                points[a as usize][axis]
                    .total_cmp(&points[b as usize][axis])
                    .then(a.cmp(&b))
            });
            let first = nodes.len();
            nodes[ni].first_child = first as u32;
            let split = node.start + mid as u32;
            for (s, e) in [(node.start, split), (split, node.end)] {
                nodes.push(Node {
                    start: s,
                    end: e,
                    first_child: 0,
                    depth: node.depth + 1,
                    lo: DVec3::ZERO,
                    hi: DVec3::ZERO,
                });
            }
            stack.push(first + 1);
            stack.push(first);
        }
        let mut leaves: Vec<u32> = (0..nodes.len() as u32)
            .filter(|&i| nodes[i as usize].is_leaf())
            .collect();
        leaves.sort_by_key(|&i| nodes[i as usize].start);
        let xs = order.iter().map(|&i| points[i as usize].x).collect();
        let ys = order.iter().map(|&i| points[i as usize].y).collect();
        let zs = order.iter().map(|&i| points[i as usize].z).collect();
        Tree {
            xs,
            ys,
            zs,
            order,
            nodes,
            leaves,
        }
    }

    pub fn len(&self) -> usize {
        self.order.len()
    }

    pub fn point(&self, i: usize) -> DVec3 {
        DVec3::new(self.xs[i], self.ys[i], self.zs[i])
    }

    /// Every point, in tree order.
    pub fn points(&self) -> Vec<DVec3> {
        (0..self.len()).map(|i| self.point(i)).collect()
    }

    /// Input-ordered values -> tree order.
    pub fn to_tree_order(&self, values: &[f64]) -> Vec<f64> {
        self.order.iter().map(|&i| values[i as usize]).collect()
    }

    /// Tree-ordered values -> input order.
    pub fn to_input_order<T: Copy + Default>(&self, values: &[T]) -> Vec<T> {
        let mut out = vec![T::default(); values.len()];
        for (&i, &v) in self.order.iter().zip(values) {
            out[i as usize] = v;
        }
        out
    }

    /// The `k` points nearest to `q` (tree positions), nearest first, ties by position.
    pub fn nearest(&self, q: DVec3, k: usize) -> Vec<u32> {
        let mut best: Vec<(f64, u32)> = Vec::with_capacity(k + 1);
        let mut stack = vec![0usize];
        while let Some(ni) = stack.pop() {
            let node = &self.nodes[ni];
            let d_box = box_distance_sq(q, node.lo, node.hi);
            if best.len() == k && d_box > best[k - 1].0 {
                continue;
            }
            if node.is_leaf() {
                for i in node.start..node.end {
                    let d = (self.point(i as usize) - q).length_squared();
                    if best.len() < k || (d, i) < best[k - 1] {
                        let pos = best.partition_point(|e| *e < (d, i));
                        best.insert(pos, (d, i));
                        best.truncate(k);
                    }
                }
            } else {
                let a = node.first_child as usize;
                let (da, db) = (
                    box_distance_sq(q, self.nodes[a].lo, self.nodes[a].hi),
                    box_distance_sq(q, self.nodes[a + 1].lo, self.nodes[a + 1].hi),
                );
                if da <= db {
                    stack.push(a + 1);
                    stack.push(a);
                } else {
                    stack.push(a);
                    stack.push(a + 1);
                }
            }
        }
        best.into_iter().map(|(_, i)| i).collect()
    }
}

fn box_distance_sq(q: DVec3, lo: DVec3, hi: DVec3) -> f64 {
    let d = (lo - q).max(DVec3::ZERO).max(q - hi);
    d.length_squared()
}

fn bounds(points: &[DVec3], idx: &[u32]) -> (DVec3, DVec3) {
    let mut lo = DVec3::splat(f64::INFINITY);
    let mut hi = DVec3::splat(f64::NEG_INFINITY);
    for &i in idx {
        lo = lo.min(points[i as usize]);
        hi = hi.max(points[i as usize]);
    }
    if idx.is_empty() {
        (DVec3::ZERO, DVec3::ZERO)
    } else {
        (lo, hi)
    }
}

/// Chebyshev proxy grid of one node.
#[derive(Debug, Clone, Copy)]
struct Grid {
    offset: u32,
    dims: [u8; 3],
}

impl Grid {
    fn size(&self) -> usize {
        self.dims[0] as usize * self.dims[1] as usize * self.dims[2] as usize
    }
}

/// A source tree with proxy grids: evaluates `sum_j q_j |x - y_j|` (and its gradient) at target leaves.
#[derive(Debug, Clone)]
pub(crate) struct Treecode {
    pub tree: Tree,
    pub params: TreecodeParams,
    /// Per node: proxy grid, if the node has more points than grid nodes (else its points are used).
    grids: Vec<Option<Grid>>,
    px: Vec<f64>,
    py: Vec<f64>,
    pz: Vec<f64>,
    /// Depth levels (deepest first), each the nodes with grids at that depth and their proxy range.
    levels: Vec<(Vec<u32>, usize, usize)>,
}

/// Near and far interactions of each target leaf, flattened. Entry: node index, high bit = use proxies.
#[derive(Debug, Clone)]
pub(crate) struct InteractionLists {
    offsets: Vec<u32>,
    entries: Vec<u32>,
}

const FAR_BIT: u32 = 1 << 31;

/// Targets in leaves (a tree's point order), for evaluation.
pub(crate) trait Targets: Sync {
    fn leaf_ranges(&self) -> Vec<(usize, usize, DVec3, f64)>;
    fn target(&self, i: usize) -> DVec3;
}

impl Targets for Tree {
    fn leaf_ranges(&self) -> Vec<(usize, usize, DVec3, f64)> {
        self.leaves
            .iter()
            .map(|&l| {
                let n = &self.nodes[l as usize];
                (n.start as usize, n.end as usize, n.centre(), n.radius())
            })
            .collect()
    }
    fn target(&self, i: usize) -> DVec3 {
        self.point(i)
    }
}

impl Treecode {
    pub fn new(points: &[DVec3], params: TreecodeParams) -> Treecode {
        let tree = Tree::build(points, params.leaf_size);
        let mut grids = vec![None; tree.nodes.len()];
        let max_depth = tree.nodes.iter().map(|n| n.depth).max().unwrap_or(0);
        let mut by_depth: Vec<Vec<u32>> = vec![Vec::new(); max_depth as usize + 1];
        let mut dims_of = vec![[0u8; 3]; tree.nodes.len()];
        for (i, node) in tree.nodes.iter().enumerate() {
            let dims = grid_dims(node.lo, node.hi, params);
            let size = dims.iter().map(|&d| d as usize).product::<usize>();
            if node.len() > size {
                by_depth[node.depth as usize].push(i as u32);
                dims_of[i] = dims;
            }
        }
        let (mut px, mut py, mut pz) = (Vec::new(), Vec::new(), Vec::new());
        let mut levels = Vec::new();
        for nodes_at in by_depth.into_iter().rev() {
            let begin = px.len();
            for &ni in &nodes_at {
                let node = &tree.nodes[ni as usize];
                let dims = dims_of[ni as usize];
                grids[ni as usize] = Some(Grid {
                    offset: px.len() as u32,
                    dims,
                });
                let cx = cheb_nodes(node.lo.x, node.hi.x, dims[0] as usize);
                let cy = cheb_nodes(node.lo.y, node.hi.y, dims[1] as usize);
                let cz = cheb_nodes(node.lo.z, node.hi.z, dims[2] as usize);
                for &x in &cx {
                    for &y in &cy {
                        for &z in &cz {
                            px.push(x);
                            py.push(y);
                            pz.push(z);
                        }
                    }
                }
            }
            levels.push((nodes_at, begin, px.len()));
        }
        Treecode {
            tree,
            params,
            grids,
            px,
            py,
            pz,
            levels,
        }
    }

    /// Proxy charges for tree-ordered point charges `q`, computed bottom-up.
    pub fn upward(&self, q: &[f64]) -> Vec<f64> {
        let mut proxies = vec![0.0; self.px.len()];
        for (nodes_at, begin, end) in &self.levels {
            let (done, rest) = proxies.split_at_mut(*begin);
            let current = &mut rest[..end - begin];
            let sizes: Vec<usize> = nodes_at
                .iter()
                .map(|&n| self.grids[n as usize].map_or(0, |g| g.size()))
                .collect();
            let chunks = split_by_sizes(current, &sizes);
            let done: &[f64] = done;
            nodes_at
                .par_iter()
                .zip(chunks.into_par_iter())
                .for_each(|(&ni, out)| self.node_charges(ni as usize, q, done, out));
        }
        proxies
    }

    fn node_charges(&self, ni: usize, q: &[f64], proxies: &[f64], out: &mut [f64]) {
        let node = &self.tree.nodes[ni];
        let grid = self.grids[ni].expect("node with grid");
        let [nx, ny, nz] = grid.dims.map(|d| d as usize);
        let (cx, cy, cz) = (
            cheb_nodes(node.lo.x, node.hi.x, nx),
            cheb_nodes(node.lo.y, node.hi.y, ny),
            cheb_nodes(node.lo.z, node.hi.z, nz),
        );
        let mut wx = vec![0.0; nx];
        let mut wy = vec![0.0; ny];
        let mut wz = vec![0.0; nz];
        let mut add = |p: DVec3, charge: f64| {
            lagrange_weights(&cx, p.x, &mut wx);
            lagrange_weights(&cy, p.y, &mut wy);
            lagrange_weights(&cz, p.z, &mut wz);
            let mut k = 0;
            for &a in &wx {
                let ca = charge * a;
                for &b in &wy {
                    let cab = ca * b;
                    for &c in &wz {
                        out[k] += cab * c;
                        k += 1;
                    }
                }
            }
        };
        let mut sources = Vec::with_capacity(2);
        if node.is_leaf() {
            sources.push(ni);
        } else {
            sources.push(node.first_child as usize);
            sources.push(node.first_child as usize + 1);
        }
        for s in sources {
            match self.grids[s] {
                Some(g) if s != ni => {
                    let o = g.offset as usize;
                    for k in o..o + g.size() {
                        add(DVec3::new(self.px[k], self.py[k], self.pz[k]), proxies[k]);
                    }
                }
                _ => {
                    let child = &self.tree.nodes[s];
                    for i in child.start as usize..child.end as usize {
                        add(self.tree.point(i), q[i]);
                    }
                }
            }
        }
    }

    /// Interaction lists of every target leaf against this source tree.
    pub fn interactions(&self, targets: &dyn Targets) -> InteractionLists {
        let leaves = targets.leaf_ranges();
        let lists: Vec<Vec<u32>> = leaves
            .par_iter()
            .map(|&(_, _, centre, radius)| self.leaf_list(centre, radius))
            .collect();
        let (offsets, entries) = flatten_lists(lists);
        InteractionLists { offsets, entries }
    }

    fn leaf_list(&self, centre: DVec3, radius: f64) -> Vec<u32> {
        let mut list = Vec::new();
        let mut stack = vec![0usize];
        let theta = self.params.theta;
        while let Some(ni) = stack.pop() {
            let node = &self.tree.nodes[ni];
            if node.len() == 0 {
                continue;
            }
            let dist = (node.centre() - centre).length();
            let far = node.radius() <= theta * (dist - radius);
            if far {
                match self.grids[ni] {
                    Some(_) => list.push(ni as u32 | FAR_BIT),
                    None => list.push(ni as u32),
                }
            } else if node.is_leaf() {
                list.push(ni as u32);
            } else {
                stack.push(node.first_child as usize + 1);
                stack.push(node.first_child as usize);
            }
        }
        list
    }

    /// Values (and optionally gradients) at the targets, in target order, for tree-ordered charges `q`.
    pub fn evaluate(
        &self,
        targets: &dyn Targets,
        lists: &InteractionLists,
        q: &[f64],
        proxies: &[f64],
        values: &mut [f64],
        gradients: Option<&mut [DVec3]>,
    ) {
        let leaves = targets.leaf_ranges();
        let sizes: Vec<usize> = leaves.iter().map(|l| l.1 - l.0).collect();
        let value_chunks = split_by_sizes(values, &sizes);
        let grad_chunks: Vec<Option<&mut [DVec3]>> = match gradients {
            Some(g) => split_by_sizes(g, &sizes).into_iter().map(Some).collect(),
            None => (0..sizes.len()).map(|_| None).collect(),
        };
        value_chunks
            .into_par_iter()
            .zip(grad_chunks.into_par_iter())
            .enumerate()
            .for_each(|(li, (vals, grads))| {
                let (start, end, _, _) = leaves[li];
                let entries =
                    &lists.entries[lists.offsets[li] as usize..lists.offsets[li + 1] as usize];
                let tpos: Vec<DVec3> = (start..end).map(|i| targets.target(i)).collect();
                vals.fill(0.0);
                match grads {
                    None => {
                        for &e in entries {
                            let (sx, sy, sz, sq) = self.entry_sources(e, q, proxies);
                            for (t, v) in tpos.iter().zip(vals.iter_mut()) {
                                *v += sum_r(*t, sx, sy, sz, sq);
                            }
                        }
                    }
                    Some(grads) => {
                        grads.fill(DVec3::ZERO);
                        for &e in entries {
                            let (sx, sy, sz, sq) = self.entry_sources(e, q, proxies);
                            for ((t, v), g) in
                                tpos.iter().zip(vals.iter_mut()).zip(grads.iter_mut())
                            {
                                let (dv, dg) = sum_r_grad(*t, sx, sy, sz, sq);
                                *v += dv;
                                *g += dg;
                            }
                        }
                    }
                }
            });
    }

    #[inline]
    fn entry_sources<'a>(
        &'a self,
        e: u32,
        q: &'a [f64],
        proxies: &'a [f64],
    ) -> (&'a [f64], &'a [f64], &'a [f64], &'a [f64]) {
        let ni = (e & !FAR_BIT) as usize;
        if e & FAR_BIT != 0 {
            let g = self.grids[ni].expect("far entry has grid");
            let r = g.offset as usize..g.offset as usize + g.size();
            (
                &self.px[r.clone()],
                &self.py[r.clone()],
                &self.pz[r.clone()],
                &proxies[r],
            )
        } else {
            let n = &self.tree.nodes[ni];
            let r = n.start as usize..n.end as usize;
            (
                &self.tree.xs[r.clone()],
                &self.tree.ys[r.clone()],
                &self.tree.zs[r.clone()],
                &q[r],
            )
        }
    }

    /// Bytes held by the treecode (for the memory budget).
    pub fn memory_bytes(&self) -> usize {
        self.tree.len() * (3 * 8 + 4)
            + self.tree.nodes.len() * std::mem::size_of::<Node>()
            + self.px.len() * 3 * 8
            + self.grids.len() * std::mem::size_of::<Option<Grid>>()
    }
}

impl InteractionLists {
    pub fn memory_bytes(&self) -> usize {
        (self.offsets.len() + self.entries.len()) * 4
    }
}

/// Lists concatenated, with the offset of each list's start (CSR; one more offset than lists).
pub(crate) fn flatten_lists<T: Copy>(lists: Vec<Vec<T>>) -> (Vec<u32>, Vec<T>) {
    let mut offsets = Vec::with_capacity(lists.len() + 1);
    let mut entries = Vec::with_capacity(lists.iter().map(Vec::len).sum());
    offsets.push(0);
    for l in lists {
        entries.extend_from_slice(&l);
        offsets.push(entries.len() as u32);
    }
    (offsets, entries)
}

/// Splits `data` into consecutive chunks of the given sizes.
pub(crate) fn split_by_sizes<'a, T>(mut data: &'a mut [T], sizes: &[usize]) -> Vec<&'a mut [T]> {
    let mut out = Vec::with_capacity(sizes.len());
    for &s in sizes {
        let (head, tail) = std::mem::take(&mut data).split_at_mut(s);
        out.push(head);
        data = tail;
    }
    out
}

fn grid_dims(lo: DVec3, hi: DVec3, params: TreecodeParams) -> [u8; 3] {
    let half = (hi - lo) * 0.5;
    let a_max = half.max_element();
    let n_max = params.nodes_per_side;
    let mut dims = [1u8; 3];
    if a_max <= 0.0 {
        return dims;
    }
    // Error along a side of half-width a at distance d ~ (a / 2d)^n, with d >= a_max / theta.
    let reference = (params.theta / 2.0).ln() * n_max as f64;
    for (k, dim) in dims.iter_mut().enumerate() {
        let a = half[k];
        if a <= 1e-9 * a_max {
            *dim = 1;
            continue;
        }
        let rate = (params.theta * a / a_max / 2.0).ln();
        let n = (reference / rate).ceil() as usize;
        *dim = n.clamp(2, n_max) as u8;
    }
    dims
}

/// Chebyshev points of the second kind on [lo, hi] (a single midpoint if n == 1 or the side is empty).
fn cheb_nodes(lo: f64, hi: f64, n: usize) -> Vec<f64> {
    let mid = 0.5 * (lo + hi);
    let half = 0.5 * (hi - lo);
    if n <= 1 {
        return vec![mid];
    }
    (0..n)
        .map(|k| mid + half * (std::f64::consts::PI * k as f64 / (n - 1) as f64).cos())
        .collect()
}

/// Barycentric Lagrange weights of `x` on Chebyshev-2 `nodes`.
fn lagrange_weights(nodes: &[f64], x: f64, out: &mut [f64]) {
    let n = nodes.len();
    if n == 1 {
        out[0] = 1.0;
        return;
    }
    let mut total = 0.0;
    for k in 0..n {
        let d = x - nodes[k];
        if d == 0.0 {
            out.fill(0.0);
            out[k] = 1.0;
            return;
        }
        let mut w = if k % 2 == 0 { 1.0 } else { -1.0 };
        if k == 0 || k == n - 1 {
            w *= 0.5;
        }
        out[k] = w / d;
        total += out[k];
    }
    for o in out.iter_mut() {
        *o /= total;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn direct(points: &[DVec3], q: &[f64], t: DVec3) -> (f64, DVec3) {
        let mut v = 0.0;
        let mut g = DVec3::ZERO;
        for (p, &c) in points.iter().zip(q) {
            let d = t - *p;
            let r = d.length();
            v += c * r;
            if r > 0.0 {
                g += c * d / r;
            }
        }
        (v, g)
    }

    #[test]
    fn treecode_matches_direct_sum_within_requested_accuracy() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        // Frame-like: 20 planes of points, plus random charges of both signs.
        let points: Vec<DVec3> = (0..6000)
            .map(|i| {
                let plane = (i % 20) as f64 * 1.5;
                DVec3::new(
                    rng.random_range(0.0..40.0),
                    rng.random_range(0.0..30.0),
                    plane,
                )
            })
            .collect();
        let q: Vec<f64> = (0..points.len())
            .map(|_| rng.random_range(-1.0..1.0))
            .collect();
        for eps in [1e-2, 1e-4, 1e-6] {
            let tc = Treecode::new(&points, TreecodeParams::for_accuracy(eps));
            let targets = Tree::build(
                &(0..500)
                    .map(|_| {
                        DVec3::new(
                            rng.random_range(-5.0..45.0),
                            rng.random_range(-5.0..35.0),
                            rng.random_range(-5.0..35.0),
                        )
                    })
                    .collect::<Vec<_>>(),
                32,
            );
            let lists = tc.interactions(&targets);
            let qt = tc.tree.to_tree_order(&q);
            let prox = tc.upward(&qt);
            let mut vals = vec![0.0; targets.len()];
            let mut grads = vec![DVec3::ZERO; targets.len()];
            tc.evaluate(&targets, &lists, &qt, &prox, &mut vals, Some(&mut grads));
            let mut vals2 = vec![0.0; targets.len()];
            tc.evaluate(&targets, &lists, &qt, &prox, &mut vals2, None);
            // Relative to the sum of absolute contributions, the scale the accuracy refers to.
            let mut worst: f64 = 0.0;
            for i in 0..targets.len() {
                let t = targets.point(i);
                let (v, g) = direct(&points, &q, t);
                let scale: f64 = points
                    .iter()
                    .zip(&q)
                    .map(|(p, c)| c.abs() * (t - *p).length())
                    .sum();
                worst = worst.max((vals[i] - v).abs() / scale);
                assert!((vals[i] - vals2[i]).abs() <= 1e-9 * scale);
                let gscale: f64 = q.iter().map(|c| c.abs()).sum();
                assert!(
                    (grads[i] - g).length() <= 50.0 * eps * gscale,
                    "gradient {eps}"
                );
            }
            assert!(worst <= eps, "eps {eps}: worst relative error {worst}");
        }
    }

    #[test]
    fn nearest_matches_brute_force() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let points: Vec<DVec3> = (0..700)
            .map(|_| DVec3::new(rng.random(), rng.random(), rng.random()))
            .collect();
        let tree = Tree::build(&points, 16);
        let q = DVec3::splat(0.4);
        let got: Vec<u32> = tree.nearest(q, 25);
        let mut d: Vec<f64> = points.iter().map(|p| (*p - q).length_squared()).collect();
        d.sort_by(f64::total_cmp);
        for (k, &i) in got.iter().enumerate() {
            assert_eq!((tree.point(i as usize) - q).length_squared(), d[k]);
        }
    }
}
