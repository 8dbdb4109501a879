//! A sparse cell hash: integer cell coordinates packed into one `u64` key, and hash maps and sets keyed
//! by it. The surfacing lattice keys its nodes, cells and edges this way, and [`super::PointBuckets`]
//! sorts its buckets by the same key.

use std::collections::{HashMap, HashSet};
use std::hash::{BuildHasherDefault, Hasher};

/// Bits per axis in a packed cell key (three axes fit in 60 bits, leaving 4 bits for a caller's tag,
/// e.g. the edge direction of a lattice edge).
pub(crate) const CELL_AXIS_BITS: u32 = 20;
/// Largest cell coordinate a key can hold along each axis.
pub(crate) const CELL_AXIS_MAX: i64 = (1 << CELL_AXIS_BITS) - 1;

/// Packs non-negative cell coordinates (each at most [`CELL_AXIS_MAX`]) into one key; sorting keys
/// orders cells by z, then y, then x, so the cells of one x-row have consecutive keys.
#[inline]
pub(crate) fn pack_cell(c: [i32; 3]) -> u64 {
    debug_assert!(c.iter().all(|&x| x >= 0 && (x as i64) <= CELL_AXIS_MAX));
    c[0] as u64 | (c[1] as u64) << CELL_AXIS_BITS | (c[2] as u64) << (2 * CELL_AXIS_BITS)
}

/// The cell coordinates of a key made by [`pack_cell`].
#[inline]
pub(crate) fn unpack_cell(key: u64) -> [i32; 3] {
    let mask = (1u64 << CELL_AXIS_BITS) - 1;
    [
        (key & mask) as i32,
        ((key >> CELL_AXIS_BITS) & mask) as i32,
        ((key >> (2 * CELL_AXIS_BITS)) & mask) as i32,
    ]
}

/// Whether each coordinate fits in a packed key.
#[inline]
pub(crate) fn fits_cell_key(c: [i32; 3]) -> bool {
    c.iter().all(|&x| (0..=CELL_AXIS_MAX).contains(&(x as i64)))
}

/// Multiplicative hash for packed keys (the std SipHash costs more than the lookups it guards; keys are
/// not attacker-controlled).
#[derive(Debug, Default, Clone, Copy)]
pub(crate) struct CellKeyHasher(u64);

impl Hasher for CellKeyHasher {
    fn finish(&self) -> u64 {
        self.0
    }
    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = (self.0.rotate_left(5) ^ b as u64).wrapping_mul(0x51_7c_c1_b7_27_22_0a_95);
        }
    }
    fn write_u64(&mut self, key: u64) {
        // Fibonacci hashing, folded so the high bits reach the low bits hashbrown uses.
        let h = key.wrapping_mul(0x9E37_79B9_7F4A_7C15);
        self.0 = h ^ (h >> 29);
    }
}

/// A map from packed cell keys.
pub(crate) type CellMap<V> = HashMap<u64, V, BuildHasherDefault<CellKeyHasher>>;
/// A set of packed cell keys.
pub(crate) type CellSet = HashSet<u64, BuildHasherDefault<CellKeyHasher>>;

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[test]
    fn keys_roundtrip_and_sort_like_zyx_tuples() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let max = CELL_AXIS_MAX as i32;
        let mut cells: Vec<[i32; 3]> = (0..2000)
            .map(|_| std::array::from_fn(|_| rng.random_range(0..=max)))
            .collect();
        cells.extend([[0, 0, 0], [max, max, max], [max, 0, 0], [0, max, 0]]);
        for &c in &cells {
            assert!(fits_cell_key(c));
            assert_eq!(unpack_cell(pack_cell(c)), c);
        }
        // Key order is (z, y, x) order.
        let mut by_key = cells.clone();
        by_key.sort_by_key(|&c| pack_cell(c));
        let mut by_tuple = cells;
        by_tuple.sort_by_key(|&c| (c[2], c[1], c[0]));
        assert_eq!(by_key, by_tuple);
        assert!(!fits_cell_key([-1, 0, 0]));
        assert!(!fits_cell_key([0, max + 1, 0]));
    }

    #[test]
    fn map_and_set_agree_with_std_collections() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let mut map: CellMap<u32> = CellMap::default();
        let mut reference = std::collections::BTreeMap::new();
        let mut set = CellSet::default();
        for i in 0..5000u32 {
            let c: [i32; 3] = std::array::from_fn(|_| rng.random_range(0..64));
            let key = pack_cell(c);
            *map.entry(key).or_insert(0) += i;
            *reference.entry(key).or_insert(0) += i;
            set.insert(key);
        }
        assert_eq!(map.len(), reference.len());
        assert_eq!(set.len(), reference.len());
        for (k, v) in &reference {
            assert_eq!(map[k], *v);
            assert!(set.contains(k));
        }
    }
}
