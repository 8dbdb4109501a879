//! PLUS device-set configuration XML: the Image->Probe calibration and the volume reconstruction settings.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::io::Read;
use std::path::Path;

use glam::DMat4;

use super::atomic::write_bytes_atomic;
use super::sequence::{Calibration, ClipRect, mat4_from_row_major, mat4_to_row_major};
use crate::{Error, FormatProblem, Result};

/// Device-set files are a few kB; anything this large is not one and is not read into memory.
const MAX_CONFIG_BYTES: u64 = 64 << 20;

/// Reads the calibration of a PLUS device set: every `CoordinateDefinitions/Transform`, the Image->Probe
/// matrix (or the inverse of a Probe->Image one), and the `VolumeReconstruction` attributes with the clip
/// rectangle.
/// Refuses a clip rectangle (`ClipRectangleOrigin`/`Size`) outside the frames of `sequence`: every
/// pixel would be clipped, and the run would end in an empty volume or no samples after all its work.
pub fn check_clip_fits(
    calibration: &Calibration,
    sequence: &super::TrackedSequence,
    calibration_path: &Path,
    sequence_path: &Path,
) -> Result<()> {
    let Some(clip) = calibration.clip else {
        return Ok(());
    };
    let [x, y] = clip.origin_px;
    let [w, h] = clip.size_px;
    // A zero size means no clipping (as PLUS reads it).
    if w == 0 || h == 0 || sequence.width == 0 || sequence.height == 0 {
        return Ok(());
    }
    if x >= sequence.width || y >= sequence.height {
        return Err(Error::InvalidInput(format!(
            "{}: the clip rectangle (ClipRectangleOrigin {x} {y}, ClipRectangleSize {w} {h}) lies \
             outside the {} x {} pixel frames of {}: no pixel would be used",
            calibration_path.display(),
            sequence.width,
            sequence.height,
            sequence_path.display()
        )));
    }
    Ok(())
}

pub fn read_calibration(path: &Path) -> Result<Calibration> {
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let len = file.metadata().map_err(|e| Error::io(path, e))?.len();
    if len > MAX_CONFIG_BYTES {
        return Err(Error::format(
            path,
            FormatProblem::SizeMismatch,
            format!("{len} bytes is far too large for a PLUS device-set file"),
        ));
    }
    let mut bytes = Vec::with_capacity(len as usize);
    file.take(MAX_CONFIG_BYTES)
        .read_to_end(&mut bytes)
        .map_err(|e| Error::io(path, e))?;
    let text = String::from_utf8(bytes)
        .map_err(|_| Error::format(path, FormatProblem::Corrupt, "not UTF-8 text"))?;
    parse_calibration(&text, path)
}

/// Deepest element nesting accepted in an XML file. PLUS device sets nest about 6 deep; the limit keeps
/// a crafted file from exhausting the stack of the tree walks.
pub const MAX_XML_DEPTH: usize = 256;

/// Most XML nodes accepted (elements, text, comments): device sets hold a few hundred.
const MAX_XML_NODES: u32 = 100_000;

/// Parses XML text with bounds: element nesting at most [`MAX_XML_DEPTH`] (checked by a scan before
/// the parser builds anything) and at most 100,000 nodes. `path` names the file in errors.
pub fn parse_xml<'a>(text: &'a str, path: &Path) -> Result<roxmltree::Document<'a>> {
    if let Some((depth, line)) = nesting_beyond(text, MAX_XML_DEPTH) {
        return Err(Error::format(
            path,
            FormatProblem::Corrupt,
            format!(
                "XML elements nest {depth} deep by line {line}, over the limit of {MAX_XML_DEPTH}: \
                 not a PLUS device set"
            ),
        ));
    }
    let options = roxmltree::ParsingOptions {
        nodes_limit: MAX_XML_NODES,
        ..roxmltree::ParsingOptions::default()
    };
    roxmltree::Document::parse_with_options(text, options).map_err(|e| {
        Error::format(
            path,
            FormatProblem::Corrupt,
            format!("not well-formed XML: {e}"),
        )
    })
}

