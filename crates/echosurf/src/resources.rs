//! Time accounting per pipeline stage (for `--report` and the benchmarks), fallible allocation, and
//! the resident size the memory budgets start from.
//!
//! Peak memory per stage is measured by the caller, not here: it needs process-wide state (Linux's
//! resettable high-water mark), which belongs to the application. The library announces each stage
//! through [`Progress::stage_started`] and records what the caller measured
//! (docs/decisions/0033-library-state.md).

use std::cell::Cell;
use std::time::Instant;

use crate::progress::{NoProgress, Progress};

thread_local! {
    /// How many [`fallibly`] calls this thread is inside. Thread-local state, kept on purpose: a
    /// global allocator is told nothing but the layout, so the only way for a `try_reserve` to say
    /// "I handle failure" is state of the allocating thread; per thread and scoped to one call, it is
    /// not shared by concurrent runs (docs/decisions/0033-library-state.md).
    static FALLIBLE_DEPTH: Cell<u32> = const { Cell::new(0) };
}

/// Leaves the [`fallibly`] scope when dropped, so a panic inside it does not leave the thread marked.
struct FallibleScope;

impl Drop for FallibleScope {
    fn drop(&mut self) {
        FALLIBLE_DEPTH.with(|d| d.set(d.get() - 1));
    }
}

/// Runs `reserve` (a `try_reserve` whose failure the caller turns into an error) telling a process's
/// global allocator that a failed allocation here is handled: it should return null rather than end
/// the process (the CLI's allocator ends it cleanly on any other failure).
pub fn fallibly<T>(reserve: impl FnOnce() -> T) -> T {
    FALLIBLE_DEPTH.with(|d| d.set(d.get() + 1));
    let _scope = FallibleScope;
    reserve()
}

/// True inside [`fallibly`] on this thread (for a global allocator's failure path).
pub fn allocation_is_fallible() -> bool {
    FALLIBLE_DEPTH.try_with(|d| d.get() > 0).unwrap_or(false)
}

/// A zeroed buffer of `n` elements, or a [`crate::Error::ResourceLimit`] naming `what` when the
/// allocation fails (instead of the abort a plain `vec!` gives under `ulimit -v` or overcommit limits).
pub fn try_zeroed_vec<T: Clone + Default>(n: usize, what: &str) -> crate::Result<Vec<T>> {
    let mut v = Vec::new();
    crate::resources::fallibly(|| v.try_reserve_exact(n)).map_err(|_| {
        crate::Error::ResourceLimit(format!(
            "{what}: could not allocate {n} x {} bytes",
            std::mem::size_of::<T>()
        ))
    })?;
    v.resize(n, T::default());
    Ok(v)
}

/// Fraction of the machine's memory a run may plan to use by default.
const DEFAULT_BUDGET_FRACTION: f64 = 0.5;
/// Budget when the machine's memory cannot be read.
const FALLBACK_BUDGET_BYTES: u64 = 8 << 30;

/// The default memory budget: half of `MemTotal` from `/proc/meminfo`, or 8 GiB where that is
/// unavailable (also `budget::default_memory_budget_bytes`).
pub fn default_memory_budget_bytes() -> u64 {
    std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|text| {
            let line = text.lines().find(|l| l.starts_with("MemTotal:"))?;
            let kib: u64 = line["MemTotal:".len()..]
                .trim()
                .trim_end_matches("kB")
                .trim()
                .parse()
                .ok()?;
            Some((kib as f64 * 1024.0 * DEFAULT_BUDGET_FRACTION) as u64)
        })
        .unwrap_or(FALLBACK_BUDGET_BYTES)
}

/// Current resident set size in bytes, if the platform reports it.
pub fn current_rss_bytes() -> Option<u64> {
    read_status_kib("VmRSS:").map(|k| k * 1024)
}

/// A `kB` field of `/proc/self/status` (e.g. `"VmHWM:"`), if the platform reports it. Reads only.
pub fn read_status_kib(key: &str) -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with(key))?;
    line[key.len()..]
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()
        .ok()
}

/// Wall time and peak memory of one stage.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct StageUsage {
    pub stage: String,
    pub seconds: f64,
    /// Peak resident memory during the stage (bytes), or the process's lifetime peak when
    /// `peak_is_per_stage` is false.
    pub peak_rss_bytes: Option<u64>,
    pub peak_is_per_stage: bool,
}

