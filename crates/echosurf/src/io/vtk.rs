//! Legacy VTK polydata (`.vtk`), the format 3D Slicer hands models to command-line modules in.
//!
//! Written as binary (big-endian, as the legacy format requires) file version 4.2, the version Slicer
//! itself writes for compatibility: `POINTS n float`, `POLYGONS m 4m` and, when the mesh has them,
//! `POINT_DATA n` / `NORMALS Normals float`. The second line, the free-text header, carries the
//! coordinate-system tag (`SPACE=RAS` / `SPACE=LPS`) where Slicer writes and looks for it.
//!
//! Read: ASCII and binary, versions 2 to 5 (legacy `POLYGONS n size` cells and the version-5
//! `OFFSETS` / `CONNECTIVITY` arrays), points of any numeric type, `TRIANGLE_STRIPS` (split into
//! triangles), `VERTICES` and `LINES` (skipped), point normals. Reading stops, keeping the geometry
//! read so far, at the first section it does not know (cell data, scalars, field data after the cells).
//! Every count is checked against the bytes left in the file before anything is allocated for it.

use std::io::Write;
use std::path::Path;

use glam::DVec3;

use crate::mesh::Mesh;
use crate::{Error, FormatProblem, Result};

/// What `read` returns: the mesh as stored (no coordinate change) and the free-text header line.
pub(crate) struct VtkMesh {
    pub mesh: Mesh,
    pub header: String,
}

/// The longest header line the legacy format allows.
const MAX_HEADER_CHARS: usize = 256;

/// Writes `mesh` as binary legacy VTK polydata with `header` (one line, at most 256 characters) as
/// the file's header line.
pub(crate) fn write(path: &Path, mesh: &Mesh, header: &str) -> Result<()> {
    if header.len() > MAX_HEADER_CHARS || header.contains(['\n', '\r']) {
        return Err(Error::InvalidInput(format!(
            "{}: a VTK header is one line of at most {MAX_HEADER_CHARS} characters",
            path.display()
        )));
    }
    let normals = !mesh.normals.is_empty() && mesh.normals.len() == mesh.vertices.len();
    crate::io::atomic::write_atomic(path, |w| {
        write!(
            w,
            "# vtk DataFile Version 4.2\n{header}\nBINARY\nDATASET POLYDATA\nPOINTS {} float\n",
            mesh.vertices.len()
        )?;
        for v in &mesh.vertices {
            write_f32s_be(w, [v.x, v.y, v.z])?;
        }
        let t = mesh.triangles.len();
        write!(w, "\nPOLYGONS {t} {}\n", 4 * t)?;
        for tri in &mesh.triangles {
            w.write_all(&3i32.to_be_bytes())?;
            for &i in tri {
                w.write_all(&(i as i32).to_be_bytes())?;
            }
        }
        w.write_all(b"\n")?;
        if normals {
            write!(
                w,
                "POINT_DATA {}\nNORMALS Normals float\n",
                mesh.vertices.len()
            )?;
            for n in &mesh.normals {
                write_f32s_be(w, [n.x, n.y, n.z])?;
            }
            w.write_all(b"\n")?;
        }
        Ok(())
    })
}

fn write_f32s_be(w: &mut impl Write, values: [f64; 3]) -> std::io::Result<()> {
    for v in values {
        w.write_all(&(v as f32).to_be_bytes())?;
    }
    Ok(())
}

/// The numeric types a legacy VTK array may be stored in.
#[derive(Debug, Clone, Copy)]
enum DataType {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    I64,
    U64,
    F32,
    F64,
}

