//! Sending side of a peer link: outstanding messages, packet numbers in flight, loss
//! detection, probe timeout, RTT estimation and pacing.
//!
//! Loss detection follows QUIC (RFC 9002): a packet is lost when a packet sent three
//! numbers later was acknowledged, or when a later packet was acknowledged and it has been
//! outstanding for 9/8 of the round trip. When nothing is acknowledged for a probe timeout
//! after the newest packet left (`srtt + 4·rttvar + ack delay`, at most two round trips the
//! first time as RACK-TLP's tail loss probe, doubling each time it fires), the two oldest
//! packets are sent again as probes; declaring the whole window lost on a timer would resend
//! it all. ACKs report every gap of the window (see [`crate::wire::MAX_ACK_RANGES`]), so a
//! packet is sent again only when it was lost.

use std::collections::{BTreeMap, VecDeque};
use std::sync::Arc;
use std::time::{Duration, Instant};

use super::cc::{BURST_TIME, Bbr, SendMark};
use super::{EdgeWireStats, Endpoint, EndpointConfig, Event, Peer};
use crate::wire::{
    Body, DATA_OVERHEAD, FRAME_HEADER_BYTES, Frame, K_FRAMES, SESSION_HEADER_BYTES, TAG_BYTES,
    encode_frame, session_header_into,
};

/// A sending edge: its credit and counters.
pub(crate) struct SendEdge {
    pub(crate) peer: usize,
    capacity: u64,
    /// Messages the peer allows in total (cumulative).
    pub(crate) granted: u64,
    /// Messages sent in total.
    pub(crate) sent: u64,
    pub(crate) stats: EdgeWireStats,
}

impl SendEdge {
    pub(crate) fn new(peer: usize, capacity: u64) -> Self {
        SendEdge {
            peer,
            capacity,
            granted: capacity,
            sent: 0,
            stats: EdgeWireStats::default(),
        }
    }

    pub(crate) fn available(&self) -> u64 {
        self.granted.saturating_sub(self.sent)
    }

    pub(crate) fn reset(&mut self) {
        self.granted = self.capacity;
        self.sent = 0;
    }
}

struct OutMsg {
    data: Arc<[u8]>,
    acked: Vec<bool>,
    remaining: u32,
}

/// A chunk: (edge, message sequence, chunk index).
type ChunkId = (u32, u64, u32);

struct Sent {
    /// The chunks it carries, in order (several when small messages were coalesced).
    chunks: Vec<ChunkId>,
    at: Instant,
    retransmit: bool,
    /// Bytes on the wire.
    size: u64,
    /// For its delivery-rate sample.
    mark: SendMark,
}

/// Per-peer sending state.
pub(crate) struct SendState {
    next_pn: u64,
    msgs: crate::FastMap<(u32, u64), OutMsg>,
    /// Chunks to send, retransmissions first: (edge, seq, chunk, is retransmission).
    pending: VecDeque<(u32, u64, u32, bool)>,
    in_flight: BTreeMap<u64, Sent>,
    largest_acked: u64,
    srtt: Option<Duration>,
    latest_rtt: Duration,
    rttvar: Duration,
    /// The round trip known is the handshake's, which spans every HELLO lost before it
    /// (200 ms and more at 20% loss): the first sample of data replaces it instead of
    /// averaging in, or the loss detection's time threshold waits on it for dozens of
    /// samples.
    rtt_provisional: bool,
    backoff: u32,
    /// When the newest DATA packet was sent (or a probe timeout last fired): the probe
    /// timeout counts from here (RFC 9002 §6.2.1), so a lost tail is probed one timeout after
    /// it left, not after the last acknowledgement.
    last_sent: Instant,
    /// Last time new data was acknowledged (or data was queued while none was outstanding);
    /// the stall timeout counts from here.
    data_progress: Instant,
    /// Nothing was outstanding since the last progress: the next send starts the clock.
    data_idle: bool,
    tokens: f64,
    refilled: Instant,
    /// Bytes of the DATA packets in flight.
    bytes_in_flight: u64,
    /// The congestion controller (when `congestion_control` is on).
    cc: Bbr,
    /// Packets the probe timeout may still send past the window.
    probes: u32,
}

