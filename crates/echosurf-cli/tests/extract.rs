//! `echosurf extract` end to end on a small simulated sphere sweep: the whole pipeline runs, writes a
//! manifold mesh near the true surface, a report and a preview; bad requests fail cleanly.

use std::path::{Path, PathBuf};
use std::process::Output;

mod common;
use common::echosurf;

/// `echosurf extract SEQ --calibration CONFIG --out OUT` followed by `extra`.
fn extract(seq: &Path, config: &Path, out: &Path, extra: &[&str]) -> Output {
    let mut args = vec![
        "extract",
        seq.to_str().unwrap(),
        "--calibration",
        config.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    echosurf(&args)
}

/// `echosurf compare MESH TRUTH --json`, which must succeed on an oriented manifold mesh.
/// `extract` of the ridge sheet from 10,000 samples with `extra`, which must succeed; returns what it
/// printed.
fn extract_ridge(seq: &Path, config: &Path, out: &Path, extra: &[&str]) -> String {
    let mut args = vec!["--max-samples", "10000", "--sheet", "ridge"];
    args.extend_from_slice(extra);
    let run = extract(seq, config, out, &args);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    String::from_utf8_lossy(&run.stdout).into_owned()
}

fn compare_manifold(mesh: &Path, truth: &Path) -> serde_json::Value {
    let cmp = echosurf(&[
        "compare",
        mesh.to_str().unwrap(),
        truth.to_str().unwrap(),
        "--json",
    ]);
    assert!(cmp.status.success(), "{}", mesh.display());
    let c: serde_json::Value = serde_json::from_slice(&cmp.stdout).unwrap();
    assert_eq!(c["mesh_oriented_manifold"], true, "{}: {c}", mesh.display());
    c
}

fn simulate(dir: &Path) -> (PathBuf, PathBuf) {
    let out = echosurf(&[
        "simulate",
        "--phantom",
        "sphere",
        "--seed",
        "3",
        "--frames-per-sweep",
        "30",
        "--width",
        "128",
        "--height",
        "100",
        "--pixel-size",
        "0.3",
        "--out",
        dir.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    (dir.join("sim.mha"), dir.join("sim_config.xml"))
}

#[test]
fn extract_recovers_the_sphere_cap_and_reports_every_stage() {
    let dir = tempfile::tempdir().unwrap();
    let (seq, config) = simulate(dir.path());
    let mesh = dir.path().join("mesh.ply");
    let report = dir.path().join("report.json");
    let preview = dir.path().join("preview.png");
    let model = dir.path().join("fit.esrbf");
    let outputs = common::extract_config(
        dir.path(),
        "outputs.toml",
        &format!("[outputs]\nmodel = {:?}\n", model.to_str().unwrap()),
    );
    let out = extract(
        &seq,
        &config,
        &mesh,
        &[
            "--max-samples",
            "10000",
            "--report",
            report.to_str().unwrap(),
            "--preview",
            preview.to_str().unwrap(),
            &outputs[0],
            &outputs[1],
        ],
    );
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(preview.exists());

    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    let stages: Vec<&str> = report["stages"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["stage"].as_str().unwrap())
        .collect();
    for stage in ["segment", "samples", "fit", "surface"] {
        assert!(
            stages.contains(&stage),
            "missing stage {stage} in {stages:?}"
        );
    }
    assert_eq!(report["counts"]["samples"].as_u64(), Some(10_000));
    assert!(report["counts"]["triangles"][0].as_u64().unwrap() > 1000);
    // The echo levels the pipeline reads from the images are the simulator's (water ~16, iso between).
    let background = report["levels"]["background"].as_f64().unwrap();
    assert!(
        (10.0..25.0).contains(&background),
        "background {background}"
    );

    let truth = dir.path().join("truth.ply");
    let c = compare_manifold(&mesh, &truth);
    // Loose bounds for a 10k-sample fit of a 30-frame sweep (measured: median 1.8 mm, 19% of the whole
    // sphere within 1 mm; only its beam-facing cap is ever imaged). A broken stage lands far outside.
    let median = c["accuracy"]["median_mm"].as_f64().unwrap();
    assert!(median < 3.0, "median mesh-to-truth distance {median} mm");
    let completeness = c["completeness_1mm"].as_f64().unwrap();
    assert!(completeness > 0.08, "completeness {completeness}");

    // Scored on what the sweep could show (`--sequence`): the truth it swept facing its beam within 30
    // degrees. The cap facing the probe is what a sweep from above images, so it is far more complete
    // than the whole sphere; the side facing the probe is part of the truth facing the beam either way.
    let swept_with = |side: &str, extra: &[&str]| {
        let mut args = vec![
            "compare",
            mesh.to_str().unwrap(),
            truth.to_str().unwrap(),
            "--json",
            "--sequence",
            seq.to_str().unwrap(),
            "--calibration",
            config.to_str().unwrap(),
            "--facing",
            side,
        ];
        args.extend_from_slice(extra);
        let out = echosurf(&args);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        assert_eq!(v["swept_facing"]["max_angle_deg"], 30.0);
        assert_eq!(v["swept_facing"]["side"], side);
        v["swept_facing"].clone()
    };
    let swept = |side: &str| swept_with(side, &[]);
    let (either, probe) = (swept("either"), swept("probe"));
    let area = |v: &serde_json::Value| v["truth_area_mm2"].as_f64().unwrap();
    assert!(area(&probe) > 0.0 && area(&probe) <= area(&either));
    // Measured: 0.83 of the probe-facing swept truth within 1 mm, against 0.18 of the whole sphere.
    let swept_completeness = probe["completeness_1mm"].as_f64().unwrap();
    assert!(
        swept_completeness > 0.6 && swept_completeness > 3.0 * completeness,
        "probe-facing completeness {swept_completeness} (whole truth {completeness})"
    );
    assert!(probe["truth_patches"].as_u64().unwrap() >= 1);
    // The swept part written as a miss map: fewer vertices than the whole truth, and about as much of
    // it within 1 mm as the score says (the score weighs by area, the map counts vertices).
    let swept_map = dir.path().join("swept_miss.ply");
    swept_with("probe", &["--swept-miss-map", swept_map.to_str().unwrap()]);
    let whole = echosurf::io::read_mesh(&truth).unwrap().vertices.len();
    let map = echosurf::io::read_point_cloud(&swept_map).unwrap();
    let distances = map.scalar("distance_mm").unwrap();
    assert!(!distances.is_empty() && distances.len() < whole);
    let within = distances.iter().filter(|&&d| d <= 1.0).count() as f64 / distances.len() as f64;
    assert!(
        (within - swept_completeness).abs() < 0.15,
        "{within} of the map's vertices within 1 mm, score {swept_completeness}"
    );
    // The table lists each patch that is not whole: a triangle far from the sphere misses them all.
    let far = dir.path().join("far.ply");
    echosurf::io::write_mesh(
        &far,
        &echosurf::mesh::Mesh {
            vertices: vec![
                glam::DVec3::new(500.0, 0.0, 0.0),
                glam::DVec3::new(501.0, 0.0, 0.0),
                glam::DVec3::new(500.0, 1.0, 0.0),
            ],
            normals: vec![],
            triangles: vec![[0, 1, 2]],
        },
    )
    .unwrap();
    let out = echosurf(&[
        "compare",
        far.to_str().unwrap(),
        truth.to_str().unwrap(),
        "--sequence",
        seq.to_str().unwrap(),
        "--calibration",
        config.to_str().unwrap(),
    ]);
    assert!(out.status.success());
    let text = String::from_utf8_lossy(&out.stdout);
    let patches = either["truth_patches"].as_u64().unwrap();
    assert!(
        text.contains(&format!("0 whole, 0 split, {patches} missed")),
        "{text}"
    );
    assert_eq!(text.matches("missed: ").count() as u64, patches, "{text}");
    assert!(text.contains("patch 0 missed: ") && text.contains("no piece within 1 mm"));

    // The saved model surfaces again at two levels without refitting: one manifold mesh per level, the
    // higher level enclosing less (fewer triangles around the brighter core of the echo).
    let levels_out = dir.path().join("levels.ply");
    let out = echosurf(&[
        "surface",
        model.to_str().unwrap(),
        "--iso",
        "25,40",
        "--out",
        levels_out.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let mut triangles = Vec::new();
    for name in ["levels_iso25.ply", "levels_iso40.ply"] {
        let path = dir.path().join(name);
        let c = compare_manifold(&path, &truth);
        triangles.push(c["mesh_topology"]["triangles"].as_u64().unwrap());
    }
    assert!(triangles[0] > triangles[1], "{triangles:?}");
    let out = echosurf(&[
        "surface",
        model.to_str().unwrap(),
        "--iso",
        "999",
        "--out",
        levels_out.to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("outside"));
}

#[test]
fn extract_refuses_bad_requests_without_writing() {
    let dir = tempfile::tempdir().unwrap();
    let (seq, config) = simulate(dir.path());
    let mesh = dir.path().join("mesh.ply");
    let small = ["--max-samples", "2000"];

    // An iso-level above every grey level cannot give a surface.
    let out = extract(
        &seq,
        &config,
        &mesh,
        &[&small[..], &["--iso", "300"]].concat(),
    );
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("iso-level 300") && err.contains("outside"),
        "{err}"
    );
    // The library's option is named as the flag that sets it.
    assert!(
        err.contains("set --iso to auto") && !err.contains("ExtractOptions::"),
        "{err}"
    );
    assert!(!err.contains("panicked"));
    assert!(!mesh.exists());

    let out = extract(
        &seq,
        &config,
        &mesh,
        &[&small[..], &["--iso", "fifty"]].concat(),
    );
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("not a number"));

    // A negative gap to bridge is refused by name (its file and key).
    let gap = common::extract_config(
        dir.path(),
        "gap.toml",
        "[tuning.cleanup]\nbridge_gap_mm = -1.0\n",
    );
    let out = extract(
        &seq,
        &config,
        &mesh,
        &[&small[..], &[&gap[0], &gap[1]]].concat(),
    );
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("gap.toml: tuning.cleanup.bridge_gap_mm must be 0 or a positive"),
        "{err}"
    );
    assert!(!mesh.exists());

    // A device set without an Image->Probe transform names the file.
    let bad_config = dir.path().join("no_calibration.xml");
    std::fs::write(
        &bad_config,
        "<PlusConfiguration><CoordinateDefinitions/></PlusConfiguration>",
    )
    .unwrap();
    let out = extract(&seq, &bad_config, &mesh, &[]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("no_calibration.xml"), "{err}");
    assert!(!mesh.exists());
    let leftovers: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().contains("echosurf-tmp"))
        .collect();
    assert!(leftovers.is_empty());
}

/// `--sheet ridge` moves the proximal sheet of the iso-sheath onto the echo ridge: on the simulated
/// sphere it lies closer to the true surface than the iso-surface at the same level, and stays a
/// manifold.
#[test]
fn ridge_sheet_lies_closer_to_the_surface_than_the_iso_sheath() {
    let dir = tempfile::tempdir().unwrap();
    let (seq, config) = simulate(dir.path());
    let truth = dir.path().join("truth.ply");
    let mut medians = Vec::new();
    for sheet in ["iso", "ridge"] {
        let mesh = dir.path().join(format!("{sheet}.ply"));
        let out = extract(
            &seq,
            &config,
            &mesh,
            &["--max-samples", "10000", "--sheet", sheet],
        );
        assert!(
            out.status.success(),
            "{sheet}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let c = compare_manifold(&mesh, &truth);
        assert!(
            c["mesh_topology"]["triangles"].as_u64().unwrap() > 100,
            "{sheet}: {c}"
        );
        medians.push(c["accuracy"]["median_mm"].as_f64().unwrap());
    }
    eprintln!(
        "median mesh-to-truth distance: iso {:.3} mm, ridge {:.3} mm",
        medians[0], medians[1]
    );
    assert!(medians[1] < 0.8 * medians[0], "{medians:?}");
    let bad = extract(
        &seq,
        &config,
        &dir.path().join("bad.ply"),
        &["--sheet", "middle"],
    );
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("--sheet middle"));
    for (section, toml, message) in [
        (
            "ridge",
            "reach_mm = 0.0",
            "tuning.ridge.reach_mm must be a positive",
        ),
        (
            "ridge",
            "bridge_mm = nan",
            "tuning.ridge.bridge_mm must be 0 or a positive",
        ),
        (
            "weak_echoes",
            "level_fraction = 1.0",
            "tuning.weak_echoes.level_fraction must be a fraction",
        ),
        (
            "weak_echoes",
            "reach_mm = 0.0",
            "tuning.weak_echoes.reach_mm must be a positive",
        ),
    ] {
        let file = common::extract_config(
            dir.path(),
            "ridge.toml",
            &format!("[tuning.{section}]\n{toml}\n"),
        );
        let bad = extract(
            &seq,
            &config,
            &dir.path().join("bad.ply"),
            &[&file[0], &file[1]],
        );
        assert!(!bad.status.success(), "{toml}");
        let err = String::from_utf8_lossy(&bad.stderr);
        assert!(
            err.contains("ridge.toml: ") && err.contains(message),
            "{toml}: {err}"
        );
    }
    assert!(!dir.path().join("bad.ply").exists());
}

#[test]
fn pieces_one_frame_echoes_are_removed_with_a_warning_saying_how_to_keep_them() {
    // Two frames far apart: every piece of the surface lies in one of them.
    let dir = tempfile::tempdir().unwrap();
    let sim = echosurf(&[
        "simulate",
        "--phantom",
        "sphere",
        "--frames-per-sweep",
        "2",
        "--sweeps",
        "1",
        "--width",
        "128",
        "--height",
        "100",
        "--out",
        dir.path().to_str().unwrap(),
    ]);
    assert!(sim.status.success());
    let (seq, config) = (
        dir.path().join("sim.mha"),
        dir.path().join("sim_config.xml"),
    );
    let report_path = dir.path().join("report.json");
    let mesh = dir.path().join("mesh.ply");
    let out = extract(
        &seq,
        &config,
        &mesh,
        &["--report", report_path.to_str().unwrap()],
    );
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    // The default asks for 3 frames; a 2-frame recording is asked for 2.
    assert!(
        stderr.contains(
            "was echoed by fewer than 2 frames and removed (tuning.cleanup.min_echo_frames = 0 keeps them)"
        ),
        "{stderr}"
    );
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&report_path).unwrap()).unwrap();
    assert_eq!(report["sheets"][0]["min_echo_frames"], 2);
    let removed = report["sheets"][0]["pieces_without_echoes"]
        .as_u64()
        .unwrap();
    assert!(removed >= 1);
    assert!(echosurf::io::read_mesh(&mesh).unwrap().is_empty());
    // Turned off, the same pieces are there.
    let kept = dir.path().join("kept.ply");
    let keep = common::extract_config(
        dir.path(),
        "keep.toml",
        "[tuning.cleanup]\nmin_echo_frames = 0\n",
    );
    let out = extract(&seq, &config, &kept, &[&keep[0], &keep[1]]);
    assert!(out.status.success());
    let mesh = echosurf::io::read_mesh(&kept).unwrap();
    assert_eq!(mesh.topology().components as u64, removed);
}

