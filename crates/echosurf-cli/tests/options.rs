//! The two tiers of `extract` options end to end: `--print-config` writes the full set, `--config`
//! reads it back to the same bytes, bad files are refused by file and key, a PLUS XML given to
//! `--config` points to `--calibration`, and `--help` stays short.

use std::path::Path;

mod common;
use common::{echosurf, echosurf_ok};

/// `extract` of the small sphere sweep into `out` with `extra`; returns the mesh bytes and the report
/// without its timing and memory fields (which change from run to run).
fn extract_small(seq: &Path, calibration: &Path, out: &Path, extra: &[&str]) -> (Vec<u8>, String) {
    let report = out.with_extension("json");
    let mut args = vec![
        "extract",
        seq.to_str().unwrap(),
        "--calibration",
        calibration.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--max-samples",
        "3000",
        "--report",
        report.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    echosurf_ok(&args);
    let mut json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    let object = json.as_object_mut().unwrap();
    for timing in ["total_seconds", "peak_rss_bytes"] {
        object.remove(timing).unwrap();
    }
    let stages: Vec<serde_json::Value> = object["stages"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["stage"].clone())
        .collect();
    object.insert("stages".into(), stages.into());
    object["fit"]
        .as_object_mut()
        .unwrap()
        .remove("fit_seconds")
        .unwrap();
    (std::fs::read(out).unwrap(), json.to_string())
}

#[test]
fn the_printed_config_reproduces_the_defaults_byte_for_byte() {
    let dir = tempfile::tempdir().unwrap();
    let (seq, calibration) = common::simulate_small_sphere(dir.path(), "3", &[]);
    // Printed without a sequence, exit 0.
    let printed = echosurf_ok(&["extract", "--print-config"]);
    let text = String::from_utf8(printed.stdout).unwrap();
    let parsed: toml::Table = toml::from_str(&text).unwrap();
    for section in ["user", "tuning", "outputs"] {
        assert!(parsed.contains_key(section), "{text}");
    }
    assert_eq!(parsed["user"]["smoothing_mm"].as_float(), Some(2.0));
    let file = dir.path().join("x.toml");
    std::fs::write(&file, &text).unwrap();

    let plain = extract_small(&seq, &calibration, &dir.path().join("plain.ply"), &[]);
    let with_file = extract_small(
        &seq,
        &calibration,
        &dir.path().join("file.ply"),
        &["--config", file.to_str().unwrap()],
    );
    assert!(!plain.0.is_empty());
    assert!(plain.0 == with_file.0, "the meshes differ");
    assert_eq!(plain.1, with_file.1);
}

#[test]
fn flags_override_the_file_and_the_file_overrides_the_defaults() {
    let dir = tempfile::tempdir().unwrap();
    let (seq, calibration) = common::simulate_small_sphere(dir.path(), "4", &[]);
    let file = dir.path().join("o.toml");
    std::fs::write(
        &file,
        "[user]\nseed = 9\nresolution_mm = 1.0\n[tuning.sampling]\nbin_mm = 0.0\n",
    )
    .unwrap();
    let (_, report) = extract_small(
        &seq,
        &calibration,
        &dir.path().join("m.ply"),
        &["--config", file.to_str().unwrap(), "--seed", "5"],
    );
    let report: serde_json::Value = serde_json::from_str(&report).unwrap();
    let p = &report["parameters"];
    // --seed beats the file; the file's resolution and block size beat the defaults.
    assert_eq!(p["seed"], 5);
    assert_eq!(p["resolution_mm"], 1.0);
    assert_eq!(p["sample_bin_mm"], 0.0);
    assert_eq!(report["counts"]["samples"], 3000);
    // --print-config shows what would run.
    let shown = echosurf_ok(&[
        "extract",
        "--print-config",
        "--config",
        file.to_str().unwrap(),
        "--seed",
        "5",
    ]);
    let shown: toml::Table = toml::from_str(&String::from_utf8(shown.stdout).unwrap()).unwrap();
    assert_eq!(shown["user"]["seed"].as_integer(), Some(5));
    assert_eq!(shown["user"]["resolution_mm"].as_float(), Some(1.0));
}

/// `extract --calibration C --out M --config FILE` on a sweep that need not exist: the file is read first.
fn refused_config(dir: &Path, name: &str, text: &str) -> String {
    let file = dir.join(name);
    std::fs::write(&file, text).unwrap();
    let out = echosurf(&[
        "extract",
        dir.join("none.mha").to_str().unwrap(),
        "--calibration",
        dir.join("none.xml").to_str().unwrap(),
        "--out",
        dir.join("m.ply").to_str().unwrap(),
        "--config",
        file.to_str().unwrap(),
    ]);
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert!(!dir.join("m.ply").exists());
    stderr
}

#[test]
fn bad_values_and_unknown_keys_are_refused_naming_the_file_and_the_key() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let err = refused_config(d, "range.toml", "[tuning.segment]\nthreshold = 1.5\n");
    assert!(
        err.contains("range.toml: tuning.segment.threshold must be in (0, 1], got 1.5"),
        "{err}"
    );
    let err = refused_config(d, "user.toml", "[user]\nresolution_mm = -1.0\n");
    assert!(
        err.contains("user.toml: user.resolution_mm must be a positive number of mm"),
        "{err}"
    );
    let err = refused_config(d, "type.toml", "[tuning.ridge]\nreach_mm = \"far\"\n");
    assert!(
        err.contains("type.toml") && err.contains("reach_mm") && err.contains("invalid type"),
        "{err}"
    );
    let err = refused_config(d, "unknown.toml", "[tuning.ridge]\ncolour = 1\n");
    assert!(
        err.contains("unknown.toml") && err.contains("unknown field `colour`"),
        "{err}"
    );
    let err = refused_config(d, "section.toml", "[tuning.ridges]\nreach_mm = 1.0\n");
    assert!(
        err.contains("section.toml") && err.contains("unknown field `ridges`"),
        "{err}"
    );
    let err = refused_config(d, "word.toml", "[user]\nsheet = \"flat\"\n");
    assert!(
        err.contains("word.toml") && err.contains("expected one of auto, iso, ridge"),
        "{err}"
    );
    // A flag out of range is named as the flag.
    let out = echosurf(&[
        "extract",
        "s.mha",
        "--calibration",
        "c.xml",
        "--out",
        "m.ply",
        "--resolution",
        "0",
    ]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("--resolution must be a positive number of mm"),
        "{stderr}"
    );
}