impl DataType {
    fn parse(name: &str) -> Option<DataType> {
        Some(match name.to_ascii_lowercase().as_str() {
            "char" | "signed_char" | "vtktypeint8" => DataType::I8,
            "unsigned_char" | "bit" | "vtktypeuint8" => DataType::U8,
            "short" | "vtktypeint16" => DataType::I16,
            "unsigned_short" | "vtktypeuint16" => DataType::U16,
            "int" | "vtktypeint32" => DataType::I32,
            "unsigned_int" | "vtktypeuint32" => DataType::U32,
            "long" | "vtktypeint64" | "vtkidtype" => DataType::I64,
            "unsigned_long" | "vtktypeuint64" => DataType::U64,
            "float" | "vtktypefloat32" => DataType::F32,
            "double" | "vtktypefloat64" => DataType::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            DataType::I8 | DataType::U8 => 1,
            DataType::I16 | DataType::U16 => 2,
            DataType::I32 | DataType::U32 | DataType::F32 => 4,
            DataType::I64 | DataType::U64 | DataType::F64 => 8,
        }
    }

    /// One big-endian value of this type (`bytes.len() == self.size()`).
    fn decode(self, b: &[u8]) -> f64 {
        let a = |n: usize| -> [u8; 8] {
            let mut out = [0u8; 8];
            out[..n].copy_from_slice(&b[..n]);
            out
        };
        match self {
            DataType::I8 => b[0] as i8 as f64,
            DataType::U8 => b[0] as f64,
            DataType::I16 => i16::from_be_bytes([b[0], b[1]]) as f64,
            DataType::U16 => u16::from_be_bytes([b[0], b[1]]) as f64,
            DataType::I32 => i32::from_be_bytes([b[0], b[1], b[2], b[3]]) as f64,
            DataType::U32 => u32::from_be_bytes([b[0], b[1], b[2], b[3]]) as f64,
            DataType::F32 => f32::from_be_bytes([b[0], b[1], b[2], b[3]]) as f64,
            DataType::I64 => i64::from_be_bytes(a(8)) as f64,
            DataType::U64 => u64::from_be_bytes(a(8)) as f64,
            DataType::F64 => f64::from_be_bytes(a(8)),
        }
    }
}

/// A position in the file, reading text lines and ASCII or binary arrays.
struct Reader<'a> {
    path: &'a Path,
    bytes: &'a [u8],
    pos: usize,
    binary: bool,
}

impl<'a> Reader<'a> {
    fn error(&self, problem: FormatProblem, message: impl Into<String>) -> Error {
        Error::format(self.path, problem, format!("VTK file: {}", message.into()))
    }

