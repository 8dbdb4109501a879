//! Reconstruction settings from a PLUS device-set `VolumeReconstruction` element, read as PLUS's
//! `vtkPlusVolumeReconstructor::ReadConfiguration` reads them (enum values case-insensitive,
//! deprecated `Compounding` / `Calculation` honoured when `CompoundingMode` is absent).

use std::collections::BTreeMap;
use std::path::Path;

use glam::DVec3;

use super::{
    Compounding, HoleFilling, HoleFillingElement, Interpolation, PositionArithmetic, VoxelOptions,
};
use crate::io::ClipRect;
use crate::{Error, FormatProblem, Result};

/// Where a problem was found: a file, or the calibration's attribute map.
#[derive(Clone, Copy)]
enum Source<'a> {
    File(&'a Path),
    Attributes,
}

impl Source<'_> {
    fn error(self, problem: FormatProblem, message: String) -> Error {
        match self {
            Source::File(p) => Error::format(p, problem, message),
            Source::Attributes => Error::InvalidInput(message),
        }
    }
}

fn parse_numbers(src: Source, key: &str, value: &str, count: usize) -> Result<Vec<f64>> {
    let parsed: std::result::Result<Vec<f64>, _> =
        value.split_whitespace().map(str::parse::<f64>).collect();
    match parsed {
        Ok(v) if v.len() == count && v.iter().all(|x| x.is_finite()) => Ok(v),
        _ => Err(src.error(
            FormatProblem::BadValue,
            format!("VolumeReconstruction {key}=\"{value}\": expected {count} finite numbers"),
        )),
    }
}

fn parse_int(src: Source, key: &str, value: &str) -> Result<i64> {
    value.trim().parse::<i64>().map_err(|_| {
        src.error(
            FormatProblem::BadValue,
            format!("{key}=\"{value}\" is not an integer"),
        )
    })
}

