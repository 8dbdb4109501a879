//! `echosurf render`: a shaded PNG preview of a mesh from four viewpoints.

use std::path::PathBuf;

use echosurf::render::{Projection, RenderOptions, render_views, write_png};

use super::outputs::{Holds, check_outputs, output};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The mesh to draw (.ply, .stl or .obj).
    pub mesh: PathBuf,
    /// The PNG to write.
    #[arg(long)]
    pub out: PathBuf,
    /// Picture width in pixels (2 x 2 grid of square views: front, side, top, oblique).
    #[arg(long, default_value_t = 800)]
    pub size: u32,
    /// A second mesh drawn translucently over the first (e.g. the ground truth).
    #[arg(long)]
    pub ghost: Option<PathBuf>,
    /// Orthographic instead of perspective projection.
    #[arg(long)]
    pub orthographic: bool,
    /// Colour the mesh by each vertex's distance to this mesh (e.g. the ground truth): an error map,
    /// blue at 0 through green and yellow to red at --scale-mm and beyond.
    #[arg(long, value_name = "MESH")]
    pub distance_to: Option<PathBuf>,
    /// With --distance-to: the distance (mm) shown red.
    #[arg(long, requires = "distance_to", default_value_t = 1.0)]
    pub scale_mm: f64,
    /// Draw in the plain mesh colour even when the PLY gives its vertices colours (`red green blue`,
    /// as `compare --error-map` writes them), which are drawn otherwise.
    #[arg(long, conflicts_with = "distance_to")]
    pub plain: bool,
    /// Draw the outlines of this tracked sequence's frames over the mesh (every --outline-every-th
    /// frame), where its poses put them: the mesh must be in the sequence's world frame, as `extract`
    /// writes it.
    #[arg(long)]
    pub sequence: Option<PathBuf>,
    /// PLUS device-set XML of the sequence (Image->Probe calibration, clip rectangle).
    #[arg(long, requires = "sequence")]
    pub calibration: Option<PathBuf>,
    /// World frame of the sequence's poses, as in `extract`: auto, tracker or reference.
    #[arg(long, requires = "sequence", default_value = "auto")]
    pub world: String,
    /// With --sequence: outline every this-many-th frame.
    #[arg(long, requires = "sequence", default_value_t = super::extract::PREVIEW_OUTLINE_EVERY)]
    pub outline_every: usize,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let mut inputs = vec![args.mesh.clone()];
    inputs.extend(args.ghost.iter().cloned());
    inputs.extend(args.distance_to.iter().cloned());
    if let Some(sequence) = &args.sequence {
        inputs.extend(echosurf::io::sequence_files(sequence));
    }
    inputs.extend(args.calibration.iter().cloned());
    check_outputs(&inputs, &[output("--out", &args.out, Holds::Png)])?;
    if args.outline_every == 0 {
        anyhow::bail!("--outline-every must be at least 1");
    }
    if !(args.scale_mm.is_finite() && args.scale_mm > 0.0) {
        anyhow::bail!(
            "--scale-mm must be a positive distance, got {}",
            args.scale_mm
        );
    }
    let mesh = echosurf::io::read_mesh(&args.mesh)?;
    let own_colours = if args.plain || args.distance_to.is_some() {
        None
    } else {
        echosurf::io::read_vertex_colours(&args.mesh)?
    };
    let from_file = own_colours.is_some();
    let vertex_colours = match &args.distance_to {
        Some(path) => {
            let to = echosurf::io::read_mesh(path)?;
            Some(echosurf::metrics::vertex_distance_map(&mesh, &to, args.scale_mm).1)
        }
        None => own_colours,
    };
    let ghost = match &args.ghost {
        Some(path) => Some(echosurf::io::read_mesh(path)?),
        None => None,
    };
    let overlay_lines = match &args.sequence {
        Some(path) => {
            let (sequence, calibration, poses) =
                super::extract::posed_sequence(path, args.calibration.as_deref(), &args.world)?;
            let outlines =
                echosurf::pipeline::frame_outlines(&sequence, &poses, calibration.as_ref());
            super::extract::every_nth_outline(&outlines, args.outline_every)
        }
        None => Vec::new(),
    };
    let defaults = RenderOptions::default();
    let options = RenderOptions {
        size_px: args.size,
        ghost,
        projection: if args.orthographic {
            Projection::Orthographic
        } else {
            defaults.projection
        },
        colour_bar: args
            .distance_to
            .as_ref()
            .map(|_| echosurf::render::distance_colour_bar(args.scale_mm)),
        vertex_colours,
        overlay_lines,
        ..defaults
    };
    let image = render_views(&mesh, &options)?;
    write_png(&args.out, &image)?;
    outln!(
        "{} ({} x {} px, {} triangles)",
        args.out.display(),
        image.width,
        image.height,
        mesh.triangles.len()
    );
    if from_file {
        outln!("drawn in the colours the file gives its vertices (--plain ignores them)");
    }
    if let Some(path) = &args.distance_to {
        outln!(
            "coloured by distance to {}: blue 0 mm to red {} mm and beyond",
            path.display(),
            args.scale_mm
        );
    }
    Ok(())
}