    /// The next line (without its line break), or `None` at the end of the file.
    fn line(&mut self) -> Option<&'a [u8]> {
        if self.pos >= self.bytes.len() {
            return None;
        }
        let rest = &self.bytes[self.pos..];
        let end = rest.iter().position(|&b| b == b'\n').unwrap_or(rest.len());
        self.pos += (end + 1).min(rest.len());
        let line = &rest[..end];
        Some(line.strip_suffix(b"\r").unwrap_or(line))
    }

    /// The words of the next line that has any, or `None` at the end of the file.
    fn keyword_line(&mut self) -> Result<Option<Vec<&'a str>>> {
        while let Some(line) = self.line() {
            let text = std::str::from_utf8(line)
                .map_err(|_| self.error(FormatProblem::Corrupt, "a keyword line is not text"))?;
            let words: Vec<&str> = text.split_whitespace().collect();
            if !words.is_empty() {
                return Ok(Some(words));
            }
        }
        Ok(None)
    }

    /// `count` values of type `ty`, as f64 (exact for every integer below 2^53).
    fn values(&mut self, count: usize, ty: DataType, what: &str) -> Result<Vec<f64>> {
        let left = self.bytes.len() - self.pos;
        if self.binary {
            let needed = count as u128 * ty.size() as u128;
            if needed > left as u128 {
                return Err(self.error(
                    FormatProblem::Truncated,
                    format!(
                        "{what}: {count} values need {needed} bytes but {left} are left in the file"
                    ),
                ));
            }
            let end = self.pos + count * ty.size();
            let out = self.bytes[self.pos..end]
                .chunks_exact(ty.size())
                .map(|b| ty.decode(b))
                .collect();
            self.pos = end;
            Ok(out)
        } else {
            // Each ASCII value takes at least one character and one separator.
            if count as u128 > (left as u128).div_ceil(2) {
                return Err(self.error(
                    FormatProblem::Truncated,
                    format!("{what}: {count} values cannot fit in the {left} bytes left"),
                ));
            }
            let mut out = Vec::with_capacity(count);
            for k in 0..count {
                let token = self.token().ok_or_else(|| {
                    self.error(
                        FormatProblem::Truncated,
                        format!("{what}: the file ends after {k} of {count} values"),
                    )
                })?;
                let value = std::str::from_utf8(token)
                    .ok()
                    .and_then(|t| t.parse::<f64>().ok())
                    .ok_or_else(|| {
                        self.error(
                            FormatProblem::BadValue,
                            format!(
                                "{what}: value {k} ({:?}) is not a number",
                                String::from_utf8_lossy(token)
                            ),
                        )
                    })?;
                out.push(value);
            }
            Ok(out)
        }
    }

    /// The next whitespace-separated word of an ASCII array.
    fn token(&mut self) -> Option<&'a [u8]> {
        let rest = &self.bytes[self.pos..];
        let start = rest.iter().position(|b| !b.is_ascii_whitespace())?;
        let len = rest[start..]
            .iter()
            .position(|b| b.is_ascii_whitespace())
            .unwrap_or(rest.len() - start);
        self.pos += start + len;
        Some(&rest[start..start + len])
    }

    fn count(&self, word: Option<&&str>, what: &str) -> Result<usize> {
        word.and_then(|w| w.parse::<usize>().ok()).ok_or_else(|| {
            self.error(
                FormatProblem::BadValue,
                format!("{what} is not a non-negative integer"),
            )
        })
    }

    fn data_type(&self, word: Option<&&str>, what: &str) -> Result<DataType> {
        let name = word.copied().unwrap_or("");
        DataType::parse(name).ok_or_else(|| {
            self.error(
                FormatProblem::Unsupported,
                format!("{what}: unknown data type {name:?}"),
            )
        })
    }

    /// A cell's point index, checked to be an integer naming one of `vertex_count` points.
    fn index(&self, value: f64, vertex_count: usize, what: &str) -> Result<u32> {
        if value.fract() == 0.0 && value >= 0.0 && value < vertex_count as f64 {
            Ok(value as u32)
        } else {
            Err(self.error(
                FormatProblem::BadValue,
                format!("{what} refers to point {value} but there are {vertex_count} points"),
            ))
        }
    }

    /// The cells of a `POLYGONS`/`TRIANGLE_STRIPS`/`LINES`/`VERTICES` section whose keyword line is
    /// `words`, as point-index lists.
    fn cells(
        &mut self,
        words: &[&str],
        version_5: bool,
        vertex_count: usize,
    ) -> Result<Vec<Vec<u32>>> {
        let section = words[0];
        if version_5 {
            // `POLYGONS n_offsets n_connectivity`, then `OFFSETS type` and `CONNECTIVITY type` arrays.
            let n_offsets = self.count(words.get(1), &format!("{section} offset count"))?;
            let n_conn = self.count(words.get(2), &format!("{section} connectivity size"))?;
            let mut arrays = Vec::with_capacity(2);
            for (name, n) in [("OFFSETS", n_offsets), ("CONNECTIVITY", n_conn)] {
                let line = self.keyword_line()?.unwrap_or_default();
                if line.first() != Some(&name) {
                    return Err(self.error(
                        FormatProblem::MissingField,
                        format!("{section} has no {name} array"),
                    ));
                }
                let ty = self.data_type(line.get(1), name)?;
                arrays.push(self.values(n, ty, &format!("{section} {name}"))?);
            }
            let (offsets, conn) = (&arrays[0], &arrays[1]);
            let mut cells = Vec::with_capacity(n_offsets.saturating_sub(1));
            let bad = || {
                self.error(
                    FormatProblem::BadValue,
                    format!("{section} offsets must rise from 0 to the connectivity size {n_conn}"),
                )
            };
            if offsets.first().is_some_and(|&o| o != 0.0) || offsets.is_empty() && n_conn != 0 {
                return Err(bad());
            }
            for (c, pair) in offsets.windows(2).enumerate() {
                let (a, b) = (pair[0], pair[1]);
                if !(b >= a && b <= n_conn as f64 && b.fract() == 0.0) {
                    return Err(bad());
                }
                let ids = conn[a as usize..b as usize]
                    .iter()
                    .map(|&v| self.index(v, vertex_count, &format!("{section} cell {c}")))
                    .collect::<Result<Vec<u32>>>()?;
                cells.push(ids);
            }
            if offsets.last().is_some_and(|&o| o != n_conn as f64) {
                return Err(bad());
            }
            Ok(cells)
        } else {
            // `POLYGONS n size`, then per cell: its point count and its point indices.
            let n = self.count(words.get(1), &format!("{section} cell count"))?;
            let size = self.count(words.get(2), &format!("{section} size"))?;
            let values = self.values(size, DataType::I32, section)?;
            let mut cells = Vec::with_capacity(n.min(size));
            let mut at = 0usize;
            for c in 0..n {
                let len = values.get(at).copied().ok_or_else(|| {
                    self.error(
                        FormatProblem::SizeMismatch,
                        format!(
                            "{section}: {n} cells promised but the size {size} ends at cell {c}"
                        ),
                    )
                })?;
                if !(len >= 0.0 && len.fract() == 0.0 && at + 1 + len as usize <= size) {
                    return Err(self.error(
                        FormatProblem::BadValue,
                        format!("{section} cell {c} claims {len} points, past the section's size"),
                    ));
                }
                let ids = values[at + 1..at + 1 + len as usize]
                    .iter()
                    .map(|&v| self.index(v, vertex_count, &format!("{section} cell {c}")))
                    .collect::<Result<Vec<u32>>>()?;
                cells.push(ids);
                at += 1 + len as usize;
            }
            if at != size {
                return Err(self.error(
                    FormatProblem::SizeMismatch,
                    format!("{section}: {n} cells use {at} values, the size says {size}"),
                ));
            }
            Ok(cells)
        }
    }
}

