//! The whole route from a tracked sequence to surfaces: segment -> samples -> reduce -> fit -> surface,
//! with defaults derived from the data and a report of what every stage did, how long it took and how
//! much memory it needed. The CLI's `extract`, `sample` and `demo` are thin wrappers around this.

use glam::DVec3;

use crate::io::pose::{
    FramePlane, MIN_SWEEP_SPAN_MM, clip_corners_px, frame_corners, sweep_span_mm,
};
use crate::io::{Calibration, PoseResolution, ReferenceChoice, TrackedSequence, resolve_poses};
use crate::mesh::Mesh;
use crate::progress::Progress;
use crate::rbf::{FitOptions, FitReport, RbfModel};
use crate::resources::{StageMeter, StageUsage};
use crate::samples::{
    IntensityLevels, SampleSet, collect_samples_binned_with_cells, estimate_echo_levels,
    estimate_levels, near_echo_flags, priority_decimate, random_decimate,
};
use crate::segment::crests::{CrestCache, crest_crop};
use crate::segment::{
    BandMasks, InitialBand, ResolvedParameters, SegmentOptions, segment_sequence,
};
use crate::surface::{
    RidgeOptions, SheetOptions, SurfaceDomain, SurfaceOptions, SurfaceStats, WeakRidge,
    extend_ridge_sheet, extract_surfaces_with_stats, proximal_sheet_on_ridge, sheet_through_points,
};
use crate::{Error, Result};
use echo_reach::EchoReach;

mod echo_reach;
mod extract_options;
mod options;
mod report;
mod sample_stage;
mod surface_stage;
mod voxel_route;

pub use options::{
    CleanupTuning, ExtractConfig, MethodChoice, OptionError, SamplingTuning, Tuning, UserOptions,
};

pub use voxel_route::{VoxelRouteOptions, VoxelRouteReport, smooth_masked_gaussian};

pub use extract_options::*;
pub use report::*;
pub use sample_stage::*;
pub use surface_stage::*;

/// The whole pipeline on an in-memory sequence.
pub fn extract(
    sequence: &TrackedSequence,
    calibration: Option<&Calibration>,
    options: &ExtractOptions,
    progress: &dyn Progress,
) -> Result<ExtractOutput> {
    extract_reusing(sequence, calibration, options, Reused::default(), progress)
}

/// [`extract`] on bands segmented elsewhere (`masks`: one per frame of `sequence`, as
/// [`segment_sequence`] makes them): `live` segments each frame once, as it arrives, and refits
/// from here. The RBF route only; no memory budget check.
pub fn extract_with_masks(
    sequence: &TrackedSequence,
    calibration: Option<&Calibration>,
    options: &ExtractOptions,
    masks: BandMasks,
    progress: &dyn Progress,
) -> Result<ExtractOutput> {
    let reused = Reused {
        masks: Some(masks),
        crests: None,
    };
    extract_reusing(sequence, calibration, options, reused, progress)
}

/// What earlier work on the same recording (one that only grows, as `live` records it) hands to
/// [`extract_reusing`].
#[derive(Debug, Default)]
pub struct Reused<'a> {
    /// Bands segmented elsewhere, one per frame (see [`extract_with_masks`]).
    pub masks: Option<BandMasks>,
    /// The frames' echo crests found so far: the frames not in it are added, and the mesh is the
    /// one [`extract`] makes.
    pub crests: Option<&'a mut CrestCache>,
}

/// [`extract`], reusing what `reused` holds. With masks: the RBF route only, no memory budget check.
pub fn extract_reusing(
    sequence: &TrackedSequence,
    calibration: Option<&Calibration>,
    options: &ExtractOptions,
    reused: Reused,
    progress: &dyn Progress,
) -> Result<ExtractOutput> {
    let mut meter = StageMeter::new(progress);
    let prepared = match reused.masks {
        None => {
            if let Method::Voxel(route) = &options.method {
                return voxel_route::extract_voxel(sequence, calibration, options, route, progress);
            }
            if let Some(budget) = options.memory_budget_bytes {
                crate::budget::check_extract_budget(sequence, budget, progress)?;
            }
            prepare_samples(sequence, calibration, options, &mut meter, progress)?
        }
        Some(masks) => {
            if masks.masks.len() != sequence.frames.len() {
                return Err(Error::InvalidInput(format!(
                    "{} band masks for {} frames",
                    masks.masks.len(),
                    sequence.frames.len()
                )));
            }
            let poses = place_frames(sequence, calibration, options, &mut meter)?;
            prepare_samples_from_masks(sequence, calibration, options, &mut meter, poses, masks)?
        }
    };
    let mut own_crests = CrestCache::default();
    let crests = reused.crests.unwrap_or(&mut own_crests);
    extract_from_prepared(
        sequence,
        calibration,
        options,
        meter,
        prepared,
        crests,
        progress,
    )
}

