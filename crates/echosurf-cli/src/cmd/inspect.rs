//! `echosurf inspect`: what is in a tracked sequence and where its frames are.

use std::path::PathBuf;

use anyhow::Context;
use echosurf::io::{self, ReferenceChoice};

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
    pub config: Option<PathBuf>,
    /// World frame to place the frames in.
    #[arg(long, value_enum, default_value = "auto")]
    pub reference: ReferenceArg,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let sequence = io::read_sequence(&args.sequence)?;
    let calibration = args
        .config
        .as_deref()
        .map(io::read_calibration)
        .transpose()?;
    let summary = io::summarise(
        &sequence,
        calibration.as_ref(),
        args.reference.into(),
        &args.sequence,
    )?;
    if args.json {
        let text = serde_json::to_string_pretty(&summary).context("serialising the summary")?;
        println!("{text}");
    } else {
        print!("{}", summary.to_text(&args.sequence.display().to_string()));
    }
    Ok(())
}
