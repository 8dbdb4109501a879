//! Point-cloud PLY: `vertex` with float `x y z` plus named float scalar properties (binary little-endian
//! written, ASCII and binary accepted on input, extra properties kept).
//!
//! The PLY parser here is the only one in the crate: [`crate::io::mesh_io`] reads mesh PLY files through
//! [`PlyFile::parse`] too. It decodes every element of every encoding (`ascii`, `binary_little_endian`,
//! `binary_big_endian`) and property type into f64 columns; list properties (face indices) become flat
//! value arrays with per-row offsets. Every count in the header is checked against the bytes actually
//! present before anything is allocated from it, so a hostile header cannot make us reserve memory.

use std::io::Write;
use std::path::Path;

use glam::DVec3;

use crate::{Error, FormatProblem, Result};

/// Points (mm, Reference frame) with named per-point scalars such as `intensity`, `value`, `gx`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PointCloud {
    pub positions: Vec<DVec3>,
    /// (name, one value per point), in file order.
    pub scalars: Vec<(String, Vec<f32>)>,
}

impl PointCloud {
    /// The scalar called `name`, if present.
    pub fn scalar(&self, name: &str) -> Option<&[f32]> {
        self.scalars
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, v)| v.as_slice())
    }
}

/// Reads the `vertex` element of a PLY file (any encoding): `x y z` are required and must be finite;
/// every other scalar vertex property is kept (as f32) in file order; list properties are skipped.
pub fn read_point_cloud(path: &Path) -> Result<PointCloud> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let ply = PlyFile::parse(path, &bytes)?;
    let vertex = ply.element("vertex").ok_or_else(|| {
        Error::format(
            path,
            FormatProblem::MissingField,
            "PLY file has no `vertex` element",
        )
    })?;
    let positions = vertex.positions(path)?;
    let scalars = vertex
        .properties
        .iter()
        .zip(&vertex.columns)
        .filter(|(p, _)| !matches!(p.name.as_str(), "x" | "y" | "z"))
        .filter_map(|(p, c)| match c {
            Column::Scalar(values) => {
                Some((p.name.clone(), values.iter().map(|&v| v as f32).collect()))
            }
            Column::List { .. } => None,
        })
        .collect();
    Ok(PointCloud { positions, scalars })
}

/// Writes a binary little-endian PLY: `float x y z` then one `float` property per scalar, in order.
pub fn write_point_cloud(path: &Path, cloud: &PointCloud) -> Result<()> {
    let n = cloud.positions.len();
    for (name, values) in &cloud.scalars {
        if !is_valid_property_name(name) || matches!(name.as_str(), "x" | "y" | "z") {
            return Err(Error::InvalidInput(format!(
                "{}: scalar name {name:?} cannot be a PLY property name",
                path.display()
            )));
        }
        if values.len() != n {
            return Err(Error::InvalidInput(format!(
                "{}: scalar `{name}` has {} values for {n} points",
                path.display(),
                values.len()
            )));
        }
    }
    let mut header =
        String::from("ply\nformat binary_little_endian 1.0\ncomment echosurf point cloud, mm\n");
    header.push_str(&format!(
        "element vertex {n}\nproperty float x\nproperty float y\nproperty float z\n"
    ));
    for (name, _) in &cloud.scalars {
        header.push_str(&format!("property float {name}\n"));
    }
    header.push_str("end_header\n");
    crate::io::atomic::write_atomic(path, |w| {
        w.write_all(header.as_bytes())?;
        let mut row = Vec::with_capacity(4 * (3 + cloud.scalars.len()));
        for (i, p) in cloud.positions.iter().enumerate() {
            row.clear();
            for c in [p.x, p.y, p.z] {
                row.extend_from_slice(&(c as f32).to_le_bytes());
            }
            for (_, values) in &cloud.scalars {
                row.extend_from_slice(&values[i].to_le_bytes());
            }
            w.write_all(&row)?;
        }
        Ok(())
    })
}

