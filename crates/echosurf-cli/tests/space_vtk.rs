//! Meshes in Slicer's coordinate spaces and as legacy VTK, end to end: `--space ras` and `--space lps`
//! give files that differ in the tag and the signs of x and y only; reports state frame and space; the
//! VTK written opens in an independent reader (Python `meshio` or `vtk`, when installed).

use std::path::Path;

mod common;
use common::{echosurf_ok, simulate_small_sphere};

fn extract(seq: &Path, config: &Path, out: &Path, report: &Path, space: &str) {
    echosurf_ok(&[
        "extract",
        seq.to_str().unwrap(),
        "--calibration",
        config.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--report",
        report.to_str().unwrap(),
        "--max-samples",
        "4000",
        "--resolution",
        "1.0",
        "--space",
        space,
    ]);
}

#[test]
fn ras_and_lps_meshes_differ_in_the_tag_and_the_signs_of_x_and_y_only() {
    let dir = tempfile::tempdir().unwrap();
    let (seq, config) = simulate_small_sphere(dir.path(), "3", &[]);
    for ext in ["vtk", "ply"] {
        let ras = dir.path().join(format!("ras.{ext}"));
        let lps = dir.path().join(format!("lps.{ext}"));
        let ras_report = dir.path().join(format!("ras_{ext}.json"));
        let lps_report = dir.path().join(format!("lps_{ext}.json"));
        extract(&seq, &config, &ras, &ras_report, "ras");
        extract(&seq, &config, &lps, &lps_report, "LPS");
        let a = std::fs::read(&ras).unwrap();
        let mut b = std::fs::read(&lps).unwrap();
        assert_eq!(a.len(), b.len(), "{ext}");
        let tag = b
            .windows(9)
            .position(|w| w == b"SPACE=LPS")
            .expect("LPS tag");
        assert_eq!(&a[tag..tag + 9], b"SPACE=RAS", "{ext}: tags at one place");
        b[tag..tag + 9].copy_from_slice(b"SPACE=RAS");
        let differing: Vec<usize> = (0..a.len()).filter(|&i| a[i] != b[i]).collect();
        assert!(!differing.is_empty(), "{ext}: the coordinates must differ");
        assert!(
            differing.iter().all(|&i| a[i] ^ b[i] == 0x80),
            "{ext}: bytes differ beyond sign bits"
        );
        // Read back: each file lands in the same working coordinates.
        let (m_ras, t_ras) = echosurf::io::read_mesh_and_space(&ras).unwrap();
        let (m_lps, t_lps) = echosurf::io::read_mesh_and_space(&lps).unwrap();
        assert_eq!(t_ras, Some(echosurf::io::Space::Ras));
        assert_eq!(t_lps, Some(echosurf::io::Space::Lps));
        assert!(!m_ras.is_empty());
        assert_eq!(m_ras, m_lps, "{ext}");
        // Reports name the frame and the space, and otherwise agree but for timings.
        let read = |p: &Path| -> serde_json::Value {
            serde_json::from_slice(&std::fs::read(p).unwrap()).unwrap()
        };
        let (ra, rb) = (read(&ras_report), read(&lps_report));
        assert_eq!(ra["coordinates"]["space"], "RAS");
        assert_eq!(rb["coordinates"]["space"], "LPS");
        for r in [&ra, &rb] {
            let frame = r["coordinates"]["frame"].as_str().unwrap();
            assert!(["Reference", "Tracker"].contains(&frame), "{frame}");
            assert_eq!(r["coordinates"]["frame"], r["parameters"]["world_frame"]);
        }
        assert_eq!(ra["counts"], rb["counts"]);
        assert_eq!(ra["parameters"], rb["parameters"]);
    }
}