const INITIAL_RTO: Duration = Duration::from_millis(200);

impl SendState {
    pub(crate) fn new(config: &EndpointConfig, now: Instant) -> Self {
        SendState {
            next_pn: 1,
            msgs: Default::default(),
            pending: VecDeque::new(),
            in_flight: BTreeMap::new(),
            largest_acked: 0,
            srtt: None,
            latest_rtt: Duration::ZERO,
            rttvar: Duration::ZERO,
            rtt_provisional: false,
            backoff: 0,
            last_sent: now,
            data_progress: now,
            data_idle: true,
            tokens: 16.0 * config.max_packet_bytes as f64,
            refilled: now,
            bytes_in_flight: 0,
            cc: Bbr::new(config.max_packet_bytes, config.ack_delay, now),
            probes: 0,
        }
    }

    /// The rate it paces at, bytes per second: the controller's (when on), capped by
    /// `pacing_bytes_per_s`; `None` when neither paces.
    fn pacing_rate(&self, config: &EndpointConfig) -> Option<f64> {
        let cc = config
            .congestion_control
            .then(|| self.cc.pacing_rate(self.srtt));
        match (cc, config.pacing_bytes_per_s) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }

    /// Whether the window lets a packet of `size` bytes go.
    fn window_open(&self, config: &EndpointConfig, size: u64) -> bool {
        // Probes go out whatever the window says (RFC 9002 §7.5): they are how a sender whose
        // whole window was lost learns that, and a window still full of that loss would
        // otherwise hold them back, one probe timeout after another.
        self.probes > 0
            || (self.in_flight.len() < config.window_packets
                && (!config.congestion_control
                    || self.bytes_in_flight == 0
                    || self.bytes_in_flight + size <= self.cc.window()))
    }

    /// The congestion controller's state.
    pub(crate) fn congestion(&self) -> &Bbr {
        &self.cc
    }

    pub(crate) fn queue_message(
        &mut self,
        edge: u32,
        seq: u64,
        data: Arc<[u8]>,
        chunk_bytes: usize,
    ) {
        let chunks = data.len().div_ceil(chunk_bytes).max(1) as u32;
        self.msgs.insert(
            (edge, seq),
            OutMsg {
                data,
                acked: vec![false; chunks as usize],
                remaining: chunks,
            },
        );
        self.pending
            .extend((0..chunks).map(|c| (edge, seq, c, false)));
    }

    /// Messages not yet fully acknowledged.
    pub(crate) fn outstanding(&self) -> u64 {
        self.msgs.len() as u64
    }

    /// Drops everything outstanding (the peer restarted).
    pub(crate) fn reset(&mut self, config: &EndpointConfig, now: Instant) {
        *self = SendState::new(config, now);
    }

    /// A new session numbers its packets from 1 again; chunks in flight in the old session
    /// go out again in the new one.
    pub(crate) fn restart_numbers(&mut self) {
        self.next_pn = 1;
        self.largest_acked = 0;
        self.bytes_in_flight = 0;
        let in_flight = std::mem::take(&mut self.in_flight);
        for sent in in_flight.into_values().rev() {
            for &(edge, seq, chunk) in sent.chunks.iter().rev() {
                self.pending.push_front((edge, seq, chunk, true));
            }
        }
    }

    /// The next packet number of the session (every packet kind takes one).
    pub(crate) fn take_pn(&mut self) -> u64 {
        let pn = self.next_pn;
        self.next_pn += 1;
        pn
    }

