//! Progress reporting from long library stages without tying the library to a terminal.

/// Receives progress from a long stage. The CLI maps it onto indicatif bars; tests ignore it.
pub trait Progress: Sync {
    /// A stage named `stage` starts; `total` units of work are expected (0 if unknown).
    fn start(&self, stage: &str, total: u64);
    /// `done` of `total` units of the current stage are complete.
    fn advance(&self, done: u64);
    /// The current stage is finished.
    fn finish(&self);
    /// A measured pipeline stage (`poses`, `segment`, `samples`, `fit`, ...) starts. Returns true when
    /// the caller measures this stage's peak memory alone (the CLI resets the process's high-water
    /// mark here); the library itself measures nothing process-wide.
    fn stage_started(&self, _stage: &str) -> bool {
        false
    }
    /// The measured stage `stage` ended: the peak resident memory (bytes) the caller measured for it
    /// (or for the process so far, where [`Progress::stage_started`] returned false), if it measures.
    fn stage_peak_rss_bytes(&self, _stage: &str) -> Option<u64> {
        None
    }
    /// A memory-budget check compared `bytes`, its estimate of the run's peak resident memory (an
    /// application may keep the largest: the CLI's `--memory-report`).
    fn memory_estimate(&self, _bytes: u64) {}
}

/// Progress sink that discards everything.
#[derive(Debug, Default, Clone, Copy)]
pub struct NoProgress;

impl Progress for NoProgress {
    fn start(&self, _stage: &str, _total: u64) {}
    fn advance(&self, _done: u64) {}
    fn finish(&self) {}
}
