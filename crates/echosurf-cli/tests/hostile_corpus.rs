//! The hostile corpus (generated from the real PLUS files by `crates/echosurf-testkit/src/corpus.rs`)
//! through the `echosurf` binary: every case must exit non-zero, say which file and what is wrong, never
//! panic, write no output, finish quickly and stay within a memory bound. Wall time and peak RSS of every
//! case are printed (`cargo test -p echosurf-cli --test hostile_corpus -- --nocapture`).

use echosurf_testkit as testkit;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use testkit::corpus::{Case, Companions, Target, generate};

const BIN: &str = env!("CARGO_BIN_EXE_echosurf");

/// Bound on one refusal's wall time. The target is < 1 s (typical here: 2-50 ms in the dev profile); the
/// assert is looser because the test machine is shared with other builds.
const MAX_SECONDS: f64 = 5.0;

/// Fixed memory allowance on top of twice the input: the binary, its allocator and thread pools.
const FIXED_BUDGET_BYTES: u64 = 64 << 20;

fn args_for(case: &Case, c: &Companions, out: &Path) -> Option<Vec<PathBuf>> {
    let p = case.path.clone();
    let s = |x: &str| PathBuf::from(x);
    Some(match case.target {
        Target::Sequence => vec![s("inspect"), p],
        Target::SequenceForExtract => vec![
            s("extract"),
            p,
            s("--calibration"),
            c.config.clone(),
            s("--out"),
            out.join("mesh.ply"),
        ],
        Target::Config => vec![
            s("reconstruct"),
            c.sequence.clone(),
            s("--calibration"),
            p,
            s("--out"),
            out.join("volume.mha"),
        ],
        Target::InitialBand => vec![
            s("extract"),
            c.sequence.clone(),
            s("--calibration"),
            c.config.clone(),
            s("--init"),
            p,
            s("--out"),
            out.join("mesh.ply"),
        ],
        Target::PointCloud => vec![s("fit"), p, s("--out"), out.join("model.esrbf")],
        Target::Mesh => vec![s("compare"), p, c.mesh.clone()],
        Target::Model => vec![
            s("eval"),
            p,
            c.cloud.clone(),
            s("--out"),
            out.join("values.ply"),
        ],
        Target::Volume => return None,
    })
}

/// Peak RSS (bytes) and the output of a run under `/usr/bin/time -f %M` (GNU time), where available.
fn run(args: &[PathBuf], time_file: &Path) -> (std::process::Output, Option<u64>) {
    let gnu_time = Path::new("/usr/bin/time");
    let mut cmd = if gnu_time.exists() {
        let mut c = Command::new(gnu_time);
        c.arg("-f").arg("%M").arg("-o").arg(time_file).arg(BIN);
        c
    } else {
        Command::new(BIN)
    };
    let output = cmd
        .args(args)
        .env("RAYON_NUM_THREADS", "2")
        .output()
        .unwrap();
    let peak = std::fs::read_to_string(time_file)
        .ok()
        .and_then(|t| t.lines().last()?.trim().parse::<u64>().ok())
        .map(|kib| kib * 1024);
    (output, peak)
}

