//! The voxel route (`extract --method voxel`): what users of PLUS / 3D Slicer do today, done well so the
//! comparison with the direct route is honest.
//!
//! 1. Reconstruct ALL pixels inside the clip rectangle into a grid, exactly as PLUS would with the
//!    configuration's `VolumeReconstruction` settings ([`crate::voxel::reconstruct_volume`]); the spacing
//!    is the configuration's `OutputSpacing` when it sets one, else the surfacer resolution.
//! 2. Optionally smooth with a separable Gaussian as a *normalised* convolution over the voxels that hold
//!    data (hit or hole-filled): `G*(w v) / G*w`. Empty voxels neither darken their neighbours nor count
//!    as data, and small gaps between frames are bridged where at least [`MIN_DATA_WEIGHT`] of the
//!    kernel's weight is data.
//! 3. Marching cubes at the iso-level(s); triangles in cells with a corner that holds no data are
//!    dropped (the voxel counterpart of the RBF route's region of trust: no surface where nothing was
//!    seen, in particular no wall where bright data meets the unswept part of the grid).
//!
//! With `--iso auto` the level follows the RBF route's rule (Otsu split into background and boundary,
//! [`crate::samples::ISO_FRACTION`] of the way up) applied to the smoothed voxels with data, not to the
//! segmentation's kept pixels: compounding and smoothing lower the thin specular boundary echoes (on the
//! simulated duck a 1 mm Gaussian takes them from ~130 to below 50), so the pixels' level would miss most
//! of the boundary. The voxel route never segments.
//! Normals point toward lower grey values, as on the RBF route.

use glam::DVec3;
use rayon::prelude::*;

use super::{
    ExtractOptions, ExtractOutput, ExtractReport, ExtractedSurface, IsoLevels, StageCounts,
    UsedParameters, frame_outlines, median_frame_spacing_mm, trust_distance_for,
};
use crate::io::{Calibration, TrackedSequence};
use crate::mesh::Mesh;
use crate::progress::Progress;
use crate::resources::StageMeter;
use crate::samples::{ISO_FRACTION, IntensityLevels, SampleSet};
use crate::voxel::{Compounding, Interpolation, VoxelOptions, reconstruct_volume};
use crate::{Error, Result};

/// Share of the Gaussian kernel's weight that must fall on data for a smoothed voxel to hold data. At a
/// straight data edge the share is 0.5; 0.3 bridges gaps of about one sigma between frames without
/// extrapolating far past the swept region.
pub const MIN_DATA_WEIGHT: f64 = 0.3;

/// Settings of the voxel route besides those it shares with the RBF route (iso-levels, segmentation
/// for `--iso auto`, surfacer resolution as the default spacing).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct VoxelRouteOptions {
    /// Isotropic grid spacing (mm). `None` (`"auto"` in the TOML): the configuration's
    /// `OutputSpacing` if it has one, else the surfacer resolution (`ExtractOptions::surface.resolution_mm`).
    #[serde(with = "crate::serde_forms::auto_f64")]
    pub spacing_mm: Option<f64>,
    /// Sigma of the Gaussian pre-smoothing (mm); 0 = none. The grid's memory budget is
    /// [`ExtractOptions::memory_budget_bytes`] (`None`: the reconstruction's default).
    pub smoothing_sigma_mm: f64,
}

impl Default for VoxelRouteOptions {
    /// Sigma 1 mm: the most accurate on the simulated hand, and less smoothing leaves speckle fragments
    /// (measured in docs/decisions/0013-direct-rbf-vs-voxel-route.md, "The voxel route's smoothing").
    fn default() -> Self {
        VoxelRouteOptions {
            spacing_mm: None,
            smoothing_sigma_mm: 1.0,
        }
    }
}

/// Buffers per voxel the route adds to the reconstructed volume: the grey levels as f32 (4) and the
/// data mask (1); smoothing holds the weighted values, the weights, the new mask and the result
/// (4 + 4 + 1 + 4) at once; without it, the surface field (4) is the last.
fn route_bytes_per_voxel(smoothing_sigma_mm: f64) -> u64 {
    if smoothing_sigma_mm > 0.0 { 18 } else { 9 }
}

