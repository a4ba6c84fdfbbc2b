//! The stage toolkit: what every stage needs and none should write again — a fixed
//! [`Cadence`] of ticks with overruns counted, a [`Latency`] histogram read in milliseconds,
//! typed [`Port`]s (a port's name and message type declared once, used by the kind's
//! declaration, by `send` and by `Input::on`), and [`lock`] for mutexes shared with blocking
//! threads.
//!
//! Nothing here reads a clock it is not given: [`Cadence::end_tick_at`] takes `now`, so cadences
//! are tested in virtual time; [`Cadence::end_tick`] is the same with `Instant::now()`.

use std::marker::PhantomData;
use std::sync::{Mutex, MutexGuard};
use std::time::{Duration, Instant};

use hdrhistogram::Histogram;

use crate::stage::NextTick;

/// A fixed-rate tick: each tick is due one `interval` after the previous one was due, so
/// work that takes part of the interval does not slow the rate down. A tick whose work ends
/// after the next one was due is an **overrun**: the next tick then comes at once and the
/// cadence goes on from there (no burst of catch-up ticks).
///
/// A cadence made [`Cadence::catching_up`] instead keeps its average rate: after an overrun
/// it ticks at once until it is back on schedule (a source offering a fixed message rate).
///
/// Use: call [`Cadence::end_tick`] at the end of each tick's work and return what it gives.
#[derive(Clone, Debug)]
pub struct Cadence {
    interval: Duration,
    due: Option<Instant>,
    catch_up: bool,
    ticks: u64,
    overruns: u64,
}

impl Cadence {
    /// A cadence of one tick every `interval` (zero: as fast as the work allows, never an
    /// overrun).
    pub fn new(interval: Duration) -> Self {
        Cadence {
            interval,
            due: None,
            catch_up: false,
            ticks: 0,
            overruns: 0,
        }
    }

    /// One tick every `interval_ms` milliseconds (negative or non-finite: zero).
    pub fn every_ms(interval_ms: f64) -> Self {
        let s = interval_ms / 1000.0;
        Self::new(if s.is_finite() && s > 0.0 {
            Duration::from_secs_f64(s)
        } else {
            Duration::ZERO
        })
    }

    /// `hz` ticks a second (not positive or not finite: as fast as the work allows).
    pub fn hz(hz: f64) -> Self {
        Self::every_ms(if hz > 0.0 { 1000.0 / hz } else { 0.0 })
    }

    /// The same cadence, but ticks missed by an overrun are made up at once, so the number
    /// of ticks keeps to the rate on average.
    pub fn catching_up(mut self) -> Self {
        self.catch_up = true;
        self
    }

    /// The interval between ticks.
    pub fn interval(&self) -> Duration {
        self.interval
    }

    /// Marks the start of the first tick (later calls do nothing). Optional: without it the
    /// first tick counts as due when it ends.
    pub fn begin_at(&mut self, now: Instant) {
        self.due.get_or_insert(now);
    }

    /// [`Cadence::begin_at`] now.
    pub fn begin(&mut self) {
        self.begin_at(Instant::now());
    }

    /// Ends a tick whose work finished at `now`: when the next one is due.
    pub fn end_tick_at(&mut self, now: Instant) -> NextTick {
        let due = *self.due.get_or_insert(now);
        self.ticks += 1;
        let target = due + self.interval;
        if target < now && !self.interval.is_zero() {
            self.overruns += 1;
        }
        let next = if self.catch_up {
            target
        } else {
            target.max(now)
        };
        self.due = Some(next);
        NextTick::After(next.saturating_duration_since(now))
    }

    /// [`Cadence::end_tick_at`] now.
    pub fn end_tick(&mut self) -> NextTick {
        self.end_tick_at(Instant::now())
    }

    /// Ticks ended so far.
    pub fn ticks(&self) -> u64 {
        self.ticks
    }

    /// Ticks whose work ran past the next tick's due time.
    pub fn overruns(&self) -> u64 {
        self.overruns
    }
}