fn options_from_map(
    attrs: &BTreeMap<String, String>,
    clip: Option<ClipRect>,
    hole_filling: Option<HoleFilling>,
    src: Source,
) -> Result<VoxelOptions> {
    let mut o = VoxelOptions::default();
    let get = |k: &str| attrs.get(k).map(|s| s.trim());
    if let Some(v) = get("OutputSpacing") {
        let s = parse_numbers(src, "OutputSpacing", v, 3)?;
        o.spacing_mm = DVec3::new(s[0], s[1], s[2]);
        if o.spacing_mm.min_element() <= 0.0 {
            return Err(src.error(
                FormatProblem::BadValue,
                format!("VolumeReconstruction OutputSpacing=\"{v}\" must be positive"),
            ));
        }
    }
    if let Some(v) = get("OutputOrigin") {
        let s = parse_numbers(src, "OutputOrigin", v, 3)?;
        o.output_origin_mm = Some(DVec3::new(s[0], s[1], s[2]));
    }
    if let Some(v) = get("OutputExtent") {
        let s = parse_numbers(src, "OutputExtent", v, 6)?;
        if s.iter().any(|x| x.fract() != 0.0 || x.abs() > 1e9) {
            return Err(src.error(
                FormatProblem::BadValue,
                format!("VolumeReconstruction OutputExtent=\"{v}\" must be 6 integers"),
            ));
        }
        let e = [s[0], s[1], s[2], s[3], s[4], s[5]].map(|x| x as i64);
        // PLUS treats an all-zero extent as "not set".
        if e.iter().any(|&x| x != 0) {
            if e[1] < e[0] || e[3] < e[2] || e[5] < e[4] {
                return Err(src.error(
                    FormatProblem::BadValue,
                    format!("VolumeReconstruction OutputExtent=\"{v}\" is empty"),
                ));
            }
            o.output_extent = Some(e);
        }
    }
    o.clip = clip;
    if o.clip.is_none()
        && let (Some(origin), Some(size)) = (get("ClipRectangleOrigin"), get("ClipRectangleSize"))
    {
        let a = parse_numbers(src, "ClipRectangleOrigin", origin, 2)?;
        let b = parse_numbers(src, "ClipRectangleSize", size, 2)?;
        if a.iter().chain(&b).any(|&x| x < 0.0 || x.fract() != 0.0) {
            return Err(src.error(
                FormatProblem::BadValue,
                "ClipRectangleOrigin/Size must be non-negative integers".into(),
            ));
        }
        o.clip = Some(ClipRect {
            origin_px: [a[0] as usize, a[1] as usize],
            size_px: [b[0] as usize, b[1] as usize],
        });
    }
    if let Some(v) = get("Interpolation") {
        o.interpolation = if v.eq_ignore_ascii_case("NEAREST_NEIGHBOR") {
            Interpolation::NearestNeighbor
        } else if v.eq_ignore_ascii_case("LINEAR") {
            Interpolation::Linear
        } else {
            return Err(src.error(
                FormatProblem::BadValue,
                format!("Interpolation=\"{v}\": expected NEAREST_NEIGHBOR or LINEAR"),
            ));
        };
    }
    if let Some(v) = get("Optimization") {
        o.position_arithmetic = if v.eq_ignore_ascii_case("FULL") {
            PositionArithmetic::FixedPoint14
        } else if v.eq_ignore_ascii_case("PARTIAL") || v.eq_ignore_ascii_case("NONE") {
            PositionArithmetic::Double
        } else {
            return Err(src.error(
                FormatProblem::BadValue,
                format!("Optimization=\"{v}\": expected FULL, PARTIAL or NONE"),
            ));
        };
    }
    let mode = get("CompoundingMode");
    o.compounding = match mode {
        Some(v) if v.eq_ignore_ascii_case("MEAN") => Compounding::Mean,
        Some(v) if v.eq_ignore_ascii_case("MAXIMUM") => Compounding::Maximum,
        Some(v) if v.eq_ignore_ascii_case("LATEST") => Compounding::Latest,
        Some(v) if v.eq_ignore_ascii_case("IMPORTANCE_MASK") => {
            o.ignored_settings.push(
                "CompoundingMode=IMPORTANCE_MASK (importance masks are not supported; MEAN used)"
                    .into(),
            );
            Compounding::Mean
        }
        Some(v) => {
            return Err(src.error(
                FormatProblem::BadValue,
                format!("CompoundingMode=\"{v}\": expected MEAN, MAXIMUM or LATEST"),
            ));
        }
        None => {
            if get("Calculation").is_some_and(|c| c.eq_ignore_ascii_case("MAXIMUM")) {
                Compounding::Maximum
            } else if get("Compounding").is_some_and(|c| c.eq_ignore_ascii_case("OFF")) {
                Compounding::Latest
            } else {
                Compounding::Mean
            }
        }
    };
    if let Some(v) = get("PixelRejectionThreshold") {
        o.pixel_rejection_threshold = Some(parse_numbers(src, "PixelRejectionThreshold", v, 1)?[0]);
    }
    if let Some(v) = get("SkipInterval") {
        // PLUS resets values below 1 to 1.
        o.skip_interval = parse_int(src, "SkipInterval", v)?.max(1) as usize;
    }
    let fill = match get("FillHoles") {
        Some(v) if v.eq_ignore_ascii_case("ON") => true,
        Some(v) if v.eq_ignore_ascii_case("OFF") => false,
        Some(v) => {
            return Err(src.error(
                FormatProblem::BadValue,
                format!("FillHoles=\"{v}\": expected ON or OFF"),
            ));
        }
        None => false,
    };
    if fill {
        o.hole_filling = hole_filling.unwrap_or_else(|| HoleFilling::stick(9, 1));
    }
    for key in [
        "FanAnglesDeg",
        "FanAngles",
        "FanOriginPixel",
        "FanOrigin",
        "FanRadiusStartPixel",
        "FanRadiusStopPixel",
        "FanDepth",
        "EnableFanAnglesAutoDetect",
    ] {
        if let Some(v) = get(key) {
            let zero = v.split_whitespace().all(|t| t.parse::<f64>() == Ok(0.0))
                || v.eq_ignore_ascii_case("FALSE");
            if !zero {
                o.ignored_settings
                    .push(format!("{key}=\"{v}\" (fan clipping is not applied)"));
            }
        }
    }
    o.hole_filling.validate().map_err(|e| match src {
        Source::File(p) => Error::format(p, FormatProblem::BadValue, e.to_string()),
        Source::Attributes => e,
    })?;
    Ok(o)
}

/// From the calibration's raw attribute map (see [`VoxelOptions::from_calibration`]).
pub(super) fn options_from_attributes(
    attrs: &BTreeMap<String, String>,
    clip: Option<ClipRect>,
    hole_filling: Option<HoleFilling>,
) -> Result<VoxelOptions> {
    options_from_map(attrs, clip, hole_filling, Source::Attributes)
}

fn find_volume_reconstruction<'a>(
    doc: &'a roxmltree::Document<'a>,
) -> Option<roxmltree::Node<'a, 'a>> {
    doc.descendants()
        .find(|n| n.is_element() && n.tag_name().name() == "VolumeReconstruction")
}

fn element_attr<'a>(node: roxmltree::Node<'a, 'a>, name: &str) -> Option<&'a str> {
    node.attributes()
        .find(|a| a.name().eq_ignore_ascii_case(name))
        .map(|a| a.value())
}

