//! `echosurf sample`: the samples the fit of `extract` would see (same segmentation, block averaging and
//! thinning, same defaults), as a point cloud.

use std::path::PathBuf;

use anyhow::Context;
use echosurf::io;
use echosurf::pipeline::{self, ExtractOptions};
use echosurf::resources::StageMeter;
use echosurf::segment::InitialBand;

use super::extract::echo_margin;
use super::outputs::{Holds, check_outputs, output};
use super::segment::{SegmentArgs, world_choice};
use crate::progress::BarProgress;

#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub segment: SegmentArgs,
    /// Keep at most this many samples (the paper: ~10k large features, ~100k detail); default: all.
    #[arg(long)]
    pub max_samples: Option<usize>,
    /// Average kept pixels over blocks of about this size (mm) first; 0 = single pixels.
    #[arg(long, default_value_t = 0.4)]
    pub sample_bin: f64,
    /// Echo-priority thinning margin (mm), as in `extract`; 0 = uniform random thinning.
    #[arg(long, default_value_t = pipeline::DEFAULT_ECHO_MARGIN_MM)]
    pub echo_margin: f64,
    /// Seed of the random thinning (`extract` uses the same default).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Output point cloud (binary PLY, x y z in mm + float intensity).
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let seg = &args.segment;
    check_outputs(
        &seg.input_files(),
        &[output("--out", &args.out, Holds::PointCloud)],
    )?;
    if !(args.sample_bin.is_finite() && args.sample_bin >= 0.0) {
        anyhow::bail!("--sample-bin must be a size in mm >= 0");
    }
    let sequence = super::inputs::read_sequence(&seg.sequence)?;
    let calibration = io::read_calibration(&seg.calibration)?;
    let init = match (&seg.init, seg.auto_init) {
        (Some(path), false) => InitialBand::load(path, sequence.width, sequence.height)?,
        (None, true) => InitialBand::Auto,
        _ => anyhow::bail!("give the initial band with --init FILE or ask for --auto-init"),
    };
    // After the band: a bad band file is the more specific complaint.
    super::inputs::check_clip(&calibration, &sequence, &seg.calibration, &seg.sequence)?;
    let options = ExtractOptions {
        init,
        segment: seg.options(),
        reference: world_choice(&seg.world)?,
        max_samples: args.max_samples.unwrap_or(usize::MAX),
        seed: args.seed,
        sample_bin_mm: args.sample_bin,
        echo_margin_mm: echo_margin(args.echo_margin)?,
        ..ExtractOptions::default()
    };
    let progress = BarProgress::new();
    let prepared = pipeline::prepare_samples(
        &sequence,
        Some(&calibration),
        &options,
        &mut StageMeter::new(&progress),
        &progress,
    )
    .with_context(|| format!("sampling {}", seg.sequence.display()))?;
    for w in &prepared.masks.warnings {
        eprintln!("warning: {w}");
    }
    let set = &prepared.samples;
    io::write_point_cloud(&args.out, &set.to_point_cloud())?;
    out!(
        "wrote {} of {} samples ({} kept pixels, {} near echoes; {} world frame)",
        set.len(),
        prepared.all.len(),
        prepared.counts.kept_pixels,
        prepared.counts.near_echo_samples,
        prepared.poses.world_frame
    );
    match prepared.levels {
        Some(l) => outln!(
            "; levels: background {:.1}, boundary {:.1}, suggested iso {:.1}",
            l.background,
            l.boundary,
            l.iso
        ),
        None => outln!(),
    }
    Ok(())
}
