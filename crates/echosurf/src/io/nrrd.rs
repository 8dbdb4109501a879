//! NRRD PLUS sequence reader (`.igs.nrrd`, raw or gzip encoding, `key:=value` custom fields).
//!
//! PLUS writes the same per-frame fields as in MetaImage (`Seq_Frame0000_ProbeToTrackerTransform:=...`),
//! except that the image status is `Seq_FrameNNNN_Status`. Sizes are checked against the bytes present
//! before anything is allocated, as in the MetaImage reader.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufReader;
use std::path::Path;

use super::metaimage::open_data_file;
use super::seq_decode::{
    Assembled, Compression, FrameFieldCollector, Layout, assemble, line_to_str, read_header_line,
    read_pixel_block, split_frame_key, truncate_for_message,
};
use super::sequence::{ElementType, TrackedSequence};
use crate::{Error, FormatProblem, Result};

/// Reads a PLUS NRRD sequence. Pixels are brought to MF orientation.
pub fn read_sequence(path: &Path) -> Result<TrackedSequence> {
    let file = File::open(path).map_err(|e| Error::io(path, e))?;
    let file_len = file.metadata().map_err(|e| Error::io(path, e))?.len();
    let mut reader = BufReader::with_capacity(1 << 16, file);
    let mut consumed: u64 = 0;

    let magic = read_header_line(&mut reader, path, &mut consumed)?
        .ok_or_else(|| Error::format(path, FormatProblem::Truncated, "empty file"))?;
    if !magic.starts_with(b"NRRD000") {
        return Err(Error::format(
            path,
            FormatProblem::Unsupported,
            "not a NRRD file (no NRRD000x magic line)",
        ));
    }

    // Basic fields (`key: value`) keyed in lower case; custom fields (`key:=value`) as written.
    let mut fields: BTreeMap<String, String> = BTreeMap::new();
    let mut custom: BTreeMap<String, String> = BTreeMap::new();
    let mut frame_fields = FrameFieldCollector::default();
    let mut ended = false;
    let mut line_number = 1usize;
    while let Some(line) = read_header_line(&mut reader, path, &mut consumed)? {
        line_number += 1;
        let text = line_to_str(&line, path)?;
        if text.is_empty() {
            ended = true;
            break;
        }
        if text.starts_with('#') {
            continue;
        }
        if let Some((key, value)) = text.split_once(":=") {
            let key = key.trim();
            let value = value.trim();
            if let Some((index, name)) = split_frame_key(key) {
                frame_fields.push(index, name, value);
            } else {
                custom.insert(key.to_string(), value.to_string());
            }
        } else if let Some((key, value)) = text.split_once(": ") {
            fields.insert(key.trim().to_ascii_lowercase(), value.trim().to_string());
        } else {
            return Err(Error::format(
                path,
                FormatProblem::Corrupt,
                format!(
                    "header line {line_number} is neither `field: value` nor `key:=value`: {:?}",
                    truncate_for_message(text)
                ),
            ));
        }
    }
    let detached = fields
        .get("data file")
        .or_else(|| fields.get("datafile"))
        .cloned();
    if !ended && detached.is_none() {
        return Err(Error::format(
            path,
            FormatProblem::Truncated,
            "header does not end with a blank line (file truncated?)",
        ));
    }

    let required = |key: &str| -> Result<&String> {
        fields.get(key).ok_or_else(|| {
            Error::format(
                path,
                FormatProblem::MissingField,
                format!("NRRD field `{key}` is missing"),
            )
        })
    };
    let dimension: usize = required("dimension")?
        .parse()
        .map_err(|_| Error::format(path, FormatProblem::BadValue, "`dimension` is not a number"))?;
    let sizes_text = required("sizes")?;
    let sizes: Vec<usize> = sizes_text
        .split_ascii_whitespace()
        .map(|t| t.parse::<usize>())
        .collect::<std::result::Result<_, _>>()
        .map_err(|_| {
            Error::format(
                path,
                FormatProblem::BadValue,
                format!("sizes = {sizes_text:?} is not a list of sizes"),
            )
        })?;
    if sizes.len() != dimension {
        return Err(Error::format(
            path,
            FormatProblem::BadValue,
            format!(
                "dimension is {dimension} but sizes has {} values",
                sizes.len()
            ),
        ));
    }
    let kinds: Vec<String> = fields
        .get("kinds")
        .map(|k| k.split_ascii_whitespace().map(str::to_string).collect())
        .unwrap_or_default();
    // A leading non-spatial axis (kinds `vector`, `RGB-color`, ...) holds the channels.
    let leading_channels = dimension == 4
        || (dimension == 3
            && kinds.first().is_some_and(|k| {
                !k.eq_ignore_ascii_case("domain") && !k.eq_ignore_ascii_case("space")
            }));
    let (channels, width, height, frames) = match (dimension, leading_channels) {
        (2, _) => (1, sizes[0], sizes[1], 1),
        (3, false) => (1, sizes[0], sizes[1], sizes[2]),
        (3, true) => (sizes[0], sizes[1], sizes[2], 1),
        (4, _) => (sizes[0], sizes[1], sizes[2], sizes[3]),
        _ => {
            return Err(Error::format(
                path,
                FormatProblem::Unsupported,
                format!("dimension {dimension} (only 2D images and 3D sequences are read)"),
            ));
        }
    };
    if channels == 0 {
        return Err(Error::format(
            path,
            FormatProblem::BadValue,
            "channel axis of size 0",
        ));
    }
    let element = parse_type(required("type")?, path)?;
    let compression = match required("encoding")?.to_ascii_lowercase().as_str() {
        "raw" => Compression::None,
        "gz" | "gzip" => Compression::Gzip,
        other => {
            return Err(Error::format(
                path,
                FormatProblem::Unsupported,
                format!("encoding {other} (read: raw, gz)"),
            ));
        }
    };
    let big_endian = match fields.get("endian").map(|e| e.to_ascii_lowercase()) {
        None => false,
        Some(e) if e == "little" => false,
        Some(e) if e == "big" => true,
        Some(e) => {
            return Err(Error::format(
                path,
                FormatProblem::BadValue,
                format!("endian {e:?} is neither little nor big"),
            ));
        }
    };
    for skip in ["line skip", "lineskip", "byte skip", "byteskip"] {
        if let Some(v) = fields.get(skip)
            && v.trim() != "0"
        {
            return Err(Error::format(
                path,
                FormatProblem::Unsupported,
                format!("`{skip}: {v}` is not supported"),
            ));
        }
    }

    let layout = Layout {
        width,
        height,
        channels,
        frames,
        element,
        big_endian,
    };
    let tracking_only = width == 0 || height == 0;
    let bytes = if tracking_only {
        if frames > frame_fields.len() + 1 {
            return Err(Error::format(
                path,
                FormatProblem::SizeMismatch,
                format!(
                    "tracking-only file claims {frames} frames but has only {} per-frame fields",
                    frame_fields.len()
                ),
            ));
        }
        None
    } else {
        let expected = layout.total_bytes(path)?;
        match detached {
            None => Some(read_pixel_block(
                reader,
                file_len.saturating_sub(consumed),
                expected,
                compression,
                None,
                path,
            )?),
            Some(name) => {
                if name.contains(' ') || name.eq_ignore_ascii_case("LIST") {
                    return Err(Error::format(
                        path,
                        FormatProblem::Unsupported,
                        format!("data file {name:?}: file lists and patterns are not read"),
                    ));
                }
                let (data_path, data, available) = open_data_file(path, &name)?;
                Some(read_pixel_block(
                    BufReader::with_capacity(1 << 16, data),
                    available,
                    expected,
                    compression,
                    None,
                    &data_path,
                )?)
            }
        }
    };

    let frames = frame_fields.build(frames, &["Status", "ImageStatus"], path)?;
    let orientation = custom
        .remove("ultrasound image orientation")
        .unwrap_or_default();
    let mut header: BTreeMap<String, String> = BTreeMap::new();
    if let Some(t) = custom.remove("ultrasound image type") {
        header.insert("UltrasoundImageType".into(), t);
    }
    for (k, v) in custom {
        header.insert(k, v);
    }
    const INTERPRETED: &[&str] = &[
        "dimension",
        "sizes",
        "type",
        "encoding",
        "endian",
        "data file",
        "datafile",
        "kinds",
    ];
    for (k, v) in fields {
        if !INTERPRETED.contains(&k.as_str()) {
            header.insert(k, v);
        }
    }
    if !kinds.is_empty() {
        header.insert("Kinds".into(), kinds.join(" "));
    }
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

fn parse_type(name: &str, path: &Path) -> Result<ElementType> {
    Ok(match name.trim() {
        "uchar" | "unsigned char" | "uint8" | "uint8_t" => ElementType::U8,
        "signed char" | "int8" | "int8_t" => ElementType::I8,
        "ushort" | "unsigned short" | "unsigned short int" | "uint16" | "uint16_t" => {
            ElementType::U16
        }
        "short" | "short int" | "signed short" | "signed short int" | "int16" | "int16_t" => {
            ElementType::I16
        }
        "float" => ElementType::F32,
        other => {
            return Err(Error::format(
                path,
                FormatProblem::Unsupported,
                format!("type {other} (read: uint8, int8, uint16, int16, float)"),
            ));
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::sequence::PixelData;
    use std::io::Write;

    #[test]
    fn reads_raw_and_gz_with_flip() {
        let dir = tempfile::tempdir().unwrap();
        let header = "NRRD0004\n# comment\ndimension: 3\ntype: uint8\nsizes: 2 2 1\nencoding: raw\n\
            endian: little\nkinds: domain domain list\nultrasound image orientation:=UNA\n\
            Seq_Frame0000_ProbeToTrackerTransform:=1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1\n\
            Seq_Frame0000_Status:=INVALID\nSeq_Frame0000_Timestamp:=3\n\n";
        let p = dir.path().join("a.nrrd");
        let mut bytes = header.as_bytes().to_vec();
        bytes.extend_from_slice(&[1, 2, 3, 4]);
        std::fs::write(&p, &bytes).unwrap();
        let s = read_sequence(&p).unwrap();
        assert_eq!(s.pixels, PixelData::U8(vec![4, 3, 2, 1]));
        assert!(!s.frames[0].image_valid);
        assert_eq!(s.frames[0].timestamp_s, Some(3.0));
        assert_eq!(s.orientation, "UNA");

        let gz_header = header.replace("encoding: raw", "encoding: gz");
        let mut enc = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
        enc.write_all(&[1, 2, 3, 4]).unwrap();
        let mut bytes = gz_header.into_bytes();
        bytes.extend_from_slice(&enc.finish().unwrap());
        let p2 = dir.path().join("b.nrrd");
        std::fs::write(&p2, &bytes).unwrap();
        assert_eq!(read_sequence(&p2).unwrap(), s);
    }

    #[test]
    fn detached_data_file() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("h.nhdr");
        std::fs::write(
            &p,
            "NRRD0004\ndimension: 2\ntype: ushort\nsizes: 2 1\nencoding: raw\nendian: big\n\
             data file: h.raw\n",
        )
        .unwrap();
        let missing = read_sequence(&p).unwrap_err();
        assert_eq!(missing.problem(), Some(FormatProblem::MissingField));
        std::fs::write(dir.path().join("h.raw"), [0u8, 1, 1, 0]).unwrap();
        let s = read_sequence(&p).unwrap();
        assert_eq!(s.pixels, PixelData::U16(vec![1, 256]));
    }

    #[test]
    fn truncated_header_and_data() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("t.nrrd");
        std::fs::write(&p, "NRRD0004\ndimension: 3\ntype: uint8\nsizes: 2 2 1\n").unwrap();
        assert_eq!(
            read_sequence(&p).unwrap_err().problem(),
            Some(FormatProblem::Truncated)
        );
        std::fs::write(
            &p,
            "NRRD0004\ndimension: 3\ntype: uint8\nsizes: 2 2 1000\nencoding: raw\n\n1234",
        )
        .unwrap();
        assert_eq!(
            read_sequence(&p).unwrap_err().problem(),
            Some(FormatProblem::Truncated)
        );
    }
}
