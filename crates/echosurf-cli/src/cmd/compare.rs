//! `echosurf compare`: score a mesh against a ground-truth mesh.

use std::path::PathBuf;

use anyhow::Context;
use echosurf::mesh::MeshTopology;
use echosurf::metrics::{CompareOptions, Comparison, SurfaceDistances, compare_meshes};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The mesh to score (.ply, .stl or .obj).
    pub mesh: PathBuf,
    /// The ground-truth mesh (.ply, .stl or .obj).
    pub truth: PathBuf,
    /// Print one JSON object instead of the table.
    #[arg(long)]
    pub json: bool,
    /// Area samples per mm^2 on each surface.
    #[arg(long, default_value_t = CompareOptions::default().samples_per_mm2)]
    pub samples_per_mm2: f64,
    /// Upper bound on samples per surface.
    #[arg(long, default_value_t = CompareOptions::default().max_samples)]
    pub max_samples: usize,
    /// Seed of the sample placement.
    #[arg(long, default_value_t = CompareOptions::default().seed)]
    pub seed: u64,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let mesh = echosurf::io::read_mesh(&args.mesh)?;
    let truth = echosurf::io::read_mesh(&args.truth)?;
    let options = CompareOptions {
        samples_per_mm2: args.samples_per_mm2,
        max_samples: args.max_samples,
        seed: args.seed,
        ..CompareOptions::default()
    };
    let comparison = compare_meshes(&mesh, &truth, &options).with_context(|| {
        format!(
            "comparing {} with {}",
            args.mesh.display(),
            args.truth.display()
        )
    })?;
    if args.json {
        // One flat object: the comparison's fields plus the inputs and the derived topology verdicts.
        let mut value = serde_json::to_value(&comparison)?;
        let object = value
            .as_object_mut()
            .context("comparison serialises to an object")?;
        object.insert("mesh".into(), serde_json::json!(args.mesh));
        object.insert("truth".into(), serde_json::json!(args.truth));
        for (key, topo) in [
            ("mesh", &comparison.mesh_topology),
            ("truth", &comparison.truth_topology),
        ] {
            object.insert(
                format!("{key}_oriented_manifold"),
                topo.is_oriented_manifold().into(),
            );
            object.insert(
                format!("{key}_watertight"),
                topo.is_closed_manifold().into(),
            );
        }
        println!("{}", serde_json::to_string(&value)?);
    } else {
        print!("{}", table(&args, &comparison));
    }
    Ok(())
}

fn table(args: &Args, c: &Comparison) -> String {
    let mut out = format!(
        "mesh  {}\ntruth {}\n\n",
        args.mesh.display(),
        args.truth.display()
    );
    out.push_str(&format!(
        "{:<22} {:>9} {:>9} {:>9} {:>9} {:>9} {:>9}\n",
        "distance (mm)", "mean", "rms", "median", "p95", "max", "samples"
    ));
    let row = |name: &str, d: &SurfaceDistances| {
        format!(
            "{:<22} {:>9.4} {:>9.4} {:>9.4} {:>9.4} {:>9.4} {:>9}\n",
            name, d.mean_mm, d.rms_mm, d.median_mm, d.p95_mm, d.max_mm, d.samples
        )
    };
    out.push_str(&row("accuracy mesh->truth", &c.accuracy));
    out.push_str(&row("reverse truth->mesh", &c.reverse));
    out.push_str(&format!(
        "\ncompleteness (truth within 1 mm) {:.2} %\nsymmetric Hausdorff              {:.4} mm\n\
         area mesh / truth                {:.1} / {:.1} mm^2\n\n",
        100.0 * c.completeness_1mm,
        c.hausdorff_mm,
        c.mesh_area_mm2,
        c.truth_area_mm2
    ));
    out.push_str(&format!(
        "{:<22} {:>12} {:>12}\n",
        "topology", "mesh", "truth"
    ));
    let topo_row = |name: &str, f: &dyn Fn(&MeshTopology) -> String| {
        format!(
            "{:<22} {:>12} {:>12}\n",
            name,
            f(&c.mesh_topology),
            f(&c.truth_topology)
        )
    };
    let yes_no = |b: bool| if b { "yes" } else { "no" }.to_string();
    out.push_str(&topo_row("triangles", &|t| t.triangles.to_string()));
    out.push_str(&topo_row("components", &|t| t.components.to_string()));
    out.push_str(&topo_row("oriented manifold", &|t| {
        yes_no(t.is_oriented_manifold())
    }));
    out.push_str(&topo_row("watertight", &|t| yes_no(t.is_closed_manifold())));
    out.push_str(&topo_row("boundary edges", &|t| {
        t.boundary_edges.to_string()
    }));
    out.push_str(&topo_row("non-manifold edges", &|t| {
        t.nonmanifold_edges.to_string()
    }));
    out.push_str(&topo_row("non-manifold vertices", &|t| {
        t.nonmanifold_vertices.to_string()
    }));
    out.push_str(&topo_row("misoriented edges", &|t| {
        t.misoriented_edges.to_string()
    }));
    out.push_str(&topo_row("degenerate triangles", &|t| {
        t.degenerate_triangles.to_string()
    }));
    out.push_str(&topo_row("Euler characteristic", &|t| {
        t.euler_characteristic.to_string()
    }));
    out
}
