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