/// Adds to `cache` the echo crests of the frames of `sequence` it lacks, as [`extract_reusing`] with
/// `options` reads them, `step` frames at a time while `go_on()` holds; nothing when `options` read no
/// crests (the iso-surface, crests off, the voxel route). For a recording that grows (`live`): the final
/// mesh then reads only the frames that came after.
pub fn add_echo_crests(
    sequence: &TrackedSequence,
    calibration: Option<&Calibration>,
    options: &ExtractOptions,
    cache: &mut CrestCache,
    step: usize,
    go_on: &dyn Fn() -> bool,
) -> Result<()> {
    if options.sheet == Sheet::Iso
        || !options.image_crests.enabled
        || matches!(options.method, Method::Voxel(_))
    {
        return Ok(());
    }
    options.image_crests.crest.validate()?;
    let poses = resolve_poses(
        sequence,
        calibration,
        options.reference,
        std::path::Path::new("<sequence>"),
    )?;
    let clip = calibration.and_then(|c| c.clip);
    let Some(crop) = crest_crop(sequence, &poses, clip, options.segment.detect_data_region) else {
        return Ok(());
    };
    for frames in poses.poses.chunks(step.max(1)) {
        if !go_on() {
            break;
        }
        cache.fill(sequence, frames, crop, &options.image_crests.crest);
    }
    Ok(())
}

