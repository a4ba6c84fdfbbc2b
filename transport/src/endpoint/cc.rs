//! Congestion control of one peer link: a BBR-style model (Cardwell et al., "BBR:
//! Congestion-Based Congestion Control", ACM Queue 2016; the delivery-rate estimator of
//! draft-cheng-iccrg-delivery-rate-estimation).
//!
//! The sender measures the rate at which the path delivers (bytes acknowledged over the time
//! they took, per acknowledgement) and the path's shortest round trip, and paces at a gain
//! over the largest recent delivery rate, with at most twice the bandwidth-delay product in
//! flight. Why a model and not a loss-based window (NewReno, CUBIC): the links this runtime
//! is run over are emulated with random loss, and so are the wireless links of its clients;
//! a loss-based controller halves its window at every loss, so at 10-30% random loss it
//! collapses to a few packets a round trip, where a rate model keeps the link full and lets
//! loss recovery resend what was lost. Queue-building is bounded by the in-flight cap.
//!
//! States as in BBR v1: Startup (gain 2/ln 2 until the delivery rate stops growing by 25% for
//! three rounds), Drain (the inverse gain until in flight falls to one bandwidth-delay
//! product), ProbeBW (gains 5/4, 3/4, then six rounds of 1, each for one minimum round trip).
//! Departures: no ProbeRTT (the minimum round trip is kept for 10 s, and a link's edges are
//! idle often enough to refresh it); losses do not change the model.

use std::time::{Duration, Instant};

/// Startup's gain: 2/ln 2, the smallest that doubles the delivery rate each round.
const HIGH_GAIN: f64 = 2.885;
/// ProbeBW's pacing gains, one per minimum round trip.
const CYCLE: [f64; 8] = [1.25, 0.75, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0];
/// Rounds the largest delivery rate is remembered for.
const BW_ROUNDS: u64 = 10;
/// How long the smallest round trip is remembered.
const RTPROP_FOR: Duration = Duration::from_secs(10);
/// The largest share of lost packets a delivery-rate sample makes up for (see `on_ack`).
const MAX_RANDOM_LOSS: f64 = 0.3;
/// The share of lost packets a delivery-rate sample takes as congestion (see `on_ack`).
const CONGESTIVE_LOSS: f64 = 0.05;
/// The longest burst the sender's pacer lets go at once (`send::burst`): queueing up to it
/// at the ends is the sender's own, not the path's.
pub(crate) const BURST_TIME: Duration = Duration::from_millis(2);
/// ProbeBW's window: this many times the bandwidth over the round trip (and the ends'
/// delays), plus [`HEADROOM_PACKETS`] (BBR v1: 2×, and 4 packets).
const CWND_GAIN: f64 = 1.75;
/// Packets every flow's ProbeBW window holds beyond its share (see [`Bbr::window`]).
const HEADROOM_PACKETS: u64 = 64;
/// How long ProbeRTT holds the window at [`MIN_PACKETS`] (BBR's 200 ms).
const PROBE_RTT_FOR: Duration = Duration::from_millis(200);
/// Packets in flight allowed before the path is measured, and at the least.
const INITIAL_PACKETS: u64 = 32;
const MIN_PACKETS: u64 = 4;

/// The controller's phase.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Phase {
    /// Doubling the rate each round until it stops growing.
    Startup,
    /// Emptying the queue Startup built.
    Drain,
    /// Cruising at the measured rate, probing for more every eighth round trip.
    ProbeBw,
    /// The minimum round trip was not seen again for `RTPROP_FOR`: four packets in flight
    /// for `PROBE_RTT_FOR` and a round, so that the queue drains and the path's round trip
    /// is measured afresh (flows sharing a queue do this together, and each then sees the
    /// empty path instead of the queue the others keep).
    ProbeRtt,
}

