//! The voxel route users take today (PLUS / 3D Slicer): splat pixels into a grid, fill holes, then
//! marching cubes. Built in so echosurf can compare itself against it honestly on the same data.
//!
//! The conventions follow PLUS's `vtkPlusVolumeReconstructor`, so a volume made here can be
//! checked voxel by voxel against one PLUS made:
//! - output box: the clipped corners of every placed frame in the world frame; origin = their
//!   minimum, `dims = round((max - min) / spacing) + 1` (see [`GridRounding`] for PLUS's
//!   other versions);
//! - pixel (u, v) lands at `M * (u, v, 0, 1)` in voxel index space (by default with PLUS's 14-bit
//!   fixed-point matrix, see [`PositionArithmetic`]), rounded with `floor(x + 0.5)` (nearest
//!   neighbour) or spread over the 8 surrounding voxels (trilinear; for integer data the weights,
//!   running mean and accumulation also in PLUS's fixed point);
//! - MEAN keeps PLUS's running mean with an accumulation buffer (256 per whole pixel, saturating at
//!   65535) and PLUS's integer arithmetic, so rounding matches;
//! - hole filling reads the unfilled volume and writes a new one (STICK, GAUSSIAN, ...), as
//!   `vtkPlusFillHolesInVolume` does.
//!
//! Work is split over z-slabs of the output: every voxel still sees the pixels in the same order as
//! a single-threaded run, so the output is identical for any thread count.

mod config;
mod fill;
mod mha;
mod paste;

use std::borrow::Cow;

use glam::{DMat4, DVec3};

use crate::io::{ClipRect, ElementType, PoseResolution, TrackedSequence};
use crate::progress::Progress;
use crate::{Error, Result};

pub use config::{hole_filling_from_xml, options_from_config_xml};
pub use mha::{read_volume_mha, write_volume_mha};

/// How a pixel is spread into the grid.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Interpolation {
    /// The pixel goes to the one voxel its centre rounds to (PLUS `NEAREST_NEIGHBOR`).
    NearestNeighbor,
    /// The pixel is spread over the 8 surrounding voxels with trilinear weights (PLUS `LINEAR`,
    /// PLUS's default).
    #[default]
    Linear,
}

/// How several pixels falling into one voxel combine.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Compounding {
    /// Weighted running mean (PLUS `MEAN`, PLUS's default).
    #[default]
    Mean,
    /// Brightest pixel wins (PLUS `MAXIMUM`).
    Maximum,
    /// Last inserted pixel wins (PLUS `LATEST`).
    Latest,
}

/// One hole-filling method of PLUS's `HoleFillingElement`. An empty voxel is given the value of the
/// first element that succeeds for it; if none succeeds it stays 0.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum HoleFillingElement {
    /// Search the 13 stick directions for the nearest hit voxel on both sides (each side within
    /// `length_limit` voxels in total); interpolate along the shortest stick(s).
    Stick {
        length_limit: usize,
        sticks_to_use: usize,
    },
    /// Gaussian-weighted mean of the hit voxels in a `size`^3 cube, if more than `min_ratio` of the
    /// cube is hit.
    Gaussian {
        size: usize,
        stdev: f64,
        min_ratio: f64,
    },
    /// As `Gaussian`, with each voxel's weight multiplied by its accumulation.
    GaussianAccumulation {
        size: usize,
        stdev: f64,
        min_ratio: f64,
    },
    /// Mean of the hit voxels in the nearest non-empty cube shell, up to `size`^3.
    NearestNeighbor { size: usize, min_ratio: f64 },
    /// Inverse-distance-weighted mean of the hit voxels in a `size`^3 cube.
    DistanceWeightInverse { size: usize, min_ratio: f64 },
}

/// The hole-filling elements tried in order; empty = no hole filling.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct HoleFilling {
    pub elements: Vec<HoleFillingElement>,
}

impl HoleFilling {
    pub fn none() -> Self {
        Self::default()
    }

