//! What the segmentation gives: the kept pixels of every frame, as masks and as a PLUS sequence.

use super::bone;
use super::options::ResolvedParameters;
use crate::io::{PixelData, TrackedFrame, TrackedSequence};

/// The kept pixels of every frame of a sequence.
#[derive(Debug, Clone, PartialEq)]
pub struct BandMasks {
    pub width: usize,
    pub height: usize,
    /// One mask per sequence frame, row-major, 255 = kept, 0 = dropped (all 0 for frames without a pose).
    pub masks: Vec<Vec<u8>>,
    /// Lost bands, re-initialisations, frames where nothing was found; each names its frame index.
    pub warnings: Vec<String>,
    /// Sequence frame indices where the band was (re-)initialised: sweep starts and recoveries.
    pub initialised_frames: Vec<usize>,
    /// Frame metadata (poses, timestamps) of the sequence, so the masks can be written as a PLUS file.
    pub frames: Vec<TrackedFrame>,
    /// Orientation written with the masks (MF plus the third letter of the source, if any).
    pub orientation: String,
    pub parameters: ResolvedParameters,
    /// The sweep was segmented as bone ([`bone`]): each band is the bone echo's surface.
    pub bone_sweep: bool,
    /// For a bone sweep, per frame and per column of the full frame, the column's bone echo (row in
    /// the full frame); empty otherwise.
    pub bone_echoes: Vec<Vec<Option<bone::BoneEcho>>>,
}

impl BandMasks {
    /// Number of kept pixels in frame `index`.
    pub fn kept_count(&self, index: usize) -> usize {
        self.masks[index].iter().filter(|&&m| m != 0).count()
    }

    /// Fraction of all pixels of all frames that are kept.
    pub fn kept_fraction(&self) -> f64 {
        let total = self.width * self.height * self.masks.len();
        if total == 0 {
            return 0.0;
        }
        let kept: usize = (0..self.masks.len()).map(|i| self.kept_count(i)).sum();
        kept as f64 / total as f64
    }

    /// The masks as a PLUS sequence (MET_UCHAR, same W x H x N and per-frame fields as the source).
    pub fn to_sequence(&self) -> TrackedSequence {
        let mut pixels = Vec::with_capacity(self.width * self.height * self.masks.len());
        for m in &self.masks {
            pixels.extend_from_slice(m);
        }
        TrackedSequence {
            width: self.width,
            height: self.height,
            channels: 1,
            orientation: self.orientation.clone(),
            frames: self.frames.clone(),
            pixels: PixelData::U8(pixels),
            header: Default::default(),
        }
    }
}