/// Parses a legacy VTK polydata file; `path` names the file in errors.
pub(crate) fn read(path: &Path, bytes: &[u8]) -> Result<VtkMesh> {
    let mut r = Reader {
        path,
        bytes,
        pos: 0,
        binary: false,
    };
    let magic = r.line().unwrap_or_default();
    let magic = String::from_utf8_lossy(magic);
    let Some(version) = magic
        .trim()
        .strip_prefix("# vtk DataFile Version")
        .map(str::trim)
    else {
        return Err(r.error(
            FormatProblem::Unsupported,
            "not a legacy VTK file (no `# vtk DataFile Version` line)",
        ));
    };
    let major: u32 = version
        .split('.')
        .next()
        .and_then(|m| m.parse().ok())
        .ok_or_else(|| {
            r.error(
                FormatProblem::BadValue,
                format!("unreadable version {version:?}"),
            )
        })?;
    let header = r
        .line()
        .ok_or_else(|| r.error(FormatProblem::Truncated, "no header line"))?;
    let header = String::from_utf8_lossy(header).into_owned();
    let encoding = r
        .keyword_line()?
        .ok_or_else(|| r.error(FormatProblem::Truncated, "no ASCII/BINARY line"))?;
    r.binary = match encoding[0].to_ascii_uppercase().as_str() {
        "ASCII" => false,
        "BINARY" => true,
        other => {
            return Err(r.error(
                FormatProblem::BadValue,
                format!("expected ASCII or BINARY, found {other:?}"),
            ));
        }
    };
    let dataset = r.keyword_line()?.unwrap_or_default();
    match dataset.as_slice() {
        [d, kind, ..] if d.eq_ignore_ascii_case("DATASET") => {
            if !kind.eq_ignore_ascii_case("POLYDATA") {
                return Err(r.error(
                    FormatProblem::Unsupported,
                    format!("the dataset is {kind}, not POLYDATA (a surface mesh)"),
                ));
            }
        }
        _ => return Err(r.error(FormatProblem::MissingField, "no DATASET POLYDATA line")),
    }

    let mut vertices: Option<Vec<DVec3>> = None;
    let mut triangles = Vec::new();
    let mut normals = Vec::new();
    let mut saw_polygons = false;
    while let Some(words) = r.keyword_line()? {
        let keyword = words[0].to_ascii_uppercase();
        match keyword.as_str() {
            "POINTS" if vertices.is_none() => {
                let n = r.count(words.get(1), "POINTS count")?;
                if u32::try_from(n).is_err() {
                    return Err(r.error(FormatProblem::Unsupported, "more than 2^32 points"));
                }
                let ty = r.data_type(words.get(2), "POINTS")?;
                let xyz = r.values(n.saturating_mul(3), ty, "POINTS")?;
                let points: Vec<DVec3> = xyz
                    .chunks_exact(3)
                    .map(|c| DVec3::new(c[0], c[1], c[2]))
                    .collect();
                if let Some(i) = points.iter().position(|p| !p.is_finite()) {
                    return Err(r.error(
                        FormatProblem::BadValue,
                        format!("point {i} is not finite ({})", points[i]),
                    ));
                }
                vertices = Some(points);
            }
            "POLYGONS" | "TRIANGLE_STRIPS" | "LINES" | "VERTICES" => {
                let Some(points) = &vertices else {
                    return Err(r.error(
                        FormatProblem::MissingField,
                        format!("{keyword} before POINTS"),
                    ));
                };
                let n = points.len();
                let cells = r.cells(&words, major >= 5, n)?;
                match keyword.as_str() {
                    "POLYGONS" => {
                        saw_polygons = true;
                        for (c, cell) in cells.iter().enumerate() {
                            crate::io::polygons::push_polygon(
                                path,
                                &format!("VTK polygon {c}"),
                                cell,
                                n,
                                &mut triangles,
                            )?;
                        }
                    }
                    "TRIANGLE_STRIPS" => {
                        saw_polygons = true;
                        for strip in &cells {
                            for (k, w) in strip.windows(3).enumerate() {
                                // Every other triangle of a strip is wound the other way.
                                triangles.push(if k % 2 == 0 {
                                    [w[0], w[1], w[2]]
                                } else {
                                    [w[1], w[0], w[2]]
                                });
                            }
                        }
                    }
                    _ => {} // points and lines are not part of a surface
                }
            }
            "POINT_DATA" => {
                let n = r.count(words.get(1), "POINT_DATA count")?;
                let points = vertices.as_ref().map_or(0, Vec::len);
                if n != points {
                    return Err(r.error(
                        FormatProblem::SizeMismatch,
                        format!("POINT_DATA for {n} points but the file has {points}"),
                    ));
                }
                let Some(attribute) = r.keyword_line()? else {
                    break;
                };
                if !attribute[0].eq_ignore_ascii_case("NORMALS") {
                    break; // an attribute echosurf does not keep: the geometry is complete
                }
                let ty = r.data_type(attribute.get(2), "NORMALS")?;
                let values = r.values(n.saturating_mul(3), ty, "NORMALS")?;
                normals = crate::io::polygons::unit_normals(
                    values.chunks_exact(3).map(|c| DVec3::new(c[0], c[1], c[2])),
                );
                break;
            }
            // Cell data, field data, metadata: nothing echosurf keeps follows.
            _ => break,
        }
    }
    let Some(vertices) = vertices else {
        return Err(r.error(FormatProblem::MissingField, "no POINTS section"));
    };
    if !saw_polygons && !vertices.is_empty() {
        return Err(r.error(
            FormatProblem::MissingField,
            "no POLYGONS section (a point cloud or lines, not a surface)",
        ));
    }
    Ok(VtkMesh {
        mesh: Mesh {
            vertices,
            normals,
            triangles,
        },
        header,
    })
}