    /// PLUS's STICK filling (its test configurations use length 9, 1 stick).
    pub fn stick(length_limit: usize, sticks_to_use: usize) -> Self {
        HoleFilling {
            elements: vec![HoleFillingElement::Stick {
                length_limit,
                sticks_to_use,
            }],
        }
    }

    /// PLUS's GAUSSIAN filling over a `size`^3 cube.
    pub fn gaussian(size: usize, stdev: f64, min_ratio: f64) -> Self {
        HoleFilling {
            elements: vec![HoleFillingElement::Gaussian {
                size,
                stdev,
                min_ratio,
            }],
        }
    }

    pub fn is_enabled(&self) -> bool {
        !self.elements.is_empty()
    }

    fn validate(&self) -> Result<()> {
        for e in &self.elements {
            let (size, ratio) = match *e {
                HoleFillingElement::Stick {
                    length_limit,
                    sticks_to_use,
                } => {
                    if !(2..=1000).contains(&length_limit) || !(1..=13).contains(&sticks_to_use) {
                        return Err(Error::InvalidInput(format!(
                            "hole filling STICK needs a length limit in 2..=1000 and 1..=13 sticks, got {length_limit} and {sticks_to_use}"
                        )));
                    }
                    continue;
                }
                HoleFillingElement::Gaussian {
                    size,
                    stdev,
                    min_ratio,
                }
                | HoleFillingElement::GaussianAccumulation {
                    size,
                    stdev,
                    min_ratio,
                } => {
                    if !(stdev.is_finite() && stdev > 0.0) {
                        return Err(Error::InvalidInput(format!(
                            "hole filling Gaussian needs a positive Stdev, got {stdev}"
                        )));
                    }
                    (size, min_ratio)
                }
                HoleFillingElement::NearestNeighbor { size, min_ratio }
                | HoleFillingElement::DistanceWeightInverse { size, min_ratio } => {
                    (size, min_ratio)
                }
            };
            if !(1..=101).contains(&size) || size % 2 == 0 {
                return Err(Error::InvalidInput(format!(
                    "hole filling kernel Size must be odd and in 1..=101, got {size}"
                )));
            }
            if !ratio.is_finite() || !(0.0..=1.0).contains(&ratio) {
                return Err(Error::InvalidInput(format!(
                    "hole filling MinimumKnownVoxelsRatio must be in [0, 1], got {ratio}"
                )));
            }
        }
        Ok(())
    }
}

/// Arithmetic of the pixel -> voxel-index mapping (and of trilinear splatting of integer data).
/// PLUS's `Optimization="FULL"` (its default) quantises the mapping to fixed point with 14
/// fractional bits; the bits decide which voxel a pixel near a voxel boundary lands in, so matching
/// PLUS voxel for voxel needs the same choice.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum PositionArithmetic {
    /// Matrix entries rounded to multiples of 2^-14, positions summed exactly in integers
    /// (PLUS `FULL`).
    #[default]
    FixedPoint14,
    /// Double precision (PLUS `PARTIAL` / `NONE`).
    Double,
}

/// How the fitted grid's voxel count per axis follows from the frames' span: `count - 1 =
/// round(span / spacing)`. PLUS changed this over time; all variants keep the origin at the
/// frames' minimum corner.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum GridRounding {
    /// `floor(span / spacing + 0.5)`: the grid of PLUS's NN_MEAN regression reference
    /// (147x106x105 on the spine sweep); every nearest-neighbour pixel lands inside.
    #[default]
    Nearest,
    /// `ceil`: current PLUS (the grid always reaches past the farthest corner; 148x107x105).
    Ceil,
    /// `floor` (truncation): older PLUS (`SpinePhantomFreehandReconstructed.mha`, 147x106x104).
    Floor,
}

/// Explicit output grid (PLUS `OutputOrigin` + `OutputExtent`): voxel (i, j, k) for i in
/// `extent[0]..=extent[1]` etc. sits at `origin_mm + (i, j, k) * spacing`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OutputGrid {
    pub origin_mm: DVec3,
    pub extent: [i64; 6],
}

