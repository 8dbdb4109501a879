//! `echosurf bench`: direct RBF route against the voxel route on simulated phantoms at three noise
//! levels (and user cases with truth), plus the fit's time against the number of samples.

use std::path::PathBuf;

use anyhow::Context;
use echosurf::io::{self, atomic::write_bytes_atomic};
use echosurf::pipeline::VoxelRouteOptions;
use echosurf::rbf::FitOptions;
use echosurf_bench::{
    BenchOptions, NoiseLevel, RouteResult, ScalingSamples, accuracy_vs_time_plot,
    bench_fit_scaling, fit_scaling_plot, fit_sizes, markdown_table,
};
use echosurf_sim::PhantomKind;

use super::extract::parse_iso;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// What to run: `all` (default), `routes` (RBF vs voxel on the phantoms and cases) or `fit` (the fit's
    /// time, iterations and memory against the number of samples).
    #[arg(default_value = "all")]
    pub what: String,
    /// Solver of the fit-scaling run: auto, direct, pu or fast.
    #[arg(long, default_value = "auto")]
    pub solver: String,
    /// Directory for table.md, bench.json, accuracy_vs_time.svg and fit_scaling.svg.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Small images, few frames, small fits: a CI-sized run (seconds, not minutes).
    #[arg(long)]
    pub quick: bool,
    /// Simulated phantoms, comma separated (empty: none).
    #[arg(long, default_value = "duck,hand")]
    pub phantoms: String,
    /// Noise levels of the simulated phantoms, comma separated: low, default, high.
    #[arg(long, default_value = "low,default,high")]
    pub noise: String,
    /// A user case SEQUENCE,CONFIG,TRUTH_MESH (repeatable).
    #[arg(long)]
    pub case: Vec<String>,
    /// RBF route: decimation target (default 100000; 3000 with --quick).
    #[arg(long)]
    pub max_samples: Option<usize>,
    /// Iso-level for both routes, or `auto` (each route's automatic level).
    #[arg(long, default_value = "auto")]
    pub iso: String,
    /// Voxel route: Gaussian sigma in mm.
    #[arg(long, default_value_t = 1.0)]
    pub voxel_smoothing: f64,
    /// Largest sample count of the fit-scaling run (1k, 3k, 10k, ... up to this; 0 = skip it).
    /// Default 100000; 3000 with --quick.
    #[arg(long)]
    pub fit_max: Option<usize>,
    /// The fit-scaling run also fits band pixels of this sweep, SEQUENCE,CONFIG (repeatable): each
    /// frame smoothed (2 px Gaussian), above 45 grey, dilated 10 px; raw grey levels at their world
    /// positions, random subsets of each size.
    #[arg(long, value_name = "SEQUENCE,CONFIG")]
    pub fit_band: Vec<String>,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
}

/// Every band pixel of the sweep `--fit-band SEQUENCE,CONFIG` (placed by the config's calibration),
/// with the sequence's file name.
fn fit_band_pixels(spec: &str) -> anyhow::Result<(String, Vec<glam::DVec3>, Vec<f64>)> {
    let parts: Vec<&str> = spec.split(',').map(str::trim).collect();
    let [seq, config] = parts[..] else {
        anyhow::bail!("--fit-band {spec}: expected SEQUENCE,CONFIG");
    };
    let (points, values) = echosurf_bench::sweep_band_pixels(seq.as_ref(), config.as_ref())?;
    if points.is_empty() {
        anyhow::bail!("--fit-band {seq}: no pixel of its frames is above the band's threshold");
    }
    let name = std::path::Path::new(seq)
        .file_name()
        .map_or_else(|| seq.to_string(), |n| n.to_string_lossy().into_owned());
    Ok((name, points, values))
}

fn parse_noise(text: &str) -> anyhow::Result<Vec<NoiseLevel>> {
    text.split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| match s.to_ascii_lowercase().as_str() {
            "low" => Ok(NoiseLevel::Low),
            "default" => Ok(NoiseLevel::Default),
            "high" => Ok(NoiseLevel::High),
            other => anyhow::bail!("--noise {other}: expected low, default or high"),
        })
        .collect()
}