/// A histogram of durations (microsecond resolution, 3 significant digits) read in
/// milliseconds; an empty one reads 0.
#[derive(Clone, Debug)]
pub struct Latency {
    us: Histogram<u64>,
}

impl Default for Latency {
    fn default() -> Self {
        Latency {
            us: Histogram::new(3).expect("3 significant digits is valid"),
        }
    }
}

impl Latency {
    /// An empty histogram.
    pub fn new() -> Self {
        Self::default()
    }

    /// Records `d` (at least 1 µs).
    pub fn record(&mut self, d: Duration) {
        // Auto-resizing histogram: recording a positive value cannot fail.
        let _ = self.us.record((d.as_micros() as u64).max(1));
    }

    /// Records `seconds` (negative and non-finite values are ignored).
    pub fn record_s(&mut self, seconds: f64) {
        if seconds.is_finite() && seconds >= 0.0 {
            let _ = self.us.record(((seconds * 1e6) as u64).max(1));
        }
    }

    /// Values recorded.
    pub fn count(&self) -> u64 {
        self.us.len()
    }

    /// Whether nothing was recorded.
    pub fn is_empty(&self) -> bool {
        self.us.is_empty()
    }

    /// The `q` quantile (0..=1), ms.
    pub fn quantile_ms(&self, q: f64) -> f64 {
        if self.us.is_empty() {
            0.0
        } else {
            self.us.value_at_quantile(q) as f64 / 1000.0
        }
    }

    /// Median, ms.
    pub fn p50_ms(&self) -> f64 {
        self.quantile_ms(0.5)
    }

    /// 99th percentile, ms.
    pub fn p99_ms(&self) -> f64 {
        self.quantile_ms(0.99)
    }

    /// Mean, ms.
    pub fn mean_ms(&self) -> f64 {
        if self.us.is_empty() {
            0.0
        } else {
            self.us.mean() / 1000.0
        }
    }

    /// Largest value, ms.
    pub fn max_ms(&self) -> f64 {
        if self.us.is_empty() {
            0.0
        } else {
            self.us.max() as f64 / 1000.0
        }
    }

    /// Adds every value of `other`.
    pub fn merge(&mut self, other: &Latency) {
        let _ = self.us.add(&other.us);
    }
}

/// A stage port: its name and the message type it carries, declared once as a constant
/// (`pub const OUT: Port<FrameMsg> = Port::new("out");`) and used by the kind's
/// declaration ([`StageKind::output`](crate::StageKind::output)), by
/// [`StageCtx::send`](crate::StageCtx::send) and by [`Input::on`](crate::Input::on), so a
/// port's name is written once and a message of another type does not compile.
pub struct Port<T> {
    name: &'static str,
    ty: PhantomData<fn() -> T>,
}

impl<T> Port<T> {
    /// The port named `name`.
    pub const fn new(name: &'static str) -> Self {
        Port {
            name,
            ty: PhantomData,
        }
    }

    /// The port's name.
    pub const fn name(&self) -> &'static str {
        self.name
    }
}

impl<T> Clone for Port<T> {
    fn clone(&self) -> Self {
        *self
    }
}

impl<T> Copy for Port<T> {}

impl<T> std::fmt::Debug for Port<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Port({}: {})", self.name, std::any::type_name::<T>())
    }
}

