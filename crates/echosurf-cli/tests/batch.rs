//! `echosurf batch` end to end: three sweeps, one broken: two meshes, one reported failure, a non-zero
//! exit; a rerun redoes nothing (the summary says skipped, the files keep their modification times);
//! `--shard 0/2` and `--shard 1/2` together cover every row once.

use std::path::Path;

mod common;
use common::{echosurf, simulate_small_sphere};

/// The summary table's rows: (row, name, status).
fn summary(path: &Path) -> Vec<(usize, String, String)> {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines = text.lines();
    assert!(lines.next().unwrap().starts_with("row\tname\tstatus"));
    lines
        .map(|l| {
            let f: Vec<&str> = l.split('\t').collect();
            (f[0].parse().unwrap(), f[1].to_string(), f[2].to_string())
        })
        .collect()
}

#[test]
fn a_batch_with_a_broken_sweep_finishes_the_others_and_resumes() {
    let dir = tempfile::tempdir().unwrap();
    simulate_small_sphere(&dir.path().join("a"), "3", &[]);
    simulate_small_sphere(&dir.path().join("b"), "4", &[]);
    std::fs::create_dir(dir.path().join("c")).unwrap();
    std::fs::write(
        dir.path().join("c/sim.mha"),
        b"ObjectType = Image\nNDims = banana\n",
    )
    .unwrap();
    std::fs::copy(
        dir.path().join("a/sim_config.xml"),
        dir.path().join("c/sim_config.xml"),
    )
    .unwrap();
    let manifest = dir.path().join("study.toml");
    std::fs::write(
        &manifest,
        "options = [\"--max-samples\", \"3000\", \"--resolution\", \"1.0\"]\n\
         [[sweep]]\nname = \"first\"\nsequence = \"a/sim.mha\"\ncalibration = \"a/sim_config.xml\"\n\
         [[sweep]]\nname = \"broken\"\nsequence = \"c/sim.mha\"\ncalibration = \"c/sim_config.xml\"\n\
         [[sweep]]\nname = \"second\"\nsequence = \"b/sim.mha\"\ncalibration = \"b/sim_config.xml\"\n\
         options = [\"--sheet\", \"iso\", \"--space\", \"lps\"]\n",
    )
    .unwrap();
    let out = dir.path().join("out");
    let batch = |extra: &[&str]| {
        let mut args = vec![
            "batch",
            manifest.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        echosurf(&args)
    };
    let run = batch(&["--jobs", "2"]);
    assert!(
        !run.status.success(),
        "a failed sweep makes the exit code non-zero"
    );
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(
        stderr.contains("broken: FAILED") && stderr.contains("sim.mha"),
        "{stderr}"
    );
    let rows = summary(&out.join("summary.tsv"));
    let status: Vec<(&str, &str)> = rows
        .iter()
        .map(|(_, n, s)| (n.as_str(), s.as_str()))
        .collect();
    assert_eq!(
        status,
        [("first", "done"), ("broken", "failed"), ("second", "done")]
    );
    for name in ["first", "second"] {
        let mesh = echosurf::io::read_mesh(&out.join(format!("{name}.ply"))).unwrap();
        assert!(!mesh.is_empty(), "{name}");
        let report: serde_json::Value = serde_json::from_slice(
            &std::fs::read(out.join(format!("{name}.report.json"))).unwrap(),
        )
        .unwrap();
        assert_eq!(report["batch"]["name"], name);
        assert!(report["coordinates"]["frame"].is_string());
    }
    let second: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("second.report.json")).unwrap()).unwrap();
    assert_eq!(
        second["coordinates"]["space"], "LPS",
        "per-row options apply"
    );
    assert!(!out.join("broken.ply").exists() && !out.join("broken.report.json").exists());

    // A rerun: the two finished rows are skipped and their files untouched; the broken one fails again.
    let mtimes = || -> Vec<std::time::SystemTime> {
        [
            "first.ply",
            "first.report.json",
            "second.ply",
            "second.report.json",
        ]
        .iter()
        .map(|f| std::fs::metadata(out.join(f)).unwrap().modified().unwrap())
        .collect()
    };
    let before = mtimes();
    let rerun = batch(&[]);
    assert!(!rerun.status.success());
    let rows = summary(&out.join("summary.tsv"));
    let status: Vec<&str> = rows.iter().map(|(_, _, s)| s.as_str()).collect();
    assert_eq!(status, ["skipped", "failed", "skipped"]);
    assert_eq!(mtimes(), before);

    // Shards: rows k with k mod 2 = I, each row in exactly one shard's summary.
    for i in 0..2 {
        let _ = batch(&["--shard", &format!("{i}/2")]);
    }
    let mut covered: Vec<usize> = (0..2)
        .flat_map(|i| summary(&out.join(format!("summary-shard-{i}-of-2.tsv"))))
        .map(|(row, _, _)| row)
        .collect();
    covered.sort_unstable();
    assert_eq!(covered, [0, 1, 2]);
    let shard0: Vec<usize> = summary(&out.join("summary-shard-0-of-2.tsv"))
        .iter()
        .map(|r| r.0)
        .collect();
    assert_eq!(shard0, [0, 2]);
    assert_eq!(mtimes(), before, "the shards found the rows finished too");

    // Other options for a row: its report no longer matches, so it is run again.
    let text = std::fs::read_to_string(&manifest).unwrap();
    let changed = text.replace(
        "name = \"first\"\n",
        "name = \"first\"\noptions = [\"--seed\", \"2\"]\n",
    );
    std::fs::write(&manifest, changed).unwrap();
    let run = batch(&["--shard", "0/3"]);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let rows = summary(&out.join("summary-shard-0-of-3.tsv"));
    assert_eq!(rows, [(0, "first".to_string(), "done".to_string())]);
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("first.report.json")).unwrap()).unwrap();
    assert_eq!(report["parameters"]["seed"], 2);
}
