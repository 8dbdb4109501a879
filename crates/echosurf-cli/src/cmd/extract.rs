//! `echosurf extract`: sequence + calibration -> surface mesh(es), with an optional report and preview.

use std::path::{Path, PathBuf};

use anyhow::Context;
use echosurf::io;
use echosurf::pipeline::{
    self, ExtractOptions, ExtractOutput, IsoLevels, Method, Sheet, VoxelRouteOptions, WeakEchoes,
};
use echosurf::rbf::FitOptions;
use echosurf::render::{RenderOptions, render_views, write_png};
use echosurf::segment::InitialBand;
use echosurf::surface::{SheetOptions, SurfaceOptions};

use super::outputs::{Holds, Output, check_outputs, output};
use super::segment::{SegmentArgs, world_choice};
use crate::progress::BarProgress;

#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub segment: SegmentArgs,
    /// Iso-level(s) of the boundary echo, comma separated (one mesh each), or `auto`: between the
    /// background and boundary echo levels of the kept pixels.
    #[arg(long, default_value = "auto")]
    pub iso: String,
    /// Output mesh (.ply, .stl, .obj or .vtk). With several levels, `_iso<LEVEL>` is added before the
    /// extension.
    #[arg(long)]
    pub out: PathBuf,
    #[command(flatten)]
    pub space: super::space::SpaceArg,
    /// Route: `rbf` (segment, fit one RBF to the kept pixels, surface it) or `voxel` (PLUS-like volume of
    /// all clipped pixels with the config's VolumeReconstruction settings, Gaussian, marching cubes).
    #[arg(long, default_value = "rbf")]
    pub method: String,
    /// Voxel route: sigma of the Gaussian pre-smoothing in mm (0 = none).
    #[arg(long, default_value_t = 1.0)]
    pub voxel_smoothing: f64,
    /// Voxel route: grid spacing in mm (default: the config's OutputSpacing, else --resolution).
    #[arg(long)]
    pub voxel_spacing: Option<f64>,
    /// Voxel route: refuse grids needing more memory than this many MB.
    #[arg(long)]
    pub voxel_memory_mb: Option<u64>,
    /// Random decimation target for the samples handed to the fit.
    #[arg(long, default_value_t = 100_000)]
    pub max_samples: usize,
    /// Smoothing weight w in mm (larger = smoother; 0 interpolates the speckle).
    #[arg(long)]
    pub smoothing: Option<f64>,
    /// RBF solver: auto (partition of unity above 2,000 samples), direct, pu, or fast (the single
    /// global spline; slower).
    #[arg(long, default_value = "auto")]
    pub solver: String,
    /// Fitting accuracy: largest allowed |s(x_i) - f_i - w l_i| in grey levels.
    #[arg(long)]
    pub accuracy: Option<f64>,
    /// Lattice spacing of the surfacer in mm.
    #[arg(long, default_value_t = 0.5)]
    pub resolution: f64,
    /// Region of trust: no surface farther than this (mm) from any sample. Default: from frame spacing.
    #[arg(long)]
    pub trust_distance: Option<f64>,
    /// Average kept pixels over blocks of about this size (mm) before decimation; 0 = single pixels.
    #[arg(long, default_value_t = 0.4)]
    pub sample_bin: f64,
    /// Echo-priority thinning: keep the samples within this many mm of an echo first (up to half the
    /// budget), the rest at random; 0 = the paper's uniform random decimation.
    #[arg(long, default_value_t = pipeline::DEFAULT_ECHO_MARGIN_MM)]
    pub echo_margin: f64,
    /// Output surface: `iso` (the iso-surface, a sheath of two sheets around a thin echo), `ridge`
    /// (one smooth sheet through the echo's ridge: on the boundary, open where no echo came back), or
    /// `auto`: the ridge sheet on a bone sweep and where the echoes are thin ridges (80 % of the
    /// iso-surface's probe side finds the echo's peak within 1.5 mm along the beam), the iso-surface
    /// otherwise.
    #[arg(long, default_value = "auto")]
    pub sheet: String,
    /// Ridge sheet: distance (mm) over which the sheet averages the ridge points.
    #[arg(long, default_value_t = SheetOptions::default().smoothing_mm)]
    pub ridge_smoothing: f64,
    /// Ridge sheet: how far (mm) the sheet may reach from the nearest ridge point (larger bridges more
    /// gaps and extrapolates more at the edges).
    #[arg(long, default_value_t = SheetOptions::default().reach_mm)]
    pub ridge_reach: f64,
    /// Ridge sheet: also bridge gaps between its pieces over up to this many mm in the sheet's plane,
    /// where points surround the gap on a common plane (no overhang at rims, no ramps across folds or
    /// steps); 0 = off.
    #[arg(long, default_value_t = SheetOptions::default().bridge_mm)]
    pub ridge_bridge: f64,
    /// Ridge sheet: also take the ridges of weaker echoes, whose peak passes a lower level this
    /// fraction of the way from the iso-level down to the background, where they continue the ridge of
    /// a strong echo (hysteresis: fills the sheet between frames and along walls turning from the beam);
    /// 0 = off.
    #[arg(long, default_value_t = WeakEchoes::default().level_fraction)]
    pub ridge_weak: f64,
    /// Ridge sheet: how far (mm) a weak echo's ridge may continue from a strong one.
    #[arg(long, default_value_t = WeakEchoes::default().reach_mm)]
    pub ridge_weak_reach: f64,
    /// Ridge sheet: first remove the triangles farther than this (mm) from every echo (a kept sample
    /// block as bright as the lowest level the sheet was drawn at, reaching out of its frame half the
    /// gap to the next frame): flaps the fitted function made where no echo was recorded. 0 keeps them.
    #[arg(long, default_value_t = pipeline::DEFAULT_MAX_ECHO_DISTANCE_MM, value_name = "MM")]
    pub max_echo_distance: f64,
    /// Remove connected pieces of the surface smaller than this (mm^2); 0 keeps all. Default: 5 for the
    /// iso sheet, 2 for the ridge sheet.
    #[arg(long)]
    pub min_component_area: Option<f64>,
    /// Remove pieces of the surface that echoes from fewer than this many frames back (an echo: a kept
    /// sample block at or above the surface's level within 1 mm); 0 keeps every piece.
    #[arg(long, default_value_t = pipeline::DEFAULT_MIN_ECHO_FRAMES)]
    pub min_echo_frames: usize,
    /// Join kept pieces whose boundaries pass within this distance (mm) of each other, facing each
    /// other and facing alike, and close the seam between them; 0 joins nothing.
    #[arg(long, default_value_t = pipeline::DEFAULT_BRIDGE_GAP_MM)]
    pub bridge_gap: f64,
    /// Peel this many rings of triangles off each piece's rim, never cutting or removing a piece: the
    /// rims are the least accurate part of the surface. 0 keeps them.
    #[arg(long, default_value_t = 0, value_name = "RINGS")]
    pub trim_rim: usize,
    /// Seed of the random decimation (and of everything else random).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Refuse up front when the run would need more than this many MB (default: half the machine's memory).
    #[arg(long)]
    pub memory_budget: Option<f64>,
    /// Write what every stage did (counts, parameters, time, peak memory) as JSON.
    #[arg(long)]
    pub report: Option<PathBuf>,
    /// Write a rendered picture of the mesh with the frame outlines.
    #[arg(long)]
    pub preview: Option<PathBuf>,
    /// Also save the fitted model (.esrbf) for `echosurf surface`.
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Also write the fitted samples as a point cloud PLY.
    #[arg(long)]
    pub samples: Option<PathBuf>,
}