pub fn run(args: Args) -> anyhow::Result<()> {
    if !(args.voxel_smoothing.is_finite() && args.voxel_smoothing >= 0.0) {
        anyhow::bail!("--voxel-smoothing must be a non-negative number of mm");
    }
    let (run_routes, run_fit) = match args.what.to_ascii_lowercase().as_str() {
        "all" => (true, true),
        "routes" => (true, false),
        "fit" => (false, true),
        other => anyhow::bail!("bench {other}: expected all, routes or fit"),
    };
    let solver = super::fit::parse_solver(&args.solver)?;
    let noise = parse_noise(&args.noise)?;
    let phantoms: Vec<PhantomKind> = if run_routes {
        args.phantoms
            .split(',')
            .map(str::trim)
            .filter(|s| !s.is_empty())
            .map(PhantomKind::parse)
            .collect()
    } else {
        Vec::new()
    };
    let cases: &[String] = if run_routes { &args.case } else { &[] };
    let options = BenchOptions {
        quick: args.quick,
        iso: parse_iso(&args.iso)?,
        max_samples: args
            .max_samples
            .unwrap_or(if args.quick { 3_000 } else { 100_000 }),
        voxel: VoxelRouteOptions {
            smoothing_sigma_mm: args.voxel_smoothing,
            ..VoxelRouteOptions::default()
        },
        seed: args.seed,
    };
    if let Some(dir) = &args.out {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }

    let mut results: Vec<RouteResult> = Vec::new();
    for phantom in &phantoms {
        for &level in &noise {
            eprintln!(
                "bench: simulating {} / {} ...",
                phantom.name(),
                level.name()
            );
            let case =
                echosurf_bench::simulated_case(phantom.clone(), level, args.quick, args.seed)
                    .with_context(|| format!("simulating {} / {}", phantom.name(), level.name()))?;
            eprintln!("bench: running both routes on {} ...", case.name);
            results.extend(echosurf_bench::run_case(
                &case,
                &options,
                &crate::memory::StageMemory,
            )?);
        }
    }
    for spec in cases {
        let parts: Vec<&str> = spec.split(',').map(str::trim).collect();
        let [seq, config, truth] = parts[..] else {
            anyhow::bail!("--case {spec}: expected SEQUENCE,CONFIG,TRUTH_MESH");
        };
        let sequence = io::read_sequence(seq.as_ref())?;
        let calibration = io::read_calibration(config.as_ref())?;
        let truth_mesh = io::read_mesh(truth.as_ref())?;
        let case = echosurf_bench::user_case(seq.to_string(), sequence, calibration, truth_mesh)?;
        eprintln!("bench: running both routes on {} ...", case.name);
        results.extend(echosurf_bench::run_case(
            &case,
            &options,
            &crate::memory::StageMemory,
        )?);
    }

    let fit_max = args
        .fit_max
        .unwrap_or(if args.quick { 3_000 } else { 100_000 });
    let sizes = if run_fit {
        fit_sizes(fit_max)
    } else {
        Vec::new()
    };
    let scaling = if sizes.is_empty() {
        Vec::new()
    } else {
        eprintln!("bench: fit scaling at {sizes:?} samples ...");
        let fit_options = FitOptions {
            solver,
            ..FitOptions::default()
        };
        let mut rows =
            bench_fit_scaling(&sizes, &fit_options, args.seed, ScalingSamples::Synthetic)?;
        for spec in &args.fit_band {
            let (name, points, values) = fit_band_pixels(spec)?;
            eprintln!(
                "bench: fit scaling on {} band pixels of {name} ...",
                points.len()
            );
            let source = ScalingSamples::BandPixels {
                name: &name,
                points: &points,
                values: &values,
            };
            rows.extend(bench_fit_scaling(&sizes, &fit_options, args.seed, source)?);
        }
        rows
    };

    let mut table = if run_routes {
        markdown_table(&results)
    } else {
        String::new()
    };
    if !scaling.is_empty() {
        if !table.is_empty() {
            table.push('\n');
        }
        table.push_str("| samples from | samples | fit (s) | iterations | max residual | evaluate N points (s) | solver bytes / sample |\n|---|---:|---:|---:|---:|---:|---:|\n");
        for r in &scaling {
            table.push_str(&format!(
                "| {} | {} | {:.2} | {} | {:.2} | {:.3} | {:.0} |\n",
                r.samples_from,
                r.samples,
                r.fit_seconds,
                r.iterations,
                r.max_residual,
                r.eval_seconds,
                r.solver_bytes_per_sample
            ));
        }
    }
    out!("{table}");
    if let Some(dir) = &args.out {
        write_bytes_atomic(&dir.join("table.md"), table.as_bytes())?;
        let json = serde_json::json!({
            "options": {
                "quick": args.quick,
                "iso": args.iso,
                "max_samples": options.max_samples,
                "voxel_smoothing_mm": args.voxel_smoothing,
                "seed": args.seed,
                "what": args.what,
                "solver": args.solver,
            },
            "routes": results,
            "fit_scaling": scaling,
        });
        write_bytes_atomic(
            &dir.join("bench.json"),
            serde_json::to_string_pretty(&json)?.as_bytes(),
        )?;
        if run_routes {
            write_bytes_atomic(
                &dir.join("accuracy_vs_time.svg"),
                accuracy_vs_time_plot(&results).to_svg().as_bytes(),
            )?;
        }
        if !scaling.is_empty() {
            write_bytes_atomic(
                &dir.join("fit_scaling.svg"),
                fit_scaling_plot(&scaling).to_svg().as_bytes(),
            )?;
        }
        eprintln!("bench: wrote {}", dir.display());
    }
    Ok(())
}
