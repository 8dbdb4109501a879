//! MetaImage (`.mha`, `.mhd` + `.raw`/`.zraw`) PLUS sequence reader and writer.
//!
//! The reader accepts what PLUS and ITK have written over the years: fields in any order, padded and
//! repeated values, CRLF, missing `Kinds`, old `ToolToTracker` names, tracking-only files, volumes without
//! per-frame fields. Every size in the header is checked against the bytes actually present before
//! anything is allocated.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};

use super::atomic::write_atomic;
use super::seq_decode::{
    Assembled, Compression, FrameFieldCollector, Layout, assemble, line_to_str, read_header_line,
    read_pixel_block, split_frame_key, truncate_for_message,
};
use super::sequence::{ElementType, PixelData, TrackedSequence, mat4_to_row_major};
use crate::{Error, FormatProblem, Result};

/// Global fields the reader interprets itself; everything else goes to `TrackedSequence::header`.
const INTERPRETED_FIELDS: &[&str] = &[
    "ObjectType",
    "NDims",
    "DimSize",
    "ElementType",
    "ElementNumberOfChannels",
    "BinaryData",
    "BinaryDataByteOrderMSB",
    "ElementByteOrderMSB",
    "CompressedData",
    "CompressedDataSize",
    "ElementDataFile",
    "UltrasoundImageOrientation",
];

/// Fields the writer always writes itself (in PLUS order), so header copies of them are not repeated.
const WRITER_FIELDS: &[&str] = &[
    "ObjectType",
    "NDims",
    "AnatomicalOrientation",
    "BinaryData",
    "BinaryDataByteOrderMSB",
    "ElementByteOrderMSB",
    "CenterOfRotation",
    "CompressedData",
    "CompressedDataSize",
    "DimSize",
    "ElementNumberOfChannels",
    "ElementSpacing",
    "ElementType",
    "Kinds",
    "Offset",
    "TransformMatrix",
    "UltrasoundImageOrientation",
    "ElementDataFile",
];

