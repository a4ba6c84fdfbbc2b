//! A seeded, sans-IO link emulator: what a home, campus or continental link does to packets.
//!
//! This machine's kernel has no netem, so placement experiments emulate links here. One
//! emulator shapes one direction of one pair of nodes; the sending side applies it before a
//! datagram reaches the socket. Every call takes `now`; the same seed and the same calls
//! give the same drops, copies and delivery times.
//!
//! Model, per datagram, in this order: loss (dropped with probability `loss`); bandwidth (the
//! datagram is serialized onto a link of `bandwidth_mbps`; when more than `queue_limit_bytes`
//! wait for the link, it is tail-dropped like a router buffer would); latency plus Gaussian
//! jitter of standard deviation `jitter_ms`, clamped at zero and never earlier than the
//! datagram before it (a link's delay varies, but a FIFO path does not reorder); reordering
//! (with probability `reorder` the datagram is held back one extra latency + 1 ms, and only
//! these arrive out of order);
//! duplication (with probability `duplicate` a second copy follows 0–1 ms later).

use std::cmp::Reverse;
use std::collections::BinaryHeap;
use std::time::{Duration, Instant};

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// How one direction of a link behaves.
#[derive(Clone, Copy, Debug, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct LinkProfile {
    /// One-way latency, milliseconds.
    pub latency_ms: f64,
    /// Standard deviation of the latency, milliseconds.
    pub jitter_ms: f64,
    /// Bandwidth cap in megabits per second; `None` is uncapped.
    pub bandwidth_mbps: Option<f64>,
    /// Loss probability in [0, 1].
    pub loss: f64,
    /// Duplication probability in [0, 1].
    pub duplicate: f64,
    /// Probability in [0, 1] that a datagram is held back and arrives out of order.
    pub reorder: f64,
}

impl LinkProfile {
    /// A campus network, the link of the photon examples and of every scaling benchmark:
    /// 5 ms ± 1 ms one way, 1 Gbit/s, 0.1% loss.
    pub const CAMPUS: LinkProfile = LinkProfile {
        latency_ms: 5.0,
        jitter_ms: 1.0,
        bandwidth_mbps: Some(1000.0),
        loss: 0.001,
        duplicate: 0.0,
        reorder: 0.0,
    };

    /// One router at home: 2 ms ± 2 ms one way, 200 Mbit/s, 0.5% loss (what 802.11ac
    /// leaves after its own retries; wireless clients vary most, CloudLight §5.1).
    pub const HOME_WIFI: LinkProfile = LinkProfile {
        latency_ms: 2.0,
        jitter_ms: 2.0,
        bandwidth_mbps: Some(200.0),
        loss: 0.005,
        duplicate: 0.0,
        reorder: 0.0,
    };

    /// A server elsewhere in the town, through an access provider: 10 ms ± 2 ms one way,
    /// 100 Mbit/s, 0.1% loss (CloudLight §5.1's "most plausible deployment").
    pub const CITY: LinkProfile = LinkProfile {
        latency_ms: 10.0,
        jitter_ms: 2.0,
        bandwidth_mbps: Some(100.0),
        loss: 0.001,
        duplicate: 0.0,
        reorder: 0.0,
    };

    /// 1,200 km (the paper's Santa Clara to Salt Lake City): 15 ms ± 2 ms one way (a
    /// 30 ms ping: the route is longer than the distance, and light in fibre covers 200 km
    /// per ms), 50 Mbit/s, 0.1% loss.
    pub const CONTINENTAL_1200KM: LinkProfile = LinkProfile {
        latency_ms: 15.0,
        jitter_ms: 2.0,
        bandwidth_mbps: Some(50.0),
        loss: 0.001,
        duplicate: 0.0,
        reorder: 0.0,
    };