/// A PLY property name we can write: a non-empty token of printable ASCII without whitespace.
pub(crate) fn is_valid_property_name(name: &str) -> bool {
    !name.is_empty() && name.bytes().all(|b| b.is_ascii_graphic())
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Encoding {
    Ascii,
    BinaryLittleEndian,
    BinaryBigEndian,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum ScalarType {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl ScalarType {
    fn parse(name: &str) -> Option<Self> {
        Some(match name {
            "char" | "int8" => Self::I8,
            "uchar" | "uint8" => Self::U8,
            "short" | "int16" => Self::I16,
            "ushort" | "uint16" => Self::U16,
            "int" | "int32" => Self::I32,
            "uint" | "uint32" => Self::U32,
            "float" | "float32" => Self::F32,
            "double" | "float64" => Self::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Self::I8 | Self::U8 => 1,
            Self::I16 | Self::U16 => 2,
            Self::I32 | Self::U32 | Self::F32 => 4,
            Self::F64 => 8,
        }
    }

    fn is_integer(self) -> bool {
        !matches!(self, Self::F32 | Self::F64)
    }

    /// Decodes one value from exactly `self.size()` bytes.
    fn decode(self, b: &[u8], little: bool) -> f64 {
        macro_rules! get {
            ($t:ty, $n:expr) => {{
                let mut a = [0u8; $n];
                a.copy_from_slice(&b[..$n]);
                if little {
                    <$t>::from_le_bytes(a) as f64
                } else {
                    <$t>::from_be_bytes(a) as f64
                }
            }};
        }
        match self {
            Self::I8 => b[0] as i8 as f64,
            Self::U8 => b[0] as f64,
            Self::I16 => get!(i16, 2),
            Self::U16 => get!(u16, 2),
            Self::I32 => get!(i32, 4),
            Self::U32 => get!(u32, 4),
            Self::F32 => get!(f32, 4),
            Self::F64 => get!(f64, 8),
        }
    }
}

#[derive(Debug, Clone, PartialEq)]
pub(crate) enum PropertyKind {
    Scalar(ScalarType),
    List { count: ScalarType, item: ScalarType },
}

#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Property {
    pub name: String,
    pub kind: PropertyKind,
}

/// Decoded values of one property for all rows of its element.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Column {
    Scalar(Vec<f64>),
    /// Row `r` holds `values[offsets[r]..offsets[r + 1]]`.
    List {
        offsets: Vec<usize>,
        values: Vec<f64>,
    },
}

#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Element {
    pub name: String,
    pub count: usize,
    pub properties: Vec<Property>,
    /// One column per property, same order.
    pub columns: Vec<Column>,
}

impl Element {
    pub(crate) fn scalar(&self, name: &str) -> Option<&[f64]> {
        self.properties
            .iter()
            .zip(&self.columns)
            .find_map(|(p, c)| match c {
                Column::Scalar(v) if p.name == name => Some(v.as_slice()),
                _ => None,
            })
    }

    pub(crate) fn list(&self, name: &str) -> Option<(&[usize], &[f64])> {
        self.properties
            .iter()
            .zip(&self.columns)
            .find_map(|(p, c)| match c {
                Column::List { offsets, values } if p.name == name => {
                    Some((offsets.as_slice(), values.as_slice()))
                }
                _ => None,
            })
    }

    /// The `x y z` columns as finite positions.
    pub(crate) fn positions(&self, path: &Path) -> Result<Vec<DVec3>> {
        let axis = |name: &str| {
            self.scalar(name).ok_or_else(|| {
                Error::format(
                    path,
                    FormatProblem::MissingField,
                    format!(
                        "PLY `{}` element has no scalar property `{name}`",
                        self.name
                    ),
                )
            })
        };
        let (x, y, z) = (axis("x")?, axis("y")?, axis("z")?);
        let mut positions = Vec::with_capacity(self.count);
        for i in 0..self.count {
            let p = DVec3::new(x[i], y[i], z[i]);
            if !p.is_finite() {
                return Err(Error::format(
                    path,
                    FormatProblem::BadValue,
                    format!("PLY vertex {i} has a non-finite coordinate ({p})"),
                ));
            }
            positions.push(p);
        }
        Ok(positions)
    }
}

/// A fully decoded PLY file.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct PlyFile {
    pub encoding: Encoding,
    pub elements: Vec<Element>,
}

/// The header may not be longer than this; real headers are a few hundred bytes.
const MAX_HEADER_BYTES: usize = 1 << 20;

impl PlyFile {
    pub(crate) fn element(&self, name: &str) -> Option<&Element> {
        self.elements.iter().find(|e| e.name == name)
    }

