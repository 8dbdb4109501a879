//! Volumes as MetaImage `.mha`, laid out as PLUS's `SaveReconstructedVolumeToMetafile` writes them
//! (identity `TransformMatrix`, `Offset` = origin, `AnatomicalOrientation = RAI`, LOCAL data,
//! optionally one zlib stream), so 3D Slicer opens them in the same Reference frame.

use std::io::{Read, Write};
use std::path::Path;

use flate2::Compression;
use flate2::read::ZlibDecoder;
use flate2::write::ZlibEncoder;
use glam::DVec3;

use super::{ReconstructionStats, Volume, VoxelValues};
use crate::io::ElementType;
use crate::io::atomic::write_atomic;
use crate::{Error, FormatProblem, Result};

/// Little-endian bytes of the volume in its element type (integer types rounded and clamped).
fn volume_bytes(volume: &Volume) -> Vec<u8> {
    match (&volume.values, volume.element_type) {
        (VoxelValues::U8(v), _) => v.clone(),
        (VoxelValues::F32(v), t) => {
            let mut out = Vec::with_capacity(v.len() * t.size_bytes());
            for &x in v {
                let r = (x as f64).round();
                match t {
                    ElementType::U8 => out.push(r.clamp(0.0, 255.0) as u8),
                    ElementType::I8 => out.push(r.clamp(-128.0, 127.0) as i8 as u8),
                    ElementType::U16 => {
                        out.extend_from_slice(&(r.clamp(0.0, 65535.0) as u16).to_le_bytes())
                    }
                    ElementType::I16 => {
                        out.extend_from_slice(&(r.clamp(-32768.0, 32767.0) as i16).to_le_bytes())
                    }
                    ElementType::F32 => out.extend_from_slice(&x.to_le_bytes()),
                }
            }
            out
        }
    }
}

/// Writes `volume` as a MetaImage `.mha` (zlib-compressed data if `compress`), atomically.
pub fn write_volume_mha(path: &Path, volume: &Volume, compress: bool) -> Result<()> {
    let n = volume.len();
    if volume.values.len() != n || n == 0 {
        return Err(Error::InvalidInput(format!(
            "volume holds {} values for {}x{}x{} voxels",
            volume.values.len(),
            volume.dims[0],
            volume.dims[1],
            volume.dims[2]
        )));
    }
    if !(volume.origin_mm.is_finite()
        && volume.spacing_mm.is_finite()
        && volume.spacing_mm.min_element() > 0.0)
    {
        return Err(Error::InvalidInput(
            "volume origin and spacing must be finite, spacing positive".into(),
        ));
    }
    let raw = volume_bytes(volume);
    let data = if compress {
        let mut enc = ZlibEncoder::new(Vec::new(), Compression::default());
        enc.write_all(&raw).map_err(|e| Error::io(path, e))?;
        enc.finish().map_err(|e| Error::io(path, e))?
    } else {
        raw
    };
    let o = volume.origin_mm;
    let s = volume.spacing_mm;
    let mut header = String::new();
    header.push_str("ObjectType = Image\nNDims = 3\nBinaryData = True\n");
    header.push_str("BinaryDataByteOrderMSB = False\n");
    if compress {
        header.push_str(&format!(
            "CompressedData = True\nCompressedDataSize = {}\n",
            data.len()
        ));
    } else {
        header.push_str("CompressedData = False\n");
    }
    header.push_str("TransformMatrix = 1 0 0 0 1 0 0 0 1\n");
    header.push_str(&format!("Offset = {} {} {}\n", o.x, o.y, o.z));
    header.push_str("CenterOfRotation = 0 0 0\nAnatomicalOrientation = RAI\n");
    header.push_str(&format!("ElementSpacing = {} {} {}\n", s.x, s.y, s.z));
    header.push_str(&format!(
        "DimSize = {} {} {}\n",
        volume.dims[0], volume.dims[1], volume.dims[2]
    ));
    header.push_str(&format!(
        "ElementType = {}\n",
        volume.element_type.metaimage_name()
    ));
    header.push_str("ElementDataFile = LOCAL\n");
    write_atomic(path, |w| {
        w.write_all(header.as_bytes())?;
        w.write_all(&data)
    })
}

fn bad(path: &Path, problem: FormatProblem, message: impl Into<String>) -> Error {
    Error::format(path, problem, message)
}

