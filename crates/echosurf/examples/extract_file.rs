//! Extracts the surface of one tracked PLUS sweep, as `echosurf extract` does with its defaults, and
//! writes it as a PLY mesh (in the sweep's own coordinates, tagged `SPACE=RAS`):
//! `cargo run --release -p echosurf --example extract_file -- SEQUENCE.igs.mha CALIBRATION.xml OUT.ply`

use std::path::{Path, PathBuf};

use echosurf::io::{self, Space};
use echosurf::mesh::Mesh;
use echosurf::pipeline::{self, ExtractOptions};
use echosurf::progress::NoProgress;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<PathBuf> = std::env::args_os().skip(1).map(PathBuf::from).collect();
    let [sequence_path, calibration_path, out_path] = args.as_slice() else {
        return Err("usage: extract_file SEQUENCE.igs.mha CALIBRATION.xml OUT.ply".into());
    };
    refuse_overwriting_an_input(out_path, &[sequence_path, calibration_path])?;

    let sequence = io::read_sequence(sequence_path)?;
    let calibration = io::read_calibration(calibration_path)?;
    let output = pipeline::extract(
        &sequence,
        Some(&calibration),
        &ExtractOptions::default(),
        &NoProgress,
    )?;

    // `--iso auto` (the default) gives one level; with several levels the CLI writes one file each.
    let mesh = Mesh::merged(output.surfaces.iter().map(|s| &s.mesh));
    io::write_mesh_in(out_path, &mesh, Space::Ras)?;

    let levels: Vec<String> = output
        .surfaces
        .iter()
        .map(|s| format!("{:.1}", s.level))
        .collect();
    let topology = mesh.topology();
    println!(
        "{}: iso {} ({} frame), {} triangles in {} pieces, {:.2} s",
        out_path.display(),
        levels.join(", "),
        output.report.parameters.world_frame,
        topology.triangles,
        topology.components,
        output.report.total_seconds
    );
    for warning in &output.report.warnings {
        eprintln!("warning: {warning}");
    }
    Ok(())
}

/// The output must not be one of the inputs (the library's writer replaces files atomically, so a
/// wrong argument order would silently replace the recording).
fn refuse_overwriting_an_input(out: &Path, inputs: &[&PathBuf]) -> Result<(), String> {
    let Ok(out_resolved) = out.canonicalize() else {
        return Ok(()); // does not exist yet
    };
    for input in inputs {
        if input.canonicalize().ok().as_deref() == Some(out_resolved.as_path()) {
            return Err(format!(
                "{}: the output would replace an input",
                out.display()
            ));
        }
    }
    Ok(())
}