/// Default memory budget for the grid and its buffers: 2 GiB.
pub const DEFAULT_MEMORY_BUDGET_BYTES: u64 = 2 << 30;

/// Settings of a reconstruction. `Default` is PLUS's defaults at 0.5 mm.
#[derive(Debug, Clone, PartialEq)]
pub struct VoxelOptions {
    /// Voxel size along x, y, z (PLUS `OutputSpacing`).
    pub spacing_mm: DVec3,
    pub interpolation: Interpolation,
    pub compounding: Compounding,
    pub hole_filling: HoleFilling,
    /// Pixels outside are not inserted; PLUS includes the far edge (`origin + size`) when inside
    /// the image.
    pub clip: Option<ClipRect>,
    /// Origin override (PLUS `OutputOrigin`); used with `output_extent`.
    pub output_origin_mm: Option<DVec3>,
    /// Extent override (PLUS `OutputExtent`, inclusive voxel index ranges x0 x1 y0 y1 z0 z1).
    /// Without it the grid is fitted to the frames.
    pub output_extent: Option<[i64; 6]>,
    /// Voxel count rule of the fitted grid.
    pub grid_rounding: GridRounding,
    /// Fixed-point (PLUS default) or double pixel positions.
    pub position_arithmetic: PositionArithmetic,
    /// Pixels darker than this are not inserted (PLUS `PixelRejectionThreshold`).
    pub pixel_rejection_threshold: Option<f64>,
    /// Insert every n-th placed frame (PLUS `SkipInterval`); the grid still covers all frames.
    pub skip_interval: usize,
    /// Refuse (with the spacing that would fit) when the grid and its buffers need more.
    pub memory_budget_bytes: u64,
    /// Buffers per voxel the caller allocates after the reconstruction (the voxel route's smoothing
    /// and surface field), counted in the budget; 0 for the volume alone.
    pub extra_bytes_per_voxel: u64,
    /// Settings read from a configuration that this implementation does not apply (fan clipping,
    /// importance masks, ...), for the caller to report.
    pub ignored_settings: Vec<String>,
}

impl Default for VoxelOptions {
    fn default() -> Self {
        VoxelOptions {
            spacing_mm: DVec3::splat(0.5),
            interpolation: Interpolation::default(),
            compounding: Compounding::default(),
            hole_filling: HoleFilling::none(),
            clip: None,
            output_origin_mm: None,
            output_extent: None,
            grid_rounding: GridRounding::default(),
            position_arithmetic: PositionArithmetic::default(),
            pixel_rejection_threshold: None,
            skip_interval: 1,
            memory_budget_bytes: DEFAULT_MEMORY_BUDGET_BYTES,
            extra_bytes_per_voxel: 0,
            ignored_settings: Vec::new(),
        }
    }
}

impl VoxelOptions {
    /// Options from the `VolumeReconstruction` attributes kept in the calibration (and its clip
    /// rectangle). The nested `HoleFilling` elements are not in that attribute map: with
    /// `FillHoles="ON"` this assumes PLUS's usual STICK(9, 1); use [`options_from_config_xml`] to
    /// read the elements themselves.
    pub fn from_calibration(calibration: &crate::io::Calibration) -> Result<Self> {
        config::options_from_attributes(&calibration.volume_reconstruction, calibration.clip, None)
    }

    /// Options from a PLUS device-set file: every `VolumeReconstruction` attribute and its
    /// `HoleFilling` elements (defaults when the file has no such element).
    pub fn from_config_file(path: &std::path::Path) -> Result<Self> {
        let xml = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        options_from_config_xml(&xml, path)
    }