#[test]
fn the_cli_refuses_every_corpus_file_quickly_and_within_memory() {
    let dir = tempfile::tempdir().unwrap();
    let companions = testkit::corpus::companions(dir.path());
    let cases = generate(dir.path());
    let out = dir.path().join("out");
    std::fs::create_dir(&out).unwrap();
    let time_file = dir.path().join("time.txt");
    let mut failures = Vec::new();
    let mut ran = 0;
    let mut memory_checked = false;
    for case in &cases {
        let Some(args) = args_for(case, &companions, &out) else {
            continue;
        };
        let _ = std::fs::remove_file(&time_file);
        let name = case
            .path
            .file_name()
            .unwrap()
            .to_string_lossy()
            .into_owned();
        let start = Instant::now();
        let (output, peak) = run(&args, &time_file);
        let seconds = start.elapsed().as_secs_f64();
        ran += 1;
        let stderr = String::from_utf8_lossy(&output.stderr);
        let input_bytes = std::fs::metadata(&case.path).map(|m| m.len()).unwrap_or(0);
        // "Real data" is what the file legitimately holds: lying files are bounded by their seed (< 2 MB),
        // not by the 100 MB junk line or what a header claims.
        let memory_bound = 2 * input_bytes.min(2 << 20) + FIXED_BUDGET_BYTES;
        eprintln!(
            "{name:40} {:>7.1} ms  peak {:>6} KiB  exit {:?}  {}",
            seconds * 1e3,
            peak.map(|b| (b / 1024).to_string())
                .unwrap_or_else(|| "?".into()),
            output.status.code(),
            stderr.lines().next().unwrap_or("")
        );
        if output.status.success() {
            failures.push(format!("{name}: exit code 0"));
        }
        if stderr.contains("panicked") {
            failures.push(format!("{name}: panicked: {stderr}"));
        }
        if !stderr.contains(&name) {
            failures.push(format!("{name}: stderr does not name the file: {stderr}"));
        }
        let lower = stderr.to_ascii_lowercase();
        if !case
            .problem_words
            .iter()
            .any(|w| lower.contains(&w.to_ascii_lowercase()))
        {
            failures.push(format!(
                "{name}: stderr does not say the problem ({:?}): {stderr}",
                case.problem_words
            ));
        }
        if seconds > MAX_SECONDS {
            failures.push(format!("{name}: took {seconds:.2} s"));
        }
        if let Some(peak) = peak {
            memory_checked = true;
            if peak > memory_bound {
                failures.push(format!(
                    "{name}: peak RSS {peak} B > bound {memory_bound} B"
                ));
            }
        }
        let left: Vec<_> = std::fs::read_dir(&out)
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        if !left.is_empty() {
            failures.push(format!("{name}: left output files {left:?}"));
        }
    }
    if !memory_checked {
        eprintln!("peak memory NOT checked: /usr/bin/time (GNU time) is not available");
    }
    drop(dir);
    assert!(ran >= 30, "only {ran} CLI cases");
    assert!(
        failures.is_empty(),
        "{} failures:\n{}",
        failures.len(),
        failures.join("\n")
    );
}