/// Parses `--iso`: `auto` or comma-separated numbers.
pub fn parse_iso(text: &str) -> anyhow::Result<IsoLevels> {
    if text.trim().eq_ignore_ascii_case("auto") {
        return Ok(IsoLevels::Auto);
    }
    let levels = text
        .split(',')
        .map(|s| {
            s.trim()
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .with_context(|| {
                    format!("--iso: `{s}` is not a number (expected auto or LEVEL[,LEVEL...])")
                })
        })
        .collect::<anyhow::Result<Vec<f64>>>()?;
    // Each level's mesh is named after it: a level listed twice would be written twice to one file.
    for (k, level) in levels.iter().enumerate() {
        if levels[..k].contains(level) {
            anyhow::bail!("--iso lists the level {} twice", format_level(*level));
        }
    }
    Ok(IsoLevels::Levels(levels))
}

/// Where the mesh of `level` goes: `out` itself for a single level, else `stem_iso<level>.ext`.
pub fn mesh_path(out: &Path, level: f64, several: bool) -> PathBuf {
    if !several {
        return out.to_path_buf();
    }
    let stem = out
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let ext = out
        .extension()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "ply".into());
    out.with_file_name(format!("{stem}_iso{}.{ext}", format_level(level)))
}

/// The mesh files of `iso`'s levels (as [`mesh_path`] names them), each with the option behind it.
pub fn mesh_outputs(out: &Path, iso: &IsoLevels) -> Vec<Output> {
    match iso {
        IsoLevels::Levels(levels) if levels.len() > 1 => levels
            .iter()
            .map(|&level| {
                let option = format!("--out (iso {})", format_level(level));
                output(option, &mesh_path(out, level, true), Holds::Mesh)
            })
            .collect(),
        _ => vec![output("--out", out, Holds::Mesh)],
    }
}