    fn validate(&self) -> Result<()> {
        let s = self.spacing_mm;
        if !(s.is_finite() && s.min_element() > 0.0) {
            return Err(Error::InvalidInput(format!(
                "voxel spacing must be positive and finite, got {} {} {} mm",
                s.x, s.y, s.z
            )));
        }
        if self.skip_interval == 0 {
            return Err(Error::InvalidInput(
                "skip interval must be at least 1".into(),
            ));
        }
        if let Some(o) = self.output_origin_mm
            && !o.is_finite()
        {
            return Err(Error::InvalidInput("output origin must be finite".into()));
        }
        if let Some(e) = self.output_extent
            && (e[1] < e[0] || e[3] < e[2] || e[5] < e[4])
        {
            return Err(Error::InvalidInput(format!(
                "output extent {e:?} is empty (each max must be >= its min)"
            )));
        }
        if let Some(t) = self.pixel_rejection_threshold
            && !t.is_finite()
        {
            return Err(Error::InvalidInput(
                "pixel rejection threshold must be finite".into(),
            ));
        }
        self.hole_filling.validate()
    }
}

/// Voxel values in the element type of the input pixels: `u8` for B-mode, `f32` for anything else
/// (integer types keep integer values and PLUS's integer arithmetic).
#[derive(Debug, Clone, PartialEq)]
pub enum VoxelValues {
    U8(Vec<u8>),
    F32(Vec<f32>),
}

impl VoxelValues {
    pub fn len(&self) -> usize {
        match self {
            VoxelValues::U8(v) => v.len(),
            VoxelValues::F32(v) => v.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub fn get_f32(&self, i: usize) -> f32 {
        match self {
            VoxelValues::U8(v) => v[i] as f32,
            VoxelValues::F32(v) => v[i],
        }
    }
}

/// What happened during a reconstruction.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct ReconstructionStats {
    pub frames_inserted: usize,
    /// Placed frames left out by the skip interval.
    pub frames_skipped: usize,
    /// Pixels that landed inside the grid.
    pub pixels_inserted: u64,
    /// Voxels hit by at least one pixel.
    pub voxels_hit: usize,
    /// Empty voxels given a value by hole filling.
    pub voxels_filled: usize,
    /// Voxels still without a value.
    pub voxels_empty: usize,
    /// MEAN insertions into a saturated accumulation buffer (PLUS warns about these).
    pub accumulation_overflows: u64,
}

/// A reconstructed volume, x fastest, then y, then z.
#[derive(Debug, Clone, PartialEq)]
pub struct Volume {
    pub dims: [usize; 3],
    /// World position of voxel (0, 0, 0), mm.
    pub origin_mm: DVec3,
    pub spacing_mm: DVec3,
    pub values: VoxelValues,
    /// Element type written to `.mha` (the input's).
    pub element_type: ElementType,
    /// PLUS's accumulation buffer before hole filling: 0 = no pixel reached the voxel, 256 per
    /// whole pixel (trilinear splats add their weight * 256), saturating at 65535. Empty for a
    /// volume read from a file.
    pub accumulation: Vec<u16>,
    pub stats: ReconstructionStats,
}

impl Volume {
    pub fn len(&self) -> usize {
        self.dims[0] * self.dims[1] * self.dims[2]
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Flat index of voxel (i, j, k).
    pub fn index(&self, i: usize, j: usize, k: usize) -> usize {
        (k * self.dims[1] + j) * self.dims[0] + i
    }

    /// World position of voxel (i, j, k).
    pub fn voxel_position_mm(&self, i: usize, j: usize, k: usize) -> DVec3 {
        self.origin_mm + DVec3::new(i as f64, j as f64, k as f64) * self.spacing_mm
    }

    /// Values as f32 (borrowed when already f32), x fastest: what marching cubes takes.
    pub fn values_f32(&self) -> Cow<'_, [f32]> {
        match &self.values {
            VoxelValues::U8(v) => Cow::Owned(v.iter().map(|&x| x as f32).collect()),
            VoxelValues::F32(v) => Cow::Borrowed(v),
        }
    }

