//! `echosurf surface`: iso-surfaces of a saved RBF model, so one fit can be surfaced at several levels
//! and resolutions without refitting.

use std::path::PathBuf;

use anyhow::Context;
use echosurf::io;
use echosurf::pipeline::{IsoLevels, surface_domain};
use echosurf::rbf::RbfModel;
use echosurf::surface::{SurfaceOptions, extract_surfaces_with_stats};

use super::extract::{mesh_outputs, mesh_path, parse_iso};
use super::outputs::check_outputs;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Fitted model (.esrbf) from `echosurf fit` or `echosurf extract --model`.
    pub model: PathBuf,
    /// Iso-level(s), comma separated; one mesh each.
    #[arg(long)]
    pub iso: String,
    /// Output mesh (.ply, .stl, .obj or .vtk). With several levels, `_iso<LEVEL>` is added before the
    /// extension.
    #[arg(long)]
    pub out: PathBuf,
    #[command(flatten)]
    pub space: super::space::SpaceArg,
    /// Lattice spacing in mm.
    #[arg(long, default_value_t = 0.5)]
    pub resolution: f64,
    /// Region of trust: no surface farther than this (mm) from any centre of the model.
    #[arg(long, default_value_t = 3.0)]
    pub trust_distance: f64,
    /// Refuse before surfacing when it would need more than this many MB (default: half the
    /// machine's memory).
    #[arg(long)]
    pub memory_budget: Option<f64>,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let iso = parse_iso(&args.iso)?;
    let levels = match &iso {
        IsoLevels::Levels(v) if !v.is_empty() => v.clone(),
        _ => anyhow::bail!(
            "--iso: give the level(s) as numbers (a model carries no echo statistics)"
        ),
    };
    let outputs = mesh_outputs(&args.out, &iso);
    check_outputs(std::slice::from_ref(&args.model), &outputs)?;
    let model = RbfModel::load(&args.model)?;
    let centres = model.centres().to_vec();
    if centres.is_empty() {
        anyhow::bail!("{}: the model has no centres", args.model.display());
    }
    // The model's own values at its centres say where each level passes.
    let values = model.values(&centres);
    if let Some(bad) = values.iter().position(|v| !v.is_finite()) {
        anyhow::bail!(
            "{}: the model's value at its centre {bad} is {}: its coefficients are out of range",
            args.model.display(),
            values[bad]
        );
    }
    let (lo, hi) = values
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
    for &k in &levels {
        if !(k > lo && k < hi) {
            anyhow::bail!(
                "{}: --iso {k}: level {k} never crossed: it is outside the model's values at its \
                 centres, which span {lo:.1}..{hi:.1}, so there is no surface",
                args.model.display()
            );
        }
    }
    let domain = surface_domain(
        &centres,
        &values,
        &levels,
        0.1 * (hi - lo),
        args.trust_distance,
    );
    let budget = super::extract::memory_budget_bytes(args.memory_budget)?;
    echosurf::budget::check_surface_budget(
        domain.seeds.len() as u64,
        args.resolution,
        budget,
        &crate::memory::StageMemory,
    )
    .with_context(|| format!("surfacing {}", args.model.display()))?;
    let options = SurfaceOptions {
        resolution_mm: args.resolution,
        trust_distance_mm: args.trust_distance,
        ..SurfaceOptions::default()
    };
    let (meshes, stats) = extract_surfaces_with_stats(&model, &levels, &domain, &options)
        .with_context(|| format!("surfacing {}", args.model.display()))?;
    let several = levels.len() > 1;
    for (&k, mesh) in levels.iter().zip(&meshes) {
        let path = mesh_path(&args.out, k, several);
        io::write_mesh_in(&path, mesh, args.space.space)?;
        let t = mesh.topology();
        outln!(
            "iso {k}: {} triangles, {} component(s), {} boundary edges -> {}",
            mesh.triangles.len(),
            t.components,
            t.boundary_edges,
            path.display()
        );
    }
    for l in &stats.levels {
        outln!(
            "iso {}: vertices within {:.4} grey of the level at worst",
            l.level,
            l.max_level_error
        );
        if l.off_level_vertices > 0 {
            eprintln!(
                "warning: iso {}: {} of {} vertices are more than {} grey off the level (worst {:.2})",
                l.level,
                l.off_level_vertices,
                l.vertices,
                echosurf::surface::LEVEL_TOLERANCE,
                l.max_level_error
            );
        }
    }
    outln!(
        "{} field evaluations ({:.1} per triangle)",
        stats.value_evaluations + stats.gradient_evaluations,
        stats.evaluations_per_triangle()
    );
    Ok(())
}