fn numbers(path: &Path, key: &str, value: &str, count: usize) -> Result<Vec<f64>> {
    let v: Vec<f64> = value
        .split_whitespace()
        .map(|t| t.parse::<f64>())
        .collect::<std::result::Result<_, _>>()
        .map_err(|_| {
            bad(
                path,
                FormatProblem::BadValue,
                format!("{key} = '{value}' is not a list of numbers"),
            )
        })?;
    if v.len() < count || v.iter().any(|x| !x.is_finite()) {
        return Err(bad(
            path,
            FormatProblem::BadValue,
            format!("{key} = '{value}': expected {count} finite numbers"),
        ));
    }
    Ok(v)
}

/// Reads a scalar 3D (or 2D) MetaImage volume (`.mha` with LOCAL data, or `.mhd` + data file),
/// raw or zlib-compressed. The accumulation buffer of the result is empty.
pub fn read_volume_mha(path: &Path) -> Result<Volume> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let mut pos = 0usize;
    let mut fields: Vec<(String, String)> = Vec::new();
    let mut data_file = None;
    while pos < bytes.len() {
        let end = bytes[pos..]
            .iter()
            .position(|&b| b == b'\n')
            .map(|e| pos + e)
            .unwrap_or(bytes.len());
        let line = std::str::from_utf8(&bytes[pos..end])
            .map_err(|_| bad(path, FormatProblem::Corrupt, "header line is not text"))?
            .trim_end_matches('\r');
        pos = (end + 1).min(bytes.len());
        if line.trim().is_empty() {
            continue;
        }
        let Some((key, value)) = line.split_once('=') else {
            return Err(bad(
                path,
                FormatProblem::Corrupt,
                format!("header line '{line}' has no '='"),
            ));
        };
        let (key, value) = (key.trim().to_string(), value.trim().to_string());
        if key == "ElementDataFile" {
            data_file = Some(value);
            break;
        }
        fields.push((key, value));
        if fields.len() > 100_000 {
            return Err(bad(path, FormatProblem::Corrupt, "header never ends"));
        }
    }
    let data_file = data_file
        .ok_or_else(|| bad(path, FormatProblem::MissingField, "no ElementDataFile line"))?;
    let get = |k: &str| {
        fields
            .iter()
            .find(|(key, _)| key == k)
            .map(|(_, v)| v.as_str())
    };
    let ndims = get("NDims")
        .ok_or_else(|| bad(path, FormatProblem::MissingField, "no NDims"))?
        .parse::<usize>()
        .map_err(|_| bad(path, FormatProblem::BadValue, "NDims is not a number"))?;
    if !(2..=3).contains(&ndims) {
        return Err(bad(
            path,
            FormatProblem::Unsupported,
            format!("NDims = {ndims}: only 2D and 3D volumes are read"),
        ));
    }
    let dim_text =
        get("DimSize").ok_or_else(|| bad(path, FormatProblem::MissingField, "no DimSize"))?;
    let dim_values: Vec<usize> = dim_text
        .split_whitespace()
        .map(|t| t.parse::<usize>())
        .collect::<std::result::Result<_, _>>()
        .map_err(|_| {
            bad(
                path,
                FormatProblem::BadValue,
                format!("DimSize = '{dim_text}'"),
            )
        })?;
    if dim_values.len() < ndims || dim_values[..ndims].contains(&0) {
        return Err(bad(
            path,
            FormatProblem::BadValue,
            format!("DimSize = '{dim_text}' for NDims = {ndims}"),
        ));
    }
    let dims = [
        dim_values[0],
        dim_values[1],
        if ndims == 3 { dim_values[2] } else { 1 },
    ];
    if get("ElementNumberOfChannels").is_some_and(|c| c.trim() != "1") {
        return Err(bad(
            path,
            FormatProblem::Unsupported,
            "only single-channel volumes are read",
        ));
    }
    if get("BinaryDataByteOrderMSB")
        .or(get("ElementByteOrderMSB"))
        .is_some_and(|v| v.eq_ignore_ascii_case("true"))
    {
        return Err(bad(
            path,
            FormatProblem::Unsupported,
            "big-endian data is not supported",
        ));
    }
    let element_type = match get("ElementType") {
        Some("MET_UCHAR") => ElementType::U8,
        Some("MET_CHAR") => ElementType::I8,
        Some("MET_USHORT") => ElementType::U16,
        Some("MET_SHORT") => ElementType::I16,
        Some("MET_FLOAT") => ElementType::F32,
        Some(other) => {
            return Err(bad(
                path,
                FormatProblem::Unsupported,
                format!("ElementType {other} is not supported"),
            ));
        }
        None => return Err(bad(path, FormatProblem::MissingField, "no ElementType")),
    };
    if let Some(m) = get("TransformMatrix") {
        let m = numbers(path, "TransformMatrix", m, ndims * ndims)?;
        let identity = (0..ndims * ndims)
            .all(|i| (m[i] - if i % (ndims + 1) == 0 { 1.0 } else { 0.0 }).abs() < 1e-9);
        if !identity {
            return Err(bad(
                path,
                FormatProblem::Unsupported,
                "rotated volumes (non-identity TransformMatrix) are not supported",
            ));
        }
    }
    let spacing = match get("ElementSpacing") {
        Some(v) => numbers(path, "ElementSpacing", v, ndims)?,
        None => vec![1.0; 3],
    };
    if spacing[..ndims].iter().any(|&s| s <= 0.0) {
        return Err(bad(
            path,
            FormatProblem::BadValue,
            "ElementSpacing must be positive",
        ));
    }
    let origin = match get("Offset").or(get("Origin")).or(get("Position")) {
        Some(v) => numbers(path, "Offset", v, ndims)?,
        None => vec![0.0; 3],
    };
    let count = dims
        .iter()
        .try_fold(1usize, |acc, &d| acc.checked_mul(d))
        .and_then(|n| n.checked_mul(element_type.size_bytes()).map(|b| (n, b)));
    let (voxels, raw_len) = count.ok_or_else(|| {
        bad(
            path,
            FormatProblem::SizeMismatch,
            "DimSize is absurdly large",
        )
    })?;

    let external;
    let payload: &[u8] = if data_file.eq_ignore_ascii_case("LOCAL") {
        &bytes[pos..]
    } else {
        let data_path = path.parent().unwrap_or(Path::new(".")).join(&data_file);
        // Only a regular file: an empty name (the folder) or a device like /dev/zero never ends.
        if data_file.trim().is_empty() || !data_path.is_file() {
            return Err(bad(
                path,
                FormatProblem::MissingField,
                format!(
                    "data file {} is not a readable regular file",
                    data_path.display()
                ),
            ));
        }
        external = std::fs::read(&data_path).map_err(|e| Error::io(&data_path, e))?;
        &external
    };
    let compressed = get("CompressedData").is_some_and(|v| v.eq_ignore_ascii_case("true"));
    let raw: Vec<u8> = if compressed {
        let size = match get("CompressedDataSize") {
            Some(s) => s.parse::<usize>().map_err(|_| {
                bad(
                    path,
                    FormatProblem::BadValue,
                    "CompressedDataSize is not a number",
                )
            })?,
            None => payload.len(),
        };
        if size > payload.len() {
            return Err(bad(
                path,
                FormatProblem::Truncated,
                format!(
                    "CompressedDataSize = {size} but only {} bytes follow the header",
                    payload.len()
                ),
            ));
        }
        let mut out = Vec::new();
        // Never inflate beyond what the header promises (+1 to detect excess).
        ZlibDecoder::new(&payload[..size])
            .take(raw_len as u64 + 1)
            .read_to_end(&mut out)
            .map_err(|e| bad(path, FormatProblem::Corrupt, format!("zlib data: {e}")))?;
        if out.len() != raw_len {
            return Err(bad(
                path,
                FormatProblem::SizeMismatch,
                format!(
                    "data inflates to {} bytes, DimSize needs {raw_len}",
                    out.len()
                ),
            ));
        }
        out
    } else {
        if payload.len() < raw_len {
            return Err(bad(
                path,
                FormatProblem::Truncated,
                format!("{} data bytes, DimSize needs {raw_len}", payload.len()),
            ));
        }
        payload[..raw_len].to_vec()
    };
    let values = match element_type {
        ElementType::U8 => VoxelValues::U8(raw),
        ElementType::I8 => VoxelValues::F32(raw.iter().map(|&b| b as i8 as f32).collect()),
        ElementType::U16 => VoxelValues::F32(
            raw.chunks_exact(2)
                .map(|c| u16::from_le_bytes([c[0], c[1]]) as f32)
                .collect(),
        ),
        ElementType::I16 => VoxelValues::F32(
            raw.chunks_exact(2)
                .map(|c| i16::from_le_bytes([c[0], c[1]]) as f32)
                .collect(),
        ),
        ElementType::F32 => VoxelValues::F32(
            raw.chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect(),
        ),
    };
    debug_assert_eq!(values.len(), voxels);
    Ok(Volume {
        dims,
        origin_mm: DVec3::new(
            origin[0],
            origin[1],
            if ndims == 3 { origin[2] } else { 0.0 },
        ),
        spacing_mm: DVec3::new(
            spacing[0],
            spacing[1],
            if ndims == 3 { spacing[2] } else { 1.0 },
        ),
        values,
        element_type,
        accumulation: Vec::new(),
        stats: ReconstructionStats::default(),
    })
}