    /// True for voxels some pixel reached (before hole filling); all true for a volume read from
    /// a file (no accumulation buffer).
    pub fn hit_mask(&self) -> Vec<bool> {
        if self.accumulation.len() == self.len() {
            self.accumulation.iter().map(|&a| a != 0).collect()
        } else {
            vec![true; self.len()]
        }
    }
}

/// The grid a reconstruction would use, without allocating it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GridGeometry {
    pub dims: [usize; 3],
    pub origin_mm: DVec3,
    pub spacing_mm: DVec3,
}

impl GridGeometry {
    pub fn voxel_count(&self) -> u128 {
        self.dims.iter().map(|&d| d as u128).product()
    }
}

/// Bytes per voxel for values, accumulation and (with hole filling) the filled copy.
fn bytes_per_voxel(element_type: ElementType, hole_filling: bool) -> u64 {
    let value = if element_type == ElementType::U8 {
        1
    } else {
        4
    };
    value + 2 + if hole_filling { value } else { 0 }
}

/// Memory the grid and its buffers would need, bytes (writing a `.mha` needs about one more byte
/// per voxel for the encoded data).
pub fn estimated_memory_bytes(
    geometry: &GridGeometry,
    element_type: ElementType,
    options: &VoxelOptions,
) -> u128 {
    geometry.voxel_count()
        * (bytes_per_voxel(element_type, options.hole_filling.is_enabled()) as u128
            + options.extra_bytes_per_voxel as u128)
}

/// World (min, max) corners of the clipped frames, as PLUS's `AddImageToExtent` takes them.
fn frames_bounds(
    sequence: &TrackedSequence,
    poses: &PoseResolution,
    clip: Option<ClipRect>,
) -> Option<(DVec3, DVec3)> {
    if sequence.width == 0 || sequence.height == 0 || poses.poses.is_empty() {
        return None;
    }
    let (mut min_x, mut max_x) = (0.0, (sequence.width - 1) as f64);
    let (mut min_y, mut max_y) = (0.0, (sequence.height - 1) as f64);
    if let Some(c) = clip.filter(|c| c.size_px[0] > 0 && c.size_px[1] > 0) {
        min_x = f64::max(min_x, c.origin_px[0] as f64);
        max_x = f64::min(max_x, (c.origin_px[0] + c.size_px[0]) as f64);
        min_y = f64::max(min_y, c.origin_px[1] as f64);
        max_y = f64::min(max_y, (c.origin_px[1] + c.size_px[1]) as f64);
    }
    let corners = [
        DVec3::new(min_x, min_y, 0.0),
        DVec3::new(min_x, max_y, 0.0),
        DVec3::new(max_x, min_y, 0.0),
        DVec3::new(max_x, max_y, 0.0),
    ];
    let mut lo = DVec3::splat(f64::INFINITY);
    let mut hi = DVec3::splat(f64::NEG_INFINITY);
    for pose in &poses.poses {
        for c in corners {
            let p = pose.image_to_world.transform_point3(c);
            lo = lo.min(p);
            hi = hi.max(p);
        }
    }
    (lo.is_finite() && hi.is_finite()).then_some((lo, hi))
}

/// Largest number of voxels along one axis accepted before any allocation is considered.
const MAX_AXIS_VOXELS: f64 = 1.0e7;