/// What the voxel route did, for the report.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct VoxelRouteReport {
    pub spacing_mm: [f64; 3],
    pub dims: [usize; 3],
    pub interpolation: String,
    pub compounding: String,
    pub hole_filling: String,
    pub smoothing_sigma_mm: f64,
    pub voxels_hit: usize,
    pub voxels_filled: usize,
    pub voxels_empty: usize,
    /// Voxels holding data after smoothing (hit, filled, or bridged by the smoothing).
    pub voxels_with_data: usize,
    /// Marching-cubes triangles dropped because their cell touched a voxel without data.
    pub triangles_dropped_at_data_edge: usize,
    /// Configuration settings the reconstruction does not apply.
    pub ignored_settings: Vec<String>,
}

/// The voxel route; `options.method` is ignored (the caller dispatched on it).
pub(super) fn extract_voxel(
    sequence: &TrackedSequence,
    calibration: Option<&Calibration>,
    options: &ExtractOptions,
    route: &VoxelRouteOptions,
    progress: &dyn Progress,
) -> Result<ExtractOutput> {
    if !(route.smoothing_sigma_mm.is_finite() && route.smoothing_sigma_mm >= 0.0) {
        return Err(Error::InvalidInput(format!(
            "voxel smoothing must be a non-negative number of mm, got {}",
            route.smoothing_sigma_mm
        )));
    }
    if let Some(s) = route.spacing_mm
        && !(s.is_finite() && s > 0.0)
    {
        return Err(Error::InvalidInput(format!(
            "voxel spacing must be a positive number of mm, got {s}"
        )));
    }
    let mut meter = StageMeter::new(progress);
    let mut warnings = Vec::new();

    let requested = match &options.iso {
        IsoLevels::Levels(v) if v.is_empty() => {
            return Err(Error::InvalidInput("no iso-level given".into()));
        }
        IsoLevels::Levels(v) => Some(v.clone()),
        IsoLevels::Auto => None,
    };
    let poses = super::place_frames(sequence, calibration, options, &mut meter)?;
    let mut counts = StageCounts {
        frames: sequence.frames.len(),
        frames_used: poses.poses.len(),
        pixels: poses.poses.len() * sequence.width * sequence.height,
        ..Default::default()
    };

    let mut voxel_options = match calibration {
        Some(c) => VoxelOptions::from_calibration(c)?,
        None => VoxelOptions::default(),
    };
    let config_sets_spacing =
        calibration.is_some_and(|c| c.volume_reconstruction.contains_key("OutputSpacing"));
    match route.spacing_mm {
        Some(s) => voxel_options.spacing_mm = DVec3::splat(s),
        None if !config_sets_spacing => {
            voxel_options.spacing_mm = DVec3::splat(options.surface.resolution_mm)
        }
        None => {}
    }
    if let Some(b) = options.memory_budget_bytes {
        voxel_options.memory_budget_bytes = b;
    }
    voxel_options.extra_bytes_per_voxel = route_bytes_per_voxel(route.smoothing_sigma_mm);
    let volume = meter.stage("reconstruct", || {
        reconstruct_volume(sequence, &poses, &voxel_options, progress)
    })?;

    let (values, has_data) = meter.stage("smooth", || {
        let raw = volume.values_f32();
        let has_data: Vec<bool> = raw
            .iter()
            .zip(&volume.accumulation)
            .map(|(&v, &a)| a != 0 || v != 0.0)
            .collect();
        if route.smoothing_sigma_mm > 0.0 {
            smooth_masked_gaussian(
                &raw,
                &has_data,
                volume.dims,
                volume.spacing_mm,
                route.smoothing_sigma_mm,
            )
        } else {
            (raw.into_owned(), has_data)
        }
    });
    let voxels_with_data = has_data.iter().filter(|&&d| d).count();
    // `auto`: the same rule as the RBF route (Otsu background / boundary, ISO_FRACTION of the way up),
    // applied to what this route surfaces: the (smoothed) voxels with data. Compounding and smoothing
    // lower thin boundary echoes, so the kept pixels' level would lie above most boundaries here.
    let intensity_levels = if requested.is_none() {
        let data: Vec<f32> = values
            .iter()
            .zip(&has_data)
            .filter(|(_, d)| **d)
            .map(|(&v, _)| v)
            .collect();
        Some(volume_levels(data).ok_or_else(|| {
            Error::InvalidInput(
                "cannot choose an iso-level automatically: the volume holds one grey level".into(),
            )
        })?)
    } else {
        None
    };
    let iso_auto = requested.is_none();
    let levels = match (requested, intensity_levels) {
        (Some(v), _) => v,
        (None, Some(l)) => vec![l.iso as f64],
        (None, None) => unreachable!("levels estimated above"),
    };
    check_levels_in_volume(&levels, &values, &has_data)?;

    let (meshes, dropped) = meter.stage("surface", || -> Result<(Vec<Mesh>, usize)> {
        // No data = NaN, which marching cubes treats as below every level; those cells are dropped.
        let field: Vec<f32> = values
            .iter()
            .zip(&has_data)
            .map(|(&v, &d)| if d { v } else { f32::NAN })
            .collect();
        let mut meshes = Vec::with_capacity(levels.len());
        let mut dropped = 0;
        for &level in &levels {
            let mesh = crate::surface::marching_cubes(
                &field,
                volume.dims,
                volume.origin_mm,
                volume.spacing_mm,
                level,
            )?;
            let (mesh, n) = drop_cells_without_data(mesh, &has_data, &volume);
            dropped += n;
            meshes.push(mesh);
        }
        Ok((meshes, dropped))
    })?;
    for (level, mesh) in levels.iter().zip(&meshes) {
        if mesh.is_empty() {
            warnings.push(format!(
                "iso-level {level}: no surface found in the reconstructed volume"
            ));
        }
    }
    warnings.extend(
        voxel_options
            .ignored_settings
            .iter()
            .map(|s| format!("volume reconstruction: {s} is not applied")),
    );

    counts.triangles = meshes.iter().map(|m| m.triangles.len()).collect();
    let spacing = median_frame_spacing_mm(sequence, &poses);
    let stats = &volume.stats;
    let voxel_report = VoxelRouteReport {
        spacing_mm: volume.spacing_mm.to_array(),
        dims: volume.dims,
        interpolation: match voxel_options.interpolation {
            Interpolation::NearestNeighbor => "nearest",
            Interpolation::Linear => "linear",
        }
        .into(),
        compounding: match voxel_options.compounding {
            Compounding::Mean => "mean",
            Compounding::Maximum => "maximum",
            Compounding::Latest => "latest",
        }
        .into(),
        hole_filling: if voxel_options.hole_filling.is_enabled() {
            format!("{:?}", voxel_options.hole_filling.elements)
        } else {
            "none".into()
        },
        smoothing_sigma_mm: route.smoothing_sigma_mm,
        voxels_hit: stats.voxels_hit,
        voxels_filled: stats.voxels_filled,
        voxels_empty: stats.voxels_empty,
        voxels_with_data,
        triangles_dropped_at_data_edge: dropped,
        ignored_settings: voxel_options.ignored_settings.clone(),
    };
    let report = ExtractReport {
        method: "voxel".into(),
        parameters: UsedParameters {
            iso_levels: levels.clone(),
            iso_auto,
            smoothing_mm: options.fit.smoothing,
            accuracy_grey: options.fit.accuracy,
            eval_accuracy: options.fit.eval_accuracy,
            max_samples: options.max_samples,
            seed: options.seed,
            resolution_mm: volume.spacing_mm.x,
            trust_distance_mm: options
                .trust_distance_mm
                .unwrap_or_else(|| trust_distance_for(spacing)),
            world_frame: poses.world_frame.clone(),
            pixel_size_mm: calibration
                .map(|c| c.pixel_size_mm())
                .unwrap_or([f64::NAN, f64::NAN]),
            median_frame_spacing_mm: spacing,
            sample_bin_mm: options.sample_bin_mm,
            echo_margin_mm: None,
            sheet: super::Sheet::Iso,
            min_component_area_mm2: Some(0.0),
            segment: None,
        },
        levels: intensity_levels,
        counts,
        fit: None,
        surface: None,
        sheets: levels
            .iter()
            .map(|&level| super::SheetUsed::iso_surface(level))
            .collect(),
        voxel: Some(voxel_report),
        total_seconds: meter.total_seconds(),
        peak_rss_bytes: meter.peak_rss_bytes(),
        stages: meter.stages,
        warnings,
    };
    Ok(ExtractOutput {
        surfaces: levels
            .into_iter()
            .zip(meshes)
            .map(|(level, mesh)| ExtractedSurface { level, mesh })
            .collect(),
        model: None,
        samples: SampleSet::default(),
        frame_outlines: frame_outlines(sequence, &poses, calibration),
        report,
    })
}

