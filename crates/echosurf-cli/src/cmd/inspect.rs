//! `echosurf inspect`: what is in a tracked sequence and where its frames are.

use std::path::PathBuf;

use anyhow::Context;
use echosurf::io::{self, ReferenceChoice};

use super::outputs::{Holds, check_outputs, output};

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ReferenceArg {
    /// Reference when a reference sensor is tracked, else Tracker.
    Auto,
    /// ProbeToTracker * ImageToProbe.
    Tracker,
    /// inverse(ReferenceToTracker) * ProbeToTracker * ImageToProbe.
    Reference,
}

impl From<ReferenceArg> for ReferenceChoice {
    fn from(r: ReferenceArg) -> Self {
        match r {
            ReferenceArg::Auto => ReferenceChoice::Auto,
            ReferenceArg::Tracker => ReferenceChoice::Tracker,
            ReferenceArg::Reference => ReferenceChoice::Reference,
        }
    }
}

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Tracked sequence (.mha, .mhd, .nrrd).
    pub sequence: PathBuf,
    /// PLUS device-set XML with the Image->Probe calibration (needed for positions and bounds in mm).
    #[arg(long)]
    pub calibration: Option<PathBuf>,
    /// World frame to place the frames in.
    #[arg(long, value_enum, default_value = "auto")]
    pub reference: ReferenceArg,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
    /// Write a frame as a grey PNG of the frame's size, to draw the first band on (`--init` of
    /// `segment`, `sample` and `extract` takes a PNG mask of that size, or a JSON polygon in its pixel
    /// coordinates). The frame is the first of the first sweep (where that band is used) unless
    /// `--frame` says otherwise.
    #[arg(long, value_name = "PNG")]
    pub frame_png: Option<PathBuf>,
    /// Which frame `--frame-png` writes (0-based index in the file).
    #[arg(long, value_name = "INDEX", requires = "frame_png")]
    pub frame: Option<usize>,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    if let Some(png) = &args.frame_png {
        let mut inputs = io::sequence_files(&args.sequence);
        inputs.extend(args.calibration.iter().cloned());
        check_outputs(&inputs, &[output("--frame-png", png, Holds::Png)])?;
    }
    let sequence = super::inputs::read_sequence(&args.sequence)?;
    let calibration = args
        .calibration
        .as_deref()
        .map(|c| super::inputs::read_calibration_for(c, &sequence, &args.sequence))
        .transpose()?;
    let summary = io::summarise(
        &sequence,
        calibration.as_ref(),
        args.reference.into(),
        &args.sequence,
    )?;
    // The frame first: a bad --frame fails before anything is printed.
    let mut written = None;
    if let Some(png) = &args.frame_png {
        let index = match args.frame {
            Some(index) => index,
            None => summary
                .sweeps
                .first()
                .map(|s| s.first_frame)
                .with_context(|| {
                    format!(
                        "{}: no valid frame to write (use --frame to pick one)",
                        args.sequence.display()
                    )
                })?,
        };
        echosurf::segment::write_frame_png(png, &sequence, index)
            .with_context(|| format!("{}: --frame-png", args.sequence.display()))?;
        written = Some(format!(
            "frame {index} written to {} ({} x {} px): draw the first band on it, as a PNG mask of \
             that size (non-zero = band) or a JSON polygon {{\"polygon\": [[u, v], ...]}} in its pixels",
            png.display(),
            sequence.width,
            sequence.height
        ));
    }
    if args.json {
        let text = serde_json::to_string_pretty(&summary).context("serialising the summary")?;
        outln!("{text}");
    } else {
        out!("{}", summary.to_text(&args.sequence.display().to_string()));
    }
    if let Some(line) = written {
        if args.json {
            eprintln!("{line}");
        } else {
            outln!("{line}");
        }
    }
    Ok(())
}
