//! What the CLI's end-to-end tests share: running the `echosurf` binary this build made.
#![allow(dead_code)]

use std::ffi::OsStr;
use std::process::{Command, Output};

/// Runs `echosurf ARGS` and returns its status and output unchecked (for the refusals).
pub fn echosurf<S: AsRef<OsStr>>(args: &[S]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_echosurf"))
        .args(args)
        .output()
        .expect("run echosurf")
}

/// Runs `echosurf ARGS` and asserts it succeeded; the failure names the arguments and what it printed.
pub fn echosurf_ok<S: AsRef<OsStr>>(args: &[S]) -> Output {
    let out = echosurf(args);
    assert!(
        out.status.success(),
        "echosurf {:?} failed: {}",
        args.iter().map(|a| a.as_ref()).collect::<Vec<_>>(),
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// Simulates a small sphere sweep (96 x 80 px at 0.4 mm, 20 frames per sweep) into `dir` with `seed`
/// and any `extra` simulate arguments; returns (sequence, calibration).
pub fn simulate_small_sphere(
    dir: &std::path::Path,
    seed: &str,
    extra: &[&str],
) -> (std::path::PathBuf, std::path::PathBuf) {
    let out = dir.to_str().expect("a UTF-8 test folder");
    let mut args = vec![
        "simulate",
        "--phantom",
        "sphere",
        "--seed",
        seed,
        "--frames-per-sweep",
        "20",
        "--width",
        "96",
        "--height",
        "80",
        "--pixel-size",
        "0.4",
        "--out",
        out,
    ];
    args.extend_from_slice(extra);
    echosurf_ok(&args);
    (dir.join("sim.mha"), dir.join("sim_config.xml"))
}

/// Writes `toml` (sections of the `extract --print-config` file) to `dir/name` and returns
/// `["--config", path]` for `echosurf extract`.
#[allow(dead_code)]
pub fn extract_config(dir: &std::path::Path, name: &str, toml: &str) -> [String; 2] {
    let path = dir.join(name);
    std::fs::write(&path, toml).unwrap();
    ["--config".into(), path.to_str().unwrap().into()]
}
