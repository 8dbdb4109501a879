//! Hostile input, round two (issue 28), through the `echosurf` binary, every file generated here: outputs
//! that are devices, pipes, sockets, links or inputs; parser and standard-output faults; nonsense the
//! readers used to accept; inputs that ask for unbounded memory or time; SIGTERM and SIGHUP. Every
//! refusal must exit 1 or 2, name the file and the problem on stderr, never panic or abort, finish
//! within 10 s and stay within twice its inputs' size plus 64 MB of peak memory (where GNU time is
//! there to measure it). Per-case wall time and peak RSS: `cargo test -p echosurf-cli --test
//! hostile_round2 -- --nocapture`.

mod common;

use std::ffi::OsString;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

const BIN: &str = env!("CARGO_BIN_EXE_echosurf");

/// Bound on one case's wall time.
const MAX_SECONDS: f64 = 10.0;

/// Fixed memory allowance on top of twice the inputs: the binary, its allocator and thread pools.
const FIXED_BUDGET_BYTES: u64 = 64 << 20;

/// A small simulated sphere (uncompressed, so tests can edit its header) and a model fitted on it.
struct Fixture {
    dir: tempfile::TempDir,
    sequence: PathBuf,
    config: PathBuf,
    truth: PathBuf,
}

impl Fixture {
    fn new() -> Fixture {
        let dir = tempfile::tempdir().unwrap();
        let sim = dir.path().join("sim");
        common::echosurf_ok(&[
            OsString::from("simulate"),
            "--phantom".into(),
            "sphere".into(),
            "--frames-per-sweep".into(),
            "8".into(),
            "--width".into(),
            "64".into(),
            "--height".into(),
            "64".into(),
            "--uncompressed".into(),
            "--out".into(),
            sim.clone().into(),
        ]);
        Fixture {
            sequence: sim.join("sim.mha"),
            config: sim.join("sim_config.xml"),
            truth: sim.join("truth.ply"),
            dir,
        }
    }

    fn path(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }

    fn write(&self, name: &str, bytes: impl AsRef<[u8]>) -> PathBuf {
        let path = self.path(name);
        std::fs::write(&path, bytes).unwrap();
        path
    }

    /// The sequence's header text and its pixel bytes.
    fn sequence_parts(&self) -> (String, Vec<u8>) {
        let bytes = std::fs::read(&self.sequence).unwrap();
        let marker = b"ElementDataFile = LOCAL\n";
        let at = bytes
            .windows(marker.len())
            .position(|w| w == marker)
            .expect("LOCAL data")
            + marker.len();
        (
            String::from_utf8(bytes[..at].to_vec()).unwrap(),
            bytes[at..].to_vec(),
        )
    }

    /// A copy of the sequence with its header edited by `edit`.
    fn edited_sequence(&self, name: &str, edit: impl Fn(&str) -> String) -> PathBuf {
        let (header, data) = self.sequence_parts();
        let mut bytes = edit(&header).into_bytes();
        bytes.extend_from_slice(&data);
        self.write(name, bytes)
    }

    /// A copy of the calibration with `edit` applied to its text.
    fn edited_config(&self, name: &str, edit: impl Fn(&str) -> String) -> PathBuf {
        let text = std::fs::read_to_string(&self.config).unwrap();
        self.write(name, edit(&text))
    }
}

/// One hostile run: the arguments, the files it reads (for the memory bound), what stderr must name
/// (the file) and say (one of the problem words, case-insensitive).
struct Case {
    name: String,
    args: Vec<OsString>,
    inputs: Vec<PathBuf>,
    names: String,
    problem: Vec<&'static str>,
}

