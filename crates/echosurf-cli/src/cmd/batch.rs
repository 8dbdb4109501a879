//! `echosurf batch MANIFEST --out DIR`: `extract` over the sweeps a TOML manifest lists, resumable and
//! shardable. Each finished sweep leaves `DIR/NAME.EXT` and `DIR/NAME.report.json`; the report names
//! the inputs and options it was made from, and a rerun skips every row whose report says the same.
//! A failing sweep is reported in the summary table and does not stop the others; the exit code says
//! whether any failed. `--shard I/N` runs rows k with k mod N = I, so a scheduler's array of N jobs
//! covers the manifest once. Manifest format: `docs/guide/batch.md`.

use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};

use anyhow::Context;
use clap::Parser;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The manifest (TOML): `[[sweep]]` tables with `sequence`, `calibration` (the PLUS XML; `config` also read), optional `name` and `options`.
    pub manifest: PathBuf,
    /// Folder for the meshes, reports and summary (created if missing).
    #[arg(long)]
    pub out: PathBuf,
    /// Run only rows k with k mod N = I (0-based rows in manifest order), e.g.
    /// `--shard $SLURM_ARRAY_TASK_ID/$SLURM_ARRAY_TASK_COUNT`.
    #[arg(long, value_name = "I/N", value_parser = parse_shard)]
    pub shard: Option<Shard>,
    /// Sweeps extracted at once (each also uses the machine's threads).
    #[arg(long, default_value_t = 1)]
    pub jobs: usize,
    /// Mesh file type: ply, stl, obj or vtk.
    #[arg(long, default_value = "ply")]
    pub mesh_format: String,
}

/// `--shard I/N`: this process runs rows k with k mod `count` = `index`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Shard {
    pub index: usize,
    pub count: usize,
}

fn parse_shard(text: &str) -> Result<Shard, String> {
    let (i, n) = text
        .split_once('/')
        .ok_or_else(|| format!("`{text}`: expected I/N, e.g. 0/4"))?;
    let (index, count) = (
        i.trim()
            .parse::<usize>()
            .map_err(|_| format!("`{i}` is not a row index"))?,
        n.trim()
            .parse::<usize>()
            .map_err(|_| format!("`{n}` is not a shard count"))?,
    );
    if count == 0 || index >= count {
        return Err(format!("`{text}`: need 0 <= I < N"));
    }
    Ok(Shard { index, count })
}

/// The manifest file.
#[derive(Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct Manifest {
    /// Extract options every row gets before its own.
    #[serde(default)]
    options: Vec<String>,
    #[serde(default)]
    sweep: Vec<Row>,
}

/// One sweep of the manifest.
#[derive(Debug, Clone, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct Row {
    /// Output base name; default: the sequence's file name up to its first dot.
    name: Option<String>,
    sequence: PathBuf,
    /// The PLUS device-set XML; `config`, its old name, is still read.
    #[serde(alias = "config")]
    calibration: PathBuf,
    /// `echosurf extract` options for this sweep, e.g. `["--sheet", "ridge"]`.
    #[serde(default)]
    options: Vec<String>,
}

/// A row ready to run: paths resolved against the manifest's folder, options merged.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
struct Job {
    row: usize,
    name: String,
    sequence: PathBuf,
    #[serde(alias = "config")]
    calibration: PathBuf,
    options: Vec<String>,
    mesh: String,
}

/// What became of a row, for the summary table.
#[derive(Debug, Clone)]
enum Outcome {
    Done {
        triangles: usize,
        pieces: usize,
        seconds: f64,
    },
    Skipped,
    Failed(String),
}