/// The nesting depth and line where element nesting first exceeds `limit`, if it does. A light scan of
/// tags: comments, CDATA, processing instructions and declarations are skipped, quoted attribute values
/// may hold `>`; well-formedness is the parser's business.
fn nesting_beyond(text: &str, limit: usize) -> Option<(usize, usize)> {
    let bytes = text.as_bytes();
    let mut depth = 0usize;
    let mut i = 0;
    let skip_to = |from: usize, end: &str| -> usize {
        text[from..]
            .find(end)
            .map_or(bytes.len(), |k| from + k + end.len())
    };
    while i < bytes.len() {
        if bytes[i] != b'<' {
            i += 1;
            continue;
        }
        let rest = &text[i..];
        if rest.starts_with("<!--") {
            i = skip_to(i + 4, "-->");
        } else if rest.starts_with("<![CDATA[") {
            i = skip_to(i + 9, "]]>");
        } else if rest.starts_with("<?") {
            i = skip_to(i + 2, "?>");
        } else if rest.starts_with("<!") {
            i = skip_to(i + 2, ">");
        } else if rest.starts_with("</") {
            depth = depth.saturating_sub(1);
            i = skip_to(i + 2, ">");
        } else {
            // An opening tag: find its end outside quotes; `/>` closes it at once.
            let mut j = i + 1;
            let mut quote = None;
            while j < bytes.len() {
                match (quote, bytes[j]) {
                    (None, b'"' | b'\'') => quote = Some(bytes[j]),
                    (Some(q), c) if c == q => quote = None,
                    (None, b'>') => break,
                    _ => {}
                }
                j += 1;
            }
            let self_closing = j > i + 1 && bytes.get(j - 1) == Some(&b'/');
            if !self_closing {
                depth += 1;
                if depth > limit {
                    let line = 1 + bytes[..i].iter().filter(|&&b| b == b'\n').count();
                    return Some((depth, line));
                }
            }
            i = j + 1;
        }
    }
    None
}

/// Largest departure of a transform's bottom row from `0 0 0 1` accepted as rounding.
const AFFINE_TOLERANCE: f64 = 1e-6;

/// `Err(bottom row)` unless the matrix's bottom row is `0 0 0 1` (an affine transform).
pub fn check_affine(m: &DMat4) -> std::result::Result<(), [f64; 4]> {
    let row = [m.x_axis.w, m.y_axis.w, m.z_axis.w, m.w_axis.w];
    let want = [0.0, 0.0, 0.0, 1.0];
    if row
        .iter()
        .zip(want)
        .all(|(v, w)| (v - w).abs() <= AFFINE_TOLERANCE)
    {
        Ok(())
    } else {
        Err(row)
    }
}

