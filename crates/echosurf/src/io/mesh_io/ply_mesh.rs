//! Meshes as PLY: the reader (through the one parser in [`crate::io::ply`]), the writer with optional
//! per-vertex values, and per-vertex colours.

use super::Space;
use super::check_mesh;
use super::has_normals;
use super::write_f32s;
use super::{MeshFormat, format_of};
use crate::Error;
use crate::FormatProblem;
use crate::Result;
use crate::io::ply::PlyFile;
use crate::io::polygons::push_polygon;
use crate::io::polygons::unit_normals;
use crate::mesh::Mesh;
use glam::DVec3;
use std::io::Write;
use std::path::Path;

/// The colours a PLY mesh gives its vertices (`red green blue` vertex properties, 0-255), in the vertex
/// order [`read_mesh`] keeps; `None` for a PLY without them and for STL and OBJ.
pub fn read_vertex_colours(path: &Path) -> Result<Option<Vec<[u8; 3]>>> {
    if format_of(path) != Some(MeshFormat::Ply) {
        return Ok(None);
    }
    let cloud = crate::io::ply::read_point_cloud(path)?;
    let (Some(r), Some(g), Some(b)) = (
        cloud.scalar("red"),
        cloud.scalar("green"),
        cloud.scalar("blue"),
    ) else {
        return Ok(None);
    };
    let byte = |v: f32| v.round().clamp(0.0, 255.0) as u8;
    Ok(Some(
        r.iter()
            .zip(g)
            .zip(b)
            .map(|((&r, &g), &b)| [byte(r), byte(g), byte(b)])
            .collect(),
    ))
}

/// Per-vertex extras of a PLY mesh: one `float` value and an sRGB colour (`uchar red green blue`,
/// which MeshLab, ParaView and 3D Slicer show).
pub(super) struct VertexValues<'a> {
    name: &'a str,
    values: &'a [f32],
    colours: &'a [[u8; 3]],
}

/// Writes a binary PLY mesh whose vertices also carry `float NAME` and a colour, e.g. an error map
/// (each vertex's distance to a ground truth, coloured on a scale), in `space`.
pub fn write_ply_with_vertex_values(
    path: &Path,
    mesh: &Mesh,
    name: &str,
    values: &[f32],
    colours: &[[u8; 3]],
    space: Space,
) -> Result<()> {
    let n = mesh.vertices.len();
    if values.len() != n || colours.len() != n {
        return Err(Error::InvalidInput(format!(
            "{}: {} values and {} colours for {n} vertices",
            path.display(),
            values.len(),
            colours.len()
        )));
    }
    let reserved = ["x", "y", "z", "nx", "ny", "nz", "red", "green", "blue"];
    if !crate::io::ply::is_valid_property_name(name) || reserved.contains(&name) {
        return Err(Error::InvalidInput(format!(
            "{}: {name:?} cannot name a vertex value",
            path.display()
        )));
    }
    check_mesh(path, mesh)?;
    write_ply_rows(
        path,
        &space.convert(mesh),
        Some(VertexValues {
            name,
            values,
            colours,
        }),
        space,
    )
}

pub(super) fn write_ply_rows(
    path: &Path,
    mesh: &Mesh,
    extra: Option<VertexValues>,
    space: Space,
) -> Result<()> {
    let normals = has_normals(mesh);
    // Slicer writes the tag as a comment of its own.
    let mut header = format!(
        "ply\nformat binary_little_endian 1.0\ncomment echosurf mesh, mm\ncomment {}\n",
        space.tag()
    );
    header.push_str(&format!(
        "element vertex {}\nproperty float x\nproperty float y\nproperty float z\n",
        mesh.vertices.len()
    ));
    if normals {
        header.push_str("property float nx\nproperty float ny\nproperty float nz\n");
    }
    if let Some(extra) = &extra {
        header.push_str(&format!(
            "property float {}\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n",
            extra.name
        ));
    }
    header.push_str(&format!(
        "element face {}\nproperty list uchar int vertex_indices\nend_header\n",
        mesh.triangles.len()
    ));
    crate::io::atomic::write_atomic(path, |w| {
        w.write_all(header.as_bytes())?;
        for (i, v) in mesh.vertices.iter().enumerate() {
            write_f32s(w, &[v.x, v.y, v.z])?;
            if normals {
                let n = mesh.normals[i];
                write_f32s(w, &[n.x, n.y, n.z])?;
            }
            if let Some(extra) = &extra {
                w.write_all(&extra.values[i].to_le_bytes())?;
                w.write_all(&extra.colours[i])?;
            }
        }
        for t in &mesh.triangles {
            let mut row = [0u8; 13];
            row[0] = 3;
            for (k, &i) in t.iter().enumerate() {
                row[1 + 4 * k..5 + 4 * k].copy_from_slice(&(i as i32).to_le_bytes());
            }
            w.write_all(&row)?;
        }
        Ok(())
    })
}

pub(super) fn parse_ply_mesh(path: &Path, bytes: &[u8]) -> Result<Mesh> {
    let ply = PlyFile::parse(path, bytes)?;
    let vertex = ply.element("vertex").ok_or_else(|| {
        Error::format(
            path,
            FormatProblem::MissingField,
            "PLY file has no `vertex` element",
        )
    })?;
    let vertices = vertex.positions(path)?;
    if u32::try_from(vertices.len()).is_err() {
        return Err(Error::format(
            path,
            FormatProblem::Unsupported,
            "more than 2^32 vertices",
        ));
    }
    let normals = match (
        vertex.scalar("nx"),
        vertex.scalar("ny"),
        vertex.scalar("nz"),
    ) {
        (Some(x), Some(y), Some(z)) => {
            unit_normals((0..vertices.len()).map(|i| DVec3::new(x[i], y[i], z[i])))
        }
        _ => Vec::new(),
    };
    let face = ply.element("face").ok_or_else(|| {
        Error::format(
            path,
            FormatProblem::MissingField,
            "PLY file has no `face` element (a point cloud, not a mesh?)",
        )
    })?;
    let (offsets, values) = face
        .list("vertex_indices")
        .or_else(|| face.list("vertex_index"))
        .ok_or_else(|| {
            Error::format(
                path,
                FormatProblem::MissingField,
                "PLY `face` element has no `vertex_indices` list",
            )
        })?;
    let mut triangles = Vec::with_capacity(face.count);
    let mut polygon = Vec::new();
    for f in 0..face.count {
        polygon.clear();
        for &v in &values[offsets[f]..offsets[f + 1]] {
            if !(0.0..=u32::MAX as f64).contains(&v) || v.fract() != 0.0 {
                return Err(Error::format(
                    path,
                    FormatProblem::BadValue,
                    format!("PLY face {f} has vertex index {v}"),
                ));
            }
            polygon.push(v as u32);
        }
        push_polygon(
            path,
            &format!("PLY face {f}"),
            &polygon,
            vertices.len(),
            &mut triangles,
        )?;
    }
    Ok(Mesh {
        vertices,
        normals,
        triangles,
    })
}
