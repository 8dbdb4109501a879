//! Structured mutation fuzzing of every reader of a user's file (cargo-fuzz needs nightly; this runs on the
//! fixed stable toolchain and in CI). Seeds are real PLUS files cut down and files from our own writers
//! (see `testkit::seeds`); each case applies 1-4 mutations chosen by a seeded ChaCha generator: bit flips,
//! byte insertion/deletion, truncation, header number swaps (huge, negative, zero, NaN, inf, empty),
//! duplicated/removed/swapped header lines. Every parse must return Ok or an error naming the file; a
//! panic fails the test and prints the seed and case so it can be replayed (and becomes a regression case).
//!
//! `ECHOSURF_FUZZ_CASES=N` (default 150 per seed) and `ECHOSURF_FUZZ_SEED=S` run longer/other campaigns:
//! `ECHOSURF_FUZZ_CASES=20000 cargo test --release -p echosurf --test fuzz_readers`.

use echosurf_testkit as testkit;

use std::panic::{AssertUnwindSafe, catch_unwind};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const SWAP_VALUES: &[&str] = &[
    "0",
    "-1",
    "-2147483648",
    "4294967296",
    "18446744073709551615",
    "99999999999999999999999",
    "1e308",
    "-1e308",
    "NaN",
    "inf",
    "-inf",
    "",
    "1",
    "3",
    "65536",
];

/// Where the text header ends (mutations of header fields target it); the whole file for text formats.
fn header_len(bytes: &[u8]) -> usize {
    let find = |pat: &[u8]| {
        bytes
            .windows(pat.len())
            .position(|w| w == pat)
            .map(|p| p + pat.len())
    };
    find(b"ElementDataFile = LOCAL\n")
        .or_else(|| find(b"end_header\n"))
        .or_else(|| find(b"\n\n"))
        .unwrap_or(bytes.len())
        .min(bytes.len())
}

fn mutate(rng: &mut ChaCha8Rng, seed: &[u8]) -> Vec<u8> {
    let mut b = seed.to_vec();
    let rounds = rng.random_range(1..=4);
    for _ in 0..rounds {
        let head = header_len(&b).max(1);
        match rng.random_range(0..9) {
            0 => {
                if !b.is_empty() {
                    let i = rng.random_range(0..b.len());
                    b[i] ^= 1 << rng.random_range(0..8);
                }
            }
            1 => {
                let i = rng.random_range(0..=b.len());
                let n = rng.random_range(1..16);
                let ins: Vec<u8> = (0..n).map(|_| rng.random()).collect();
                b.splice(i..i, ins);
            }
            2 => {
                if !b.is_empty() {
                    let i = rng.random_range(0..b.len());
                    let n = rng.random_range(1..=64.min(b.len() - i));
                    b.drain(i..i + n);
                }
            }
            3 => {
                let i = rng.random_range(0..=b.len());
                b.truncate(i);
            }
            4..=6 => {
                // Replace one number in the header with a hostile value.
                let head = head.min(b.len());
                let starts: Vec<usize> = (0..head)
                    .filter(|&i| {
                        b[i].is_ascii_digit() && (i == 0 || !b[i - 1].is_ascii_alphanumeric())
                    })
                    .collect();
                if !starts.is_empty() {
                    let s = starts[rng.random_range(0..starts.len())];
                    let mut e = s;
                    while e < head && (b[e].is_ascii_digit() || b".-+eE".contains(&b[e])) {
                        e += 1;
                    }
                    let v = SWAP_VALUES[rng.random_range(0..SWAP_VALUES.len())];
                    b.splice(s..e, v.bytes());
                }
            }
            _ => {
                // Duplicate, remove or swap header lines.
                let head = head.min(b.len());
                let mut lines: Vec<Vec<u8>> = b[..head]
                    .split_inclusive(|&c| c == b'\n')
                    .map(|l| l.to_vec())
                    .collect();
                if lines.len() >= 2 {
                    let i = rng.random_range(0..lines.len());
                    let j = rng.random_range(0..lines.len());
                    match rng.random_range(0..3) {
                        0 => {
                            let l = lines[i].clone();
                            lines.insert(j, l);
                        }
                        1 => {
                            lines.remove(i);
                        }
                        _ => lines.swap(i, j),
                    }
                    let rest = b[head..].to_vec();
                    b = lines.concat();
                    b.extend(rest);
                }
            }
        }
    }
    b
}

#[test]
fn mutated_files_never_panic_and_errors_name_the_file() {
    let cases: usize = std::env::var("ECHOSURF_FUZZ_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(150);
    let campaign: u64 = std::env::var("ECHOSURF_FUZZ_SEED")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(9);
    let dir = tempfile::tempdir().unwrap();
    let seeds = testkit::seeds(dir.path());
    // Silence the default panic printout; panics are reported below with their case.
    let default_hook = std::panic::take_hook();
    std::panic::set_hook(Box::new(|_| {}));
    let mut failures = Vec::new();
    let mut stats = std::collections::BTreeMap::new();
    for (key, seed) in &seeds {
        // The unmutated seed must parse: otherwise the campaign would only test the first error path.
        let name = format!("fuzz_{key}");
        let path = dir.path().join(&name);
        std::fs::write(&path, seed).unwrap();
        if let Err(e) = testkit::parse(key, &path) {
            failures.push(format!("seed {key} itself does not parse: {e}"));
            continue;
        }
        let mut rng = ChaCha8Rng::seed_from_u64(campaign ^ common_hash(key));
        let (mut ok, mut err) = (0usize, 0usize);
        let mut slowest = (0.0f64, 0usize);
        for case in 0..cases {
            let bytes = mutate(&mut rng, seed);
            std::fs::write(&path, &bytes).unwrap();
            let start = std::time::Instant::now();
            let outcome = catch_unwind(AssertUnwindSafe(|| testkit::parse(key, &path)));
            let seconds = start.elapsed().as_secs_f64();
            if seconds > slowest.0 {
                slowest = (seconds, case);
            }
            match outcome {
                Ok(Ok(())) => ok += 1,
                Ok(Err(msg)) => {
                    err += 1;
                    if !msg.contains(&name) {
                        failures.push(format!(
                            "{key} case {case}: error does not name the file: {msg}"
                        ));
                    }
                }
                Err(panic) => {
                    let what = panic
                        .downcast_ref::<String>()
                        .cloned()
                        .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                        .unwrap_or_default();
                    let keep =
                        std::env::temp_dir().join(format!("echosurf-fuzz-crash-{key}-{case}"));
                    let _ = std::fs::write(&keep, &bytes);
                    failures.push(format!(
                        "{key} case {case} (campaign {campaign}) PANICKED: {what}; input saved to {}",
                        keep.display()
                    ));
                }
            }
        }
        stats.insert(
            *key,
            (
                ok,
                err,
                format!("slowest {:.3}s (case {})", slowest.0, slowest.1),
            ),
        );
    }
    std::panic::set_hook(default_hook);
    eprintln!("fuzz cases per seed (ok, error, slowest): {stats:#?}");
    assert!(
        failures.is_empty(),
        "{} failures:\n{}",
        failures.len(),
        failures.join("\n")
    );
}

fn common_hash(key: &str) -> u64 {
    key.bytes().fold(0xcbf29ce484222325u64, |h, b| {
        (h ^ b as u64).wrapping_mul(0x100000001b3)
    })
}
