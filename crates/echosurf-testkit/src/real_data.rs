//! Where the real PLUS recordings are: `shared/data/real` beside the repository (CI layout), or in the
//! nearest ancestor folder that has it (helper worktrees live deeper than the main checkout). One place
//! for every test and bench of the workspace.

use std::path::{Path, PathBuf};

pub fn real_dir() -> PathBuf {
    let beside = Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../../shared/data/real/"
    ));
    if beside.is_dir() {
        return beside.to_path_buf();
    }
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .ancestors()
        .map(|a| a.join("shared/data/real"))
        .find(|p| p.is_dir())
        .unwrap_or_else(|| beside.to_path_buf())
}

/// The path of one real recording; panics with the path when it is missing, so a test without the
/// data says what to put where instead of failing on an unreadable file later.
pub fn real(name: &str) -> PathBuf {
    let path = real_dir().join(name);
    assert!(
        path.exists(),
        "real PLUS data missing: {} (the real-data tests read `shared/data/real` beside the \
         repository, i.e. ../shared/data/real from the checkout)",
        path.display()
    );
    path
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A missing recording stops the test with its full path, not later on an unreadable file.
    #[test]
    fn a_missing_recording_panics_naming_its_path() {
        let name = "no-such-recording.igs.mha";
        let panic = std::panic::catch_unwind(|| real(name)).expect_err("a missing file must panic");
        let message = panic.downcast_ref::<String>().expect("a formatted message");
        let path = real_dir().join(name);
        assert!(
            message.starts_with(&format!("real PLUS data missing: {}", path.display())),
            "{message}"
        );
    }
}