/// What a packet carried when it was sent, for its delivery-rate sample.
#[derive(Clone, Copy, Debug)]
pub struct SendMark {
    /// Bytes delivered when it was sent.
    pub delivered: u64,
    /// Bytes declared lost when it was sent.
    pub lost: u64,
    /// When `delivered` was last advanced, at its send.
    pub delivered_at: Instant,
    /// When the first packet of the flight it belongs to was sent.
    pub first_sent_at: Instant,
    /// Sent while the sender had less to send than it was allowed.
    pub app_limited: bool,
}

/// What a controller knows, for reports.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CongestionStats {
    /// Its phase.
    pub phase: Phase,
    /// Largest recent delivery rate, bytes per second.
    pub bandwidth: Option<f64>,
    /// Smallest recent round trip.
    pub min_rtt: Option<Duration>,
    /// Bytes it lets be in flight.
    pub window: u64,
}

/// Beyond the path's round trip, what delays an acknowledgement at the ends: the sender's
/// timer granularity (the I/O thread's poll wakes in whole milliseconds).
const TIMER_GRANULARITY: Duration = Duration::from_millis(1);

/// One peer link's congestion state.
#[derive(Debug)]
pub struct Bbr {
    datagram: u64,
    /// The receiver's acknowledgement delay plus [`TIMER_GRANULARITY`]: the window covers the
    /// bandwidth over it too, or on a sub-millisecond path (loopback, a LAN) the window is a
    /// few packets and the sender waits on delayed ACKs and coarse timers.
    end_delay: Duration,
    /// Bytes acknowledged in total, and when they last grew.
    delivered: u64,
    /// Bytes declared lost in total (by the loss thresholds, not probe timeouts).
    lost: u64,
    delivered_at: Instant,
    first_sent_at: Instant,
    /// Until this many bytes are delivered, samples may come from app-limited sending.
    app_limited_until: u64,
    /// Largest delivery rate (bytes/s) per round, for the last [`BW_ROUNDS`] rounds.
    bw_samples: Vec<(u64, f64)>,
    rtprop: Option<(Duration, Instant)>,
    round: u64,
    next_round_delivered: u64,
    phase: Phase,
    full_bw: f64,
    full_bw_rounds: u32,
    cycle: usize,
    cycle_start: Instant,
    /// In ProbeRTT: when it may end, and the round it must see end first (set once the
    /// flight has drained to [`MIN_PACKETS`]).
    probe_rtt_done: Option<(Instant, u64)>,
}

impl Bbr {
    /// A controller for packets of at most `datagram` bytes, to a receiver that delays its
    /// ACKs by up to `ack_delay`.
    pub fn new(datagram: usize, ack_delay: Duration, now: Instant) -> Self {
        Bbr {
            datagram: datagram as u64,
            end_delay: ack_delay + TIMER_GRANULARITY,
            delivered: 0,
            lost: 0,
            delivered_at: now,
            first_sent_at: now,
            app_limited_until: 0,
            bw_samples: Vec::new(),
            rtprop: None,
            round: 0,
            next_round_delivered: 0,
            phase: Phase::Startup,
            full_bw: 0.0,
            full_bw_rounds: 0,
            cycle: 0,
            cycle_start: now,
            probe_rtt_done: None,
        }
    }

    /// The phase it is in.
    pub fn phase(&self) -> Phase {
        self.phase
    }

    /// The largest recent delivery rate, bytes per second (`None` before a sample).
    pub fn bandwidth(&self) -> Option<f64> {
        self.bw_samples
            .iter()
            .map(|&(_, bw)| bw)
            .fold(None, |m, bw| Some(m.map_or(bw, |m: f64| m.max(bw))))
    }

    /// The smallest recent round trip.
    pub fn min_rtt(&self) -> Option<Duration> {
        self.rtprop.map(|(rtt, _)| rtt)
    }

    /// Its state, for reports.
    pub fn stats(&self) -> CongestionStats {
        CongestionStats {
            phase: self.phase,
            bandwidth: self.bandwidth(),
            min_rtt: self.min_rtt(),
            window: self.window(),
        }
    }

