//! An interrupted `extract` leaves no partial output: killed with SIGKILL (nothing can run: no output
//! exists because outputs only appear by rename once complete) and with SIGINT (the Ctrl-C handler also
//! removes unfinished hidden temporary files and exits with 130). A stale temporary file of a dead
//! process is removed by the next write into the same folder.

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

const BIN: &str = env!("CARGO_BIN_EXE_echosurf");

/// A simulated sphere sweep; `start_extract` asks for 400k samples and a 0.15 mm lattice, which takes
/// far longer than the moment the test waits before interrupting it (the default extract is fast).
fn simulate(dir: &Path) {
    let status = Command::new(BIN)
        .args([
            "simulate",
            "--phantom",
            "sphere",
            "--frames-per-sweep",
            "20",
            "--out",
        ])
        .arg(dir)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .unwrap();
    assert!(status.success());
}

fn start_extract(sim: &Path, out: &Path) -> Child {
    // The model has no flag: it is an output of the option file, kept beside the sweep.
    let options = sim.join(format!(
        "{}.toml",
        out.file_name().unwrap().to_string_lossy()
    ));
    std::fs::write(
        &options,
        format!(
            "[tuning.sampling]\nbin_mm = 0.0\n[outputs]\nmodel = {:?}\n",
            out.join("model.esrbf").to_str().unwrap()
        ),
    )
    .unwrap();
    Command::new(BIN)
        .arg("extract")
        .arg(sim.join("sim.mha"))
        .arg("--calibration")
        .arg(sim.join("sim_config.xml"))
        .arg("--out")
        .arg(out.join("mesh.ply"))
        .arg("--report")
        .arg(out.join("report.json"))
        .arg("--config")
        .arg(&options)
        .arg("--preview")
        .arg(out.join("preview.png"))
        .args(["--max-samples", "400000", "--resolution", "0.15"])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

/// Waits until the run has been going for `seconds`, asserting it has not finished (else the test would
/// prove nothing).
fn let_it_run(child: &mut Child, seconds: f64) {
    let start = Instant::now();
    while start.elapsed().as_secs_f64() < seconds {
        assert!(
            child.try_wait().unwrap().is_none(),
            "extract finished before it could be interrupted"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

fn entries(dir: &Path) -> Vec<String> {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect()
}

#[test]
fn killed_or_interrupted_extract_leaves_no_partial_output() {
    let dir = tempfile::tempdir().unwrap();
    let sim = dir.path().join("sim");
    simulate(&sim);

    // SIGKILL: the process dies wherever it is; nothing at the destination.
    let out = dir.path().join("out_kill");
    std::fs::create_dir(&out).unwrap();
    let mut child = start_extract(&sim, &out);
    let_it_run(&mut child, 1.0);
    child.kill().unwrap();
    let status = child.wait().unwrap();
    // Killed by the signal, not finished: no exit code.
    assert_eq!(
        status.code(),
        None,
        "extract finished before SIGKILL arrived"
    );
    let left: Vec<String> = entries(&out)
        .into_iter()
        .filter(|n| !n.contains(".echosurf-tmp-"))
        .collect();
    assert!(left.is_empty(), "partial outputs after SIGKILL: {left:?}");

    // SIGINT: the handler runs, exit code 130, and not even a hidden temp file remains.
    let out = dir.path().join("out_int");
    std::fs::create_dir(&out).unwrap();
    let mut child = start_extract(&sim, &out);
    let_it_run(&mut child, 1.0);
    let status = Command::new("kill")
        .arg("-INT")
        .arg(child.id().to_string())
        .status()
        .unwrap();
    assert!(status.success());
    let output = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(130), "stderr: {stderr}");
    assert!(stderr.contains("interrupted"), "{stderr}");
    assert!(
        entries(&out).is_empty(),
        "left after SIGINT: {:?}",
        entries(&out)
    );
}

#[test]
fn next_write_removes_stale_temp_files_of_dead_processes() {
    let dir = tempfile::tempdir().unwrap();
    // PIDs on Linux are below 2^22, so 4194999 is no running process.
    let stale = dir.path().join(".mesh.ply.echosurf-tmp-4194999");
    std::fs::write(&stale, b"half a mesh").unwrap();
    let status = Command::new(BIN)
        .args([
            "simulate",
            "--phantom",
            "sphere",
            "--frames-per-sweep",
            "4",
            "--width",
            "32",
        ])
        .args(["--height", "32", "--out"])
        .arg(dir.path())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .unwrap();
    assert!(status.success());
    if Path::new("/proc/self").exists() {
        assert!(
            !stale.exists(),
            "stale temp file survived a write into its folder"
        );
    }
}