/// Reads a PLUS MetaImage sequence (or any 2D/3D MetaImage: a file without per-frame fields gives frames
/// without transforms). Pixels are brought to MF orientation.
pub fn read_sequence(path: &Path) -> Result<TrackedSequence> {
    let file = File::open(path).map_err(|e| Error::io(path, e))?;
    let file_len = file.metadata().map_err(|e| Error::io(path, e))?.len();
    let mut reader = BufReader::with_capacity(1 << 16, file);

    let mut global: BTreeMap<String, String> = BTreeMap::new();
    let mut frame_fields = FrameFieldCollector::default();
    let mut consumed: u64 = 0;
    let mut data_file: Option<String> = None;
    let mut line_number = 0usize;
    while let Some(line) = read_header_line(&mut reader, path, &mut consumed)? {
        line_number += 1;
        if line_number == 1 && !(line.starts_with(b"ObjectType") || line.starts_with(b"NDims")) {
            return Err(Error::format(
                path,
                FormatProblem::Unsupported,
                "not a MetaImage file (first line is neither ObjectType nor NDims)",
            ));
        }
        let text = line_to_str(&line, path)?;
        if text.trim().is_empty() {
            continue;
        }
        let Some((key, value)) = text.split_once('=') else {
            let at_end = reader
                .fill_buf()
                .map_err(|e| Error::io(path, e))?
                .is_empty();
            return Err(Error::format(
                path,
                if at_end {
                    FormatProblem::Truncated
                } else {
                    FormatProblem::Corrupt
                },
                format!(
                    "header line {line_number} is not `Key = Value`: {:?}",
                    truncate_for_message(text)
                ),
            ));
        };
        let key = key.trim();
        let value = value.trim();
        if let Some((index, name)) = split_frame_key(key) {
            frame_fields.push(index, name, value);
        } else if key == "ElementDataFile" {
            data_file = Some(value.to_string());
            break;
        } else {
            global.insert(key.to_string(), value.to_string());
        }
    }
    let Some(data_file) = data_file else {
        return Err(Error::format(
            path,
            FormatProblem::Truncated,
            "file ends before the header's ElementDataFile line (truncated?)",
        ));
    };

    if let Some(object_type) = global.get("ObjectType")
        && !object_type.eq_ignore_ascii_case("Image")
    {
        return Err(Error::format(
            path,
            FormatProblem::Unsupported,
            format!("ObjectType = {object_type} (only Image is read)"),
        ));
    }
    let dims = parse_dims(&global, path)?;
    let (element, element_is_other) = match global.get("ElementType") {
        None => {
            return Err(Error::format(
                path,
                FormatProblem::MissingField,
                "ElementType is missing",
            ));
        }
        Some(name) => parse_element_type(name, path)?,
    };
    let channels = match global.get("ElementNumberOfChannels") {
        None => 1,
        Some(v) => v.parse::<usize>().ok().filter(|&c| c >= 1).ok_or_else(|| {
            Error::format(
                path,
                FormatProblem::BadValue,
                format!("ElementNumberOfChannels = {v:?} is not a positive integer"),
            )
        })?,
    };
    let big_endian = match global
        .get("BinaryDataByteOrderMSB")
        .or_else(|| global.get("ElementByteOrderMSB"))
    {
        None => false,
        Some(v) => parse_bool(v, "BinaryDataByteOrderMSB", path)?,
    };
    let compressed = match global.get("CompressedData") {
        None => false,
        Some(v) => parse_bool(v, "CompressedData", path)?,
    };
    let compressed_size = match global.get("CompressedDataSize") {
        None => None,
        Some(v) => Some(v.parse::<u64>().map_err(|_| {
            Error::format(
                path,
                FormatProblem::BadValue,
                format!("CompressedDataSize = {v:?} is not a byte count"),
            )
        })?),
    };
    let orientation = global
        .get("UltrasoundImageOrientation")
        .cloned()
        .unwrap_or_default();

    let layout = Layout {
        width: dims[0],
        height: dims[1],
        channels,
        frames: dims[2],
        element,
        big_endian,
    };
    // Tracker-only recordings carry no image: MET_OTHER, or a 0 x 0 / 1 x 1 placeholder.
    let tracking_only =
        element_is_other || dims[0] == 0 || dims[1] == 0 || (dims[0] == 1 && dims[1] == 1);

    let bytes = if tracking_only {
        // No pixels are read, so the frame count is only bounded by the per-frame fields present.
        if layout.frames > frame_fields.len() + 1 {
            return Err(Error::format(
                path,
                FormatProblem::SizeMismatch,
                format!(
                    "tracking-only file claims {} frames but has only {} per-frame fields",
                    layout.frames,
                    frame_fields.len()
                ),
            ));
        }
        None
    } else {
        let expected = layout.total_bytes(path)?;
        let compression = if compressed {
            Compression::Zlib
        } else {
            Compression::None
        };
        if data_file.eq_ignore_ascii_case("LOCAL") {
            let available = file_len.saturating_sub(consumed);
            Some(read_pixel_block(
                reader,
                available,
                expected,
                compression,
                compressed_size,
                path,
            )?)
        } else {
            if data_file.eq_ignore_ascii_case("LIST") || data_file.contains('%') {
                return Err(Error::format(
                    path,
                    FormatProblem::Unsupported,
                    format!("ElementDataFile = {data_file}: file lists and patterns are not read"),
                ));
            }
            let (data_path, data, available) = open_data_file(path, &data_file)?;
            Some(read_pixel_block(
                BufReader::with_capacity(1 << 16, data),
                available,
                expected,
                compression,
                compressed_size,
                &data_path,
            )?)
        }
    };

    let frames = frame_fields.build(layout.frames, &["ImageStatus"], path)?;
    let header = global
        .into_iter()
        .filter(|(k, _)| !INTERPRETED_FIELDS.contains(&k.as_str()))
        .collect();
    assemble(
        Assembled {
            layout,
            orientation,
            frames,
            bytes,
            header,
        },
        path,
    )
}

