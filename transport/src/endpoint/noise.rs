//! Rate-limited logging of bad datagrams: the first of each kind in a window is logged with
//! its details, the rest are counted and summarised once per window, so a flood of garbage
//! costs a few log lines, not one per datagram.

use std::time::{Duration, Instant};

/// Length of a logging window.
const WINDOW: Duration = Duration::from_secs(10);

pub(crate) struct Noise {
    window_end: Instant,
    /// (what, count in this window) for the kinds seen in this window.
    counts: Vec<(&'static str, u64)>,
}

impl Noise {
    pub(crate) fn new(now: Instant) -> Self {
        Noise {
            window_end: now + WINDOW,
            counts: Vec::new(),
        }
    }

    /// Notes one occurrence of `what`; `detail` is only formatted for the first in a window.
    pub(crate) fn note(
        &mut self,
        now: Instant,
        what: &'static str,
        detail: impl FnOnce() -> String,
    ) {
        self.flush(now);
        match self.counts.iter_mut().find(|(w, _)| *w == what) {
            Some((_, n)) => *n += 1,
            None => {
                tracing::warn!(
                    "{what}: {} (further ones are summarised every {WINDOW:?})",
                    detail()
                );
                self.counts.push((what, 1));
            }
        }
    }

    /// Writes the summary of a window that has ended.
    pub(crate) fn flush(&mut self, now: Instant) {
        if now < self.window_end {
            return;
        }
        for (what, n) in self.counts.drain(..) {
            if n > 1 {
                tracing::warn!("{what}: {n} in the last {WINDOW:?}");
            }
        }
        self.window_end = now + WINDOW;
    }

    /// When the current window ends (only matters while something was noted).
    pub(crate) fn next_flush(&self) -> Instant {
        if self.counts.is_empty() {
            self.window_end + WINDOW * 1000
        } else {
            self.window_end
        }
    }
}
