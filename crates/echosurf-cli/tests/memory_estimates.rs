//! `--memory-budget` estimates against the peak resident memory each command measured itself
//! (`--memory-report`), one small simulated case per command; the real sweeps' table is
//! `scripts/memory_table.sh` (docs/decisions/0028-memory-budget-estimates.md).

mod common;

use std::ffi::OsString;
use std::path::{Path, PathBuf};

/// Largest allowed factor between the estimate and the measured peak, either way (issue 28).
const MAX_RATIO: f64 = 1.5;

/// (estimate, peak) in MB from a `--memory-report` line; the peak is `None` where the platform
/// reports no resident memory.
fn report(stderr: &str) -> (f64, Option<f64>) {
    let line = stderr
        .lines()
        .find(|l| l.starts_with("memory: "))
        .unwrap_or_else(|| panic!("no memory report in:\n{stderr}"));
    let figure = |key: &str| {
        let rest = line.split(key).nth(1)?;
        rest.split_whitespace().next()?.parse::<f64>().ok()
    };
    let estimate = figure("estimate ").unwrap_or_else(|| panic!("no estimate in `{line}`"));
    (estimate, figure("peak resident "))
}

fn run_and_check(label: &str, args: &[OsString]) {
    let mut args = args.to_vec();
    args.push("--memory-report".into());
    let out = common::echosurf_ok(&args);
    let stderr = String::from_utf8_lossy(&out.stderr);
    let (estimate, peak) = report(&stderr);
    assert!(estimate > 0.0, "{label}: {stderr}");
    if let Some(peak) = peak {
        let ratio = peak / estimate;
        assert!(
            (1.0 / MAX_RATIO..=MAX_RATIO).contains(&ratio),
            "{label}: estimate {estimate} MB, peak {peak} MB (ratio {ratio:.2})"
        );
    }
}

fn os(parts: &[&dyn AsRef<std::ffi::OsStr>]) -> Vec<OsString> {
    parts.iter().map(|p| p.as_ref().to_os_string()).collect()
}

/// The automatic level an extract report chose.
fn iso_of(report: &Path) -> String {
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(report).unwrap()).unwrap();
    json["parameters"]["iso_levels"][0]
        .as_f64()
        .expect("an iso-level in the report")
        .to_string()
}

/// An `extract --config` file in `dir` asking for the model and the samples too (they have no flag).
fn outputs_config(dir: &Path, model: &Path, samples: &Path) -> PathBuf {
    let file = dir.join("outputs.toml");
    std::fs::write(
        &file,
        format!(
            "[outputs]\nmodel = {:?}\nsamples = {:?}\n",
            model.to_str().unwrap(),
            samples.to_str().unwrap()
        ),
    )
    .unwrap();
    file
}

#[test]
fn every_budgeted_command_estimates_its_peak_within_one_and_a_half_times() {
    let dir = tempfile::tempdir().unwrap();
    let (seq, config) = common::simulate_small_sphere(dir.path(), "3", &[]);
    let d = dir.path();
    let (mesh, model, samples, json) = (
        d.join("m.ply"),
        d.join("m.esrbf"),
        d.join("s.ply"),
        d.join("r.json"),
    );
    run_and_check(
        "extract",
        &os(&[
            &"extract",
            &seq,
            &"--calibration",
            &config,
            &"--out",
            &mesh,
            &"--config",
            &outputs_config(d, &model, &samples),
            &"--report",
            &json,
        ]),
    );
    run_and_check(
        "extract --method voxel",
        &os(&[
            &"extract",
            &seq,
            &"--calibration",
            &config,
            &"--method",
            &"voxel",
            &"--out",
            &d.join("v.ply"),
        ]),
    );
    run_and_check(
        "reconstruct",
        &os(&[
            &"reconstruct",
            &seq,
            &"--calibration",
            &config,
            &"--out",
            &d.join("v.mha"),
        ]),
    );
    run_and_check(
        "fit",
        &os(&[&"fit", &samples, &"--out", &d.join("refit.esrbf")]),
    );
    run_and_check(
        "surface",
        &os(&[
            &"surface",
            &model,
            &"--iso",
            &iso_of(&json),
            &"--out",
            &d.join("surface.ply"),
        ]),
    );
    run_and_check("compare", &os(&[&"compare", &mesh, &d.join("truth.ply")]));
}

/// `fit` and `surface` refuse past their budget before the work, naming the figure and the option.
#[test]
fn fit_and_surface_refuse_past_the_budget_naming_the_option() {
    let dir = tempfile::tempdir().unwrap();
    let (seq, config) = common::simulate_small_sphere(dir.path(), "4", &[]);
    let d = dir.path();
    let (model, samples, json) = (d.join("m.esrbf"), d.join("s.ply"), d.join("r.json"));
    common::echosurf_ok(&os(&[
        &"extract",
        &seq,
        &"--calibration",
        &config,
        &"--out",
        &d.join("m.ply"),
        &"--config",
        &outputs_config(d, &model, &samples),
        &"--report",
        &json,
    ]));
    let refit = d.join("refit.esrbf");
    let out = common::echosurf(&os(&[
        &"fit",
        &samples,
        &"--out",
        &refit,
        &"--memory-budget",
        &"1",
    ]));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("s.ply") && stderr.contains("memory budget is 1 MB"),
        "{stderr}"
    );
    assert!(stderr.contains("--memory-budget"), "{stderr}");
    assert!(!refit.exists());
    let surface = d.join("surface.ply");
    let out = common::echosurf(&os(&[
        &"surface",
        &model,
        &"--iso",
        &iso_of(&json),
        &"--out",
        &surface,
        &"--memory-budget",
        &"1",
    ]));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("m.esrbf") && stderr.contains("--resolution"),
        "{stderr}"
    );
    assert!(!surface.exists());
}

/// Under an address-space limit below what the run needs, any failed allocation (not only the big
/// buffers reserved fallibly) ends the run with exit 1 and a message, not an abort (134), and leaves
/// no output or hidden temporary file.
#[test]
fn running_out_of_address_space_is_an_error_not_an_abort() {
    if !Path::new("/bin/sh").exists() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let (seq, config) = common::simulate_small_sphere(dir.path(), "5", &[]);
    let out_dir = dir.path().join("out");
    std::fs::create_dir(&out_dir).unwrap();
    let mesh = out_dir.join("m.ply");
    // This extract's peak resident memory is about 100 MB; 150 MB of address space holds the
    // binary, the thread stacks and the allocator's arenas but not the run.
    let output = std::process::Command::new("/bin/sh")
        .arg("-c")
        .arg("ulimit -v 150000 && exec \"$0\" extract \"$1\" --calibration \"$2\" --out \"$3\"")
        .arg(env!("CARGO_BIN_EXE_echosurf"))
        .arg(&seq)
        .arg(&config)
        .arg(&mesh)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("error: out of memory"), "{stderr}");
    let left: Vec<_> = std::fs::read_dir(&out_dir)
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert!(left.is_empty(), "left {left:?}");
}