/// `name` relative to the folder of `header_path` (absolute names are kept).
pub(crate) fn sibling_path(header_path: &Path, name: &str) -> PathBuf {
    let name = Path::new(name);
    if name.is_absolute() {
        return name.to_path_buf();
    }
    match header_path.parent() {
        Some(dir) => dir.join(name),
        None => name.to_path_buf(),
    }
}

/// Opens the detached data file `name` of header `header` (relative to its folder) and returns its path,
/// handle and length. Only regular files: an empty name (the header's folder), a folder or a device such
/// as `/dev/zero` would otherwise be read without end.
pub(crate) fn open_data_file(header: &Path, name: &str) -> Result<(PathBuf, File, u64)> {
    if name.trim().is_empty() {
        return Err(Error::format(
            header,
            FormatProblem::MissingField,
            "the data file name is empty (expected LOCAL or a file name)",
        ));
    }
    let data_path = sibling_path(header, name);
    let data = File::open(&data_path).map_err(|e| data_file_error(header, &data_path, e))?;
    let meta = data
        .metadata()
        .map_err(|e| data_file_error(header, &data_path, e))?;
    if !meta.is_file() {
        return Err(Error::format(
            header,
            FormatProblem::BadValue,
            format!("data file {} is not a regular file", data_path.display()),
        ));
    }
    Ok((data_path, data, meta.len()))
}

/// A detached data file that cannot be opened: named in the error of the header file.
pub(crate) fn data_file_error(header: &Path, data: &Path, e: std::io::Error) -> Error {
    if e.kind() == std::io::ErrorKind::NotFound {
        Error::format(
            header,
            FormatProblem::MissingField,
            format!("data file {} does not exist", data.display()),
        )
    } else {
        Error::format(
            header,
            FormatProblem::BadValue,
            format!("data file {} cannot be opened: {e}", data.display()),
        )
    }
}

/// `[width, height, frames]` from NDims / DimSize.
fn parse_dims(global: &BTreeMap<String, String>, path: &Path) -> Result<[usize; 3]> {
    let dim_size = global
        .get("DimSize")
        .ok_or_else(|| Error::format(path, FormatProblem::MissingField, "DimSize is missing"))?;
    let dims: Vec<usize> = dim_size
        .split_ascii_whitespace()
        .map(|t| t.parse::<usize>())
        .collect::<std::result::Result<_, _>>()
        .map_err(|_| {
            Error::format(
                path,
                FormatProblem::BadValue,
                format!("DimSize = {dim_size:?} is not a list of sizes"),
            )
        })?;
    let ndims = match global.get("NDims") {
        None => dims.len(),
        Some(v) => v.parse::<usize>().map_err(|_| {
            Error::format(
                path,
                FormatProblem::BadValue,
                format!("NDims = {v:?} is not a number"),
            )
        })?,
    };
    if dims.len() != ndims {
        return Err(Error::format(
            path,
            FormatProblem::BadValue,
            format!("NDims = {ndims} but DimSize has {} values", dims.len()),
        ));
    }
    match ndims {
        2 => Ok([dims[0], dims[1], 1]),
        3 => Ok([dims[0], dims[1], dims[2]]),
        _ => Err(Error::format(
            path,
            FormatProblem::Unsupported,
            format!("NDims = {ndims} (only 2D images and 3D sequences are read)"),
        )),
    }
}

/// Element type, and whether it was MET_OTHER (no image).
fn parse_element_type(name: &str, path: &Path) -> Result<(ElementType, bool)> {
    Ok(match name.trim() {
        "MET_UCHAR" => (ElementType::U8, false),
        "MET_CHAR" => (ElementType::I8, false),
        "MET_USHORT" => (ElementType::U16, false),
        "MET_SHORT" => (ElementType::I16, false),
        "MET_FLOAT" => (ElementType::F32, false),
        "MET_OTHER" => (ElementType::U8, true),
        other => {
            return Err(Error::format(
                path,
                FormatProblem::Unsupported,
                format!(
                    "ElementType = {other} (read: MET_UCHAR, MET_CHAR, MET_USHORT, MET_SHORT, MET_FLOAT)"
                ),
            ));
        }
    })
}