/// `tuning.cleanup.trim_rim_rings = 1` peels the rims of the ridge sheet: fewer triangles, the same pieces, and the far tail
/// of the distances to the truth shorter (the rims are where a sheet is least accurate).
#[test]
fn trimming_the_rim_keeps_the_pieces_and_shortens_the_tail() {
    let dir = tempfile::tempdir().unwrap();
    let (seq, config) = simulate(dir.path());
    let truth = dir.path().join("truth.ply");
    let mut scores = Vec::new();
    for (name, extra) in [("kept", "0"), ("trimmed", "1")] {
        let mesh = dir.path().join(format!("{name}.ply"));
        let trim = common::extract_config(
            dir.path(),
            "trim.toml",
            &format!("[tuning.cleanup]\ntrim_rim_rings = {extra}\n"),
        );
        let said = extract_ridge(&seq, &config, &mesh, &[&trim[0], &trim[1]]);
        assert_eq!(
            said.contains("rim triangles trimmed (1 ring)"),
            extra == "1",
            "{said}"
        );
        scores.push(compare_manifold(&mesh, &truth));
    }
    let get = |c: &serde_json::Value, a: &str, b: &str| c[a][b].as_f64().unwrap();
    let (kept, trimmed) = (&scores[0], &scores[1]);
    eprintln!(
        "p95 {:.3} -> {:.3} mm, triangles {} -> {}",
        get(kept, "accuracy", "p95_mm"),
        get(trimmed, "accuracy", "p95_mm"),
        kept["mesh_topology"]["triangles"],
        trimmed["mesh_topology"]["triangles"]
    );
    assert!(get(trimmed, "mesh_topology", "triangles") < get(kept, "mesh_topology", "triangles"));
    assert_eq!(
        kept["mesh_topology"]["components"],
        trimmed["mesh_topology"]["components"]
    );
    assert!(get(trimmed, "accuracy", "p95_mm") < get(kept, "accuracy", "p95_mm"));
}