#[test]
fn a_truth_written_in_lps_reads_back_where_the_ras_one_is() {
    let dir = tempfile::tempdir().unwrap();
    let (ras_dir, lps_dir) = (dir.path().join("ras"), dir.path().join("lps"));
    simulate_small_sphere(&ras_dir, "3", &[]);
    simulate_small_sphere(&lps_dir, "3", &["--space", "lps"]);
    let (ras, ras_tag) = echosurf::io::read_mesh_and_space(&ras_dir.join("truth.ply")).unwrap();
    let (lps, lps_tag) = echosurf::io::read_mesh_and_space(&lps_dir.join("truth.ply")).unwrap();
    assert_eq!(ras_tag, Some(echosurf::io::Space::Ras));
    assert_eq!(lps_tag, Some(echosurf::io::Space::Lps));
    assert_eq!(ras, lps);
    let description: serde_json::Value =
        serde_json::from_slice(&std::fs::read(lps_dir.join("phantom.json")).unwrap()).unwrap();
    assert_eq!(description["coordinates"]["space"], "LPS");
    // compare reads an LPS mesh into RAS: the two truths coincide.
    let out = echosurf_ok(&[
        "compare",
        lps_dir.join("truth.ply").to_str().unwrap(),
        ras_dir.join("truth.ply").to_str().unwrap(),
        "--json",
    ]);
    let c: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(c["coordinates"]["mesh_tag"], "LPS");
    assert_eq!(c["coordinates"]["truth_tag"], "RAS");
    assert!(c["hausdorff_mm"].as_f64().unwrap() < 1e-4, "{c}");
}

/// A Python that can import `module`: `ECHOSURF_PYTHON`, else `python3`.
fn python_with(module: &str) -> Option<String> {
    let python = std::env::var("ECHOSURF_PYTHON").unwrap_or_else(|_| "python3".into());
    let ok = std::process::Command::new(&python)
        .args(["-c", &format!("import {module}")])
        .output()
        .is_ok_and(|o| o.status.success());
    ok.then_some(python)
}

#[test]
fn the_vtk_written_opens_in_an_independent_reader() {
    // VTK's own reader (PyPI `vtk`); meshio reads no legacy POLYDATA, so it cannot stand in.
    let Some(python) = python_with("vtk") else {
        eprintln!(
            "skipping: `import vtk` fails in python3 (set ECHOSURF_PYTHON to a Python with \
             `pip install vtk`)"
        );
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let (seq, config) = simulate_small_sphere(dir.path(), "3", &[]);
    let vtk = dir.path().join("mesh.vtk");
    extract(&seq, &config, &vtk, &dir.path().join("r.json"), "lps");
    // The reader prints the points and triangles it found; they must be what the file says.
    let script = "import sys, vtk\nr = vtk.vtkPolyDataReader()\nr.SetFileName(sys.argv[1])\n\
                  r.Update()\nd = r.GetOutput()\nn = d.GetNumberOfPoints()\n\
                  print(n, d.GetNumberOfPolys())\nprint(r.GetHeader())\n\
                  for i in range(n): print(*map(repr, d.GetPoint(i)))\nids = vtk.vtkIdList()\n\
                  d.GetPolys().InitTraversal()\n\
                  while d.GetPolys().GetNextCell(ids): print(*[ids.GetId(k) for k in range(3)])\n";
    let out = std::process::Command::new(&python)
        .args(["-c", script, vtk.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "vtk: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8(out.stdout).unwrap();
    let mut lines = text.lines();
    let counts: Vec<usize> = lines
        .next()
        .unwrap()
        .split(' ')
        .map(|t| t.parse().unwrap())
        .collect();
    assert!(lines.next().unwrap().contains("SPACE=LPS"));
    // The file as stored (LPS): x and y negated from the working coordinates.
    let mesh = echosurf::io::Space::Lps.convert(&echosurf::io::read_mesh(&vtk).unwrap());
    assert_eq!(counts, vec![mesh.vertices.len(), mesh.triangles.len()]);
    for v in &mesh.vertices {
        let p: Vec<f64> = lines
            .next()
            .unwrap()
            .split(' ')
            .map(|t| t.parse().unwrap())
            .collect();
        assert_eq!(p, vec![v.x, v.y, v.z]);
    }
    for t in &mesh.triangles {
        let f: Vec<u32> = lines
            .next()
            .unwrap()
            .split(' ')
            .map(|t| t.parse().unwrap())
            .collect();
        assert_eq!(f, t.to_vec());
    }
}
