//! Initial bands: loaders for a user's mask (PNG) or polygon (JSON), polygon rasterisation, and the
//! automatic band (beyond the paper, which needed a user to draw the first band).

use std::path::Path;

use super::InitialBand;
use crate::{Error, FormatProblem, Result};

/// Largest mask we accept (pixels), so a corrupt PNG header cannot make us allocate without bound.
const MAX_MASK_PIXELS: u64 = 1 << 28;

impl InitialBand {
    /// Reads a PNG mask (any colour type or depth): a pixel is in the band if any colour channel is
    /// non-zero and, with an alpha channel, it is not fully transparent. 16-bit samples are kept at
    /// 16 bits, so a value of 1 counts as in the band.
    pub fn from_png(path: &Path) -> Result<InitialBand> {
        Self::read_png(path, None)
    }

    /// [`InitialBand::from_png`], also checking that the mask has the frames' size: from the header,
    /// before anything is decoded.
    pub fn from_png_sized(path: &Path, width: usize, height: usize) -> Result<InitialBand> {
        Self::read_png(path, Some((width, height)))
    }

    fn read_png(path: &Path, frame_size: Option<(usize, usize)>) -> Result<InitialBand> {
        let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
        let mut decoder = png::Decoder::new(std::io::BufReader::new(file));
        // Palette and low bit depths to 8 bits, tRNS to alpha; 16-bit samples stay 16-bit.
        decoder.set_transformations(png::Transformations::EXPAND);
        let bad = |m: String| Error::format(path, FormatProblem::Corrupt, m);
        let mut reader = decoder
            .read_info()
            .map_err(|e| bad(format!("not a readable PNG mask: {e}")))?;
        let (width, height) = {
            let info = reader.info();
            (info.width as usize, info.height as usize)
        };
        if let Some((fw, fh)) = frame_size
            && (width, height) != (fw, fh)
        {
            return Err(Error::format(
                path,
                FormatProblem::SizeMismatch,
                format!(
                    "initial band mask is {width}x{height} pixels but the frames are {fw}x{fh}"
                ),
            ));
        }
        if width as u64 * height as u64 > MAX_MASK_PIXELS || width == 0 || height == 0 {
            return Err(Error::format(
                path,
                FormatProblem::SizeMismatch,
                format!("PNG mask of {width}x{height} pixels is empty or too large"),
            ));
        }
        let mut buf =
            crate::resources::try_zeroed_vec::<u8>(reader.output_buffer_size(), "the PNG mask")
                .map_err(|e| bad(e.to_string()))?;
        let frame = reader
            .next_frame(&mut buf)
            .map_err(|e| bad(format!("PNG mask does not decode: {e}")))?;
        let channels = frame.color_type.samples();
        let sample_bytes = match frame.bit_depth {
            png::BitDepth::Sixteen => 2,
            _ => 1,
        };
        // A band painted on a transparent layer: its unpainted pixels are see-through, whatever
        // colour they carry.
        let colours = match frame.color_type {
            png::ColorType::GrayscaleAlpha | png::ColorType::Rgba => channels - 1,
            _ => channels,
        };
        let stride = frame.line_size;
        let pixel_bytes = channels * sample_bytes;
        let colour_bytes = colours * sample_bytes;
        let mut data = Vec::with_capacity(width * height);
        for v in 0..height {
            let row = &buf[v * stride..v * stride + width * pixel_bytes];
            data.extend(row.chunks_exact(pixel_bytes).map(|px| {
                let (colour, alpha) = px.split_at(colour_bytes);
                colour.iter().any(|&x| x != 0)
                    && alpha
                        .chunks_exact(sample_bytes)
                        .all(|a| a.iter().any(|&x| x != 0))
            }));
        }
        Ok(InitialBand::Mask {
            width,
            height,
            data,
        })
    }

    /// Reads `{"polygon": [[u, v], ...]}` (pixel coordinates of the MF-oriented frame, at least 3 vertices).
    pub fn from_polygon_json(path: &Path) -> Result<InitialBand> {
        #[derive(serde::Deserialize)]
        struct PolygonFile {
            polygon: Vec<[f64; 2]>,
        }
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let parsed: PolygonFile = serde_json::from_str(&text).map_err(|e| {
            Error::format(
                path,
                FormatProblem::BadValue,
                format!("expected JSON {{\"polygon\": [[u, v], ...]}}: {e}"),
            )
        })?;
        if parsed.polygon.len() < 3 {
            return Err(Error::format(
                path,
                FormatProblem::BadValue,
                format!(
                    "the initial polygon has {} vertices; it needs at least 3",
                    parsed.polygon.len()
                ),
            ));
        }
        if parsed.polygon.iter().flatten().any(|x| !x.is_finite()) {
            return Err(Error::format(
                path,
                FormatProblem::BadValue,
                "polygon vertex is not finite",
            ));
        }
        Ok(InitialBand::Polygon(parsed.polygon))
    }