    /// Parses header and body; `path` only names the file in errors.
    pub(crate) fn parse(path: &Path, bytes: &[u8]) -> Result<PlyFile> {
        let bad = |problem, msg: String| Error::format(path, problem, msg);
        if !bytes.starts_with(b"ply\n") && !bytes.starts_with(b"ply\r\n") {
            return Err(bad(
                FormatProblem::Unsupported,
                "not a PLY file (no `ply` magic line)".into(),
            ));
        }
        // The header ends at the first line that reads `end_header` (LF or CRLF line breaks).
        let search = &bytes[..bytes.len().min(MAX_HEADER_BYTES)];
        let mut line_start = 0;
        let mut header_end = None;
        while line_start < search.len() {
            let line_end = search[line_start..]
                .iter()
                .position(|&b| b == b'\n')
                .map(|i| line_start + i);
            let line = &search[line_start..line_end.unwrap_or(search.len())];
            if line.trim_ascii() == b"end_header" {
                header_end = Some((line_start, line_end.map_or(search.len(), |e| e + 1)));
                break;
            }
            match line_end {
                Some(e) => line_start = e + 1,
                None => break,
            }
        }
        let (end_pos, body_start) = header_end.ok_or_else(|| {
            bad(
                FormatProblem::Truncated,
                "PLY header has no `end_header` line".into(),
            )
        })?;
        let header = std::str::from_utf8(&bytes[..end_pos]).map_err(|_| {
            bad(
                FormatProblem::Corrupt,
                "PLY header is not valid text".into(),
            )
        })?;

        let mut encoding = None;
        let mut elements: Vec<Element> = Vec::new();
        for (line_no, line) in header.lines().enumerate().skip(1) {
            let mut tokens = line.split_whitespace();
            let Some(keyword) = tokens.next() else {
                continue;
            };
            let line_err = |msg: &str| {
                bad(
                    FormatProblem::BadValue,
                    format!("PLY header line {}: {msg}: {line:?}", line_no + 1),
                )
            };
            match keyword {
                "comment" | "obj_info" => {}
                "format" => {
                    encoding = Some(match tokens.next() {
                        Some("ascii") => Encoding::Ascii,
                        Some("binary_little_endian") => Encoding::BinaryLittleEndian,
                        Some("binary_big_endian") => Encoding::BinaryBigEndian,
                        _ => {
                            return Err(bad(
                                FormatProblem::Unsupported,
                                format!("unknown PLY format line {line:?}"),
                            ));
                        }
                    });
                }
                "element" => {
                    let (Some(name), Some(count)) = (tokens.next(), tokens.next()) else {
                        return Err(line_err("element needs a name and a count"));
                    };
                    let count: usize = count
                        .parse()
                        .map_err(|_| line_err("element count is not a non-negative integer"))?;
                    elements.push(Element {
                        name: name.to_string(),
                        count,
                        properties: Vec::new(),
                        columns: Vec::new(),
                    });
                }
                "property" => {
                    let Some(element) = elements.last_mut() else {
                        return Err(line_err("property before any element"));
                    };
                    let parts: Vec<&str> = tokens.collect();
                    let property = match parts.as_slice() {
                        ["list", count, item, name] => {
                            let count = ScalarType::parse(count)
                                .filter(|t| t.is_integer())
                                .ok_or_else(|| line_err("bad list count type"))?;
                            let item = ScalarType::parse(item)
                                .ok_or_else(|| line_err("bad list item type"))?;
                            Property {
                                name: name.to_string(),
                                kind: PropertyKind::List { count, item },
                            }
                        }
                        [ty, name] => Property {
                            name: name.to_string(),
                            kind: PropertyKind::Scalar(
                                ScalarType::parse(ty)
                                    .ok_or_else(|| line_err("unknown property type"))?,
                            ),
                        },
                        _ => return Err(line_err("malformed property line")),
                    };
                    element.properties.push(property);
                }
                _ => return Err(line_err("unknown header keyword")),
            }
        }
        let encoding = encoding.ok_or_else(|| {
            bad(
                FormatProblem::MissingField,
                "PLY header has no `format` line".into(),
            )
        })?;

        let mut reader = BodyReader {
            path,
            bytes,
            pos: body_start,
            encoding,
        };
        for element in &mut elements {
            reader.read_element(element)?;
        }
        Ok(PlyFile { encoding, elements })
    }
}

struct BodyReader<'a> {
    path: &'a Path,
    bytes: &'a [u8],
    pos: usize,
    encoding: Encoding,
}