/// Share of the data voxels assumed brighter than the boundary level: boundaries are thin sheets, a
/// small part of a volume that is mostly water and tissue speckle.
pub const BOUNDARY_PERCENTILE: f64 = 0.995;

/// Background = median of the data voxels, boundary = their [`BOUNDARY_PERCENTILE`] quantile, iso =
/// [`ISO_FRACTION`] of the way up (the RBF route's rule). Otsu's split, used on the kept pixels, separates
/// water from tissue speckle in a whole volume instead of background from boundary. `None` when all
/// values are equal.
pub fn volume_levels(mut data: Vec<f32>) -> Option<IntensityLevels> {
    data.retain(|v| v.is_finite());
    if data.is_empty() {
        return None;
    }
    let n = data.len();
    let median_index = n / 2;
    let top_index = ((n as f64 * BOUNDARY_PERCENTILE) as usize).min(n - 1);
    let (_, &mut top, _) = data.select_nth_unstable_by(top_index, f32::total_cmp);
    let (_, &mut background, _) =
        data[..=top_index].select_nth_unstable_by(median_index, f32::total_cmp);
    if top <= background {
        return None;
    }
    Some(IntensityLevels {
        background,
        boundary: top,
        strong_echo: top,
        iso: background + ISO_FRACTION * (top - background),
    })
}

