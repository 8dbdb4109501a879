//! Mesh files: PLY (binary little-endian with vertex normals), STL (binary), OBJ; chosen by extension.

use std::path::Path;

use crate::mesh::Mesh;
use crate::{Error, Result};

pub fn read_mesh(path: &Path) -> Result<Mesh> {
    let _ = path;
    Err(Error::InvalidInput(
        "mesh reading is not implemented yet".into(),
    ))
}

pub fn write_mesh(path: &Path, mesh: &Mesh) -> Result<()> {
    let _ = (path, mesh);
    Err(Error::InvalidInput(
        "mesh writing is not implemented yet".into(),
    ))
}