/// A level as a person would write it: the automatic level is chosen in single precision, and its
/// double-precision digits (`112.19999694824219`) would only say so.
fn format_level(level: f64) -> String {
    if level.fract() == 0.0 {
        format!("{level:.0}")
    } else if f64::from(level as f32) == level {
        format!("{}", level as f32)
    } else {
        format!("{level}")
    }
}

/// `--method` and the voxel route's options.
fn parse_method(args: &Args) -> anyhow::Result<Method> {
    match args.method.to_ascii_lowercase().as_str() {
        "rbf" => Ok(Method::Rbf),
        "voxel" => {
            if !(args.voxel_smoothing.is_finite() && args.voxel_smoothing >= 0.0) {
                anyhow::bail!("--voxel-smoothing must be a non-negative number of mm");
            }
            if let Some(s) = args.voxel_spacing
                && !(s.is_finite() && s > 0.0)
            {
                anyhow::bail!("--voxel-spacing must be a positive number of mm");
            }
            Ok(Method::Voxel(VoxelRouteOptions {
                spacing_mm: args.voxel_spacing,
                smoothing_sigma_mm: args.voxel_smoothing,
                // --voxel-memory-mb, else --memory-budget when given (else the voxel default).
                memory_budget_bytes: match (args.voxel_memory_mb, args.memory_budget) {
                    (Some(mb), _) => Some(mb.saturating_mul(1 << 20)),
                    (None, Some(_)) => Some(memory_budget_bytes(args.memory_budget)?),
                    (None, None) => None,
                },
            }))
        }
        other => anyhow::bail!("--method {other}: expected rbf or voxel"),
    }
}

/// Adds to a voxel grid's memory refusal which options set its spacing and the budget.
pub fn name_voxel_options(error: echosurf::Error, spacing_option: &str) -> anyhow::Error {
    match error {
        echosurf::Error::ResourceLimit(message) => anyhow::anyhow!(
            "{message} ({spacing_option} sets the spacing, --memory-budget the budget)"
        ),
        other => other.into(),
    }
}

/// `--memory-budget MB`, or the machine default.
pub fn memory_budget_bytes(mb: Option<f64>) -> anyhow::Result<u64> {
    match mb {
        None => Ok(echosurf::budget::default_memory_budget_bytes()),
        Some(mb) if mb.is_finite() && mb > 0.0 => Ok((mb * 1e6) as u64),
        Some(mb) => anyhow::bail!("--memory-budget must be a positive number of MB, got {mb}"),
    }
}

/// `--sheet iso|ridge|auto`.
pub(crate) fn parse_sheet(text: &str) -> anyhow::Result<Sheet> {
    Ok(match text.to_ascii_lowercase().as_str() {
        "iso" => Sheet::Iso,
        "ridge" => Sheet::EchoRidge,
        "auto" => Sheet::Auto,
        other => anyhow::bail!("--sheet {other}: expected auto, iso or ridge"),
    })
}

