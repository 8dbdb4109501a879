//! The library's progress hook for Python: runs the work without the GIL, calls the user's
//! `progress(stage, fraction)` (taking the GIL only for the call), watches for Ctrl-C, and stops the
//! work when the callback raises or a signal arrives.
//!
//! The library has no cancellation hook, so stopping unwinds out of it from inside the progress call
//! with [`std::panic::resume_unwind`] (which runs no panic hook and prints nothing) and catches that
//! unwind at [`PyProgress::run`]; rayon carries it from worker threads to the caller. The library
//! writes no file during `extract` or `fit` here, so nothing is left half-written.

use std::panic::AssertUnwindSafe;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use echosurf::progress::Progress;
use pyo3::exceptions::PyKeyboardInterrupt;
use pyo3::prelude::*;

use crate::EchosurfError;

/// How often Ctrl-C is looked for while no callback fraction is due.
const SIGNAL_CHECK_INTERVAL: Duration = Duration::from_millis(100);

/// The unwind payload that stops the library's work.
struct Stop;

/// The stage being reported.
#[derive(Debug)]
struct Stage {
    name: String,
    total: u64,
    /// Last fraction handed to the callback, in hundredths (-1: none yet).
    last_percent: i64,
    last_signal_check: Instant,
}

/// Forwards the library's progress to an optional Python callable.
#[derive(Debug)]
pub struct PyProgress {
    callback: Option<Py<PyAny>>,
    stage: Mutex<Stage>,
    /// The exception that stopped the work (raised by the callback, or Ctrl-C).
    error: Mutex<Option<PyErr>>,
}

impl PyProgress {
    pub fn new(callback: Option<Py<PyAny>>) -> Self {
        PyProgress {
            callback,
            stage: Mutex::new(Stage {
                name: String::new(),
                total: 0,
                last_percent: -1,
                last_signal_check: Instant::now(),
            }),
            error: Mutex::new(None),
        }
    }

    /// Runs `work` with the GIL released. A library error becomes [`EchosurfError`] with its
    /// message; an exception from the callback (or Ctrl-C) stops the work and is raised as is.
    pub fn run<T: Send>(
        &self,
        py: Python<'_>,
        work: impl FnOnce() -> Result<T, String> + Send,
    ) -> PyResult<T> {
        let result = py.detach(|| std::panic::catch_unwind(AssertUnwindSafe(work)));
        let stopped = self.take_error();
        match result {
            Ok(Ok(value)) => match stopped {
                Some(error) => Err(error),
                None => Ok(value),
            },
            Ok(Err(message)) => Err(stopped.unwrap_or_else(|| EchosurfError::new_err(message))),
            Err(payload) if payload.is::<Stop>() => {
                Err(stopped.unwrap_or_else(|| PyKeyboardInterrupt::new_err("stopped")))
            }
            Err(payload) => std::panic::resume_unwind(payload),
        }
    }

    fn take_error(&self) -> Option<PyErr> {
        self.error.lock().ok().and_then(|mut slot| slot.take())
    }

    /// Hands `fraction` of `stage` to the callback when `due`, checks for Ctrl-C when due or every
    /// [`SIGNAL_CHECK_INTERVAL`]; unwinds out of the library when either raised.
    fn report(&self, update: impl FnOnce(&mut Stage) -> Option<(String, f64)>) {
        let (call, check_signals) = {
            let Ok(mut stage) = self.stage.lock() else {
                return;
            };
            let call = update(&mut stage).filter(|_| self.callback.is_some());
            let check = call.is_some() || stage.last_signal_check.elapsed() >= SIGNAL_CHECK_INTERVAL;
            if check {
                stage.last_signal_check = Instant::now();
            }
            (call, check)
        };
        if !check_signals {
            return;
        }
        let failure = Python::attach(|py| {
            // Signals are delivered to the main thread only; elsewhere this returns Ok.
            py.check_signals()?;
            if let (Some((name, fraction)), Some(callback)) = (call, &self.callback) {
                callback.call1(py, (name, fraction))?;
            }
            Ok::<(), PyErr>(())
        })
        .err();
        if let Some(error) = failure {
            if let Ok(mut slot) = self.error.lock() {
                slot.get_or_insert(error);
            }
            std::panic::resume_unwind(Box::new(Stop));
        }
    }
}

impl Progress for PyProgress {
    fn start(&self, stage: &str, total: u64) {
        self.report(|s| {
            s.name = stage.to_string();
            s.total = total;
            s.last_percent = 0;
            Some((s.name.clone(), 0.0))
        });
    }

    fn advance(&self, done: u64) {
        self.report(|s| {
            if s.total == 0 {
                return None;
            }
            let fraction = (done as f64 / s.total as f64).clamp(0.0, 1.0);
            let percent = (fraction * 100.0).floor() as i64;
            (percent > s.last_percent).then(|| {
                s.last_percent = percent;
                (s.name.clone(), fraction)
            })
        });
    }

    fn finish(&self) {
        self.report(|s| {
            s.last_percent = 100;
            Some((s.name.clone(), 1.0))
        });
    }

    /// The process's peak resident memory so far (not reset per stage: that is process-wide state
    /// the Python process owns).
    fn stage_peak_rss_bytes(&self, _stage: &str) -> Option<u64> {
        echosurf::resources::read_status_kib("VmHWM:").map(|kib| kib * 1024)
    }
}