impl BodyReader<'_> {
    fn truncated(&self, element: &str) -> Error {
        Error::format(
            self.path,
            FormatProblem::Truncated,
            format!("PLY file ends inside element `{element}`"),
        )
    }

    fn remaining(&self) -> usize {
        self.bytes.len() - self.pos
    }

    fn read_element(&mut self, element: &mut Element) -> Result<()> {
        // Smallest possible encoded row: binary scalars at their size, list counts at theirs (empty
        // list); ascii at least one digit plus a separator per value.
        let min_row_bytes: usize = element
            .properties
            .iter()
            .map(|p| match (&p.kind, self.encoding) {
                (_, Encoding::Ascii) => 2,
                (PropertyKind::Scalar(t), _) => t.size(),
                (PropertyKind::List { count, .. }, _) => count.size(),
            })
            .sum();
        // An ascii file may omit the final line break, hence the +1.
        let fits = match min_row_bytes {
            0 => element.count <= self.remaining(),
            n => element
                .count
                .checked_mul(n)
                .is_some_and(|need| need <= self.remaining() + 1),
        };
        if !fits {
            return Err(Error::format(
                self.path,
                FormatProblem::SizeMismatch,
                format!(
                    "PLY header promises {} `{}` rows but the file has only {} bytes left",
                    element.count,
                    element.name,
                    self.remaining()
                ),
            ));
        }
        let count = element.count;
        element.columns = element
            .properties
            .iter()
            .map(|p| match p.kind {
                PropertyKind::Scalar(_) => Column::Scalar(Vec::with_capacity(count)),
                PropertyKind::List { .. } => {
                    let mut offsets = Vec::with_capacity(count + 1);
                    offsets.push(0);
                    Column::List {
                        offsets,
                        values: Vec::with_capacity(3 * count.min(self.remaining())),
                    }
                }
            })
            .collect();
        for _ in 0..count {
            for (property, column) in element.properties.iter().zip(element.columns.iter_mut()) {
                match (&property.kind, column) {
                    (PropertyKind::Scalar(t), Column::Scalar(values)) => {
                        let v = self.value(*t, &element.name)?;
                        values.push(v);
                    }
                    (PropertyKind::List { count: ct, item }, Column::List { offsets, values }) => {
                        let n = self.value(*ct, &element.name)?;
                        if !(0.0..=u32::MAX as f64).contains(&n) {
                            return Err(Error::format(
                                self.path,
                                FormatProblem::BadValue,
                                format!(
                                    "PLY list `{}` of `{}` has a negative length",
                                    property.name, element.name
                                ),
                            ));
                        }
                        let n = n as usize;
                        let min_item = if self.encoding == Encoding::Ascii {
                            2
                        } else {
                            item.size()
                        };
                        if n.saturating_mul(min_item) > self.remaining() + 1 {
                            return Err(self.truncated(&element.name));
                        }
                        for _ in 0..n {
                            values.push(self.value(*item, &element.name)?);
                        }
                        offsets.push(values.len());
                    }
                    _ => unreachable!("columns are built from the properties"),
                }
            }
        }
        Ok(())
    }

    fn value(&mut self, ty: ScalarType, element: &str) -> Result<f64> {
        match self.encoding {
            Encoding::Ascii => {
                while self.pos < self.bytes.len() && self.bytes[self.pos].is_ascii_whitespace() {
                    self.pos += 1;
                }
                let start = self.pos;
                while self.pos < self.bytes.len() && !self.bytes[self.pos].is_ascii_whitespace() {
                    self.pos += 1;
                }
                if start == self.pos {
                    return Err(self.truncated(element));
                }
                let token = std::str::from_utf8(&self.bytes[start..self.pos]).unwrap_or("");
                let parsed = if ty.is_integer() {
                    token.parse::<i64>().ok().map(|v| v as f64)
                } else {
                    token.parse::<f64>().ok()
                };
                parsed.ok_or_else(|| {
                    Error::format(
                        self.path,
                        FormatProblem::BadValue,
                        format!("PLY element `{element}`: {token:?} is not a number"),
                    )
                })
            }
            Encoding::BinaryLittleEndian | Encoding::BinaryBigEndian => {
                let size = ty.size();
                if self.remaining() < size {
                    return Err(self.truncated(element));
                }
                let v = ty.decode(
                    &self.bytes[self.pos..self.pos + size],
                    self.encoding == Encoding::BinaryLittleEndian,
                );
                self.pos += size;
                Ok(v)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cloud() -> PointCloud {
        PointCloud {
            positions: vec![
                DVec3::new(1.5, -2.25, 3.0),
                DVec3::new(0.0, 10.0, -7.5),
                DVec3::new(100.125, 0.5, 0.25),
            ],
            scalars: vec![
                ("intensity".into(), vec![12.0, 255.0, 0.5]),
                ("value".into(), vec![-1.0, 2.0, 3.5]),
            ],
        }
    }

    #[test]
    fn binary_round_trip_is_exact_for_f32_values() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("p.ply");
        let c = cloud();
        write_point_cloud(&path, &c).unwrap();
        let back = read_point_cloud(&path).unwrap();
        assert_eq!(back, c);
        assert_eq!(back.scalar("value").unwrap(), &[-1.0, 2.0, 3.5]);
        let empty = PointCloud::default();
        write_point_cloud(&path, &empty).unwrap();
        assert_eq!(read_point_cloud(&path).unwrap(), empty);
    }

    #[test]
    fn ascii_and_big_endian_with_extra_properties_are_read() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.ply");
        std::fs::write(
            &path,
            "ply\r\nformat ascii 1.0\r\ncomment hi\r\nelement vertex 2\r\nproperty double x\r\n\
             property float y\r\nproperty float z\r\nproperty uchar red\r\n\
             property list uchar int tags\r\nelement camera 1\r\nproperty float f\r\nend_header\r\n\
             1 2 3 200 2 7 8\r\n-1e1 0.5 6 0 0\r\n42\r\n",
        )
        .unwrap();
        let c = read_point_cloud(&path).unwrap();
        assert_eq!(
            c.positions,
            vec![DVec3::new(1.0, 2.0, 3.0), DVec3::new(-10.0, 0.5, 6.0)]
        );
        assert_eq!(c.scalars, vec![("red".to_string(), vec![200.0, 0.0])]);

        let mut be = b"ply\nformat binary_big_endian 1.0\nelement vertex 1\nproperty short x\n\
property float y\nproperty double z\nproperty uint q\nend_header\n"
            .to_vec();
        be.extend_from_slice(&(-3i16).to_be_bytes());
        be.extend_from_slice(&2.5f32.to_be_bytes());
        be.extend_from_slice(&1e-3f64.to_be_bytes());
        be.extend_from_slice(&4_000_000_000u32.to_be_bytes());
        std::fs::write(&path, &be).unwrap();
        let c = read_point_cloud(&path).unwrap();
        assert_eq!(c.positions, vec![DVec3::new(-3.0, 2.5, 1e-3)]);
        assert_eq!(c.scalar("q").unwrap(), &[4e9f32]);
    }

    #[test]
    fn hostile_files_give_format_errors() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("h.ply");
        let head = "ply\nformat binary_little_endian 1.0\nelement vertex 18446744073709551615\n\
                    property float x\nproperty float y\nproperty float z\nend_header\n";
        let cases: Vec<(Vec<u8>, FormatProblem)> = vec![
            (head.as_bytes().to_vec(), FormatProblem::SizeMismatch),
            (
                head.replace("18446744073709551615", "2").into_bytes(),
                FormatProblem::SizeMismatch,
            ),
            (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n".to_vec(), FormatProblem::Truncated),
            (b"solid x\n".to_vec(), FormatProblem::Unsupported),
            (
                b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n\
property float z\nend_header\n1 nan 2\n"
                    .to_vec(),
                FormatProblem::BadValue,
            ),
            (
                b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n\
property float z\nend_header\n1 zz 2\n"
                    .to_vec(),
                FormatProblem::BadValue,
            ),
            (
                b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n".to_vec(),
                FormatProblem::MissingField,
            ),
            (
                b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty list uint float x\n\
end_header\n\xff\xff\xff\xff"
                    .to_vec(),
                FormatProblem::Truncated,
            ),
            (
                b"ply\nformat weird 1.0\nend_header\n".to_vec(),
                FormatProblem::Unsupported,
            ),
        ];
        for (bytes, problem) in cases {
            std::fs::write(&path, &bytes).unwrap();
            let err = read_point_cloud(&path).unwrap_err();
            assert_eq!(
                err.problem(),
                Some(problem),
                "{err} for {:?}",
                String::from_utf8_lossy(&bytes)
            );
            assert!(err.to_string().contains("h.ply"), "{err}");
        }
    }

    #[test]
    fn writer_rejects_mismatched_scalars() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("w.ply");
        let mut c = cloud();
        c.scalars[0].1.pop();
        assert!(matches!(
            write_point_cloud(&path, &c),
            Err(Error::InvalidInput(_))
        ));
        let mut c = cloud();
        c.scalars[0].0 = "two words".into();
        assert!(matches!(
            write_point_cloud(&path, &c),
            Err(Error::InvalidInput(_))
        ));
        assert!(!path.exists());
    }
}
