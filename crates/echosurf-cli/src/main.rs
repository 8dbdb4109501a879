//! `echosurf`: the command-line face of the echosurf library. Each subcommand lives in `cmd/` and only
//! parses arguments, calls the library and prints; all the work is in the library.

#[macro_use]
mod stdout;
mod cmd;
mod memory;
mod oom;
mod phrasing;
mod progress;
mod temp_files;

#[global_allocator]
static ALLOCATOR: oom::CleanOutOfMemory = oom::CleanOutOfMemory;

use std::process::ExitCode;

use clap::{Parser, Subcommand};

/// Direct surface extraction from tracked freehand 3D ultrasound.
#[derive(Debug, Parser)]
#[command(name = "echosurf", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
    /// After the command, print on stderr the memory it estimated it would need (the largest figure a
    /// --memory-budget check compared) and the peak resident memory it measured.
    #[arg(long, global = true)]
    memory_report: bool,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Summarise a tracked sequence: frames, poses, sweeps, bounds.
    Inspect(cmd::inspect::Args),
    /// Simulate tracked B-mode sweeps of a phantom, with ground truth.
    Simulate(cmd::simulate::Args),
    /// Segment a band of pixels around the boundary in every frame.
    Segment(cmd::segment::Args),
    /// Fit a biharmonic RBF to a point cloud with intensities.
    Fit(cmd::fit::Args),
    /// Evaluate a fitted RBF model (values and gradients) at points.
    Eval(cmd::eval::Args),
    /// Extract iso-surfaces of a fitted RBF model.
    Surface(cmd::surface::Args),
    /// The whole pipeline: sequence -> mesh.
    Extract(Box<cmd::extract::Args>),
    /// Write the samples the fit would see as a point cloud.
    Sample(cmd::sample::Args),
    /// Score a mesh against a ground-truth mesh.
    Compare(cmd::compare::Args),
    /// Render a mesh to a PNG preview.
    Render(cmd::render::Args),
    /// Reconstruct a voxel volume from a tracked sequence (the PLUS route).
    Reconstruct(cmd::reconstruct::Args),
    /// Benchmarks: direct RBF route against the voxel route, fit scaling.
    Bench(cmd::bench::Args),
    /// Simulate the duck, extract, compare with truth, render, and summarise.
    Demo(cmd::demo::Args),
    /// Run as a 3D Slicer command-line module (`--xml` prints its description); see echosurf-slicer.
    SlicerModule(Box<cmd::slicer::Args>),
    /// Extract every sweep a manifest lists: resumable, shardable (--shard I/N), one summary table.
    Batch(cmd::batch::Args),
    /// Record tracked frames from an OpenIGTLink server, send the growing surface back as POLYDATA.
    Live(cmd::live::Args),
}

impl Command {
    /// Whose flags the library's option names are phrased in.
    fn terms(&self) -> phrasing::Terms {
        use phrasing::Terms;
        match self {
            Command::Extract(_) | Command::Batch(_) | Command::SlicerModule(_) => Terms::Extract,
            Command::Fit(_) => Terms::Fit,
            Command::Surface(_) => Terms::Surface,
            Command::Compare(_) => Terms::Compare,
            Command::Segment(_) | Command::Sample(_) => Terms::Segment,
            _ => Terms::Library,
        }
    }
}

/// `--memory-report`: the estimate and the measured peak, in MB, and their ratio.
fn memory_report_line() -> String {
    let mb = |b: u64| format!("{:.1} MB", b as f64 / 1e6);
    let estimate = memory::largest_estimate_bytes();
    let peak = memory::lifetime_peak_rss_bytes();
    let text = |b: Option<u64>| b.map(mb).unwrap_or_else(|| "none".into());
    let ratio = match (estimate, peak) {
        (Some(e), Some(p)) => format!(" (peak / estimate {:.2})", p as f64 / e as f64),
        _ => String::new(),
    };
    format!(
        "memory: estimate {}, peak resident {}{ratio}",
        text(estimate),
        text(peak)
    )
}

/// Exit code of a run stopped by Ctrl-C, SIGTERM or SIGHUP (128 + SIGINT, as shells report Ctrl-C).
const INTERRUPTED_EXIT_CODE: i32 = 130;

fn main() -> ExitCode {
    // Ctrl-C, SIGTERM and SIGHUP (the `termination` feature of ctrlc): remove the unfinished hidden
    // temporary outputs, so an interrupted run leaves neither a partial file nor litter. Finished
    // outputs were renamed into place whole and stay.
    temp_files::install();
    let _ = ctrlc::set_handler(|| {
        // A live session stops on the first Ctrl-C and writes what it recorded.
        if cmd::live::STOP.get().is_some_and(|stop| stop.request()) {
            eprintln!("\nstopping: writing the recorded frames (Ctrl-C again to quit at once)");
            return;
        }
        let removed = temp_files::remove_in_flight();
        eprintln!(
            "\ninterrupted: no output was left half-written ({removed} unfinished file(s) removed)"
        );
        std::process::exit(INTERRUPTED_EXIT_CODE);
    });
    // Dense factorisations (the direct RBF solve) run sequentially: faer's rayon-parallel LU sums in an
    // order that depends on the thread count, and outputs must be byte-identical for any thread count.
    faer::set_global_parallelism(faer::Par::Seq);
    let cli = Cli::parse();
    let terms = cli.command.terms();
    let result = match cli.command {
        Command::Inspect(a) => cmd::inspect::run(a),
        Command::Simulate(a) => cmd::simulate::run(a),
        Command::Segment(a) => cmd::segment::run(a),
        Command::Fit(a) => cmd::fit::run(a),
        Command::Eval(a) => cmd::eval::run(a),
        Command::Surface(a) => cmd::surface::run(a),
        Command::Extract(a) => cmd::extract::run(*a),
        Command::Sample(a) => cmd::sample::run(a),
        Command::Compare(a) => cmd::compare::run(a),
        Command::Render(a) => cmd::render::run(a),
        Command::Reconstruct(a) => cmd::reconstruct::run(a),
        Command::Bench(a) => cmd::bench::run(a),
        Command::Demo(a) => cmd::demo::run(a),
        Command::SlicerModule(a) => cmd::slicer::run(*a),
        Command::Batch(a) => cmd::batch::run(a),
        Command::Live(a) => cmd::live::run(a),
    };
    let result = result.and_then(|()| Ok(stdout::flush_out()?));
    if cli.memory_report {
        eprintln!("{}", memory_report_line());
    }
    match result {
        Ok(()) => ExitCode::SUCCESS,
        // The reader of our output left (`| head`): stop quietly, as a program killed by SIGPIPE would.
        Err(e)
            if e.chain().any(|c| {
                c.downcast_ref::<stdout::StdoutError>()
                    .is_some_and(stdout::StdoutError::is_broken_pipe)
            }) =>
        {
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("error: {}", phrasing::error_message(&e, terms));
            ExitCode::FAILURE
        }
    }
}