/// Locks `m`, taking the value even if a thread panicked while holding it: a panic in a
/// kernel fails its stage anyway, and what it left behind is still readable for the report.
pub fn lock<T: ?Sized>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ms(v: u64) -> Duration {
        Duration::from_millis(v)
    }

    #[test]
    fn cadence_keeps_its_rate_when_work_takes_part_of_the_interval() {
        let t0 = Instant::now();
        let mut c = Cadence::every_ms(100.0);
        c.begin_at(t0);
        // Work of 30 ms: the next tick is 70 ms away, due at 100 ms.
        assert_eq!(c.end_tick_at(t0 + ms(30)), NextTick::After(ms(70)));
        // The second tick started at 100 ms and worked 90 ms: 10 ms to go.
        assert_eq!(c.end_tick_at(t0 + ms(190)), NextTick::After(ms(10)));
        assert_eq!((c.ticks(), c.overruns()), (2, 0));
    }

    #[test]
    fn cadence_counts_an_overrun_and_goes_on_without_a_burst() {
        let t0 = Instant::now();
        let mut c = Cadence::every_ms(100.0);
        c.begin_at(t0);
        // 350 ms of work: three ticks missed, one overrun, the next tick at once.
        assert_eq!(c.end_tick_at(t0 + ms(350)), NextTick::After(Duration::ZERO));
        assert_eq!(c.overruns(), 1);
        // From then on the cadence counts from 350 ms, not from 0.
        assert_eq!(c.end_tick_at(t0 + ms(360)), NextTick::After(ms(90)));
        assert_eq!((c.ticks(), c.overruns()), (2, 1));
    }

    #[test]
    fn a_catching_up_cadence_makes_up_missed_ticks() {
        let t0 = Instant::now();
        let mut c = Cadence::every_ms(100.0).catching_up();
        c.begin_at(t0);
        // 250 ms of work: ticks due at 100 and 200 ms come at once, then 300 ms on time.
        assert_eq!(c.end_tick_at(t0 + ms(250)), NextTick::After(Duration::ZERO));
        assert_eq!(c.end_tick_at(t0 + ms(251)), NextTick::After(Duration::ZERO));
        assert_eq!(c.end_tick_at(t0 + ms(252)), NextTick::After(ms(48)));
        assert_eq!((c.ticks(), c.overruns()), (3, 2));
    }

    #[test]
    fn cadence_without_begin_starts_when_the_first_tick_ends() {
        let t0 = Instant::now();
        let mut c = Cadence::hz(10.0);
        assert_eq!(c.end_tick_at(t0), NextTick::After(ms(100)));
        let mut fast = Cadence::every_ms(0.0);
        fast.begin_at(t0);
        assert_eq!(
            fast.end_tick_at(t0 + ms(5)),
            NextTick::After(Duration::ZERO)
        );
        assert_eq!(fast.overruns(), 0, "a zero interval never overruns");
        assert_eq!(Cadence::every_ms(f64::NAN).interval(), Duration::ZERO);
        assert_eq!(Cadence::hz(-1.0).interval(), Duration::ZERO);
    }

    #[test]
    fn latency_reads_milliseconds_and_empty_reads_zero() {
        let mut l = Latency::new();
        assert_eq!(
            (l.p50_ms(), l.p99_ms(), l.mean_ms(), l.max_ms()),
            (0.0, 0.0, 0.0, 0.0)
        );
        for i in 1..=100 {
            l.record(ms(i));
        }
        l.record_s(f64::NAN);
        l.record_s(-1.0);
        assert_eq!(l.count(), 100);
        assert!((l.p50_ms() - 50.0).abs() < 0.1, "{}", l.p50_ms());
        assert!((l.p99_ms() - 99.0).abs() < 0.1, "{}", l.p99_ms());
        assert!((l.mean_ms() - 50.5).abs() < 0.1, "{}", l.mean_ms());
        assert!((l.max_ms() - 100.0).abs() < 0.1, "{}", l.max_ms());
        let mut m = Latency::new();
        m.record_s(0.2);
        m.merge(&l);
        assert_eq!(m.count(), 101);
        assert!((m.max_ms() - 200.0).abs() < 0.2);
    }

    #[test]
    fn lock_survives_a_panic_in_another_holder() {
        let m = std::sync::Arc::new(Mutex::new(5));
        let m2 = m.clone();
        let _ = std::thread::spawn(move || {
            let _g = m2.lock().unwrap();
            panic!("kernel failed");
        })
        .join();
        assert!(m.is_poisoned());
        assert_eq!(*lock(&m), 5);
    }
}
