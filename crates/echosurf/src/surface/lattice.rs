//! The cubic lattice: integer node/cell coordinates (packed into keys by [`crate::spatial::cell_grid`])
//! and batched field evaluation.

use glam::DVec3;
use rayon::prelude::*;

use super::ScalarField;
use crate::spatial::cell_grid::CELL_AXIS_MAX;
use crate::{Error, Result};

/// A lattice may have at most this many cells per axis (its nodes must fit in a packed cell key).
pub(crate) const MAX_CELLS_PER_AXIS: i64 = CELL_AXIS_MAX - 1;

/// Integer lattice coordinates (node or cell; a cell is named by its lowest corner node).
pub(crate) type Ijk = [i32; 3];

/// Offset of cube corner `c` (bit 0 = x, bit 1 = y, bit 2 = z).
#[inline]
pub(crate) fn corner_offset(c: usize) -> Ijk {
    [(c & 1) as i32, ((c >> 1) & 1) as i32, ((c >> 2) & 1) as i32]
}

#[inline]
pub(crate) fn add(a: Ijk, b: Ijk) -> Ijk {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

/// The cubic lattice covering the domain box (rounded up to whole cells).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Lattice {
    pub origin_mm: DVec3,
    pub spacing_mm: f64,
    /// Cells per axis; nodes run from 0 to `cells` inclusive.
    pub cells: Ijk,
}

impl Lattice {
    pub fn new(bounds_min_mm: DVec3, bounds_max_mm: DVec3, spacing_mm: f64) -> Result<Lattice> {
        if !(spacing_mm.is_finite() && spacing_mm > 0.0) {
            return Err(Error::InvalidInput(format!(
                "surface resolution must be a positive number of mm, got {spacing_mm}"
            )));
        }
        if !(bounds_min_mm.is_finite() && bounds_max_mm.is_finite()) {
            return Err(Error::InvalidInput(format!(
                "surface bounds must be finite, got {bounds_min_mm} .. {bounds_max_mm}"
            )));
        }
        let extent = bounds_max_mm - bounds_min_mm;
        if extent.min_element() <= 0.0 {
            return Err(Error::InvalidInput(format!(
                "surface bounds are empty: min {bounds_min_mm} is not below max {bounds_max_mm}"
            )));
        }
        let mut cells = [0i32; 3];
        for a in 0..3 {
            let n = (extent[a] / spacing_mm).ceil().max(1.0);
            if n > MAX_CELLS_PER_AXIS as f64 {
                return Err(Error::ResourceLimit(format!(
                    "surface lattice would need {n} cells along axis {a} ({:.1} mm at {spacing_mm} mm); \
                     at most {MAX_CELLS_PER_AXIS} fit: coarsen the resolution or shrink the bounds",
                    extent[a]
                )));
            }
            cells[a] = n as i32;
        }
        Ok(Lattice {
            origin_mm: bounds_min_mm,
            spacing_mm,
            cells,
        })
    }

    #[inline]
    pub fn node_position(&self, n: Ijk) -> DVec3 {
        self.origin_mm + DVec3::new(n[0] as f64, n[1] as f64, n[2] as f64) * self.spacing_mm
    }

    #[inline]
    pub fn cell_centre(&self, c: Ijk) -> DVec3 {
        self.origin_mm + (DVec3::new(c[0] as f64, c[1] as f64, c[2] as f64) + 0.5) * self.spacing_mm
    }

    #[inline]
    pub fn contains_cell(&self, c: Ijk) -> bool {
        (0..3).all(|a| c[a] >= 0 && c[a] < self.cells[a])
    }

    /// The cell containing a point, or `None` outside the lattice.
    pub fn cell_of(&self, p: DVec3) -> Option<Ijk> {
        let q = (p - self.origin_mm) / self.spacing_mm;
        if !q.is_finite() {
            return None;
        }
        let c = [q.x.floor(), q.y.floor(), q.z.floor()];
        let c = [c[0] as i64, c[1] as i64, c[2] as i64];
        let inside = (0..3).all(|a| c[a] >= 0 && c[a] < self.cells[a] as i64);
        inside.then(|| [c[0] as i32, c[1] as i32, c[2] as i32])
    }

    pub fn node_count(&self) -> u128 {
        self.cells.iter().map(|&c| c as u128 + 1).product()
    }
}

/// Counts what the surfacer asked of the field.
#[derive(Debug, Default, Clone, Copy)]
pub(crate) struct EvalCounter {
    pub values: usize,
    pub gradients: usize,
}

/// Points per task of a parallel batch: large enough to amortise a batched evaluator's setup.
const EVAL_CHUNK: usize = 2048;

/// Field values at many points, in parallel chunks (each point's value does not depend on the chunking,
/// so the result is independent of the thread count). Non-finite values are an error.
pub(crate) fn evaluate_values(
    field: &dyn ScalarField,
    points: &[DVec3],
    counter: &mut EvalCounter,
) -> Result<Vec<f64>> {
    let mut out = vec![0.0; points.len()];
    out.par_chunks_mut(EVAL_CHUNK)
        .zip(points.par_chunks(EVAL_CHUNK))
        .for_each(|(o, p)| field.values(p, o));
    counter.values += points.len();
    let undefined_allowed = field.nan_means_undefined();
    if let Some(i) = out
        .iter()
        .position(|v| !(v.is_finite() || undefined_allowed && v.is_nan()))
    {
        return Err(Error::Numerical(format!(
            "the scalar field is not finite ({}) at {} mm",
            out[i], points[i]
        )));
    }
    Ok(out)
}

/// Values and gradients at many points, in parallel chunks.
pub(crate) fn evaluate_gradients(
    field: &dyn ScalarField,
    points: &[DVec3],
    counter: &mut EvalCounter,
) -> (Vec<f64>, Vec<DVec3>) {
    let mut values = vec![0.0; points.len()];
    let mut gradients = vec![DVec3::ZERO; points.len()];
    values
        .par_chunks_mut(EVAL_CHUNK)
        .zip(gradients.par_chunks_mut(EVAL_CHUNK))
        .zip(points.par_chunks(EVAL_CHUNK))
        .for_each(|((v, g), p)| field.values_and_gradients(p, v, g));
    counter.gradients += points.len();
    (values, gradients)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lattice_rejects_bad_parameters() {
        assert!(Lattice::new(DVec3::ZERO, DVec3::ONE, 0.0).is_err());
        assert!(Lattice::new(DVec3::ZERO, DVec3::ONE, f64::NAN).is_err());
        assert!(Lattice::new(DVec3::ONE, DVec3::ZERO, 0.5).is_err());
        assert!(Lattice::new(DVec3::ZERO, DVec3::splat(1e9), 1e-3).is_err());
        let l = Lattice::new(DVec3::ZERO, DVec3::new(1.0, 1.2, 0.1), 0.5).unwrap();
        assert_eq!(l.cells, [2, 3, 1]);
        assert_eq!(l.cell_of(DVec3::new(0.9, 1.4, 0.0)), Some([1, 2, 0]));
        assert_eq!(l.cell_of(DVec3::new(-0.1, 0.0, 0.0)), None);
    }
}