/// A level outside the grey levels of the voxels with data has no surface.
fn check_levels_in_volume(levels: &[f64], values: &[f32], has_data: &[bool]) -> Result<()> {
    let (lo, hi) = values
        .iter()
        .zip(has_data)
        .filter(|(_, d)| **d)
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), (&x, _)| {
            (a.min(x), b.max(x))
        });
    if lo > hi {
        return Err(Error::InvalidInput(
            "the reconstructed volume holds no data (no pixel landed in the grid)".into(),
        ));
    }
    for &level in levels {
        if !level.is_finite() {
            return Err(Error::InvalidInput(format!(
                "iso-level {level} is not a number"
            )));
        }
        if level <= lo as f64 || level >= hi as f64 {
            return Err(Error::InvalidInput(format!(
                "iso-level {level} is outside the grey levels of the volume ({lo} to {hi}): it would \
                 give no surface"
            )));
        }
    }
    Ok(())
}

/// Drops the triangles whose marching-cubes cell has a corner without data, then the unused vertices.
fn drop_cells_without_data(
    mesh: Mesh,
    has_data: &[bool],
    volume: &crate::voxel::Volume,
) -> (Mesh, usize) {
    let [nx, ny, nz] = volume.dims;
    let cell_ok = |c: DVec3| -> bool {
        let q = (c - volume.origin_mm) / volume.spacing_mm;
        // A triangle lies inside one cell; its centroid is strictly inside unless degenerate, so the
        // clamp only matters for rounding at the grid's far faces.
        let i = (q.x.floor().max(0.0) as usize).min(nx.saturating_sub(2));
        let j = (q.y.floor().max(0.0) as usize).min(ny.saturating_sub(2));
        let k = (q.z.floor().max(0.0) as usize).min(nz.saturating_sub(2));
        (0..8).all(|corner| {
            let (di, dj, dk) = (corner & 1, (corner >> 1) & 1, corner >> 2);
            has_data[volume.index(i + di, j + dj, k + dk)]
        })
    };
    let keep: Vec<bool> = mesh
        .triangles
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(|i| mesh.vertices[i as usize]);
            cell_ok((a + b + c) / 3.0)
        })
        .collect();
    let dropped = keep.iter().filter(|&&k| !k).count();
    if dropped == 0 {
        return (mesh, 0);
    }
    let mut new_index = vec![u32::MAX; mesh.vertices.len()];
    let mut out = Mesh::default();
    let with_normals = mesh.normals.len() == mesh.vertices.len();
    for (t, _) in mesh.triangles.iter().zip(&keep).filter(|(_, k)| **k) {
        let mapped = t.map(|i| {
            let slot = &mut new_index[i as usize];
            if *slot == u32::MAX {
                *slot = out.vertices.len() as u32;
                out.vertices.push(mesh.vertices[i as usize]);
                if with_normals {
                    out.normals.push(mesh.normals[i as usize]);
                }
            }
            *slot
        });
        out.triangles.push(mapped);
    }
    (out, dropped)
}

