//! Face and normal checks shared by the mesh readers (PLY, OBJ in `mesh_io`, VTK in `vtk`): one place,
//! so the readers agree on what a bad face or a degenerate normal is.

use std::path::Path;

use glam::DVec3;

use crate::{Error, FormatProblem, Result};

/// Appends the fan triangulation of a polygon, after checking every index.
pub(crate) fn push_polygon(
    path: &Path,
    what: &str,
    polygon: &[u32],
    vertex_count: usize,
    triangles: &mut Vec<[u32; 3]>,
) -> Result<()> {
    if polygon.len() < 3 {
        return Err(Error::format(
            path,
            FormatProblem::BadValue,
            format!(
                "{what} has {} vertices (a face needs at least 3)",
                polygon.len()
            ),
        ));
    }
    if let Some(&i) = polygon.iter().find(|&&i| i as usize >= vertex_count) {
        return Err(Error::format(
            path,
            FormatProblem::BadValue,
            format!("{what} refers to vertex {i} but there are only {vertex_count} vertices"),
        ));
    }
    for k in 1..polygon.len() - 1 {
        triangles.push([polygon[0], polygon[k], polygon[k + 1]]);
    }
    Ok(())
}

/// Normalised normals, or none at all if any is zero or not finite (a mesh has all or none).
pub(crate) fn unit_normals(normals: impl Iterator<Item = DVec3>) -> Vec<DVec3> {
    let mut out = Vec::new();
    for n in normals {
        match n.try_normalize() {
            Some(u) => out.push(u),
            None => return Vec::new(),
        }
    }
    out
}