    /// 3,600 km (the paper's Salt Lake City to Williamstown): 35 ms ± 4 ms one way (a
    /// 70 ms ping), 50 Mbit/s, 0.2% loss.
    pub const CONTINENTAL_3600KM: LinkProfile = LinkProfile {
        latency_ms: 35.0,
        jitter_ms: 4.0,
        bandwidth_mbps: Some(50.0),
        loss: 0.002,
        duplicate: 0.0,
        reorder: 0.0,
    };

    /// The named profiles a topology's `[[link]]` may give as `profile`, after the networks
    /// CloudLight §5.1 tested on (it names them, not their figures: these are typical ones).
    pub const NAMED: [(&'static str, LinkProfile); 5] = [
        ("home-wifi", LinkProfile::HOME_WIFI),
        ("campus", LinkProfile::CAMPUS),
        ("city", LinkProfile::CITY),
        ("continental-1200km", LinkProfile::CONTINENTAL_1200KM),
        ("continental-3600km", LinkProfile::CONTINENTAL_3600KM),
    ];

    /// The named profile `name`, if there is one.
    pub fn named(name: &str) -> Option<LinkProfile> {
        LinkProfile::NAMED
            .iter()
            .find(|(n, _)| *n == name)
            .map(|(_, p)| *p)
    }

    /// The names of [`LinkProfile::NAMED`], comma-separated (for messages).
    pub fn names() -> String {
        LinkProfile::NAMED
            .iter()
            .map(|(n, _)| *n)
            .collect::<Vec<_>>()
            .join(", ")
    }

    /// True when the profile changes nothing (the emulator can be bypassed).
    pub fn is_transparent(&self) -> bool {
        *self == LinkProfile::default()
    }
}

/// What the emulator did so far.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct EmulatorStats {
    /// Datagrams given to [`LinkEmulator::send`].
    pub offered: u64,
    /// Dropped by `loss`.
    pub lost: u64,
    /// Dropped because the bandwidth queue was full.
    pub queue_drops: u64,
    /// Extra copies made.
    pub duplicated: u64,
    /// Held back to arrive out of order.
    pub reordered: u64,
    /// Handed out by [`LinkEmulator::poll`].
    pub delivered: u64,
}

/// One direction of an emulated link.
pub struct LinkEmulator {
    profile: LinkProfile,
    rng: ChaCha8Rng,
    queue: BinaryHeap<Reverse<(Instant, u64, Vec<u8>)>>,
    order: u64,
    link_free_at: Option<Instant>,
    last_at: Option<Instant>,
    /// Most bytes allowed to wait for the bandwidth-limited link.
    pub queue_limit_bytes: usize,
    stats: EmulatorStats,
}

impl LinkEmulator {
    /// An emulator with `profile`, seeded with `seed`; the router queue defaults to 1 MiB.
    pub fn new(profile: LinkProfile, seed: u64) -> Self {
        LinkEmulator {
            profile,
            rng: ChaCha8Rng::seed_from_u64(seed),
            queue: BinaryHeap::new(),
            order: 0,
            link_free_at: None,
            last_at: None,
            queue_limit_bytes: 1 << 20,
            stats: EmulatorStats::default(),
        }
    }

    /// The profile.
    pub fn profile(&self) -> &LinkProfile {
        &self.profile
    }

    /// Counters so far.
    pub fn stats(&self) -> EmulatorStats {
        self.stats
    }

    fn push(&mut self, at: Instant, datagram: Vec<u8>) {
        self.order += 1;
        self.queue.push(Reverse((at, self.order, datagram)));
    }

    fn gaussian(&mut self) -> f64 {
        // Box–Muller.
        let u1: f64 = self.rng.random::<f64>().max(f64::MIN_POSITIVE);
        let u2: f64 = self.rng.random();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }

