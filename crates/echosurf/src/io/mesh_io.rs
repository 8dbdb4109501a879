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

use std::collections::HashMap;
use std::io::Write;
use std::path::Path;

use glam::DVec3;

use crate::io::ply::PlyFile;
use crate::io::polygons::{push_polygon, unit_normals};
use crate::mesh::Mesh;
use crate::{Error, FormatProblem, Result};

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

/// The anatomical coordinate system a mesh file's numbers are in, as 3D Slicer names it: RAS (+x
/// right, +y anterior, +z superior) or LPS (+x left, +y posterior: x and y negated). echosurf's working
/// coordinates are RAS: the tracking frame's numbers as Slicer shows them.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "UPPERCASE")]
pub enum Space {
    /// The working coordinates unchanged.
    #[default]
    Ras,
    /// x and y negated (a half turn about z: the winding of triangles stays valid).
    Lps,
}

impl Space {
    /// `RAS` or `LPS`, the spelling of the tag.
    pub fn name(self) -> &'static str {
        match self {
            Space::Ras => "RAS",
            Space::Lps => "LPS",
        }
    }

    /// The tag Slicer writes and looks for: `SPACE=RAS` or `SPACE=LPS`.
    pub fn tag(self) -> &'static str {
        match self {
            Space::Ras => "SPACE=RAS",
            Space::Lps => "SPACE=LPS",
        }
    }

    /// `ras` or `lps` (any case).
    pub fn parse(text: &str) -> Option<Space> {
        match text.trim().to_ascii_lowercase().as_str() {
            "ras" => Some(Space::Ras),
            "lps" => Some(Space::Lps),
            _ => None,
        }
    }

    /// The space a tag in `text` names, as Slicer finds it: the first of `SPACE=RAS`, `SPACE=LPS`
    /// anywhere in the text (RAS looked for first, as Slicer does).
    pub fn find_tag(text: &[u8]) -> Option<Space> {
        let has = |tag: &str| text.windows(tag.len()).any(|w| w == tag.as_bytes());
        if has(Space::Ras.tag()) {
            Some(Space::Ras)
        } else if has(Space::Lps.tag()) {
            Some(Space::Lps)
        } else {
            None
        }
    }

    /// `mesh` (in working RAS coordinates) in this space, or back: the change is its own inverse.
    pub fn convert(self, mesh: &Mesh) -> Mesh {
        match self {
            Space::Ras => mesh.clone(),
            Space::Lps => {
                let flip = |v: &DVec3| DVec3::new(-v.x, -v.y, v.z);
                Mesh {
                    vertices: mesh.vertices.iter().map(flip).collect(),
                    normals: mesh.normals.iter().map(flip).collect(),
                    triangles: mesh.triangles.clone(),
                }
            }
        }
    }
}

