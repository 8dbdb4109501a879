//! The in-memory tracked sequence: frames normalised to MF orientation, per-frame poses with their status,
//! and the probe calibration. Readers produce it, the writer consumes it, every later stage reads it.

use std::collections::BTreeMap;

use glam::{DMat4, DVec3};

/// Pixel element type as stored in the file (MetaImage `ElementType`, NRRD `type`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum ElementType {
    U8,
    I8,
    U16,
    I16,
    F32,
}

impl ElementType {
    pub fn size_bytes(self) -> usize {
        match self {
            ElementType::U8 | ElementType::I8 => 1,
            ElementType::U16 | ElementType::I16 => 2,
            ElementType::F32 => 4,
        }
    }

    /// The MetaImage spelling (`MET_UCHAR`, ...).
    pub fn metaimage_name(self) -> &'static str {
        match self {
            ElementType::U8 => "MET_UCHAR",
            ElementType::I8 => "MET_CHAR",
            ElementType::U16 => "MET_USHORT",
            ElementType::I16 => "MET_SHORT",
            ElementType::F32 => "MET_FLOAT",
        }
    }
}

/// Pixel storage of all frames, frame after frame, rows top (near) to bottom (far) after MF
/// normalisation, `channels` interleaved values per pixel.
#[derive(Debug, Clone, PartialEq)]
pub enum PixelData {
    U8(Vec<u8>),
    I8(Vec<i8>),
    U16(Vec<u16>),
    I16(Vec<i16>),
    F32(Vec<f32>),
}

impl PixelData {
    pub fn element_type(&self) -> ElementType {
        match self {
            PixelData::U8(_) => ElementType::U8,
            PixelData::I8(_) => ElementType::I8,
            PixelData::U16(_) => ElementType::U16,
            PixelData::I16(_) => ElementType::I16,
            PixelData::F32(_) => ElementType::F32,
        }
    }

    pub fn len(&self) -> usize {
        match self {
            PixelData::U8(v) => v.len(),
            PixelData::I8(v) => v.len(),
            PixelData::U16(v) => v.len(),
            PixelData::I16(v) => v.len(),
            PixelData::F32(v) => v.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Value at flat index `i` as f32 (grey levels as read, no rescaling).
    pub fn get_f32(&self, i: usize) -> f32 {
        match self {
            PixelData::U8(v) => v[i] as f32,
            PixelData::I8(v) => v[i] as f32,
            PixelData::U16(v) => v[i] as f32,
            PixelData::I16(v) => v[i] as f32,
            PixelData::F32(v) => v[i],
        }
    }
}

/// A rigid or affine transform of one frame with its tracking status. An invalid pose must not be used.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameTransform {
    /// Maps points of the `From` frame into the `To` frame (column vectors, mm).
    pub matrix: DMat4,
    pub valid: bool,
}

/// Per-frame metadata of a tracked sequence.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct TrackedFrame {
    pub timestamp_s: Option<f64>,
    /// `ImageStatus = OK` (true when the file has no status field).
    pub image_valid: bool,
    /// Transforms keyed by their name without the `Transform` suffix, e.g. `"ProbeToTracker"`.
    pub transforms: BTreeMap<String, FrameTransform>,
    /// Every other per-frame field as written (`FrameNumber`, `UnfilteredTimestamp`, ...), kept for
    /// round-tripping.
    pub fields: BTreeMap<String, String>,
}

/// A tracked ultrasound sequence. Pixel data is always stored MF-oriented (see FORMATS.md), whatever
/// orientation the file had; `orientation` records what the file said.
#[derive(Debug, Clone, PartialEq)]
pub struct TrackedSequence {
    pub width: usize,
    pub height: usize,
    pub channels: usize,
    /// `UltrasoundImageOrientation` as read (e.g. `"MFA"`); the pixels have already been brought to MF.
    pub orientation: String,
    pub frames: Vec<TrackedFrame>,
    /// `width * height * channels * frames.len()` values, or empty for a tracking-only sequence (whose
    /// `width` / `height` stay what the file said, often 0 or 1; the writer marks it `MET_OTHER`).
    pub pixels: PixelData,
    /// Global header fields not otherwise represented, kept for round-tripping (e.g.
    /// `UltrasoundImageType`).
    pub header: BTreeMap<String, String>,
}

impl TrackedSequence {
    /// True when the sequence carries no images (tracker-only recordings).
    pub fn is_tracking_only(&self) -> bool {
        self.pixels.is_empty()
    }

    pub fn frame_len(&self) -> usize {
        self.width * self.height * self.channels
    }