    /// How long outstanding data has gone without an acknowledgement of new data.
    pub(crate) fn stalled_for(&self, now: Instant) -> Option<Duration> {
        (!self.msgs.is_empty() && !self.data_idle)
            .then(|| now.saturating_duration_since(self.data_progress))
    }

    /// When outstanding data will count as stalled.
    pub(crate) fn stall_deadline(&self, config: &EndpointConfig) -> Option<Instant> {
        (!self.msgs.is_empty() && !self.data_idle)
            .then(|| self.data_progress + config.stall_timeout + Duration::from_millis(1))
    }

    /// Whether a round trip was measured.
    pub(crate) fn srtt_known(&self) -> bool {
        self.srtt.is_some()
    }

    pub(crate) fn srtt(&self) -> Duration {
        self.srtt.unwrap_or(Duration::ZERO)
    }

    /// A round-trip sample of the handshake: sets the timers until data gives one.
    pub(crate) fn provisional_rtt_sample(&mut self, rtt: Duration, config: &EndpointConfig) {
        self.rtt_sample(rtt, config);
        self.rtt_provisional = true;
    }

    pub(crate) fn rtt_sample(&mut self, rtt: Duration, _config: &EndpointConfig) {
        self.latest_rtt = rtt;
        match self.srtt {
            _ if std::mem::take(&mut self.rtt_provisional) => {
                self.srtt = Some(rtt);
                self.rttvar = rtt / 2;
            }
            None => {
                self.srtt = Some(rtt);
                self.rttvar = rtt / 2;
            }
            Some(s) => {
                let diff = s.abs_diff(rtt);
                self.rttvar = (self.rttvar * 3 + diff) / 4;
                self.srtt = Some((s * 7 + rtt) / 8);
            }
        }
        self.backoff = 0;
    }

    /// Probe timeout, with backoff. The first probe after progress is a tail loss probe
    /// (RFC 8985 §7.2): at most two round trips, so that a young RTT variance (half the
    /// first sample) does not hold a lost tail for three.
    fn pto(&self, config: &EndpointConfig) -> Duration {
        // `max_rto` bounds the backoff, but never below two round trips: on a path of
        // seconds a 1 s cap fires before any ACK can come back.
        let cap = config.max_rto.max(
            self.srtt
                .map_or(Duration::ZERO, |s| s * 2 + config.ack_delay),
        );
        let base = match self.srtt {
            None => INITIAL_RTO,
            Some(s) => {
                // RFC 9002 §6.2.1: the variance term is at least the timer granularity.
                let pto = s + (self.rttvar * 4).max(Duration::from_millis(1)) + config.ack_delay;
                // The tail loss probe's round trip is the latest one when that is shorter:
                // a window sent at once measures the queue it builds at the receiver (a
                // smoothed 2 ms on loopback), while the few packets of a tail cross an
                // empty path; waiting twice the smoothed round trip for them was most of a
                // lossy transfer's time. A probe sent early costs two packets, not the
                // window (it never shrinks the congestion window).
                let pto = if self.backoff == 0 {
                    pto.min(s.min(self.latest_rtt) * 2 + config.ack_delay)
                } else {
                    pto
                };
                pto.clamp(config.min_rto, cap)
            }
        };
        (base * 2u32.saturating_pow(self.backoff.min(16))).min(cap)
    }

    /// How long a packet may stay unacknowledged after a later one was acknowledged.
    fn time_threshold(&self) -> Duration {
        let rtt = self.srtt.unwrap_or(INITIAL_RTO).max(self.latest_rtt);
        (rtt * 9 / 8).max(Duration::from_millis(1))
    }

    fn refill(&mut self, config: &EndpointConfig, now: Instant) {
        if let Some(rate) = self.pacing_rate(config) {
            let dt = now.saturating_duration_since(self.refilled).as_secs_f64();
            self.tokens = (self.tokens + dt * rate).min(burst(config, rate));
        }
        self.refilled = now;
    }