    fn bdp(&self) -> Option<f64> {
        Some(self.bandwidth()? * self.min_rtt()?.as_secs_f64())
    }

    /// The bandwidth over the round trip and the ends' delays: what the window must cover.
    fn window_bdp(&self) -> Option<f64> {
        Some(self.bandwidth()? * (self.min_rtt()? + self.end_delay).as_secs_f64())
    }

    fn pacing_gain(&self) -> f64 {
        match self.phase {
            Phase::Startup => HIGH_GAIN,
            Phase::Drain => 1.0 / HIGH_GAIN,
            Phase::ProbeBw => CYCLE[self.cycle],
            Phase::ProbeRtt => 1.0,
        }
    }

    /// Bytes it lets be in flight.
    pub fn window(&self) -> u64 {
        let floor = MIN_PACKETS * self.datagram;
        if self.phase == Phase::ProbeRtt {
            return floor;
        }
        match self.window_bdp() {
            None => INITIAL_PACKETS * self.datagram,
            Some(bdp) => {
                let gain = if self.phase == Phase::ProbeBw {
                    CWND_GAIN
                } else {
                    HIGH_GAIN
                };
                // The same number of packets for every flow, beyond its share: flows limited
                // by their windows share a queue in proportion to them, and a window
                // proportional to the estimate keeps any split as it is (BBR v1's probing
                // moved 66/34 by 0.15 Mbit/s a second); an equal addend moves them towards
                // equal shares, as additive increase does. At most one product (a path of a
                // few packets keeps a few), at least 4 packets, so that acknowledgement
                // aggregation does not starve a small window.
                let dg = self.datagram as f64;
                let head = (HEADROOM_PACKETS as f64 * dg).min(bdp.max(4.0 * dg));
                ((gain * bdp + head) as u64).max(floor)
            }
        }
    }

    /// The rate it paces at, bytes per second: the gain over the measured rate, or before a
    /// measurement the initial window over `srtt` (1 ms before any round trip).
    pub fn pacing_rate(&self, srtt: Option<Duration>) -> f64 {
        match self.bandwidth() {
            Some(bw) if bw > 0.0 => self.pacing_gain() * bw,
            _ => {
                let rtt = srtt
                    .unwrap_or(Duration::from_millis(1))
                    .as_secs_f64()
                    .max(1e-4);
                HIGH_GAIN * (INITIAL_PACKETS * self.datagram) as f64 / rtt
            }
        }
    }

    /// A packet is sent with `in_flight` bytes already out; `app_limited` when the sender
    /// has nothing more to send after it. Returns what the packet carries for its sample.
    pub fn on_send(&mut self, now: Instant, in_flight: u64, app_limited: bool) -> SendMark {
        if in_flight == 0 {
            // A new flight: the rate is measured from here, not over the idle time.
            self.first_sent_at = now;
            self.delivered_at = now;
        }
        if app_limited {
            self.app_limited_until = self.delivered + in_flight + self.datagram;
        }
        SendMark {
            delivered: self.delivered,
            lost: self.lost,
            delivered_at: self.delivered_at,
            first_sent_at: self.first_sent_at,
            app_limited: self.app_limited_until > self.delivered,
        }
    }

    /// Packets of `bytes` in total were declared lost.
    pub fn on_loss(&mut self, bytes: u64) {
        self.lost += bytes;
    }

