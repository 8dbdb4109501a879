//! `echosurf fit`: fit the biharmonic RBF to a point cloud with intensities and save the model.

use std::path::PathBuf;

use anyhow::Context;
use echosurf::rbf::{FitOptions, SolverChoice, fit};

use super::outputs::{Holds, check_outputs, output};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Point cloud PLY with float x y z and a float `intensity` vertex property.
    pub points: PathBuf,
    /// Output model (.esrbf).
    #[arg(long)]
    pub out: PathBuf,
    /// Smoothing weight w in mm (0 interpolates; larger is smoother).
    #[arg(long, default_value_t = FitOptions::default().smoothing)]
    pub smoothing: f64,
    /// Fitting accuracy: largest allowed system residual, in grey levels.
    #[arg(long, default_value_t = FitOptions::default().accuracy)]
    pub accuracy: f64,
    /// Greedy centre reduction down to at most this many centres.
    #[arg(long)]
    pub max_centres: Option<usize>,
    /// Greedy centre reduction without a fixed budget.
    #[arg(long)]
    pub reduce: bool,
    /// Seed of the centre reduction's initial subset.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Solver: `auto` (dense up to 2,000 samples, partition of unity above), `direct`, `pu`, or `fast`
    /// (the single global spline, treecode + two-level Schwarz GMRES; slower, exact to the accuracy).
    #[arg(long, default_value = "auto")]
    pub solver: String,
    /// Print the fit report as JSON on stdout.
    #[arg(long)]
    pub json: bool,
    /// Refuse before fitting when the fit would need more than this many MB (default: half the
    /// machine's memory).
    #[arg(long)]
    pub memory_budget: Option<f64>,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    check_outputs(
        std::slice::from_ref(&args.points),
        &[output("--out", &args.out, Holds::AnyName)],
    )?;
    let cloud = echosurf::io::read_point_cloud(&args.points)?;
    let intensity = cloud.scalar("intensity").with_context(|| {
        format!(
            "{}: no float `intensity` vertex property to fit",
            args.points.display()
        )
    })?;
    let values: Vec<f64> = intensity.iter().map(|&v| v as f64).collect();
    let options = FitOptions {
        smoothing: args.smoothing,
        accuracy: args.accuracy,
        max_centres: args.max_centres,
        reduce_centres: args.reduce,
        seed: args.seed,
        solver: parse_solver(&args.solver)?,
        ..FitOptions::default()
    };
    let budget = super::extract::memory_budget_bytes(args.memory_budget)?;
    echosurf::budget::check_fit_budget(
        values.len() as u64,
        &options,
        budget,
        &crate::memory::StageMemory,
    )
    .with_context(|| format!("fitting {}", args.points.display()))?;
    let progress = crate::progress::BarProgress::new();
    let (model, report) = fit(&cloud.positions, &values, &options, &progress)
        .with_context(|| format!("fitting {}", args.points.display()))?;
    model.save(&args.out)?;
    if args.json {
        outln!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        outln!(
            "{} samples ({} after merging) -> {} centres, {:?} solver, {} iterations, \
             max residual {:.3}, rms {:.3}, {:.2} s -> {}",
            report.input_points,
            report.merged_points,
            report.centres,
            report.solver,
            report.iterations,
            report.max_residual,
            report.rms_residual,
            report.fit_seconds,
            args.out.display()
        );
    }
    Ok(())
}

/// `--solver` for `fit` and `extract`.
pub fn parse_solver(text: &str) -> anyhow::Result<SolverChoice> {
    Ok(match text.to_ascii_lowercase().as_str() {
        "auto" => SolverChoice::Auto,
        "direct" => SolverChoice::Direct,
        "pu" => SolverChoice::PartitionOfUnity,
        "fast" => SolverChoice::Fast,
        other => anyhow::bail!("--solver {other}: expected auto, direct, pu or fast"),
    })
}
