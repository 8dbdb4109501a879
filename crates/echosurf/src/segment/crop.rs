//! The clip rectangle and the frame crops the propagation works on: clipping, the data region, grey
//! levels of a crop, and copying bands between crops and full-frame masks.

use std::collections::BTreeSet;

use glam::DMat4;

use crate::io::{ClipRect, PixelData, PoseResolution, TrackedSequence};

/// Pixel size (mm) of a frame's Image->World matrix: mean length of its first two columns.
pub(super) fn pixel_size_of(image_to_world: &DMat4) -> f64 {
    0.5 * (image_to_world.x_axis.truncate().length() + image_to_world.y_axis.truncate().length())
}

/// The clip rectangle intersected with the frame; `None` if it leaves nothing.
/// A clip rectangle that reaches beyond the frames is cut to them, and said so: it usually means a
/// calibration made for another image size, whose pixel size and origin are then wrong too.
pub(super) fn clip_beyond_frame_warning(
    clip: Option<ClipRect>,
    width: usize,
    height: usize,
) -> Option<String> {
    let clip = clip.filter(|c| !c.fits(width, height))?;
    Some(format!(
        "the clip rectangle ({}) reaches beyond the {width} x {height} px frames and is cut to them: \
         is the calibration for this image size?",
        clip.describe()
    ))
}

pub(super) fn effective_clip(
    clip: Option<ClipRect>,
    width: usize,
    height: usize,
) -> Option<ClipRect> {
    let c = clip.unwrap_or(ClipRect {
        origin_px: [0, 0],
        size_px: [width, height],
    });
    let u0 = c.origin_px[0].min(width);
    let v0 = c.origin_px[1].min(height);
    let u1 = c.origin_px[0].saturating_add(c.size_px[0]).min(width);
    let v1 = c.origin_px[1].saturating_add(c.size_px[1]).min(height);
    (u1 > u0 && v1 > v0).then_some(ClipRect {
        origin_px: [u0, v0],
        size_px: [u1 - u0, v1 - v0],
    })
}

/// The bounding box, inside `clip`, of the pixels that are non-zero in any of up to 16 frames spread over
/// the posed frames; `None` if all are zero.
pub fn data_region(
    sequence: &TrackedSequence,
    poses: &PoseResolution,
    clip: ClipRect,
) -> Option<ClipRect> {
    let n = poses.poses.len();
    if n == 0 {
        return Some(clip);
    }
    let picks: BTreeSet<usize> = (0..n.min(16))
        .map(|k| poses.poses[k * n / n.min(16)].frame_index)
        .collect();
    let [u0, v0] = clip.origin_px;
    let [cw, ch] = clip.size_px;
    let (mut umin, mut umax, mut vmin, mut vmax) = (usize::MAX, 0, usize::MAX, 0);
    let mut grey = Vec::new();
    for f in picks {
        load_grey_crop(sequence, f, clip, &mut grey);
        for v in 0..ch {
            let row = &grey[v * cw..(v + 1) * cw];
            if let Some(first) = row.iter().position(|&x| x != 0.0) {
                let last = row.iter().rposition(|&x| x != 0.0).unwrap_or(first);
                umin = umin.min(first);
                umax = umax.max(last);
                vmin = vmin.min(v);
                vmax = vmax.max(v);
            }
        }
    }
    (umin <= umax).then(|| ClipRect {
        origin_px: [u0 + umin, v0 + vmin],
        size_px: [umax - umin + 1, vmax - vmin + 1],
    })
}

/// Grey levels (channels averaged) of the clip rectangle of frame `index`.
pub(super) fn load_grey_crop(
    sequence: &TrackedSequence,
    index: usize,
    clip: ClipRect,
    out: &mut Vec<f32>,
) {
    let (w, c) = (sequence.width, sequence.channels.max(1));
    let [u0, v0] = clip.origin_px;
    let [cw, ch] = clip.size_px;
    out.clear();
    out.reserve(cw * ch);
    let base = index * sequence.frame_len();
    match (&sequence.pixels, c) {
        (PixelData::U8(data), 1) => {
            for v in v0..v0 + ch {
                let row = base + v * w + u0;
                out.extend(data[row..row + cw].iter().map(|&x| x as f32));
            }
        }
        _ => {
            for v in v0..v0 + ch {
                for u in u0..u0 + cw {
                    out.push(sequence.pixel_f32(index, u, v));
                }
            }
        }
    }
}

pub(super) fn crop_bool(full: &[bool], width: usize, clip: ClipRect) -> Vec<bool> {
    let [u0, v0] = clip.origin_px;
    let [cw, ch] = clip.size_px;
    let mut out = Vec::with_capacity(cw * ch);
    for v in v0..v0 + ch {
        out.extend_from_slice(&full[v * width + u0..v * width + u0 + cw]);
    }
    out
}

/// The band a mask keeps, cropped to `clip`.
pub(super) fn band_from_mask(mask: &[u8], clip: ClipRect, width: usize, band: &mut Vec<bool>) {
    let [u0, v0] = clip.origin_px;
    let [cw, ch] = clip.size_px;
    band.clear();
    for r in 0..ch {
        let row = (v0 + r) * width + u0;
        band.extend(mask[row..row + cw].iter().map(|&m| m != 0));
    }
}

/// Sets to 255 the pixels of `mask` that `band` keeps (a union with what is there: masks start empty,
/// and the backward pass adds to the forward pass's).
pub(super) fn add_to_mask(band: &[bool], clip: ClipRect, width: usize, mask: &mut [u8]) {
    let [u0, v0] = clip.origin_px;
    let [cw, ch] = clip.size_px;
    for r in 0..ch {
        let dst = &mut mask[(v0 + r) * width + u0..(v0 + r) * width + u0 + cw];
        for (d, &b) in dst.iter_mut().zip(&band[r * cw..(r + 1) * cw]) {
            if b {
                *d = 255;
            }
        }
    }
}
