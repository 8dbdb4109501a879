//! `echosurf-slicer`: the executable 3D Slicer discovers as a command-line module. Slicer runs it as
//! `echosurf-slicer --xml` and then with the module's arguments, never with a subcommand, so it
//! forwards every argument to `echosurf slicer-module`, the `echosurf` binary beside it.

use std::process::{Command, ExitCode};

fn main() -> ExitCode {
    let beside = std::env::current_exe()
        .ok()
        .and_then(|exe| exe.parent().map(|dir| dir.to_path_buf()))
        .unwrap_or_default();
    let echosurf = beside.join(format!("echosurf{}", std::env::consts::EXE_SUFFIX));
    match Command::new(&echosurf)
        .arg("slicer-module")
        .args(std::env::args_os().skip(1))
        .status()
    {
        Ok(status) => match status.code() {
            Some(0) => ExitCode::SUCCESS,
            Some(code) => ExitCode::from(u8::try_from(code).unwrap_or(1)),
            None => ExitCode::FAILURE,
        },
        Err(e) => {
            eprintln!(
                "error: cannot run {} (echosurf-slicer needs the echosurf binary beside it): {e}",
                echosurf.display()
            );
            ExitCode::FAILURE
        }
    }
}
