//! A bounding-volume hierarchy over axis-aligned boxes: median splits along the longest axis of the
//! items' centres (ties broken by item index, so the tree does not depend on the selection algorithm),
//! at most [`LEAF_ITEMS`] items per leaf. Queries: every leaf item whose box may contain a point, and
//! the item nearest a point under the caller's exact distance.

use glam::DVec3;

/// Items per leaf.
pub(crate) const LEAF_ITEMS: usize = 4;
/// Depth bound; a query's fixed stack holds at most two entries per level.
const MAX_DEPTH: usize = 30;
const STACK_SIZE: usize = 64;

#[derive(Debug, Clone, Copy)]
struct Node {
    lo: DVec3,
    hi: DVec3,
    /// Leaf: first slot in `order`. Internal: index of the left child; the right child follows it.
    start: u32,
    /// Items in a leaf; 0 for an internal node.
    count: u32,
}

impl Node {
    const EMPTY: Node = Node {
        lo: DVec3::ZERO,
        hi: DVec3::ZERO,
        start: 0,
        count: 0,
    };

    fn distance_squared(&self, p: DVec3) -> f64 {
        let d = (self.lo - p).max(p - self.hi).max(DVec3::ZERO);
        d.length_squared()
    }
}

/// A BVH over items given by a centre (what splits sort by) and a box (what queries prune by).
#[derive(Debug, Clone, Default)]
pub(crate) struct BoxTree {
    nodes: Vec<Node>,
    /// Item index at each slot; a leaf owns a contiguous run of slots.
    order: Vec<u32>,
}

impl BoxTree {
    /// Builds the tree over items `0..centres.len()`; `bounds[i]` is item i's box (lo, hi).
    pub fn new(centres: &[DVec3], bounds: &[(DVec3, DVec3)]) -> BoxTree {
        debug_assert_eq!(centres.len(), bounds.len());
        let n = centres.len().min(bounds.len());
        let mut tree = BoxTree {
            nodes: Vec::new(),
            order: (0..n as u32).collect(),
        };
        if n == 0 {
            return tree;
        }
        tree.nodes.reserve(2 * n / LEAF_ITEMS + 1);
        tree.nodes.push(Node::EMPTY);
        tree.split(centres, bounds, 0, n, 0, 0);
        tree
    }

    fn split(
        &mut self,
        centres: &[DVec3],
        bounds: &[(DVec3, DVec3)],
        start: usize,
        end: usize,
        node: usize,
        depth: usize,
    ) {
        let slice = &mut self.order[start..end];
        let (mut lo, mut hi) = (DVec3::INFINITY, DVec3::NEG_INFINITY);
        let (mut clo, mut chi) = (DVec3::INFINITY, DVec3::NEG_INFINITY);
        for &item in slice.iter() {
            let (blo, bhi) = bounds[item as usize];
            lo = lo.min(blo);
            hi = hi.max(bhi);
            let c = centres[item as usize];
            clo = clo.min(c);
            chi = chi.max(c);
        }
        if slice.len() <= LEAF_ITEMS || depth >= MAX_DEPTH {
            self.nodes[node] = Node {
                lo,
                hi,
                start: start as u32,
                count: slice.len() as u32,
            };
            return;
        }
        let extent = chi - clo;
        let axis = if extent.x >= extent.y && extent.x >= extent.z {
            0
        } else if extent.y >= extent.z {
            1
        } else {
            2
        };
        let mid = slice.len() / 2;
        slice.select_nth_unstable_by(mid, |a, b| {
            centres[*a as usize][axis]
                .total_cmp(&centres[*b as usize][axis])
                .then(a.cmp(b))
        });
        let left = self.nodes.len();
        self.nodes.push(Node::EMPTY);
        self.nodes.push(Node::EMPTY);
        self.nodes[node] = Node {
            lo,
            hi,
            start: left as u32,
            count: 0,
        };
        self.split(centres, bounds, start, start + mid, left, depth + 1);
        self.split(centres, bounds, start + mid, end, left + 1, depth + 1);
    }

    /// The item index at each slot (slots of one leaf are contiguous).
    pub fn order(&self) -> &[u32] {
        &self.order
    }

    /// Approximate heap size in bytes.
    pub fn memory_bytes(&self) -> usize {
        self.nodes.len() * std::mem::size_of::<Node>() + self.order.len() * 4
    }

    /// Calls `f(item)` for every item of every leaf whose box contains `p` (closed), leaves depth first,
    /// left before right, items in slot order. The caller tests each item's own box.
    pub fn visit_leaves_containing(&self, p: DVec3, mut f: impl FnMut(u32)) {
        if self.nodes.is_empty() {
            return;
        }
        let mut stack = [0u32; STACK_SIZE];
        let mut top = 1usize;
        while top > 0 {
            top -= 1;
            let node = &self.nodes[stack[top] as usize];
            if p.cmplt(node.lo).any() || p.cmpgt(node.hi).any() {
                continue;
            }
            if node.count > 0 {
                let start = node.start as usize;
                for &item in &self.order[start..start + node.count as usize] {
                    f(item);
                }
            } else if top + 2 <= STACK_SIZE {
                stack[top] = node.start + 1;
                stack[top + 1] = node.start;
                top += 2;
            }
        }
    }

