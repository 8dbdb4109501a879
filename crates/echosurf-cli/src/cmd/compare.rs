//! `echosurf compare`: score a mesh against a ground-truth mesh.

use std::path::PathBuf;

use anyhow::Context;
use echosurf::io;
use echosurf::mesh::MeshTopology;
use echosurf::metrics::{CompareOptions, Comparison, SurfaceDistances, compare_meshes};
use echosurf_bench::{FacingSide, SweptFacingScore, SweptFacingTruth};

use super::outputs::{Holds, Output, check_outputs, output};

/// Which side of a wall counts as facing the beam.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum FacingArg {
    /// Either side of the wall.
    Either,
    /// The side facing the probe (the truth's outward normal against the beam).
    Probe,
}

impl From<FacingArg> for FacingSide {
    fn from(f: FacingArg) -> Self {
        match f {
            FacingArg::Either => FacingSide::Either,
            FacingArg::Probe => FacingSide::Probe,
        }
    }
}

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The mesh to score (.ply, .stl, .obj or .vtk; one tagged SPACE=LPS is read into RAS).
    pub mesh: PathBuf,
    /// The ground-truth mesh (.ply, .stl, .obj or .vtk).
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
    /// Also score the truth this tracked sequence swept and that faces its beam: completeness within
    /// 1 mm and the mesh's pieces per echoing patch. The truth must be in the sequence's world frame
    /// (as `extract` writes meshes); the recorded poses stand for where the frames were.
    #[arg(long)]
    pub sequence: Option<PathBuf>,
    /// PLUS device-set XML of the sequence (Image->Probe calibration, clip rectangle).
    #[arg(long, requires = "sequence")]
    pub calibration: Option<PathBuf>,
    /// World frame of the sequence's poses, as in `extract`: auto, tracker or reference.
    #[arg(long, requires = "sequence", default_value = "auto")]
    pub world: String,
    /// With --sequence: largest angle between the truth's normal and a sweeping frame's beam (degrees).
    #[arg(long, requires = "sequence", default_value_t = 30.0)]
    pub facing_deg: f64,
    /// With --sequence: which side of a wall must face the beam.
    #[arg(long, requires = "sequence", value_enum, default_value = "either")]
    pub facing: FacingArg,
    /// Write the mesh as a PLY error map: each vertex carries `distance_mm` to the truth and a colour,
    /// blue at 0 through green and yellow to red at --map-scale-mm and beyond.
    #[arg(long, value_name = "PLY")]
    pub error_map: Option<PathBuf>,
    /// Write the truth as a PLY map of what the mesh misses: each truth vertex's `distance_mm` to the
    /// mesh, coloured as --error-map.
    #[arg(long, value_name = "PLY")]
    pub miss_map: Option<PathBuf>,
    /// With --sequence: write the truth it swept facing its beam (the part that score counts) as a PLY
    /// map of what the mesh misses, as --miss-map.
    #[arg(long, value_name = "PLY", requires = "sequence")]
    pub swept_miss_map: Option<PathBuf>,
    /// Distance (mm) shown red on the maps.
    #[arg(long, default_value_t = 1.0)]
    pub map_scale_mm: f64,
    /// Refuse up front when the area samples would need more than this many MB (default: half the
    /// machine's memory).
    #[arg(long)]
    pub memory_budget: Option<f64>,
    /// Coordinates of the maps written.
    #[command(flatten)]
    pub space: super::space::SpaceArg,
}

/// Writes `mesh` coloured by each vertex's distance to `to` (see `Args::error_map`).
fn write_distance_map(
    path: &std::path::Path,
    mesh: &echosurf::mesh::Mesh,
    to: &echosurf::mesh::Mesh,
    scale_mm: f64,
    space: io::Space,
) -> anyhow::Result<String> {
    let (distances, colours) = echosurf::metrics::vertex_distance_map(mesh, to, scale_mm);
    let values: Vec<f32> = distances.iter().map(|&d| d as f32).collect();
    io::write_ply_with_vertex_values(path, mesh, "distance_mm", &values, &colours, space)?;
    Ok(format!(
        "{}: {} vertices coloured by distance_mm, blue 0 mm to red {scale_mm} mm and beyond",
        path.display(),
        mesh.vertices.len()
    ))
}

