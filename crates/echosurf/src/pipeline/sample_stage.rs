//! From a segmented sequence to the samples of the fit: placing frames, collecting and thinning
//! the kept pixels, and checking the fit against the data.

use super::{
    BandMasks, Calibration, ECHO_BUDGET_SHARE, ECHO_LEVEL_FRACTION, Error, ExtractOptions,
    IntensityLevels, MIN_SWEEP_SPAN_MM, PoseResolution, Progress, Result, SampleSet, StageCounts,
    StageMeter, TrackedSequence, collect_samples_binned_with_cells, estimate_echo_levels,
    estimate_levels, near_echo_flags, priority_decimate, random_decimate, resolve_poses,
    segment_sequence, sweep_span_mm,
};

/// The samples of a sequence and what it took to get them (shared by `extract` and `sample`).
#[derive(Debug)]
pub struct PreparedSamples {
    pub poses: PoseResolution,
    pub masks: BandMasks,
    /// All kept pixels as samples.
    pub all: SampleSet,
    /// The decimated set handed to the fit.
    pub samples: SampleSet,
    pub levels: Option<IntensityLevels>,
    pub counts: StageCounts,
    pub pixel_size_mm: [f64; 2],
}

/// The first stage of both routes: refuses a sequence without images and resolves every frame's pose.
pub(crate) fn place_frames(
    sequence: &TrackedSequence,
    calibration: Option<&Calibration>,
    options: &ExtractOptions,
    meter: &mut StageMeter,
) -> Result<PoseResolution> {
    if sequence.is_tracking_only() {
        return Err(Error::InvalidInput(
            "the sequence has no images (tracking only): nothing to extract a surface from".into(),
        ));
    }
    let poses = meter.stage("poses", || {
        resolve_poses(
            sequence,
            calibration,
            options.reference,
            std::path::Path::new("<sequence>"),
        )
    })?;
    let span_mm = sweep_span_mm(sequence.width, sequence.height, &poses.poses);
    if let Some(mm) = span_mm.filter(|&mm| mm < MIN_SWEEP_SPAN_MM) {
        return Err(Error::InvalidInput(format!(
            "all {} placed frames lie within {mm:.2} mm of one plane: the probe was not swept (or its \
             poses do not change), so the frames hold no volume to extract a surface from",
            poses.poses.len()
        )));
    }
    Ok(poses)
}

/// Places the frames, segments the bands and turns kept pixels into (decimated) samples.
pub fn prepare_samples(
    sequence: &TrackedSequence,
    calibration: Option<&Calibration>,
    options: &ExtractOptions,
    meter: &mut StageMeter,
    progress: &dyn Progress,
) -> Result<PreparedSamples> {
    let poses = place_frames(sequence, calibration, options, meter)?;
    let clip = calibration.and_then(|c| c.clip);
    let masks = meter.stage("segment", || {
        segment_sequence(
            sequence,
            &poses,
            clip,
            &options.init,
            &options.segment,
            progress,
        )
    })?;
    prepare_samples_from_masks(sequence, calibration, options, meter, poses, masks)
}