fn case<A: Into<OsString> + Clone>(
    name: &str,
    args: &[A],
    inputs: &[&Path],
    names: impl AsRef<Path>,
    problem: &[&'static str],
) -> Case {
    Case {
        name: name.to_string(),
        args: args.iter().cloned().map(Into::into).collect(),
        inputs: inputs.iter().map(|p| p.to_path_buf()).collect(),
        names: names.as_ref().display().to_string(),
        problem: problem.to_vec(),
    }
}

/// Runs `args` under GNU time where available; the output and the peak RSS in bytes.
fn run_measured(args: &[OsString], time_file: &Path) -> (std::process::Output, Option<u64>) {
    let _ = std::fs::remove_file(time_file);
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
        .stdin(Stdio::null())
        .output()
        .unwrap();
    let peak = std::fs::read_to_string(time_file)
        .ok()
        .and_then(|t| t.lines().last()?.trim().parse::<u64>().ok())
        .map(|kib| kib * 1024);
    (output, peak)
}

/// Runs every case; returns how many ran. Fails listing every case that did not refuse cleanly.
fn refuse_all(cases: &[Case], scratch: &Path) -> usize {
    let time_file = scratch.join("time.txt");
    let mut failures = Vec::new();
    for case in cases {
        let start = Instant::now();
        let (output, peak) = run_measured(&case.args, &time_file);
        let seconds = start.elapsed().as_secs_f64();
        let stderr = String::from_utf8_lossy(&output.stderr);
        let input_bytes: u64 = case
            .inputs
            .iter()
            .filter_map(|p| std::fs::metadata(p).ok())
            .map(|m| m.len())
            .sum();
        let bound = 2 * input_bytes + FIXED_BUDGET_BYTES;
        eprintln!(
            "{:44} {:>7.1} ms  peak {:>7} KiB  exit {:?}  {}",
            case.name,
            seconds * 1e3,
            peak.map(|b| (b / 1024).to_string())
                .unwrap_or_else(|| "?".into()),
            output.status.code(),
            stderr.lines().last().unwrap_or("")
        );
        let fail = |why: String| format!("{}: {why}\n  stderr: {stderr}", case.name);
        if !matches!(output.status.code(), Some(1 | 2)) {
            failures.push(fail(format!("exit {:?}, not 1 or 2", output.status)));
        }
        if stderr.contains("panicked") || stderr.contains("overflow") {
            failures.push(fail("panicked or overflowed".into()));
        }
        if !stderr.contains(&case.names) {
            failures.push(fail(format!("stderr does not name {}", case.names)));
        }
        let lower = stderr.to_ascii_lowercase();
        if !case
            .problem
            .iter()
            .any(|w| lower.contains(&w.to_ascii_lowercase()))
        {
            failures.push(fail(format!("stderr says none of {:?}", case.problem)));
        }
        if seconds > MAX_SECONDS {
            failures.push(fail(format!("took {seconds:.1} s")));
        }
        if let Some(peak) = peak
            && peak > bound
        {
            failures.push(fail(format!("peak RSS {peak} B over {bound} B")));
        }
    }
    assert!(
        failures.is_empty(),
        "{} of {} cases failed:\n{}",
        failures.len(),
        cases.len(),
        failures.join("\n")
    );
    cases.len()
}

/// Writes an `extract --config` file at `file` holding `toml` then `[outputs] model = model` (the
/// model has no flag) and returns the file.
fn model_config(file: PathBuf, toml: &str, model: &Path) -> PathBuf {
    std::fs::write(
        &file,
        format!("{toml}\n[outputs]\nmodel = {:?}\n", model.to_str().unwrap()),
    )
    .unwrap();
    file
}

fn os(parts: &[&dyn AsRefOs]) -> Vec<OsString> {
    parts.iter().map(|p| p.os()).collect()
}

/// Anything that is an argument: `&str` or a path.
trait AsRefOs {
    fn os(&self) -> OsString;
}

impl AsRefOs for &str {
    fn os(&self) -> OsString {
        OsString::from(self)
    }
}

impl AsRefOs for PathBuf {
    fn os(&self) -> OsString {
        self.clone().into_os_string()
    }
}

impl AsRefOs for &Path {
    fn os(&self) -> OsString {
        self.as_os_str().to_owned()
    }
}

/// A named pipe made by `mkfifo`, if the tool is there.
fn fifo(path: &Path) -> bool {
    Command::new("mkfifo")
        .arg(path)
        .status()
        .is_ok_and(|s| s.success())
}

/// A v1 `.esrbf` model (the layout of `RbfModel::save`) with these centres and coefficients.
fn model_bytes(centres: &[[f64; 3]], coefficients: &[f64], constant: f64) -> Vec<u8> {
    let mut bytes = b"ESRBF\r\n\x1a".to_vec();
    bytes.extend_from_slice(&1u32.to_le_bytes());
    bytes.extend_from_slice(&(centres.len() as u64).to_le_bytes());
    for v in [0.0, 1e-3, 0.0, 0.0, 0.0, constant, 0.0, 0.0, 0.0] {
        bytes.extend_from_slice(&f64::to_le_bytes(v));
    }
    for c in centres {
        for v in c {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    for l in coefficients {
        bytes.extend_from_slice(&l.to_le_bytes());
    }
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in &bytes {
        h ^= b as u64;
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    bytes.extend_from_slice(&h.to_le_bytes());
    bytes
}

/// Eight centres on a cube's corners, the cube 20 mm wide around the origin.
fn cube_centres() -> Vec<[f64; 3]> {
    let mut c = Vec::new();
    for x in [-10.0, 10.0] {
        for y in [-10.0, 10.0] {
            for z in [-10.0, 10.0] {
                c.push([x, y, z]);
            }
        }
    }
    c
}

/// A point cloud PLY (ASCII) of a few points.
fn cloud_text(points: &[[f64; 3]]) -> String {
    let mut t = format!(
        "ply\nformat ascii 1.0\nelement vertex {}\nproperty float x\nproperty float y\n\
         property float z\nproperty float intensity\nend_header\n",
        points.len()
    );
    for p in points {
        t.push_str(&format!("{} {} {} 1\n", p[0], p[1], p[2]));
    }
    t
}

/// A PNG whose header claims `width x height` but whose data is a few junk bytes.
fn lying_png(width: u32, height: u32) -> Vec<u8> {
    let chunk = |kind: &[u8], data: &[u8]| {
        let mut c = (data.len() as u32).to_be_bytes().to_vec();
        c.extend_from_slice(kind);
        c.extend_from_slice(data);
        let mut crc = flate2::Crc::new();
        crc.update(kind);
        crc.update(data);
        c.extend_from_slice(&crc.sum().to_be_bytes());
        c
    };
    let mut ihdr = width.to_be_bytes().to_vec();
    ihdr.extend_from_slice(&height.to_be_bytes());
    ihdr.extend_from_slice(&[8, 0, 0, 0, 0]);
    let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
    png.extend(chunk(b"IHDR", &ihdr));
    png.extend(chunk(b"IDAT", &[0x78, 0x9c, 0x03, 0x00]));
    png.extend(chunk(b"IEND", &[]));
    png
}

/// A grey PNG mask of the fixture's frame size, a disc of `value` on 0, at 8 or 16 bits.
fn disc_png(path: &Path, value: u16, sixteen: bool) {
    let (w, h) = (64u32, 64u32);
    let inside = |x: u32, y: u32| {
        let (dx, dy) = (x as f64 - 32.0, y as f64 - 40.0);
        dx * dx + dy * dy < 15.0 * 15.0
    };
    let mut encoder = png::Encoder::new(std::fs::File::create(path).unwrap(), w, h);
    encoder.set_color(png::ColorType::Grayscale);
    let mut data = Vec::new();
    for y in 0..h {
        for x in 0..w {
            let v = if inside(x, y) { value } else { 0 };
            if sixteen {
                data.extend_from_slice(&v.to_be_bytes());
            } else {
                data.push(v as u8);
            }
        }
    }
    encoder.set_depth(if sixteen {
        png::BitDepth::Sixteen
    } else {
        png::BitDepth::Eight
    });
    let mut writer = encoder.write_header().unwrap();
    writer.write_image_data(&data).unwrap();
}

/// Class 1: outputs that are not ours to replace, refused before any work.
#[test]
fn outputs_that_are_special_files_links_to_inputs_or_unwritable_are_refused() {
    let f = Fixture::new();
    let (seq, config) = (&f.sequence, &f.config);
    let out = f.path("out");
    std::fs::create_dir(&out).unwrap();
    let extract = |rest: &[&dyn AsRefOs]| {
        let mut a = os(&[&"extract", seq, &"--calibration", config]);
        a.extend(os(rest));
        a
    };
    let mut cases = Vec::new();
    let pipe = out.join("pipe.ply");
    let have_fifo = fifo(&pipe);
    if have_fifo {
        cases.push(case(
            "extract --out FIFO",
            &extract(&[&"--out", &pipe]),
            &[seq],
            &pipe,
            &["named pipe"],
        ));
        let report = out.join("report-pipe.json");
        assert!(fifo(&report));
        let mesh = out.join("m.ply");
        cases.push(case(
            "extract --report FIFO",
            &extract(&[&"--out", &mesh, &"--report", &report]),
            &[seq],
            &report,
            &["named pipe"],
        ));
        let model = out.join("model-pipe.esrbf");
        assert!(fifo(&model));
        let with_model = model_config(out.join("model-pipe.toml"), "", &model);
        cases.push(case(
            "extract outputs.model FIFO",
            &extract(&[&"--out", &mesh, &"--config", &with_model]),
            &[seq],
            &model,
            &["named pipe"],
        ));
        let masks = out.join("masks-pipe.mha");
        assert!(fifo(&masks));
        let args = os(&[
            &"segment",
            seq,
            &"--calibration",
            config,
            &"--auto-init",
            &"--out",
            &masks,
        ]);
        cases.push(case(
            "segment --out FIFO",
            &args,
            &[seq],
            &masks,
            &["named pipe"],
        ));
        let volume = out.join("volume-pipe.mha");
        assert!(fifo(&volume));
        let args = os(&[
            &"reconstruct",
            seq,
            &"--calibration",
            config,
            &"--out",
            &volume,
        ]);
        cases.push(case(
            "reconstruct --out FIFO",
            &args,
            &[seq],
            &volume,
            &["named pipe"],
        ));
        let map = out.join("map-pipe.ply");
        assert!(fifo(&map));
        let args = os(&[&"compare", &f.truth, &f.truth, &"--error-map", &map]);
        cases.push(case(
            "compare --error-map FIFO",
            &args,
            &[&f.truth],
            &map,
            &["named pipe"],
        ));
        let frame = out.join("frame-pipe.png");
        assert!(fifo(&frame));
        let args = os(&[&"inspect", seq, &"--frame-png", &frame]);
        cases.push(case(
            "inspect --frame-png FIFO",
            &args,
            &[seq],
            &frame,
            &["named pipe"],
        ));
    }
    #[cfg(unix)]
    {
        let socket = out.join("socket.json");
        let _listener = std::os::unix::net::UnixListener::bind(&socket).unwrap();
        let mesh = out.join("m.ply");
        cases.push(case(
            "extract --report socket",
            &extract(&[&"--out", &mesh, &"--report", &socket]),
            &[seq],
            &socket,
            &["socket"],
        ));
        std::mem::forget(_listener);
    }
    let folder = out.join("folder.ply");
    std::fs::create_dir(&folder).unwrap();
    cases.push(case(
        "extract --out folder",
        &extract(&[&"--out", &folder]),
        &[seq],
        &folder,
        &["folder"],
    ));
    // /proc takes no new files, even from root: the folder check must try for real.
    let proc_mesh = PathBuf::from("/proc/echosurf-mesh.ply");
    if Path::new("/proc/self").exists() {
        cases.push(case(
            "extract --out in read-only /proc",
            &extract(&[&"--out", &proc_mesh]),
            &[seq],
            &proc_mesh,
            &["cannot create files"],
        ));
        let proc_report = PathBuf::from("/proc/echosurf-report.json");
        let mesh = out.join("m.ply");
        cases.push(case(
            "extract --report in read-only /proc",
            &extract(&[&"--out", &mesh, &"--report", &proc_report]),
            &[seq],
            &proc_report,
            &["cannot create files"],
        ));
        let proc_volume = PathBuf::from("/proc/echosurf-volume.mha");
        let args = os(&[
            &"reconstruct",
            seq,
            &"--calibration",
            config,
            &"--out",
            &proc_volume,
        ]);
        cases.push(case(
            "reconstruct --out in /proc",
            &args,
            &[seq],
            &proc_volume,
            &["cannot create files"],
        ));
        let proc_model = PathBuf::from("/proc/echosurf.esrbf");
        let cloud = f.write("cloud.ply", cloud_text(&cube_centres()));
        let args = os(&[&"fit", &cloud, &"--out", &proc_model]);
        cases.push(case(
            "fit --out in /proc",
            &args,
            &[&cloud],
            &proc_model,
            &["cannot create files"],
        ));
    }
    let missing = out.join("missing").join("mesh.ply");
    cases.push(case(
        "extract --out in a missing folder",
        &extract(&[&"--out", &missing]),
        &[seq],
        out.join("missing"),
        &["does not exist"],
    ));
    // A hard link and a symbolic link to the sequence are the sequence.
    let hard = out.join("hard.mha");
    std::fs::hard_link(seq, &hard).unwrap();
    let args = os(&[
        &"segment",
        seq,
        &"--calibration",
        config,
        &"--auto-init",
        &"--out",
        &hard,
    ]);
    cases.push(case(
        "segment --out hard link to input",
        &args,
        &[seq],
        &hard,
        &["an input"],
    ));
    #[cfg(unix)]
    {
        let link = out.join("link.mha");
        std::os::unix::fs::symlink(seq, &link).unwrap();
        let args = os(&[
            &"reconstruct",
            seq,
            &"--calibration",
            config,
            &"--out",
            &link,
        ]);
        cases.push(case(
            "reconstruct --out symlink to input",
            &args,
            &[seq],
            &link,
            &["an input"],
        ));
        let config_link = out.join("config-link.json");
        std::os::unix::fs::symlink(config, &config_link).unwrap();
        let mesh = out.join("m.ply");
        cases.push(case(
            "extract --report symlink to the config",
            &extract(&[&"--out", &mesh, &"--report", &config_link]),
            &[seq],
            &config_link,
            &["an input"],
        ));
        let dangling = out.join("dangling.ply");
        std::os::unix::fs::symlink(out.join("nowhere").join("x.ply"), &dangling).unwrap();
        cases.push(case(
            "extract --out link into a missing folder",
            &extract(&[&"--out", &dangling]),
            &[seq],
            &dangling,
            &["does not exist"],
        ));
    }
    // A PNG preview into a device refuses by its name; the device stays.
    let null = PathBuf::from("/dev/null");
    cases.push(case(
        "extract --preview /dev/null (not .png)",
        &extract(&[&"--out", &out.join("m.ply"), &"--preview", &null]),
        &[seq],
        &null,
        &["must end in .png"],
    ));
    let cloud = f.write("points.ply", cloud_text(&cube_centres()));
    let model = f.write("cube.esrbf", model_bytes(&cube_centres(), &[0.0; 8], 1.0));
    let args = os(&[&"eval", &model, &cloud, &"--out", &cloud]);
    cases.push(case(
        "eval --out = its points",
        &args,
        &[&cloud],
        &cloud,
        &["an input"],
    ));
    let args = os(&[&"fit", &cloud, &"--out", &cloud]);
    cases.push(case(
        "fit --out = its points",
        &args,
        &[&cloud],
        &cloud,
        &["an input"],
    ));
    let args = os(&[&"surface", &model, &"--iso", &"1", &"--out", &model]);
    cases.push(case(
        "surface --out = its model",
        &args,
        &[&model],
        &model,
        &["an input", "must end"],
    ));
    // simulate: its own phantom mesh is an input; bad names and a file as the folder are refused.
    let phantom_dir = f.path("phantom");
    std::fs::create_dir(&phantom_dir).unwrap();
    let phantom = phantom_dir.join("truth.ply");
    std::fs::copy(&f.truth, &phantom).unwrap();
    let args = os(&[&"simulate", &"--phantom", &phantom, &"--out", &phantom_dir]);
    cases.push(case(
        "simulate into its phantom's folder",
        &args,
        &[&phantom],
        &phantom,
        &["an input"],
    ));
    let args = os(&[&"simulate", &"--name", &"../up", &"--out", &out]);
    cases.push(case(
        "simulate --name ../up",
        &args,
        &[],
        "../up",
        &["plain file name"],
    ));
    let args = os(&[&"simulate", &"--out", &f.truth]);
    cases.push(case(
        "simulate --out a file",
        &args,
        &[],
        &f.truth,
        &["not a folder"],
    ));
    let before = std::fs::read(&phantom).unwrap();
    let ran = refuse_all(&cases, f.dir.path());
    assert_eq!(
        std::fs::read(&phantom).unwrap(),
        before,
        "the phantom changed"
    );
    assert!(ran >= if have_fifo { 25 } else { 18 }, "{ran} cases");
    // Nothing was written anywhere: the out folder holds only what the test put there.
    let mut left: Vec<String> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| !n.contains("pipe") && n != "socket.json")
        .collect();
    left.sort();
    assert_eq!(
        left,
        [
            "config-link.json",
            "dangling.ply",
            "folder.ply",
            "hard.mha",
            "link.mha"
        ]
    );
}

/// A device as an output is written directly and stays a device; a symbolic link's target gets the
/// data and the link stays; `simulate --name` keeps a second run's truth apart from the first's.
#[test]
fn devices_are_written_directly_links_followed_and_simulations_kept_apart() {
    let f = Fixture::new();
    let out = f.path("out");
    std::fs::create_dir(&out).unwrap();
    let mesh = out.join("mesh.ply");
    let target = out.join("report-target.json");
    std::fs::write(&target, b"old").unwrap();
    let link = out.join("report-link.json");
    #[cfg(unix)]
    std::os::unix::fs::symlink("report-target.json", &link).unwrap();
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        let null = Path::new("/dev/null");
        let kind = |p: &Path| std::fs::symlink_metadata(p).unwrap().file_type();
        assert!(kind(null).is_char_device());
        common::echosurf_ok(&os(&[
            &"extract",
            &f.sequence,
            &"--calibration",
            &f.config,
            &"--out",
            &mesh,
            &"--report",
            &PathBuf::from("/dev/null"),
            &"--config",
            &model_config(out.join("link.toml"), "", &link),
        ]));
        assert!(kind(null).is_char_device(), "/dev/null was replaced");
        assert!(kind(&link).is_symlink(), "the link was replaced");
        let model = std::fs::read(&target).unwrap();
        assert!(
            model.starts_with(b"ESRBF"),
            "the link's target did not get the model"
        );
        // /dev/stdout as the report: the JSON arrives on standard output.
        let run = common::echosurf_ok(&os(&[
            &"extract",
            &f.sequence,
            &"--calibration",
            &f.config,
            &"--out",
            &mesh,
            &"--report",
            &PathBuf::from("/dev/stdout"),
        ]));
        let stdout = String::from_utf8_lossy(&run.stdout);
        assert!(stdout.contains("\"stages\""), "{stdout}");
    }
    // Two simulations with different names in one folder: both truths stay.
    let both = f.path("both");
    for name in ["first", "second"] {
        common::echosurf_ok(&os(&[
            &"simulate",
            &"--phantom",
            &"sphere",
            &"--frames-per-sweep",
            &"4",
            &"--width",
            &"32",
            &"--height",
            &"32",
            &"--name",
            &name,
            &"--seed",
            &if name == "first" { "1" } else { "2" },
            &"--out",
            &both,
        ]));
    }
    for name in ["first", "second"] {
        for file in [
            format!("{name}.mha"),
            format!("{name}_config.xml"),
            format!("{name}_truth.ply"),
            format!("{name}_phantom.json"),
        ] {
            assert!(both.join(&file).exists(), "{file} missing");
        }
    }
    assert!(!both.join("truth.ply").exists());
    assert_ne!(
        std::fs::read(both.join("first.mha")).unwrap(),
        std::fs::read(both.join("second.mha")).unwrap()
    );
}

/// Class 2: parser limits and standard-output faults.
#[test]
fn deep_xml_and_failing_standard_output_end_cleanly() {
    let f = Fixture::new();
    let seq = &f.sequence;
    let out = f.path("out");
    std::fs::create_dir(&out).unwrap();
    let deep = |n: usize| {
        format!(
            "<PlusConfiguration>{}{}</PlusConfiguration>",
            "<a>".repeat(n),
            "</a>".repeat(n)
        )
    };
    let deep_config = f.write("deep.xml", deep(20_000));
    let deeper_config = f.write("deeper.xml", deep(200_000));
    let mut cases = vec![
        case(
            "reconstruct: config 20000 deep",
            &os(&[
                &"reconstruct",
                seq,
                &"--calibration",
                &deep_config,
                &"--out",
                &out.join("v.mha"),
            ]),
            &[seq, &deep_config],
            &deep_config,
            &["nest"],
        ),
        case(
            "extract: config 200000 deep",
            &os(&[
                &"extract",
                seq,
                &"--calibration",
                &deeper_config,
                &"--out",
                &out.join("m.ply"),
            ]),
            &[seq, &deeper_config],
            &deeper_config,
            &["nest"],
        ),
        case(
            "inspect: config 20000 deep",
            &os(&[&"inspect", seq, &"--calibration", &deep_config]),
            &[seq, &deep_config],
            &deep_config,
            &["nest"],
        ),
    ];
    // Deep in an attribute-heavy disguise: quotes holding `>` and self-closing tags between.
    let disguised = f.write(
        "disguised.xml",
        format!(
            "<PlusConfiguration>{}{}</PlusConfiguration>",
            "<a x=\"1>2\"><b/>".repeat(5_000),
            "</a>".repeat(5_000)
        ),
    );
    cases.push(case(
        "segment: disguised deep config",
        &os(&[
            &"segment",
            seq,
            &"--calibration",
            &disguised,
            &"--auto-init",
            &"--out",
            &out.join("k.mha"),
        ]),
        &[seq, &disguised],
        &disguised,
        &["nest"],
    ));
    let many = f.write(
        "many.xml",
        format!(
            "<PlusConfiguration>{}</PlusConfiguration>",
            "<a/>".repeat(200_000)
        ),
    );
    cases.push(case(
        "inspect: config with 200k nodes",
        &os(&[&"inspect", seq, &"--calibration", &many]),
        &[seq, &many],
        &many,
        &["limit"],
    ));
    let laughs = f.write(
        "laughs.xml",
        "<?xml version=\"1.0\"?><!DOCTYPE l [<!ENTITY a \"aaaaaaaaaa\"><!ENTITY b \"&a;&a;&a;&a;&a;&a;&a;&a;\">\
         <!ENTITY c \"&b;&b;&b;&b;&b;&b;&b;&b;\">]><PlusConfiguration>&c;</PlusConfiguration>",
    );
    cases.push(case(
        "inspect: config with a DTD",
        &os(&[&"inspect", seq, &"--calibration", &laughs]),
        &[seq, &laughs],
        &laughs,
        &["dtd", "well-formed"],
    ));
    let garbage = f.write("garbage.xml", "<PlusConfiguration><a></b>");
    cases.push(case(
        "reconstruct: ill-formed config",
        &os(&[
            &"reconstruct",
            seq,
            &"--calibration",
            &garbage,
            &"--out",
            &out.join("v.mha"),
        ]),
        &[seq, &garbage],
        &garbage,
        &["well-formed"],
    ));
    let ran = refuse_all(&cases, f.dir.path());
    assert_eq!(ran, 7);

    // A full disk behind standard output: a clean error, for the text, JSON and table printers.
    if Path::new("/dev/full").exists() {
        for args in [
            os(&[&"inspect", seq]),
            os(&[&"inspect", seq, &"--json"]),
            os(&[&"compare", &f.truth, &f.truth, &"--samples-per-mm2", &"1"]),
        ] {
            let full = std::fs::OpenOptions::new()
                .write(true)
                .open("/dev/full")
                .unwrap();
            let output = Command::new(BIN).args(&args).stdout(full).output().unwrap();
            let stderr = String::from_utf8_lossy(&output.stderr);
            assert_eq!(output.status.code(), Some(1), "{args:?}: {stderr}");
            assert!(stderr.contains("writing to standard output"), "{stderr}");
            assert!(stderr.contains("No space left"), "{stderr}");
            assert!(!stderr.contains("panicked"), "{stderr}");
        }
    }
    // A reader that is gone before anything is printed (`| head -c 0`): EPIPE, and the run ends
    // quietly (the sequence takes far longer to read than closing the pipe).
    for json in [true, false] {
        let mut args = os(&[&"inspect", seq]);
        if json {
            args.push("--json".into());
        }
        let mut child = Command::new(BIN)
            .args(&args)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        drop(child.stdout.take());
        let output = child.wait_with_output().unwrap();
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(output.status.success(), "{:?}: {stderr}", output.status);
        assert!(stderr.is_empty(), "{stderr}");
    }
}

/// Class 3: nonsense the readers used to accept.
#[test]
fn nonsense_geometry_pixels_and_models_are_refused_or_warned() {
    let f = Fixture::new();
    let (seq, config) = (&f.sequence, &f.config);
    let out = f.path("out");
    std::fs::create_dir(&out).unwrap();
    let bottom_row = |text: &str, row: &str| text.replace(" 0 0 0 1\"", &format!(" {row}\""));
    let mut cases = Vec::new();
    for (k, row) in ["0 0 0.5 1", "0 0 0 2", "1 0 0 1", "0 0 0 0"]
        .iter()
        .enumerate()
    {
        let bad = f.edited_config(&format!("projective{k}.xml"), |t| bottom_row(t, row));
        cases.push(case(
            &format!("reconstruct: ImageToProbe bottom row {row}"),
            &os(&[
                &"reconstruct",
                seq,
                &"--calibration",
                &bad,
                &"--out",
                &out.join("v.mha"),
            ]),
            &[seq, &bad],
            &bad,
            &["not affine"],
        ));
    }
    let bad = f.edited_config("projective-extract.xml", |t| bottom_row(t, "0 0 0.5 1"));
    cases.push(case(
        "extract: ImageToProbe not affine",
        &os(&[
            &"extract",
            seq,
            &"--calibration",
            &bad,
            &"--out",
            &out.join("m.ply"),
        ]),
        &[seq, &bad],
        &bad,
        &["not affine"],
    ));
    // A tracked frame's ProbeToTracker with a projective bottom row, in frames 0, 3 and the last.
    for frame in [0usize, 3, 39] {
        let key = format!("Seq_Frame{frame:04}_ProbeToTrackerTransform = ");
        let bad = f.edited_sequence(&format!("projective{frame}.mha"), |h| {
            h.lines()
                .map(|l| {
                    if l.starts_with(&key) {
                        l.replace(" 0 0 0 1", " 0 0.25 0 1")
                    } else {
                        l.to_string()
                    }
                })
                .collect::<Vec<_>>()
                .join("\n")
                + "\n"
        });
        let frame_words: &'static str = Box::leak(format!("frame {frame}:").into_boxed_str());
        cases.push(case(
            &format!("inspect: frame {frame} ProbeToTracker not affine"),
            &os(&[&"inspect", &bad, &"--calibration", config]),
            &[&bad],
            &bad,
            &[frame_words],
        ));
    }
    let bad = f.edited_sequence("projective-extract.mha", |h| {
        let key = "Seq_Frame0007_ProbeToTrackerTransform = ";
        let line = h.lines().find(|l| l.starts_with(key)).unwrap();
        h.replace(line, &line.replace(" 0 0 0 1", " 0.1 0 0 1"))
    });
    cases.push(case(
        "extract: frame 7 transform not affine",
        &os(&[
            &"extract",
            &bad,
            &"--calibration",
            config,
            &"--out",
            &out.join("m.ply"),
        ]),
        &[&bad],
        &bad,
        &["not affine"],
    ));
    let twice = f.edited_config("twice.xml", |t| {
        let line = t
            .lines()
            .find(|l| l.contains("From=\"Image\""))
            .unwrap()
            .to_string();
        t.replace(&line, &format!("{line}\n{line}"))
    });
    cases.push(case(
        "reconstruct: two Image->Probe",
        &os(&[
            &"reconstruct",
            seq,
            &"--calibration",
            &twice,
            &"--out",
            &out.join("v.mha"),
        ]),
        &[seq, &twice],
        &twice,
        &["two image->probe"],
    ));
    cases.push(case(
        "inspect: two Image->Probe",
        &os(&[&"inspect", seq, &"--calibration", &twice]),
        &[seq, &twice],
        &twice,
        &["lines 4 and 5"],
    ));
    for (name, root) in [
        ("root-config.xml", "Configuration"),
        ("root-svg.xml", "svg"),
    ] {
        let bad = f.edited_config(name, |t| t.replace("PlusConfiguration", root));
        cases.push(case(
            &format!("extract: root <{root}>"),
            &os(&[
                &"extract",
                seq,
                &"--calibration",
                &bad,
                &"--out",
                &out.join("m.ply"),
            ]),
            &[seq, &bad],
            &bad,
            &["not <plusconfiguration>"],
        ));
    }
    // MET_FLOAT frames with a NaN, an infinity: refused, counted, the first frame named.
    let (header, data) = f.sequence_parts();
    let float_header = header.replace("MET_UCHAR", "MET_FLOAT");
    for (name, value, at) in [
        ("nan.mha", f32::NAN, 64 * 64 * 5 + 7),
        ("inf.mha", f32::INFINITY, 3),
        ("neg-inf.mha", f32::NEG_INFINITY, data.len() - 1),
    ] {
        let mut bytes = float_header.clone().into_bytes();
        for (i, &b) in data.iter().enumerate() {
            let v = if i == at { value } else { b as f32 };
            bytes.extend_from_slice(&v.to_le_bytes());
        }
        let path = f.write(name, bytes);
        let frame = at / (64 * 64);
        let said: &'static str = Box::leak(
            format!(
                "1 of {} met_float pixels are nan or infinite (the first in frame {frame})",
                data.len()
            )
            .into_boxed_str(),
        );
        cases.push(case(
            &format!("inspect: MET_FLOAT with {value}"),
            &os(&[&"inspect", &path]),
            &[&path],
            &path,
            &[said],
        ));
        if name == "nan.mha" {
            cases.push(case(
                "reconstruct: MET_FLOAT with NaN",
                &os(&[
                    &"reconstruct",
                    &path,
                    &"--calibration",
                    config,
                    &"--out",
                    &out.join("v.mha"),
                ]),
                &[&path],
                &path,
                &["nan or infinite"],
            ));
        }
    }
    // Models whose coefficients overflow: eval and surface refuse rather than print inf.
    let cloud = f.write(
        "points.ply",
        cloud_text(&[[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]]),
    );
    for (name, l) in [("huge.esrbf", 1e308), ("big.esrbf", 1e300)] {
        let coefficients: Vec<f64> = (0..8).map(|i| if i % 2 == 0 { l } else { -l }).collect();
        let model = f.write(name, model_bytes(&cube_centres(), &coefficients, 0.0));
        cases.push(case(
            &format!("eval: coefficients {l:e}"),
            &os(&[&"eval", &model, &cloud, &"--out", &out.join("values.ply")]),
            &[&model, &cloud],
            &model,
            &["out of range"],
        ));
        if l > 1e307 {
            cases.push(case(
                &format!("surface: coefficients {l:e}"),
                &os(&[
                    &"surface",
                    &model,
                    &"--iso",
                    &"1",
                    &"--out",
                    &out.join("s.ply"),
                ]),
                &[&model],
                &model,
                &["out of range"],
            ));
        }
    }
    let nan_model = model_bytes(&cube_centres(), &[f64::NAN; 8], 0.0);
    let nan_path = f.write("nan.esrbf", nan_model);
    cases.push(case(
        "eval: NaN coefficients",
        &os(&[
            &"eval",
            &nan_path,
            &cloud,
            &"--out",
            &out.join("values.ply"),
        ]),
        &[&nan_path],
        &nan_path,
        &["finite"],
    ));
    let ran = refuse_all(&cases, f.dir.path());
    assert!(ran >= 21, "{ran}");
    assert_eq!(
        std::fs::read_dir(&out).unwrap().count(),
        0,
        "a refusal wrote"
    );

    // Timestamps that go backwards: a warning naming the file and where, the run goes on.
    let backwards = f.edited_sequence("backwards.mha", |h| {
        h.replace(
            "Seq_Frame0005_Timestamp = 0.25",
            "Seq_Frame0005_Timestamp = 0.01",
        )
    });
    let run = common::echosurf_ok(&os(&[&"inspect", &backwards, &"--calibration", config]));
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(
        stderr.contains(&format!(
            "warning: {}: timestamps go backwards 1 time(s), first at frame 5",
            backwards.display()
        )),
        "{stderr}"
    );

    // A 16-bit PNG mask with value 1 is the same band as an 8-bit mask with 255.
    let (m8, m16) = (f.path("band8.png"), f.path("band16.png"));
    disc_png(&m8, 255, false);
    disc_png(&m16, 1, true);
    let masks = |init: &Path, name: &str| {
        let path = out.join(name);
        common::echosurf_ok(&os(&[
            &"segment",
            seq,
            &"--calibration",
            config,
            &"--init",
            &init,
            &"--out",
            &path,
        ]));
        std::fs::read(path).unwrap()
    };
    assert_eq!(masks(&m8, "masks8.mha"), masks(&m16, "masks16.mha"));
}

/// Class 4: inputs that ask for unbounded memory or time, refused from their headers and sizes.
#[test]
fn unbounded_memory_and_time_are_refused_up_front() {
    let f = Fixture::new();
    let (seq, config) = (&f.sequence, &f.config);
    let out = f.path("out");
    std::fs::create_dir(&out).unwrap();
    let mut cases = Vec::new();
    for (name, w, h) in [
        ("huge-mask.png", 16384, 16384),
        ("wide-mask.png", 1 << 30, 1),
        ("small-mask.png", 32, 32),
    ] {
        let png = f.write(name, lying_png(w, h));
        cases.push(case(
            &format!("extract --init {w}x{h} PNG"),
            &os(&[
                &"extract",
                seq,
                &"--calibration",
                config,
                &"--init",
                &png,
                &"--out",
                &out.join("m.ply"),
            ]),
            &[seq, &png],
            &png,
            // The PNG decoder's own limit on a row's size can speak first.
            &["but the frames are 64x64", "limits are exceeded"],
        ));
    }
    let ply_header = |format: &str, faces: u64| {
        format!(
            "ply\nformat {format} 1.0\nelement vertex 3\nproperty float x\nproperty float y\n\
             property float z\nelement face {faces}\nproperty list uchar int vertex_indices\nend_header\n"
        )
    };
    let ascii = f.write(
        "50M-faces-ascii.ply",
        ply_header("ascii", 50_000_000) + "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n",
    );
    let mut binary = ply_header("binary_little_endian", 50_000_000).into_bytes();
    for v in [0f32, 0., 0., 1., 0., 0., 0., 1., 0.] {
        binary.extend_from_slice(&v.to_le_bytes());
    }
    binary.push(3);
    for i in [0i32, 1, 2] {
        binary.extend_from_slice(&i.to_le_bytes());
    }
    let binary = f.write("50M-faces-binary.ply", binary);
    let mut stl = vec![0u8; 80];
    stl.extend_from_slice(&50_000_000u32.to_le_bytes());
    stl.extend_from_slice(&[0u8; 50]);
    let stl = f.write("50M-triangles.stl", stl);
    for mesh in [&ascii, &binary, &stl] {
        cases.push(case(
            &format!("compare: {}", mesh.file_name().unwrap().to_string_lossy()),
            &os(&[&"compare", mesh, &f.truth]),
            &[mesh, &f.truth],
            mesh,
            &["promises", "claims", "50000000", "truncated", "ends"],
        ));
        cases.push(case(
            &format!("render: {}", mesh.file_name().unwrap().to_string_lossy()),
            &os(&[&"render", mesh, &"--out", &out.join("view.png")]),
            &[mesh],
            mesh,
            &["promises", "claims", "50000000", "truncated", "ends"],
        ));
    }
    let huge_vertices = f.write(
        "vertices.ply",
        "ply\nformat binary_little_endian 1.0\nelement vertex 4000000000\nproperty double x\n\
         property double y\nproperty double z\nend_header\n",
    );
    cases.push(case(
        "fit: 4e9 vertices claimed",
        &os(&[&"fit", &huge_vertices, &"--out", &out.join("model.esrbf")]),
        &[&huge_vertices],
        &huge_vertices,
        &["promises", "claims", "bytes"],
    ));
    for (density, max) in [
        ("1e12", "18446744073709551615"),
        ("1e300", "18446744073709551615"),
        ("1e9", "1000000000000"),
    ] {
        cases.push(case(
            &format!("compare --samples-per-mm2 {density} --max-samples {max}"),
            &os(&[
                &"compare",
                &f.truth,
                &f.truth,
                &"--samples-per-mm2",
                &density,
                &"--max-samples",
                &max,
            ]),
            &[&f.truth],
            &f.truth,
            &["memory budget", "--samples-per-mm2"],
        ));
    }
    cases.push(case(
        "compare --memory-budget 1",
        &os(&[&"compare", &f.truth, &f.truth, &"--memory-budget", &"1"]),
        &[&f.truth],
        &f.truth,
        &["memory budget is 1 MB"],
    ));
    // A clip rectangle that misses the 64 x 64 frames.
    let clip = |origin: &str, size: &str| {
        f.edited_config(&format!("clip-{}.xml", origin.replace(' ', "-")), |t| {
            t.replace(
                "</PlusConfiguration>",
                &format!(
                    "<VolumeReconstruction OutputSpacing=\"0.5 0.5 0.5\" ClipRectangleOrigin=\"{origin}\" \
                     ClipRectangleSize=\"{size}\"/></PlusConfiguration>"
                ),
            )
        })
    };
    for (origin, size) in [
        ("64 0", "10 10"),
        ("0 64", "10 10"),
        ("100000 100000", "5 5"),
    ] {
        let bad = clip(origin, size);
        cases.push(case(
            &format!("reconstruct: clip at {origin}"),
            &os(&[
                &"reconstruct",
                seq,
                &"--calibration",
                &bad,
                &"--out",
                &out.join("v.mha"),
            ]),
            &[seq, &bad],
            &bad,
            &["clip rectangle"],
        ));
    }
    let bad = clip("70 70", "10 10");
    for command in ["extract", "sample", "segment"] {
        let output = if command == "segment" {
            "k.mha"
        } else {
            "k.ply"
        };
        let mut args = os(&[
            &command,
            seq,
            &"--calibration",
            &bad,
            &"--out",
            &out.join(output),
        ]);
        if command != "extract" {
            args.push("--auto-init".into());
        }
        cases.push(case(
            &format!("{command}: clip outside"),
            &args,
            &[seq, &bad],
            &bad,
            &["outside the 64 x 64"],
        ));
    }
    // Levels a model never crosses (its values span 1..1 plus a small slope).
    let model = f.write(
        "flat.esrbf",
        model_bytes(
            &cube_centres(),
            &[1e-3, -1e-3, 1e-3, -1e-3, -1e-3, 1e-3, -1e-3, 1e-3],
            1.0,
        ),
    );
    for level in ["1e6", "-50", "1000"] {
        let iso = format!("--iso={level}");
        cases.push(case(
            &format!("surface --iso {level} never crossed"),
            &os(&[
                &"surface",
                &model,
                &iso.as_str(),
                &"--out",
                &out.join("s.ply"),
            ]),
            &[&model],
            &model,
            &["never crossed"],
        ));
    }
    // --memory-budget on every route (a 0.1 mm lattice or grid, which the default budget allows).
    for method in ["rbf", "voxel"] {
        cases.push(case(
            &format!("extract --method {method} --memory-budget 1"),
            &os(&[
                &"extract",
                seq,
                &"--calibration",
                config,
                &"--method",
                &method,
                &"--resolution",
                &"0.1",
                &"--memory-budget",
                &"1",
                &"--out",
                &out.join("m.ply"),
            ]),
            &[seq],
            seq,
            &["memory budget"],
        ));
    }
    cases.push(case(
        "reconstruct --memory-budget 1 --spacing 0.05",
        &os(&[
            &"reconstruct",
            seq,
            &"--calibration",
            config,
            &"--spacing",
            &"0.05",
            &"--memory-budget",
            &"1",
            &"--out",
            &out.join("v.mha"),
        ]),
        &[seq],
        seq,
        &["memory budget"],
    ));
    // A header that promises gigabytes of pixels the file does not hold.
    let (header, data) = f.sequence_parts();
    let lying = f.write(
        "lying.mha",
        [
            header
                .replace("DimSize = 64 64 40", "DimSize = 100000 100000 1000")
                .into_bytes(),
            data.clone(),
        ]
        .concat(),
    );
    cases.push(case(
        "inspect: DimSize 100000 100000 1000",
        &os(&[&"inspect", &lying]),
        &[&lying],
        &lying,
        &["promises", "too large", "bytes"],
    ));
    let ran = refuse_all(&cases, f.dir.path());
    assert!(ran >= 27, "{ran}");
    let left: Vec<_> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert!(left.is_empty(), "a refusal wrote {left:?}");

    // Under an address-space limit a buffer that does not fit is an error, not an abort: a sequence
    // whose 256 MB of pixels are really there (a sparse file), read under `ulimit -v` 200 MB.
    if Path::new("/bin/sh").exists() {
        let big_header = header
            .replace("DimSize = 64 64 40", "DimSize = 1024 1024 256")
            .lines()
            .filter(|l| !l.starts_with("Seq_Frame"))
            .collect::<Vec<_>>()
            .join("\n")
            + "\n";
        let big = f.path("big.mha");
        let mut file = std::fs::File::create(&big).unwrap();
        file.write_all(big_header.as_bytes()).unwrap();
        file.set_len(big_header.len() as u64 + (256 << 20)).unwrap();
        drop(file);
        let output = Command::new("/bin/sh")
            .arg("-c")
            .arg("ulimit -v 204800 && exec \"$0\" inspect \"$1\"")
            .arg(BIN)
            .arg(&big)
            .env("RAYON_NUM_THREADS", "1")
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert_eq!(output.status.code(), Some(1), "{stderr}");
        assert!(stderr.contains("could not allocate"), "{stderr}");
        assert!(stderr.contains("big.mha"), "{stderr}");
    }
}

/// Class 5: SIGTERM and SIGHUP clean up like Ctrl-C: exit 130, no output, no hidden temporary file.
#[test]
fn sigterm_and_sighup_leave_no_temporary_files() {
    let dir = tempfile::tempdir().unwrap();
    let sim = dir.path().join("sim");
    common::echosurf_ok(&os(&[
        &"simulate",
        &"--phantom",
        &"sphere",
        &"--frames-per-sweep",
        &"20",
        &"--out",
        &sim,
    ]));
    for signal in ["TERM", "HUP"] {
        let out = dir.path().join(signal);
        std::fs::create_dir(&out).unwrap();
        let mut child = Command::new(BIN)
            .args(os(&[
                &"extract",
                &sim.join("sim.mha"),
                &"--calibration",
                &sim.join("sim_config.xml"),
                &"--out",
                &out.join("mesh.ply"),
                &"--config",
                &model_config(
                    dir.path().join(format!("{signal}.toml")),
                    "[tuning.sampling]\nbin_mm = 0.0",
                    &out.join("model.esrbf"),
                ),
                &"--max-samples",
                &"400000",
                &"--resolution",
                &"0.15",
            ]))
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let start = Instant::now();
        while start.elapsed() < Duration::from_secs(1) {
            assert!(child.try_wait().unwrap().is_none(), "finished too soon");
            std::thread::sleep(Duration::from_millis(50));
        }
        let status = Command::new("kill")
            .arg(format!("-{signal}"))
            .arg(child.id().to_string())
            .status()
            .unwrap();
        assert!(status.success());
        let output = child.wait_with_output().unwrap();
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert_eq!(output.status.code(), Some(130), "SIG{signal}: {stderr}");
        assert!(stderr.contains("interrupted"), "{stderr}");
        let left: Vec<_> = std::fs::read_dir(&out)
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert!(left.is_empty(), "left after SIG{signal}: {left:?}");
    }
}