/// How the report names a sheet, and why `auto` chose it.
pub(crate) fn describe_sheet(used: &echosurf::pipeline::SheetUsed, asked: Sheet) -> String {
    let name = match used.sheet {
        Sheet::EchoRidge => "ridge",
        _ => "iso",
    };
    let weak = used
        .weak_ridge_level
        .map(|l| format!(", extended by weaker echoes down to {l:.1}"))
        .unwrap_or_default();
    let why = match (asked, used.ridge_reached_share) {
        (Sheet::Auto, Some(share)) => format!(
            "{name} sheet (auto: {:.0} % of the probe side reached an echo ridge, {} {:.0} %)",
            100.0 * share,
            if used.sheet == Sheet::EchoRidge {
                "at least"
            } else {
                "below"
            },
            100.0 * echosurf::pipeline::AUTO_RIDGE_MIN_REACHED_SHARE
        ),
        _ => format!("{name} sheet"),
    };
    let far = match used.triangles_far_from_echoes {
        0 => String::new(),
        n => format!(
            ", {n} triangle{} farther than {} mm from an echo removed",
            if n == 1 { "" } else { "s" },
            used.max_echo_distance_mm
        ),
    };
    let unbacked = match used.pieces_without_echoes {
        0 => String::new(),
        n => format!(
            ", {n} piece{} echoed by fewer than {} frames removed",
            if n == 1 { "" } else { "s" },
            used.min_echo_frames
        ),
    };
    let bridged = match used.bridged_pieces {
        0 => String::new(),
        n => format!(
            ", {n} piece{} joined to a neighbour across a gap",
            if n == 1 { "" } else { "s" }
        ),
    };
    let trimmed = match used.rim_triangles_trimmed {
        0 => String::new(),
        n => format!(
            ", {n} rim triangle{} trimmed ({} ring{})",
            if n == 1 { "" } else { "s" },
            used.trim_rim_rings,
            if used.trim_rim_rings == 1 { "" } else { "s" }
        ),
    };
    why + &weak + &far + &unbacked + &bridged + &trimmed
}

/// A tracked sequence given to score or draw a mesh against (`compare --sequence`, `render
/// --sequence`): the sequence, its calibration if given, and where its frames are in `world`.
pub(crate) fn posed_sequence(
    path: &Path,
    config: Option<&Path>,
    world: &str,
) -> anyhow::Result<(
    io::TrackedSequence,
    Option<io::Calibration>,
    io::PoseResolution,
)> {
    let sequence = super::inputs::read_sequence(path)?;
    let calibration = config
        .map(|c| super::inputs::read_calibration_for(c, &sequence, path))
        .transpose()?;
    let poses = io::resolve_poses(&sequence, calibration.as_ref(), world_choice(world)?, path)?;
    Ok((sequence, calibration, poses))
}

pub fn run(args: Args) -> anyhow::Result<()> {
    run_with(args, &BarProgress::new()).map(|_| ())
}