/// Gaussian smoothing of `values` (x fastest) as a normalised convolution over the voxels where
/// `has_data`: returns `G*(d v) / G*d` and, as the new data mask, `G*d >= MIN_DATA_WEIGHT` (the kernel is
/// normalised, so `G*d` is the share of the kernel's weight on data). Voxels without data get 0.
/// Separable, truncated at 3 sigma; each output row is summed in a fixed order, so the result does not
/// depend on the thread count.
pub fn smooth_masked_gaussian(
    values: &[f32],
    has_data: &[bool],
    dims: [usize; 3],
    spacing_mm: DVec3,
    sigma_mm: f64,
) -> (Vec<f32>, Vec<bool>) {
    let n = dims[0] * dims[1] * dims[2];
    assert_eq!(values.len(), n, "values do not match the grid");
    assert_eq!(has_data.len(), n, "data mask does not match the grid");
    let mut weighted: Vec<f32> = values
        .iter()
        .zip(has_data)
        .map(|(&v, &d)| if d { v } else { 0.0 })
        .collect();
    let mut weight: Vec<f32> = has_data.iter().map(|&d| f32::from(u8::from(d))).collect();
    for axis in 0..3 {
        let kernel = gaussian_kernel(sigma_mm / spacing_mm[axis]);
        weighted = convolve_axis(&weighted, dims, axis, &kernel);
        weight = convolve_axis(&weight, dims, axis, &kernel);
    }
    let min_weight = MIN_DATA_WEIGHT as f32;
    let mask: Vec<bool> = weight.iter().map(|&w| w >= min_weight).collect();
    let smoothed = weighted
        .iter()
        .zip(&weight)
        .zip(&mask)
        .map(|((&v, &w), &ok)| if ok { v / w } else { 0.0 })
        .collect();
    (smoothed, mask)
}

/// Normalised Gaussian taps for a sigma in voxels, radius ceil(3 sigma) (at least 1 tap each side).
fn gaussian_kernel(sigma_voxels: f64) -> Vec<f32> {
    let radius = (3.0 * sigma_voxels).ceil().max(1.0) as i64;
    let taps: Vec<f64> = (-radius..=radius)
        .map(|k| (-0.5 * (k as f64 / sigma_voxels).powi(2)).exp())
        .collect();
    let sum: f64 = taps.iter().sum();
    taps.iter().map(|t| (t / sum) as f32).collect()
}

