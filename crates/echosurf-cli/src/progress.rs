//! indicatif progress bars behind the library's [`echosurf::progress::Progress`] callback.

use std::sync::Mutex;

use echosurf::progress::Progress;
use indicatif::{ProgressBar, ProgressStyle};

/// Draws one bar per stage on stderr; silent when stderr is not a terminal (CI, pipes).
#[derive(Debug, Default)]
pub struct BarProgress {
    bar: Mutex<Option<ProgressBar>>,
}

#[allow(dead_code)]
impl BarProgress {
    pub fn new() -> Self {
        Self::default()
    }
}

impl Progress for BarProgress {
    fn start(&self, stage: &str, total: u64) {
        let bar = if total > 0 {
            ProgressBar::new(total)
        } else {
            ProgressBar::new_spinner()
        };
        let style =
            ProgressStyle::with_template("{msg:>10} [{bar:30}] {pos}/{len} {elapsed_precise}")
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .progress_chars("=> ");
        bar.set_style(style);
        bar.set_message(stage.to_string());
        if let Ok(mut slot) = self.bar.lock() {
            if let Some(old) = slot.take() {
                old.finish_and_clear();
            }
            *slot = Some(bar);
        }
    }

    fn advance(&self, done: u64) {
        if let Ok(slot) = self.bar.lock()
            && let Some(bar) = slot.as_ref()
        {
            bar.set_position(done);
        }
    }

    fn finish(&self) {
        if let Ok(mut slot) = self.bar.lock()
            && let Some(bar) = slot.take()
        {
            bar.finish_and_clear();
        }
    }

    fn stage_started(&self, stage: &str) -> bool {
        crate::memory::StageMemory.stage_started(stage)
    }

    fn stage_peak_rss_bytes(&self, stage: &str) -> Option<u64> {
        crate::memory::StageMemory.stage_peak_rss_bytes(stage)
    }

    fn memory_estimate(&self, bytes: u64) {
        crate::memory::record_estimate(bytes);
    }
}
