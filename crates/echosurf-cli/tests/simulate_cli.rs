//! `echosurf simulate` end to end: files, preview, byte-identical reruns across thread counts.

use std::path::Path;
use std::process::Command;

fn run(out: &Path, threads: &str, extra: &[&str]) {
    let status = Command::new(env!("CARGO_BIN_EXE_echosurf"))
        .args([
            "simulate",
            "--phantom",
            "sphere",
            "--seed",
            "7",
            "--frames-per-sweep",
            "5",
        ])
        .args([
            "--sweeps",
            "2",
            "--width",
            "64",
            "--height",
            "64",
            "--pixel-size",
            "0.5",
        ])
        .args(["--truth-resolution", "1.5", "--threads", threads, "--out"])
        .arg(out)
        .args(extra)
        .status()
        .unwrap();
    assert!(status.success());
}

#[test]
fn simulate_writes_identical_files_for_the_same_seed() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = (dir.path().join("a"), dir.path().join("b"));
    let preview = dir.path().join("montage.png");
    run(&a, "1", &["--preview", preview.to_str().unwrap()]);
    run(&b, "2", &[]);
    for name in ["sim.mha", "sim_config.xml", "truth.ply", "phantom.json"] {
        let (x, y) = (
            std::fs::read(a.join(name)).unwrap(),
            std::fs::read(b.join(name)).unwrap(),
        );
        assert!(!x.is_empty(), "{name} empty");
        assert_eq!(x, y, "{name} differs between runs");
    }
    let png = std::fs::read(&preview).unwrap();
    assert_eq!(&png[1..4], b"PNG");
    // No leftovers of the atomic writes.
    for entry in std::fs::read_dir(&a).unwrap() {
        let name = entry.unwrap().file_name();
        assert!(!name.to_string_lossy().starts_with('.'), "{name:?}");
    }
}

#[test]
fn simulate_rejects_bad_parameters() {
    let dir = tempfile::tempdir().unwrap();
    let output = Command::new(env!("CARGO_BIN_EXE_echosurf"))
        .args(["simulate", "--pixel-size=-1", "--out"])
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(!output.status.success());
    assert!(String::from_utf8_lossy(&output.stderr).contains("pixel size"));
}

#[test]
fn simulate_bone_physics_writes_the_probe_side_truth_and_records_the_knobs() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("bone");
    let status = Command::new(env!("CARGO_BIN_EXE_echosurf"))
        .args(["simulate", "--phantom", "bone", "--frames-per-sweep", "3"])
        .args(["--width", "48", "--height", "48", "--pixel-size", "0.8"])
        .args(["--truth-resolution", "1.5", "--scatterer-density", "0.5"])
        .args(["--specular-exponent", "6", "--out"])
        .arg(&out)
        .status()
        .unwrap();
    assert!(status.success());
    let description: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("phantom.json")).unwrap()).unwrap();
    let acoustics = &description["options"]["acoustics"];
    assert_eq!(acoustics["scatterer_density"], 0.5);
    assert_eq!(acoustics["specular_exponent"], 6.0);
    assert_eq!(acoustics["depth_gain_compensation"], true);
    // The bone preset: bone's attenuation in the object, tissue around it.
    assert_eq!(acoustics["object"]["attenuation_db_per_cm_mhz"], 20.0);
    // The truth is the probe side only: an open sheet, every triangle facing up.
    let truth = echosurf::io::read_mesh(&out.join("truth.ply")).unwrap();
    assert!(!truth.triangles.is_empty());
    assert!(!truth.topology().is_closed_manifold());
    for t in &truth.triangles {
        let [a, b, c] = t.map(|i| truth.vertices[i as usize]);
        assert!((b - a).cross(c - a).z > 0.0);
    }
}

#[test]
fn simulate_rejects_a_bad_physics_knob() {
    let dir = tempfile::tempdir().unwrap();
    let output = Command::new(env!("CARGO_BIN_EXE_echosurf"))
        .args(["simulate", "--scatterer-density", "0", "--out"])
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(!output.status.success());
    assert!(String::from_utf8_lossy(&output.stderr).contains("scatterer_density"));
}