/// The RBF route after the samples: fit, surface, sheets and pieces, and the report.
fn extract_from_prepared(
    sequence: &TrackedSequence,
    calibration: Option<&Calibration>,
    options: &ExtractOptions,
    mut meter: StageMeter,
    prepared: PreparedSamples,
    crest_cache: &mut CrestCache,
    progress: &dyn Progress,
) -> Result<ExtractOutput> {
    let mut warnings = prepared.masks.warnings.clone();

    let (levels, iso_auto) = match &options.iso {
        IsoLevels::Auto => {
            let l = prepared.levels.ok_or_else(|| {
                Error::InvalidInput(
                    "cannot choose an iso-level automatically: the kept pixels all have one grey level".into(),
                )
            })?;
            (vec![l.iso as f64], true)
        }
        IsoLevels::Levels(v) if v.is_empty() => {
            return Err(Error::InvalidInput("no iso-level given".into()));
        }
        IsoLevels::Levels(v) => (v.clone(), false),
    };
    check_levels(&levels, &prepared.samples)?;

    let positions = &prepared.samples.positions;
    let values: Vec<f64> = prepared
        .samples
        .intensities
        .iter()
        .map(|&v| v as f64)
        .collect();
    let (model, fit_report) = meter.stage("fit", || {
        let fit_options = FitOptions {
            seed: options.seed,
            ..options.fit.clone()
        };
        crate::rbf::fit(positions, &values, &fit_options, progress)
    })?;
    if let Some(w) = implausible_fit_warning(&fit_report, &values) {
        warnings.push(w);
    }

    let spacing = median_frame_spacing_mm(sequence, &prepared.poses);
    let trust_distance_mm = options
        .trust_distance_mm
        .unwrap_or_else(|| trust_distance_for(spacing));
    let seed_band = match prepared.levels {
        Some(l) => SEED_BAND_FRACTION * (l.boundary - l.background).abs() as f64,
        None => 10.0,
    };
    let domain = surface_domain(positions, &values, &levels, seed_band, trust_distance_mm);
    let surface_options = SurfaceOptions {
        trust_distance_mm,
        ..options.surface.clone()
    };
    if let Some(budget) = options.memory_budget_bytes {
        crate::budget::check_surface_budget(
            domain.seeds.len() as u64,
            surface_options.resolution_mm,
            budget,
            progress,
        )?;
    }
    let (mut meshes, surface_stats) = meter.stage("surface", || {
        extract_surfaces_with_stats(&model, &levels, &domain, &surface_options)
    })?;
    for l in &surface_stats.levels {
        if l.off_level_vertices > 0 {
            warnings.push(format!(
                "iso-level {}: {} of {} vertices could not be put within {} grey of the level (worst \
                 {:.2}); they are kept and counted in the report (surface.levels.off_level_vertices)",
                l.level,
                l.off_level_vertices,
                l.vertices,
                crate::surface::LEVEL_TOLERANCE,
                l.max_level_error
            ));
        }
    }
    let mut sheets: Vec<SheetUsed> = levels
        .iter()
        .map(|&level| SheetUsed::iso_surface(level))
        .collect();
    // The frames' echo crests extend a ridge sheet (not on a bone sweep). Finding them (per frame, in
    // parallel) runs beside drawing the sheets, whose sequential steps leave a core idle.
    let mut crests = None;
    if options.sheet != Sheet::Iso {
        let beams = FrameBeams::new(sequence, &prepared.poses, trust_distance_mm);
        let ridge = RidgeInputs {
            model: &model,
            beams: &beams,
            domain: &domain,
            surface_options: &surface_options,
            levels: prepared.levels,
            bone_sweep: prepared.counts.bone_sweep,
        };
        crests = meter.stage("ridge", || {
            let ridges = echo_ridges_to_draw(&meshes, &mut sheets, &ridge, options);
            let find_crests = ridges.iter().any(Option::is_some)
                && !prepared.counts.bone_sweep
                && options.image_crests.enabled;
            let (drawn, crests) = rayon::join(
                || draw_echo_ridge_sheets(&mut meshes, &mut sheets, &ridges, &ridge, options),
                || {
                    find_crests.then(|| {
                        oriented_echo_crests(
                            sequence,
                            &prepared.poses,
                            calibration.and_then(|c| c.clip),
                            options.segment.detect_data_region,
                            &options.image_crests,
                            crest_cache,
                        )
                    })
                },
            );
            drawn?;
            crests.transpose()
        })?;
    }
    let extension = crests.as_ref().map(|crests| CrestExtension {
        crests,
        domain: &domain,
        surface_options: &surface_options,
    });
    meter.stage("pieces", || {
        remove_and_join_pieces(
            &mut meshes,
            &mut sheets,
            &prepared,
            [sequence.width, sequence.height],
            trust_distance_mm,
            extension.as_ref(),
            options,
        )
    })?;
    for (used, mesh) in sheets.iter().zip(&meshes) {
        if mesh.is_empty() && used.pieces_without_echoes > 0 {
            warnings.push(format!(
                "iso-level {}: every piece of surface ({}) was echoed by fewer than {} frames and removed \
                 (tuning.cleanup.min_echo_frames = 0 keeps them)",
                used.level, used.pieces_without_echoes, used.min_echo_frames
            ));
        } else if mesh.is_empty() {
            warnings.push(format!(
                "iso-level {}: no surface found inside the region of trust",
                used.level
            ));
        }
    }

    let mut counts = prepared.counts.clone();
    counts.centres = fit_report.centres;
    counts.triangles = meshes.iter().map(|m| m.triangles.len()).collect();
    let report = ExtractReport {
        method: "rbf".into(),
        parameters: UsedParameters {
            iso_levels: levels.clone(),
            iso_auto,
            smoothing_mm: options.fit.smoothing,
            accuracy_grey: options.fit.accuracy,
            eval_accuracy: options.fit.eval_accuracy,
            max_samples: options.max_samples,
            seed: options.seed,
            resolution_mm: surface_options.resolution_mm,
            trust_distance_mm,
            world_frame: prepared.poses.world_frame.clone(),
            pixel_size_mm: prepared.pixel_size_mm,
            median_frame_spacing_mm: spacing,
            sample_bin_mm: options.sample_bin_mm,
            echo_margin_mm: options.echo_margin_mm,
            sheet: options.sheet,
            min_component_area_mm2: options.min_component_area_mm2,
            segment: Some(prepared.masks.parameters),
        },
        levels: prepared.levels,
        counts,
        fit: Some(fit_report),
        surface: Some(surface_stats),
        sheets,
        voxel: None,
        total_seconds: meter.total_seconds(),
        peak_rss_bytes: meter.peak_rss_bytes(),
        stages: meter.stages,
        warnings,
    };
    let frame_outlines = frame_outlines(sequence, &prepared.poses, calibration);
    Ok(ExtractOutput {
        surfaces: levels
            .into_iter()
            .zip(meshes)
            .map(|(level, mesh)| ExtractedSurface { level, mesh })
            .collect(),
        model: Some(model),
        samples: prepared.samples,
        frame_outlines,
        report,
    })
}

#[cfg(test)]
mod tests;