fn parse_bool(value: &str, key: &str, path: &Path) -> Result<bool> {
    match value.trim().to_ascii_lowercase().as_str() {
        "true" | "1" => Ok(true),
        "false" | "0" => Ok(false),
        _ => Err(Error::format(
            path,
            FormatProblem::BadValue,
            format!("{key} = {value:?} is not True or False"),
        )),
    }
}

/// Writes a PLUS MetaImage sequence (`ElementDataFile = LOCAL`), zlib-compressed if `compress`.
/// Pixels are written as stored (MF), so `UltrasoundImageOrientation = MF`. A tracking-only sequence is
/// written with `ElementType = MET_OTHER` and no pixel data.
pub fn write_sequence(path: &Path, sequence: &TrackedSequence, compress: bool) -> Result<()> {
    let header = sequence_header_text(sequence, compress, None)?;
    let tracking_only = sequence.is_tracking_only();
    if !tracking_only {
        let expected = sequence
            .frame_len()
            .checked_mul(sequence.frames.len())
            .ok_or_else(|| Error::InvalidInput("sequence size overflows".into()))?;
        if sequence.pixels.len() != expected {
            return Err(Error::InvalidInput(format!(
                "sequence has {} pixel values but {} x {} x {} channels x {} frames needs {expected}",
                sequence.pixels.len(),
                sequence.width,
                sequence.height,
                sequence.channels,
                sequence.frames.len()
            )));
        }
    }
    if compress && !tracking_only {
        let mut encoder =
            flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::default());
        write_pixels_le(&mut encoder, &sequence.pixels).map_err(|e| Error::io(path, e))?;
        let stream = encoder.finish().map_err(|e| Error::io(path, e))?;
        let header = sequence_header_text(sequence, compress, Some(stream.len()))?;
        write_atomic(path, |w| {
            w.write_all(header.as_bytes())?;
            w.write_all(&stream)
        })
    } else {
        write_atomic(path, |w| {
            w.write_all(header.as_bytes())?;
            if !tracking_only {
                write_pixels_le(w, &sequence.pixels)?;
            }
            Ok(())
        })
    }
}

fn write_pixels_le<W: Write>(w: &mut W, pixels: &PixelData) -> std::io::Result<()> {
    const CHUNK: usize = 1 << 15;
    match pixels {
        PixelData::U8(v) => w.write_all(v),
        PixelData::I8(v) => {
            for c in v.chunks(CHUNK) {
                let b: Vec<u8> = c.iter().map(|&x| x as u8).collect();
                w.write_all(&b)?;
            }
            Ok(())
        }
        PixelData::U16(v) => {
            for c in v.chunks(CHUNK) {
                let b: Vec<u8> = c.iter().flat_map(|x| x.to_le_bytes()).collect();
                w.write_all(&b)?;
            }
            Ok(())
        }
        PixelData::I16(v) => {
            for c in v.chunks(CHUNK) {
                let b: Vec<u8> = c.iter().flat_map(|x| x.to_le_bytes()).collect();
                w.write_all(&b)?;
            }
            Ok(())
        }
        PixelData::F32(v) => {
            for c in v.chunks(CHUNK) {
                let b: Vec<u8> = c.iter().flat_map(|x| x.to_le_bytes()).collect();
                w.write_all(&b)?;
            }
            Ok(())
        }
    }
}

/// A name that can stand left of ` = ` in a MetaImage header and read back as the same key.
fn check_key(key: &str) -> Result<()> {
    if key.is_empty()
        || key
            .chars()
            .any(|c| c.is_whitespace() || c == '=' || c.is_control())
    {
        return Err(Error::InvalidInput(format!(
            "field name {key:?} cannot be written to a MetaImage header"
        )));
    }
    Ok(())
}

