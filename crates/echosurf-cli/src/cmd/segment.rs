//! `echosurf segment`.

use std::path::PathBuf;

use anyhow::Context;
use echosurf::io::{self, ReferenceChoice};
use echosurf::segment::bone::BoneMode;
use echosurf::segment::{
    InitialBand, Length, SegmentOptions, default_preview_frames, segment_sequence,
    write_band_preview,
};

use super::outputs::{Holds, check_outputs, output};
use crate::progress::BarProgress;

/// `--world`: auto, tracker or reference (case-insensitive).
pub(crate) fn world_choice(text: &str) -> anyhow::Result<ReferenceChoice> {
    Ok(match text.to_ascii_lowercase().as_str() {
        "auto" => ReferenceChoice::Auto,
        "tracker" => ReferenceChoice::Tracker,
        "reference" => ReferenceChoice::Reference,
        other => anyhow::bail!("--world {other}: expected auto, tracker or reference"),
    })
}

/// Options shared by `segment` and `sample`: the sequence, its calibration, the initial band and the
/// paper's parameters.
#[derive(Debug, clap::Args)]
pub struct SegmentArgs {
    /// Tracked sequence (.igs.mha, .mhd, .igs.nrrd).
    pub sequence: PathBuf,
    /// PLUS device-set XML with the Image->Probe calibration (and clip rectangle).
    #[arg(long)]
    pub calibration: PathBuf,
    /// Initial band for the first frame of each sweep: a PNG mask of the frame size (non-zero = band) or a
    /// JSON polygon {"polygon": [[u, v], ...]} in pixels of the MF-oriented frame.
    #[arg(long, conflicts_with = "auto_init")]
    pub init: Option<PathBuf>,
    /// Find the initial band automatically (bright connected echo structures).
    #[arg(long)]
    pub auto_init: bool,
    /// Speckle-robust edgels (beyond the paper): chained along the boundary with hysteresis, one per
    /// column in each layer (--chain-layers), short chains dropped; smoothing 1 mm unless given.
    #[arg(long)]
    pub chain_edgels: bool,
    /// With --chain-edgels or --wall-band: how many boundaries one column may cross, each chained
    /// on its own (a wall seen through another, as a hollow organ's far wall through its near one);
    /// 1 = one per column.
    #[arg(long, default_value_t = 2, value_parser = clap::value_parser!(u32).range(1..=8))]
    pub chain_layers: u32,
    /// Every echoing wall in a band of fixed width in mm (beyond the paper): --chain-edgels (two
    /// layers) --backward-pass --sigma-mm 2.5 --truncation-mm 5.33, the paper's 15 / 32 px at 1/6 mm
    /// per pixel (the middle of its 0.1-0.2 mm/px); the widths, smoothing and layers can still be given.
    #[arg(long)]
    pub wall_band: bool,
    /// After each sweep, propagate the band back from its last frame too and keep the union (beyond
    /// the paper): an echo entering the view is kept at full width on its first frame.
    #[arg(long)]
    pub backward_pass: bool,
    /// The band follows only the echoes it holds (the paper's likelihood "for pixels in B_i", read
    /// strictly): edgels outside it are ignored, so a first band drawn around one structure (--init)
    /// stays on it; echoes that come into view away from the band are not picked up.
    #[arg(long)]
    pub follow_band: bool,
    /// Bone: `auto` segments a sweep made in contact with tissue whose frames show bright echoes over
    /// an acoustic shadow as bone (the band is the bone's surface, not the tissue under the probe);
    /// `always` or `never` decide instead. Only with the automatic first band.
    #[arg(long, default_value = "auto", value_parser = ["auto", "always", "never"])]
    pub bone: String,
    /// Gaussian smoothing before the gradients, in px (default 0.5 mm, 1 mm with --chain-edgels or
    /// --wall-band).
    #[arg(long, conflicts_with = "smoothing_mm")]
    pub smoothing_px: Option<f64>,
    /// Gaussian smoothing before the gradients, in mm.
    #[arg(long)]
    pub smoothing_mm: Option<f64>,
    /// M, edgels kept per frame (default: --edgel-fraction x clip width).
    #[arg(long)]
    pub edgels: Option<usize>,
    /// M as a fraction of the number of columns.
    #[arg(long, default_value_t = 0.75)]
    pub edgel_fraction: f64,
    /// Drop edgels weaker than this fraction of the frame's strongest (beyond the paper; 0 = the paper's
    /// plain M largest; default 0.35). With --smoothing-mm 1, 0.4 gives a narrower band (docs/pipeline.md).
    #[arg(long)]
    pub edgel_floor: Option<f64>,
    /// Prior inside the carried band (C1).
    #[arg(long, default_value_t = 1.0)]
    pub prior_inside: f64,
    /// Prior outside the carried band (C0).
    #[arg(long, default_value_t = 0.2)]
    pub prior_outside: f64,
    /// Sigma of the Gaussian proximity weight in px (paper: 15).
    #[arg(long, conflicts_with = "sigma_mm")]
    pub sigma_px: Option<f64>,
    /// Sigma of the Gaussian proximity weight in mm (converted with the pixel size).
    #[arg(long)]
    pub sigma_mm: Option<f64>,
    /// Truncation of the proximity weight in px (paper: 32).
    #[arg(long, conflicts_with = "truncation_mm")]
    pub truncation_px: Option<f64>,
    /// Truncation of the proximity weight in mm.
    #[arg(long)]
    pub truncation_mm: Option<f64>,
    /// Threshold T on the new map.
    #[arg(long, default_value_t = 0.35)]
    pub threshold: f64,
    /// World frame: auto, tracker or reference.
    #[arg(long, default_value = "auto")]
    pub world: String,
}

