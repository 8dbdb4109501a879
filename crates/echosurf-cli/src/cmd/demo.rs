//! `echosurf demo`: the whole product in one command on built-in data. Simulates a tracked sweep of the
//! hollow duck phantom (the paper's test object), extracts its surface, scores it against the truth and
//! renders it, then says where everything is.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use echosurf::io;
use echosurf::metrics::{CompareOptions, compare_meshes};
use echosurf::pipeline::{self, ExtractOptions};
use echosurf_sim::{SimulationNames, SimulationOptions, simulate, write_simulation_as};

use super::extract::write_preview;
use crate::progress::BarProgress;

/// The distance shown red on the demo's error map (mm).
const ERROR_MAP_SCALE_MM: f64 = 1.0;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Folder for everything the demo writes.
    #[arg(long, default_value = "echosurf-demo")]
    pub out: PathBuf,
    /// Seed of the simulation (same seed, same bytes).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Output surface, as for `extract`: `auto`, `iso` (the paper's iso-surface) or `ridge` (one sheet
    /// on each echo's ridge).
    #[arg(long, default_value = "auto")]
    pub sheet: String,
    #[command(flatten)]
    pub space: super::space::SpaceArg,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let start = Instant::now();
    let sheet = super::extract::parse_sheet(&args.sheet)?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let sim_options = SimulationOptions {
        seed: args.seed,
        ..SimulationOptions::default()
    };
    outln!("simulating a freehand sweep of the duck phantom ...");
    let sim = simulate(&sim_options, &BarProgress::new())?;
    let files = write_simulation_as(
        &args.out,
        &SimulationNames::plain("duck"),
        &sim,
        &sim_options,
        args.space.space,
    )?;
    let sim_seconds = start.elapsed().as_secs_f64();

    outln!("extracting the surface ...");
    let options = ExtractOptions {
        seed: args.seed,
        sheet,
        ..ExtractOptions::default()
    };
    let output = pipeline::extract(
        &sim.sequence,
        Some(&sim.calibration_written),
        &options,
        &BarProgress::new(),
    )?;
    let mesh_path = args.out.join("duck_surface.ply");
    let surface = output
        .surfaces
        .first()
        .context("the pipeline returned no surface")?;
    io::write_mesh_in(&mesh_path, &surface.mesh, args.space.space)?;
    let report_path = args.out.join("duck_report.json");
    let report = super::space::with_coordinates(
        &output.report,
        &output.report.parameters.world_frame,
        args.space.space,
    )?;
    io::atomic::write_bytes_atomic(
        &report_path,
        serde_json::to_string_pretty(&report)?.as_bytes(),
    )?;

    // All true walls in one mesh (the duck's outer and inner wall): each extracted sheet is scored
    // against the wall it belongs to.
    let truth = echosurf_sim::merged_truth(&sim.truth);
    if truth.is_empty() {
        anyhow::bail!("the simulation has no truth surface");
    }
    let comparison = compare_meshes(&surface.mesh, &truth, &CompareOptions::default())?;
    // Completeness of what could be seen: truth swept by a frame and facing its beam within 30 degrees
    // (a specular echo at 30 degrees is down to cos^12 = 18 %; beyond ~40 degrees nothing comes back).
    let facing_mask = echosurf_bench::swept_beam_facing_mask(
        &truth,
        &sim.true_image_to_world,
        sim.sequence.width,
        sim.sequence.height,
        sim.calibration_true.clip,
        1.5,
        echosurf_bench::FacingSide::Either,
        30.0,
    );
    let facing = compare_meshes(
        &surface.mesh,
        &truth,
        &CompareOptions {
            truth_mask: Some(facing_mask),
            ..CompareOptions::default()
        },
    )?;
    let preview_path = args.out.join("duck_preview.png");
    // Where the surface is off: blue on the true walls, red 1 mm (the completeness distance) or more.
    let error_map_path = args.out.join("duck_error_map.png");
    let error_map = echosurf::render::render_views(
        &surface.mesh,
        &echosurf::render::RenderOptions {
            vertex_colours: Some(
                echosurf::metrics::vertex_distance_map(&surface.mesh, &truth, ERROR_MAP_SCALE_MM).1,
            ),
            colour_bar: Some(echosurf::render::distance_colour_bar(ERROR_MAP_SCALE_MM)),
            ..echosurf::render::RenderOptions::default()
        },
    )?;
    echosurf::render::write_png(&error_map_path, &error_map)?;
    write_preview(&preview_path, &output, Some(truth))?;

    let r = &output.report;
    outln!();
    outln!(
        "echosurf demo: duck phantom, {} frames in {} sweeps",
        sim.sequence.frames.len(),
        sim.sweeps.len()
    );
    outln!(
        "  samples {} of {} kept pixels; iso {:.1} (background {:.1}, boundary {:.1})",
        r.counts.samples,
        r.counts.kept_pixels,
        surface.level,
        r.levels.map(|l| l.background).unwrap_or(f32::NAN),
        r.levels.map(|l| l.boundary).unwrap_or(f32::NAN)
    );
    outln!(
        "  surface: {}, {} triangles, {} component(s)",
        r.sheets
            .first()
            .map(|used| super::extract::describe_sheet(used, r.parameters.sheet))
            .unwrap_or_default(),
        surface.mesh.triangles.len(),
        comparison.mesh_topology.components
    );
    outln!(
        "  accuracy vs true walls: mean {:.2} mm, p95 {:.2} mm; completeness (1 mm) {:.1} % of the \
         walls, {:.1} % of the swept walls facing the beam within 30 deg",
        comparison.accuracy.mean_mm,
        comparison.accuracy.p95_mm,
        100.0 * comparison.completeness_1mm,
        100.0 * facing.completeness_1mm
    );
    let stages: Vec<String> = r
        .stages
        .iter()
        .map(|s| format!("{} {:.2}s", s.stage, s.seconds))
        .collect();
    outln!(
        "  time: simulate {sim_seconds:.1}s, extract {:.1}s ({})",
        r.total_seconds,
        stages.join(", ")
    );
    outln!("files:");
    outln!("  sequence     {}", files.sequence.display());
    outln!("  calibration  {}", files.calibration.display());
    for t in &files.truth {
        outln!("  truth        {}", t.display());
    }
    outln!("  surface      {}", mesh_path.display());
    outln!("  report       {}", report_path.display());
    outln!("  preview      {}", preview_path.display());
    outln!(
        "  error map    {} (distance to the true walls: blue 0 mm to red {ERROR_MAP_SCALE_MM} mm and beyond)",
        error_map_path.display()
    );
    outln!("total {:.1} s", start.elapsed().as_secs_f64());
    Ok(())
}
