//! `echosurf extract`: sequence + calibration -> surface mesh(es), with an optional report and preview.

use std::path::{Path, PathBuf};

use anyhow::Context;
use echosurf::io;
use echosurf::pipeline::{
    self, ExtractConfig, ExtractOutput, IsoLevels, Method, MethodChoice, Sheet,
};
use echosurf::render::{RenderOptions, render_views, write_png};
use echosurf::segment::InitialBand;

use super::outputs::{Holds, Output, check_outputs, output};
use super::segment::world_choice;
use crate::progress::BarProgress;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Tracked sequence (.igs.mha, .mhd, .igs.nrrd).
    #[arg(required_unless_present = "print_config")]
    pub sequence: Option<PathBuf>,
    /// PLUS device-set XML with the Image->Probe calibration (and clip rectangle).
    #[arg(long, required_unless_present = "print_config")]
    pub calibration: Option<PathBuf>,
    /// Output mesh (.ply, .stl, .obj or .vtk). With several levels, `_iso<LEVEL>` is added before the
    /// extension.
    #[arg(long, required_unless_present = "print_config")]
    pub out: Option<PathBuf>,
    /// Initial band for the first frame of each sweep: a PNG mask of the frame size (non-zero = band) or a
    /// JSON polygon {"polygon": [[u, v], ...]} in pixels of the MF-oriented frame. Default: found
    /// automatically (bright connected echo structures).
    #[arg(long)]
    pub init: Option<PathBuf>,
    /// Iso-level(s) of the boundary echo, comma separated (one mesh each), or `auto` (the default):
    /// between the background and boundary echo levels of the kept pixels.
    #[arg(long)]
    pub iso: Option<String>,
    /// Smoothing weight w in mm (larger = smoother; 0 interpolates the speckle) [default: 2].
    #[arg(long)]
    pub smoothing: Option<f64>,
    /// Output surface: `iso` (the iso-surface, a sheath of two sheets around a thin echo), `ridge`
    /// (one smooth sheet through the echo's ridge: on the boundary, open where no echo came back), or
    /// `auto` (the default): the ridge sheet on a bone sweep and where the echoes are thin ridges, the
    /// iso-surface otherwise.
    #[arg(long)]
    pub sheet: Option<String>,
    /// Lattice spacing of the surfacer in mm [default: 0.5].
    #[arg(long)]
    pub resolution: Option<f64>,
    /// Random decimation target for the samples handed to the fit [default: 100000].
    #[arg(long)]
    pub max_samples: Option<usize>,
    /// Route: `rbf` (the default: segment, fit one RBF to the kept pixels, surface it) or `voxel`
    /// (PLUS-like volume of all clipped pixels with the calibration's VolumeReconstruction settings,
    /// Gaussian, marching cubes).
    #[arg(long)]
    pub method: Option<String>,
    /// Seed of the random decimation (and of everything else random) [default: 1].
    #[arg(long)]
    pub seed: Option<u64>,
    /// Refuse up front when the run would need more than this many MB (default: half the machine's memory).
    #[arg(long)]
    pub memory_budget: Option<f64>,
    #[command(flatten)]
    pub space: super::space::SpaceArg,
    /// Write what every stage did (counts, parameters, time, peak memory) as JSON.
    #[arg(long)]
    pub report: Option<PathBuf>,
    /// Write a rendered picture of the mesh with the frame outlines.
    #[arg(long)]
    pub preview: Option<PathBuf>,
    /// Every other option (segmentation, sampling, fit, surfacer, ridge sheet, clean-up, voxel route)
    /// from this TOML file, as `--print-config` writes it; missing keys take the defaults and the
    /// options above override it.
    #[arg(long, value_name = "FILE.toml")]
    pub config: Option<PathBuf>,
    /// Write the full option set (the defaults, with --config and the options above applied) as TOML
    /// to stdout and exit.
    #[arg(long)]
    pub print_config: bool,
}

/// The paths a run needs: present unless `--print-config` (clap checks).
struct RunPaths<'a> {
    sequence: &'a Path,
    calibration: &'a Path,
    out: &'a Path,
}