    /// Grey levels of frame `index` as f32, row-major (`v * width + u`); multi-channel pixels are
    /// averaged. Panics if `index` is out of range or the sequence is tracking-only.
    pub fn frame_f32(&self, index: usize) -> Vec<f32> {
        let n = self.width * self.height;
        let c = self.channels.max(1);
        let base = index * self.frame_len();
        (0..n)
            .map(|p| {
                let s: f32 = (0..c).map(|k| self.pixels.get_f32(base + p * c + k)).sum();
                s / c as f32
            })
            .collect()
    }

    /// Grey level of pixel (u = column, v = row) of frame `index`, channels averaged.
    pub fn pixel_f32(&self, index: usize, u: usize, v: usize) -> f32 {
        let c = self.channels.max(1);
        let base = index * self.frame_len() + (v * self.width + u) * c;
        (0..c).map(|k| self.pixels.get_f32(base + k)).sum::<f32>() / c as f32
    }

    /// Names of all transforms present in any frame, sorted.
    pub fn transform_names(&self) -> Vec<String> {
        let mut names: Vec<String> = self
            .frames
            .iter()
            .flat_map(|f| f.transforms.keys().cloned())
            .collect();
        names.sort();
        names.dedup();
        names
    }
}

/// Pixels outside this rectangle are not image data (PLUS `ClipRectangleOrigin` / `ClipRectangleSize`,
/// in pixels of the MF-oriented frame).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct ClipRect {
    pub origin_px: [usize; 2],
    pub size_px: [usize; 2],
}

impl ClipRect {
    pub fn contains(&self, u: usize, v: usize) -> bool {
        u >= self.origin_px[0]
            && v >= self.origin_px[1]
            && u < self.origin_px[0] + self.size_px[0]
            && v < self.origin_px[1] + self.size_px[1]
    }

    /// Whether the rectangle lies within a `width` x `height` image. One that reaches beyond it is cut
    /// to the image (as PLUS does), but usually means the calibration was made for another image size.
    pub fn fits(&self, width: usize, height: usize) -> bool {
        self.origin_px[0].saturating_add(self.size_px[0]) <= width
            && self.origin_px[1].saturating_add(self.size_px[1]) <= height
    }

    /// `origin U V, size W x H px`, as the calibration gives it.
    pub fn describe(&self) -> String {
        format!(
            "origin {} {}, size {} x {} px",
            self.origin_px[0], self.origin_px[1], self.size_px[0], self.size_px[1]
        )
    }
}

/// A probe calibration and the other settings of a PLUS device-set file that echosurf uses.
#[derive(Debug, Clone, PartialEq)]
pub struct Calibration {
    /// Image (pixel) -> Probe (mm): a full affine carrying the pixel size, possibly anisotropic and sheared.
    pub image_to_probe: DMat4,
    /// Clip rectangle of the `VolumeReconstruction` element, if any.
    pub clip: Option<ClipRect>,
    /// Every `CoordinateDefinitions/Transform` as (from, to, matrix), including Image->Probe.
    pub transforms: Vec<(String, String, DMat4)>,
    /// Raw attributes of the `VolumeReconstruction` element (`OutputSpacing`, `Interpolation`, ...).
    pub volume_reconstruction: BTreeMap<String, String>,
}

impl Calibration {
    /// Calibration with just an Image->Probe matrix.
    pub fn from_image_to_probe(image_to_probe: DMat4) -> Self {
        Calibration {
            image_to_probe,
            clip: None,
            transforms: vec![("Image".into(), "Probe".into(), image_to_probe)],
            volume_reconstruction: BTreeMap::new(),
        }
    }

    /// Pixel size in mm along image x (columns) and y (rows): lengths of the first two matrix columns.
    pub fn pixel_size_mm(&self) -> [f64; 2] {
        [
            self.image_to_probe.x_axis.truncate().length(),
            self.image_to_probe.y_axis.truncate().length(),
        ]
    }
}

/// A 4x4 matrix from 16 numbers in row-major order, as PLUS writes them.
pub fn mat4_from_row_major(m: &[f64; 16]) -> DMat4 {
    DMat4::from_cols_array(m).transpose()
}

/// The 16 numbers of a matrix in row-major order, as PLUS writes them.
pub fn mat4_to_row_major(m: &DMat4) -> [f64; 16] {
    m.transpose().to_cols_array()
}

/// Position of pixel (u, v) of an MF frame in the world, given its Image->World matrix. No half-pixel shift.
pub fn pixel_to_world(image_to_world: &DMat4, u: f64, v: f64) -> DVec3 {
    image_to_world.transform_point3(DVec3::new(u, v, 0.0))
}