    /// Loads an initial band by extension: `.png` mask (checked against the frame size) or `.json` polygon.
    pub fn load(path: &Path, width: usize, height: usize) -> Result<InitialBand> {
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().to_ascii_lowercase())
            .unwrap_or_default();
        if name.ends_with(".png") {
            Self::from_png_sized(path, width, height)
        } else if name.ends_with(".json") {
            Self::from_polygon_json(path)
        } else {
            Err(Error::format(
                path,
                FormatProblem::Unsupported,
                "initial band must be a .png mask or a .json polygon",
            ))
        }
    }
}

/// Pixels (u, v) of a `width x height` frame whose point (u, v) lies inside the closed polygon (even-odd
/// rule; pixel (u, v) is the point (u, v), as in the Image frame). Errors on fewer than 3 vertices, a
/// non-finite vertex, or a polygon that covers no pixel of the frame.
pub fn rasterize_polygon(vertices: &[[f64; 2]], width: usize, height: usize) -> Result<Vec<bool>> {
    if vertices.len() < 3 {
        return Err(Error::InvalidInput(format!(
            "the initial polygon has {} vertices; it needs at least 3",
            vertices.len()
        )));
    }
    if vertices.iter().flatten().any(|x| !x.is_finite()) {
        return Err(Error::InvalidInput("polygon vertex is not finite".into()));
    }
    let mut mask = vec![false; width * height];
    let mut crossings: Vec<f64> = Vec::new();
    for v in 0..height {
        let y = v as f64;
        crossings.clear();
        for i in 0..vertices.len() {
            let [x0, y0] = vertices[i];
            let [x1, y1] = vertices[(i + 1) % vertices.len()];
            // Half-open rule on y so a vertex on the scan line is counted once.
            if (y0 <= y) != (y1 <= y) {
                crossings.push(x0 + (y - y0) * (x1 - x0) / (y1 - y0));
            }
        }
        crossings.sort_by(f64::total_cmp);
        for pair in crossings.chunks_exact(2) {
            let start = pair[0].ceil().max(0.0);
            let end = pair[1].floor().min(width as f64 - 1.0);
            if start > end {
                continue;
            }
            for u in start as usize..=end as usize {
                mask[v * width + u] = true;
            }
        }
    }
    if !mask.iter().any(|&m| m) {
        return Err(Error::InvalidInput(format!(
            "the initial polygon covers no pixel of the {width}x{height} frame"
        )));
    }
    Ok(mask)
}

/// Bright connected echo structures of a strongly smoothed frame, as seed pixel indices (row-major, in
/// index order). Threshold: Otsu's between-class split of the smoothed grey levels, raised to at least
/// mean + 1 standard deviation so a mostly dark frame does not split its speckle. Structures are
/// 8-connected; each is scored by its echo mass (sum of grey level above the threshold) and every
/// structure scoring at least `keep_fraction` of the strongest is kept. Empty when the frame is flat.
pub fn find_echo_structures(
    smoothed: &[f32],
    width: usize,
    height: usize,
    keep_fraction: f32,
    labels: &mut Vec<u32>,
    stack: &mut Vec<u32>,
) -> Vec<u32> {
    let n = width * height;
    if n == 0 {
        return Vec::new();
    }
    let (lo, hi) = smoothed
        .iter()
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), &x| {
            (a.min(x), b.max(x))
        });
    if hi.partial_cmp(&lo) != Some(std::cmp::Ordering::Greater) {
        return Vec::new();
    }
    let threshold = otsu_threshold(smoothed, lo, hi).max({
        let mean = smoothed.iter().map(|&x| x as f64).sum::<f64>() / n as f64;
        let var = smoothed
            .iter()
            .map(|&x| (x as f64 - mean).powi(2))
            .sum::<f64>()
            / n as f64;
        (mean + var.sqrt()) as f32
    });
    labels.clear();
    labels.resize(n, 0);
    let mut masses: Vec<f64> = vec![0.0];
    for start in 0..n {
        if labels[start] != 0 || smoothed[start] <= threshold {
            continue;
        }
        let label = masses.len() as u32;
        let mut mass = 0.0f64;
        labels[start] = label;
        stack.clear();
        stack.push(start as u32);
        while let Some(i) = stack.pop() {
            let i = i as usize;
            mass += (smoothed[i] - threshold) as f64;
            let (u, v) = (i % width, i / width);
            for dv in -1i64..=1 {
                for du in -1i64..=1 {
                    let (nu, nv) = (u as i64 + du, v as i64 + dv);
                    if nu < 0 || nv < 0 || nu >= width as i64 || nv >= height as i64 {
                        continue;
                    }
                    let j = nv as usize * width + nu as usize;
                    if labels[j] == 0 && smoothed[j] > threshold {
                        labels[j] = label;
                        stack.push(j as u32);
                    }
                }
            }
        }
        masses.push(mass);
    }
    let best = masses.iter().copied().fold(0.0, f64::max);
    if best <= 0.0 {
        return Vec::new();
    }
    let keep: Vec<bool> = masses
        .iter()
        .enumerate()
        .map(|(l, &m)| l > 0 && m >= keep_fraction as f64 * best)
        .collect();
    (0..n as u32)
        .filter(|&i| keep[labels[i as usize] as usize])
        .collect()
}