/// `extract` with progress reported to `progress`: checks, runs the pipeline, writes every output and
/// prints the summary; returns what the pipeline produced (for the Slicer module's return values).
pub fn run_with(
    args: Args,
    progress: &dyn echosurf::progress::Progress,
) -> anyhow::Result<ExtractOutput> {
    let seg = &args.segment;
    let iso = parse_iso(&args.iso)?;
    if !(args.resolution.is_finite() && args.resolution > 0.0) {
        anyhow::bail!("--resolution must be a positive number of mm");
    }
    for (flag, mm) in [
        ("--ridge-smoothing", args.ridge_smoothing),
        ("--ridge-reach", args.ridge_reach),
        ("--ridge-weak-reach", args.ridge_weak_reach),
    ] {
        if !(mm.is_finite() && mm > 0.0) {
            anyhow::bail!("{flag} must be a positive number of mm, got {mm}");
        }
    }
    if !(args.ridge_bridge.is_finite() && args.ridge_bridge >= 0.0) {
        anyhow::bail!(
            "--ridge-bridge must be 0 or a positive number of mm, got {}",
            args.ridge_bridge
        );
    }
    if !(args.ridge_weak.is_finite() && (0.0..1.0).contains(&args.ridge_weak)) {
        anyhow::bail!(
            "--ridge-weak must be a fraction in [0, 1) of the way from the iso-level to the background, got {}",
            args.ridge_weak
        );
    }
    check_outputs(&seg.input_files(), &planned_outputs(&args, &iso))?;
    let sequence = super::inputs::read_sequence(&seg.sequence)?;
    let calibration = io::read_calibration(&seg.config)?;
    let init = match &seg.init {
        Some(path) => InitialBand::load(path, sequence.width, sequence.height)?,
        None => InitialBand::Auto,
    };
    // After the band: a bad band file is the more specific complaint.
    super::inputs::check_clip(&calibration, &sequence, &seg.config, &seg.sequence)?;
    let method = parse_method(&args)?;
    let defaults = FitOptions::default();
    let options = ExtractOptions {
        method,
        iso,
        init,
        segment: seg.options(),
        reference: world_choice(&seg.world)?,
        max_samples: args.max_samples,
        seed: args.seed,
        fit: FitOptions {
            smoothing: args.smoothing.unwrap_or(pipeline::DEFAULT_SMOOTHING_MM),
            accuracy: args.accuracy.unwrap_or(defaults.accuracy),
            seed: args.seed,
            solver: super::fit::parse_solver(&args.solver)?,
            ..defaults
        },
        surface: SurfaceOptions {
            resolution_mm: args.resolution,
            ..SurfaceOptions::default()
        },
        trust_distance_mm: args.trust_distance,
        sample_bin_mm: args.sample_bin,
        echo_margin_mm: echo_margin(args.echo_margin)?,
        sheet: parse_sheet(&args.sheet)?,
        echo_sheet: SheetOptions {
            smoothing_mm: args.ridge_smoothing,
            reach_mm: args.ridge_reach,
            bridge_mm: args.ridge_bridge,
            ..SheetOptions::default()
        },
        weak_echoes: WeakEchoes {
            level_fraction: args.ridge_weak,
            reach_mm: args.ridge_weak_reach,
        },
        min_echo_frames: args.min_echo_frames,
        trim_rim_rings: args.trim_rim,
        max_echo_distance_mm: if args.max_echo_distance.is_finite() && args.max_echo_distance >= 0.0
        {
            args.max_echo_distance
        } else {
            anyhow::bail!("--max-echo-distance must be a distance in mm >= 0")
        },
        bridge_gap_mm: if args.bridge_gap.is_finite() && args.bridge_gap >= 0.0 {
            args.bridge_gap
        } else {
            anyhow::bail!("--bridge-gap must be a distance in mm >= 0")
        },
        min_component_area_mm2: match args.min_component_area {
            Some(a) if !(a.is_finite() && a >= 0.0) => {
                anyhow::bail!("--min-component-area must be an area in mm^2 >= 0")
            }
            a => a,
        },
        memory_budget_bytes: Some(memory_budget_bytes(args.memory_budget)?),
    };
    let voxel = matches!(options.method, Method::Voxel(_));
    let output = pipeline::extract(&sequence, Some(&calibration), &options, progress)
        .map_err(|e| {
            if voxel {
                name_voxel_options(e, "--voxel-spacing")
            } else {
                e.into()
            }
        })
        .with_context(|| format!("extracting a surface from {}", seg.sequence.display()))?;
    write_outputs(&args, &output)?;
    print_summary(&args, &output)?;
    Ok(output)
}

/// The files `write_outputs` will write, each with the option that names it: one mesh per level
/// (`--iso auto` is one level), then the optional model, samples, report and preview.
fn planned_outputs(args: &Args, iso: &IsoLevels) -> Vec<Output> {
    let mut files = mesh_outputs(&args.out, iso);
    for (option, path, holds) in [
        ("--model", &args.model, Holds::AnyName),
        ("--samples", &args.samples, Holds::PointCloud),
        ("--report", &args.report, Holds::AnyName),
        ("--preview", &args.preview, Holds::Png),
    ] {
        files.extend(path.as_deref().map(|p| output(option, p, holds)));
    }
    files
}

