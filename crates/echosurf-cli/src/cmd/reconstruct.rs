//! `echosurf reconstruct`: a voxel volume from a tracked sequence, as PLUS's VolumeReconstructor
//! makes it, with the defaults taken from the configuration's `VolumeReconstruction` element.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use echosurf::io::{ReferenceChoice, resolve_poses};
use echosurf::voxel::{
    Compounding, HoleFilling, HoleFillingElement, Interpolation, options_from_config_xml,
    reconstruct_volume, write_volume_mha,
};
use glam::DVec3;

use super::outputs::{Holds, check_outputs, output};

use crate::progress::BarProgress;

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum InterpolationArg {
    /// Nearest voxel (PLUS NEAREST_NEIGHBOR).
    Nn,
    /// Trilinear splat over 8 voxels (PLUS LINEAR).
    Linear,
}

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum CompoundingArg {
    Mean,
    Max,
    Latest,
}

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum FillHolesArg {
    None,
    /// PLUS STICK (the configuration's parameters if it has a STICK element, else length 9, 1 stick).
    Stick,
    /// PLUS GAUSSIAN (the configuration's parameters if it has one, else size 5, stdev 0.6667,
    /// more than 25% of the cube known).
    Gaussian,
}

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Tracked sequence (.mha, .mhd, .nrrd).
    pub sequence: PathBuf,
    /// PLUS device-set XML: calibration and VolumeReconstruction settings.
    #[arg(long)]
    pub calibration: PathBuf,
    /// Output volume (.mha).
    #[arg(long)]
    pub out: PathBuf,
    /// Isotropic voxel size in mm (default: the configuration's OutputSpacing, else 0.5).
    #[arg(long)]
    pub spacing: Option<f64>,
    /// Splatting (default: the configuration's Interpolation, else linear as in PLUS).
    #[arg(long, value_enum)]
    pub interpolation: Option<InterpolationArg>,
    /// Compounding (default: the configuration's CompoundingMode, else mean).
    #[arg(long, value_enum)]
    pub compounding: Option<CompoundingArg>,
    /// Hole filling (default: the configuration's FillHoles and HoleFilling elements).
    #[arg(long, value_enum)]
    pub fill_holes: Option<FillHolesArg>,
    /// Refuse grids whose buffers need more than this many MB (default: half the machine's memory).
    #[arg(long)]
    pub memory_budget: Option<f64>,
    /// Write the voxel data uncompressed (default: zlib, as PLUS writes).
    #[arg(long)]
    pub uncompressed: bool,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let mut inputs = echosurf::io::sequence_files(&args.sequence);
    inputs.push(args.calibration.clone());
    check_outputs(&inputs, &[output("--out", &args.out, Holds::MetaImage)])?;
    let started = Instant::now();
    let sequence = super::inputs::read_sequence(&args.sequence)?;
    let calibration =
        super::inputs::read_calibration_for(&args.calibration, &sequence, &args.sequence)?;
    let xml = std::fs::read_to_string(&args.calibration)
        .with_context(|| format!("reading {}", args.calibration.display()))?;
    let mut options = options_from_config_xml(&xml, &args.calibration)?;
    if options.clip.is_none() {
        options.clip = calibration.clip;
    }
    if let Some(s) = args.spacing {
        anyhow::ensure!(
            s.is_finite() && s > 0.0,
            "--spacing must be a positive number of mm, got {s}"
        );
        options.spacing_mm = DVec3::splat(s);
    }
    if let Some(i) = args.interpolation {
        options.interpolation = match i {
            InterpolationArg::Nn => Interpolation::NearestNeighbor,
            InterpolationArg::Linear => Interpolation::Linear,
        };
    }
    if let Some(c) = args.compounding {
        options.compounding = match c {
            CompoundingArg::Mean => Compounding::Mean,
            CompoundingArg::Max => Compounding::Maximum,
            CompoundingArg::Latest => Compounding::Latest,
        };
    }
    if let Some(f) = args.fill_holes {
        let configured = echosurf::voxel::hole_filling_from_xml(&xml, &args.calibration)?;
        let pick =
            |want: fn(&HoleFillingElement) -> bool| configured.elements.iter().copied().find(&want);
        options.hole_filling = match f {
            FillHolesArg::None => HoleFilling::none(),
            FillHolesArg::Stick => pick(|e| matches!(e, HoleFillingElement::Stick { .. }))
                .map(|e| HoleFilling { elements: vec![e] })
                .unwrap_or_else(|| HoleFilling::stick(9, 1)),
            FillHolesArg::Gaussian => pick(|e| matches!(e, HoleFillingElement::Gaussian { .. }))
                .map(|e| HoleFilling { elements: vec![e] })
                .unwrap_or_else(|| HoleFilling::gaussian(5, 0.6667, 0.25)),
        };
    }
    options.memory_budget_bytes = super::extract::memory_budget_bytes(args.memory_budget)?;
    for ignored in &options.ignored_settings {
        eprintln!("warning: {}: ignored {ignored}", args.calibration.display());
    }

    let poses = resolve_poses(
        &sequence,
        Some(&calibration),
        ReferenceChoice::Auto,
        &args.sequence,
    )?;
    for (frame, reason) in &poses.skipped {
        eprintln!("warning: frame {frame} not used: {reason}");
    }
    let progress = BarProgress::new();
    let recon_started = Instant::now();
    let volume = reconstruct_volume(&sequence, &poses, &options, &progress)
        .map_err(|e| super::extract::name_voxel_options(e, "--spacing"))
        .with_context(|| format!("reconstructing {}", args.sequence.display()))?;
    let recon_s = recon_started.elapsed().as_secs_f64();
    write_volume_mha(&args.out, &volume, !args.uncompressed)?;

    let s = &volume.stats;
    let n = volume.len() as f64;
    outln!(
        "{}: {}x{}x{} voxels at {} mm, origin {:.4} {:.4} {:.4} mm ({} frame)",
        args.out.display(),
        volume.dims[0],
        volume.dims[1],
        volume.dims[2],
        format_spacing(volume.spacing_mm),
        volume.origin_mm.x,
        volume.origin_mm.y,
        volume.origin_mm.z,
        poses.world_frame
    );
    outln!(
        "{:?} / {:?}, hole filling {}: {} frames, {} pixels; voxels hit {:.1}%, filled {:.1}%, empty {:.1}%",
        options.interpolation,
        options.compounding,
        describe_filling(&options.hole_filling),
        s.frames_inserted,
        s.pixels_inserted,
        100.0 * s.voxels_hit as f64 / n,
        100.0 * s.voxels_filled as f64 / n,
        100.0 * s.voxels_empty as f64 / n
    );
    if s.accumulation_overflows > 0 {
        eprintln!(
            "warning: {} voxels received more than 255 pixels (PLUS's accumulation limit); a finer spacing avoids this",
            s.accumulation_overflows
        );
    }
    outln!(
        "reconstruction {:.2} s, total {:.2} s",
        recon_s,
        started.elapsed().as_secs_f64()
    );
    Ok(())
}

fn format_spacing(s: DVec3) -> String {
    if s.x == s.y && s.y == s.z {
        format!("{}", s.x)
    } else {
        format!("{} {} {}", s.x, s.y, s.z)
    }
}

fn describe_filling(h: &HoleFilling) -> String {
    if h.elements.is_empty() {
        return "off".into();
    }
    h.elements
        .iter()
        .map(|e| match e {
            HoleFillingElement::Stick {
                length_limit,
                sticks_to_use,
            } => format!("STICK({length_limit}, {sticks_to_use})"),
            HoleFillingElement::Gaussian { size, stdev, .. } => {
                format!("GAUSSIAN({size}, {stdev})")
            }
            HoleFillingElement::GaussianAccumulation { size, stdev, .. } => {
                format!("GAUSSIAN_ACCUMULATION({size}, {stdev})")
            }
            HoleFillingElement::NearestNeighbor { size, .. } => format!("NEAREST_NEIGHBOR({size})"),
            HoleFillingElement::DistanceWeightInverse { size, .. } => {
                format!("DISTANCE_WEIGHT_INVERSE({size})")
            }
        })
        .collect::<Vec<_>>()
        .join(" then ")
}