    /// The next time this state needs attention (retransmission timeout, or pacing when
    /// only pacing holds data back: the peer is `up` and the window open).
    pub(crate) fn next_timer(&self, config: &EndpointConfig, up: bool) -> Option<Instant> {
        let loss = self
            .in_flight
            .range(..self.largest_acked)
            .next()
            .map(|(_, sent)| sent.at + self.time_threshold());
        let probe = (!self.in_flight.is_empty()).then(|| self.last_sent + self.pto(config));
        let rto = match (loss, probe) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        };
        let sendable = up
            && !self.pending.is_empty()
            && self.window_open(config, config.max_packet_bytes as u64);
        let pace = match (self.pacing_rate(config), sendable) {
            (Some(rate), true) if self.tokens < config.max_packet_bytes as f64 => {
                let need = config.max_packet_bytes as f64 - self.tokens;
                // Capped so that no rate, however small, overflows the clock.
                let wait = Duration::try_from_secs_f64(need / rate)
                    .unwrap_or(Duration::MAX)
                    .min(Duration::from_secs(3600));
                Some(self.refilled + wait)
            }
            _ => None,
        };
        match (rto, pace) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }
}

/// Bytes a pacer at `rate` may send at once: [`BURST_TIME`] worth, at least 16 packets.
fn burst(config: &EndpointConfig, rate: f64) -> f64 {
    (16.0 * config.max_packet_bytes as f64).max(rate * BURST_TIME.as_secs_f64())
}

/// The next chunk worth sending: pops entries of chunks already acknowledged or of
/// messages gone, and returns the first live one without popping it.
fn next_live(s: &mut SendState) -> Option<(u32, u64, u32, bool)> {
    while let Some(&(edge, seq, chunk, retransmit)) = s.pending.front() {
        match s.msgs.get(&(edge, seq)) {
            Some(m) if !m.acked[chunk as usize] => return Some((edge, seq, chunk, retransmit)),
            _ => {
                s.pending.pop_front();
            }
        }
    }
    None
}