/// `--memory-budget` refuses up front (no time spent, nothing written) and says what would fit.
#[test]
fn memory_budget_refuses_up_front_with_what_would_fit() {
    let dir = tempfile::tempdir().unwrap();
    let sim = dir.path().join("sim");
    let status = Command::new(BIN)
        .args([
            "simulate",
            "--phantom",
            "sphere",
            "--frames-per-sweep",
            "8",
            "--width",
            "64",
        ])
        .args(["--height", "64", "--out"])
        .arg(&sim)
        .output()
        .unwrap();
    assert!(status.status.success());
    let extract = |extra: &[&str]| {
        let start = Instant::now();
        let out = Command::new(BIN)
            .arg("extract")
            .arg(sim.join("sim.mha"))
            .arg("--calibration")
            .arg(sim.join("sim_config.xml"))
            .arg("--out")
            .arg(dir.path().join("mesh.ply"))
            .args(extra)
            .output()
            .unwrap();
        (out, start.elapsed().as_secs_f64())
    };
    // A 0.05 mm lattice follows 100 times the nodes of the default 0.5 mm over the same surface:
    // refused before surfacing, naming the resolution.
    let (out, seconds) = extract(&["--resolution", "0.05", "--memory-budget", "300"]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(stderr.contains("memory budget is 300 MB"), "{stderr}");
    assert!(stderr.contains("--resolution"), "{stderr}");
    assert!(seconds < MAX_SECONDS, "refusal took {seconds} s");
    // Every kept sample in one dense system needs gigabytes: refused after segmentation with a
    // sample count that fits.
    let direct = dir.path().join("direct.toml");
    std::fs::write(&direct, "[tuning.fit]\nsolver = \"direct\"\n").unwrap();
    let (out, _) = extract(&[
        "--max-samples",
        "100000",
        "--config",
        direct.to_str().unwrap(),
        "--memory-budget",
        "300",
    ]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(stderr.contains("--max-samples"), "{stderr}");
    assert!(!dir.path().join("mesh.ply").exists());
    // Nonsense budgets are refused as such.
    let (out, _) = extract(&["--memory-budget", "0"]);
    assert!(String::from_utf8_lossy(&out.stderr).contains("positive number of MB"));
}

/// An output named like an input (the sequence, its detached `.raw`, the calibration), like another
/// output or for another format is refused before any work, and every input keeps its bytes.
#[test]
fn outputs_never_replace_inputs_or_each_other() {
    let dir = tempfile::tempdir().unwrap();
    let copy = |name: &str| {
        let to = dir.path().join(name);
        std::fs::copy(testkit::real_data::real(name), &to).unwrap();
        to
    };
    let nwire = copy("NwirePhantomFreehand.igs.mha");
    let config = copy("PlusDeviceSet_NwirePhantomFreehand_vtkVolumeReconstructorTest2.xml");
    let video = copy("Prostate10_video.igs.mhd");
    let raw = copy("Prostate10_video.raw");
    let inputs = [&nwire, &config, &video, &raw];
    let before: Vec<Vec<u8>> = inputs.iter().map(|p| std::fs::read(p).unwrap()).collect();
    let p = PathBuf::from;
    let in_dir = |name: &str| dir.path().join(name);
    std::fs::create_dir(in_dir("sub")).unwrap();
    // `echosurf COMMAND SEQUENCE --calibration CONFIG REST...` must fail, saying `says`, quickly.
    let refused = |command: &str, sequence: &Path, rest: &[PathBuf], says: &str| {
        let mut args = vec![
            PathBuf::from(command),
            sequence.to_path_buf(),
            p("--calibration"),
            config.clone(),
        ];
        args.extend_from_slice(rest);
        let start = Instant::now();
        let out = Command::new(BIN).args(&args).output().unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?} succeeded");
        assert!(stderr.contains(says), "{args:?}: {stderr}");
        assert!(!stderr.contains("panicked"), "{stderr}");
        let seconds = start.elapsed().as_secs_f64();
        assert!(seconds < MAX_SECONDS, "{args:?} took {seconds} s to refuse");
    };
    let out_to = |path: PathBuf| [p("--out"), path];
    // The masks would have replaced the recording.
    let roundabout = in_dir("sub/../NwirePhantomFreehand.igs.mha");
    let auto_out = [p("--auto-init"), p("--out"), roundabout];
    refused("segment", &nwire, &auto_out, "that is");
    // A detached data file is an input too; so is the calibration.
    refused(
        "extract",
        &video,
        &out_to(raw.clone()),
        "an input of this run",
    );
    refused("reconstruct", &nwire, &out_to(config.clone()), "--out");
    // Two outputs of one run in one file, also through a level's derived name.
    let twice = [
        p("--out"),
        in_dir("mesh.ply"),
        p("--preview"),
        in_dir("mesh.ply"),
    ];
    refused("extract", &nwire, &twice, "--out and --preview both name");
    let derived = [
        p("--iso"),
        p("40,60"),
        p("--out"),
        in_dir("mesh.ply"),
        p("--report"),
        in_dir("mesh_iso60.ply"),
    ];
    refused(
        "extract",
        &nwire,
        &derived,
        "--out (iso 60) and --report both name",
    );
    // An output named for another format, refused before the work rather than after it.
    let masks_png = [p("--auto-init"), p("--out"), in_dir("masks.png")];
    refused("segment", &nwire, &masks_png, "must end in .mha");
    let xyz = out_to(in_dir("mesh.xyz"));
    refused("extract", &nwire, &xyz, "must end in .ply, .stl, .obj");
    for (path, bytes) in inputs.iter().zip(&before) {
        assert_eq!(
            &std::fs::read(path).unwrap(),
            bytes,
            "{} changed",
            path.display()
        );
    }
    let mut left: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    left.sort();
    let mut expected: Vec<String> = inputs
        .iter()
        .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
        .chain(["sub".to_string()])
        .collect();
    expected.sort();
    assert_eq!(left, expected, "a refused run wrote a file");
}