/// Reads the manifest and the jobs of this shard.
fn read_jobs(args: &Args, extension: &str) -> anyhow::Result<Vec<Job>> {
    let text = std::fs::read_to_string(&args.manifest)
        .with_context(|| format!("reading {}", args.manifest.display()))?;
    let manifest: Manifest = toml::from_str(&text).map_err(|e| {
        anyhow::anyhow!("{}: {}", args.manifest.display(), e.to_string().trim_end())
    })?;
    if manifest.sweep.is_empty() {
        anyhow::bail!("{}: no [[sweep]] rows", args.manifest.display());
    }
    let base = match args.manifest.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let mut jobs = Vec::with_capacity(manifest.sweep.len());
    for (k, row) in manifest.sweep.iter().enumerate() {
        let name = match &row.name {
            Some(n) => n.clone(),
            None => row
                .sequence
                .file_name()
                .map(|f| {
                    f.to_string_lossy()
                        .split('.')
                        .next()
                        .unwrap_or_default()
                        .to_string()
                })
                .unwrap_or_default(),
        };
        let plain = !name.is_empty()
            && !name.starts_with('.')
            && !name.contains(['/', '\\'])
            && name != "summary";
        if !plain {
            anyhow::bail!(
                "{}: sweep {k} has name {name:?}; a name must be a plain file name (not `summary`)",
                args.manifest.display()
            );
        }
        if let Some(other) = jobs.iter().find(|j: &&Job| j.name == name) {
            anyhow::bail!(
                "{}: sweeps {} and {k} are both named {name:?}; give each a `name`",
                args.manifest.display(),
                other.row
            );
        }
        jobs.push(Job {
            row: k,
            name: name.clone(),
            sequence: base.join(&row.sequence),
            calibration: base.join(&row.calibration),
            options: manifest
                .options
                .iter()
                .chain(&row.options)
                .cloned()
                .collect(),
            mesh: format!("{name}.{extension}"),
        });
    }
    Ok(match args.shard {
        Some(s) => jobs
            .into_iter()
            .filter(|j| j.row % s.count == s.index)
            .collect(),
        None => jobs,
    })
}

fn report_path(dir: &Path, job: &Job) -> PathBuf {
    dir.join(format!("{}.report.json", job.name))
}

/// A row is finished when its mesh exists and its report names the same job.
fn finished(dir: &Path, job: &Job) -> bool {
    let Ok(text) = std::fs::read(report_path(dir, job)) else {
        return false;
    };
    let Ok(report) = serde_json::from_slice::<serde_json::Value>(&text) else {
        return false;
    };
    let same = serde_json::from_value::<Job>(report["batch"].clone()).is_ok_and(|recorded| {
        Job {
            row: job.row,
            ..recorded
        } == *job
    });
    same && dir.join(&job.mesh).is_file()
}

/// `echosurf extract` as a batch row runs it: its own parser, so a row's options mean what they mean
/// on the command line.
#[derive(Debug, Parser)]
struct ExtractCommand {
    #[command(flatten)]
    args: super::extract::Args,
}

fn run_job(dir: &Path, job: &Job) -> anyhow::Result<Outcome> {
    let mesh = dir.join(&job.mesh);
    let mut words: Vec<std::ffi::OsString> = vec![
        "extract".into(),
        job.sequence.clone().into(),
        "--calibration".into(),
        job.calibration.clone().into(),
        "--out".into(),
        mesh.into(),
    ];
    words.extend(job.options.iter().map(Into::into));
    let args = ExtractCommand::try_parse_from(words)
        .map_err(|e| anyhow::anyhow!("options {:?}: {}", job.options, e.to_string().trim_end()))?
        .args;
    let several_levels = matches!(
        args.extract_config()?.user.iso,
        echosurf::pipeline::IsoLevels::Levels(ref levels) if levels.len() > 1
    );
    if args.report.is_some() || several_levels {
        anyhow::bail!(
            "a batch row writes its own report and one mesh: no --report, one --iso level"
        );
    }
    let space = args.space.space;
    let output = super::extract::run_with(args, &crate::memory::StageMemory)?;
    let mut report = super::space::with_coordinates(
        &output.report,
        &output.report.parameters.world_frame,
        space,
    )?;
    report["batch"] = serde_json::to_value(job)?;
    let text = serde_json::to_string_pretty(&report)?;
    // Written last: a row is finished once its report is there.
    echosurf::io::atomic::write_bytes_atomic(&report_path(dir, job), text.as_bytes())?;
    Ok(Outcome::Done {
        triangles: output.surfaces.iter().map(|s| s.mesh.triangles.len()).sum(),
        pieces: output
            .surfaces
            .iter()
            .map(|s| s.mesh.topology().components)
            .sum(),
        seconds: output.report.total_seconds,
    })
}