/// Appends the next DATA packet for peer `p` to `out`, sealed, if the window and pacing
/// allow one; whether it did. When the first chunk leaves room, the chunks queued behind it
/// that fit go in the same packet, in order (a [`Body::Frames`] packet): small messages
/// travel many to a packet instead of one each.
pub(crate) fn poll_data(ep: &mut Endpoint, p: usize, now: Instant, out: &mut Vec<u8>) -> bool {
    let Endpoint {
        peers,
        send_edges,
        config,
        ..
    } = ep;
    let Peer {
        send: s,
        session,
        stats,
        up,
        ..
    } = &mut peers[p];
    let Some(session) = session.as_ref() else {
        return false;
    };
    if !*up || s.pending.is_empty() || !s.window_open(config, config.max_packet_bytes as u64) {
        return false;
    }
    s.refill(config, now);
    let paced = s.pacing_rate(config).is_some();
    let cb = config.chunk_bytes();
    let chunk_len = |s: &SendState, (edge, seq, chunk): ChunkId| {
        let len = s.msgs[&(edge, seq)].data.len();
        len.saturating_sub(chunk as usize * cb).min(cb)
    };
    let Some((edge, seq, chunk, first_retransmit)) = next_live(s) else {
        return false;
    };
    // Which chunks go: the first, then those behind it that fit in the packet.
    let budget = config.max_packet_bytes - (SESSION_HEADER_BYTES + TAG_BYTES);
    let mut chunks = vec![(edge, seq, chunk)];
    let mut marks = vec![first_retransmit];
    let mut used = FRAME_HEADER_BYTES + chunk_len(s, (edge, seq, chunk));
    s.pending.pop_front();
    while used + FRAME_HEADER_BYTES < budget {
        let Some((e, q, c, r)) = next_live(s) else {
            break;
        };
        let n = FRAME_HEADER_BYTES + chunk_len(s, (e, q, c));
        if used + n > budget {
            break;
        }
        s.pending.pop_front();
        chunks.push((e, q, c));
        marks.push(r);
        used += n;
    }
    let retransmit = marks.iter().any(|&r| r);
    let size = if chunks.len() == 1 {
        DATA_OVERHEAD + used - FRAME_HEADER_BYTES
    } else {
        SESSION_HEADER_BYTES + TAG_BYTES + used
    };
    if paced && s.tokens < size as f64 {
        for (&(e, q, c), &r) in chunks.iter().zip(&marks).rev() {
            s.pending.push_front((e, q, c, r));
        }
        return false;
    }
    s.tokens -= size as f64;
    s.probes = s.probes.saturating_sub(1);
    s.last_sent = now;
    if s.data_idle {
        s.data_idle = false;
        s.data_progress = now;
    }
    let pn = s.next_pn;
    s.next_pn += 1;
    let start = out.len();
    let payload_of = |(edge, seq, chunk): ChunkId| {
        let data = &s.msgs[&(edge, seq)].data;
        let at = chunk as usize * cb;
        (data.len() as u32, &data[at..(at + cb).min(data.len())])
    };
    if let [(edge, seq, chunk)] = chunks[..] {
        let (len, payload) = payload_of((edge, seq, chunk));
        let body = Body::Data {
            edge,
            seq,
            len,
            chunk,
            payload,
        };
        body.encode_onto(out, session.secrets.id, pn);
    } else {
        session_header_into(out, K_FRAMES, session.secrets.id, pn);
        for &(edge, seq, chunk) in &chunks {
            let (len, payload) = payload_of((edge, seq, chunk));
            let frame = Frame {
                edge,
                seq,
                len,
                chunk,
                payload,
            };
            encode_frame(out, &frame);
        }
    }
    session
        .secrets
        .send
        .seal_in(pn, out, start, SESSION_HEADER_BYTES);
    let size = (out.len() - start) as u64;
    // App-limited: nothing else waits to go (the window and pacing allow more).
    let app_limited = s.pending.is_empty();
    let mark = s.cc.on_send(now, s.bytes_in_flight, app_limited);
    s.bytes_in_flight += size;
    stats.data_packets_sent += 1;
    if retransmit {
        stats.retransmissions += 1;
    }
    // Each edge is charged its frames; the packet's own header and tag go to the first.
    let mut overhead = size.saturating_sub(used as u64);
    for &id in &chunks {
        let frame = (FRAME_HEADER_BYTES + payload_of(id).1.len()) as u64;
        if let Some(e) = send_edges.get_mut(&id.0) {
            e.stats.wire_bytes += frame + std::mem::take(&mut overhead);
            if retransmit {
                e.stats.retransmissions += 1;
            }
        }
    }
    s.in_flight.insert(
        pn,
        Sent {
            chunks,
            at: now,
            retransmit,
            size,
            mark,
        },
    );
    true
}