impl Args {
    fn paths(&self) -> anyhow::Result<RunPaths<'_>> {
        match (&self.sequence, &self.calibration, &self.out) {
            (Some(sequence), Some(calibration), Some(out)) => Ok(RunPaths {
                sequence,
                calibration,
                out,
            }),
            _ => anyhow::bail!("give the sequence, --calibration and --out"),
        }
    }

    /// Every file this reads: the sequence (with a detached data file), the calibration, the band
    /// and the option file.
    fn input_files(&self) -> Vec<PathBuf> {
        let mut files: Vec<PathBuf> = self
            .sequence
            .iter()
            .flat_map(|s| io::sequence_files(s))
            .collect();
        files.extend(self.calibration.iter().cloned());
        files.extend(self.init.iter().cloned());
        files.extend(self.config.iter().cloned());
        files
    }

    /// The option set: the defaults, then `--config`, then the user options given here; validated.
    pub fn extract_config(&self) -> anyhow::Result<ExtractConfig> {
        Ok(self.config_file()?.options())
    }

    /// [`Self::extract_config`] with the `[outputs]` of `--config`.
    pub fn config_file(&self) -> anyhow::Result<ConfigFile> {
        let mut file = match &self.config {
            Some(path) => read_config(path)?,
            None => ConfigFile::default(),
        };
        let config = &mut file.options;
        let user = &mut config.user;
        if let Some(iso) = &self.iso {
            user.iso = parse_iso(iso)?;
        }
        if let Some(w) = self.smoothing {
            user.smoothing_mm = w;
        }
        if let Some(sheet) = &self.sheet {
            user.sheet = parse_sheet(sheet)?;
        }
        if let Some(mm) = self.resolution {
            user.resolution_mm = mm;
        }
        if let Some(n) = self.max_samples {
            user.max_samples = n;
        }
        if let Some(method) = &self.method {
            user.method = match method.to_ascii_lowercase().as_str() {
                "rbf" => MethodChoice::Rbf,
                "voxel" => MethodChoice::Voxel,
                other => anyhow::bail!("--method {other}: expected rbf or voxel"),
            };
        }
        if let Some(seed) = self.seed {
            user.seed = seed;
        }
        if let Some(mb) = self.memory_budget {
            config.tuning.memory_budget_mb = Some(mb);
        }
        config.validate().map_err(|e| {
            let flag = cli_flag(&e.field);
            match (&self.config, flag) {
                // Given on the command line: the flag is what the user typed.
                (_, Some(flag)) if flag_given(self, flag) => {
                    anyhow::anyhow!("{flag} {}", e.problem)
                }
                (Some(path), _) => anyhow::anyhow!("{}: {e}", path.display()),
                (None, Some(flag)) => anyhow::anyhow!("{flag} {}", e.problem),
                (None, None) => anyhow::anyhow!("{e}"),
            }
        })?;
        Ok(file)
    }
}

/// The `--config` file: both tiers of options, and the niche outputs that have no flag.
#[derive(Debug, Clone, Default)]
pub struct ConfigFile {
    pub options: ExtractConfig,
    pub outputs: ExtraOutputs,
}

impl ConfigFile {
    pub fn options(self) -> ExtractConfig {
        self.options
    }

    /// The file as `--print-config` writes it: every option with its value, then `[outputs]`
    /// (commented out where not set).
    pub fn to_toml(&self) -> anyhow::Result<String> {
        let mut text = toml::to_string(&self.options)?;
        text.push_str("\n[outputs]\n");
        let line = |key: &str, path: &Option<PathBuf>, example: &str, what: &str| match path {
            Some(p) => format!(
                "{key} = {}  # {what}\n",
                toml::Value::from(p.display().to_string())
            ),
            None => format!("# {key} = \"{example}\"  # {what}\n"),
        };
        text.push_str(&line(
            "model",
            &self.outputs.model,
            "model.esrbf",
            "also save the fitted model, for `echosurf surface`",
        ));
        text.push_str(&line(
            "samples",
            &self.outputs.samples,
            "samples.ply",
            "also write the fitted samples as a point cloud",
        ));
        Ok(text)
    }
}

/// `[outputs]` of the `--config` file (paths relative to the working directory, as on the command line).
#[derive(Debug, Clone, Default, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ExtraOutputs {
    /// Also save the fitted model (.esrbf) for `echosurf surface`.
    pub model: Option<PathBuf>,
    /// Also write the fitted samples as a point cloud PLY.
    pub samples: Option<PathBuf>,
}

/// What the `--config` TOML holds.
#[derive(Debug, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
struct ConfigToml {
    user: echosurf::pipeline::UserOptions,
    tuning: echosurf::pipeline::Tuning,
    outputs: ExtraOutputs,
}

impl Default for ConfigToml {
    fn default() -> Self {
        let ExtractConfig { user, tuning } = ExtractConfig::default();
        ConfigToml {
            user,
            tuning,
            outputs: ExtraOutputs::default(),
        }
    }
}

/// The command-line flag of a user-tier field, if it has one.
fn cli_flag(field: &str) -> Option<&'static str> {
    Some(match field {
        "user.iso" => "--iso",
        "user.smoothing_mm" => "--smoothing",
        "user.resolution_mm" => "--resolution",
        "user.max_samples" => "--max-samples",
        "tuning.memory_budget_mb" => "--memory-budget",
        _ => return None,
    })
}

/// Whether `flag` was given on the command line.
fn flag_given(args: &Args, flag: &str) -> bool {
    match flag {
        "--iso" => args.iso.is_some(),
        "--smoothing" => args.smoothing.is_some(),
        "--resolution" => args.resolution.is_some(),
        "--max-samples" => args.max_samples.is_some(),
        "--memory-budget" => args.memory_budget.is_some(),
        _ => false,
    }
}