/// One 1-D convolution pass along `axis`, zero outside the grid; parallel over output rows along x.
fn convolve_axis(input: &[f32], dims: [usize; 3], axis: usize, kernel: &[f32]) -> Vec<f32> {
    let [nx, ny, nz] = dims;
    let radius = (kernel.len() / 2) as i64;
    let stride = [1, nx, nx * ny][axis];
    let extent = dims[axis] as i64;
    let mut out = vec![0.0f32; input.len()];
    out.par_chunks_mut(nx.max(1))
        .enumerate()
        .for_each(|(row, out_row)| {
            let (y, z) = (row % ny, row / ny);
            debug_assert!(z < nz);
            for (x, o) in out_row.iter_mut().enumerate() {
                let centre = x + nx * (y + ny * z);
                let position = [x, y, z][axis] as i64;
                let mut sum = 0.0f64;
                for (t, &w) in kernel.iter().enumerate() {
                    let offset = t as i64 - radius;
                    let p = position + offset;
                    if p < 0 || p >= extent {
                        continue;
                    }
                    let index = (centre as i64 + offset * stride as i64) as usize;
                    sum += w as f64 * input[index] as f64;
                }
                *o = sum as f32;
            }
        });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A linear ramp is reproduced exactly by a normalised, symmetric kernel away from the data edge,
    /// and voxels without data neither darken nor brighten their neighbours.
    #[test]
    fn masked_smoothing_keeps_a_ramp_and_ignores_empty_voxels() {
        let dims = [20, 12, 10];
        let n = dims[0] * dims[1] * dims[2];
        let mut values = vec![0.0f32; n];
        let mut has_data = vec![false; n];
        for z in 0..dims[2] {
            for y in 0..dims[1] {
                for x in 0..dims[0] {
                    let i = x + dims[0] * (y + dims[1] * z);
                    // Data only for x < 14; beyond it the voxels are empty (value 0).
                    if x < 14 {
                        values[i] = 10.0 + 3.0 * x as f32 + 2.0 * y as f32;
                        has_data[i] = true;
                    }
                }
            }
        }
        let (smoothed, mask) =
            smooth_masked_gaussian(&values, &has_data, dims, DVec3::splat(0.5), 0.5);
        let at = |x: usize, y: usize, z: usize| x + dims[0] * (y + dims[1] * z);
        // Interior, >= 3 sigma (3 voxels) from every edge: the ramp is unchanged (f32 rounding only).
        for (x, y, z) in [(5, 5, 5), (8, 4, 4), (10, 6, 5)] {
            let expected = 10.0 + 3.0 * x as f32 + 2.0 * y as f32;
            assert!((smoothed[at(x, y, z)] - expected).abs() < 1e-3);
            assert!(mask[at(x, y, z)]);
        }
        // Next to the empty region the value is a mean of data only: between the ramp values in reach,
        // not pulled toward the empty voxels' 0.
        let edge = smoothed[at(13, 5, 5)];
        assert!(
            edge > 10.0 + 3.0 * 10.0 && edge <= 10.0 + 3.0 * 13.0 + 10.0,
            "{edge}"
        );
        // Far past the data edge: no data.
        assert!(!mask[at(19, 5, 5)]);
        assert_eq!(smoothed[at(19, 5, 5)], 0.0);
        // One voxel past the edge (sigma = 1 voxel): weight share ~0.16 < 0.3 -> still no data.
        assert!(!mask[at(15, 5, 5)]);
    }

    #[test]
    fn kernel_is_normalised_and_symmetric() {
        for sigma in [0.3, 1.0, 2.7] {
            let k = gaussian_kernel(sigma);
            assert_eq!(k.len() % 2, 1);
            let sum: f32 = k.iter().sum();
            assert!((sum - 1.0).abs() < 1e-6);
            for i in 0..k.len() / 2 {
                assert_eq!(k[i], k[k.len() - 1 - i]);
            }
        }
    }
}
