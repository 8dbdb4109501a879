//! The hidden temporary files the library's atomic writer has in flight, so the Ctrl-C handler and
//! the out-of-memory path can remove unfinished outputs before the process ends. Installed into the
//! library by [`install`] at start-up (the registry is process-wide state, so the application owns it).

use std::path::{Path, PathBuf};
use std::sync::{Mutex, MutexGuard};

use echosurf::io::atomic::TempFileRegistry;

/// Temporary files being written by this process. Renames happen under this lock, so a signal handler
/// holding it sees every temporary file either still in flight or already renamed into place.
static IN_FLIGHT: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());

fn in_flight() -> MutexGuard<'static, Vec<PathBuf>> {
    IN_FLIGHT
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner())
}

/// [`IN_FLIGHT`] as the library's registry.
struct InFlight;

impl TempFileRegistry for InFlight {
    fn add(&self, tmp: &Path) {
        in_flight().push(tmp.to_path_buf());
    }

    fn settle(&self, tmp: &Path, settle: &mut dyn FnMut()) {
        let mut registry = in_flight();
        registry.retain(|p| p != tmp);
        settle();
        drop(registry);
    }
}

/// Makes the library report its temporary files here (idempotent).
pub fn install() {
    echosurf::io::atomic::set_temp_file_registry(&InFlight);
}

/// Removes this process's unfinished temporary files and returns how many there were. For a Ctrl-C
/// handler: call it, then exit without returning (the lock stays held so no rename can follow).
pub fn remove_in_flight() -> usize {
    let registry = in_flight();
    for tmp in registry.iter() {
        let _ = std::fs::remove_file(tmp);
    }
    let n = registry.len();
    // Keep the guard alive until the process exits: a writer thread must not rename afterwards.
    std::mem::forget(registry);
    n
}

/// [`remove_in_flight`] for a process ending from inside its allocator: waits at most about a second
/// for the registry, which the failing thread itself may hold, and then gives up (`None`).
pub fn try_remove_in_flight() -> Option<usize> {
    for _ in 0..100 {
        let registry = match IN_FLIGHT.try_lock() {
            Ok(guard) => guard,
            Err(std::sync::TryLockError::Poisoned(poisoned)) => poisoned.into_inner(),
            Err(std::sync::TryLockError::WouldBlock) => {
                std::thread::sleep(std::time::Duration::from_millis(10));
                continue;
            }
        };
        for tmp in registry.iter() {
            let _ = std::fs::remove_file(tmp);
        }
        let n = registry.len();
        std::mem::forget(registry);
        return Some(n);
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    #[test]
    fn a_write_is_registered_while_in_flight_and_forgotten_once_renamed() {
        install();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.bin");
        let tmp = echosurf::io::atomic::temp_path(&path);
        echosurf::io::atomic::write_atomic(&path, |w| {
            assert!(
                in_flight().contains(&tmp),
                "{} not registered",
                tmp.display()
            );
            assert!(tmp.exists());
            w.write_all(b"a")
        })
        .unwrap();
        assert!(!in_flight().contains(&tmp));
        assert_eq!(std::fs::read(&path).unwrap(), b"a");
        // A failed write is forgotten too, and leaves nothing behind.
        let failed = dir.path().join("b.bin");
        let failed_tmp = echosurf::io::atomic::temp_path(&failed);
        let err = echosurf::io::atomic::write_atomic(&failed, |_| Err(std::io::Error::other("no")));
        assert!(err.is_err());
        assert!(!in_flight().contains(&failed_tmp));
        assert!(!failed.exists() && !failed_tmp.exists());
    }
}
