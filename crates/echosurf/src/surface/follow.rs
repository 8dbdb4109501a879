//! Which lattice cells the surface crosses: surface-following from seeds, or a full-grid scan.
//!
//! Lattice values are evaluated once and shared by all levels. Surface-following keeps them in a
//! [`CellMap`] (the shared sparse cell hash) keyed by packed lattice coordinates and evaluates each wave
//! of new nodes in one parallel batch. A cell is *crossed* when its corners lie on both sides of the
//! level; under marching tetrahedra the surface leaves a cell only through a face whose corners straddle
//! the level, so growing through such faces from one crossed cell reaches every crossed cell of that
//! connected piece of surface. Cells outside the lattice or outside the region of trust are neither
//! grown into nor surfaced.

use glam::DVec3;

use super::ScalarField;
use super::lattice::{EvalCounter, Ijk, Lattice, add, corner_offset};
use crate::Result;
use crate::spatial::PointBuckets;
use crate::spatial::cell_grid::{CellMap, CellSet, fits_cell_key, pack_cell, unpack_cell};

/// Cached lattice values: a dense array for the full grid, a hash map when following the surface.
#[derive(Debug)]
pub(crate) enum NodeValues {
    Dense { dims: [usize; 3], values: Vec<f64> },
    Sparse(CellMap<f64>),
}

impl NodeValues {
    #[inline]
    pub fn get(&self, n: Ijk) -> f64 {
        match self {
            NodeValues::Dense { dims, values } => {
                values[n[0] as usize + dims[0] * (n[1] as usize + dims[1] * n[2] as usize)]
            }
            NodeValues::Sparse(map) => map[&pack_cell(n)],
        }
    }

    pub fn len(&self) -> usize {
        match self {
            NodeValues::Dense { values, .. } => values.len(),
            NodeValues::Sparse(map) => map.len(),
        }
    }
}

/// The crossed cells of every level (sorted packed keys) and the lattice values they need.
#[derive(Debug)]
pub(crate) struct CrossedCells {
    pub per_level: Vec<Vec<u64>>,
    pub nodes: NodeValues,
    pub seed_cells: usize,
}

/// Largest lattice the full-grid mode evaluates (nodes, 8 bytes each); beyond it the caller must pass
/// seeds.
pub(crate) const MAX_FULL_GRID_NODES: u128 = 1 << 26;

#[inline]
fn cell_corners(cell: Ijk) -> [Ijk; 8] {
    std::array::from_fn(|c| add(cell, corner_offset(c)))
}

/// Corners on both sides of the level, none undefined (NaN).
fn straddles(values: &[f64; 8], level: f64) -> bool {
    if values.iter().any(|v| v.is_nan()) {
        return false;
    }
    let high = values.iter().filter(|&&v| v > level).count();
    high != 0 && high != 8
}

fn trusted(lattice: &Lattice, trust: Option<&PointBuckets>, cell: Ijk) -> bool {
    trust.is_none_or(|t| t.contains(lattice.cell_centre(cell)))
}

/// Scans every cell of the lattice.
pub(crate) fn full_grid(
    field: &dyn ScalarField,
    lattice: &Lattice,
    levels: &[f64],
    trust: Option<&PointBuckets>,
    counter: &mut EvalCounter,
) -> Result<CrossedCells> {
    let node_count = lattice.node_count();
    if node_count > MAX_FULL_GRID_NODES {
        return Err(crate::Error::ResourceLimit(format!(
            "a full-grid surface scan would evaluate {node_count} lattice nodes (at most \
             {MAX_FULL_GRID_NODES}); pass seeds for surface-following or coarsen the resolution"
        )));
    }
    let dims = lattice.cells.map(|c| c as usize + 1);
    // Evaluate in slabs of whole z-layers (about a million points each) so the point list stays small.
    let layer = dims[0] * dims[1];
    let layers_per_slab = (1 << 20) / layer.max(1) + 1;
    let mut values = Vec::with_capacity(node_count as usize);
    for k0 in (0..dims[2]).step_by(layers_per_slab) {
        let mut points = Vec::with_capacity(layer * layers_per_slab.min(dims[2] - k0));
        for k in k0..(k0 + layers_per_slab).min(dims[2]) {
            for j in 0..dims[1] {
                for i in 0..dims[0] {
                    points.push(lattice.node_position([i as i32, j as i32, k as i32]));
                }
            }
        }
        values.extend(super::lattice::evaluate_values(field, &points, counter)?);
    }
    let nodes = NodeValues::Dense { dims, values };
    let mut per_level = Vec::with_capacity(levels.len());
    for &level in levels {
        let mut cells = Vec::new();
        for k in 0..lattice.cells[2] {
            for j in 0..lattice.cells[1] {
                for i in 0..lattice.cells[0] {
                    let cell = [i, j, k];
                    let v = cell_corners(cell).map(|n| nodes.get(n));
                    if straddles(&v, level) && trusted(lattice, trust, cell) {
                        cells.push(pack_cell(cell));
                    }
                }
            }
        }
        per_level.push(cells);
    }
    Ok(CrossedCells {
        per_level,
        nodes,
        seed_cells: 0,
    })
}

