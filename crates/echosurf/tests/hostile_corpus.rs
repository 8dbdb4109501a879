//! The hostile corpus through the library readers: every case must give an error (never a panic) whose
//! message names the file and the problem. The same files go through the CLI binary in
//! `crates/echosurf-cli/tests/hostile_corpus.rs`, which also bounds time and memory.

use echosurf_testkit as testkit;

use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::Path;

use echosurf::io;
use testkit::corpus::{Target, generate};

fn read_case(target: Target, path: &Path, config: &Path) -> echosurf::Result<()> {
    use echosurf::segment::InitialBand;
    match target {
        Target::Sequence => io::read_sequence(path).map(|_| ()),
        Target::SequenceForExtract => {
            let sequence = io::read_sequence(path)?;
            let calibration = io::read_calibration(config)?;
            // Errors of the in-memory pipeline carry no file name; the CLI adds it (checked there).
            echosurf::pipeline::extract(
                &sequence,
                Some(&calibration),
                &echosurf::pipeline::ExtractOptions::default(),
                &echosurf::progress::NoProgress,
            )
            .map(|_| ())
            .map_err(|e| match e {
                e @ (echosurf::Error::Format { .. } | echosurf::Error::Io { .. }) => e,
                other => echosurf::Error::format(
                    path,
                    echosurf::FormatProblem::NoValidFrames,
                    other.to_string(),
                ),
            })
        }
        Target::Config => io::read_calibration(path).map(|_| ()),
        Target::InitialBand => {
            InitialBand::load(path, testkit::SMALL_W, testkit::SMALL_H).map(|_| ())
        }
        Target::PointCloud => io::read_point_cloud(path).map(|_| ()),
        Target::Mesh => io::read_mesh(path).map(|_| ()),
        Target::Model => echosurf::rbf::RbfModel::load(path).map(|_| ()),
        Target::Volume => echosurf::voxel::read_volume_mha(path).map(|_| ()),
    }
}

#[test]
fn every_corpus_file_is_refused_with_a_message_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let companions = testkit::corpus::companions(dir.path());
    let cases = generate(dir.path());
    assert!(cases.len() >= 30, "only {} corpus cases", cases.len());
    let mut failures = Vec::new();
    for case in &cases {
        let name = case
            .path
            .file_name()
            .unwrap()
            .to_string_lossy()
            .into_owned();
        let outcome = catch_unwind(AssertUnwindSafe(|| {
            read_case(case.target, &case.path, &companions.config)
        }));
        match outcome {
            Err(_) => failures.push(format!("{name}: PANICKED")),
            Ok(Ok(())) => failures.push(format!("{name}: accepted")),
            Ok(Err(e)) => {
                let msg = e.to_string();
                let lower = msg.to_ascii_lowercase();
                // The in-memory pipeline has no file name and says `<sequence>`; the CLI names the file.
                let named = msg.contains(&name)
                    || (case.target == Target::SequenceForExtract && msg.contains("<sequence>"));
                if !named {
                    failures.push(format!("{name}: error does not name the file: {msg}"));
                } else if !case.problem_words.iter().any(|w| lower.contains(w)) {
                    failures.push(format!(
                        "{name}: error does not say the problem (expected one of {:?}): {msg}",
                        case.problem_words
                    ));
                } else {
                    eprintln!("{name}: {msg}");
                }
            }
        }
    }
    // The 100 MB file is only needed for the duration of the test.
    drop(dir);
    assert!(
        failures.is_empty(),
        "{} of {} cases failed:\n{}",
        failures.len(),
        cases.len(),
        failures.join("\n")
    );
}