    /// Offers a datagram to the link at `now`.
    pub fn send(&mut self, now: Instant, datagram: Vec<u8>) {
        self.stats.offered += 1;
        let p = self.profile;
        if p.loss > 0.0 && self.rng.random::<f64>() < p.loss {
            self.stats.lost += 1;
            return;
        }
        let mut at = now;
        if let Some(mbps) = p.bandwidth_mbps {
            let start = self.link_free_at.map_or(now, |f| f.max(now));
            let waiting_s = start.saturating_duration_since(now).as_secs_f64();
            if waiting_s * mbps * 1e6 / 8.0 > self.queue_limit_bytes as f64 {
                self.stats.queue_drops += 1;
                return;
            }
            let tx = Duration::from_secs_f64(datagram.len() as f64 * 8.0 / (mbps * 1e6));
            at = start + tx;
            self.link_free_at = Some(at);
        }
        let mut delay_ms = p.latency_ms;
        if p.jitter_ms > 0.0 {
            delay_ms += p.jitter_ms * self.gaussian();
        }
        let mut at = at + Duration::from_secs_f64(delay_ms.max(0.0) / 1000.0);
        if p.reorder > 0.0 && self.rng.random::<f64>() < p.reorder {
            self.stats.reordered += 1;
            at += Duration::from_secs_f64((p.latency_ms + 1.0) / 1000.0);
        } else {
            // FIFO: jitter delays, it does not overtake.
            at = self.last_at.map_or(at, |l| at.max(l));
            self.last_at = Some(at);
        }
        if p.duplicate > 0.0 && self.rng.random::<f64>() < p.duplicate {
            self.stats.duplicated += 1;
            let extra = Duration::from_secs_f64(self.rng.random::<f64>() / 1000.0);
            self.push(at + extra, datagram.clone());
        }
        self.push(at, datagram);
    }

    /// For a link that only loses (no delay, jitter, bandwidth cap, reordering or
    /// duplication) with nothing held: decides the fate of one datagram offered now without
    /// taking it — `Some(true)` when it passes (the caller sends it at once, as
    /// [`LinkEmulator::send`] then [`LinkEmulator::poll`] would), `Some(false)` when it is
    /// lost; `None` when the link needs the datagram ([`LinkEmulator::send`]). A sender
    /// then neither copies nor queues what the link would hand straight back.
    pub fn pass_now(&mut self) -> Option<bool> {
        let p = self.profile;
        let immediate = p.latency_ms == 0.0
            && p.jitter_ms == 0.0
            && p.bandwidth_mbps.is_none()
            && p.reorder == 0.0
            && p.duplicate == 0.0
            && self.queue.is_empty();
        if !immediate {
            return None;
        }
        self.stats.offered += 1;
        if p.loss > 0.0 && self.rng.random::<f64>() < p.loss {
            self.stats.lost += 1;
            return Some(false);
        }
        self.stats.delivered += 1;
        Some(true)
    }

    /// The next datagram due at `now`, if any.
    pub fn poll(&mut self, now: Instant) -> Option<Vec<u8>> {
        if self
            .queue
            .peek()
            .is_some_and(|Reverse((at, _, _))| *at <= now)
        {
            self.stats.delivered += 1;
            return self.queue.pop().map(|Reverse((_, _, d))| d);
        }
        None
    }

    /// When the next datagram is due.
    pub fn next_due(&self) -> Option<Instant> {
        self.queue.peek().map(|Reverse((at, _, _))| *at)
    }

    /// Datagrams waiting.
    pub fn len(&self) -> usize {
        self.queue.len()
    }