struct Follower<'a> {
    field: &'a dyn ScalarField,
    lattice: &'a Lattice,
    trust: Option<&'a PointBuckets>,
    values: CellMap<f64>,
    counter: &'a mut EvalCounter,
}

impl Follower<'_> {
    /// Evaluates every corner of `cells` not yet cached, in one batch (sorted, so deterministic).
    fn ensure_corners(&mut self, cells: &[Ijk]) -> Result<()> {
        let mut missing: Vec<u64> = Vec::new();
        for &cell in cells {
            for n in cell_corners(cell) {
                let key = pack_cell(n);
                if !self.values.contains_key(&key) {
                    missing.push(key);
                }
            }
        }
        missing.sort_unstable();
        missing.dedup();
        if missing.is_empty() {
            return Ok(());
        }
        let points: Vec<DVec3> = missing
            .iter()
            .map(|&k| self.lattice.node_position(unpack_cell(k)))
            .collect();
        let values = super::lattice::evaluate_values(self.field, &points, self.counter)?;
        self.values.reserve(missing.len());
        for (k, v) in missing.into_iter().zip(values) {
            self.values.insert(k, v);
        }
        Ok(())
    }

    fn corner_values(&self, cell: Ijk) -> [f64; 8] {
        cell_corners(cell).map(|n| self.values[&pack_cell(n)])
    }

    /// Grows from `frontier` (crossed, trusted cells already in `visited`) through straddling faces.
    fn grow(&mut self, level: f64, mut frontier: Vec<Ijk>, visited: &mut CellSet) -> Result<()> {
        while !frontier.is_empty() {
            self.ensure_corners(&frontier)?;
            let mut next = Vec::new();
            for &cell in &frontier {
                let v = self.corner_values(cell);
                for axis in 0..3 {
                    for side in 0..2 {
                        // Corners of the face at `axis` = side.
                        let face = (0..8).filter(|c| (c >> axis) & 1 == side);
                        if face.clone().any(|c| v[c].is_nan()) {
                            continue;
                        }
                        let high = face.filter(|&c| v[c] > level).count();
                        if high == 0 || high == 4 {
                            continue;
                        }
                        let mut neighbour = cell;
                        neighbour[axis] += if side == 1 { 1 } else { -1 };
                        if !self.lattice.contains_cell(neighbour)
                            || visited.contains(&pack_cell(neighbour))
                            || !trusted(self.lattice, self.trust, neighbour)
                        {
                            continue;
                        }
                        visited.insert(pack_cell(neighbour));
                        next.push(neighbour);
                    }
                }
            }
            next.sort_unstable_by_key(|&c| pack_cell(c));
            frontier = next;
        }
        Ok(())
    }
}