    /// Packets of `bytes` in total were newly acknowledged; `newest` is the mark and send time
    /// of the most recently sent of them, `rtt` a round-trip sample if one was taken, and
    /// `in_flight` what is still out.
    pub fn on_ack(
        &mut self,
        now: Instant,
        bytes: u64,
        newest: (SendMark, Instant),
        rtt: Option<Duration>,
        in_flight: u64,
    ) {
        let (mark, sent_at) = newest;
        self.delivered += bytes;
        self.delivered_at = now;
        self.first_sent_at = sent_at;
        let stale = self
            .rtprop
            .is_some_and(|(_, at)| now.duration_since(at) > RTPROP_FOR);
        if let Some(rtt) = rtt
            && self.rtprop.is_none_or(|(min, _)| rtt <= min || stale)
        {
            self.rtprop = Some((rtt, now));
        }
        if stale && self.phase != Phase::ProbeRtt && self.phase != Phase::Startup {
            self.phase = Phase::ProbeRtt;
            self.probe_rtt_done = None;
        }
        // Rounds: one ends when a packet sent after the previous end is acknowledged.
        let round_ended = mark.delivered >= self.next_round_delivered;
        if round_ended {
            self.next_round_delivered = self.delivered;
            self.round += 1;
        }
        // The delivery rate over the packet's flight, slower of its sending and its acking.
        let interval = sent_at
            .saturating_duration_since(mark.first_sent_at)
            .max(now.saturating_duration_since(mark.delivered_at));
        if interval > Duration::ZERO {
            let delivered = (self.delivered - mark.delivered) as f64;
            // Random loss is not congestion. Over a path whose queue is empty (the round
            // trip near its minimum) the bytes lost beyond `CONGESTIVE_LOSS` of those sent
            // count as carried, up to `MAX_RANDOM_LOSS` of them: without this a rate
            // model's probe at 5/4 can never exceed its estimate once 1/5 of the packets
            // are lost, and BBR v1 then decays under random loss. The few percent that
            // competing flows lose at a shared queue count as BBR counts them, not at all,
            // and so does loss at a full queue (a long round trip).
            let queue_free = rtt
                .zip(self.min_rtt())
                .is_some_and(|(rtt, min)| rtt <= min + min / 4 + self.end_delay + BURST_TIME);
            let lost = if queue_free {
                let lost = (self.lost - mark.lost) as f64;
                let sent = delivered + lost;
                (lost - CONGESTIVE_LOSS * sent)
                    .clamp(0.0, delivered * MAX_RANDOM_LOSS / (1.0 - MAX_RANDOM_LOSS))
            } else {
                0.0
            };
            let rate = (delivered + lost) / interval.as_secs_f64();
            let max = self.bandwidth().unwrap_or(0.0);
            // An app-limited sample says only that the path does at least this much.
            if !mark.app_limited || rate > max {
                let round = self.round;
                match self.bw_samples.iter_mut().find(|(r, _)| *r == round) {
                    Some((_, bw)) => *bw = bw.max(rate),
                    None => self.bw_samples.push((round, rate)),
                }
                self.bw_samples.retain(|&(r, _)| r + BW_ROUNDS > round);
            }
        }
        self.advance(now, round_ended, mark.app_limited, in_flight);
    }

    fn advance(&mut self, now: Instant, round_ended: bool, app_limited: bool, in_flight: u64) {
        let bdp = self.bdp().unwrap_or(f64::MAX);
        match self.phase {
            Phase::Startup => {
                if round_ended && !app_limited {
                    let bw = self.bandwidth().unwrap_or(0.0);
                    if bw >= self.full_bw * 1.25 {
                        self.full_bw = bw;
                        self.full_bw_rounds = 0;
                    } else {
                        self.full_bw_rounds += 1;
                    }
                    if self.full_bw_rounds >= 3 {
                        self.phase = Phase::Drain;
                    }
                }
                if self.phase == Phase::Drain && (in_flight as f64) <= bdp {
                    self.enter_probe_bw(now);
                }
            }
            Phase::Drain => {
                if (in_flight as f64) <= bdp {
                    self.enter_probe_bw(now);
                }
            }
            Phase::ProbeRtt => match self.probe_rtt_done {
                None if in_flight <= MIN_PACKETS * self.datagram => {
                    self.probe_rtt_done = Some((now + PROBE_RTT_FOR, self.round + 1));
                }
                Some((at, round)) if now >= at && self.round >= round => {
                    // The smallest round trip of the drained path stands for another
                    // `RTPROP_FOR`.
                    if let Some((_, stamp)) = &mut self.rtprop {
                        *stamp = now;
                    }
                    self.probe_rtt_done = None;
                    self.enter_probe_bw(now);
                }
                _ => {}
            },
            Phase::ProbeBw => {
                let rtprop = self.min_rtt().unwrap_or(Duration::from_millis(1));
                let elapsed = now.saturating_duration_since(self.cycle_start) > rtprop;
                let gain = CYCLE[self.cycle];
                let next = if gain > 1.0 {
                    elapsed && (in_flight as f64) >= gain * bdp
                } else if gain < 1.0 {
                    elapsed || (in_flight as f64) <= bdp
                } else {
                    elapsed
                };
                if next {
                    self.cycle = (self.cycle + 1) % CYCLE.len();
                    self.cycle_start = now;
                }
            }
        }
    }