/// Reads `--config FILE.toml`: unknown keys and bad values are errors naming the file and the key;
/// a PLUS XML (the old meaning of `--config`) gets a pointer to `--calibration`.
pub fn read_config(path: &Path) -> anyhow::Result<ConfigFile> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    let is_xml_name = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("xml"));
    let text = String::from_utf8_lossy(&bytes);
    if is_xml_name
        || text
            .trim_start_matches('\u{feff}')
            .trim_start()
            .starts_with('<')
    {
        anyhow::bail!(
            "{} is a PLUS device-set XML; give it with --calibration (--config takes the TOML that \
             `echosurf extract --print-config` writes)",
            path.display()
        );
    }
    let file: ConfigToml = toml::from_str(&text)
        .map_err(|e| anyhow::anyhow!("{}: {}", path.display(), e.to_string().trim_end()))?;
    let options = ExtractConfig {
        user: file.user,
        tuning: file.tuning,
    };
    options
        .validate()
        .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
    Ok(ConfigFile {
        options,
        outputs: file.outputs,
    })
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
    let minor = match used.minor_pieces_removed {
        0 => String::new(),
        n => format!(
            ", {n} piece{} under {} % of the largest removed",
            if n == 1 { "" } else { "s" },
            100.0 * used.min_piece_share_of_largest
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
    why + &weak + &far + &unbacked + &bridged + &minor + &trimmed
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
    if args.print_config {
        out!("{}", args.config_file()?.to_toml()?);
        return Ok(());
    }
    run_with(args, &BarProgress::new()).map(|_| ())
}

/// `extract` with progress reported to `progress`: checks, runs the pipeline, writes every output and
/// prints the summary; returns what the pipeline produced (for the Slicer module's return values).
pub fn run_with(
    args: Args,
    progress: &dyn echosurf::progress::Progress,
) -> anyhow::Result<ExtractOutput> {
    if args.print_config {
        anyhow::bail!("--print-config writes the options and runs nothing");
    }
    let ConfigFile {
        options: config,
        outputs: extra,
    } = args.config_file()?;
    let paths = args.paths()?;
    check_outputs(
        &args.input_files(),
        &planned_outputs(&args, &extra, paths.out, &config.user.iso),
    )?;
    let sequence = super::inputs::read_sequence(paths.sequence)?;
    let calibration = io::read_calibration(paths.calibration)?;
    let init = match &args.init {
        Some(path) => InitialBand::load(path, sequence.width, sequence.height)?,
        None => InitialBand::Auto,
    };
    // After the band: a bad band file is the more specific complaint.
    super::inputs::check_clip(&calibration, &sequence, paths.calibration, paths.sequence)?;
    let options = config.to_extract_options(init);
    let voxel = matches!(options.method, Method::Voxel(_));
    let output = pipeline::extract(&sequence, Some(&calibration), &options, progress)
        .map_err(|e| {
            if voxel {
                name_voxel_options(e, "tuning.voxel.spacing_mm")
            } else {
                e.into()
            }
        })
        .with_context(|| format!("extracting a surface from {}", paths.sequence.display()))?;
    write_outputs(&args, &extra, paths.out, &output)?;
    print_summary(paths.out, &output)?;
    Ok(output)
}

/// The files `write_outputs` will write, each with the option that names it: one mesh per level
/// (`--iso auto` is one level), then the optional model, report and preview.
fn planned_outputs(args: &Args, extra: &ExtraOutputs, out: &Path, iso: &IsoLevels) -> Vec<Output> {
    let mut files = mesh_outputs(out, iso);
    for (option, path, holds) in [
        ("outputs.model", &extra.model, Holds::AnyName),
        ("outputs.samples", &extra.samples, Holds::PointCloud),
        ("--report", &args.report, Holds::AnyName),
        ("--preview", &args.preview, Holds::Png),
    ] {
        files.extend(path.as_deref().map(|p| output(option, p, holds)));
    }
    files
}

/// Writes meshes to `out`, then the optional model, report and preview (each atomically).
pub fn write_outputs(
    args: &Args,
    extra: &ExtraOutputs,
    out: &Path,
    output: &ExtractOutput,
) -> anyhow::Result<()> {
    let several = output.surfaces.len() > 1;
    for s in &output.surfaces {
        io::write_mesh_in(&mesh_path(out, s.level, several), &s.mesh, args.space.space)?;
    }
    if let Some(path) = &extra.model {
        match &output.model {
            Some(model) => model.save(path)?,
            None => anyhow::bail!("outputs.model: the voxel route fits no model"),
        }
    }
    if let Some(path) = &extra.samples {
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

fn print_summary(out: &Path, output: &ExtractOutput) -> anyhow::Result<()> {
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
            mesh_path(out, s.level, several).display()
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