/// The grid for `options`: the explicit `output_extent` if given, else fitted to the frames.
pub fn grid_geometry(
    sequence: &TrackedSequence,
    poses: &PoseResolution,
    options: &VoxelOptions,
) -> Result<GridGeometry> {
    options.validate()?;
    let spacing = options.spacing_mm;
    if let Some(e) = options.output_extent {
        let origin = options.output_origin_mm.unwrap_or(DVec3::ZERO);
        let mut dims = [0usize; 3];
        for a in 0..3 {
            let n = e[2 * a + 1] as i128 - e[2 * a] as i128 + 1;
            if n as f64 > MAX_AXIS_VOXELS {
                return Err(Error::ResourceLimit(format!(
                    "output extent {e:?} has {n} voxels along axis {a}, more than the {MAX_AXIS_VOXELS} accepted"
                )));
            }
            dims[a] = n as usize;
        }
        let start = DVec3::new(e[0] as f64, e[2] as f64, e[4] as f64);
        return Ok(GridGeometry {
            dims,
            origin_mm: origin + start * spacing,
            spacing_mm: spacing,
        });
    }
    let (lo, hi) = frames_bounds(sequence, poses, options.clip).ok_or_else(|| {
        Error::InvalidInput("no placed frame with image data to reconstruct a volume from".into())
    })?;
    let mut dims = [0usize; 3];
    for a in 0..3 {
        let span = (hi[a] - lo[a]) / spacing[a];
        let n = match options.grid_rounding {
            GridRounding::Nearest => paste::plus_round(span),
            GridRounding::Ceil => span.ceil(),
            GridRounding::Floor => span.floor(),
        };
        if !(n.is_finite() && n < MAX_AXIS_VOXELS) {
            return Err(Error::ResourceLimit(format!(
                "the frames span {:.1} mm along axis {a}: at {} mm spacing that is {n:.0} voxels, more than the {MAX_AXIS_VOXELS} accepted; use a coarser spacing",
                hi[a] - lo[a],
                spacing[a]
            )));
        }
        dims[a] = n as usize + 1;
    }
    Ok(GridGeometry {
        dims,
        origin_mm: lo,
        spacing_mm: spacing,
    })
}

fn format_bytes(bytes: u128) -> String {
    let b = bytes as f64;
    if b >= 1e9 {
        format!("{:.2} GB", b / 1e9)
    } else if b >= 1e6 {
        format!("{:.1} MB", b / 1e6)
    } else {
        format!("{:.1} kB", b / 1e3)
    }
}

/// Refuses grids over the budget, naming the spacing that would fit.
fn check_memory_budget(
    sequence: &TrackedSequence,
    poses: &PoseResolution,
    options: &VoxelOptions,
    geometry: &GridGeometry,
    element_type: ElementType,
    progress: &dyn Progress,
) -> Result<()> {
    // Plus one frame's splatting buffers and what is resident already (the decoded sequence, the
    // process), or the decoded sequence where the resident size is not reported.
    let resident = match crate::budget::resident_bytes() {
        0 => sequence.pixels.len() as u128 * sequence.pixels.element_type().size_bytes() as u128,
        r => r as u128,
    };
    let frame_bytes = paste::frame_working_bytes(sequence, options) + resident;
    let need = estimated_memory_bytes(geometry, element_type, options) + frame_bytes;
    progress.memory_estimate(need.min(u64::MAX as u128) as u64);
    let budget = options.memory_budget_bytes as u128;
    // Flat voxel indices are u32 in the splatting buffers.
    let too_many = geometry.voxel_count() >= u32::MAX as u128;
    if need <= budget && !too_many {
        return Ok(());
    }
    let grid = format!(
        "a {}x{}x{} grid at {} mm spacing needs {} with its values, accumulation buffers and the decoded frames",
        geometry.dims[0],
        geometry.dims[1],
        geometry.dims[2],
        fmt_spacing(options.spacing_mm),
        format_bytes(need)
    );
    if options.output_extent.is_some() {
        return Err(Error::ResourceLimit(format!(
            "{grid}, over the memory budget of {}: shrink the output extent or raise the budget",
            format_bytes(budget)
        )));
    }
    // Scale the spacing until the fitted grid fits (volume scales with spacing^3).
    let mut factor = ((need as f64 / budget.max(1) as f64).cbrt()).max(1.0);
    for _ in 0..64 {
        let trial = VoxelOptions {
            spacing_mm: options.spacing_mm * factor,
            ..options.clone()
        };
        if let Ok(g) = grid_geometry(sequence, poses, &trial)
            && estimated_memory_bytes(&g, element_type, &trial) + frame_bytes <= budget
            && g.voxel_count() < u32::MAX as u128
        {
            return Err(Error::ResourceLimit(format!(
                "{grid}, over the memory budget of {}: a spacing of {} mm or coarser would fit (or raise the memory budget)",
                format_bytes(budget),
                fmt_spacing(trial.spacing_mm.map(|s| (s * 1000.0).ceil() / 1000.0))
            )));
        }
        factor *= 1.05;
    }
    Err(Error::ResourceLimit(format!(
        "{grid}, over the memory budget of {}{}",
        format_bytes(budget),
        if frame_bytes >= budget {
            format!(
                " (the decoded frames and the process alone take {}: raise the memory budget)",
                format_bytes(frame_bytes)
            )
        } else {
            String::new()
        }
    )))
}

