//! The run-wide scene clock.
//!
//! Scene state is a pure function of scene time, so every stage evaluates the scene at
//! `SceneClock::scene_time_s()`. The clock is anchored to a wall-clock epoch (Unix
//! nanoseconds) so that nodes in other processes, given the same epoch, agree on scene time.

use std::time::{Duration, SystemTime, UNIX_EPOCH};

/// Maps wall-clock time to scene time: `start_s + time_scale · (now − epoch)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SceneClock {
    epoch_unix_ns: u64,
    start_s: f64,
    time_scale: f64,
}

/// Wall-clock time now, nanoseconds since the Unix epoch.
pub fn now_unix_ns() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap_or(Duration::ZERO)
        .as_nanos() as u64
}

impl SceneClock {
    /// A clock whose scene time is `start_s` at wall-clock `epoch_unix_ns` and advances
    /// `time_scale` scene seconds per wall second.
    pub fn new(epoch_unix_ns: u64, start_s: f64, time_scale: f64) -> Self {
        SceneClock {
            epoch_unix_ns,
            start_s,
            time_scale,
        }
    }

    /// A clock starting now at scene time `start_s`.
    pub fn starting_now(start_s: f64, time_scale: f64) -> Self {
        Self::new(now_unix_ns(), start_s, time_scale)
    }

    /// The wall-clock epoch, nanoseconds since the Unix epoch.
    pub fn epoch_unix_ns(&self) -> u64 {
        self.epoch_unix_ns
    }

    /// Scene time at wall-clock `unix_ns`.
    pub fn scene_time_at_s(&self, unix_ns: u64) -> f64 {
        let wall_s = (unix_ns as f64 - self.epoch_unix_ns as f64) * 1e-9;
        self.start_s + self.time_scale * wall_s
    }

    /// Scene time now, in seconds.
    pub fn scene_time_s(&self) -> f64 {
        self.scene_time_at_s(now_unix_ns())
    }

    /// Wall seconds since the epoch.
    pub fn elapsed_s(&self) -> f64 {
        (now_unix_ns() as f64 - self.epoch_unix_ns as f64) * 1e-9
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scene_time_follows_scale_and_start() {
        let c = SceneClock::new(1_000_000_000, 10.0, 0.5);
        assert_eq!(c.scene_time_at_s(1_000_000_000), 10.0);
        assert!((c.scene_time_at_s(3_000_000_000) - 11.0).abs() < 1e-12);
    }
}