    fn enter_probe_bw(&mut self, now: Instant) {
        self.phase = Phase::ProbeBw;
        // Start in a cruising phase, as BBR picks one at random but the probing ones.
        self.cycle = 2;
        self.cycle_start = now;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A fluid model of one sender on a path of `rate` bytes/s and `rtt`: every `step` it
    /// sends what its pacing and window allow, and packets are acknowledged one round trip
    /// (plus queueing) later.
    fn converge(rate: f64, rtt: Duration, rounds: u32) -> Bbr {
        converge_lossy(rate, rtt, rounds, 0).0
    }

    /// Phases a fluid run went through, in order, each once per visit, on a path whose
    /// round trip becomes `later` after a second.
    fn phases(rate: f64, rtt: Duration, later: Duration, rounds: u32) -> (Bbr, Vec<Phase>) {
        let mut seen = Vec::new();
        let path = move |t: Duration| {
            if t < Duration::from_secs(1) {
                rtt
            } else {
                later
            }
        };
        let (bbr, _) = converge_model(rate, rtt, &path, rounds, 0, &mut |b: &Bbr| {
            if seen.last() != Some(&b.phase()) {
                seen.push(b.phase());
            }
        });
        (bbr, seen)
    }

    /// As [`converge`], losing every `lose_every`th packet after the bottleneck (none when
    /// 0); also returns the bytes/s that arrived over the second half.
    fn converge_lossy(rate: f64, rtt: Duration, rounds: u32, lose_every: u64) -> (Bbr, f64) {
        converge_model(rate, rtt, &|_| rtt, rounds, lose_every, &mut |_| {})
    }

    /// The fluid model; `path(t)` is the round trip at time `t` from the start, `rtt` the
    /// unit of `rounds`.
    fn converge_model(
        rate: f64,
        rtt: Duration,
        path: &dyn Fn(Duration) -> Duration,
        rounds: u32,
        lose_every: u64,
        watch: &mut dyn FnMut(&Bbr),
    ) -> (Bbr, f64) {
        let start = Instant::now();
        let mut bbr = Bbr::new(1200, Duration::ZERO, start);
        let mut now = start;
        let mut queue_free_at = start;
        let mut flight: std::collections::VecDeque<(Instant, SendMark, Instant, u64, bool)> =
            Default::default();
        let mut in_flight = 0u64;
        let mut next_send = start;
        let end = start + rtt * rounds;
        let half = start + rtt * (rounds / 2);
        let (mut sent_count, mut arrived) = (0u64, 0u64);
        while now < end {
            while let Some(&(due, mark, sent, size, lost)) = flight.front() {
                if due > now {
                    break;
                }
                flight.pop_front();
                in_flight -= size;
                if lost {
                    // Found lost by the packets behind it, at about the time it was due.
                    bbr.on_loss(size);
                } else {
                    if now >= half {
                        arrived += size;
                    }
                    bbr.on_ack(now, size, (mark, sent), Some(now - sent), in_flight);
                }
                watch(&bbr);
            }
            if now >= next_send && in_flight + 1200 <= bbr.window() {
                let mark = bbr.on_send(now, in_flight, false);
                in_flight += 1200;
                let serialized = queue_free_at.max(now) + Duration::from_secs_f64(1200.0 / rate);
                queue_free_at = serialized;
                sent_count += 1;
                let lost = lose_every > 0 && sent_count % lose_every == 0;
                flight.push_back((serialized + path(now - start), mark, now, 1200, lost));
                next_send = now + Duration::from_secs_f64(1200.0 / bbr.pacing_rate(Some(rtt)));
            }
            now += Duration::from_micros(50);
        }
        let secs = (end - half).as_secs_f64();
        (bbr, arrived as f64 / secs)
    }

    #[test]
    fn it_finds_the_bottleneck_rate_and_round_trip_and_leaves_startup() {
        // 50 Mbit/s, 80 ms.
        let bbr = converge(50e6 / 8.0, Duration::from_millis(80), 60);
        let bw = bbr.bandwidth().unwrap() * 8.0 / 1e6;
        assert!((45.0..=55.0).contains(&bw), "{bw} Mbit/s");
        let rtt = bbr.min_rtt().unwrap();
        assert!(
            rtt >= Duration::from_millis(80) && rtt < Duration::from_millis(82),
            "{rtt:?}"
        );
        assert_eq!(bbr.phase(), Phase::ProbeBw);
        // Twice the bandwidth-delay product (500 kB, plus 1 ms of timer) and a few packets.
        let w = bbr.window();
        assert!((900_000..1_120_000).contains(&w), "{w}");
    }

    /// A flow that does not see its minimum round trip again for `RTPROP_FOR` (here the
    /// route got longer, 40 -> 60 ms; with competing flows, their queue) drains its flight
    /// in ProbeRTT, measures the path afresh and goes back to cruising.
    #[test]
    fn a_flow_that_lost_its_minimum_round_trip_probes_for_it() {
        let (rtt, later) = (Duration::from_millis(40), Duration::from_millis(60));
        // 14 s.
        let (bbr, seen) = phases(50e6 / 8.0, rtt, later, 350);
        assert_eq!(
            seen,
            [
                Phase::Startup,
                Phase::Drain,
                Phase::ProbeBw,
                Phase::ProbeRtt,
                Phase::ProbeBw
            ],
            "{seen:?}"
        );
        let min = bbr.min_rtt().unwrap();
        assert!(
            min >= later && min < later + Duration::from_millis(2),
            "{min:?}"
        );
    }

    /// Random loss after the bottleneck (a lossy wireless hop): the link stays busy. BBR v1
    /// counts only what arrives, so at 20% loss its probe at 5/4 never measures more than
    /// its estimate and the rate drifts down; the lost bytes beyond 5% count as carried.
    #[test]
    fn random_loss_keeps_the_bottleneck_busy() {
        let rate = 50e6 / 8.0;
        for (lose_every, least) in [(10, 0.85), (5, 0.75), (4, 0.65)] {
            let (bbr, arrived) = converge_lossy(rate, Duration::from_millis(40), 120, lose_every);
            let loss = 1.0 / lose_every as f64;
            let busy = arrived / (1.0 - loss) / rate;
            eprintln!(
                "{loss} loss: {:.1} of 50 Mbit/s arrive, the link busy {busy:.2}, {:?}",
                arrived * 8.0 / 1e6,
                bbr.stats()
            );
            assert!(busy >= least, "at {loss} loss the link is busy {busy:.2}");
            // Not more than the link plus the probe's gain either.
            let bw = bbr.bandwidth().unwrap();
            assert!(bw <= rate * 1.3, "{bw} of {rate}");
        }
    }
}