/// Writes meshes, then the optional model, samples, report and preview (each atomically).
pub fn write_outputs(args: &Args, output: &ExtractOutput) -> anyhow::Result<()> {
    let several = output.surfaces.len() > 1;
    for s in &output.surfaces {
        io::write_mesh_in(
            &mesh_path(&args.out, s.level, several),
            &s.mesh,
            args.space.space,
        )?;
    }
    if let Some(path) = &args.model {
        match &output.model {
            Some(model) => model.save(path)?,
            None => anyhow::bail!("--model: the voxel route fits no model"),
        }
    }
    if let Some(path) = &args.samples {
        io::write_point_cloud(path, &output.samples.to_point_cloud())?;
    }
    if let Some(path) = &args.report {
        let report = super::space::with_coordinates(
            &output.report,
            &output.report.parameters.world_frame,
            args.space.space,
        )?;
        let json = serde_json::to_string_pretty(&report)?;
        io::atomic::write_bytes_atomic(path, json.as_bytes())?;
    }
    if let Some(path) = &args.preview {
        write_preview(path, output, None)?;
    }
    Ok(())
}

/// Renders all surfaces (merged) with the frame outlines, optionally over a ghost of the truth.
/// Every 8th frame's outline is enough to show the sweep without hiding the surface.
pub(crate) const PREVIEW_OUTLINE_EVERY: usize = 8;

/// The outlines of every `every`-th frame, from the four segments per frame of
/// `pipeline::frame_outlines`.
pub(crate) fn every_nth_outline(
    outlines: &[[glam::DVec3; 2]],
    every: usize,
) -> Vec<[glam::DVec3; 2]> {
    outlines
        .chunks(4)
        .step_by(every.max(1))
        .flatten()
        .copied()
        .collect()
}

pub fn write_preview(
    path: &Path,
    output: &ExtractOutput,
    ghost: Option<echosurf::mesh::Mesh>,
) -> anyhow::Result<()> {
    let mut mesh = echosurf::mesh::Mesh::default();
    for s in &output.surfaces {
        let base = mesh.vertices.len() as u32;
        mesh.vertices.extend(&s.mesh.vertices);
        mesh.normals.extend(&s.mesh.normals);
        mesh.triangles
            .extend(s.mesh.triangles.iter().map(|t| t.map(|i| i + base)));
    }
    if mesh.normals.len() != mesh.vertices.len() {
        mesh.normals.clear();
    }
    if mesh.is_empty() {
        eprintln!("warning: no surface to render; preview not written");
        return Ok(());
    }
    let options = RenderOptions {
        overlay_lines: every_nth_outline(&output.frame_outlines, PREVIEW_OUTLINE_EVERY),
        ghost,
        ..RenderOptions::default()
    };
    let image = render_views(&mesh, &options)?;
    write_png(path, &image)?;
    Ok(())
}

fn print_sample_counts(
    c: &pipeline::StageCounts,
    fit: Option<&echosurf::rbf::FitReport>,
) -> anyhow::Result<()> {
    // Partition of unity stores each patch's samples, overlaps included: not a reduction of the samples.
    let model = match fit {
        Some(f) if f.patches > 0 => format!(
            "{} patches of {:.0} samples on average",
            f.patches, f.mean_patch_points
        ),
        _ => format!("{} centres", c.centres),
    };
    if c.bone_sweep {
        outln!(
            "bone: bright echoes over an acoustic shadow in most frames, the probe on tissue: the band is the \
             bone's echo, fitted against each echo's own contrast (--bone never: the paper's band)"
        );
    }
    outln!(
        "{} of {} frames used; kept {} of {} pixels ({:.1}%); {} samples -> {model}",
        c.frames_used,
        c.frames,
        c.kept_pixels,
        c.pixels,
        100.0 * c.kept_pixels as f64 / c.pixels.max(1) as f64,
        c.samples,
    );
    Ok(())
}

