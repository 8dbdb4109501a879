//! `echosurf simulate`: tracked B-mode sweeps of a phantom with ground truth.

use std::path::PathBuf;

use anyhow::Context;
use echosurf_sim::{
    PhantomKind, PhysicsPreset, SimulationNames, SimulationOptions, Surround, simulate,
    write_preview, write_simulation_as,
};

use super::outputs::{Holds, check_outputs, output};

/// The default `--name`, whose truth and description keep their historic names.
const DEFAULT_NAME: &str = "sim";

#[derive(Debug, clap::Args)]
pub struct Args {
    /// sphere | ellipsoid | torus | duck | hand | bone | PATH to a closed STL/PLY/OBJ mesh (mm).
    #[arg(long, default_value = "duck")]
    phantom: String,
    /// Output folder (created if missing).
    #[arg(long)]
    out: PathBuf,
    /// Base name of the files: NAME.mha, NAME_config.xml, NAME_truth.ply, NAME_phantom.json (with the
    /// default `sim`: sim.mha, sim_config.xml, truth.ply, phantom.json).
    #[arg(long, default_value = DEFAULT_NAME)]
    name: String,
    /// Random seed: same arguments and seed give identical files.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Scan, noise and motion settings (boxed: they are many).
    #[command(flatten)]
    knobs: Box<Knobs>,
    /// A perfect system: no tracker noise, no calibration error, no object motion.
    #[arg(long)]
    no_errors: bool,
    /// Lattice spacing (mm) of the true surfaces.
    #[arg(long)]
    truth_resolution: Option<f64>,
    /// Write the sequence without zlib compression.
    #[arg(long)]
    uncompressed: bool,
    /// Also write a PNG montage of 12 frames.
    #[arg(long)]
    preview: Option<PathBuf>,
    /// Worker threads (default: all cores). The output does not depend on it.
    #[arg(long)]
    threads: Option<usize>,
    /// Coordinates of the truth meshes.
    #[command(flatten)]
    space: super::space::SpaceArg,
}

/// Named physics (`--physics`).
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
enum PhysicsArg {
    /// The water bath of the paper's phantoms.
    Default,
    /// The object in soft tissue: speckle all around it.
    Tissue,
    /// A bone surface in soft tissue: strong echo, full shadow below.
    Bone,
}

/// Medium around the object (`--surround`).
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
enum SurroundArg {
    Water,
    Tissue,
}

/// Optional settings; each left out keeps the library default.
#[derive(Debug, clap::Args)]
struct Knobs {
    /// Starting physics, which the knobs below then change (default: `bone` for `--phantom bone`,
    /// `default` otherwise).
    #[arg(long, value_enum)]
    physics: Option<PhysicsArg>,
    /// n in cos^n: how fast a specular echo falls with the angle between wall normal and beam.
    #[arg(long)]
    specular_exponent: Option<f64>,
    /// Share (0, 1] of the 0.1 mm cells holding a diffuse scatterer (1 = fully developed speckle).
    #[arg(long)]
    scatterer_density: Option<f64>,
    /// Shadow strength: share [0, 1] of the amplitude lost at each interface crossed.
    #[arg(long)]
    interface_loss: Option<f64>,
    /// Medium around the object (and in the duck's cavity).
    #[arg(long, value_enum)]
    surround: Option<SurroundArg>,
    /// Frames per sweep.
    #[arg(long)]
    frames_per_sweep: Option<usize>,
    /// Number of sweeps (default: enough to cover the object: top passes plus two side sweeps).
    #[arg(long)]
    sweeps: Option<usize>,
    /// Image width in pixels.
    #[arg(long)]
    width: Option<usize>,
    /// Image height (depth) in pixels.
    #[arg(long)]
    height: Option<usize>,
    /// Pixel size in mm (square pixels).
    #[arg(long)]
    pixel_size: Option<f64>,
    /// Probe centre frequency in MHz (attenuation scales with it).
    #[arg(long)]
    frequency: Option<f64>,
    /// Axial / lateral PSF full width at half maximum (mm).
    #[arg(long)]
    axial_fwhm: Option<f64>,
    #[arg(long)]
    lateral_fwhm: Option<f64>,
    /// Electronic noise floor (dB re full scale).
    #[arg(long)]
    noise_db: Option<f64>,
    /// Tracker noise: standard deviation per axis (mm, degrees).
    #[arg(long)]
    tracker_noise_mm: Option<f64>,
    #[arg(long)]
    tracker_noise_deg: Option<f64>,
    /// Calibration error of the written calibration (mm, degrees).
    #[arg(long)]
    calibration_error_mm: Option<f64>,
    #[arg(long)]
    calibration_error_deg: Option<f64>,
    /// Hand tremor amplitude (mm).
    #[arg(long)]
    tremor_mm: Option<f64>,
    /// Untracked object motion amplitude (mm); 0 = still.
    #[arg(long)]
    object_motion_mm: Option<f64>,
}

