//! A PNG montage of frames with the band tinted and outlined, for a person to judge the segmentation.

use std::path::Path;

use super::BandMasks;
use crate::io::TrackedSequence;
use crate::io::atomic::write_png_atomic;
use crate::{Error, Result};

/// Montages wider than this are drawn at a reduced scale.
const MAX_MONTAGE_WIDTH_PX: usize = 2000;
const GAP_PX: usize = 4;

/// Up to `count` frames spread evenly over the frames that have a non-empty band.
pub fn default_preview_frames(masks: &BandMasks, count: usize) -> Vec<usize> {
    let with_band: Vec<usize> = (0..masks.masks.len())
        .filter(|&i| masks.masks[i].iter().any(|&m| m != 0))
        .collect();
    if with_band.len() <= count || count == 0 {
        return with_band;
    }
    let mut picked: Vec<usize> = (0..count)
        .map(|k| with_band[k * (with_band.len() - 1) / (count - 1).max(1)])
        .collect();
    picked.dedup();
    picked
}

/// Writes a grid of `frames` (grey) with the kept band tinted green and its outline in yellow; the grid
/// is scaled down (box average) to at most ~2000 px wide.
pub fn write_band_preview(
    path: &Path,
    sequence: &TrackedSequence,
    masks: &BandMasks,
    frames: &[usize],
) -> Result<()> {
    let (w, h) = (sequence.width, sequence.height);
    if (masks.width, masks.height) != (w, h) || masks.masks.len() != sequence.frames.len() {
        return Err(Error::InvalidInput(format!(
            "masks are {}x{}x{} but the sequence is {w}x{h}x{}",
            masks.width,
            masks.height,
            masks.masks.len(),
            sequence.frames.len()
        )));
    }
    if frames.is_empty() {
        return Err(Error::InvalidInput("no frames to preview".into()));
    }
    if let Some(&bad) = frames.iter().find(|&&f| f >= sequence.frames.len()) {
        return Err(Error::InvalidInput(format!(
            "preview frame {bad} is out of range (the sequence has {} frames)",
            sequence.frames.len()
        )));
    }
    let cols = (frames.len() as f64).sqrt().ceil() as usize;
    let rows = frames.len().div_ceil(cols);
    let scale = (cols * w).div_ceil(MAX_MONTAGE_WIDTH_PX).max(1);
    let (tw, th) = (w.div_ceil(scale), h.div_ceil(scale));
    let (mw, mh) = (
        cols * tw + (cols + 1) * GAP_PX,
        rows * th + (rows + 1) * GAP_PX,
    );
    let mut rgb = vec![32u8; mw * mh * 3];
    let mut grey = vec![0f32; tw * th];
    let mut kept = vec![false; tw * th];
    for (slot, &f) in frames.iter().enumerate() {
        // Box-average grey, "any kept" band at the tile scale.
        grey.fill(0.0);
        kept.fill(false);
        let mut counts = vec![0u32; tw * th];
        let mask = &masks.masks[f];
        for v in 0..h {
            for u in 0..w {
                let t = (v / scale) * tw + u / scale;
                grey[t] += sequence.pixel_f32(f, u, v);
                counts[t] += 1;
                kept[t] |= mask[v * w + u] != 0;
            }
        }
        let (x0, y0) = (
            GAP_PX + (slot % cols) * (tw + GAP_PX),
            GAP_PX + (slot / cols) * (th + GAP_PX),
        );
        for ty in 0..th {
            for tx in 0..tw {
                let t = ty * tw + tx;
                let g = (grey[t] / counts[t].max(1) as f32).clamp(0.0, 255.0);
                let inside = kept[t];
                let edge = inside && {
                    let n = |dx: i64, dy: i64| {
                        let (x, y) = (tx as i64 + dx, ty as i64 + dy);
                        x < 0
                            || y < 0
                            || x >= tw as i64
                            || y >= th as i64
                            || !kept[y as usize * tw + x as usize]
                    };
                    n(-1, 0) || n(1, 0) || n(0, -1) || n(0, 1)
                };
                let px = if edge {
                    [255, 230, 0]
                } else if inside {
                    [
                        (g * 0.75) as u8,
                        (g * 0.75 + 64.0).min(255.0) as u8,
                        (g * 0.75) as u8,
                    ]
                } else {
                    [g as u8; 3]
                };
                let o = ((y0 + ty) * mw + x0 + tx) * 3;
                rgb[o..o + 3].copy_from_slice(&px);
            }
        }
    }
    write_png_atomic(path, mw as u32, mh as u32, png::ColorType::Rgb, &rgb)
}

/// Writes frame `index` as an 8-bit grey PNG of the frame's own size, pixel for pixel and MF-oriented:
/// the picture to draw a first band on (`--init` takes a PNG mask of this size, or a JSON polygon in its
/// pixel coordinates). 8-bit frames are written as stored; other pixel types are mapped linearly from
/// the frame's own range to 0..255, and channels are averaged.
pub fn write_frame_png(path: &Path, sequence: &TrackedSequence, index: usize) -> Result<()> {
    if sequence.is_tracking_only() {
        return Err(Error::InvalidInput(
            "the sequence holds no images (tracking only): there is no frame to write".into(),
        ));
    }
    if index >= sequence.frames.len() {
        return Err(Error::InvalidInput(format!(
            "frame {index} is out of range (the sequence has {} frames, 0-{})",
            sequence.frames.len(),
            sequence.frames.len().saturating_sub(1)
        )));
    }
    let grey = sequence.frame_f32(index);
    let as_stored = matches!(sequence.pixels, crate::io::PixelData::U8(_));
    let (lo, hi) = grey
        .iter()
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &g| {
            (lo.min(g), hi.max(g))
        });
    let bytes: Vec<u8> = if as_stored {
        grey.iter()
            .map(|&g| g.round().clamp(0.0, 255.0) as u8)
            .collect()
    } else if hi > lo {
        let scale = 255.0 / (hi - lo);
        grey.iter()
            .map(|&g| ((g - lo) * scale).round().clamp(0.0, 255.0) as u8)
            .collect()
    } else {
        vec![0; grey.len()]
    };
    write_png_atomic(
        path,
        sequence.width as u32,
        sequence.height as u32,
        png::ColorType::Grayscale,
        &bytes,
    )
}
