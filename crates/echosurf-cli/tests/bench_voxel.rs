//! `extract --method voxel` against a simulated sphere's truth, and `bench --quick` writing its files.

use std::path::Path;
use std::process::Command;

use echosurf::metrics::{CompareOptions, compare_meshes};

mod common;
use common::echosurf_ok as echosurf;

fn simulate_sphere(dir: &Path) {
    echosurf(&[
        "simulate",
        "--phantom",
        "sphere",
        "--seed",
        "3",
        "--frames-per-sweep",
        "30",
        "--width",
        "80",
        "--height",
        "80",
        "--pixel-size",
        "0.4",
        "--truth-resolution",
        "1.0",
        "--out",
        dir.to_str().unwrap(),
    ]);
}

#[test]
fn extract_voxel_route_finds_the_sphere() {
    let dir = tempfile::tempdir().unwrap();
    let sim = dir.path().join("sim");
    simulate_sphere(&sim);
    let (seq, config) = (sim.join("sim.mha"), sim.join("sim_config.xml"));
    let mesh_path = dir.path().join("voxel.ply");
    let report_path = dir.path().join("report.json");
    // Iso 30: between the compounded-and-smoothed water (~16) and boundary levels of this sweep, above
    // most speckle of the sphere's interior.
    echosurf(&[
        "extract",
        seq.to_str().unwrap(),
        "--calibration",
        config.to_str().unwrap(),
        "--method",
        "voxel",
        "--iso",
        "30",
        "--out",
        mesh_path.to_str().unwrap(),
        "--report",
        report_path.to_str().unwrap(),
    ]);
    let mesh = echosurf::io::read_mesh(&mesh_path).unwrap();
    let truth = echosurf::io::read_mesh(&sim.join("truth.ply")).unwrap();
    let c = compare_meshes(&mesh, &truth, &CompareOptions::default()).unwrap();
    // Loose: the voxel route sees the swept caps of the sphere within about two voxels (0.5 mm each)
    // plus the 1 mm smoothing; a misplaced grid or flipped pose would be off by many mm.
    assert!(c.accuracy.mean_mm < 1.5, "{:?}", c.accuracy);
    assert!(c.accuracy.p95_mm < 3.0, "{:?}", c.accuracy);
    assert!(c.mesh_area_mm2 > 50.0, "{}", c.mesh_area_mm2);
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&report_path).unwrap()).unwrap();
    assert_eq!(report["method"], "voxel");
    assert!(report["fit"].is_null());
    assert_eq!(report["voxel"]["spacing_mm"][0], 0.5);
    assert_eq!(report["voxel"]["smoothing_sigma_mm"], 1.0);
    let stages: Vec<&str> = report["stages"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["stage"].as_str().unwrap())
        .collect();
    assert_eq!(stages, ["poses", "reconstruct", "smooth", "surface"]);

    // --iso auto picks a level from the volume itself and still yields a surface.
    let auto_path = dir.path().join("auto.ply");
    echosurf(&[
        "extract",
        seq.to_str().unwrap(),
        "--calibration",
        config.to_str().unwrap(),
        "--method",
        "voxel",
        "--out",
        auto_path.to_str().unwrap(),
    ]);
    assert!(!echosurf::io::read_mesh(&auto_path).unwrap().is_empty());

    // A bad method is an error, not a panic.
    let bad = Command::new(env!("CARGO_BIN_EXE_echosurf"))
        .args(["extract", seq.to_str().unwrap(), "--calibration"])
        .arg(&config)
        .args(["--method", "splat", "--out"])
        .arg(dir.path().join("x.ply"))
        .output()
        .unwrap();
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("expected rbf or voxel"));
}