fn check_value(key: &str, value: &str) -> Result<()> {
    if value.chars().any(|c| c == '\n' || c == '\r') {
        return Err(Error::InvalidInput(format!(
            "value of {key} contains a line break and cannot be written to a MetaImage header"
        )));
    }
    Ok(())
}

fn format_matrix(m: &glam::DMat4) -> String {
    mat4_to_row_major(m)
        .iter()
        .map(|v| format!("{v}"))
        .collect::<Vec<_>>()
        .join(" ")
}

/// The header text, ending with `ElementDataFile = LOCAL\n`.
fn sequence_header_text(
    sequence: &TrackedSequence,
    compress: bool,
    compressed_size: Option<usize>,
) -> Result<String> {
    use std::fmt::Write as _;
    let tracking_only = sequence.is_tracking_only();
    let get = |key: &str, default: &str| -> String {
        sequence
            .header
            .get(key)
            .cloned()
            .unwrap_or_else(|| default.to_string())
    };
    let mut h = String::new();
    let mut line = |key: &str, value: &str| -> Result<()> {
        check_key(key)?;
        check_value(key, value)?;
        writeln!(h, "{key} = {value}").expect("write to String");
        Ok(())
    };
    line("ObjectType", "Image")?;
    line("NDims", "3")?;
    line(
        "AnatomicalOrientation",
        &get("AnatomicalOrientation", "RAI"),
    )?;
    line("BinaryData", "True")?;
    line("BinaryDataByteOrderMSB", "False")?;
    line("CenterOfRotation", &get("CenterOfRotation", "0 0 0"))?;
    let compressed = compress && !tracking_only;
    line("CompressedData", if compressed { "True" } else { "False" })?;
    if compressed {
        line(
            "CompressedDataSize",
            &compressed_size.unwrap_or(0).to_string(),
        )?;
    }
    line(
        "DimSize",
        &format!(
            "{} {} {}",
            sequence.width,
            sequence.height,
            sequence.frames.len()
        ),
    )?;
    line(
        "ElementNumberOfChannels",
        &sequence.channels.max(1).to_string(),
    )?;
    line("ElementSpacing", &get("ElementSpacing", "1 1 1"))?;
    line(
        "ElementType",
        if tracking_only {
            "MET_OTHER"
        } else {
            sequence.pixels.element_type().metaimage_name()
        },
    )?;
    // NDims is always 3 here, so a kept Kinds of another length (from a 2D file) is replaced.
    let kinds = get("Kinds", "domain domain list");
    let kinds = if kinds.split_ascii_whitespace().count() == 3 {
        kinds
    } else {
        "domain domain list".to_string()
    };
    line("Kinds", &kinds)?;
    line("Offset", &get("Offset", "0 0 0"))?;
    line(
        "TransformMatrix",
        &get("TransformMatrix", "1 0 0 0 1 0 0 0 1"),
    )?;
    line("UltrasoundImageOrientation", "MF")?;
    for (key, value) in &sequence.header {
        if WRITER_FIELDS.contains(&key.as_str()) {
            continue;
        }
        // Header fields carried over from other formats (NRRD `space directions`) are not MetaImage keys.
        if key.chars().any(|c| c.is_whitespace() || c == '=') {
            continue;
        }
        line(key, value)?;
    }
    for (index, frame) in sequence.frames.iter().enumerate() {
        let prefix = format!("Seq_Frame{index:04}_");
        for (name, t) in &frame.transforms {
            line(
                &format!("{prefix}{name}Transform"),
                &format_matrix(&t.matrix),
            )?;
            line(
                &format!("{prefix}{name}TransformStatus"),
                if t.valid { "OK" } else { "INVALID" },
            )?;
        }
        if let Some(t) = frame.timestamp_s {
            line(&format!("{prefix}Timestamp"), &format!("{t}"))?;
        }
        line(
            &format!("{prefix}ImageStatus"),
            if frame.image_valid { "OK" } else { "INVALID" },
        )?;
        for (name, value) in &frame.fields {
            line(&format!("{prefix}{name}"), value)?;
        }
    }
    line("ElementDataFile", "LOCAL")?;
    Ok(h)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::sequence::{FrameTransform, TrackedFrame, mat4_from_row_major};

    fn write_file(dir: &Path, name: &str, header: &str, data: &[u8]) -> PathBuf {
        let p = dir.join(name);
        let mut bytes = header.as_bytes().to_vec();
        bytes.extend_from_slice(data);
        std::fs::write(&p, bytes).unwrap();
        p
    }

    #[test]
    fn reads_any_order_crlf_padded_and_flips_mn() {
        let dir = tempfile::tempdir().unwrap();
        let header = "ObjectType = Image\r\nElementType = MET_UCHAR\r\nDimSize =  3   2    1  \r\n\
            UltrasoundImageOrientation = MN\r\nSeq_Frame0000_Timestamp = 1.5\r\n\
            NDims = 3\r\nElementDataFile = LOCAL\r\n";
        let p = write_file(dir.path(), "a.mha", header, &[0, 1, 2, 10, 11, 12]);
        let s = read_sequence(&p).unwrap();
        assert_eq!((s.width, s.height, s.frames.len()), (3, 2, 1));
        assert_eq!(s.pixels, PixelData::U8(vec![10, 11, 12, 0, 1, 2]));
        assert_eq!(s.orientation, "MN");
        assert_eq!(s.frames[0].timestamp_s, Some(1.5));
        assert!(s.frames[0].image_valid);
    }

    #[test]
    fn reads_big_endian_short_2d_and_float() {
        let dir = tempfile::tempdir().unwrap();
        let header = "ObjectType = Image\nNDims = 2\nDimSize = 2 1\nElementType = MET_SHORT\n\
            BinaryDataByteOrderMSB = True\nElementDataFile = LOCAL\n";
        let p = write_file(dir.path(), "b.mha", header, &[0xff, 0xfe, 0x00, 0x05]);
        let s = read_sequence(&p).unwrap();
        assert_eq!(s.pixels, PixelData::I16(vec![-2, 5]));
        assert_eq!(s.frames.len(), 1);

        let header = "ObjectType = Image\nNDims = 3\nDimSize = 1 2 1\nElementType = MET_FLOAT\n\
            ElementDataFile = LOCAL\n";
        let data: Vec<u8> = [1.5f32, -2.0]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let p = write_file(dir.path(), "c.mha", header, &data);
        let s = read_sequence(&p).unwrap();
        assert_eq!(s.pixels, PixelData::F32(vec![1.5, -2.0]));
    }

    #[test]
    fn reads_channels_and_char() {
        let dir = tempfile::tempdir().unwrap();
        let header = "ObjectType = Image\nNDims = 3\nDimSize = 2 1 1\nElementType = MET_CHAR\n\
            ElementNumberOfChannels = 2\nUltrasoundImageOrientation = UF\nElementDataFile = LOCAL\n";
        let p = write_file(dir.path(), "d.mha", header, &[1, 2, 0xff, 4]);
        let s = read_sequence(&p).unwrap();
        assert_eq!(s.channels, 2);
        assert_eq!(s.pixels, PixelData::I8(vec![-1, 4, 1, 2]));
    }

    #[test]
    fn reads_mhd_with_zraw_and_big_endian_float() {
        use std::io::Write as _;
        let dir = tempfile::tempdir().unwrap();
        let values = [0.5f32, -1.25, 3.0, 1e-3, 7.0, -0.0];
        let raw: Vec<u8> = values.iter().flat_map(|v| v.to_be_bytes()).collect();
        let mut enc = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::fast());
        enc.write_all(&raw).unwrap();
        let z = enc.finish().unwrap();
        std::fs::write(dir.path().join("img.zraw"), &z).unwrap();
        let header = format!(
            "ObjectType = Image\nNDims = 3\nDimSize = 3 1 2\nElementType = MET_FLOAT\n\
             ElementByteOrderMSB = True\nCompressedData = True\nCompressedDataSize = {}\n\
             ElementDataFile = img.zraw\n",
            z.len()
        );
        let p = write_file(dir.path(), "img.mhd", &header, &[]);
        let s = read_sequence(&p).unwrap();
        assert_eq!(s.pixels, PixelData::F32(values.to_vec()));
        assert_eq!(s.frames.len(), 2);
        // A CompressedDataSize larger than the data file is a truncated file.
        let lying = header.replace(
            &format!("CompressedDataSize = {}", z.len()),
            &format!("CompressedDataSize = {}", z.len() + 10),
        );
        let p = write_file(dir.path(), "lying.mhd", &lying, &[]);
        let e = read_sequence(&p).unwrap_err();
        assert_eq!(e.problem(), Some(FormatProblem::Truncated));
        assert!(e.to_string().contains("img.zraw"));
    }

    #[test]
    fn header_errors_are_typed() {
        let dir = tempfile::tempdir().unwrap();
        let cases = [
            (
                "ObjectType = Image\nNDims = 3\nElementType = MET_UCHAR\nElementDataFile = LOCAL\n",
                FormatProblem::MissingField,
            ),
            (
                "ObjectType = Image\nNDims = 3\nDimSize = 1 2\nElementType = MET_UCHAR\nElementDataFile = LOCAL\n",
                FormatProblem::BadValue,
            ),
            (
                "ObjectType = Image\nNDims = 4\nDimSize = 1 2 3 4\nElementType = MET_UCHAR\nElementDataFile = LOCAL\n",
                FormatProblem::Unsupported,
            ),
            (
                "ObjectType = Image\nNDims = 3\nDimSize = 2 2 1\nElementType = MET_DOUBLE\nElementDataFile = LOCAL\n",
                FormatProblem::Unsupported,
            ),
            (
                "ObjectType = Image\nNDims = 3\nDimSize = 2 -2 1\nElementType = MET_UCHAR\nElementDataFile = LOCAL\n",
                FormatProblem::BadValue,
            ),
            (
                "ObjectType = Image\nNDims = 3\nDimSize = 2 2 1\nElementType = MET_UCHAR\nCompressedData = maybe\nElementDataFile = LOCAL\n",
                FormatProblem::BadValue,
            ),
            (
                "ObjectType = Image\nNDims = 3\nDimSize = 2 2 1\nElementType = MET_UCHAR\nUltrasoundImageOrientation = QQ\nElementDataFile = LOCAL\n",
                FormatProblem::BadValue,
            ),
            (
                "ObjectType = Image\nNDims = 3\nDimSize = 2 2 1\nElementType = MET_UCHAR\nElementDataFile = LIST\n",
                FormatProblem::Unsupported,
            ),
            (
                "ObjectType = Mesh\nNDims = 3\nDimSize = 2 2 1\nElementType = MET_UCHAR\nElementDataFile = LOCAL\n",
                FormatProblem::Unsupported,
            ),
            ("\u{89}PNG\n", FormatProblem::Unsupported),
        ];
        for (i, (header, problem)) in cases.iter().enumerate() {
            let p = write_file(dir.path(), &format!("h{i}.mha"), header, &[1, 2, 3, 4]);
            let e = read_sequence(&p).unwrap_err();
            assert_eq!(e.problem(), Some(*problem), "case {i}: {e}");
            assert!(
                e.to_string().contains(&format!("h{i}.mha")),
                "case {i}: {e}"
            );
        }
    }

    #[test]
    fn tracking_only_met_other() {
        let dir = tempfile::tempdir().unwrap();
        let header = "ObjectType = Image\nNDims = 3\nDimSize = 0 0 2\nElementType = MET_OTHER\n\
            Seq_Frame0000_ToolToTrackerTransform = 1 0 0 1 0 1 0 2 0 0 1 3 0 0 0 1\n\
            Seq_Frame0001_ToolToTrackerTransformStatus = INVALID\n\
            Seq_Frame0001_ToolToTrackerTransform = nan 0 0 1 0 1 0 2 0 0 1 3 0 0 0 1\n\
            ElementDataFile = LOCAL\n";
        let p = write_file(dir.path(), "t.mha", header, &[]);
        let s = read_sequence(&p).unwrap();
        assert!(s.is_tracking_only());
        assert_eq!(s.frames.len(), 2);
        let t = s.frames[0].transforms["ToolToTracker"];
        assert!(t.valid);
        assert_eq!(t.matrix.w_axis.truncate(), glam::DVec3::new(1.0, 2.0, 3.0));
        assert!(!s.frames[1].transforms["ToolToTracker"].valid);
    }

    #[test]
    fn writer_round_trip_all_types() {
        let dir = tempfile::tempdir().unwrap();
        let mut frame = TrackedFrame {
            timestamp_s: Some(12.345678),
            image_valid: true,
            ..Default::default()
        };
        let m = mat4_from_row_major(&[
            0.1, 0.2, 0.3, 4.0, 0.5, 0.6, 0.7, 8.0, 0.9, 1.0, 1.1, 12.0, 0.0, 0.0, 0.0, 1.0,
        ]);
        frame.transforms.insert(
            "ProbeToTracker".into(),
            FrameTransform {
                matrix: m,
                valid: true,
            },
        );
        frame.transforms.insert(
            "ReferenceToTracker".into(),
            FrameTransform {
                matrix: m.inverse(),
                valid: false,
            },
        );
        frame.fields.insert("FrameNumber".into(), "17".into());
        let mut second = frame.clone();
        second.image_valid = false;
        second.timestamp_s = None;
        let pixel_sets = [
            PixelData::U8((0..12).map(|v| v as u8).collect()),
            PixelData::I8((0..12).map(|v| v as i8 - 6).collect()),
            PixelData::U16((0..12).map(|v| v * 1000).collect()),
            PixelData::I16((0..12).map(|v| v * -1000).collect()),
            PixelData::F32((0..12).map(|v| v as f32 * 0.25).collect()),
        ];
        for pixels in pixel_sets {
            let mut header = BTreeMap::new();
            header.insert("UltrasoundImageType".to_string(), "BRIGHTNESS".to_string());
            header.insert("Kinds".to_string(), "domain domain list".to_string());
            let seq = TrackedSequence {
                width: 3,
                height: 2,
                channels: 1,
                orientation: "MF".into(),
                frames: vec![frame.clone(), second.clone()],
                pixels,
                header,
            };
            for compress in [false, true] {
                let p = dir.path().join("rt.mha");
                write_sequence(&p, &seq, compress).unwrap();
                let back = read_sequence(&p).unwrap();
                let mut expected = seq.clone();
                // The writer's own compatibility fields come back as header fields.
                for k in [
                    "AnatomicalOrientation",
                    "CenterOfRotation",
                    "ElementSpacing",
                    "Offset",
                    "TransformMatrix",
                ] {
                    expected
                        .header
                        .insert(k.into(), back.header.get(k).cloned().unwrap());
                }
                assert_eq!(back, expected);
            }
        }
    }

    #[test]
    fn writer_rejects_bad_names_and_sizes() {
        let dir = tempfile::tempdir().unwrap();
        let mut seq = TrackedSequence {
            width: 2,
            height: 2,
            channels: 1,
            orientation: "MF".into(),
            frames: vec![TrackedFrame::default()],
            pixels: PixelData::U8(vec![0; 3]),
            header: BTreeMap::new(),
        };
        let p = dir.path().join("bad.mha");
        assert!(matches!(
            write_sequence(&p, &seq, false),
            Err(Error::InvalidInput(_))
        ));
        seq.pixels = PixelData::U8(vec![0; 4]);
        seq.frames[0].fields.insert("Bad Name".into(), "1".into());
        assert!(matches!(
            write_sequence(&p, &seq, false),
            Err(Error::InvalidInput(_))
        ));
        assert!(!p.exists());
    }
}
