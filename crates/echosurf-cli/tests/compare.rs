//! End-to-end tests of `echosurf compare`.

use std::path::Path;
use std::process::Command;

use echosurf::mesh::Mesh;
use glam::DVec3;

use echosurf_testkit::real_data;
use real_data::real;

/// An axis-aligned box from `lo` to `hi`, outward winding, closed.
fn cuboid(lo: DVec3, hi: DVec3) -> Mesh {
    let corner = |i: u32| {
        DVec3::new(
            if i & 1 != 0 { hi.x } else { lo.x },
            if i & 2 != 0 { hi.y } else { lo.y },
            if i & 4 != 0 { hi.z } else { lo.z },
        )
    };
    let quads = [
        [0, 2, 3, 1], // z = lo
        [4, 5, 7, 6], // z = hi
        [0, 1, 5, 4], // y = lo
        [2, 6, 7, 3], // y = hi
        [0, 4, 6, 2], // x = lo
        [1, 3, 7, 5], // x = hi
    ];
    Mesh {
        vertices: (0..8).map(corner).collect(),
        normals: vec![],
        triangles: quads
            .iter()
            .flat_map(|&[a, b, c, d]| [[a, b, c], [a, c, d]])
            .collect(),
    }
}

fn compare(mesh: &Path, truth: &Path, json: bool) -> std::process::Output {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_echosurf"));
    cmd.arg("compare").arg(mesh).arg(truth);
    if json {
        cmd.arg("--json");
    }
    cmd.output().unwrap()
}

#[test]
fn compare_reports_distances_completeness_and_topology() {
    let dir = tempfile::tempdir().unwrap();
    let truth = dir.path().join("truth.stl");
    let mesh = dir.path().join("mesh.ply");
    echosurf::io::write_mesh(&truth, &cuboid(DVec3::ZERO, DVec3::splat(10.0))).unwrap();
    // Grown by 0.25 mm on every side: every point of one box is 0.25 mm from the other... except
    // near edges and corners of the bigger box, where it is up to 0.25 * sqrt(3).
    echosurf::io::write_mesh(&mesh, &cuboid(DVec3::splat(-0.25), DVec3::splat(10.25))).unwrap();

    let out = compare(&mesh, &truth, true);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let mean = v["accuracy"]["mean_mm"].as_f64().unwrap();
    let max = v["accuracy"]["max_mm"].as_f64().unwrap();
    // Box faces are 0.25 mm apart; near the bigger box's edges distances grow to 0.25 * sqrt(2) and at its
    // corners 0.25 * sqrt(3) (the vertices are part of the max).
    assert!(mean > 0.25 && mean < 0.26, "{mean}");
    assert!((max - 0.25 * 3f64.sqrt()).abs() < 1e-6, "{max}");
    // Truth -> mesh: every truth point is exactly 0.25 mm inside.
    assert!((v["reverse"]["max_mm"].as_f64().unwrap() - 0.25).abs() < 1e-6);
    assert_eq!(v["completeness_1mm"].as_f64().unwrap(), 1.0);
    assert_eq!(v["mesh_watertight"], true);
    assert_eq!(v["truth_topology"]["components"], 1);
    assert_eq!(v["hausdorff_mm"], v["accuracy"]["max_mm"]);
    assert_eq!(v["walls"]["truth_walls"], 1);
    assert_eq!(v["walls"]["edges_across_walls"], 0);

    // A hollow box (walls at 0-10 and 3-7 mm) against a box just outside each wall: two walls, and
    // no piece of the mesh joins them.
    let both = |a: Mesh, b: Mesh| {
        let base = a.vertices.len() as u32;
        Mesh {
            vertices: [a.vertices, b.vertices].concat(),
            normals: vec![],
            triangles: a
                .triangles
                .into_iter()
                .chain(b.triangles.into_iter().map(|t| t.map(|i| i + base)))
                .collect(),
        }
    };
    let hollow = dir.path().join("hollow.stl");
    echosurf::io::write_mesh(
        &hollow,
        &both(
            cuboid(DVec3::ZERO, DVec3::splat(10.0)),
            cuboid(DVec3::splat(3.0), DVec3::splat(7.0)),
        ),
    )
    .unwrap();
    let two = dir.path().join("two.ply");
    echosurf::io::write_mesh(
        &two,
        &both(
            cuboid(DVec3::splat(-0.25), DVec3::splat(10.25)),
            cuboid(DVec3::splat(3.25), DVec3::splat(6.75)),
        ),
    )
    .unwrap();
    let out = compare(&two, &hollow, true);
    assert!(out.status.success());
    let w: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(w["walls"]["truth_walls"], 2);
    assert_eq!(w["walls"]["edges_across_walls"], 0);
    assert_eq!(w["walls"]["pieces_on_several_walls"], 0);

    let out = compare(&mesh, &truth, false);
    assert!(out.status.success());
    let text = String::from_utf8(out.stdout).unwrap();
    assert!(
        text.contains("completeness (truth within 1 mm) 100.00 %"),
        "{text}"
    );
    assert!(text.contains("watertight"), "{text}");
    assert!(
        text.contains("\nwalls of the truth (components)  1: 0 mesh edges across walls, 0 pieces on several walls\n"),
        "{text}"
    );

    // A missing or broken file is an error naming the file, not a panic.
    let broken = dir.path().join("broken.ply");
    std::fs::write(&broken, "ply\nformat ascii 1.0\nelement vertex 9\n").unwrap();
    let out = compare(&broken, &truth, false);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("broken.ply"), "{err}");
}