#[test]
fn bench_quick_writes_table_json_and_plots() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("bench");
    let run = echosurf(&[
        "bench",
        "--quick",
        "--phantoms",
        "sphere",
        "--noise",
        "default",
        "--max-samples",
        "500",
        "--fit-max",
        "1000",
        "--out",
        out.to_str().unwrap(),
    ]);
    let stdout = String::from_utf8_lossy(&run.stdout);
    let table = std::fs::read_to_string(out.join("table.md")).unwrap();
    assert_eq!(stdout, table);
    // Header, rule, one row per route; then the fit-scaling table with one row (1000 samples).
    for route in ["rbf", "rbf-ridge", "voxel"] {
        assert!(
            table.contains(&format!("| sphere / default | {route} |")),
            "{table}"
        );
    }
    assert!(table.contains("\n| synthetic | 1000 |"), "{table}");
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("bench.json")).unwrap()).unwrap();
    let routes = json["routes"].as_array().unwrap();
    assert_eq!(routes.len(), 3);
    for r in routes {
        assert!(r["seconds"].as_f64().unwrap() > 0.0);
        // Both completeness scores are shares; the sphere's cap faces the beam, so the strong-echo
        // mask is not empty.
        for key in ["completeness_1mm", "completeness_strong_echo_1mm"] {
            let c = r[key].as_f64().unwrap_or(f64::NAN);
            assert!((0.0..=1.0).contains(&c), "{key} {r}");
        }
        // The sphere's top cap faces the probe: one patch, scored for every route that drew a surface.
        let probe = &r["probe_facing"];
        assert_eq!(probe["side"], "probe", "{r}");
        assert_eq!(probe["max_angle_deg"], 20.0, "{r}");
        assert!(probe["truth_patches"].as_u64().unwrap() >= 1, "{r}");
        let c = probe["completeness_1mm"].as_f64().unwrap();
        assert!((0.0..=1.0).contains(&c), "{r}");
    }
    assert!(table.contains("completeness, <= 30 deg"), "{table}");
    assert!(table.contains("probe side <= 20 deg"), "{table}");
    for svg in ["accuracy_vs_time.svg", "fit_scaling.svg"] {
        let text = std::fs::read_to_string(out.join(svg)).unwrap();
        assert!(text.starts_with("<svg"), "{svg}");
        assert!(text.trim_end().ends_with("</svg>"), "{svg}");
    }
}

#[test]
fn bench_fit_runs_only_the_fit_scaling() {
    let dir = tempfile::tempdir().unwrap();
    let sim = dir.path().join("sim");
    simulate_sphere(&sim);
    let band = format!(
        "{},{}",
        sim.join("sim.mha").display(),
        sim.join("sim_config.xml").display()
    );
    let out = dir.path().join("fit");
    let run = echosurf(&[
        "bench",
        "fit",
        "--fit-max",
        "1000",
        "--solver",
        "fast",
        "--fit-band",
        &band,
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let table = std::fs::read_to_string(out.join("table.md")).unwrap();
    assert!(table.starts_with("| samples from | samples |"), "{table}");
    assert!(
        table.contains("\n| synthetic | 1000 |")
            && table.contains("\n| sim.mha | 1000 |")
            && !table.contains("| case |"),
        "{table}"
    );
    assert!(out.join("fit_scaling.svg").exists());
    assert!(!out.join("accuracy_vs_time.svg").exists());
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("bench.json")).unwrap()).unwrap();
    assert_eq!(json["routes"].as_array().unwrap().len(), 0);
    let rows = json["fit_scaling"].as_array().unwrap();
    assert_eq!(rows.len(), 2, "{json}");
    for row in rows {
        assert_eq!(row["solver"], "Fast", "{json}");
        assert_eq!(row["samples"], 1000, "{json}");
        // The fit's default accuracy (2 grey) holds on the sweep's band pixels too.
        assert!(row["max_residual"].as_f64().unwrap() <= 2.0, "{row}");
    }
    assert_eq!(rows[1]["samples_from"], "sim.mha");
    let bad = Command::new(env!("CARGO_BIN_EXE_echosurf"))
        .args(["bench", "everything"])
        .output()
        .unwrap();
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("expected all, routes or fit"));
    let bad_band = Command::new(env!("CARGO_BIN_EXE_echosurf"))
        .args([
            "bench",
            "fit",
            "--fit-max",
            "1000",
            "--fit-band",
            "only.mha",
        ])
        .output()
        .unwrap();
    assert!(!bad_band.status.success());
    assert!(
        String::from_utf8_lossy(&bad_band.stderr).contains("expected SEQUENCE,CONFIG"),
        "{}",
        String::from_utf8_lossy(&bad_band.stderr)
    );
}
