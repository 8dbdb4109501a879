//! Time and memory accounting per pipeline stage, for `--report` and the benchmarks.
//!
//! Peak memory is the process's resident-set high-water mark (`VmHWM` in `/proc/self/status`). Linux lets
//! a process reset that mark (`echo 5 > /proc/self/clear_refs`), which gives a true per-stage peak; where
//! that is unavailable the lifetime peak is reported instead and flagged as such.

use std::time::Instant;

/// A zeroed buffer of `n` elements, or a [`crate::Error::ResourceLimit`] naming `what` when the
/// allocation fails (instead of the abort a plain `vec!` gives under `ulimit -v` or overcommit limits).
pub fn try_zeroed_vec<T: Clone + Default>(n: usize, what: &str) -> crate::Result<Vec<T>> {
    let mut v = Vec::new();
    v.try_reserve_exact(n).map_err(|_| {
        crate::Error::ResourceLimit(format!(
            "{what}: could not allocate {n} x {} bytes",
            std::mem::size_of::<T>()
        ))
    })?;
    v.resize(n, T::default());
    Ok(v)
}

/// Resident-set high-water mark of this process in bytes, if the platform reports it.
pub fn peak_rss_bytes() -> Option<u64> {
    read_status_kib("VmHWM:").map(|k| k * 1024)
}

/// Current resident set size in bytes, if the platform reports it.
pub fn current_rss_bytes() -> Option<u64> {
    read_status_kib("VmRSS:").map(|k| k * 1024)
}

fn read_status_kib(key: &str) -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with(key))?;
    line[key.len()..]
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()
        .ok()
}

/// Resets the high-water mark to the current RSS; false where the platform does not allow it.
pub fn reset_peak_rss() -> bool {
    std::fs::write("/proc/self/clear_refs", b"5").is_ok()
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

/// Measures consecutive stages: call [`StageMeter::stage`] around each one.
#[derive(Debug, Default)]
pub struct StageMeter {
    pub stages: Vec<StageUsage>,
}

impl StageMeter {
    pub fn new() -> Self {
        Self::default()
    }

    /// Runs `work` as the stage `name`, recording its time and peak memory.
    pub fn stage<T>(&mut self, name: &str, work: impl FnOnce() -> T) -> T {
        let per_stage = reset_peak_rss();
        let start = Instant::now();
        let out = work();
        self.stages.push(StageUsage {
            stage: name.to_string(),
            seconds: start.elapsed().as_secs_f64(),
            peak_rss_bytes: peak_rss_bytes(),
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
    fn stage_meter_records_every_stage_in_order() {
        let mut meter = StageMeter::new();
        let v = meter.stage("alloc", || {
            let big = vec![1u8; 32 << 20];
            big.iter().map(|&b| b as u64).sum::<u64>()
        });
        assert_eq!(v, 32 << 20);
        meter.stage("idle", || ());
        assert_eq!(meter.stages.len(), 2);
        assert_eq!(meter.stages[0].stage, "alloc");
        if let (Some(alloc_peak), true) = (
            meter.stages[0].peak_rss_bytes,
            meter.stages[0].peak_is_per_stage,
        ) {
            // The 32 MiB buffer was resident during the first stage.
            assert!(alloc_peak >= 32 << 20, "{alloc_peak}");
        }
    }
}