/// The swept-truth score's inputs are checked: a missing sequence is named, `--calibration` needs
/// `--sequence`, and the facing angle must lie in (0, 90] degrees.
#[test]
fn compare_sequence_options_fail_cleanly() {
    let dir = tempfile::tempdir().unwrap();
    let truth = dir.path().join("truth.stl");
    echosurf::io::write_mesh(&truth, &cuboid(DVec3::ZERO, DVec3::splat(10.0))).unwrap();
    let run = |extra: &[&str]| {
        let out = Command::new(env!("CARGO_BIN_EXE_echosurf"))
            .arg("compare")
            .arg(&truth)
            .arg(&truth)
            .args(extra)
            .output()
            .unwrap();
        assert!(!out.status.success(), "{extra:?} should fail");
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    let missing = dir.path().join("missing.mha");
    let err = run(&["--sequence", missing.to_str().unwrap()]);
    assert!(err.contains("missing.mha"), "{err}");
    // The options of the swept-truth score mean nothing without the sequence: not silently ignored.
    for extra in [
        ["--calibration", "x.xml"],
        ["--facing", "probe"],
        ["--facing-deg", "20"],
        ["--world", "tracker"],
        ["--swept-miss-map", "swept.ply"],
    ] {
        let err = run(&extra);
        assert!(err.contains("--sequence"), "{extra:?}: {err}");
    }
    let spine = real("SpinePhantomFreehand.igs.mha");
    let config = real("PlusDeviceSet_VolumeReconstructionOnly_SpinePhantom_NN_MEAN.xml");
    let on_spine = |extra: &[&str]| {
        let mut args = vec![
            "--sequence",
            spine.to_str().unwrap(),
            "--calibration",
            config.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        run(&args)
    };
    let err = on_spine(&["--facing-deg", "0"]);
    assert!(err.contains("facing angle"), "{err}");
    // A truth the sweep never passed over (the box at the world origin) is named as such.
    let err = on_spine(&[]);
    assert!(err.contains("share a world frame"), "{err}");
}

#[test]
fn error_and_miss_maps_colour_each_vertex_by_its_distance() {
    let dir = tempfile::tempdir().unwrap();
    let truth = dir.path().join("truth.stl");
    let mesh = dir.path().join("mesh.ply");
    echosurf::io::write_mesh(&truth, &cuboid(DVec3::ZERO, DVec3::splat(10.0))).unwrap();
    // Every corner of the grown box is 0.25 * sqrt(3) mm from the truth's nearest corner; every corner
    // of the truth 0.25 mm from the grown box's nearest face.
    echosurf::io::write_mesh(&mesh, &cuboid(DVec3::splat(-0.25), DVec3::splat(10.25))).unwrap();
    let (error_map, miss_map) = (dir.path().join("error.ply"), dir.path().join("miss.ply"));
    let run = |extra: &[&std::ffi::OsStr]| {
        Command::new(env!("CARGO_BIN_EXE_echosurf"))
            .arg("compare")
            .arg(&mesh)
            .arg(&truth)
            .args(extra)
            .output()
            .unwrap()
    };
    let out = run(&[
        "--json".as_ref(),
        "--error-map".as_ref(),
        error_map.as_os_str(),
        "--miss-map".as_ref(),
        miss_map.as_os_str(),
        "--map-scale-mm".as_ref(),
        "0.5".as_ref(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(json["accuracy"]["mean_mm"].as_f64().unwrap() > 0.2);
    let said = String::from_utf8_lossy(&out.stderr);
    assert!(
        said.contains("error.ply") && said.contains("miss.ply"),
        "{said}"
    );
    for (map, corner) in [(&error_map, 0.25 * 3f64.sqrt()), (&miss_map, 0.25)] {
        assert_eq!(echosurf::io::read_mesh(map).unwrap().triangles.len(), 12);
        let cloud = echosurf::io::read_point_cloud(map).unwrap();
        let distances = cloud.scalar("distance_mm").unwrap();
        assert_eq!(distances.len(), 8);
        let want = echosurf::metrics::distance_colour(corner, 0.5);
        for (k, &d) in distances.iter().enumerate() {
            assert!((d as f64 - corner).abs() < 1e-5, "{d}");
            let got = ["red", "green", "blue"].map(|c| cloud.scalar(c).unwrap()[k] as u8);
            assert_eq!(got, want);
        }
    }

    // Refused before anything is written: a map over an input, one file for both maps, not PLY.
    let refused = dir.path().join("refused.ply");
    for (extra, says) in [
        (
            vec!["--error-map", mesh.to_str().unwrap()],
            "an input of this run",
        ),
        (
            vec![
                "--error-map",
                refused.to_str().unwrap(),
                "--miss-map",
                refused.to_str().unwrap(),
            ],
            "--miss-map",
        ),
        (vec!["--miss-map", "map.stl"], "PLY"),
        (
            vec![
                "--error-map",
                refused.to_str().unwrap(),
                "--map-scale-mm",
                "0",
            ],
            "--map-scale-mm",
        ),
    ] {
        let extra: Vec<&std::ffi::OsStr> = extra.iter().map(|s| s.as_ref()).collect();
        let out = run(&extra);
        assert!(!out.status.success(), "{extra:?}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(says), "{extra:?}: {err}");
        assert!(!refused.exists());
    }
    assert_eq!(
        echosurf::io::read_mesh(&mesh).unwrap().vertices.len(),
        8,
        "the input is untouched"
    );
}