impl SegmentArgs {
    /// Every file this reads: the sequence (with a detached data file), the calibration, the band.
    pub fn input_files(&self) -> Vec<PathBuf> {
        let mut files = io::sequence_files(&self.sequence);
        files.push(self.calibration.clone());
        files.extend(self.init.iter().cloned());
        files
    }

    pub fn options(&self) -> SegmentOptions {
        let mut defaults = if self.wall_band {
            SegmentOptions::wall_band()
        } else if self.chain_edgels {
            SegmentOptions::chained()
        } else {
            SegmentOptions::default()
        };
        if let Some(chaining) = defaults.edgel_chaining.as_mut() {
            chaining.layers = self.chain_layers as usize;
        }
        let length = |px: Option<f64>, mm: Option<f64>, default: Length| match (px, mm) {
            (Some(p), _) => Length::Px(p),
            (None, Some(m)) => Length::Mm(m),
            _ => default,
        };
        SegmentOptions {
            smoothing_sigma: length(
                self.smoothing_px,
                self.smoothing_mm,
                defaults.smoothing_sigma,
            ),
            edgel_fraction: self.edgel_fraction,
            edgel_count: self.edgels,
            min_edgel_relative_strength: self
                .edgel_floor
                .unwrap_or(defaults.min_edgel_relative_strength),
            prior_inside: self.prior_inside,
            prior_outside: self.prior_outside,
            likelihood_sigma: length(self.sigma_px, self.sigma_mm, defaults.likelihood_sigma),
            likelihood_truncation: length(
                self.truncation_px,
                self.truncation_mm,
                defaults.likelihood_truncation,
            ),
            threshold: self.threshold,
            backward_pass: self.backward_pass || defaults.backward_pass,
            follow_band: self.follow_band,
            bone: match self.bone.as_str() {
                "always" => BoneMode::Always,
                "never" => BoneMode::Never,
                _ => BoneMode::Auto,
            },
            ..defaults
        }
    }

    /// Reads everything and segments; returns the sequence, poses and masks.
    pub fn run(
        &self,
    ) -> anyhow::Result<(
        io::TrackedSequence,
        io::PoseResolution,
        echosurf::segment::BandMasks,
    )> {
        let world = world_choice(&self.world)?;
        let sequence = super::inputs::read_sequence(&self.sequence)?;
        let calibration = io::read_calibration(&self.calibration)?;
        let poses = io::resolve_poses(&sequence, Some(&calibration), world, &self.sequence)?;
        let init = match (&self.init, self.auto_init) {
            (Some(path), false) => InitialBand::load(path, sequence.width, sequence.height)?,
            (None, true) => InitialBand::Auto,
            _ => anyhow::bail!("give the initial band with --init FILE or ask for --auto-init"),
        };
        // After the band: a bad band file is the more specific complaint.
        super::inputs::check_clip(&calibration, &sequence, &self.calibration, &self.sequence)?;
        let progress = BarProgress::new();
        let masks = segment_sequence(
            &sequence,
            &poses,
            calibration.clip,
            &init,
            &self.options(),
            &progress,
        )
        .with_context(|| format!("segmenting {}", self.sequence.display()))?;
        for w in &masks.warnings {
            eprintln!("warning: {w}");
        }
        Ok((sequence, poses, masks))
    }
}

#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub segment: SegmentArgs,
    /// Output masks: PLUS .mha, W x H x N, MET_UCHAR, 255 = kept.
    #[arg(long)]
    pub out: PathBuf,
    /// Also write a PNG montage of frames with the band outlined.
    #[arg(long)]
    pub preview: Option<PathBuf>,
    /// Number of frames in the preview montage.
    #[arg(long, default_value_t = 9)]
    pub preview_frames: usize,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let mut outputs = vec![output("--out", &args.out, Holds::MetaImage)];
    outputs.extend(
        args.preview
            .as_deref()
            .map(|p| output("--preview", p, Holds::Png)),
    );
    check_outputs(&args.segment.input_files(), &outputs)?;
    let (sequence, poses, masks) = args.segment.run()?;
    io::write_sequence(&args.out, &masks.to_sequence(), true)?;
    if let Some(path) = &args.preview {
        let frames = default_preview_frames(&masks, args.preview_frames);
        if frames.is_empty() {
            eprintln!("warning: no frame has a band; preview not written");
        } else {
            write_band_preview(path, &sequence, &masks, &frames)?;
        }
    }
    let p = masks.parameters;
    outln!(
        "segmented {} of {} frames ({} skipped), kept {:.1}% of all pixels; M = {} edgels, sigma {:.1} px, \
         band +/-{:.1} px{}; {} warning(s)",
        poses.poses.len(),
        sequence.frames.len(),
        poses.skipped.len(),
        100.0 * masks.kept_fraction(),
        p.edgel_count,
        p.likelihood_sigma_px,
        p.band_radius_inside_px,
        p.pixel_size_mm
            .map(|s| format!(" ({:.2} mm at {:.3} mm/px)", p.band_radius_inside_px * s, s))
            .unwrap_or_default(),
        masks.warnings.len()
    );
    Ok(())
}
