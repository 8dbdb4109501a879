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
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let mut inputs = vec![args.mesh.clone()];
    inputs.extend(args.ghost.iter().cloned());
    check_outputs(&inputs, &[output("--out", &args.out, Holds::Png)])?;
    let mesh = echosurf::io::read_mesh(&args.mesh)?;
    let ghost = match &args.ghost {
        Some(path) => Some(echosurf::io::read_mesh(path)?),
        None => None,
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
        ..defaults
    };
    let image = render_views(&mesh, &options)?;
    write_png(&args.out, &image)?;
    println!(
        "{} ({} x {} px, {} triangles)",
        args.out.display(),
        image.width,
        image.height,
        mesh.triangles.len()
    );
    Ok(())
}