/// Parses device-set XML text; `path` names the source in errors.
pub fn parse_calibration(text: &str, path: &Path) -> Result<Calibration> {
    let doc = parse_xml(text, path)?;
    let root = doc.root_element().tag_name().name();
    if root != "PlusConfiguration" {
        return Err(Error::format(
            path,
            FormatProblem::Unsupported,
            format!("the root element is <{root}>, not <PlusConfiguration>: not a PLUS device set"),
        ));
    }
    let mut transforms = Vec::new();
    let mut image_to_probe_lines: Vec<u32> = Vec::new();
    for node in doc
        .descendants()
        .filter(|n| n.has_tag_name("CoordinateDefinitions"))
        .flat_map(|n| n.children().filter(|c| c.has_tag_name("Transform")))
    {
        let attr = |name: &str| -> Result<&str> {
            node.attribute(name).ok_or_else(|| {
                Error::format(
                    path,
                    FormatProblem::MissingField,
                    format!(
                        "CoordinateDefinitions/Transform (line {}) has no {name} attribute",
                        doc.text_pos_at(node.range().start).row
                    ),
                )
            })
        };
        let from = attr("From")?.trim().to_string();
        let to = attr("To")?.trim().to_string();
        let line = doc.text_pos_at(node.range().start).row;
        let matrix = parse_matrix(attr("Matrix")?, &format!("{from}To{to}"), path)?;
        if let Err(row) = check_affine(&matrix) {
            return Err(Error::format(
                path,
                FormatProblem::BadValue,
                format!(
                    "{from}To{to} Matrix (line {line}) is not affine: its bottom row is {} {} {} {}, \
                     not 0 0 0 1",
                    row[0], row[1], row[2], row[3]
                ),
            ));
        }
        if from == "Image" && to == "Probe" {
            image_to_probe_lines.push(line);
        }
        transforms.push((from, to, matrix));
    }
    if let [first, second, ..] = image_to_probe_lines[..] {
        return Err(Error::format(
            path,
            FormatProblem::BadValue,
            format!(
                "two Image->Probe calibrations (Transform From=\"Image\" To=\"Probe\" at lines \
                 {first} and {second}): keep the one that is right"
            ),
        ));
    }
    let image_to_probe = if let Some((_, _, m)) = transforms
        .iter()
        .find(|(f, t, _)| f == "Image" && t == "Probe")
    {
        *m
    } else if let Some((_, _, m)) = transforms
        .iter()
        .find(|(f, t, _)| f == "Probe" && t == "Image")
    {
        let det = m.determinant();
        if !det.is_finite() || det.abs() < 1e-15 {
            return Err(Error::format(
                path,
                FormatProblem::BadValue,
                "ProbeToImage matrix is singular and cannot be inverted to ImageToProbe",
            ));
        }
        m.inverse()
    } else {
        return Err(Error::format(
            path,
            FormatProblem::MissingTransform,
            "no CoordinateDefinitions/Transform From=\"Image\" To=\"Probe\" (the probe calibration)",
        ));
    };

    let mut volume_reconstruction = BTreeMap::new();
    let mut clip = None;
    if let Some(node) = doc
        .descendants()
        .find(|n| n.has_tag_name("VolumeReconstruction"))
    {
        for a in node.attributes() {
            volume_reconstruction.insert(a.name().to_string(), a.value().to_string());
        }
        let origin = node.attribute("ClipRectangleOrigin");
        let size = node.attribute("ClipRectangleSize");
        match (origin, size) {
            (Some(o), Some(s)) => {
                clip = Some(ClipRect {
                    origin_px: parse_pair(o, "ClipRectangleOrigin", path)?,
                    size_px: parse_pair(s, "ClipRectangleSize", path)?,
                });
            }
            (None, None) => {}
            _ => {
                return Err(Error::format(
                    path,
                    FormatProblem::MissingField,
                    "VolumeReconstruction has only one of ClipRectangleOrigin / ClipRectangleSize",
                ));
            }
        }
    }
    Ok(Calibration {
        image_to_probe,
        clip,
        transforms,
        volume_reconstruction,
    })
}

fn parse_matrix(text: &str, name: &str, path: &Path) -> Result<DMat4> {
    let bad = || {
        Error::format(
            path,
            FormatProblem::BadValue,
            format!("{name} Matrix is not 16 finite numbers: {:?}", text.trim()),
        )
    };
    let numbers: Vec<f64> = text
        .split_ascii_whitespace()
        .map(|t| t.parse::<f64>().ok().filter(|v| v.is_finite()))
        .collect::<Option<_>>()
        .ok_or_else(bad)?;
    let array: [f64; 16] = numbers.try_into().map_err(|_| bad())?;
    Ok(mat4_from_row_major(&array))
}

fn parse_pair(text: &str, name: &str, path: &Path) -> Result<[usize; 2]> {
    let values: Option<Vec<usize>> = text
        .split_ascii_whitespace()
        .map(|t| t.parse::<usize>().ok())
        .collect();
    match values.as_deref() {
        Some([a, b]) => Ok([*a, *b]),
        _ => Err(Error::format(
            path,
            FormatProblem::BadValue,
            format!("{name} = {text:?} is not two pixel counts"),
        )),
    }
}

fn xml_escape(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\n' => out.push_str("&#10;"),
            '\r' => out.push_str("&#13;"),
            '\t' => out.push_str("&#9;"),
            c => out.push(c),
        }
    }
    out
}

fn is_xml_name(s: &str) -> bool {
    let mut chars = s.chars();
    chars
        .next()
        .is_some_and(|c| c.is_ascii_alphabetic() || c == '_')
        && chars.all(|c| c.is_ascii_alphanumeric() || matches!(c, '_' | '-' | '.'))
}