/// An acknowledgement of packet-number ranges arrived from peer `p`.
pub(crate) fn on_ack(ep: &mut Endpoint, p: usize, now: Instant, ranges: &[(u64, u64)]) {
    let Endpoint {
        peers,
        events,
        config,
        ..
    } = ep;
    let peer = &mut peers[p];
    let s = &mut peer.send;
    let mut newest: Option<(u64, Instant, bool, SendMark)> = None;
    let mut acked_bytes = 0;
    // Ranges come highest first; those below the oldest packet in flight acknowledge
    // nothing new.
    let oldest = s.in_flight.keys().next().copied().unwrap_or(u64::MAX);
    let mut pns = Vec::new();
    for &(lo, hi) in ranges {
        if hi < oldest {
            break;
        }
        pns.clear();
        pns.extend(s.in_flight.range(lo.max(oldest)..=hi).map(|(pn, _)| *pn));
        for &pn in &pns {
            let sent = s.in_flight.remove(&pn).expect("listed above");
            s.bytes_in_flight -= sent.size;
            acked_bytes += sent.size;
            if newest.is_none_or(|(n, ..)| pn > n) {
                newest = Some((pn, sent.at, sent.retransmit, sent.mark));
            }
            for (edge, seq, chunk) in sent.chunks {
                if let Some(msg) = s.msgs.get_mut(&(edge, seq))
                    && !msg.acked[chunk as usize]
                {
                    msg.acked[chunk as usize] = true;
                    msg.remaining -= 1;
                    if msg.remaining == 0 {
                        s.msgs.remove(&(edge, seq));
                        events.push_back(Event::Delivered { edge, seq });
                    }
                }
            }
        }
    }
    if let Some((pn, at, retransmit, mark)) = newest {
        s.data_progress = now;
        peer.stall_reported = false;
        if s.msgs.is_empty() {
            s.data_idle = true;
        }
        s.largest_acked = s.largest_acked.max(pn);
        let rtt = (!retransmit).then(|| now.saturating_duration_since(at));
        if let Some(rtt) = rtt {
            s.rtt_sample(rtt, config);
            peer.stats.srtt_s = s.srtt().as_secs_f64();
        }
        s.cc.on_ack(now, acked_bytes, (mark, at), rtt, s.bytes_in_flight);
        s.backoff = 0;
    }
    detect_losses(ep, p, now);
}

/// Declares lost the packets three numbers behind the largest acknowledged one, or older
/// than the time threshold with a later one acknowledged, and queues their chunks again;
/// when the probe timeout expires, sends the oldest packet again as a probe.
pub(crate) fn detect_losses(ep: &mut Endpoint, p: usize, now: Instant) {
    let config = &ep.config;
    let s = &mut ep.peers[p].send;
    let threshold = s.time_threshold();
    let mut lost: Vec<u64> = s
        .in_flight
        .range(..s.largest_acked)
        .filter(|(pn, sent)| **pn + 3 <= s.largest_acked || sent.at + threshold <= now)
        .map(|(pn, _)| *pn)
        .collect();
    let by_threshold = !lost.is_empty();
    if lost.is_empty() && !s.in_flight.is_empty() && now >= s.last_sent + s.pto(config) {
        // Probe with the two oldest packets (RFC 9002 §6.2.4 allows two): at 20-30% loss a
        // single probe or its ACK is lost often enough for the doubling timeout to dominate.
        lost.extend(s.in_flight.keys().take(2).copied());
        s.backoff += 1;
        s.last_sent = now;
        s.probes = 2;
    }
    for pn in lost.into_iter().rev() {
        let sent = s.in_flight.remove(&pn).expect("listed above");
        s.bytes_in_flight -= sent.size;
        if by_threshold {
            s.cc.on_loss(sent.size);
        }
        for &(edge, seq, chunk) in sent.chunks.iter().rev() {
            if s.msgs
                .get(&(edge, seq))
                .is_some_and(|m| !m.acked[chunk as usize])
            {
                s.pending.push_front((edge, seq, chunk, true));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A window full of lost packets must not hold back the probes that discover the loss
    /// (a real run at 20% loss waited 2-13 s: the window had shrunk below what was in flight,
    /// and each probe timeout freed two packets' worth of it).
    #[test]
    fn probes_pass_a_full_congestion_window_and_nothing_else_does() {
        let config = EndpointConfig::new("a", "c", b"s");
        let now = Instant::now();
        let mut s = SendState::new(&config, now);
        let size = config.max_packet_bytes as u64;
        s.bytes_in_flight = 10 * s.cc.window();
        assert!(!s.window_open(&config, size), "a full window is closed");
        s.probes = 2;
        assert!(s.window_open(&config, size), "open to probes");
        s.probes = 0;
        assert!(!s.window_open(&config, size));
    }
}