fn options_from(args: &Args) -> SimulationOptions {
    let phantom = PhantomKind::parse(&args.phantom);
    let physics = match args.knobs.physics {
        Some(PhysicsArg::Default) => PhysicsPreset::Default,
        Some(PhysicsArg::Tissue) => PhysicsPreset::Tissue,
        Some(PhysicsArg::Bone) => PhysicsPreset::Bone,
        None if phantom == PhantomKind::Bone => PhysicsPreset::Bone,
        None => PhysicsPreset::Default,
    };
    let mut o = SimulationOptions {
        phantom,
        seed: args.seed,
        acoustics: physics.acoustics(),
        ..Default::default()
    };
    if let Some(surround) = args.knobs.surround {
        o.acoustics = o.acoustics.with_surround(match surround {
            SurroundArg::Water => Surround::Water,
            SurroundArg::Tissue => Surround::Tissue,
        });
    }
    if let Some(v) = args.knobs.specular_exponent {
        o.acoustics.specular_exponent = v;
    }
    if let Some(v) = args.knobs.scatterer_density {
        o.acoustics.scatterer_density = v;
    }
    if let Some(v) = args.knobs.interface_loss {
        o.acoustics.interface_loss = v;
    }
    if let Some(v) = args.knobs.frames_per_sweep {
        o.frames_per_sweep = v;
    }
    o.sweeps = args.knobs.sweeps;
    if let Some(v) = args.knobs.width {
        o.width_px = v;
    }
    if let Some(v) = args.knobs.height {
        o.height_px = v;
    }
    if let Some(v) = args.knobs.pixel_size {
        o.pixel_size_mm = v;
    }
    if let Some(v) = args.knobs.frequency {
        // Resolution scales with wavelength unless given explicitly.
        let scale = o.acoustics.frequency_mhz / v;
        o.acoustics.axial_fwhm_mm *= scale;
        o.acoustics.lateral_fwhm_mm *= scale;
        o.acoustics.frequency_mhz = v;
    }
    if let Some(v) = args.knobs.axial_fwhm {
        o.acoustics.axial_fwhm_mm = v;
    }
    if let Some(v) = args.knobs.lateral_fwhm {
        o.acoustics.lateral_fwhm_mm = v;
    }
    if let Some(v) = args.knobs.noise_db {
        o.acoustics.noise_db = v;
    }
    if let Some(v) = args.knobs.tracker_noise_mm {
        o.errors.tracker_noise_mm = v;
    }
    if let Some(v) = args.knobs.tracker_noise_deg {
        o.errors.tracker_noise_deg = v;
    }
    if let Some(v) = args.knobs.calibration_error_mm {
        o.errors.calibration_error_mm = v;
    }
    if let Some(v) = args.knobs.calibration_error_deg {
        o.errors.calibration_error_deg = v;
    }
    if let Some(v) = args.knobs.tremor_mm {
        o.motion.tremor_mm = v;
    }
    if let Some(v) = args.knobs.object_motion_mm {
        o.motion.object_motion_mm = v;
    }
    if let Some(v) = args.truth_resolution {
        o.truth_resolution_mm = v;
    }
    o.compress = !args.uncompressed;
    if args.no_errors {
        o = o.without_errors();
    }
    o
}

/// The files of `names` in `--out`, each as an output to check before the work.
fn planned_outputs(args: &Args, names: &SimulationNames) -> Vec<super::outputs::Output> {
    let dir = &args.out;
    let mut outputs = vec![
        output("--out (sequence)", &names.sequence(dir), Holds::MetaImage),
        output(
            "--out (calibration)",
            &names.calibration(dir),
            Holds::AnyName,
        ),
        output("--out (truth)", &names.truth(dir), Holds::Mesh),
        output(
            "--out (description)",
            &names.description(dir),
            Holds::AnyName,
        ),
    ];
    outputs.extend(
        args.preview
            .as_deref()
            .map(|p| output("--preview", p, Holds::Png)),
    );
    outputs
}

pub fn run(args: Args) -> anyhow::Result<()> {
    if args.name.is_empty() || args.name.contains(['/', '\\']) || args.name.starts_with('.') {
        anyhow::bail!(
            "--name {:?}: give a plain file name (no folder, not hidden)",
            args.name
        );
    }
    let names = if args.name == DEFAULT_NAME {
        SimulationNames::plain(&args.name)
    } else {
        SimulationNames::prefixed(&args.name)
    };
    let options = options_from(&args);
    let inputs: Vec<PathBuf> = match &options.phantom {
        PhantomKind::Mesh(path) => vec![path.clone()],
        _ => Vec::new(),
    };
    if args.out.is_dir() {
        check_outputs(&inputs, &planned_outputs(&args, &names))?;
    } else if args.out.exists() {
        anyhow::bail!(
            "--out {}: that is not a folder (simulate writes several files into one)",
            args.out.display()
        );
    } else if let Some(path) = &args.preview {
        // The folder is created later; the preview may go elsewhere and is checked now.
        check_outputs(&inputs, &[output("--preview", path, Holds::Png)])?;
    }
    let work = || -> anyhow::Result<()> {
        let progress = crate::progress::BarProgress::new();
        let sim = simulate(&options, &progress)?;
        let files = write_simulation_as(&args.out, &names, &sim, &options, args.space.space)?;
        outln!(
            "simulated {} frames in {} sweeps of the {} phantom",
            sim.sequence.frames.len(),
            sim.sweeps.len(),
            options.phantom.name()
        );
        outln!(
            "levels: background {:.1}, boundary {:.1}, suggested iso-level {:.1}",
            sim.background_level,
            sim.boundary_level,
            sim.suggested_iso
        );
        outln!("sequence:    {}", files.sequence.display());
        outln!("calibration: {}", files.calibration.display());
        for t in &files.truth {
            outln!("truth:       {}", t.display());
        }
        outln!("description: {}", files.description.display());
        if let Some(path) = &args.preview {
            write_preview(path, &sim, 12)?;
            outln!("preview:     {}", path.display());
        }
        Ok(())
    };
    match args.threads {
        Some(n) => rayon::ThreadPoolBuilder::new()
            .num_threads(n.max(1))
            .build()
            .context("creating the thread pool")?
            .install(work),
        None => work(),
    }
}