/// The summary table (tab-separated, one line per row of this shard, in manifest order).
fn summary_text(jobs: &[Job], outcomes: &[Option<Outcome>]) -> String {
    let mut text = String::from("row\tname\tstatus\ttriangles\tpieces\tseconds\tmesh\tmessage\n");
    for (job, outcome) in jobs.iter().zip(outcomes) {
        let (status, t, p, s, message) = match outcome {
            None => (
                "pending",
                String::new(),
                String::new(),
                String::new(),
                String::new(),
            ),
            Some(Outcome::Done {
                triangles,
                pieces,
                seconds,
            }) => (
                "done",
                triangles.to_string(),
                pieces.to_string(),
                format!("{seconds:.2}"),
                String::new(),
            ),
            Some(Outcome::Skipped) => (
                "skipped",
                String::new(),
                String::new(),
                String::new(),
                "finished by an earlier run with the same inputs and options".into(),
            ),
            Some(Outcome::Failed(e)) => (
                "failed",
                String::new(),
                String::new(),
                String::new(),
                e.replace(['\t', '\n'], " "),
            ),
        };
        text.push_str(&format!(
            "{}\t{}\t{status}\t{t}\t{p}\t{s}\t{}\t{message}\n",
            job.row, job.name, job.mesh
        ));
    }
    text
}