/// The first line of what echosurf writes into a mesh's comment or header: what it is and its space.
fn header_text(space: Space) -> String {
    format!("echosurf mesh, mm. {}", space.tag())
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

/// The tag in a PLY header's first comment that has one.
fn ply_space(bytes: &[u8]) -> Option<Space> {
    bytes
        .split(|&b| b == b'\n')
        .take_while(|line| line.trim_ascii() != b"end_header")
        .filter(|line| line.starts_with(b"comment") || line.starts_with(b"obj_info"))
        .find_map(Space::find_tag)
}

/// The tag in a binary STL's 80-byte header, or in an ASCII STL's `solid` line.
fn stl_space(bytes: &[u8]) -> Option<Space> {
    let header = if looks_like_ascii_stl(bytes) {
        bytes.split(|&b| b == b'\n').next().unwrap_or_default()
    } else {
        &bytes[..bytes.len().min(80)]
    };
    Space::find_tag(header)
}

/// The tag in the comment lines an OBJ file opens with.
fn obj_space(bytes: &[u8]) -> Option<Space> {
    bytes
        .split(|&b| b == b'\n')
        .map(<[u8]>::trim_ascii)
        .filter(|line| !line.is_empty())
        .take_while(|line| line.starts_with(b"#"))
        .find_map(Space::find_tag)
}

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
fn check_mesh(path: &Path, mesh: &Mesh) -> Result<()> {
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

fn has_normals(mesh: &Mesh) -> bool {
    !mesh.normals.is_empty() && mesh.normals.len() == mesh.vertices.len()
}

/// Per-vertex extras of a PLY mesh: one `float` value and an sRGB colour (`uchar red green blue`,
/// which MeshLab, ParaView and 3D Slicer show).
struct VertexValues<'a> {
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

fn write_ply_rows(
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

fn write_f32s(w: &mut impl Write, values: &[f64]) -> std::io::Result<()> {
    for &v in values {
        w.write_all(&(v as f32).to_le_bytes())?;
    }
    Ok(())
}

fn write_stl(path: &Path, mesh: &Mesh, space: Space) -> Result<()> {
    crate::io::atomic::write_atomic(path, |w| {
        // The header must not start with "solid", or readers may take the file for ASCII STL.
        let mut header = [b' '; 80];
        let text = header_text(space);
        header[..text.len()].copy_from_slice(text.as_bytes());
        w.write_all(&header)?;
        w.write_all(&(mesh.triangles.len() as u32).to_le_bytes())?;
        for &t in &mesh.triangles {
            let n = mesh.triangle_unit_normal(t);
            write_f32s(w, &[n.x, n.y, n.z])?;
            for i in t {
                let v = mesh.vertices[i as usize];
                write_f32s(w, &[v.x, v.y, v.z])?;
            }
            w.write_all(&[0, 0])?;
        }
        Ok(())
    })
}

fn write_obj(path: &Path, mesh: &Mesh, space: Space) -> Result<()> {
    let normals = has_normals(mesh);
    crate::io::atomic::write_atomic(path, |w| {
        writeln!(w, "# {}", header_text(space))?;
        // `{}` prints the shortest decimal that reads back to the same f64, so OBJ round-trips exactly.
        for v in &mesh.vertices {
            writeln!(w, "v {} {} {}", v.x, v.y, v.z)?;
        }
        if normals {
            for n in &mesh.normals {
                writeln!(w, "vn {} {} {}", n.x, n.y, n.z)?;
            }
        }
        for t in &mesh.triangles {
            let [a, b, c] = t.map(|i| i as u64 + 1);
            if normals {
                writeln!(w, "f {a}//{a} {b}//{b} {c}//{c}")?;
            } else {
                writeln!(w, "f {a} {b} {c}")?;
            }
        }
        Ok(())
    })
}

fn parse_ply_mesh(path: &Path, bytes: &[u8]) -> Result<Mesh> {
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

/// Welds triangle-soup corners that are bit-identical (after folding -0 into +0).
#[derive(Default)]
struct Welder {
    index: HashMap<[u64; 3], u32>,
    vertices: Vec<DVec3>,
}

impl Welder {
    fn add(&mut self, p: DVec3) -> u32 {
        let key = [p.x + 0.0, p.y + 0.0, p.z + 0.0].map(f64::to_bits);
        *self.index.entry(key).or_insert_with(|| {
            self.vertices.push(p + DVec3::ZERO);
            (self.vertices.len() - 1) as u32
        })
    }
}

const STL_HEADER: usize = 84;
const STL_FACET: usize = 50;

fn parse_stl(path: &Path, bytes: &[u8]) -> Result<Mesh> {
    if bytes.len() >= STL_HEADER {
        let count = u32::from_le_bytes(bytes[80..84].try_into().expect("4 bytes")) as usize;
        let expected = STL_HEADER as u64 + STL_FACET as u64 * count as u64;
        if expected == bytes.len() as u64 {
            return parse_binary_stl(path, bytes, count);
        }
        if !looks_like_ascii_stl(bytes) {
            let problem = if (bytes.len() as u64) < expected {
                FormatProblem::Truncated
            } else {
                FormatProblem::SizeMismatch
            };
            return Err(Error::format(
                path,
                problem,
                format!(
                    "binary STL header promises {count} triangles ({expected} bytes) but the file has {} bytes",
                    bytes.len()
                ),
            ));
        }
    } else if !looks_like_ascii_stl(bytes) {
        return Err(Error::format(
            path,
            FormatProblem::Truncated,
            format!("{} bytes is too short for an STL file", bytes.len()),
        ));
    }
    parse_ascii_stl(path, bytes)
}

fn looks_like_ascii_stl(bytes: &[u8]) -> bool {
    bytes.trim_ascii_start().starts_with(b"solid") && bytes.iter().take(4096).all(|&b| b.is_ascii())
}

fn parse_binary_stl(path: &Path, bytes: &[u8], count: usize) -> Result<Mesh> {
    let mut welder = Welder::default();
    let mut triangles = Vec::with_capacity(count);
    for (f, facet) in bytes[STL_HEADER..].chunks_exact(STL_FACET).enumerate() {
        let mut corner = [0u32; 3];
        for (k, c) in corner.iter_mut().enumerate() {
            let at = 12 + 12 * k;
            let xyz: [f64; 3] = std::array::from_fn(|a| {
                f32::from_le_bytes(
                    facet[at + 4 * a..at + 4 * a + 4]
                        .try_into()
                        .expect("4 bytes"),
                ) as f64
            });
            let p = DVec3::from(xyz);
            if !p.is_finite() {
                return Err(Error::format(
                    path,
                    FormatProblem::BadValue,
                    format!("STL triangle {f} has a non-finite corner ({p})"),
                ));
            }
            *c = welder.add(p);
        }
        triangles.push(corner);
    }
    Ok(Mesh {
        vertices: welder.vertices,
        normals: Vec::new(),
        triangles,
    })
}

fn parse_ascii_stl(path: &Path, bytes: &[u8]) -> Result<Mesh> {
    let text = std::str::from_utf8(bytes)
        .map_err(|_| Error::format(path, FormatProblem::Corrupt, "ASCII STL is not valid text"))?;
    let bad = |msg: String| Error::format(path, FormatProblem::BadValue, msg);
    let lines = text.lines().enumerate();
    let mut welder = Welder::default();
    let mut triangles = Vec::new();
    let mut corners: Vec<u32> = Vec::with_capacity(3);
    let mut in_solid = false;
    let mut in_loop = false;
    for (line_no, line) in lines {
        let mut tokens = line.split_whitespace();
        let Some(keyword) = tokens.next() else {
            continue;
        };
        let at = |msg: &str| bad(format!("ASCII STL line {}: {msg}", line_no + 1));
        match keyword {
            "solid" if !in_solid => in_solid = true,
            "endsolid" if in_solid && !in_loop => in_solid = false,
            "facet" if in_solid && !in_loop => {}
            "outer" if in_solid && !in_loop => {
                in_loop = true;
                corners.clear();
            }
            "vertex" if in_loop => {
                let xyz: Vec<f64> = tokens
                    .map(|t| t.parse::<f64>())
                    .collect::<std::result::Result<_, _>>()
                    .map_err(|_| at("vertex coordinate is not a number"))?;
                let [x, y, z] = xyz[..] else {
                    return Err(at("vertex needs three coordinates"));
                };
                let p = DVec3::new(x, y, z);
                if !p.is_finite() {
                    return Err(at("vertex coordinate is not finite"));
                }
                if corners.len() == 3 {
                    return Err(at("facet has more than three vertices"));
                }
                corners.push(welder.add(p));
            }
            "endloop" if in_loop => {
                let [a, b, c] = corners[..] else {
                    return Err(at("facet does not have three vertices"));
                };
                triangles.push([a, b, c]);
                in_loop = false;
            }
            "endfacet" if in_solid && !in_loop => {}
            _ => return Err(at(&format!("unexpected {keyword:?}"))),
        }
    }
    if in_solid || in_loop {
        return Err(Error::format(
            path,
            FormatProblem::Truncated,
            "ASCII STL ends inside a solid (no `endsolid`)",
        ));
    }
    Ok(Mesh {
        vertices: welder.vertices,
        normals: Vec::new(),
        triangles,
    })
}

fn parse_obj(path: &Path, bytes: &[u8]) -> Result<Mesh> {
    let text = std::str::from_utf8(bytes)
        .map_err(|_| Error::format(path, FormatProblem::Corrupt, "OBJ file is not valid text"))?;
    let mut vertices = Vec::new();
    let mut file_normals = Vec::new();
    // (OBJ vertex index, OBJ normal index) pairs seen on face corners.
    let mut corner_normals: Vec<(u32, u32)> = Vec::new();
    let mut triangles = Vec::new();
    let mut polygon = Vec::new();
    for (line_no, line) in text.lines().enumerate() {
        let at = |problem, msg: &str| {
            Error::format(path, problem, format!("OBJ line {}: {msg}", line_no + 1))
        };
        let mut tokens = line.split_whitespace();
        match tokens.next() {
            Some(kind @ ("v" | "vn")) => {
                let mut xyz = [0.0; 3];
                for c in &mut xyz {
                    *c = tokens
                        .next()
                        .and_then(|t| t.parse::<f64>().ok())
                        .ok_or_else(|| at(FormatProblem::BadValue, "needs three numbers"))?;
                }
                let p = DVec3::from(xyz);
                if !p.is_finite() {
                    return Err(at(FormatProblem::BadValue, "coordinate is not finite"));
                }
                if kind == "v" {
                    vertices.push(p);
                } else {
                    file_normals.push(p);
                }
            }
            Some("f") => {
                polygon.clear();
                for corner in tokens {
                    let mut parts = corner.split('/');
                    let v = resolve_obj_index(parts.next(), vertices.len()).ok_or_else(|| {
                        at(
                            FormatProblem::BadValue,
                            &format!("bad vertex index in {corner:?}"),
                        )
                    })?;
                    let _texture = parts.next();
                    if let Some(n) = parts.next().filter(|s| !s.is_empty()) {
                        let n =
                            resolve_obj_index(Some(n), file_normals.len()).ok_or_else(|| {
                                at(
                                    FormatProblem::BadValue,
                                    &format!("bad normal index in {corner:?}"),
                                )
                            })?;
                        corner_normals.push((v, n));
                    }
                    polygon.push(v);
                }
                push_polygon(
                    path,
                    &format!("OBJ line {}", line_no + 1),
                    &polygon,
                    vertices.len(),
                    &mut triangles,
                )?;
            }
            _ => {} // comments, vt, groups, materials, smoothing, lines, points
        }
    }
    if u32::try_from(vertices.len()).is_err() {
        return Err(Error::format(
            path,
            FormatProblem::Unsupported,
            "more than 2^32 vertices",
        ));
    }
    let normals = per_vertex_normals(vertices.len(), &file_normals, &corner_normals);
    Ok(Mesh {
        vertices,
        normals,
        triangles,
    })
}

/// OBJ indices are 1-based, negative ones count back from the latest element. `None` if out of range.
fn resolve_obj_index(token: Option<&str>, count: usize) -> Option<u32> {
    let i: i64 = token?.parse().ok()?;
    let zero_based = match i {
        1.. => i - 1,
        ..=-1 => count as i64 + i,
        0 => return None,
    };
    (0..count as i64)
        .contains(&zero_based)
        .then(|| u32::try_from(zero_based).ok())
        .flatten()
}

/// OBJ normals belong to face corners; a [`Mesh`] has one per vertex. Keep them only when every vertex
/// that has one is given the same normal by all its corners and every vertex has one.
fn per_vertex_normals(
    vertex_count: usize,
    file_normals: &[DVec3],
    corners: &[(u32, u32)],
) -> Vec<DVec3> {
    if corners.is_empty() {
        return Vec::new();
    }
    let mut assigned: Vec<Option<DVec3>> = vec![None; vertex_count];
    for &(v, n) in corners {
        let normal = file_normals[n as usize];
        match assigned[v as usize] {
            None => assigned[v as usize] = Some(normal),
            Some(existing) if existing == normal => {}
            Some(_) => return Vec::new(),
        }
    }
    let all: Option<Vec<DVec3>> = assigned.into_iter().collect();
    all.map(|ns| unit_normals(ns.into_iter()))
        .unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An octahedron with outward normals: closed, 6 vertices, 8 triangles.
    fn octahedron() -> Mesh {
        let vertices = vec![
            DVec3::X * 2.5,
            -DVec3::X,
            DVec3::Y * 1.25,
            -DVec3::Y,
            DVec3::Z * 0.1,
            -DVec3::Z,
        ];
        let triangles = vec![
            [0, 2, 4],
            [2, 1, 4],
            [1, 3, 4],
            [3, 0, 4],
            [2, 0, 5],
            [1, 2, 5],
            [3, 1, 5],
            [0, 3, 5],
        ];
        let normals = vertices.iter().map(|v: &DVec3| v.normalize()).collect();
        Mesh {
            vertices,
            normals,
            triangles,
        }
    }

    fn to_f32(m: &Mesh) -> Mesh {
        let r = |v: &DVec3| v.as_vec3().as_dvec3();
        Mesh {
            vertices: m.vertices.iter().map(r).collect(),
            normals: m.normals.iter().map(|n| r(n).normalize()).collect(),
            triangles: m.triangles.clone(),
        }
    }

    #[test]
    fn the_listed_extensions_are_the_formats_read_and_written() {
        for ext in MESH_EXTENSIONS {
            assert!(format_of(Path::new(&format!("m.{ext}"))).is_some(), "{ext}");
            assert!(format_of(Path::new(&format!("m.{}", ext.to_uppercase()))).is_some());
        }
        assert!(format_of(Path::new("m.xyz")).is_none());
        assert!(format_of(Path::new("ply")).is_none());
    }

    #[test]
    fn every_format_round_trips() {
        let dir = tempfile::tempdir().unwrap();
        let mesh = octahedron();
        let ply = dir.path().join("m.PLY");
        write_mesh(&ply, &mesh).unwrap();
        assert_eq!(read_mesh(&ply).unwrap(), to_f32(&mesh));

        let obj = dir.path().join("m.obj");
        write_mesh(&obj, &mesh).unwrap();
        assert_eq!(
            read_mesh(&obj).unwrap(),
            mesh,
            "OBJ keeps full f64 precision"
        );

        let vtk = dir.path().join("m.vtk");
        write_mesh(&vtk, &mesh).unwrap();
        assert_eq!(read_mesh(&vtk).unwrap(), to_f32(&mesh));

        let stl = dir.path().join("m.stl");
        write_mesh(&stl, &mesh).unwrap();
        let back = read_mesh(&stl).unwrap();
        let expected = Mesh {
            normals: vec![],
            ..to_f32(&mesh)
        };
        // Welding renumbers vertices in first-use order: compare triangles by position.
        assert_eq!(back.triangles.len(), 8);
        assert_eq!(back.vertices.len(), 6);
        for (t, u) in back.triangles.iter().zip(&expected.triangles) {
            assert_eq!(
                t.map(|i| back.vertices[i as usize]),
                u.map(|i| expected.vertices[i as usize])
            );
        }
        assert!(back.topology().is_closed_manifold());
        // Facet normals written point outward.
        let bytes = std::fs::read(&stl).unwrap();
        assert_eq!(bytes.len(), 84 + 50 * 8);
        let n0: Vec<f32> = (0..3)
            .map(|k| f32::from_le_bytes(bytes[84 + 4 * k..88 + 4 * k].try_into().unwrap()))
            .collect();
        let c = DVec3::new(2.5, 1.25, 0.1);
        assert!(DVec3::new(n0[0] as f64, n0[1] as f64, n0[2] as f64).dot(c) > 0.0);

        // Without normals as well, and an empty mesh.
        let bare = Mesh {
            normals: vec![],
            ..mesh.clone()
        };
        for p in [&ply, &obj, &vtk] {
            write_mesh(p, &bare).unwrap();
            assert!(read_mesh(p).unwrap().normals.is_empty());
            write_mesh(p, &Mesh::default()).unwrap();
            assert_eq!(read_mesh(p).unwrap(), Mesh::default());
        }
    }

    #[test]
    fn vertex_values_and_colours_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let mesh = octahedron();
        let n = mesh.vertices.len();
        let values: Vec<f32> = (0..n).map(|i| 0.25 * i as f32).collect();
        let colours: Vec<[u8; 3]> = (0..n).map(|i| [i as u8, 100, 255 - i as u8]).collect();
        let path = dir.path().join("map.ply");
        write_ply_with_vertex_values(&path, &mesh, "distance_mm", &values, &colours, Space::Ras)
            .unwrap();
        // Still a mesh to every reader, with the values and colours as vertex properties.
        assert_eq!(read_mesh(&path).unwrap(), to_f32(&mesh));
        let cloud = crate::io::read_point_cloud(&path).unwrap();
        assert_eq!(cloud.scalar("distance_mm").unwrap(), values.as_slice());
        for (k, channel) in ["red", "green", "blue"].into_iter().enumerate() {
            let got: Vec<u8> = cloud
                .scalar(channel)
                .unwrap()
                .iter()
                .map(|&c| c as u8)
                .collect();
            let want: Vec<u8> = colours.iter().map(|c| c[k]).collect();
            assert_eq!(got, want, "{channel}");
        }
        assert_eq!(read_vertex_colours(&path).unwrap(), Some(colours.clone()));
        // A plain PLY, and the formats without vertex colours: none.
        let plain = dir.path().join("plain.ply");
        write_mesh(&plain, &mesh).unwrap();
        assert_eq!(read_vertex_colours(&plain).unwrap(), None);
        let stl = dir.path().join("plain.stl");
        write_mesh(&stl, &mesh).unwrap();
        assert_eq!(read_vertex_colours(&stl).unwrap(), None);
        // Wrong counts or a name that clashes: refused, nothing written.
        let refused = dir.path().join("refused.ply");
        for (name, values, colours) in [
            ("distance_mm", &values[1..], colours.as_slice()),
            ("distance_mm", values.as_slice(), &colours[1..]),
            ("red", values.as_slice(), colours.as_slice()),
            ("two words", values.as_slice(), colours.as_slice()),
        ] {
            let written =
                write_ply_with_vertex_values(&refused, &mesh, name, values, colours, Space::Lps);
            assert!(written.is_err());
            assert!(!refused.exists());
        }
    }

    #[test]
    fn foreign_variants_are_read() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("q.ply");
        // ASCII PLY with a quad, extra properties and the `vertex_index` spelling.
        std::fs::write(
            &path,
            "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n\
             property float z\nproperty uchar red\nelement face 1\nproperty uchar flags\n\
             property list uint8 uint vertex_index\nend_header\n\
             0 0 0 1\n1 0 0 1\n1 1 0 1\n0 1 0 1\n7 4 0 1 2 3\n",
        )
        .unwrap();
        let m = read_mesh(&path).unwrap();
        assert_eq!(m.triangles, vec![[0, 1, 2], [0, 2, 3]]);

        let path = dir.path().join("q.obj");
        std::fs::write(
            &path,
            "# quad\nv 0 0 0\nv 1 0 0\nv 1 1 0 1.0\nv 0 1 0\nvt 0 0\nvn 0 0 2\ng x\n\
             f 1/1/1 2/1/1 -2/1/1 -1/1/1\n",
        )
        .unwrap();
        let m = read_mesh(&path).unwrap();
        assert_eq!(m.triangles, vec![[0, 1, 2], [0, 2, 3]]);
        assert_eq!(m.normals, vec![DVec3::Z; 4]);

        let path = dir.path().join("a.stl");
        std::fs::write(
            &path,
            "solid t\n facet normal 0 0 1\n  outer loop\n   vertex 0 0 0\n   vertex 1 0 0\n\
             vertex 0 1 0\n  endloop\n endfacet\n facet normal 0 0 1\n outer loop\n vertex 1 0 0\n\
             vertex 1 1 0\n vertex 0 1 0\n endloop\n endfacet\nendsolid t\n",
        )
        .unwrap();
        let m = read_mesh(&path).unwrap();
        assert_eq!(m.vertices.len(), 4, "shared corners are welded");
        assert_eq!(m.triangles, vec![[0, 1, 2], [1, 3, 2]]);
        assert_eq!(m.topology().boundary_edges, 4);
    }

    #[test]
    fn hostile_meshes_give_format_errors() {
        let dir = tempfile::tempdir().unwrap();
        let ply_head = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n\
                        property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n\
                        0 0 0\n1 0 0\n0 1 0\n";
        let vtk_head = "# vtk DataFile Version 4.2\nt\nASCII\nDATASET POLYDATA\nPOINTS 3 float\n\
                        0 0 0\n1 0 0\n0 1 0\n"
            .to_string();
        let mut stl_bin = vec![0u8; 80];
        stl_bin.extend_from_slice(&1000u32.to_le_bytes());
        stl_bin.extend_from_slice(&[0u8; 50]);
        let mut stl_nan = vec![0u8; 80];
        stl_nan.extend_from_slice(&1u32.to_le_bytes());
        stl_nan.extend_from_slice(&[0u8; 12]);
        stl_nan.extend_from_slice(&f32::NAN.to_le_bytes());
        stl_nan.extend_from_slice(&[0u8; 34]);
        let cases: Vec<(&str, Vec<u8>, FormatProblem)> = vec![
            (
                "a.ply",
                format!("{ply_head}3 0 1 3\n").into_bytes(),
                FormatProblem::BadValue,
            ),
            (
                "b.ply",
                format!("{ply_head}3 0 1 -1\n").into_bytes(),
                FormatProblem::BadValue,
            ),
            (
                "c.ply",
                format!("{ply_head}2 0 1\n").into_bytes(),
                FormatProblem::BadValue,
            ),
            (
                "d.ply",
                format!("{ply_head}3 0 1\n").into_bytes(),
                FormatProblem::Truncated,
            ),
            (
                "e.ply",
                ply_head.replace("face 1", "face 1000000000").into_bytes(),
                FormatProblem::SizeMismatch,
            ),
            ("f.stl", stl_bin, FormatProblem::Truncated),
            ("g.stl", stl_nan, FormatProblem::BadValue),
            (
                "h.stl",
                b"solid x\nfacet normal 0 0 1\nouter loop\nvertex 0 0\n".to_vec(),
                FormatProblem::BadValue,
            ),
            (
                "i.stl",
                b"solid x\nfacet normal 0 0 1\nouter loop\n".to_vec(),
                FormatProblem::Truncated,
            ),
            ("j.stl", b"abc".to_vec(), FormatProblem::Truncated),
            (
                "k.obj",
                b"v 0 0 0\nv 1 0 0\nf 1 2 3\n".to_vec(),
                FormatProblem::BadValue,
            ),
            (
                "l.obj",
                b"v 0 0 0\nv 1 0 0\nv 1 1 0\nf 0 1 2\n".to_vec(),
                FormatProblem::BadValue,
            ),
            ("m.obj", b"v 0 nan 0\n".to_vec(), FormatProblem::BadValue),
            ("n.obj", b"v 0 0\n".to_vec(), FormatProblem::BadValue),
            ("o.off", b"OFF\n".to_vec(), FormatProblem::Unsupported),
            (
                "p.vtk",
                vtk_head
                    .replace("POINTS 3", "POINTS 3000000000")
                    .into_bytes(),
                FormatProblem::Truncated,
            ),
            (
                "q.vtk",
                format!("{vtk_head}POLYGONS 1 4\n3 0 1 3\n").into_bytes(),
                FormatProblem::BadValue,
            ),
            (
                "r.vtk",
                format!("{vtk_head}POLYGONS 1 4\n3 0 1\n").into_bytes(),
                FormatProblem::Truncated,
            ),
            (
                "s.vtk",
                format!("{vtk_head}POLYGONS 2 4\n3 0 1 2\n").into_bytes(),
                FormatProblem::SizeMismatch,
            ),
            (
                "t.vtk",
                vtk_head
                    .replace("POLYDATA", "UNSTRUCTURED_GRID")
                    .into_bytes(),
                FormatProblem::Unsupported,
            ),
            (
                "u.vtk",
                vtk_head.replace("1 0 0", "1 nan 0").into_bytes(),
                FormatProblem::BadValue,
            ),
            (
                "v.vtk",
                b"# vtk DataFile Version 4.2\nx\nBINARY\nDATASET POLYDATA\nPOINTS 9 float\n\0\0"
                    .to_vec(),
                FormatProblem::Truncated,
            ),
            ("w.vtk", vtk_head.into_bytes(), FormatProblem::MissingField),
            ("x.vtk", b"solid\n".to_vec(), FormatProblem::Unsupported),
        ];
        for (name, bytes, problem) in cases {
            let path = dir.path().join(name);
            std::fs::write(&path, &bytes).unwrap();
            let err = read_mesh(&path).unwrap_err();
            assert_eq!(err.problem(), Some(problem), "{name}: {err}");
            assert!(err.to_string().contains(name), "{err}");
        }
    }

    #[test]
    fn writer_refuses_inconsistent_meshes() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("x.ply");
        let mut m = octahedron();
        m.triangles.push([0, 1, 6]);
        assert!(matches!(write_mesh(&path, &m), Err(Error::InvalidInput(_))));
        let mut m = octahedron();
        m.normals.pop();
        assert!(matches!(write_mesh(&path, &m), Err(Error::InvalidInput(_))));
        assert!(matches!(
            write_mesh(&dir.path().join("x.off"), &octahedron()),
            Err(Error::InvalidInput(_))
        ));
        assert!(!path.exists());
    }

    #[test]
    fn mutated_files_never_panic() {
        use rand::{Rng, SeedableRng};
        let dir = tempfile::tempdir().unwrap();
        let mut originals = Vec::new();
        for name in ["m.ply", "m.stl", "m.obj", "m.vtk"] {
            let path = dir.path().join(name);
            write_mesh(&path, &octahedron()).unwrap();
            originals.push((name, std::fs::read(&path).unwrap()));
        }
        originals.push(("a.vtk", ASCII_VTK_5.to_vec()));
        originals.push((
            "a.ply",
            b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n\
property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n\
0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"
                .to_vec(),
        ));
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let path = Path::new("fuzz");
        for (name, original) in &originals {
            for _ in 0..400 {
                let mut bytes = original.clone();
                match rng.random_range(0..3) {
                    0 => bytes.truncate(rng.random_range(0..bytes.len())),
                    1 => {
                        for _ in 0..rng.random_range(1..4) {
                            let i = rng.random_range(0..bytes.len());
                            bytes[i] = rng.random();
                        }
                    }
                    _ => {
                        // Digits and header words are where parsers go wrong: overwrite with some.
                        let i = rng.random_range(0..bytes.len());
                        let junk: &[u8] = [&b"9999999999"[..], b"-1", b"\xff\xff\xff\x7f", b"nan"]
                            [rng.random_range(0..4)];
                        for (k, &b) in junk.iter().enumerate() {
                            if let Some(x) = bytes.get_mut(i + k) {
                                *x = b;
                            }
                        }
                    }
                }
                // A format error, or a mesh that is safe to use; any panic fails the test.
                let result = match name.rsplit('.').next() {
                    Some("ply") => parse_ply_mesh(path, &bytes),
                    Some("stl") => parse_stl(path, &bytes),
                    Some("vtk") => crate::io::vtk::read(path, &bytes).map(|v| v.mesh),
                    _ => parse_obj(path, &bytes),
                };
                match result {
                    Ok(m) => {
                        assert!(m.vertices.iter().all(|v| v.is_finite()));
                        assert!(
                            m.triangles
                                .iter()
                                .flatten()
                                .all(|&i| (i as usize) < m.vertices.len())
                        );
                        assert!(m.normals.is_empty() || m.normals.len() == m.vertices.len());
                    }
                    Err(e) => assert!(e.problem().is_some(), "{e}"),
                }
                let _ = crate::io::ply::PlyFile::parse(path, &bytes);
            }
        }
    }

    /// A version-5 ASCII VTK file as VTK 9 writes it: offsets and connectivity, a quad and a strip.
    const ASCII_VTK_5: &[u8] = b"# vtk DataFile Version 5.1\nvtk output SPACE=LPS\nASCII\n\
DATASET POLYDATA\nPOINTS 5 double\n0 0 0 1 0 0 1 1 0\n0 1 0 2 1 0\n\n\
POLYGONS 2 4\nOFFSETS vtktypeint64\n0 4\nCONNECTIVITY vtktypeint64\n0 1 2 3\n\
TRIANGLE_STRIPS 2 4\nOFFSETS vtktypeint64\n0 4\nCONNECTIVITY vtktypeint64\n1 4 2 3\n\
CELL_DATA 3\nFIELD FieldData 1\n";

    #[test]
    fn foreign_vtk_variants_are_read() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("v5.vtk");
        std::fs::write(&path, ASCII_VTK_5).unwrap();
        let (m, space) = read_mesh_and_space(&path).unwrap();
        assert_eq!(space, Some(Space::Lps));
        // Quad fanned, strip split with alternating winding; LPS read into RAS.
        assert_eq!(
            m.triangles,
            vec![[0, 1, 2], [0, 2, 3], [1, 4, 2], [2, 4, 3]]
        );
        assert_eq!(m.vertices[1], DVec3::new(-1.0, 0.0, 0.0));
        assert_eq!(m.vertices[4], DVec3::new(-2.0, -1.0, 0.0));
        // Version 4 ASCII with lines, vertices and normals; untagged: read as RAS.
        let path = dir.path().join("v4.vtk");
        std::fs::write(
            &path,
            "# vtk DataFile Version 3.0\r\nno tag\r\nASCII\r\nDATASET POLYDATA\r\n\
             POINTS 3 float\r\n0 0 0 1 0 0 0 1 0\r\nVERTICES 1 2\r\n1 0\r\nLINES 1 3\r\n2 0 1\r\n\
             POLYGONS 1 4\r\n3 0 1 2\r\nPOINT_DATA 3\r\nNORMALS n float\r\n0 0 2 0 0 1 0 0 1\r\n",
        )
        .unwrap();
        let (m, space) = read_mesh_and_space(&path).unwrap();
        assert_eq!(space, None);
        assert_eq!(m.triangles, vec![[0, 1, 2]]);
        assert_eq!(m.vertices[1], DVec3::X);
        assert_eq!(m.normals, vec![DVec3::Z; 3]);
    }

    #[test]
    fn every_format_round_trips_its_space_tag() {
        let dir = tempfile::tempdir().unwrap();
        let mesh = octahedron();
        for ext in MESH_EXTENSIONS {
            for space in [Space::Ras, Space::Lps] {
                let path = dir.path().join(format!("m_{}.{ext}", space.name()));
                write_mesh_in(&path, &mesh, space).unwrap();
                let (back, tag) = read_mesh_and_space(&path).unwrap();
                assert_eq!(tag, Some(space), "{ext}");
                let want = if ext == "obj" {
                    mesh.clone()
                } else {
                    to_f32(&mesh)
                };
                if ext == "stl" {
                    assert_eq!(back.vertices.len(), 6);
                    let (lo, hi) = back.bounds().unwrap();
                    assert_eq!((lo, hi), want.bounds().unwrap(), "{ext} {space:?}");
                } else {
                    assert_eq!(back, want, "{ext} {space:?}");
                }
                // The tag is where Slicer looks: the file's text holds it once.
                let bytes = std::fs::read(&path).unwrap();
                assert_eq!(Space::find_tag(&bytes), Some(space));
            }
        }
        // The coloured PLY too.
        let n = mesh.vertices.len();
        let path = dir.path().join("map.ply");
        write_ply_with_vertex_values(
            &path,
            &mesh,
            "d",
            &vec![0.0; n],
            &vec![[0; 3]; n],
            Space::Lps,
        )
        .unwrap();
        let (back, tag) = read_mesh_and_space(&path).unwrap();
        assert_eq!((back, tag), (to_f32(&mesh), Some(Space::Lps)));
    }

    #[test]
    fn lps_and_ras_files_differ_in_the_tag_and_the_signs_of_x_and_y_only() {
        let dir = tempfile::tempdir().unwrap();
        let mesh = octahedron();
        for ext in MESH_EXTENSIONS {
            let ras_path = dir.path().join(format!("ras.{ext}"));
            let lps_path = dir.path().join(format!("lps.{ext}"));
            write_mesh_in(&ras_path, &mesh, Space::Ras).unwrap();
            write_mesh_in(&lps_path, &mesh, Space::Lps).unwrap();
            let ras = std::fs::read(&ras_path).unwrap();
            let lps = std::fs::read(&lps_path).unwrap();
            // As stored: x and y negated, z, triangles and everything else the same.
            let format = format_of(&ras_path).unwrap();
            let (stored_ras, _) = parse_mesh(&ras_path, format, &ras).unwrap();
            let (stored_lps, _) = parse_mesh(&lps_path, format, &lps).unwrap();
            assert_eq!(Space::Lps.convert(&stored_ras), stored_lps, "{ext}");
            // Byte for byte: with the tag put back, binary files differ only in sign bits (x, y and
            // their normals) and OBJ only in the minus signs of the first two numbers on a line.
            let mut lps = lps;
            let tag_at = lps.windows(9).position(|w| w == b"SPACE=LPS").unwrap();
            lps[tag_at..tag_at + 9].copy_from_slice(b"SPACE=RAS");
            assert_eq!(ras.len(), lps.len(), "{ext}");
            if ext == "obj" {
                let (r, l) = (
                    String::from_utf8(ras).unwrap(),
                    String::from_utf8(lps).unwrap(),
                );
                for (a, b) in r.lines().zip(l.lines()) {
                    let (a, b): (Vec<&str>, Vec<&str>) =
                        (a.split(' ').collect(), b.split(' ').collect());
                    for (k, (x, y)) in a.iter().zip(&b).enumerate() {
                        if (k == 1 || k == 2) && (a[0] == "v" || a[0] == "vn") {
                            let negated = x
                                .strip_prefix('-')
                                .map(str::to_owned)
                                .unwrap_or(format!("-{x}"));
                            assert_eq!(*y, negated, "{ext}: {a:?} {b:?}");
                        } else {
                            assert_eq!(x, y, "{ext}");
                        }
                    }
                }
            } else {
                let differing: Vec<usize> = (0..ras.len()).filter(|&i| ras[i] != lps[i]).collect();
                assert!(!differing.is_empty(), "{ext}");
                for i in differing {
                    assert_eq!(
                        ras[i] ^ lps[i],
                        0x80,
                        "{ext}: byte {i} differs beyond a sign bit"
                    );
                }
            }
        }
    }

    #[test]
    fn reads_the_fcal_phantom_cad_model() {
        // A binary STL whose 80-byte header starts with "solid": must not be taken for ASCII.
        let path = Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../../shared/data/real/fCal_1.0.stl"
        ));
        if !path.exists() {
            eprintln!("skipping: {} not present", path.display());
            return;
        }
        let m = read_mesh(path).unwrap();
        assert_eq!(m.triangles.len(), (1_289_884 - 84) / 50);
        let (lo, hi) = m.bounds().unwrap();
        let size = hi - lo;
        // The fCal 1.0 phantom is a box of some tens of millimetres on each side.
        assert!(
            size.min_element() > 10.0 && size.max_element() < 500.0,
            "{size}"
        );
        let topo = m.topology();
        assert!(topo.components >= 1);
        assert!(m.area_mm2() > 0.0);
    }
}