/// Measures consecutive stages: call [`StageMeter::stage`] around each one. The observer is told when
/// each stage starts and ends and may report its peak memory.
pub struct StageMeter<'a> {
    pub stages: Vec<StageUsage>,
    observer: &'a dyn Progress,
}

impl std::fmt::Debug for StageMeter<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("StageMeter")
            .field("stages", &self.stages)
            .finish_non_exhaustive()
    }
}

impl Default for StageMeter<'_> {
    fn default() -> Self {
        Self::new(&NoProgress)
    }
}

impl<'a> StageMeter<'a> {
    /// The observer the stages are announced to.
    pub fn observer(&self) -> &'a dyn Progress {
        self.observer
    }

    /// A meter announcing its stages to `observer` (the caller's progress sink).
    pub fn new(observer: &'a dyn Progress) -> Self {
        Self {
            stages: Vec::new(),
            observer,
        }
    }

    /// Runs `work` as the stage `name`, recording its time and the peak memory the observer measured.
    pub fn stage<T>(&mut self, name: &str, work: impl FnOnce() -> T) -> T {
        let per_stage = self.observer.stage_started(name);
        let start = Instant::now();
        let out = work();
        let seconds = start.elapsed().as_secs_f64();
        self.stages.push(StageUsage {
            stage: name.to_string(),
            seconds,
            peak_rss_bytes: self.observer.stage_peak_rss_bytes(name),
            peak_is_per_stage: per_stage,
        });
        out
    }

    pub fn total_seconds(&self) -> f64 {
        self.stages.iter().map(|s| s.seconds).sum()
    }

    /// Largest peak over all stages.
    pub fn peak_rss_bytes(&self) -> Option<u64> {
        self.stages.iter().filter_map(|s| s.peak_rss_bytes).max()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fallibly_marks_only_its_own_call() {
        assert!(!allocation_is_fallible());
        assert!(fallibly(allocation_is_fallible));
        assert!(fallibly(
            || fallibly(allocation_is_fallible) && allocation_is_fallible()
        ));
        assert!(!allocation_is_fallible());
        // A panic inside the scope leaves the thread unmarked.
        let caught = std::panic::catch_unwind(|| fallibly(|| panic!("inside")));
        assert!(caught.is_err());
        assert!(!allocation_is_fallible());
    }

    #[test]
    fn the_default_budget_is_half_the_machine_or_the_fallback() {
        let b = default_memory_budget_bytes();
        assert!(b >= 64 << 20, "{b}");
    }

    /// Counts the announcements and reports a made-up peak per stage.
    #[derive(Default)]
    struct Recorder {
        started: std::sync::Mutex<Vec<String>>,
    }

    impl Progress for Recorder {
        fn start(&self, _stage: &str, _total: u64) {}
        fn advance(&self, _done: u64) {}
        fn finish(&self) {}
        fn stage_started(&self, stage: &str) -> bool {
            self.started.lock().unwrap().push(stage.into());
            true
        }
        fn stage_peak_rss_bytes(&self, stage: &str) -> Option<u64> {
            Some(1000 * stage.len() as u64)
        }
    }

    #[test]
    fn stage_meter_records_every_stage_in_order_with_the_observers_peaks() {
        let recorder = Recorder::default();
        let mut meter = StageMeter::new(&recorder);
        let v = meter.stage("alloc", || 7);
        assert_eq!(v, 7);
        meter.stage("idle", || ());
        assert_eq!(*recorder.started.lock().unwrap(), ["alloc", "idle"]);
        let names: Vec<_> = meter.stages.iter().map(|s| s.stage.as_str()).collect();
        assert_eq!(names, ["alloc", "idle"]);
        assert_eq!(meter.stages[0].peak_rss_bytes, Some(5000));
        assert!(meter.stages[0].peak_is_per_stage);
        assert_eq!(meter.peak_rss_bytes(), Some(5000));
        // Without an observer that measures, no peak is claimed.
        let mut silent = StageMeter::default();
        silent.stage("alloc", || ());
        assert_eq!(silent.stages[0].peak_rss_bytes, None);
        assert!(!silent.stages[0].peak_is_per_stage);
    }
}