/// The device-set XML text of a calibration (what [`write_calibration`] writes).
pub fn calibration_xml(calibration: &Calibration) -> Result<String> {
    let matrix_text = |m: &DMat4| -> String {
        let v = mat4_to_row_major(m);
        (0..4)
            .map(|r| {
                v[r * 4..r * 4 + 4]
                    .iter()
                    .map(|x| format!("{x}"))
                    .collect::<Vec<_>>()
                    .join(" ")
            })
            .collect::<Vec<_>>()
            .join("  ")
    };
    if !calibration
        .image_to_probe
        .to_cols_array()
        .iter()
        .all(|v| v.is_finite())
    {
        return Err(Error::InvalidInput(
            "calibration ImageToProbe has non-finite entries".into(),
        ));
    }
    let mut x = String::new();
    let w = |x: &mut String, s: &str| x.push_str(s);
    w(&mut x, "<?xml version=\"1.0\" encoding=\"utf-8\"?>\n");
    w(&mut x, "<PlusConfiguration version=\"2.1\">\n");
    w(&mut x, "  <CoordinateDefinitions>\n");
    // Image->Probe always comes from `image_to_probe`, written first; other transforms follow as kept.
    let _ = writeln!(
        x,
        "    <Transform From=\"Image\" To=\"Probe\" Matrix=\"{}\" />",
        matrix_text(&calibration.image_to_probe)
    );
    for (from, to, m) in &calibration.transforms {
        if from == "Image" && to == "Probe" {
            continue;
        }
        let _ = writeln!(
            x,
            "    <Transform From=\"{}\" To=\"{}\" Matrix=\"{}\" />",
            xml_escape(from),
            xml_escape(to),
            matrix_text(m)
        );
    }
    w(&mut x, "  </CoordinateDefinitions>\n");
    let mut attrs = calibration.volume_reconstruction.clone();
    attrs.remove("ClipRectangleOrigin");
    attrs.remove("ClipRectangleSize");
    if let Some(c) = calibration.clip {
        attrs.insert(
            "ClipRectangleOrigin".into(),
            format!("{} {}", c.origin_px[0], c.origin_px[1]),
        );
        attrs.insert(
            "ClipRectangleSize".into(),
            format!("{} {}", c.size_px[0], c.size_px[1]),
        );
    }
    if !attrs.is_empty() {
        w(&mut x, "  <VolumeReconstruction");
        for (k, v) in &attrs {
            if !is_xml_name(k) {
                return Err(Error::InvalidInput(format!(
                    "VolumeReconstruction attribute name {k:?} is not an XML name"
                )));
            }
            let _ = write!(x, "\n    {k}=\"{}\"", xml_escape(v));
        }
        w(&mut x, " />\n");
    }
    w(&mut x, "</PlusConfiguration>\n");
    Ok(x)
}

/// Writes a minimal PLUS device set holding the calibration (and clip rectangle) that PLUS and echosurf read.
pub fn write_calibration(path: &Path, calibration: &Calibration) -> Result<()> {
    let xml = calibration_xml(calibration)?;
    write_bytes_atomic(path, xml.as_bytes())
}

#[cfg(test)]
mod tests {
    use super::*;

    const P: &str = "test.xml";

    #[test]
    fn probe_to_image_is_inverted() {
        let xml = r#"<PlusConfiguration><CoordinateDefinitions>
            <Transform From="Probe" To="Image" Matrix="2 0 0 1  0 4 0 2  0 0 8 3  0 0 0 1"/>
            </CoordinateDefinitions></PlusConfiguration>"#;
        let c = parse_calibration(xml, Path::new(P)).unwrap();
        let back = c.image_to_probe.inverse();
        assert!((back.x_axis.x - 2.0).abs() < 1e-12);
        assert!((c.pixel_size_mm()[1] - 0.25).abs() < 1e-12);
        assert_eq!(c.clip, None);
    }