pub fn run(args: Args) -> anyhow::Result<()> {
    if !(args.map_scale_mm.is_finite() && args.map_scale_mm > 0.0) {
        anyhow::bail!(
            "--map-scale-mm must be a positive distance, got {}",
            args.map_scale_mm
        );
    }
    let maps: Vec<Output> = [
        ("--error-map", &args.error_map),
        ("--miss-map", &args.miss_map),
        ("--swept-miss-map", &args.swept_miss_map),
    ]
    .into_iter()
    .filter_map(|(option, path)| {
        path.as_deref()
            .map(|p| output(option, p, Holds::ColouredMesh))
    })
    .collect();
    if !maps.is_empty() {
        let mut inputs = vec![args.mesh.clone(), args.truth.clone()];
        if let Some(sequence) = &args.sequence {
            inputs.extend(io::sequence_files(sequence));
        }
        inputs.extend(args.calibration.iter().cloned());
        check_outputs(&inputs, &maps)?;
    }
    let (mesh, mesh_tag) = echosurf::io::read_mesh_and_space(&args.mesh)?;
    let (truth, truth_tag) = echosurf::io::read_mesh_and_space(&args.truth)?;
    let options = CompareOptions {
        samples_per_mm2: args.samples_per_mm2,
        max_samples: args.max_samples,
        seed: args.seed,
        ..CompareOptions::default()
    };
    let budget = super::extract::memory_budget_bytes(args.memory_budget)?;
    echosurf::budget::check_compare_budget(
        &mesh,
        &truth,
        &options,
        budget,
        &crate::memory::StageMemory,
    )
    .with_context(|| {
        format!(
            "comparing {} with {}",
            args.mesh.display(),
            args.truth.display()
        )
    })?;
    let comparison = compare_meshes(&mesh, &truth, &options).with_context(|| {
        format!(
            "comparing {} with {}",
            args.mesh.display(),
            args.truth.display()
        )
    })?;
    // The frame the meshes are in, when a sequence says it (else the frame of whatever made them).
    let mut swept_frame = None;
    let mut swept_truth = None;
    let swept = match &args.sequence {
        None => None,
        Some(path) => {
            let (sequence, calibration, poses) =
                super::extract::posed_sequence(path, args.calibration.as_deref(), &args.world)?;
            swept_frame = Some(poses.world_frame.clone());
            let image_to_world: Vec<_> = poses.poses.iter().map(|p| p.image_to_world).collect();
            let score = SweptFacingTruth::new(
                &truth,
                &image_to_world,
                sequence.width,
                sequence.height,
                calibration.as_ref().and_then(|c| c.clip),
                args.facing.into(),
                args.facing_deg,
            )
            .and_then(|swept| {
                if args.swept_miss_map.is_some() {
                    swept_truth = Some(swept.selected(&truth));
                }
                swept.score(&mesh, &truth, &options)
            })
            .with_context(|| format!("scoring the truth swept by {}", path.display()))?;
            Some(score)
        }
    };
    if args.json {
        // One flat object: the comparison's fields plus the inputs and the derived topology verdicts.
        let mut value = serde_json::to_value(&comparison)?;
        let object = value
            .as_object_mut()
            .context("comparison serialises to an object")?;
        object.insert("mesh".into(), serde_json::json!(args.mesh));
        object.insert("truth".into(), serde_json::json!(args.truth));
        // The tags found (null: untagged, read as RAS); both are compared in working RAS coordinates.
        object.insert(
            "coordinates".into(),
            serde_json::json!({
                "frame": swept_frame,
                "space": args.space.space,
                "mesh_tag": mesh_tag,
                "truth_tag": truth_tag,
            }),
        );
        if let Some(score) = &swept {
            object.insert("sequence".into(), serde_json::json!(args.sequence));
            object.insert("swept_facing".into(), serde_json::to_value(score)?);
        }
        object.insert(
            "mesh_largest_piece_area_share".into(),
            echosurf_bench::largest_piece_area_share(&mesh).into(),
        );
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
        outln!("{}", serde_json::to_string(&value)?);
    } else {
        out!("{}", table(&args, &comparison, swept.as_ref()));
    }
    for (path, from, to) in [
        (&args.error_map, Some(&mesh), &truth),
        (&args.miss_map, Some(&truth), &mesh),
        (&args.swept_miss_map, swept_truth.as_ref(), &mesh),
    ] {
        if let (Some(path), Some(from)) = (path, from) {
            let line = write_distance_map(path, from, to, args.map_scale_mm, args.space.space)?;
            if args.json {
                eprintln!("{line}");
            } else {
                outln!("{line}");
            }
        }
    }
    Ok(())
}

fn table(args: &Args, c: &Comparison, swept: Option<&SweptFacingScore>) -> String {
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
         area mesh / truth                {:.1} / {:.1} mm^2\n\
         walls of the truth (components)  {}: {} mesh edges across walls, {} pieces on several walls\n\n",
        100.0 * c.completeness_1mm,
        c.hausdorff_mm,
        c.mesh_area_mm2,
        c.truth_area_mm2,
        c.walls.truth_walls,
        c.walls.edges_across_walls,
        c.walls.pieces_on_several_walls
    ));
    if let Some(s) = swept {
        let p = &s.patch_coverage;
        out.push_str(&format!(
            "swept truth facing the beam within {} degrees ({} side; frames' planes within {:.2} mm)\n\
             truth area                       {:.1} mm^2\n\
             completeness (truth within 1 mm) {:.2} %\n\
             echoing patches                  {}: {} whole, {} split, {} missed \
             (pieces of the mesh per patch)\n\n",
            s.max_angle_deg,
            match s.side {
                FacingSide::Either => "either",
                FacingSide::Probe => "probe",
            },
            s.plane_distance_mm,
            s.truth_area_mm2,
            100.0 * s.completeness_1mm,
            s.truth_patches,
            p.whole,
            p.split,
            p.missed
        ));
        // Where a patch is not whole, which pieces lie over it (pieces numbered by first triangle).
        let mut listed = false;
        for (k, d) in s.patches.iter().enumerate() {
            let verdict = match d.counted_pieces {
                0 => "missed",
                1 => continue,
                _ => "split",
            };
            let [x, y, z] = d.centroid_mm;
            let pieces: Vec<String> = d
                .pieces
                .iter()
                .map(|(piece, area)| format!("piece {piece} ({area:.1} mm^2)"))
                .collect();
            let cover = if pieces.is_empty() {
                "no piece within 1 mm".to_string()
            } else {
                format!(
                    "covered by {}; {:.1} mm^2 farther than 1 mm",
                    pieces.join(", "),
                    d.missed_mm2
                )
            };
            out.push_str(&format!(
                "  patch {k} {verdict}: {:.1} mm^2 at ({x:.1}, {y:.1}, {z:.1}); {cover}\n",
                d.area_mm2
            ));
            listed = true;
        }
        if listed {
            out.push('\n');
        }
    }
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