/// Otsu's threshold over a 256-bin histogram of values in [lo, hi].
fn otsu_threshold(values: &[f32], lo: f32, hi: f32) -> f32 {
    const BINS: usize = 256;
    let scale = (BINS - 1) as f32 / (hi - lo);
    let mut hist = [0u64; BINS];
    for &x in values {
        hist[((x - lo) * scale) as usize] += 1;
    }
    let total = values.len() as f64;
    let sum_all: f64 = hist
        .iter()
        .enumerate()
        .map(|(i, &c)| i as f64 * c as f64)
        .sum();
    let (mut w0, mut sum0) = (0.0f64, 0.0f64);
    let (mut best, mut best_bin) = (-1.0f64, 0usize);
    for (i, &c) in hist.iter().enumerate() {
        w0 += c as f64;
        sum0 += i as f64 * c as f64;
        let w1 = total - w0;
        if w0 == 0.0 || w1 == 0.0 {
            continue;
        }
        let m0 = sum0 / w0;
        let m1 = (sum_all - sum0) / w1;
        let between = w0 * w1 * (m0 - m1) * (m0 - m1);
        if between > best {
            best = between;
            best_bin = i;
        }
    }
    lo + (best_bin as f32 + 0.5) / scale
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn polygon_rasterises_a_rectangle_exactly() {
        let mask =
            rasterize_polygon(&[[2.0, 1.0], [5.0, 1.0], [5.0, 3.0], [2.0, 3.0]], 8, 6).unwrap();
        let kept: Vec<(usize, usize)> = (0..48)
            .filter(|&i| mask[i])
            .map(|i| (i % 8, i / 8))
            .collect();
        // Rows 1 and 2 (half-open in y), columns 2..=5.
        let expected: Vec<(usize, usize)> = [1, 2]
            .iter()
            .flat_map(|&v| (2..=5).map(move |u| (u, v)))
            .collect();
        assert_eq!(kept, expected);
    }

    #[test]
    fn degenerate_polygons_are_rejected() {
        assert!(rasterize_polygon(&[[0.0, 0.0], [3.0, 3.0]], 8, 8).is_err());
        assert!(
            rasterize_polygon(&[[100.0, 100.0], [120.0, 100.0], [110.0, 120.0]], 8, 8).is_err()
        );
        assert!(rasterize_polygon(&[[0.0, 0.0], [f64::NAN, 3.0], [1.0, 5.0]], 8, 8).is_err());
    }

    #[test]
    fn strongest_structure_is_found_and_weak_blobs_dropped() {
        let (w, h) = (40, 30);
        let mut img = vec![10.0f32; w * h];
        for u in 5..35 {
            img[20 * w + u] = 200.0; // long bright line
        }
        img[5 * w + 5] = 120.0; // small blob
        let mut labels = Vec::new();
        let mut stack = Vec::new();
        let seeds = find_echo_structures(&img, w, h, 0.25, &mut labels, &mut stack);
        assert_eq!(seeds.len(), 30);
        assert!(seeds.iter().all(|&i| i as usize / w == 20));
        assert!(
            find_echo_structures(&vec![3.0; w * h], w, h, 0.25, &mut labels, &mut stack).is_empty()
        );
    }
}
