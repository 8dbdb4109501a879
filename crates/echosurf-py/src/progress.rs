//! The library's progress hook for Python: runs the work on a worker thread with the GIL released,
//! calls the user's `progress(stage, fraction)` (taking the GIL only for the call), and stops the work
//! when the callback raises or Ctrl-C arrives.
//!
//! The calling thread waits for the worker and looks for signals (which Python delivers to the main
//! thread only) every [`SIGNAL_CHECK_INTERVAL`]. The library has no cancellation hook, so stopping
//! unwinds out of it from its next progress call with [`std::panic::resume_unwind`] (which runs no
//! panic hook and prints nothing); rayon carries the unwind from its threads to the worker, where
//! [`PyProgress::run`] catches it. The library writes no file during `extract` or `fit` here, so
//! nothing is left half-written.

use std::panic::AssertUnwindSafe;
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{RecvTimeoutError, channel};
use std::time::Duration;

use echosurf::progress::Progress;
use pyo3::exceptions::PyKeyboardInterrupt;
use pyo3::prelude::*;

use crate::EchosurfError;

/// How often the waiting thread looks for Ctrl-C.
const SIGNAL_CHECK_INTERVAL: Duration = Duration::from_millis(50);

/// Stack of the worker thread: that of a main thread, as the CLI runs the same work on its main thread.
const WORKER_STACK_BYTES: usize = 8 << 20;

/// The unwind payload that stops the library's work.
struct Stop;

/// The stage being reported.
#[derive(Debug)]
struct Stage {
    name: String,
    total: u64,
    /// Last fraction handed to the callback, in hundredths.
    last_percent: i64,
}

/// Forwards the library's progress to an optional Python callable.
#[derive(Debug)]
pub struct PyProgress {
    callback: Option<Py<PyAny>>,
    stage: Mutex<Stage>,
    /// Set when the work must stop; the next progress call unwinds.
    stopping: AtomicBool,
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
            }),
            stopping: AtomicBool::new(false),
            error: Mutex::new(None),
        }
    }

    /// Runs `work` on a worker thread with the GIL released. A library error becomes
    /// [`EchosurfError`] with its message; an exception from the callback, or Ctrl-C, stops the work
    /// and is raised as is.
    pub fn run<T: Send>(
        &self,
        py: Python<'_>,
        work: impl FnOnce() -> Result<T, String> + Send,
    ) -> PyResult<T> {
        let (sender, receiver) = channel();
        // Only this thread receives; the mutex makes the receiver shareable with `detach`.
        let receiver = Mutex::new(receiver);
        let outcome = std::thread::scope(|scope| {
            std::thread::Builder::new()
                .name("echosurf".into())
                .stack_size(WORKER_STACK_BYTES)
                .spawn_scoped(scope, move || {
                    // The receiver outlives the worker: sending cannot fail.
                    let _ = sender.send(std::panic::catch_unwind(AssertUnwindSafe(work)));
                })
                .map_err(|e| EchosurfError::new_err(format!("starting a worker thread: {e}")))?;
            loop {
                let received = py.detach(|| match receiver.lock() {
                    Ok(r) => r.recv_timeout(SIGNAL_CHECK_INTERVAL),
                    Err(_) => Err(RecvTimeoutError::Disconnected),
                });
                match received {
                    Ok(result) => return Ok(result),
                    Err(RecvTimeoutError::Timeout) => {
                        if let Err(signal) = py.check_signals() {
                            self.stop(signal);
                        }
                    }
                    Err(RecvTimeoutError::Disconnected) => {
                        return Err(EchosurfError::new_err(
                            "the worker thread ended without a result",
                        ));
                    }
                }
            }
        })?;
        let stopped = self.take_error();
        match outcome {
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

    /// Keeps the first reason to stop and tells the work to stop.
    fn stop(&self, error: PyErr) {
        if let Ok(mut slot) = self.error.lock() {
            slot.get_or_insert(error);
        }
        self.stopping.store(true, Ordering::SeqCst);
    }

    fn take_error(&self) -> Option<PyErr> {
        self.error.lock().ok().and_then(|mut slot| slot.take())
    }

    /// Unwinds out of the library when the work must stop; else hands the fraction `update` gives
    /// (if any) to the callback.
    fn report(&self, update: impl FnOnce(&mut Stage) -> Option<(String, f64)>) {
        if self.stopping.load(Ordering::SeqCst) {
            std::panic::resume_unwind(Box::new(Stop));
        }
        let Some(callback) = &self.callback else {
            return;
        };
        let call = match self.stage.lock() {
            Ok(mut stage) => update(&mut stage),
            Err(_) => None,
        };
        let Some((name, fraction)) = call else {
            return;
        };
        if let Err(error) = Python::attach(|py| callback.call1(py, (name, fraction))) {
            self.stop(error);
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
