//! `echosurf live`: connect to an OpenIGTLink server (PlusServer), record the tracked frames, send the
//! growing surface back as POLYDATA, and on exit write the sweep and the final mesh.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use echosurf::pipeline::ExtractOptions;
use echosurf_live::client::{self, Endpoint, LiveOptions, StopSignal};
use echosurf_live::codec::Limits;
use echosurf_live::session::{SessionOptions, update_extract_options};

/// The running session's stop handle, for the Ctrl-C handler (set once `live` starts).
pub static STOP: std::sync::OnceLock<StopSignal> = std::sync::OnceLock::new();

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The OpenIGTLink server, HOST:PORT (PlusServer's default port is 18944).
    #[arg(
        long,
        value_name = "HOST:PORT",
        required_unless_present = "serve",
        conflicts_with = "serve"
    )]
    pub connect: Option<String>,
    /// Be the server instead: listen on PORT (all interfaces) or HOST:PORT and take the frames from
    /// the client that connects (port 0: a free port, printed when listening).
    #[arg(long, value_name = "PORT|HOST:PORT")]
    pub serve: Option<String>,
    /// Only IMAGE messages from this device are frames (default: any device).
    #[arg(long)]
    pub image_device: Option<String>,
    /// Place the images by this TRANSFORM device's ProbeToReference poses (paired by timestamp,
    /// interpolated) and the config's Image->Probe calibration; without it the IMAGE matrix is the
    /// frame's ImageToReference.
    #[arg(long, value_name = "DEVICE")]
    pub transform: Option<String>,
    /// PLUS device-set XML with the Image->Probe calibration (and clip rectangle).
    #[arg(long)]
    pub calibration: PathBuf,
    /// Folder for the recorded sweep (live.igs.mha) and the final mesh (live_surface.ply).
    #[arg(long)]
    pub out: PathBuf,
    /// Stop after this many frames (default: until the server closes or Ctrl-C).
    #[arg(long)]
    pub frames: Option<usize>,
    /// Refit and send the surface after every this many new frames (0: only at the end).
    #[arg(long, default_value_t = 30)]
    pub update_every: usize,
    /// Also refit and send the surface when this many seconds have passed since the last update and
    /// new frames came (default: by frame count only).
    #[arg(long, value_name = "SECONDS")]
    pub update_seconds: Option<f64>,
    /// Sample budget of the updates during the sweep (the final mesh uses `extract`'s defaults).
    #[arg(long, default_value_t = 10_000)]
    pub update_samples: usize,
    /// Surfacer lattice spacing (mm) of the updates during the sweep (the final mesh: 0.5 mm).
    #[arg(long, default_value_t = 1.0)]
    pub update_resolution: f64,
    /// Refuse messages with a body larger than this many MB.
    #[arg(long, default_value_t = 64)]
    pub max_message_mb: u64,
    /// Give up after this many failed connection attempts in a row.
    #[arg(long, default_value_t = 8)]
    pub reconnect_attempts: usize,
    /// OpenIGTLink header version of the POLYDATA sent back (1, 2 or 3).
    #[arg(long, default_value_t = 2)]
    pub send_version: u16,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    if !(1..=3).contains(&args.send_version) {
        anyhow::bail!("--send-version must be 1, 2 or 3");
    }
    if !(args.update_resolution.is_finite() && args.update_resolution > 0.0) {
        anyhow::bail!("--update-resolution must be a positive number of mm");
    }
    if args.frames == Some(0) {
        anyhow::bail!("--frames must be at least 1");
    }
    let update_every = match args.update_seconds {
        None => None,
        Some(s) if s.is_finite() && s > 0.0 => Some(Duration::from_secs_f64(s)),
        Some(_) => anyhow::bail!("--update-seconds must be a positive number of seconds"),
    };
    let endpoint = match (args.connect, args.serve) {
        (Some(address), None) => Endpoint::Connect(address),
        (None, Some(port)) if !port.is_empty() && port.bytes().all(|b| b.is_ascii_digit()) => {
            Endpoint::Listen(format!("0.0.0.0:{port}"))
        }
        (None, Some(address)) => Endpoint::Listen(address),
        _ => anyhow::bail!("give either --connect HOST:PORT or --serve PORT"),
    };
    let calibration = echosurf::io::read_calibration(&args.calibration)?;
    if args.out.exists() && !args.out.is_dir() {
        anyhow::bail!("--out {}: exists and is not a folder", args.out.display());
    }
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let options = LiveOptions {
        endpoint,
        session: SessionOptions {
            image_device: args.image_device,
            transform_device: args.transform,
            update_every_frames: args.update_every,
            ..SessionOptions::default()
        },
        calibration,
        out_dir: args.out.clone(),
        max_frames: args.frames,
        update_extract: update_extract_options(args.update_samples, args.update_resolution),
        final_extract: ExtractOptions::default(),
        limits: Limits {
            max_body_bytes: args.max_message_mb.saturating_mul(1 << 20),
        },
        max_reconnects: args.reconnect_attempts,
        first_backoff: Duration::from_millis(200),
        send_version: args.send_version,
        update_every,
        stop: STOP.get_or_init(StopSignal::default).clone(),
    };
    let summary = client::run(&options)?;
    for u in &summary.updates {
        outln!(
            "update at {} frames: {} triangles in {:.2} s{}",
            u.frames,
            u.triangles,
            u.seconds,
            if u.sent { ", sent" } else { ", not sent" }
        );
    }
    outln!(
        "{}: {} frames recorded ({} with a pose) over {} connection(s), {} warning(s)",
        summary.ended,
        summary.frames,
        summary.frames_with_pose,
        summary.connections,
        summary.warnings.len()
    );
    outln!("sequence {}", summary.sequence_path.display());
    if summary.final_triangles > 0 {
        outln!(
            "surface  {} ({} triangles, {:.2} s after the last frame)",
            summary.mesh_path.display(),
            summary.final_triangles,
            summary.last_frame_to_mesh_s
        );
    }
    Ok(())
}
