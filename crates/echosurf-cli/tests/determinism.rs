//! Same input, parameters and seed give byte-identical outputs whatever the thread count: `simulate` and
//! `extract` (mesh, model, samples) with RAYON_NUM_THREADS=1 and 2.

use std::path::Path;
use std::process::Command;

const BIN: &str = env!("CARGO_BIN_EXE_echosurf");

fn run(args: &[&str], dir: &Path, threads: &str) {
    let out = Command::new(BIN)
        .args(args)
        .current_dir(dir)
        .env("RAYON_NUM_THREADS", threads)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "echosurf {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

fn outputs_with(threads: &str, root: &Path) -> Vec<(String, Vec<u8>)> {
    let dir = root.join(format!("t{threads}"));
    std::fs::create_dir(&dir).unwrap();
    run(
        &[
            "simulate",
            "--phantom",
            "sphere",
            "--frames-per-sweep",
            "8",
            "--width",
            "64",
            "--height",
            "64",
            "--seed",
            "7",
            "--out",
            "sim",
        ],
        &dir,
        threads,
    );
    let extract = [
        "extract",
        "sim/sim.mha",
        "--calibration",
        "sim/sim_config.xml",
        "--max-samples",
        "1500",
        "--seed",
        "3",
    ];
    // The model and samples are outputs of the option file (paths relative to the working folder).
    std::fs::write(
        dir.join("iso.toml"),
        "[outputs]\nmodel = \"model.esrbf\"\nsamples = \"samples.ply\"\n",
    )
    .unwrap();
    std::fs::write(
        dir.join("ridge.toml"),
        "[tuning.segment]\nbackward_pass = true\n",
    )
    .unwrap();
    let iso = [
        "--resolution",
        "2",
        "--out",
        "mesh.ply",
        "--config",
        "iso.toml",
    ];
    let ridge = [
        "--sheet",
        "ridge",
        "--config",
        "ridge.toml",
        "--out",
        "ridge.ply",
    ];
    run(&[&extract[..], &iso].concat(), &dir, threads);
    run(&[&extract[..], &ridge].concat(), &dir, threads);
    [
        "sim/sim.mha",
        "sim/truth.ply",
        "mesh.ply",
        "model.esrbf",
        "samples.ply",
        "ridge.ply",
    ]
    .iter()
    .map(|name| (name.to_string(), std::fs::read(dir.join(name)).unwrap()))
    .collect()
}

#[test]
fn outputs_do_not_depend_on_the_thread_count() {
    let root = tempfile::tempdir().unwrap();
    let one = outputs_with("1", root.path());
    let two = outputs_with("2", root.path());
    for ((name, a), (_, b)) in one.iter().zip(&two) {
        assert!(!a.is_empty(), "{name} is empty");
        let first_difference = a.iter().zip(b).position(|(x, y)| x != y);
        assert!(
            a == b,
            "{name} differs between 1 and 2 threads ({} vs {} bytes, first difference at byte {first_difference:?})",
            a.len(),
            b.len()
        );
    }
}