fn print_summary(args: &Args, output: &ExtractOutput) -> anyhow::Result<()> {
    let r = &output.report;
    let c = &r.counts;
    if r.voxel.is_some() {
        outln!(
            "{} of {} frames used; all {} pixels (inside the clip rectangle) go into the volume",
            c.frames_used,
            c.frames,
            c.pixels
        );
    } else {
        print_sample_counts(c, r.fit.as_ref())?;
    }
    if let Some(l) = r.levels {
        outln!(
            "echo levels: background {:.1}, boundary {:.1}, strong echoes {:.1}{}",
            l.background,
            l.boundary,
            l.strong_echo,
            if r.parameters.iso_auto {
                format!(", iso auto = {:.1}", l.iso)
            } else {
                String::new()
            }
        );
    }
    if let Some(fit) = &r.fit {
        outln!(
            "fit: w = {} mm, max system residual {:.2} grey, data misfit rms {:.2} max {:.2} grey, \
             {} iterations",
            r.parameters.smoothing_mm,
            fit.max_residual,
            fit.rms_data_misfit,
            fit.max_data_misfit,
            fit.iterations
        );
    }
    if let Some(v) = &r.voxel {
        outln!(
            "volume: {}x{}x{} voxels at {} mm ({} interpolation, {} compounding, hole filling {}); \
             {} hit, {} filled; Gaussian sigma {} mm; {} triangles dropped at the data edge",
            v.dims[0],
            v.dims[1],
            v.dims[2],
            v.spacing_mm[0],
            v.interpolation,
            v.compounding,
            v.hole_filling,
            v.voxels_hit,
            v.voxels_filled,
            v.smoothing_sigma_mm,
            v.triangles_dropped_at_data_edge
        );
    }
    let several = output.surfaces.len() > 1;
    for (s, used) in output.surfaces.iter().zip(&r.sheets) {
        let t = s.mesh.topology();
        outln!(
            "iso {}: {}, {} triangles, {} component(s), {} -> {}",
            format_level(s.level),
            describe_sheet(used, r.parameters.sheet),
            s.mesh.triangles.len(),
            t.components,
            if t.is_closed_manifold() {
                "closed manifold"
            } else if t.is_oriented_manifold() {
                "manifold with boundary"
            } else {
                "NOT manifold"
            },
            mesh_path(&args.out, s.level, several).display()
        );
    }
    let stages: Vec<String> = r
        .stages
        .iter()
        .map(|s| format!("{} {:.2}s", s.stage, s.seconds))
        .collect();
    outln!(
        "time {:.2} s ({}); peak memory {}",
        r.total_seconds,
        stages.join(", "),
        r.peak_rss_bytes
            .map(|b| format!("{:.0} MB", b as f64 / 1e6))
            .unwrap_or_else(|| "n/a".into())
    );
    for w in &r.warnings {
        eprintln!("warning: {w}");
    }
    Ok(())
}

/// `--echo-margin`: 0 selects uniform thinning; negative or non-finite is an error.
pub(crate) fn echo_margin(mm: f64) -> anyhow::Result<Option<f64>> {
    if !(mm.is_finite() && mm >= 0.0) {
        anyhow::bail!(
            "--echo-margin must be a distance in mm >= 0 (0 = uniform thinning), got {mm}"
        );
    }
    Ok((mm > 0.0).then_some(mm))
}

#[cfg(test)]
mod tests {
    use super::{IsoLevels, format_level, parse_iso};

    #[test]
    fn levels_are_written_as_a_person_would() {
        assert_eq!(format_level(40.0), "40");
        assert_eq!(format_level(60.1), "60.1");
        assert_eq!(format_level(f64::from(112.2f32)), "112.2");
        assert_eq!(format_level(-0.5), "-0.5");
    }

    #[test]
    fn iso_levels_are_auto_or_distinct_finite_numbers() {
        assert!(matches!(parse_iso(" AUTO ").unwrap(), IsoLevels::Auto));
        match parse_iso("40, 60.5").unwrap() {
            IsoLevels::Levels(levels) => assert_eq!(levels, vec![40.0, 60.5]),
            IsoLevels::Auto => panic!("numbers read as auto"),
        }
        let refused = |text: &str| parse_iso(text).unwrap_err().to_string();
        assert!(refused("40,x").contains("`x` is not a number"));
        assert!(refused("nan").contains("not a number"));
        assert!(refused("").contains("not a number"));
        assert_eq!(refused("40,60,40.0"), "--iso lists the level 40 twice");
    }
}