#[test]
fn a_plus_xml_given_to_config_points_to_calibration() {
    let dir = tempfile::tempdir().unwrap();
    let expected = |name: &str| {
        format!(
            "{} is a PLUS device-set XML; give it with --calibration (--config takes the TOML that \
             `echosurf extract --print-config` writes)",
            dir.path().join(name).display()
        )
    };
    let xml = "<PlusConfiguration version=\"2.1\"><CoordinateDefinitions/></PlusConfiguration>\n";
    // By its name, and by its content under another name.
    let err = refused_config(dir.path(), "device.xml", xml);
    assert!(err.contains(&expected("device.xml")), "{err}");
    let err = refused_config(dir.path(), "device.toml", &format!("\n  {xml}"));
    assert!(err.contains(&expected("device.toml")), "{err}");
}

#[test]
fn extract_help_lists_at_most_fifteen_options_besides_config_and_print_config() {
    let help = String::from_utf8(echosurf_ok(&["extract", "--help"]).stdout).unwrap();
    let options: Vec<&str> = help
        .lines()
        .map(str::trim_start)
        .filter(|l| l.starts_with("--") || (l.starts_with('-') && l.contains(", --")))
        .filter_map(|l| l.split_whitespace().find(|w| w.starts_with("--")))
        .filter(|o| *o != "--help")
        .collect();
    assert!(
        options.contains(&"--config") && options.contains(&"--print-config"),
        "{help}"
    );
    let others = options
        .iter()
        .filter(|o| !["--config", "--print-config"].contains(o))
        .count();
    assert!(others <= 15, "{others} options: {options:?}");
    // The user tier is on the command line.
    for flag in [
        "--calibration",
        "--iso",
        "--smoothing",
        "--sheet",
        "--resolution",
        "--max-samples",
        "--method",
        "--seed",
    ] {
        assert!(options.contains(&flag), "{flag} missing: {options:?}");
    }
}