/// [`prepare_samples`] after the segmentation: the kept pixels of `masks` (one per frame of
/// `sequence`) as (decimated) samples. `live` segments frames as they arrive and calls this.
pub fn prepare_samples_from_masks(
    sequence: &TrackedSequence,
    calibration: Option<&Calibration>,
    options: &ExtractOptions,
    meter: &mut StageMeter,
    poses: PoseResolution,
    masks: BandMasks,
) -> Result<PreparedSamples> {
    let pixel_size_mm = calibration
        .map(|c| c.pixel_size_mm())
        .unwrap_or([f64::NAN, f64::NAN]);
    let bin_px = sample_bin_px(options.sample_bin_mm, pixel_size_mm);
    if let Some(budget) = options.memory_budget_bytes {
        let counts = crate::budget::SegmentedCounts {
            frame_pixels: (poses.poses.len() * sequence.width * sequence.height) as u64,
            kept_pixels: poses
                .poses
                .iter()
                .map(|p| masks.kept_count(p.frame_index) as u64)
                .sum(),
            bin_px,
            bone_sweep: masks.bone_sweep,
        };
        crate::budget::check_extract_budget_after_segmentation(
            counts,
            fit_plan(options),
            budget,
            meter.observer(),
        )?;
    }
    // A bone band is fitted against each echo's own contrast (see `segment::bone`).
    let normalised = masks.bone_sweep.then(|| {
        let px = masks.parameters.pixel_size_mm.unwrap_or(1.0);
        let b = &options.segment.bone_echoes;
        let core = [b.band_above_mm, b.band_below_mm].map(|mm| (mm / px).round() as usize);
        crate::segment::bone::contrast_normalised(sequence, &masks.masks, &masks.bone_echoes, core)
    });
    let sampled = normalised.as_ref().unwrap_or(sequence);
    let (all, cells) = meter.stage("samples", || {
        collect_samples_binned_with_cells(sampled, &poses, &masks, bin_px)
    });
    if all.is_empty() {
        return Err(Error::InvalidInput(
            "segmentation kept no pixels: no samples to fit (check the initial band or the clip rectangle)"
                .into(),
        ));
    }
    let levels =
        estimate_echo_levels(sampled, &poses, &masks).or_else(|| estimate_levels(&all.intensities));
    let (samples, near_echo_samples) =
        meter.stage("decimate", || match (options.echo_margin_mm, levels) {
            (Some(margin_mm), Some(l)) if all.len() > options.max_samples => {
                let echo_level = l.background + ECHO_LEVEL_FRACTION * (l.boundary - l.background);
                let radius = echo_margin_cells(margin_mm, bin_px, pixel_size_mm);
                let flags = near_echo_flags(&all, &cells, echo_level, radius);
                let max_flagged = (ECHO_BUDGET_SHARE * options.max_samples as f64) as usize;
                let near = flags.iter().filter(|&&f| f).count();
                let thinned =
                    priority_decimate(&all, &flags, options.max_samples, max_flagged, options.seed);
                (thinned, near)
            }
            _ => (random_decimate(&all, options.max_samples, options.seed), 0),
        });
    let counts = StageCounts {
        frames: sequence.frames.len(),
        frames_used: poses.poses.len(),
        pixels: poses.poses.len() * sequence.width * sequence.height,
        kept_pixels: poses
            .poses
            .iter()
            .map(|p| masks.kept_count(p.frame_index))
            .sum(),
        binned_samples: all.len(),
        near_echo_samples,
        samples: samples.len(),
        bone_sweep: masks.bone_sweep,
        ..Default::default()
    };
    Ok(PreparedSamples {
        poses,
        masks,
        all,
        samples,
        levels,
        counts,
        pixel_size_mm,
    })
}

/// What the memory budget reads of `options` (see [`crate::budget::FitPlan`]).
pub fn fit_plan(options: &ExtractOptions) -> crate::budget::FitPlan<'_> {
    crate::budget::FitPlan {
        max_samples: options.max_samples,
        fit: &options.fit,
    }
}

/// Block size in pixels for [`ExtractOptions::sample_bin_mm`]: the nearest whole number of pixels along
/// each image axis, at least 1 (1 without a known pixel size).
pub fn sample_bin_px(bin_mm: f64, pixel_size_mm: [f64; 2]) -> [usize; 2] {
    pixel_size_mm.map(|p| {
        if bin_mm > 0.0 && p.is_finite() && p > 0.0 {
            ((bin_mm / p).round() as usize).clamp(1, 64)
        } else {
            1
        }
    })
}

/// [`ExtractOptions::echo_margin_mm`] in sample blocks along each image axis (at least 1 block; a
/// 1 mm guess per pixel without a known pixel size).
pub fn echo_margin_cells(
    margin_mm: f64,
    bin_px: [usize; 2],
    pixel_size_mm: [f64; 2],
) -> [usize; 2] {
    [0, 1].map(|a| {
        let block_mm = bin_px[a] as f64 * pixel_size_mm[a];
        let block_mm = if block_mm.is_finite() && block_mm > 0.0 {
            block_mm
        } else {
            bin_px[a] as f64
        };
        ((margin_mm / block_mm).ceil() as usize).clamp(1, 1024)
    })
}

/// Fits whose rms data misfit exceeds this fraction of the samples' grey range are implausible.
pub const IMPLAUSIBLE_MISFIT_FRACTION: f64 = 0.1;

/// A warning when the fit's rms data misfit `|f_i - s(x_i)|` is more than
/// [`IMPLAUSIBLE_MISFIT_FRACTION`] of the samples' grey range: the smoothing cannot explain that much,
/// the samples contradict each other where frames cross (a wrong calibration or tracking is the usual
/// reason).
pub fn implausible_fit_warning(report: &crate::rbf::FitReport, values: &[f64]) -> Option<String> {
    let (lo, hi) = values
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
    let range = hi - lo;
    (range > 0.0 && report.rms_data_misfit > IMPLAUSIBLE_MISFIT_FRACTION * range).then(|| {
        format!(
            "the fit misses the samples by {:.1} grey rms (max {:.1}) at smoothing {} mm, more than \
             {:.0} % of their grey range {:.0}-{:.0}: crossing frames disagree, most often because \
             the calibration (or tracking) does not belong to this sweep",
            report.rms_data_misfit,
            report.max_data_misfit,
            report.smoothing,
            100.0 * IMPLAUSIBLE_MISFIT_FRACTION,
            lo,
            hi
        )
    })
}