    #[test]
    fn errors_name_the_problem() {
        let missing = r#"<PlusConfiguration><CoordinateDefinitions>
            <Transform From="Phantom" To="Reference" Matrix="1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1"/>
            </CoordinateDefinitions></PlusConfiguration>"#;
        let e = parse_calibration(missing, Path::new(P)).unwrap_err();
        assert_eq!(e.problem(), Some(FormatProblem::MissingTransform));
        assert!(e.to_string().contains(P));
        let nan = r#"<PlusConfiguration><CoordinateDefinitions>
            <Transform From="Image" To="Probe" Matrix="1 0 0 0 0 NaN 0 0 0 0 1 0 0 0 0 1"/>
            </CoordinateDefinitions></PlusConfiguration>"#;
        let e = parse_calibration(nan, Path::new(P)).unwrap_err();
        assert_eq!(e.problem(), Some(FormatProblem::BadValue));
        let short = nan.replace("NaN 0 0 0 0 1 0 0 0 0 1", "1");
        let e = parse_calibration(&short, Path::new(P)).unwrap_err();
        assert_eq!(e.problem(), Some(FormatProblem::BadValue));
        let e = parse_calibration("<PlusConfiguration>", Path::new(P)).unwrap_err();
        assert_eq!(e.problem(), Some(FormatProblem::Corrupt));
        let projective = nan.replace("NaN 0 0 0 0 1 0 0 0 0 1", "1 0 0 0 0 1 0 0 0 0.5 1");
        let e = parse_calibration(&projective, Path::new(P)).unwrap_err();
        assert!(e.to_string().contains("not affine"), "{e}");
        let one =
            r#"<Transform From="Image" To="Probe" Matrix="1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1"/>"#;
        let twice = format!(
            "<PlusConfiguration><CoordinateDefinitions>\n{one}\n{one}\n</CoordinateDefinitions></PlusConfiguration>"
        );
        let e = parse_calibration(&twice, Path::new(P)).unwrap_err();
        assert!(e.to_string().contains("lines 2 and 3"), "{e}");
        let wrong_root = format!(
            "<Configuration><CoordinateDefinitions>{one}</CoordinateDefinitions></Configuration>"
        );
        let e = parse_calibration(&wrong_root, Path::new(P)).unwrap_err();
        assert!(e.to_string().contains("<Configuration>"), "{e}");
    }

    #[test]
    fn deep_nesting_is_refused_before_parsing() {
        let deep = format!(
            "<PlusConfiguration>{}{}</PlusConfiguration>",
            "<a>".repeat(20_000),
            "</a>".repeat(20_000)
        );
        let e = parse_calibration(&deep, Path::new(P)).unwrap_err();
        assert!(e.to_string().contains("nest 257 deep"), "{e}");
        // Self-closing tags, comments and quoted `>` do not count as nesting.
        let flat = format!(
            "<PlusConfiguration>{}<!-- <a><a> --><b x=\"a>b\"/></PlusConfiguration>",
            "<c/>".repeat(1000)
        );
        assert_eq!(nesting_beyond(&flat, 2), None);
        assert_eq!(nesting_beyond("<a><b><c></c></b></a>", 2), Some((3, 1)));
    }

    #[test]
    fn write_read_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let m = mat4_from_row_major(&[
            -0.00157821,
            0.0785919,
            -0.00803285,
            15.3978,
            -0.0839128,
            0.00372697,
            0.0153803,
            49.5705,
            0.0159024,
            0.00714276,
            0.0803604,
            -8.63446,
            0.0,
            0.0,
            0.0,
            1.0,
        ]);
        let mut c = Calibration::from_image_to_probe(m);
        c.transforms.push((
            "Phantom".into(),
            "Reference & co".into(),
            DMat4::from_translation(glam::DVec3::new(1.0, 2.0, 3.0)),
        ));
        c.clip = Some(ClipRect {
            origin_px: [167, 62],
            size_px: [495, 488],
        });
        c.volume_reconstruction
            .insert("OutputSpacing".into(), "0.5 0.5 0.5".into());
        c.volume_reconstruction
            .insert("ClipRectangleOrigin".into(), "167 62".into());
        c.volume_reconstruction
            .insert("ClipRectangleSize".into(), "495 488".into());
        let p = dir.path().join("cal.xml");
        write_calibration(&p, &c).unwrap();
        let back = read_calibration(&p).unwrap();
        assert_eq!(back, c);
    }
}
