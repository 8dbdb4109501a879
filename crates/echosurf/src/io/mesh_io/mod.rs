//! Mesh files: PLY (binary little-endian with vertex normals), STL (binary), OBJ, legacy VTK polydata;
//! chosen by extension.
//!
//! Readers accept what other tools write: PLY in any encoding (through the one parser in
//! [`crate::io::ply`]), binary and ASCII STL (binary files whose header starts with `solid`, like the fCal
//! CAD model, are recognised by their exact size), OBJ with `v`/`vn`/`f` and polygons, VTK as
//! [`crate::io::vtk`] describes. Polygons are fan-triangulated. STL is a triangle soup, so its corners
//! are welded by exact coordinate equality to give the mesh a topology. Bad indices, non-finite
//! coordinates and truncated data are format errors.
//!
//! Every mesh written states its coordinate system the way 3D Slicer writes and reads it: `SPACE=RAS`
//! or `SPACE=LPS` in the PLY comment, the STL 80-byte header, the OBJ comment and the VTK header line.
//! echosurf works in the tracking frame's own coordinates, which Slicer shows as RAS (see
//! `docs/decisions/0029-mesh-coordinate-space.md`); a file tagged LPS has x and y negated on the way
//! in and out. A file without a tag is taken as the working (RAS) coordinates: that is what every
//! echosurf file before the tag, and the simulator's ground truths, hold.

use std::io::Write;
use std::path::Path;

use crate::mesh::Mesh;
use crate::{Error, FormatProblem, Result};

mod obj;
mod ply_mesh;
mod space;
mod stl;

use obj::{parse_obj, write_obj};
use ply_mesh::{parse_ply_mesh, write_ply_rows};
pub use ply_mesh::{read_vertex_colours, write_ply_with_vertex_values};
pub use space::Space;
use space::{header_text, obj_space, ply_space, stl_space};
use stl::{looks_like_ascii_stl, parse_stl, write_stl};

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum MeshFormat {
    Ply,
    Stl,
    Obj,
    Vtk,
}

/// The file name extensions a mesh is read from and written to (case-insensitive).
pub const MESH_EXTENSIONS: [&str; 4] = ["ply", "stl", "obj", "vtk"];

fn format_of(path: &Path) -> Option<MeshFormat> {
    let ext = path.extension()?.to_string_lossy().to_ascii_lowercase();
    match ext.as_str() {
        "ply" => Some(MeshFormat::Ply),
        "stl" => Some(MeshFormat::Stl),
        "obj" => Some(MeshFormat::Obj),
        "vtk" => Some(MeshFormat::Vtk),
        _ => None,
    }
}

/// Reads a `.ply`, `.stl`, `.obj` or `.vtk` mesh (by extension, case-insensitive), in working (RAS)
/// coordinates: a file tagged `SPACE=LPS` has its x and y negated.
pub fn read_mesh(path: &Path) -> Result<Mesh> {
    read_mesh_and_space(path).map(|(mesh, _)| mesh)
}

/// [`read_mesh`], and the space the file's tag names (`None`: no tag, read as RAS).
pub fn read_mesh_and_space(path: &Path) -> Result<(Mesh, Option<Space>)> {
    let format = format_of(path).ok_or_else(|| {
        Error::format(
            path,
            FormatProblem::Unsupported,
            "unknown mesh file extension (expected .ply, .stl, .obj or .vtk)",
        )
    })?;
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let (mesh, space) = parse_mesh(path, format, &bytes)?;
    Ok((space.unwrap_or_default().convert(&mesh), space))
}

/// The mesh as stored in `bytes` (no coordinate change) and the space its tag names.
fn parse_mesh(path: &Path, format: MeshFormat, bytes: &[u8]) -> Result<(Mesh, Option<Space>)> {
    match format {
        MeshFormat::Ply => Ok((parse_ply_mesh(path, bytes)?, ply_space(bytes))),
        MeshFormat::Stl => Ok((parse_stl(path, bytes)?, stl_space(bytes))),
        MeshFormat::Obj => Ok((parse_obj(path, bytes)?, obj_space(bytes))),
        MeshFormat::Vtk => {
            let vtk = crate::io::vtk::read(path, bytes)?;
            let space = Space::find_tag(vtk.header.as_bytes());
            Ok((vtk.mesh, space))
        }
    }
}

/// Writes a mesh as `.ply` (binary little-endian, float vertices, vertex normals when the mesh has them),
/// `.stl` (binary, facet normals from the geometry), `.obj` (`v`, `vn`, `f`) or `.vtk` (binary legacy
/// polydata), atomically, in working coordinates tagged `SPACE=RAS`.
pub fn write_mesh(path: &Path, mesh: &Mesh) -> Result<()> {
    write_mesh_in(path, mesh, Space::Ras)
}

/// [`write_mesh`] in `space`: the working (RAS) `mesh` converted to it, and tagged with it.
pub fn write_mesh_in(path: &Path, mesh: &Mesh, space: Space) -> Result<()> {
    let format = format_of(path).ok_or_else(|| {
        Error::InvalidInput(format!(
            "{}: unknown mesh file extension (expected .ply, .stl, .obj or .vtk)",
            path.display()
        ))
    })?;
    check_mesh(path, mesh)?;
    let mesh = &space.convert(mesh);
    match format {
        MeshFormat::Ply => write_ply_rows(path, mesh, None, space),
        MeshFormat::Stl => write_stl(path, mesh, space),
        MeshFormat::Obj => write_obj(path, mesh, space),
        MeshFormat::Vtk => crate::io::vtk::write(path, mesh, &header_text(space)),
    }
}

/// Refuses to write a mesh that could not be read back: indices out of range, non-finite values, a
/// normal count that is neither zero nor one per vertex.
pub(super) fn check_mesh(path: &Path, mesh: &Mesh) -> Result<()> {
    let bad = |msg: String| Err(Error::InvalidInput(format!("{}: {msg}", path.display())));
    if !mesh.normals.is_empty() && mesh.normals.len() != mesh.vertices.len() {
        return bad(format!(
            "mesh has {} normals for {} vertices",
            mesh.normals.len(),
            mesh.vertices.len()
        ));
    }
    // PLY indices are written as `int`, STL counts triangles in a u32.
    if i32::try_from(mesh.vertices.len()).is_err() || u32::try_from(mesh.triangles.len()).is_err() {
        return bad("mesh too large for the mesh file formats".into());
    }
    if let Some(i) = mesh.vertices.iter().position(|v| !v.is_finite()) {
        return bad(format!("vertex {i} is not finite"));
    }
    if let Some(i) = mesh.normals.iter().position(|v| !v.is_finite()) {
        return bad(format!("normal {i} is not finite"));
    }
    let n = mesh.vertices.len();
    if let Some(t) = mesh
        .triangles
        .iter()
        .position(|t| t.iter().any(|&i| i as usize >= n))
    {
        return bad(format!(
            "triangle {t} {:?} indexes past the {n} vertices",
            mesh.triangles[t]
        ));
    }
    Ok(())
}

pub(super) fn has_normals(mesh: &Mesh) -> bool {
    !mesh.normals.is_empty() && mesh.normals.len() == mesh.vertices.len()
}

pub(super) fn write_f32s(w: &mut impl Write, values: &[f64]) -> std::io::Result<()> {
    for &v in values {
        w.write_all(&(v as f32).to_le_bytes())?;
    }
    Ok(())
}

#[cfg(test)]
mod tests;