/// Surface-following from seed points. A seed whose own cell is not crossed looks for crossed cells at
/// growing Chebyshev distance up to `search_radius_cells`, unless the surface was already found there.
/// Seeds are first thinned to one per block of `search_radius_cells + 1` cells along each axis.
pub(crate) fn follow_from_seeds(
    field: &dyn ScalarField,
    lattice: &Lattice,
    levels: &[f64],
    seeds: &[DVec3],
    search_radius_cells: u32,
    trust: Option<&PointBuckets>,
    counter: &mut EvalCounter,
) -> Result<CrossedCells> {
    let mut seed_cells: Vec<u64> = seeds
        .iter()
        .filter_map(|&p| lattice.cell_of(p))
        .map(pack_cell)
        .collect();
    seed_cells.sort_unstable();
    seed_cells.dedup();
    // Thin dense seeds (every sample of a sweep) to one per block of (radius + 1)^3 cells: the search
    // around the kept seed reaches every cell of its block, so the thinning loses no crossed cell of the
    // block, and the cost follows the blocks, not the samples. Keeps the lowest cell of each block.
    let block = search_radius_cells as i32 + 1;
    let block_key = |k: u64| pack_cell(unpack_cell(k).map(|c| c / block));
    seed_cells.sort_unstable_by_key(|&k| (block_key(k), k));
    seed_cells.dedup_by_key(|k| block_key(*k));
    seed_cells.sort_unstable();
    let mut follower = Follower {
        field,
        lattice,
        trust,
        values: CellMap::default(),
        counter,
    };
    let radius = search_radius_cells as i32;
    let mut per_level = Vec::with_capacity(levels.len());
    for &level in levels {
        let mut visited = CellSet::default();
        let mut pending: Vec<Ijk> = seed_cells.iter().map(|&k| unpack_cell(k)).collect();
        for r in 0..=radius {
            // Seeds with the surface already found within distance r need no search.
            pending.retain(|&s| !near_visited(s, r, &visited));
            if r == 1 && !pending.is_empty() {
                // Before searching, drop seeds whose first-order distance to the level |s - k| / |grad s|
                // is more than twice the search reach (twice: the estimate is only first-order).
                let reach = 2.0 * (radius as f64 + 1.0) * 3f64.sqrt() * lattice.spacing_mm;
                let centres: Vec<DVec3> = pending.iter().map(|&c| lattice.cell_centre(c)).collect();
                let (values, gradients) =
                    super::lattice::evaluate_gradients(field, &centres, follower.counter);
                let mut k = 0;
                pending.retain(|_| {
                    let (v, g) = (values[k], gradients[k].length());
                    k += 1;
                    !(v.is_finite() && g.is_finite()) || (v - level).abs() <= reach * g
                });
            }
            let mut candidates: Vec<Ijk> = Vec::new();
            for &s in &pending {
                for_each_ring_cell(s, r, |c| {
                    if lattice.contains_cell(c) {
                        candidates.push(c);
                    }
                });
            }
            candidates.sort_unstable_by_key(|&c| pack_cell(c));
            candidates.dedup();
            follower.ensure_corners(&candidates)?;
            let mut found = Vec::new();
            for &c in &candidates {
                if !visited.contains(&pack_cell(c))
                    && straddles(&follower.corner_values(c), level)
                    && trusted(lattice, trust, c)
                {
                    visited.insert(pack_cell(c));
                    found.push(c);
                }
            }
            follower.grow(level, found, &mut visited)?;
            if pending.is_empty() {
                break;
            }
        }
        let mut cells: Vec<u64> = visited.into_iter().collect();
        cells.sort_unstable();
        per_level.push(cells);
    }
    Ok(CrossedCells {
        per_level,
        nodes: NodeValues::Sparse(follower.values),
        seed_cells: seed_cells.len(),
    })
}

fn for_each_ring_cell(centre: Ijk, r: i32, mut f: impl FnMut(Ijk)) {
    for dz in -r..=r {
        for dy in -r..=r {
            for dx in -r..=r {
                if dx.abs().max(dy.abs()).max(dz.abs()) == r {
                    f(add(centre, [dx, dy, dz]));
                }
            }
        }
    }
}

fn near_visited(centre: Ijk, r: i32, visited: &CellSet) -> bool {
    if visited.is_empty() {
        return false;
    }
    for dz in -r..=r {
        for dy in -r..=r {
            for dx in -r..=r {
                let c = add(centre, [dx, dy, dz]);
                if fits_cell_key(c) && visited.contains(&pack_cell(c)) {
                    return true;
                }
            }
        }
    }
    false
}