/// `tuning.cleanup.max_echo_distance_mm` removes the ridge sheet's triangles far from every kept echo before the piece
/// checks: on the small sphere none lie beyond the default 1.5 mm, 298 beyond 0.5 mm (measured); the
/// mesh stays an oriented manifold, and 0 turns the check off. A negative distance is refused.
#[test]
fn triangles_far_from_every_echo_are_removed_and_reported() {
    let dir = tempfile::tempdir().unwrap();
    let (seq, config) = simulate(dir.path());
    let truth = dir.path().join("truth.ply");
    let mut removed = Vec::new();
    for distance in ["0", "1.5", "0.5"] {
        let mesh = dir.path().join(format!("mesh_{distance}.ply"));
        let report = dir.path().join(format!("report_{distance}.json"));
        let far = common::extract_config(
            dir.path(),
            "far.toml",
            &format!("[tuning.cleanup]\nmax_echo_distance_mm = {distance}\n"),
        );
        let said = extract_ridge(
            &seq,
            &config,
            &mesh,
            &[&far[0], &far[1], "--report", report.to_str().unwrap()],
        );
        compare_manifold(&mesh, &truth);
        let report: serde_json::Value =
            serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
        let sheet = &report["sheets"][0];
        assert_eq!(
            sheet["max_echo_distance_mm"].as_f64(),
            distance.parse().ok()
        );
        let n = sheet["triangles_far_from_echoes"].as_u64().unwrap();
        assert_eq!(
            said.contains(&format!("farther than {distance} mm from an echo removed")),
            n > 0,
            "{said}"
        );
        removed.push((n, echosurf::io::read_mesh(&mesh).unwrap().triangles.len()));
    }
    let [(off, all), (_, default), (near, fewer)] = removed[..] else {
        unreachable!()
    };
    assert_eq!(off, 0);
    assert_eq!(default, all);
    assert!(near > 0 && fewer < all, "{removed:?}");
    let negative = common::extract_config(
        dir.path(),
        "far.toml",
        "[tuning.cleanup]\nmax_echo_distance_mm = -1.0\n",
    );
    let refused = extract(
        &seq,
        &config,
        &dir.path().join("refused.ply"),
        &[&negative[0], &negative[1]],
    );
    assert!(!refused.status.success());
    assert!(
        String::from_utf8_lossy(&refused.stderr)
            .contains("far.toml: tuning.cleanup.max_echo_distance_mm"),
        "{}",
        String::from_utf8_lossy(&refused.stderr)
    );
    assert!(!dir.path().join("refused.ply").exists());
}
