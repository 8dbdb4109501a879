//! Peak memory per pipeline stage, measured by the application because it needs process-wide state:
//! the resident-set high-water mark (`VmHWM` in `/proc/self/status`), which Linux lets a process reset
//! (`echo 5 > /proc/self/clear_refs`) for a true per-stage peak. Where that is unavailable the lifetime
//! peak is reported instead and flagged as such. The library announces its stages through
//! [`echosurf::progress::Progress::stage_started`] and records what this measures.

use std::sync::atomic::{AtomicU64, Ordering};

/// The highest `VmHWM` seen before any [`reset_peak_rss`] (bytes), so the lifetime peak survives the
/// per-stage resets.
static PEAK_BEFORE_RESETS_BYTES: AtomicU64 = AtomicU64::new(0);

/// The largest estimate a memory-budget check of this run compared, for `--memory-report` (0: none).
static LARGEST_ESTIMATE_BYTES: AtomicU64 = AtomicU64::new(0);

/// Keeps `bytes` when it is the largest estimate yet (the library tells each through
/// [`echosurf::progress::Progress::memory_estimate`]).
pub fn record_estimate(bytes: u64) {
    LARGEST_ESTIMATE_BYTES.fetch_max(bytes, Ordering::Relaxed);
}

/// The largest estimate a budget check of this process made, if any made one.
pub fn largest_estimate_bytes() -> Option<u64> {
    match LARGEST_ESTIMATE_BYTES.load(Ordering::Relaxed) {
        0 => None,
        b => Some(b),
    }
}

/// Resident-set high-water mark of this process in bytes, if the platform reports it.
pub fn peak_rss_bytes() -> Option<u64> {
    echosurf::resources::read_status_kib("VmHWM:").map(|kib| kib * 1024)
}

/// Resets the high-water mark to the current RSS; false where the platform does not allow it. The
/// mark before the reset is kept for [`lifetime_peak_rss_bytes`].
pub fn reset_peak_rss() -> bool {
    if let Some(peak) = peak_rss_bytes() {
        PEAK_BEFORE_RESETS_BYTES.fetch_max(peak, Ordering::Relaxed);
    }
    std::fs::write("/proc/self/clear_refs", b"5").is_ok()
}

/// Resident-set high-water mark over the whole process so far (bytes), per-stage resets included; a
/// reset lowers `VmHWM` and with it what `getrusage` and `/usr/bin/time` report.
pub fn lifetime_peak_rss_bytes() -> Option<u64> {
    let before = PEAK_BEFORE_RESETS_BYTES.load(Ordering::Relaxed);
    match peak_rss_bytes() {
        Some(now) => Some(now.max(before)),
        None => (before > 0).then_some(before),
    }
}

/// Measures each announced stage's peak memory and draws nothing (batch rows, benchmarks).
#[derive(Debug, Default, Clone, Copy)]
pub struct StageMemory;

impl echosurf::progress::Progress for StageMemory {
    fn start(&self, _stage: &str, _total: u64) {}
    fn advance(&self, _done: u64) {}
    fn finish(&self) {}
    fn stage_started(&self, _stage: &str) -> bool {
        reset_peak_rss()
    }
    fn stage_peak_rss_bytes(&self, _stage: &str) -> Option<u64> {
        peak_rss_bytes()
    }
    fn memory_estimate(&self, bytes: u64) {
        record_estimate(bytes);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use echosurf::resources::StageMeter;

    #[test]
    fn stage_peaks_see_the_stages_buffers_and_the_lifetime_peak_keeps_them() {
        let mut meter = StageMeter::new(&StageMemory);
        let v = meter.stage("alloc", || {
            let big = vec![1u8; 32 << 20];
            big.iter().map(|&b| b as u64).sum::<u64>()
        });
        assert_eq!(v, 32 << 20);
        meter.stage("idle", || ());
        assert_eq!(meter.stages.len(), 2);
        if let Some(lifetime) = lifetime_peak_rss_bytes() {
            assert!(
                lifetime >= meter.peak_rss_bytes().unwrap_or(0),
                "{lifetime}"
            );
        }
        if let (Some(alloc_peak), true) = (
            meter.stages[0].peak_rss_bytes,
            meter.stages[0].peak_is_per_stage,
        ) {
            // The 32 MiB buffer was resident during the first stage.
            assert!(alloc_peak >= 32 << 20, "{alloc_peak}");
        }
    }
}
