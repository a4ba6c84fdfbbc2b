//! Run-wide counters that tell the lifecycle when a pipeline is busy, drained or finished.
//!
//! `pending` counts messages queued on any edge or being handled by a stage. A stage pushes
//! its outputs before the message it is handling is released, so `pending` can only reach
//! zero when no message is anywhere in the pipeline. `tickers` counts stages with a tick
//! scheduled or running; `ticking` counts ticks running now.

use std::sync::atomic::{AtomicBool, AtomicI64, Ordering};

/// Shared run state, one per cluster run.
#[derive(Debug, Default)]
pub struct RunControl {
    stopping: AtomicBool,
    pending: AtomicI64,
    tickers: AtomicI64,
    ticking: AtomicI64,
}

impl RunControl {
    /// Whether the run is draining: sources must stop producing.
    pub fn is_stopping(&self) -> bool {
        self.stopping.load(Ordering::SeqCst)
    }

    pub(crate) fn begin_stopping(&self) {
        self.stopping.store(true, Ordering::SeqCst);
    }

    /// Messages queued or in a handler anywhere in the pipeline.
    pub fn pending(&self) -> i64 {
        self.pending.load(Ordering::SeqCst)
    }

    pub(crate) fn add_pending(&self) {
        self.pending.fetch_add(1, Ordering::SeqCst);
    }

    pub(crate) fn done_pending(&self) {
        self.pending.fetch_sub(1, Ordering::SeqCst);
    }

    pub(crate) fn add_ticker(&self) {
        self.tickers.fetch_add(1, Ordering::SeqCst);
    }

    pub(crate) fn done_ticker(&self) {
        self.tickers.fetch_sub(1, Ordering::SeqCst);
    }

    /// Enters a tick; returns false (and enters nothing) when the run is stopping.
    pub(crate) fn enter_tick(&self) -> bool {
        self.ticking.fetch_add(1, Ordering::SeqCst);
        if self.is_stopping() {
            self.ticking.fetch_sub(1, Ordering::SeqCst);
            return false;
        }
        true
    }

    pub(crate) fn leave_tick(&self) {
        self.ticking.fetch_sub(1, Ordering::SeqCst);
    }

    /// True when nothing is queued, nothing is handled and no tick runs.
    pub fn is_drained(&self) -> bool {
        self.ticking.load(Ordering::SeqCst) == 0 && self.pending() == 0
    }

    /// True when, in addition, no stage will tick again: the pipeline finished by itself.
    pub fn is_finished(&self) -> bool {
        self.tickers.load(Ordering::SeqCst) == 0 && self.is_drained()
    }
}
