//! Iso-surface extraction: regularised marching tetrahedra (surface-following) and marching cubes.

use glam::DVec3;

use crate::mesh::Mesh;
use crate::{Error, Result};

/// A scalar field the surfacer can sample: values and gradients at many points at once (batches let a
/// fast RBF evaluator amortise its tree walks).
pub trait ScalarField: Sync {
    fn values(&self, points: &[DVec3], out: &mut [f64]);
    fn values_and_gradients(&self, points: &[DVec3], values: &mut [f64], gradients: &mut [DVec3]);
}

/// An analytic field from a closure returning (value, gradient) at a point; for tests and phantoms.
pub struct FnField<F: Fn(DVec3) -> (f64, DVec3) + Sync>(pub F);

impl<F: Fn(DVec3) -> (f64, DVec3) + Sync> std::fmt::Debug for FnField<F> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("FnField")
    }
}

impl<F: Fn(DVec3) -> (f64, DVec3) + Sync> ScalarField for FnField<F> {
    fn values(&self, points: &[DVec3], out: &mut [f64]) {
        for (p, o) in points.iter().zip(out.iter_mut()) {
            *o = (self.0)(*p).0;
        }
    }

    fn values_and_gradients(&self, points: &[DVec3], values: &mut [f64], gradients: &mut [DVec3]) {
        for ((p, v), g) in points
            .iter()
            .zip(values.iter_mut())
            .zip(gradients.iter_mut())
        {
            let (value, gradient) = (self.0)(*p);
            *v = value;
            *g = gradient;
        }
    }
}

/// Where to look for the surface.
#[derive(Debug, Clone, Default)]
pub struct SurfaceDomain {
    /// Box (mm) the surface is clipped to.
    pub bounds_min_mm: DVec3,
    pub bounds_max_mm: DVec3,
    /// Points near the surface to start surface-following from (e.g. the samples). Empty: full grid.
    pub seeds: Vec<DVec3>,
    /// Data points defining the region of trust: cells farther than `trust_distance_mm` from every one of
    /// them produce no surface. Empty: no clipping.
    pub trust_points: Vec<DVec3>,
}

/// Options of the regularised marching tetrahedra.
#[derive(Debug, Clone)]
pub struct SurfaceOptions {
    /// Lattice spacing in mm.
    pub resolution_mm: f64,
    /// Region of trust radius (mm) around `SurfaceDomain::trust_points`.
    pub trust_distance_mm: f64,
}

impl Default for SurfaceOptions {
    fn default() -> Self {
        SurfaceOptions {
            resolution_mm: 0.5,
            trust_distance_mm: 3.0,
        }
    }
}

/// One mesh per level, in the order of `levels`; normals point toward lower field values.
pub fn extract_surfaces(
    field: &dyn ScalarField,
    levels: &[f64],
    domain: &SurfaceDomain,
    options: &SurfaceOptions,
) -> Result<Vec<Mesh>> {
    let _ = (field, levels, domain, options);
    Err(Error::InvalidInput(
        "surface extraction is not implemented yet".into(),
    ))
}

/// Classic marching cubes on a regular grid: `values[x + dims[0] * (y + dims[1] * z)]`, node (i, j, k) at
/// `origin_mm + (i, j, k) * spacing_mm`; normals point toward lower values.
pub fn marching_cubes(
    values: &[f32],
    dims: [usize; 3],
    origin_mm: DVec3,
    spacing_mm: DVec3,
    level: f64,
) -> Result<Mesh> {
    let _ = (values, dims, origin_mm, spacing_mm, level);
    Err(Error::InvalidInput(
        "marching cubes is not implemented yet".into(),
    ))
}
