//! `echosurf fit` then `echosurf eval` on a small point cloud: the model reproduces the samples and the
//! output carries value and gradient properties.

use std::process::Command;

use echosurf::io::{PointCloud, read_point_cloud, write_point_cloud};
use glam::DVec3;

#[test]
fn fit_then_eval_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    let points_path = dir.path().join("points.ply");
    let model_path = dir.path().join("model.esrbf");
    let out_path = dir.path().join("values.ply");
    // A linear field plus a bump on a jittered grid; w = 0 interpolates.
    let positions: Vec<DVec3> = (0..400)
        .map(|i| {
            let (a, b, c) = (i % 8, (i / 8) % 10, i / 80);
            DVec3::new(
                a as f64 * 1.1,
                b as f64 * 0.9 + 0.05 * a as f64,
                c as f64 * 1.3,
            )
        })
        .collect();
    let intensity: Vec<f32> = positions
        .iter()
        .map(|p| {
            (20.0 + 3.0 * p.x - p.z
                + 40.0 * (-(*p - DVec3::splat(4.0)).length_squared() / 8.0).exp())
                as f32
        })
        .collect();
    write_point_cloud(
        &points_path,
        &PointCloud {
            positions: positions.clone(),
            scalars: vec![("intensity".into(), intensity.clone())],
        },
    )
    .unwrap();
    let exe = env!("CARGO_BIN_EXE_echosurf");
    let fit = Command::new(exe)
        .args([
            "fit",
            points_path.to_str().unwrap(),
            "--out",
            model_path.to_str().unwrap(),
        ])
        .args(["--smoothing", "0", "--accuracy", "0.01", "--json"])
        .output()
        .unwrap();
    assert!(
        fit.status.success(),
        "{}",
        String::from_utf8_lossy(&fit.stderr)
    );
    let report: serde_json::Value = serde_json::from_slice(&fit.stdout).unwrap();
    assert_eq!(report["centres"], 400);
    // `--solver` picks the method; the report names the one used.
    for (choice, name) in [
        ("fast", "Fast"),
        ("pu", "PartitionOfUnity"),
        ("direct", "Direct"),
    ] {
        let other = Command::new(exe)
            .args(["fit", points_path.to_str().unwrap(), "--out"])
            .arg(dir.path().join(format!("{choice}.esrbf")))
            .args([
                "--smoothing",
                "0",
                "--accuracy",
                "0.01",
                "--json",
                "--solver",
                choice,
            ])
            .output()
            .unwrap();
        assert!(
            other.status.success(),
            "{choice}: {}",
            String::from_utf8_lossy(&other.stderr)
        );
        let r: serde_json::Value = serde_json::from_slice(&other.stdout).unwrap();
        assert_eq!(r["solver"], name, "{r}");
        assert!(
            r["max_residual"].as_f64().unwrap() <= 0.01 + 1e-9,
            "{choice}: {r}"
        );
    }
    let bogus = Command::new(exe)
        .args(["fit", points_path.to_str().unwrap(), "--out"])
        .arg(dir.path().join("bogus.esrbf"))
        .args(["--solver", "magic"])
        .output()
        .unwrap();
    assert!(!bogus.status.success());
    assert!(String::from_utf8_lossy(&bogus.stderr).contains("--solver magic"));
    assert!(!dir.path().join("bogus.esrbf").exists());
    let eval = Command::new(exe)
        .args([
            "eval",
            model_path.to_str().unwrap(),
            points_path.to_str().unwrap(),
        ])
        .args(["--out", out_path.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(
        eval.status.success(),
        "{}",
        String::from_utf8_lossy(&eval.stderr)
    );
    let out = read_point_cloud(&out_path).unwrap();
    let values = out.scalar("value").unwrap();
    // f32 storage of values near 100: 1e-3 covers rounding; the fit itself is exact to 1e-6.
    for (v, f) in values.iter().zip(&intensity) {
        assert!((v - f).abs() < 1e-3, "{v} vs {f}");
    }
    for name in ["gx", "gy", "gz", "intensity"] {
        assert_eq!(out.scalar(name).unwrap().len(), 400, "{name}");
    }

    // A cloud without intensities and a missing model are reported, not panics.
    write_point_cloud(
        &points_path,
        &PointCloud {
            positions,
            scalars: vec![],
        },
    )
    .unwrap();
    let bad = Command::new(exe)
        .args([
            "fit",
            points_path.to_str().unwrap(),
            "--out",
            model_path.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("intensity"));
    let missing = Command::new(exe)
        .args([
            "eval",
            "/nonexistent/m.esrbf",
            out_path.to_str().unwrap(),
            "--out",
        ])
        .arg(dir.path().join("x.ply"))
        .output()
        .unwrap();
    assert!(!missing.status.success());
}