fn hole_filling_from_node(node: roxmltree::Node, path: &Path) -> Result<HoleFilling> {
    let src = Source::File(path);
    let mut elements = Vec::new();
    for (i, e) in node
        .children()
        .filter(|c| {
            c.is_element()
                && c.tag_name()
                    .name()
                    .eq_ignore_ascii_case("HoleFillingElement")
        })
        .enumerate()
    {
        let need = |name: &str| -> Result<&str> {
            element_attr(e, name).ok_or_else(|| {
                src.error(
                    FormatProblem::MissingField,
                    format!("HoleFillingElement {i} has no {name} attribute"),
                )
            })
        };
        let num = |name: &str| -> Result<f64> {
            let v = need(name)?;
            Ok(parse_numbers(src, name, v, 1)?[0])
        };
        let size = |name: &str| -> Result<usize> {
            let v = num(name)?;
            if v < 0.0 || v.fract() != 0.0 || v > 1e6 {
                return Err(src.error(
                    FormatProblem::BadValue,
                    format!("HoleFillingElement {i}: {name} must be a non-negative integer"),
                ));
            }
            Ok(v as usize)
        };
        let kind = need("Type")?;
        let element = match kind.to_ascii_uppercase().as_str() {
            "STICK" => HoleFillingElement::Stick {
                length_limit: size("StickLengthLimit")?,
                sticks_to_use: size("NumberOfSticksToUse")?,
            },
            "GAUSSIAN" => HoleFillingElement::Gaussian {
                size: size("Size")?,
                stdev: num("Stdev")?,
                min_ratio: num("MinimumKnownVoxelsRatio")?,
            },
            "GAUSSIAN_ACCUMULATION" => HoleFillingElement::GaussianAccumulation {
                size: size("Size")?,
                stdev: num("Stdev")?,
                min_ratio: num("MinimumKnownVoxelsRatio")?,
            },
            "NEAREST_NEIGHBOR" => HoleFillingElement::NearestNeighbor {
                size: size("Size")?,
                min_ratio: num("MinimumKnownVoxelsRatio")?,
            },
            "DISTANCE_WEIGHT_INVERSE" => HoleFillingElement::DistanceWeightInverse {
                size: size("Size")?,
                min_ratio: num("MinimumKnownVoxelsRatio")?,
            },
            other => {
                return Err(src.error(
                    FormatProblem::BadValue,
                    format!(
                        "HoleFillingElement {i}: Type=\"{other}\" (expected STICK, GAUSSIAN, GAUSSIAN_ACCUMULATION, NEAREST_NEIGHBOR or DISTANCE_WEIGHT_INVERSE)"
                    ),
                ));
            }
        };
        elements.push(element);
    }
    let filling = HoleFilling { elements };
    filling
        .validate()
        .map_err(|e| Error::format(path, FormatProblem::BadValue, e.to_string()))?;
    Ok(filling)
}

/// The `HoleFilling` elements of a PLUS device-set XML text (`path` names it in errors); empty
/// when the configuration has none.
pub fn hole_filling_from_xml(xml: &str, path: &Path) -> Result<HoleFilling> {
    let doc = crate::io::plus_config::parse_xml(xml, path)?;
    let Some(vr) = find_volume_reconstruction(&doc) else {
        return Ok(HoleFilling::none());
    };
    match vr
        .children()
        .find(|c| c.is_element() && c.tag_name().name() == "HoleFilling")
    {
        Some(hf) => hole_filling_from_node(hf, path),
        None => Ok(HoleFilling::none()),
    }
}

/// Options from a PLUS device-set XML text: every `VolumeReconstruction` attribute and its
/// `HoleFilling` elements (`path` names the file in errors). Without a `VolumeReconstruction`
/// element the defaults are returned.
pub fn options_from_config_xml(xml: &str, path: &Path) -> Result<VoxelOptions> {
    let doc = crate::io::plus_config::parse_xml(xml, path)?;
    let Some(vr) = find_volume_reconstruction(&doc) else {
        return Ok(VoxelOptions::default());
    };
    let attrs: BTreeMap<String, String> = vr
        .attributes()
        .map(|a| (a.name().to_string(), a.value().to_string()))
        .collect();
    let fill_on = attrs
        .get("FillHoles")
        .is_some_and(|v| v.trim().eq_ignore_ascii_case("ON"));
    let hole_filling = if fill_on {
        let hf = vr
            .children()
            .find(|c| c.is_element() && c.tag_name().name() == "HoleFilling")
            .ok_or_else(|| {
                Error::format(
                    path,
                    FormatProblem::MissingField,
                    "VolumeReconstruction has FillHoles=\"ON\" but no HoleFilling element",
                )
            })?;
        Some(hole_filling_from_node(hf, path)?)
    } else {
        None
    };
    options_from_map(&attrs, None, hole_filling, Source::File(path))
}