fn fmt_spacing(s: DVec3) -> String {
    if s.x == s.y && s.y == s.z {
        format!("{}", s.x)
    } else {
        format!("{} {} {}", s.x, s.y, s.z)
    }
}

/// Reconstructs a voxel volume from the placed frames as PLUS does (see the module docs).
/// Fails on an empty sequence, bad options, or a grid over `options.memory_budget_bytes`
/// ([`Error::ResourceLimit`], naming a spacing that fits).
pub fn reconstruct_volume(
    sequence: &TrackedSequence,
    poses: &PoseResolution,
    options: &VoxelOptions,
    progress: &dyn Progress,
) -> Result<Volume> {
    options.validate()?;
    if sequence.is_tracking_only() {
        return Err(Error::InvalidInput(
            "the sequence has no images (tracking only): nothing to reconstruct".into(),
        ));
    }
    let frame_count = sequence.frames.len();
    if sequence.pixels.len() != sequence.frame_len() * frame_count {
        return Err(Error::InvalidInput(format!(
            "sequence pixel data holds {} values, expected {} frames of {}x{}x{}",
            sequence.pixels.len(),
            frame_count,
            sequence.width,
            sequence.height,
            sequence.channels
        )));
    }
    if let Some(p) = poses.poses.iter().find(|p| p.frame_index >= frame_count) {
        return Err(Error::InvalidInput(format!(
            "pose for frame {} but the sequence has {frame_count} frames",
            p.frame_index
        )));
    }
    let element_type = sequence.pixels.element_type();
    let geometry = grid_geometry(sequence, poses, options)?;
    check_memory_budget(sequence, poses, options, &geometry, element_type, progress)?;

    let integer_values = element_type != ElementType::F32;
    let mut stats = ReconstructionStats::default();
    let (values, accumulation) = match element_type {
        ElementType::U8 => {
            let (v, a) = paste::paste_frames::<u8>(
                sequence, poses, options, &geometry, true, &mut stats, progress,
            )?;
            let v = if options.hole_filling.is_enabled() {
                let (filled, count) =
                    fill::fill_holes(&v, &a, geometry.dims, &options.hole_filling, true, progress);
                stats.voxels_filled = count;
                filled
            } else {
                v
            };
            (VoxelValues::U8(v), a)
        }
        _ => {
            let (v, a) = paste::paste_frames::<f32>(
                sequence,
                poses,
                options,
                &geometry,
                integer_values,
                &mut stats,
                progress,
            )?;
            let v = if options.hole_filling.is_enabled() {
                let (filled, count) = fill::fill_holes(
                    &v,
                    &a,
                    geometry.dims,
                    &options.hole_filling,
                    integer_values,
                    progress,
                );
                stats.voxels_filled = count;
                filled
            } else {
                v
            };
            (VoxelValues::F32(v), a)
        }
    };
    stats.voxels_hit = accumulation.iter().filter(|&&a| a != 0).count();
    stats.voxels_empty = accumulation.len() - stats.voxels_hit - stats.voxels_filled;
    Ok(Volume {
        dims: geometry.dims,
        origin_mm: geometry.origin_mm,
        spacing_mm: geometry.spacing_mm,
        values,
        element_type,
        accumulation,
        stats,
    })
}

/// World -> voxel-index matrix of a grid.
fn world_to_index(geometry: &GridGeometry) -> DMat4 {
    (DMat4::from_translation(geometry.origin_mm) * DMat4::from_scale(geometry.spacing_mm)).inverse()
}

#[cfg(test)]
mod tests;
