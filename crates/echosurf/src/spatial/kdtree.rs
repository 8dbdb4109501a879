//! A k-d tree over points whose leaf *cells* tile a root box (the partition-of-unity fit's patches):
//! median splits by point count along the axis of widest point spread, each split value strictly
//! between the two sides' coordinates; box queries return point indices in tree order.

use glam::DVec3;

const NO_CHILD: u32 = u32::MAX;

/// A k-d tree over points whose leaf cells tile a root box.
#[derive(Debug, Clone)]
pub(crate) struct KdTree<'a> {
    points: &'a [DVec3],
    nodes: Vec<KdNode>,
    /// Point indices in tree order; node k owns `order[start..end]`.
    order: Vec<u32>,
}

#[derive(Debug, Clone)]
struct KdNode {
    lo: DVec3,
    hi: DVec3,
    start: u32,
    end: u32,
    left: u32,
    right: u32,
}

impl<'a> KdTree<'a> {
    /// Splits `root_lo..root_hi` (which should hold every point) until a leaf holds at most `leaf`
    /// points or all its points coincide.
    pub fn new(points: &'a [DVec3], root_lo: DVec3, root_hi: DVec3, leaf: usize) -> KdTree<'a> {
        let mut tree = KdTree {
            points,
            nodes: Vec::new(),
            order: (0..points.len() as u32).collect(),
        };
        tree.split(root_lo, root_hi, 0, points.len(), leaf.max(1));
        tree
    }

    fn split(&mut self, lo: DVec3, hi: DVec3, start: usize, end: usize, leaf: usize) -> u32 {
        let id = self.nodes.len() as u32;
        self.nodes.push(KdNode {
            lo,
            hi,
            start: start as u32,
            end: end as u32,
            left: NO_CHILD,
            right: NO_CHILD,
        });
        if end - start <= leaf {
            return id;
        }
        let points = self.points;
        let slice = &mut self.order[start..end];
        let (plo, phi) = bounds(
            &slice
                .iter()
                .map(|&i| points[i as usize])
                .collect::<Vec<_>>(),
        );
        let spread = phi - plo;
        let mut axes = [0usize, 1, 2];
        axes.sort_by(|&a, &b| spread[b].total_cmp(&spread[a]).then(a.cmp(&b)));
        let Some((mid, value)) = axes
            .iter()
            .filter(|&&a| spread[a] > 0.0)
            .find_map(|&a| median_split(points, slice, a).map(|(m, v)| (m, (a, v))))
        else {
            return id; // all samples coincide: cannot split
        };
        let (axis, split_value) = value;
        let mut left_hi = hi;
        left_hi[axis] = split_value;
        let mut right_lo = lo;
        right_lo[axis] = split_value;
        let left = self.split(lo, left_hi, start, start + mid, leaf);
        let right = self.split(right_lo, hi, start + mid, end, leaf);
        let node = &mut self.nodes[id as usize];
        node.left = left;
        node.right = right;
        id
    }

    /// The leaf cells (lo, hi corners), in tree order; they tile the root box.
    pub fn leaf_cells(&self) -> Vec<(DVec3, DVec3)> {
        self.nodes
            .iter()
            .filter(|n| n.left == NO_CHILD)
            .map(|n| (n.lo, n.hi))
            .collect()
    }

    /// Points strictly inside the box, in tree order.
    pub fn in_open_box(&self, lo: DVec3, hi: DVec3) -> Vec<u32> {
        let mut out = self.in_box(lo, hi);
        out.retain(|&i| {
            let p = self.points[i as usize];
            p.cmpgt(lo).all() && p.cmplt(hi).all()
        });
        out
    }

    /// Points inside the closed box, in tree order.
    pub fn in_box(&self, lo: DVec3, hi: DVec3) -> Vec<u32> {
        let mut out = Vec::new();
        let mut stack = vec![0u32];
        while let Some(k) = stack.pop() {
            let node = &self.nodes[k as usize];
            if node.hi.cmplt(lo).any() || node.lo.cmpgt(hi).any() {
                continue;
            }
            if node.left == NO_CHILD {
                for &i in &self.order[node.start as usize..node.end as usize] {
                    let p = self.points[i as usize];
                    if p.cmpge(lo).all() && p.cmple(hi).all() {
                        out.push(i);
                    }
                }
            } else {
                stack.push(node.right);
                stack.push(node.left);
            }
        }
        out
    }
}

/// Reorders `slice` so that samples below a split value along `axis` come first; returns the count
/// below and the split value (strictly between the two sides' coordinates), near the median.
fn median_split(points: &[DVec3], slice: &mut [u32], axis: usize) -> Option<(usize, f64)> {
    let key = |i: &u32| points[*i as usize][axis];
    let mid = slice.len() / 2;
    slice.select_nth_unstable_by(mid, |a, b| key(a).total_cmp(&key(b)).then(a.cmp(b)));
    let pivot = key(&slice[mid]);
    let below_max = slice[..mid]
        .iter()
        .map(key)
        .fold(f64::NEG_INFINITY, f64::max);
    if below_max < pivot {
        return Some((mid, 0.5 * (below_max + pivot)));
    }
    // Ties at the median: put everything strictly below the pivot left, or everything up to it.
    let strictly_below = partition_in_place(slice, |i| key(i) < pivot);
    if strictly_below > 0 {
        let left_max = slice[..strictly_below]
            .iter()
            .map(key)
            .fold(f64::NEG_INFINITY, f64::max);
        return Some((strictly_below, 0.5 * (left_max + pivot)));
    }
    let up_to = partition_in_place(slice, |i| key(i) <= pivot);
    if up_to < slice.len() {
        let right_min = slice[up_to..].iter().map(key).fold(f64::INFINITY, f64::min);
        return Some((up_to, 0.5 * (pivot + right_min)));
    }
    None
}

/// Stable partition: elements satisfying `pred` first. Returns their count.
fn partition_in_place(slice: &mut [u32], pred: impl Fn(&u32) -> bool) -> usize {
    let (yes, no): (Vec<u32>, Vec<u32>) = slice.iter().partition(|i| pred(i));
    let count = yes.len();
    for (dst, src) in slice.iter_mut().zip(yes.into_iter().chain(no)) {
        *dst = src;
    }
    count
}

fn bounds(points: &[DVec3]) -> (DVec3, DVec3) {
    points.iter().fold(
        (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
        |(lo, hi), p| (lo.min(*p), hi.max(*p)),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// Clustered points on a few planes (like frames) with repeated coordinates and exact duplicates.
    fn frame_like_points(n: usize, seed: u64) -> Vec<DVec3> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut points: Vec<DVec3> = (0..n)
            .map(|i| {
                let plane = (i % 5) as f64 * 2.0;
                let x = (rng.random_range(0..40) as f64) * 0.25;
                DVec3::new(x, rng.random::<f64>() * 10.0, plane)
            })
            .collect();
        for i in 0..n / 10 {
            points[i * 10 + 1] = points[i * 10];
        }
        points
    }

    fn in_closed(p: DVec3, lo: DVec3, hi: DVec3) -> bool {
        p.cmpge(lo).all() && p.cmple(hi).all()
    }

    #[test]
    fn leaf_cells_tile_the_root_box_and_hold_each_point_once() {
        let points = frame_like_points(3000, 1);
        let (lo, hi) = (DVec3::splat(-1.0), DVec3::splat(12.0));
        let leaf = 16;
        let tree = KdTree::new(&points, lo, hi, leaf);
        let cells = tree.leaf_cells();
        let volume: f64 = cells.iter().map(|&(a, b)| (b - a).element_product()).sum();
        assert!((volume - (hi - lo).element_product()).abs() < 1e-9 * volume);
        let mut owners = vec![0usize; points.len()];
        for &(a, b) in &cells {
            let inside = tree.in_open_box(a, b);
            // Split values lie strictly between the sides, so no point is on a cell face, except
            // where a cell's points all coincide (it is not split) - those are counted by the closed box.
            let closed = tree.in_box(a, b);
            assert!(
                closed.len() <= leaf
                    || closed
                        .iter()
                        .all(|&i| points[i as usize] == points[closed[0] as usize])
            );
            assert_eq!(inside.len(), closed.len());
            for i in inside {
                owners[i as usize] += 1;
            }
        }
        assert!(owners.iter().all(|&k| k == 1));
    }

    #[test]
    fn box_queries_match_brute_force() {
        let points = frame_like_points(2000, 2);
        let tree = KdTree::new(&points, DVec3::splat(-1.0), DVec3::splat(12.0), 8);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        for _ in 0..300 {
            let c = DVec3::new(rng.random(), rng.random(), rng.random()) * 12.0 - DVec3::ONE;
            let h = DVec3::new(rng.random(), rng.random(), rng.random()) * 3.0;
            // Faces on the data's repeated coordinates, so closed and open boxes differ.
            let lo = ((c - h) * 4.0).round() / 4.0;
            let hi = ((c + h) * 4.0).round() / 4.0;
            let mut closed = tree.in_box(lo, hi);
            let mut open = tree.in_open_box(lo, hi);
            closed.sort_unstable();
            open.sort_unstable();
            let brute_closed: Vec<u32> = (0..points.len() as u32)
                .filter(|&i| in_closed(points[i as usize], lo, hi))
                .collect();
            let brute_open: Vec<u32> = (0..points.len() as u32)
                .filter(|&i| {
                    let p = points[i as usize];
                    p.cmpgt(lo).all() && p.cmplt(hi).all()
                })
                .collect();
            assert_eq!(closed, brute_closed);
            assert_eq!(open, brute_open);
        }
        // Coincident points are never split; an empty tree is one empty cell.
        let same = vec![DVec3::ONE; 50];
        let tree = KdTree::new(&same, DVec3::ZERO, DVec3::splat(2.0), 4);
        assert_eq!(tree.leaf_cells().len(), 1);
        assert_eq!(tree.in_box(DVec3::ZERO, DVec3::ONE).len(), 50);
        let tree = KdTree::new(&[], DVec3::ZERO, DVec3::ONE, 4);
        assert_eq!(tree.leaf_cells(), vec![(DVec3::ZERO, DVec3::ONE)]);
        assert!(tree.in_box(DVec3::ZERO, DVec3::ONE).is_empty());
    }
}