    /// The slot minimising `eval(slot).0` (a squared distance, at least that to the slot's box), with
    /// that slot's value `eval(slot).1`. Ties between opened leaves go to the lower slot (a box no
    /// nearer than the best so far is not opened). `known`, a (slot, squared distance,
    /// value) already evaluated (e.g. the answer for a nearby point), bounds the search from the start.
    /// `None` for an empty tree or when no slot beats `known`'s distance and `known` is `None`.
    #[inline]
    pub fn nearest<T: Copy>(
        &self,
        p: DVec3,
        known: Option<(usize, f64, T)>,
        mut eval: impl FnMut(usize) -> (f64, T),
    ) -> Option<(usize, f64, T)> {
        let root = self.nodes.first()?;
        let mut best = known;
        let (mut best_slot, mut best_d2) = best.map_or((usize::MAX, f64::INFINITY), |b| (b.0, b.1));
        // Near-first descent keeps at most one pending sibling per level.
        let mut stack = [(0u32, 0.0f64); STACK_SIZE];
        stack[0] = (0, root.distance_squared(p));
        let mut top = 1usize;
        while top > 0 {
            top -= 1;
            let (index, box_d2) = stack[top];
            if box_d2 >= best_d2 {
                continue;
            }
            let node = &self.nodes[index as usize];
            if node.count > 0 {
                let start = node.start as usize;
                for slot in start..start + node.count as usize {
                    let (d2, value) = eval(slot);
                    // Ties go to the lower slot, so the answer does not depend on the order within a leaf.
                    if d2 < best_d2 || (d2 == best_d2 && slot < best_slot) {
                        best_d2 = d2;
                        best_slot = slot;
                        best = Some((slot, d2, value));
                    }
                }
            } else {
                let left = node.start;
                let dl = self.nodes[left as usize].distance_squared(p);
                let dr = self.nodes[left as usize + 1].distance_squared(p);
                // Nearer child popped first.
                let (near, far) = if dl <= dr {
                    ((left, dl), (left + 1, dr))
                } else {
                    ((left + 1, dr), (left, dl))
                };
                if far.1 < best_d2 && top < STACK_SIZE {
                    stack[top] = far;
                    top += 1;
                }
                if near.1 < best_d2 && top < STACK_SIZE {
                    stack[top] = near;
                    top += 1;
                }
            }
        }
        best
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn random_boxes(n: usize, seed: u64) -> (Vec<DVec3>, Vec<(DVec3, DVec3)>) {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut centres = Vec::new();
        let mut bounds = Vec::new();
        for i in 0..n {
            // Some items share a centre coordinate, so the index tie-break is exercised.
            let c = if i % 7 == 3 {
                centres[i - 1]
            } else {
                DVec3::new(rng.random(), rng.random(), rng.random()) * 50.0
            };
            let h = DVec3::new(rng.random(), rng.random(), rng.random()) * 3.0 + DVec3::splat(0.1);
            centres.push(c);
            bounds.push((c - h, c + h));
        }
        (centres, bounds)
    }

    #[test]
    fn every_item_is_in_exactly_one_slot() {
        for n in [0, 1, 4, 5, 100, 1000] {
            let (centres, bounds) = random_boxes(n, n as u64);
            let tree = BoxTree::new(&centres, &bounds);
            let mut items = tree.order().to_vec();
            items.sort_unstable();
            assert_eq!(items, (0..n as u32).collect::<Vec<_>>());
        }
    }

    #[test]
    fn containing_query_finds_every_box_holding_the_point() {
        let (centres, bounds) = random_boxes(500, 11);
        let tree = BoxTree::new(&centres, &bounds);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(12);
        for _ in 0..1000 {
            let p = DVec3::new(rng.random(), rng.random(), rng.random()) * 60.0 - DVec3::splat(5.0);
            let mut found = Vec::new();
            tree.visit_leaves_containing(p, |i| {
                let (lo, hi) = bounds[i as usize];
                if p.cmpge(lo).all() && p.cmple(hi).all() {
                    found.push(i);
                }
            });
            found.sort_unstable();
            let brute: Vec<u32> = (0..bounds.len() as u32)
                .filter(|&i| {
                    let (lo, hi) = bounds[i as usize];
                    p.cmpge(lo).all() && p.cmple(hi).all()
                })
                .collect();
            assert_eq!(found, brute, "{p}");
        }
        BoxTree::default().visit_leaves_containing(DVec3::ZERO, |_| panic!("empty tree"));
    }

    #[test]
    fn nearest_matches_brute_force_with_and_without_a_known_bound() {
        let (centres, bounds) = random_boxes(700, 21);
        let tree = BoxTree::new(&centres, &bounds);
        let order = tree.order().to_vec();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(22);
        for q in 0..1000 {
            let p =
                DVec3::new(rng.random(), rng.random(), rng.random()) * 80.0 - DVec3::splat(15.0);
            // Distance to an item: to its centre, which lies strictly inside its box, so a box is never
            // pruned at a tie with its item and the lowest tied slot wins (centres repeat).
            let d2_of = |slot: usize| centres[order[slot] as usize].distance_squared(p);
            let brute_slot = (0..order.len())
                .min_by(|&a, &b| d2_of(a).total_cmp(&d2_of(b)).then(a.cmp(&b)))
                .unwrap();
            let (slot, d2, item) = tree.nearest(p, None, |s| (d2_of(s), order[s])).unwrap();
            assert_eq!(
                (slot, d2, item),
                (brute_slot, d2_of(brute_slot), order[brute_slot])
            );
            // Any known slot as a starting bound gives the same distance (on a tie the known slot may
            // be kept: boxes no nearer than it are not opened).
            let known = q % order.len();
            let hinted = tree
                .nearest(p, Some((known, d2_of(known), order[known])), |s| {
                    (d2_of(s), order[s])
                })
                .unwrap();
            assert_eq!(hinted.1, d2);
            assert_eq!(d2_of(hinted.0), d2);
            assert_eq!(hinted.2, order[hinted.0]);
            if d2_of(known) > d2 {
                assert_eq!(hinted, (slot, d2, item));
            }
        }
        assert!(
            BoxTree::default()
                .nearest(DVec3::ZERO, None, |_| (0.0, ()))
                .is_none()
        );
    }
}