/// `summary.tsv`, or `summary-shard-I-of-N.tsv` so the jobs of an array never write one file.
fn summary_path(dir: &Path, shard: Option<Shard>) -> PathBuf {
    match shard {
        None => dir.join("summary.tsv"),
        Some(s) => dir.join(format!("summary-shard-{}-of-{}.tsv", s.index, s.count)),
    }
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let extension = args.mesh_format.to_ascii_lowercase();
    if !echosurf::io::mesh_io::MESH_EXTENSIONS.contains(&extension.as_str()) {
        anyhow::bail!("--mesh-format {extension}: expected ply, stl, obj or vtk");
    }
    if args.jobs == 0 {
        anyhow::bail!("--jobs must be at least 1");
    }
    let jobs = read_jobs(&args, &extension)?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let dir = args.out.as_path();
    let summary = summary_path(dir, args.shard);
    let outcomes: Mutex<Vec<Option<Outcome>>> = Mutex::new(vec![None; jobs.len()]);
    let next = AtomicUsize::new(0);
    let record = |k: usize, outcome: Outcome| -> anyhow::Result<()> {
        let job = &jobs[k];
        match &outcome {
            Outcome::Done { triangles, .. } => {
                println!("{}: done, {triangles} triangles -> {}", job.name, job.mesh)
            }
            Outcome::Skipped => println!("{}: skipped (already finished)", job.name),
            Outcome::Failed(e) => eprintln!("{}: FAILED: {e}", job.name),
        }
        let mut all = outcomes
            .lock()
            .map_err(|_| anyhow::anyhow!("a batch worker panicked"))?;
        all[k] = Some(outcome);
        let text = summary_text(&jobs, &all);
        echosurf::io::atomic::write_bytes_atomic(&summary, text.as_bytes())?;
        Ok(())
    };
    let worker = || -> anyhow::Result<()> {
        loop {
            let k = next.fetch_add(1, Ordering::Relaxed);
            let Some(job) = jobs.get(k) else {
                return Ok(());
            };
            let outcome = if finished(dir, job) {
                Outcome::Skipped
            } else {
                match run_job(dir, job) {
                    Ok(outcome) => outcome,
                    Err(e) => Outcome::Failed(crate::phrasing::error_message(
                        &e,
                        crate::phrasing::Terms::Extract,
                    )),
                }
            };
            record(k, outcome)?;
        }
    };
    std::thread::scope(|scope| -> anyhow::Result<()> {
        let handles: Vec<_> = (0..args.jobs.min(jobs.len().max(1)))
            .map(|_| scope.spawn(worker))
            .collect();
        for h in handles {
            h.join()
                .map_err(|_| anyhow::anyhow!("a batch worker panicked"))??;
        }
        Ok(())
    })?;
    let all = outcomes
        .into_inner()
        .map_err(|_| anyhow::anyhow!("a batch worker panicked"))?;
    let failed: Vec<&str> = jobs
        .iter()
        .zip(&all)
        .filter(|(_, o)| matches!(o, Some(Outcome::Failed(_))))
        .map(|(j, _)| j.name.as_str())
        .collect();
    println!("summary: {}", summary.display());
    if !failed.is_empty() {
        anyhow::bail!(
            "{} of {} sweeps failed ({}); see {}",
            failed.len(),
            jobs.len(),
            failed.join(", "),
            summary.display()
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shards_parse_and_split_rows_by_remainder() {
        assert_eq!(parse_shard("1/3"), Ok(Shard { index: 1, count: 3 }));
        for bad in ["3/3", "0/0", "1", "a/2", "-1/2"] {
            assert!(parse_shard(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn manifests_are_checked_before_any_work() {
        let dir = tempfile::tempdir().unwrap();
        let manifest = dir.path().join("m.toml");
        let args = |shard| Args {
            manifest: manifest.clone(),
            out: dir.path().join("out"),
            shard,
            jobs: 1,
            mesh_format: "ply".into(),
        };
        let write = |text: &str| std::fs::write(&manifest, text).unwrap();
        write(
            "[[sweep]]\nsequence = \"a/p1.igs.mha\"\ncalibration = \"c.xml\"\n[[sweep]]\nsequence = \"p2.mha\"\ncalibration = \"d.xml\"\noptions = [\"--sheet\", \"iso\"]\n[[sweep]]\nname = \"x\"\nsequence = \"p3.mha\"\nconfig = \"c.xml\"\n",
        );
        let jobs = read_jobs(&args(None), "ply").unwrap();
        let names: Vec<&str> = jobs.iter().map(|j| j.name.as_str()).collect();
        assert_eq!(names, ["p1", "p2", "x"]);
        assert_eq!(jobs[0].sequence, dir.path().join("a/p1.igs.mha"));
        assert_eq!(jobs[1].options, ["--sheet", "iso"]);
        // `config`, the column's old name, still reads as `calibration`.
        assert_eq!(jobs[1].calibration, dir.path().join("d.xml"));
        assert_eq!(jobs[2].calibration, dir.path().join("c.xml"));
        let shard = |i| {
            read_jobs(&args(Some(Shard { index: i, count: 2 })), "ply")
                .unwrap()
                .iter()
                .map(|j| j.row)
                .collect::<Vec<_>>()
        };
        assert_eq!((shard(0), shard(1)), (vec![0, 2], vec![1]));
        write(
            "[[sweep]]\nsequence = \"a.mha\"\nconfig = \"c.xml\"\n[[sweep]]\nsequence = \"b/a.mha\"\nconfig = \"c.xml\"\n",
        );
        assert!(
            read_jobs(&args(None), "ply")
                .unwrap_err()
                .to_string()
                .contains("both named")
        );
        write("[[sweep]]\nsequence = \"a.mha\"\nconfig = \"c.xml\"\ncolour = 1\n");
        assert!(
            read_jobs(&args(None), "ply")
                .unwrap_err()
                .to_string()
                .contains("m.toml")
        );
        write("");
        assert!(
            read_jobs(&args(None), "ply")
                .unwrap_err()
                .to_string()
                .contains("no [[sweep]]")
        );
    }
}