    /// Whether nothing waits.
    pub fn is_empty(&self) -> bool {
        self.queue.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn drain(e: &mut LinkEmulator, until: Instant) -> Vec<(Instant, Vec<u8>)> {
        let mut out = Vec::new();
        while let Some(at) = e.next_due() {
            if at > until {
                break;
            }
            out.push((at, e.poll(at).unwrap()));
        }
        out
    }

    #[test]
    fn latency_delays_and_keeps_order_without_jitter() {
        let t0 = Instant::now();
        let mut e = LinkEmulator::new(
            LinkProfile {
                latency_ms: 20.0,
                ..Default::default()
            },
            1,
        );
        for i in 0..10u8 {
            e.send(t0 + Duration::from_millis(i as u64), vec![i]);
        }
        assert!(e.poll(t0 + Duration::from_millis(19)).is_none());
        let out = drain(&mut e, t0 + Duration::from_secs(1));
        assert_eq!(
            out.iter().map(|(_, d)| d[0]).collect::<Vec<_>>(),
            (0..10).collect::<Vec<_>>()
        );
        assert_eq!(out[0].0, t0 + Duration::from_millis(20));
    }

    /// A loss-only link decides in place what `send` and `poll` would: the same datagrams
    /// pass, in the same order, for the same seed.
    #[test]
    fn a_loss_only_link_passes_in_place_what_it_would_queue() {
        let profile = LinkProfile {
            loss: 0.3,
            ..Default::default()
        };
        let now = Instant::now();
        let (mut queued, mut in_place) =
            (LinkEmulator::new(profile, 7), LinkEmulator::new(profile, 7));
        for i in 0..1000u32 {
            queued.send(now, i.to_le_bytes().to_vec());
            let passed = queued.poll(now).is_some();
            assert_eq!(in_place.pass_now(), Some(passed), "datagram {i}");
        }
        assert_eq!(queued.stats(), in_place.stats());
        let delayed = LinkProfile {
            latency_ms: 1.0,
            ..profile
        };
        assert_eq!(LinkEmulator::new(delayed, 7).pass_now(), None);
    }

    #[test]
    fn loss_rate_matches_and_is_deterministic_by_seed() {
        let t0 = Instant::now();
        let run = |seed| {
            let mut e = LinkEmulator::new(
                LinkProfile {
                    loss: 0.1,
                    duplicate: 0.01,
                    ..Default::default()
                },
                seed,
            );
            for i in 0..20_000u32 {
                e.send(t0, i.to_le_bytes().to_vec());
            }
            let out = drain(&mut e, t0 + Duration::from_secs(1));
            (e.stats(), out)
        };
        let (a, da) = run(5);
        let (b, db) = run(5);
        assert_eq!(a, b);
        assert_eq!(da, db);
        let loss = a.lost as f64 / a.offered as f64;
        assert!((loss - 0.1).abs() < 0.01, "loss {loss}");
        assert!(a.duplicated > 100 && a.duplicated < 320, "{a:?}");
        assert_eq!(a.delivered, a.offered - a.lost + a.duplicated);
    }

    #[test]
    fn bandwidth_cap_spaces_datagrams_and_drops_when_the_queue_is_full() {
        let t0 = Instant::now();
        let mut e = LinkEmulator::new(
            LinkProfile {
                bandwidth_mbps: Some(8.0),
                ..Default::default()
            },
            1,
        );
        e.queue_limit_bytes = 10_000;
        for _ in 0..20 {
            e.send(t0, vec![0; 1000]); // 1 ms each at 8 Mbps
        }
        let out = drain(&mut e, t0 + Duration::from_secs(1));
        assert!(out.len() >= 10 && out.len() <= 12, "{}", out.len());
        assert!(e.stats().queue_drops >= 8);
        let gap = out[5].0 - out[4].0;
        assert!((gap.as_secs_f64() - 0.001).abs() < 1e-6, "{gap:?}");
    }

    #[test]
    fn reorder_holds_some_datagrams_back() {
        let t0 = Instant::now();
        let mut e = LinkEmulator::new(
            LinkProfile {
                latency_ms: 5.0,
                reorder: 0.2,
                ..Default::default()
            },
            3,
        );
        for i in 0..200u8 {
            e.send(t0 + Duration::from_micros(i as u64 * 100), vec![i]);
        }
        let got: Vec<u8> = drain(&mut e, t0 + Duration::from_secs(1))
            .into_iter()
            .map(|(_, d)| d[0])
            .collect();
        assert_eq!(got.len(), 200);
        assert!(got.windows(2).any(|w| w[0] > w[1]), "nothing was reordered");
    }
}
