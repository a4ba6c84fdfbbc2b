//! The protocol core driven in virtual time: two endpoints joined by two seeded emulators.

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use proptest::prelude::*;

use super::*;
use crate::emulator::{LinkEmulator, LinkProfile};

struct Sim {
    a: Endpoint,
    b: Endpoint,
    ab: LinkEmulator,
    ba: LinkEmulator,
    now: Instant,
    /// While true, everything b sends is dropped and nothing reaches it (b is "dead").
    b_dead: bool,
    /// b behind a NAT: its packets reach a from this port, a reaches it only there (its
    /// advertised address, port `B`, is unreachable).
    b_nat: Option<u16>,
    a_events: Vec<Event>,
    b_events: Vec<Event>,
    /// Drops the datagrams from a to b for which it returns true (targeted loss).
    drop_ab: Option<DropFilter>,
    /// Drops everything, both ways, from the first instant to the second (a blackhole).
    blackhole: Option<(Instant, Instant)>,
    /// Flips one random bit of each datagram, both ways, with this probability.
    corrupt: f64,
    rng: rand::rngs::StdRng,
    /// The port a's packets reach b from (a NAT rebinding moves it); b's packets to any
    /// other address of a are lost.
    a_port: u16,
}

type DropFilter = Box<dyn FnMut(&[u8]) -> bool>;

fn addr(port: u16) -> SocketAddr {
    SocketAddr::from(([127, 0, 0, 1], port))
}

const A: u16 = 1;
const B: u16 = 2;

fn endpoint(
    name: &str,
    peer: &str,
    peer_port: u16,
    incarnation: u64,
    secret: &[u8],
    now: Instant,
) -> Endpoint {
    let mut c = EndpointConfig::new(name, "test-cluster", secret);
    c.nonce_seed = [incarnation as u8; 32];
    c.epoch = incarnation * 10;
    c.peer_timeout = Duration::from_millis(500);
    let mut e = Endpoint::new(c, now);
    e.add_peer(peer, addr(peer_port), now);
    e
}

impl Sim {
    fn new(profile: LinkProfile, seed: u64) -> Sim {
        Sim::with_nonces(profile, seed, 11, 22)
    }

    /// A sim whose endpoints draw their nonces from seeds `na` and `nb` (another "run").
    fn with_nonces(profile: LinkProfile, seed: u64, na: u64, nb: u64) -> Sim {
        Sim::with_capacity(profile, seed, (na, nb), 4)
    }

    /// A sim whose edge 7 holds `capacity` messages end to end.
    fn with_capacity(profile: LinkProfile, seed: u64, (na, nb): (u64, u64), capacity: u64) -> Sim {
        let now = Instant::now();
        let mut a = endpoint("a", "b", B, na, b"s3cret", now);
        let mut b = endpoint("b", "a", A, nb, b"s3cret", now);
        a.open_edge(7, "b", EdgeDirection::Send, capacity).unwrap();
        b.open_edge(7, "a", EdgeDirection::Receive, capacity)
            .unwrap();
        Sim {
            a,
            b,
            ab: LinkEmulator::new(profile, seed),
            ba: LinkEmulator::new(profile, seed ^ 0xFFFF),
            now,
            b_dead: false,
            b_nat: None,
            a_events: Vec::new(),
            b_events: Vec::new(),
            drop_ab: None,
            blackhole: None,
            corrupt: 0.0,
            rng: rand::SeedableRng::seed_from_u64(seed),
            a_port: A,
        }
    }

    /// Both endpoints afresh (before they connect), with `tweak` applied to each one's
    /// configuration; edge 7 as before, capacity 4.
    fn reconfigure(&mut self, tweak: impl Fn(&mut EndpointConfig)) {
        let now = self.now;
        for (side, peer, port, dir) in [
            ("a", "b", B, EdgeDirection::Send),
            ("b", "a", A, EdgeDirection::Receive),
        ] {
            let mut c = if side == "a" {
                self.a.config().clone()
            } else {
                self.b.config().clone()
            };
            tweak(&mut c);
            let mut e = Endpoint::new(c, now);
            e.add_peer(peer, addr(port), now);
            e.open_edge(7, peer, dir, 4).unwrap();
            if side == "a" { self.a = e } else { self.b = e }
        }
    }

    /// A datagram after the path's impairments: `None` when lost.
    fn impair(&mut self, now: Instant, mut d: Vec<u8>) -> Option<Vec<u8>> {
        use rand::RngExt;
        if self
            .blackhole
            .is_some_and(|(from, to)| now >= from && now < to)
        {
            return None;
        }
        if self.corrupt > 0.0 && !d.is_empty() && self.rng.random_bool(self.corrupt) {
            let bit = self.rng.random_range(0..d.len() * 8);
            d[bit / 8] ^= 1 << (bit % 8);
        }
        Some(d)
    }

    /// Moves every datagram and timer due now, then advances virtual time to the next one.
    fn step(&mut self) {
        let now = self.now;
        self.a.handle_timeout(now);
        self.b.handle_timeout(now);
        while let Some((to, d)) = self.a.poll_transmit(now) {
            if self.drop_ab.as_mut().is_some_and(|f| f(&d)) {
                continue;
            }
            let Some(d) = self.impair(now, d) else {
                continue;
            };
            if self.b_nat.is_none_or(|port| to == addr(port)) {
                self.ab.send(now, d);
            }
        }
        while let Some((to, d)) = self.b.poll_transmit(now) {
            let Some(d) = self.impair(now, d) else {
                continue;
            };
            if !self.b_dead && to == addr(self.a_port) {
                self.ba.send(now, d);
            }
        }
        // What arrives may make either side send at once (an ACK opening the window), as
        // the driver polls after every datagram: then the next step comes right away.
        let mut arrived = false;
        while let Some(d) = self.ab.poll(now) {
            arrived = true;
            if !self.b_dead {
                self.b.handle_datagram(now, addr(self.a_port), &d);
            }
        }
        while let Some(d) = self.ba.poll(now) {
            arrived = true;
            self.a
                .handle_datagram(now, addr(self.b_nat.unwrap_or(B)), &d);
        }
        while let Some(e) = self.a.poll_event() {
            self.a_events.push(e);
        }
        while let Some(e) = self.b.poll_event() {
            self.b_events.push(e);
        }
        let next = [
            self.a.poll_timeout(),
            self.b.poll_timeout(),
            self.ab.next_due(),
            self.ba.next_due(),
        ]
        .into_iter()
        .flatten()
        .min()
        .unwrap_or(now + Duration::from_millis(10));
        let next = if arrived { now } else { next };
        self.now = next.clamp(
            now + Duration::from_micros(1),
            now + Duration::from_millis(50),
        );
    }

    /// Steps until `done` or `limit` of virtual time passes.
    fn run_until(&mut self, limit: Duration, mut done: impl FnMut(&mut Sim) -> bool) -> bool {
        let end = self.now + limit;
        for _ in 0..2_000_000 {
            if done(self) {
                return true;
            }
            if self.now > end {
                return false;
            }
            self.step();
        }
        false
    }

    fn delivered(&self) -> Vec<(u64, Vec<u8>)> {
        self.b_events
            .iter()
            .filter_map(|e| match e {
                Event::Message {
                    edge: 7,
                    seq,
                    bytes,
                } => Some((*seq, bytes.clone())),
                _ => None,
            })
            .collect()
    }

    fn delivered_count(&self) -> usize {
        self.b_events
            .iter()
            .filter(|e| matches!(e, Event::Message { edge: 7, .. }))
            .count()
    }

    /// Sends `messages` through edge 7, releasing each one at b as it arrives.
    fn transfer(&mut self, messages: &[Vec<u8>], limit: Duration) -> bool {
        let mut next = 0;
        let mut released = 0;
        self.run_until(limit, |s| {
            while next < messages.len() && s.a.credit(7) > 0 {
                s.a.send(7, messages[next].clone()).unwrap();
                next += 1;
            }
            let got = s.delivered_count();
            if got > released {
                s.b.release(7, (got - released) as u64);
                released = got;
            }
            got == messages.len()
        })
    }
}

fn pattern(len: usize, salt: u8) -> Vec<u8> {
    (0..len)
        .map(|i| (i as u8).wrapping_mul(31).wrapping_add(salt))
        .collect()
}

#[test]
fn handshake_brings_both_sides_up_and_shares_epochs() {
    let mut s = Sim::new(LinkProfile::default(), 1);
    assert!(s.run_until(Duration::from_secs(1), |s| s.a.is_up("b") && s.b.is_up("a")));
    assert!(s.a_events.contains(&Event::PeerUp {
        peer: "b".into(),
        epoch: 220
    }));
    assert!(s.b_events.contains(&Event::PeerUp {
        peer: "a".into(),
        epoch: 110
    }));
    assert_eq!(s.a.peer_epoch("b"), Some(220));
}

#[test]
fn a_wrong_secret_never_comes_up_and_is_counted() {
    let mut s = Sim::new(LinkProfile::default(), 1);
    let now = s.now;
    s.b = endpoint("b", "a", A, 22, b"guess", now);
    assert!(!s.run_until(Duration::from_millis(500), |s| s.a.is_up("b")
        || s.b.is_up("a")));
    assert!(s.a.strangers() > 0 && s.b.strangers() > 0);
    assert!(s.a_events.is_empty() && s.b_events.is_empty());
}

#[test]
fn messages_of_every_size_arrive_intact_and_in_order_through_a_bad_link() {
    let profile = LinkProfile {
        latency_ms: 5.0,
        jitter_ms: 1.0,
        loss: 0.1,
        duplicate: 0.01,
        reorder: 0.01,
        ..Default::default()
    };
    let mut s = Sim::new(profile, 42);
    let sizes = [0, 1, 1024, 16 * 1024 + 1, 1 << 20, 8 << 20];
    let messages: Vec<Vec<u8>> = sizes
        .iter()
        .enumerate()
        .map(|(i, &n)| pattern(n, i as u8))
        .collect();
    assert!(
        s.transfer(&messages, Duration::from_secs(120)),
        "not all delivered"
    );
    let got = s.delivered();
    for (i, (seq, bytes)) in got.iter().enumerate() {
        assert_eq!(*seq, i as u64);
        assert!(
            bytes == &messages[i],
            "message {i} ({} bytes) differs",
            sizes[i]
        );
    }
    let stats = s.a.peer_stats("b").unwrap();
    assert!(
        stats.retransmissions > 0,
        "10% loss must cause retransmissions"
    );
    let acked = |s: &mut Sim| {
        s.a_events
            .iter()
            .filter(|e| matches!(e, Event::Delivered { .. }))
            .count()
            == sizes.len()
    };
    assert!(
        s.run_until(Duration::from_secs(10), acked),
        "the sender learns that every message arrived"
    );
}

#[test]
fn credit_limits_messages_outstanding_and_release_restores_it() {
    let mut s = Sim::new(LinkProfile::default(), 1);
    for i in 0..4 {
        s.a.send(7, vec![i]).unwrap();
    }
    assert_eq!(s.a.send(7, vec![9]), Err(SendError::NoCredit(7)));
    assert!(s.run_until(Duration::from_secs(1), |s| s.delivered().len() == 4));
    s.run_until(Duration::from_millis(50), |_| false);
    assert_eq!(s.a.credit(7), 0, "nothing released yet");
    s.b.release(7, 3);
    assert!(s.run_until(Duration::from_secs(1), |s| s.a.credit(7) == 3));
    assert!(s.a_events.contains(&Event::Credit {
        edge: 7,
        granted: 7
    }));
}

#[test]
fn a_silent_peer_is_reported_lost_within_the_timeout_and_up_when_heard_again() {
    let mut s = Sim::new(LinkProfile::default(), 1);
    assert!(s.run_until(Duration::from_secs(1), |s| s.a.is_up("b")));
    s.b_dead = true;
    let silent_at = s.now;
    assert!(s.run_until(Duration::from_secs(2), |s| {
        s.a_events.contains(&Event::PeerLost { peer: "b".into() })
    }));
    let took = s.now - silent_at;
    assert!(
        took <= Duration::from_millis(500) + Duration::from_millis(150),
        "lost after {took:?}"
    );
    s.b_dead = false;
    assert!(s.run_until(Duration::from_secs(2), |s| s.a.is_up("b")));
}

#[test]
fn a_restarted_peer_is_detected_and_its_edges_resume() {
    let mut s = Sim::new(LinkProfile::default(), 1);
    assert!(s.transfer(&[vec![1], vec![2]], Duration::from_secs(1)));
    assert!(s.run_until(Duration::from_secs(1), |s| {
        s.a_events
            .iter()
            .filter(|e| matches!(e, Event::Delivered { .. }))
            .count()
            == 2
    }));
    // b dies with messages outstanding, then a new incarnation starts.
    s.b_dead = true;
    s.a.send(7, vec![3]).unwrap();
    s.run_until(Duration::from_millis(100), |_| false);
    let now = s.now;
    s.b = endpoint("b", "a", A, 33, b"s3cret", now);
    s.b.open_edge(7, "a", EdgeDirection::Receive, 4).unwrap();
    s.b_events.clear();
    s.b_dead = false;
    assert!(
        s.run_until(Duration::from_secs(2), |s| s.a_events.iter().any(
            |e| matches!(e, Event::PeerRestarted { peer, lost_messages: 1 } if peer == "b")
        ))
    );
    assert!(s.transfer(&[vec![4], vec![5]], Duration::from_secs(2)));
    let got: Vec<_> = s
        .delivered()
        .into_iter()
        .map(|(seq, b)| (seq, b[0]))
        .collect();
    assert_eq!(got, vec![(0, 4), (1, 5)], "streams restart at sequence 0");
}

/// A DATA packet sealed with a's session keys, as only a could make it.
fn authentic_data(
    a: &mut Endpoint,
    edge: u32,
    seq: u64,
    len: u32,
    chunk: u32,
    payload: &[u8],
) -> Vec<u8> {
    let body = Body::Data {
        edge,
        seq,
        len,
        chunk,
        payload,
    };
    let mut out = Vec::new();
    assert!(a.seal_onto(0, &body, &mut out), "a has a session");
    out
}

#[test]
fn authentic_but_invalid_data_is_refused_without_big_allocations() {
    let mut s = Sim::new(LinkProfile::default(), 1);
    assert!(s.run_until(Duration::from_secs(1), |s| s.b.is_up("a") && s.a.is_up("b")));
    let forged = [
        authentic_data(&mut s.a, 7, 0, u32::MAX, 0, &[0; 10]), // over the size bound
        authentic_data(&mut s.a, 7, 0, 100, 5, &[0; 10]),      // chunk out of range
        authentic_data(&mut s.a, 7, 99, 10, 0, &[0; 10]),      // beyond credit
        authentic_data(&mut s.a, 99, 0, 10, 0, &[0; 10]),      // unknown edge
        authentic_data(&mut s.a, 7, 0, 10, 0, &[0; 3]),        // wrong chunk length
    ];
    let now = s.now;
    for f in &forged {
        s.b.handle_datagram(now, addr(A), f);
    }
    assert_eq!(s.b.peer_stats("a").unwrap().refused, 5);
    s.b.handle_datagram(now, addr(A), b"garbage");
    assert_eq!(s.b.malformed(), 1);
    assert!(s.delivered().is_empty());
}

#[test]
fn forged_replayed_and_misdirected_packets_are_counted_and_never_obeyed() {
    let mut s = Sim::new(LinkProfile::default(), 1);
    assert!(s.run_until(Duration::from_secs(1), |s| s.b.is_up("a") && s.a.is_up("b")));
    let now = s.now;
    let genuine = authentic_data(&mut s.a, 7, 0, 1, 0, &[42]);
    // An attacker who saw the session id and packet number forges a packet around them.
    let mut forged = genuine.clone();
    let n = forged.len();
    forged[n - crate::wire::TAG_BYTES - 1] ^= 0xFF;
    s.b.handle_datagram(now, addr(A), &forged);
    assert_eq!(s.b.peer_stats("a").unwrap().forged, 1);
    // The genuine packet, sent from another address first, is not obeyed: b challenges it.
    s.b.handle_datagram(now, addr(9), &genuine);
    assert!(
        s.delivered().is_empty(),
        "obeyed a packet from an unproven address"
    );
    let challenge = s.b.poll_transmit(now).expect("a path challenge");
    assert_eq!(challenge.0, addr(9));
    assert_eq!(s.b.peer_stats("a").unwrap().misaddressed, 1);
    // Replayed from the right address, it is refused: its number was seen.
    s.b.handle_datagram(now, addr(A), &genuine);
    assert_eq!(s.b.peer_stats("a").unwrap().replayed, 1);
    assert!(s.delivered().is_empty());
    // A bit flipped in a copy of that seen packet is a forgery, not a replay.
    s.b.handle_datagram(now, addr(A), &forged);
    let stats = s.b.peer_stats("a").unwrap();
    assert_eq!((stats.forged, stats.replayed), (2, 1));
    // Huge forged packet numbers without the key fill no ack state.
    for pn in 0..100u64 {
        let body = Body::Data {
            edge: 7,
            seq: 0,
            len: 1,
            chunk: 0,
            payload: &[1],
        };
        let mut d = body.encode(
            s.b.peers[0].session.as_ref().unwrap().secrets.id,
            u64::MAX - pn,
        );
        d.extend_from_slice(&[0; crate::wire::TAG_BYTES]);
        s.b.handle_datagram(now, addr(A), &d);
    }
    assert_eq!(s.b.peer_stats("a").unwrap().forged, 102);
    assert!(
        s.transfer(&[vec![1], vec![2]], Duration::from_secs(2)),
        "the link still works"
    );
}

#[test]
fn pacing_holds_the_sending_rate() {
    let mut s = Sim::new(LinkProfile::default(), 1);
    let now = s.now;
    let mut c = s.a.config().clone();
    c.pacing_bytes_per_s = Some(1e6);
    s.a = Endpoint::new(c, now);
    s.a.add_peer("b", addr(B), now);
    s.a.open_edge(7, "b", EdgeDirection::Send, 4).unwrap();
    assert!(s.run_until(Duration::from_secs(1), |s| s.a.is_up("b")));
    let start = s.now;
    assert!(s.transfer(&[pattern(200_000, 1)], Duration::from_secs(10)));
    let took = (s.now - start).as_secs_f64();
    // 200 kB at 1 MB/s, less the initial burst allowance (16 packets).
    assert!(
        took > 0.17 && took < 0.3,
        "200 kB paced at 1 MB/s took {took} s"
    );
}

#[test]
fn a_link_paced_too_slowly_to_move_its_data_is_reported_stalled() {
    let mut s = Sim::new(LinkProfile::default(), 1);
    let now = s.now;
    let mut c = s.a.config().clone();
    c.pacing_bytes_per_s = Some(0.125); // 1e-6 Mbit/s
    c.stall_timeout = Duration::from_millis(500);
    s.a = Endpoint::new(c, now);
    s.a.add_peer("b", addr(B), now);
    s.a.open_edge(7, "b", EdgeDirection::Send, 4).unwrap();
    assert!(s.run_until(Duration::from_secs(1), |s| s.a.is_up("b")));
    for salt in 0..3 {
        s.a.send(7, pattern(50_000, salt)).unwrap();
    }
    assert!(
        s.run_until(Duration::from_secs(3), |s| {
            s.a_events
                .iter()
                .any(|e| matches!(e, Event::Stalled { .. }))
        }),
        "{:?}",
        s.a_events
    );
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 24, ..ProptestConfig::default() })]

    /// Forged DATA packets from a legitimate peer (any edge, sequence, length, chunk and
    /// payload) never panic the receiver nor make it hold more than its reassembly bound.
    #[test]
    fn forged_data_never_panics_or_exceeds_the_reassembly_bound(
        packets in proptest::collection::vec(
            (0u32..10, 0u64..8, any::<u32>(), 0u32..100_000, proptest::collection::vec(any::<u8>(), 0..1300)),
            1..200,
        )
    ) {
        let mut s = Sim::new(LinkProfile::default(), 1);
        let now = s.now;
        let mut c = s.b.config().clone();
        c.max_message_bytes = 1 << 20;
        c.max_reassembly_bytes = 3 << 20;
        s.b = Endpoint::new(c, now);
        s.b.add_peer("a", addr(A), now);
        s.b.open_edge(7, "a", EdgeDirection::Receive, 4).unwrap();
        prop_assert!(s.run_until(Duration::from_secs(1), |s| s.b.is_up("a") && s.a.is_up("b")));
        for (edge, seq, len, chunk, payload) in packets {
            let d = authentic_data(&mut s.a, edge, seq, len, chunk, &payload);
            s.b.handle_datagram(now, addr(A), &d);
            prop_assert!(s.b.reassembly_bytes("a") <= 3 << 20);
        }
    }

    /// Any mix of loss, duplication, reordering and jitter delivers every message exactly
    /// once and in order.
    #[test]
    fn any_impairment_delivers_exactly_once_in_order(
        seed in any::<u64>(),
        loss in 0.0f64..0.3,
        duplicate in 0.0f64..0.2,
        reorder in 0.0f64..0.2,
        jitter_ms in 0.0f64..3.0,
        sizes in proptest::collection::vec(0usize..20_000, 1..12),
    ) {
        let profile = LinkProfile { latency_ms: 2.0, jitter_ms, loss, duplicate, reorder, ..Default::default() };
        let mut s = Sim::new(profile, seed);
        let messages: Vec<Vec<u8>> = sizes.iter().enumerate().map(|(i, &n)| pattern(n, i as u8)).collect();
        let ok = s.transfer(&messages, Duration::from_secs(600));
        let lost = s.a_events.iter().any(|e| matches!(e, Event::PeerLost { .. }));
        prop_assert!(ok || lost, "neither delivered nor reported lost");
        let got = s.delivered();
        prop_assert!(got.len() <= messages.len());
        for (i, (seq, bytes)) in got.iter().enumerate() {
            prop_assert_eq!(*seq, i as u64);
            prop_assert!(bytes == &messages[i]);
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 16, ..ProptestConfig::default() })]

    /// Small messages travel many to a packet; under loss, duplication, reordering and
    /// jitter they still arrive byte-identical, exactly once and in order.
    #[test]
    fn coalesced_small_messages_arrive_intact_once_and_in_order(
        seed in any::<u64>(),
        loss in 0.0f64..0.3,
        duplicate in 0.0f64..0.2,
        reorder in 0.0f64..0.2,
        jitter_ms in 0.0f64..3.0,
        sizes in proptest::collection::vec(0usize..700, 1..400),
    ) {
        let profile = LinkProfile { latency_ms: 2.0, jitter_ms, loss, duplicate, reorder, ..Default::default() };
        let mut s = Sim::with_capacity(profile, seed, (11, 22), 64);
        let messages: Vec<Vec<u8>> = sizes.iter().enumerate().map(|(i, &n)| pattern(n, i as u8)).collect();
        let ok = s.transfer(&messages, Duration::from_secs(600));
        prop_assert!(ok, "{} of {} delivered", s.delivered_count(), messages.len());
        let got = s.delivered();
        prop_assert_eq!(got.len(), messages.len());
        for (i, (seq, bytes)) in got.iter().enumerate() {
            prop_assert_eq!(*seq, i as u64);
            prop_assert!(bytes == &messages[i], "message {} differs", i);
        }
    }
}

#[test]
fn small_messages_share_packets() {
    let mut s = Sim::with_capacity(LinkProfile::default(), 3, (11, 22), 64);
    let messages: Vec<Vec<u8>> = (0..640).map(|i| pattern(100, i as u8)).collect();
    assert!(s.transfer(&messages, Duration::from_secs(60)));
    let packets = s.a.peer_stats("b").unwrap().data_packets_sent;
    // 100-byte messages: 9 fit in a 1,200-byte packet.
    assert!(
        packets * 4 <= messages.len() as u64,
        "{packets} packets for {} messages",
        messages.len()
    );
    let got = s.delivered();
    assert!(
        got.iter()
            .enumerate()
            .all(|(i, (seq, b))| *seq == i as u64 && b == &messages[i])
    );
}

/// Bulk 8 MiB messages through heavy loss (each direction): every message arrives. Before
/// acks were kept from covering gaps, the receiver's range compaction acknowledged packets
/// it never received and the stream stalled for good.
fn bulk_through_loss(loss: f64, seed: u64) {
    let profile = LinkProfile {
        latency_ms: 1.0,
        loss,
        ..Default::default()
    };
    let mut s = Sim::new(profile, seed);
    let messages: Vec<Vec<u8>> = (0..5).map(|i| pattern(8 << 20, i as u8)).collect();
    let ok = s.transfer(&messages, Duration::from_secs(600));
    let got = s.delivered();
    assert!(ok, "{} of 5 delivered at {loss} loss", got.len());
    for (i, (seq, bytes)) in got.iter().enumerate() {
        assert_eq!(*seq, i as u64);
        assert!(bytes == &messages[i], "message {i} differs");
    }
}

#[test]
fn bulk_messages_cross_30_percent_loss() {
    bulk_through_loss(0.3, 7);
}

#[test]
fn bulk_messages_cross_50_percent_loss() {
    bulk_through_loss(0.5, 8);
}

/// Every handshake packet a sends while the sim runs.
fn record_handshakes(s: &mut Sim, limit: Duration) -> Vec<Vec<u8>> {
    let mut out = Vec::new();
    let end = s.now + limit;
    while s.now < end {
        let now = s.now;
        s.a.handle_timeout(now);
        s.b.handle_timeout(now);
        while let Some((_, d)) = s.a.poll_transmit(now) {
            if (1..=3).contains(&d[3]) {
                out.push(d.clone());
            }
            s.ab.send(now, d);
        }
        while let Some((_, d)) = s.b.poll_transmit(now) {
            s.ba.send(now, d);
        }
        while let Some(d) = s.ab.poll(now) {
            s.b.handle_datagram(now, addr(A), &d);
        }
        while let Some(d) = s.ba.poll(now) {
            s.a.handle_datagram(now, addr(B), &d);
        }
        s.now += Duration::from_millis(1);
    }
    out
}

#[test]
fn recorded_handshakes_from_an_earlier_run_or_this_one_change_nothing() {
    // An earlier run: record every handshake packet a sent.
    let mut earlier = Sim::with_nonces(LinkProfile::default(), 3, 5, 6);
    let old = record_handshakes(&mut earlier, Duration::from_millis(200));
    assert!(old.len() >= 2, "a HELLO and a CONFIRM were sent");
    // This run, up and carrying messages.
    let mut s = Sim::new(LinkProfile::default(), 4);
    let current = record_handshakes(&mut s, Duration::from_millis(200));
    assert!(s.transfer(&[vec![1], vec![2]], Duration::from_secs(1)));
    let before = s.b.peer_stats("a").unwrap();
    for (i, d) in old.iter().chain(&current).enumerate() {
        let now = s.now;
        // From the peer's own address and from an attacker's.
        s.b.handle_datagram(now, addr(A), d);
        s.b.handle_datagram(now, addr(100 + i as u16), d);
    }
    s.run_until(Duration::from_millis(300), |_| false);
    let after = s.b.peer_stats("a").unwrap();
    assert_eq!(after.handshakes, before.handshakes, "no new session");
    assert_eq!(after.restarts, 0);
    assert!(s.b.stats().stale_handshakes > 0);
    assert!(
        !s.a_events.iter().chain(&s.b_events).any(|e| matches!(
            e,
            Event::PeerRestarted { .. } | Event::PeerLost { .. } | Event::PeerLeft { .. }
        )),
        "{:?}",
        s.b_events
    );
    s.b_events.clear();
    assert!(
        s.transfer(&[vec![3], vec![4]], Duration::from_secs(1)),
        "the link still delivers"
    );
}

#[test]
fn peers_with_different_topologies_refuse_each_other_and_say_why() {
    let mut s = Sim::new(LinkProfile::default(), 1);
    let now = s.now;
    let mut c = s.b.config().clone();
    c.topology_digest = [9; DIGEST_BYTES];
    s.b = Endpoint::new(c, now);
    s.b.add_peer("a", addr(A), now);
    s.run_until(Duration::from_millis(500), |_| false);
    assert!(!s.a.is_up("b") && !s.b.is_up("a"));
    for events in [&s.a_events, &s.b_events] {
        let n = events
            .iter()
            .filter(|e| matches!(e, Event::TopologyMismatch { .. }))
            .count();
        assert_eq!(n, 1, "reported once: {events:?}");
    }
}

#[test]
fn a_newcomer_of_another_topology_under_a_live_peers_name_is_refused_and_the_session_stays() {
    // A second deployment sharing the secret: its node `a` (another topology, port 3) dials
    // b while the real a holds a live session.
    let mut s = Sim::new(LinkProfile::default(), 1);
    assert!(s.run_until(Duration::from_secs(1), |s| s.b.is_up("a") && s.a.is_up("b")));
    let mut c = s.a.config().clone();
    c.topology_digest = [9; DIGEST_BYTES];
    c.nonce_seed = [77; 32];
    let mut newcomer = Endpoint::new(c, s.now);
    newcomer.add_peer("b", addr(B), s.now);
    let mut newcomer_events = Vec::new();
    let end = s.now + Duration::from_secs(2);
    while s.now < end {
        let now = s.now;
        newcomer.handle_timeout(now);
        while let Some((_, d)) = newcomer.poll_transmit(now) {
            s.b.handle_datagram(now, addr(3), &d);
        }
        while let Some((to, d)) = s.b.poll_transmit(now) {
            if to == addr(3) {
                newcomer.handle_datagram(now, addr(B), &d);
            } else {
                s.ba.send(now, d);
            }
        }
        while let Some(e) = newcomer.poll_event() {
            newcomer_events.push(e);
        }
        s.step();
    }
    let mismatch = |events: &[Event]| {
        events
            .iter()
            .any(|e| matches!(e, Event::TopologyMismatch { .. }))
    };
    assert!(mismatch(&newcomer_events), "the newcomer learns why");
    assert!(!mismatch(&s.b_events), "b keeps its run: {:?}", s.b_events);
    assert!(s.b.is_up("a") && s.a.is_up("b"));
    assert!(s.b.peer_stats("a").unwrap().mismatched >= 1);
    assert!(
        s.transfer(&[vec![1], vec![2; 5000]], Duration::from_secs(2)),
        "the live session still delivers"
    );
}

#[test]
fn a_peer_that_stops_acknowledging_while_answering_heartbeats_is_reported_stalled() {
    let mut s = Sim::new(LinkProfile::default(), 1);
    let now = s.now;
    let mut c = s.a.config().clone();
    c.stall_timeout = Duration::from_millis(300);
    s.a = Endpoint::new(c, now);
    s.a.add_peer("b", addr(B), now);
    // b has no such edge: every DATA packet is refused, heartbeats still flow.
    s.a.open_edge(8, "b", EdgeDirection::Send, 4).unwrap();
    assert!(s.run_until(Duration::from_secs(1), |s| s.a.is_up("b")));
    s.a.send(8, vec![1; 10]).unwrap();
    assert!(s.run_until(Duration::from_secs(2), |s| {
        s.a_events
            .iter()
            .any(|e| matches!(e, Event::Stalled { .. }))
    }));
    assert!(s.a.is_up("b"));
}

#[test]
fn a_link_with_a_second_of_latency_each_way_comes_up_and_delivers() {
    let profile = LinkProfile {
        latency_ms: 1000.0,
        loss: 0.05,
        ..Default::default()
    };
    let mut s = Sim::new(profile, 9);
    s.reconfigure(|c| {
        c.peer_timeout = Duration::from_secs(5);
    });
    let ok = s.transfer(&[vec![1; 3000], vec![2]], Duration::from_secs(60));
    assert!(ok, "a: {:?}\nb: {:?}", s.a_events, s.b_events);
    let sessions = s.a.peer_stats("b").unwrap().handshakes;
    assert_eq!(sessions, 1, "one handshake, not one per confirm timeout");
}

#[test]
fn a_node_behind_nat_comes_up_and_delivers_though_its_advertised_address_is_unreachable() {
    // b's packets reach a from a NAT's address, and a reaches b only there; a (whose name
    // sorts first, so it would wait for b to answer its own HELLO) answers b's instead.
    let mut s = Sim::new(LinkProfile::default(), 5);
    s.b_nat = Some(99);
    let up = s.run_until(Duration::from_secs(10), |s| {
        s.a.is_up("b") && s.b.is_up("a")
    });
    assert!(up, "no session through the NAT");
    let messages: Vec<Vec<u8>> = (0..20).map(|i| pattern(3000, i)).collect();
    assert!(s.transfer(&messages, Duration::from_secs(20)));
    assert_eq!(s.delivered().len(), 20);
}

/// One transfer of `size` bytes through `loss` each way on a 10 ms round trip: (round trips
/// it took, retransmissions per data packet).
fn loss_recovery(loss: f64, size: usize, seed: u64) -> (f64, f64) {
    let profile = LinkProfile {
        latency_ms: 5.0,
        loss,
        ..Default::default()
    };
    let mut s = Sim::new(profile, seed);
    assert!(s.run_until(Duration::from_secs(5), |s| s.a.is_up("b") && s.b.is_up("a")));
    let start = s.now;
    assert!(s.transfer(&[pattern(size, seed as u8)], Duration::from_secs(600)));
    let took = (s.now - start).as_secs_f64() / 0.010;
    let st = s.a.peer_stats("b").unwrap();
    (
        took,
        st.retransmissions as f64 / st.data_packets_sent as f64,
    )
}

/// At 10% and 20% loss each way, 1 MiB and 8 MiB messages complete within a few round trips
/// of their loss-free time, and retransmissions track the loss (a packet is sent again only
/// when it was lost). Before ACKs carried every gap of a window, 20% loss cost 0.5-0.67
/// retransmissions per packet sent.
#[test]
fn loss_costs_a_few_round_trips_and_retransmissions_track_the_loss() {
    for size in [1usize << 20, 8 << 20] {
        let (clean, _) = loss_recovery(0.0, size, 0);
        // Measured: +2.7 / +4.0 round trips (1 / 8 MiB) at 10%, +5.5 / +7.3 at 20% — about
        // the rounds in which 10-20% of what is left is lost again (log N / log(1/loss)).
        for (loss, extra_mean, extra_max) in [(0.1, 5.0, 7.0), (0.2, 8.5, 11.0)] {
            let runs: Vec<(f64, f64)> =
                (0..6).map(|seed| loss_recovery(loss, size, seed)).collect();
            let mean = runs.iter().map(|r| r.0).sum::<f64>() / runs.len() as f64;
            let max = runs.iter().map(|r| r.0).fold(0.0, f64::max);
            let retx = runs.iter().map(|r| r.1).sum::<f64>() / runs.len() as f64;
            eprintln!(
                "{size} B at {loss}: mean {mean:.1} max {max:.1} round trips (loss-free {clean:.1}), {retx:.3} retransmissions per packet"
            );
            assert!(
                mean <= clean + extra_mean && max <= clean + extra_max,
                "{size} B at {loss}: mean {mean:.1} max {max:.1} round trips, loss-free {clean:.1}"
            );
            assert!(
                retx <= loss * 1.3,
                "{size} B at {loss}: {retx:.3} retransmissions per packet"
            );
        }
    }
}

/// Session packets' number (bytes 12..20, in clear).
fn packet_number(d: &[u8]) -> Option<u64> {
    (d.len() > 20 && d[3] >= 4).then(|| u64::from_le_bytes(d[12..20].try_into().unwrap()))
}

/// Sends a 20-chunk message while `drop` picks a→b packets to lose; the round trips
/// (10 ms each) it took.
fn recover(mut drop: impl FnMut(u64, usize) -> bool + 'static) -> f64 {
    let mut s = Sim::new(
        LinkProfile {
            latency_ms: 5.0,
            ..Default::default()
        },
        1,
    );
    assert!(s.run_until(Duration::from_secs(1), |s| s.a.is_up("b") && s.b.is_up("a")));
    // Learn the round trip first.
    assert!(s.transfer(&[vec![0; 10]], Duration::from_secs(1)));
    s.b.release(7, 1);
    let mut data = 0usize;
    s.drop_ab = Some(Box::new(move |d: &[u8]| {
        let is_data = d.len() > 4 && d[3] == 10; // K_DATA
        if is_data {
            data += 1;
        }
        is_data && packet_number(d).is_some_and(|pn| drop(pn, data))
    }));
    let start = s.now;
    let message = pattern(20 * 1_100, 3);
    s.a.send(7, message.clone()).unwrap();
    assert!(s.run_until(Duration::from_secs(10), |s| s.delivered_count() == 2));
    assert_eq!(s.delivered()[1].1, message);
    (s.now - start).as_secs_f64() / 0.010
}

#[test]
fn a_lost_tail_and_a_lost_retransmission_are_recovered_within_a_few_round_trips() {
    let clean = recover(|_, _| false);
    assert!(clean <= 1.2, "{clean}");
    // The last packet of the message: nothing after it to reveal the loss, so the probe
    // timeout does (about a round trip plus variance).
    let tail = recover(|_, n| n == 20);
    assert!(tail <= clean + 2.5, "tail loss took {tail:.1} round trips");
    // Packet 5 and then its retransmission (the 21st data packet): the same thresholds
    // find the second loss as the first.
    let twice = recover(|_, n| n == 5 || n == 21);
    eprintln!("round trips: clean {clean:.2}, tail lost {tail:.2}, retransmission lost {twice:.2}");
    assert!(
        twice <= clean + 3.5,
        "a lost retransmission took {twice:.1} round trips"
    );
}

/// The QUIC interop runner's "handshake loss" case: 30% of packets lost each way while two
/// nodes connect. They connect within a bound, and in one session: before challenges that a
/// newer session superseded were refused, one handshake in ten ended with each side up in a
/// session the other had dropped, and nothing crossed until the peer timed out.
#[test]
fn under_30_percent_loss_nodes_connect_in_bounded_time_and_in_one_session() {
    let mut slowest = Duration::ZERO;
    for seed in 0..150u64 {
        let profile = LinkProfile {
            latency_ms: 5.0,
            loss: 0.3,
            ..Default::default()
        };
        let mut s = Sim::new(profile, seed);
        let start = s.now;
        assert!(
            s.run_until(Duration::from_secs(5), |s| s.a.is_up("b") && s.b.is_up("a")),
            "seed {seed}: not connected within 5 s"
        );
        slowest = slowest.max(s.now - start);
        let id = |e: &Endpoint| e.peers[0].session.as_ref().map(|x| x.secrets.id);
        assert_eq!(id(&s.a), id(&s.b), "seed {seed}: two sessions");
        assert!(
            s.transfer(&[vec![1; 3000], vec![2]], Duration::from_secs(5)),
            "seed {seed}: nothing crosses"
        );
    }
    // HELLOs every 50 ms over a 10 ms round trip: a few attempts at most.
    assert!(slowest < Duration::from_millis(600), "slowest {slowest:?}");
}

/// The QUIC interop runner's "goodput" case on this project's terms: one bulk sender through
/// an emulated 50 Mbit/s, 80 ms round-trip bottleneck with a 1 MiB router queue. Congestion
/// control finds the rate: the link is kept at least 80% busy, the queue does not overflow
/// (retransmissions under 2%) and stays short (the round trip within 25% of the path's).
/// Without it, the fixed 1,024-packet window (1.2 MB, over twice the path's 500 kB
/// bandwidth-delay product) kept the queue full: a 196 ms round trip, 150 drops, 1%
/// retransmissions.
#[test]
fn a_bulk_sender_fills_a_bottleneck_without_overflowing_its_queue() {
    let profile = LinkProfile {
        latency_ms: 40.0,
        bandwidth_mbps: Some(50.0),
        ..Default::default()
    };
    let mut s = Sim::new(profile, 4);
    assert!(s.run_until(Duration::from_secs(5), |s| s.a.is_up("b") && s.b.is_up("a")));
    let start = s.now;
    let messages: Vec<Vec<u8>> = (0..4).map(|i| pattern(4 << 20, i)).collect();
    assert!(s.transfer(&messages, Duration::from_secs(60)));
    let took = (s.now - start).as_secs_f64();
    let mbps = (16 << 20) as f64 * 8.0 / took / 1e6;
    let st = s.a.peer_stats("b").unwrap();
    let retx = st.retransmissions as f64 / st.data_packets_sent as f64;
    let cc = s.a.congestion("b").unwrap();
    eprintln!(
        "16 MiB over 50 Mbit/s, 80 ms: {took:.2} s, {mbps:.1} Mbit/s of payload, {retx:.4} retransmissions per packet, queue drops {}, smoothed round trip {:.1} ms, {cc:?}",
        s.ab.stats().queue_drops,
        st.srtt_s * 1e3
    );
    // Payload over the wire's bytes (headers, ACK-free direction) is about 95%.
    assert!(mbps >= 0.8 * 50.0 * 0.95 * 0.9, "{mbps:.1} Mbit/s");
    assert!(retx < 0.02, "{retx:.4} retransmissions per packet");
    assert!(st.srtt_s < 0.1, "round trip {:.1} ms", st.srtt_s * 1e3);
    let bw = cc.bandwidth.unwrap() * 8.0 / 1e6;
    assert!((40.0..=55.0).contains(&bw), "measured {bw:.1} Mbit/s");
}

/// The interop runner's "blackhole": the path drops everything both ways for 2 s in the
/// middle of a transfer (under the peer and stall timeouts), then comes back. The transfer
/// resumes in the same session, within a few probe timeouts of the path's return.
#[test]
fn a_two_second_blackhole_mid_transfer_is_ridden_out_in_the_same_session() {
    let mut s = Sim::new(
        LinkProfile {
            latency_ms: 5.0,
            bandwidth_mbps: Some(100.0),
            ..Default::default()
        },
        2,
    );
    s.reconfigure(|c| {
        c.peer_timeout = Duration::from_secs(5);
    });
    assert!(s.run_until(Duration::from_secs(1), |s| s.a.is_up("b") && s.b.is_up("a")));
    let hole = s.now + Duration::from_millis(300);
    s.blackhole = Some((hole, hole + Duration::from_secs(2)));
    let messages: Vec<Vec<u8>> = (0..4).map(|i| pattern(2 << 20, i)).collect();
    assert!(s.transfer(&messages, Duration::from_secs(30)));
    let after = s
        .now
        .saturating_duration_since(hole + Duration::from_secs(2));
    eprintln!("blackhole of 2 s: the transfer ended {after:?} after the path came back");
    let st = s.a.peer_stats("b").unwrap();
    assert_eq!(st.handshakes, 1, "a new session");
    assert!(
        !s.a_events
            .iter()
            .chain(&s.b_events)
            .any(|e| matches!(e, Event::PeerLost { .. } | Event::Stalled { .. })),
        "{:?}",
        s.a_events
    );
    // 8 MiB at 100 Mbit/s is 0.7 s; the probe timeout, doubled through the hole, is at
    // most 1 s when the path returns.
    assert!(
        after < Duration::from_millis(2_500),
        "finished {after:?} after the hole"
    );
}

/// The interop runner's "transfer corruption": 30% of datagrams have a bit flipped, both
/// ways. Everything arrives intact and in order; the damaged packets fail their tag and are
/// counted as forged (never obeyed).
#[test]
fn thirty_percent_bit_flips_both_ways_deliver_everything_intact() {
    let mut s = Sim::new(
        LinkProfile {
            latency_ms: 2.0,
            ..Default::default()
        },
        6,
    );
    assert!(s.run_until(Duration::from_secs(1), |s| s.a.is_up("b") && s.b.is_up("a")));
    s.corrupt = 0.3;
    let messages: Vec<Vec<u8>> = (0..6).map(|i| pattern(300_000, i)).collect();
    assert!(s.transfer(&messages, Duration::from_secs(60)));
    for (i, (seq, bytes)) in s.delivered().iter().enumerate() {
        assert_eq!(*seq, i as u64);
        assert!(bytes == &messages[i]);
    }
    let forged = s.b.peer_stats("a").unwrap().forged + s.a.peer_stats("b").unwrap().forged;
    let damaged = s.b.malformed() + s.a.malformed() + forged;
    eprintln!("30% bit flips: {forged} forged packets counted, everything intact");
    assert!(forged > 200, "forged {forged}");
    assert!(damaged > 0);
}

/// The interop runner's "rebinding": a's source port changes mid-transfer (a NAT's new
/// mapping) and b's packets to the old one are lost. b challenges the new address, moves the
/// session there when a answers, and nothing is lost or delivered twice.
#[test]
fn a_nat_rebinding_mid_transfer_moves_the_session_and_loses_nothing() {
    let mut s = Sim::new(
        LinkProfile {
            latency_ms: 5.0,
            bandwidth_mbps: Some(200.0),
            ..Default::default()
        },
        3,
    );
    assert!(s.run_until(Duration::from_secs(1), |s| s.a.is_up("b") && s.b.is_up("a")));
    let messages: Vec<Vec<u8>> = (0..6).map(|i| pattern(1 << 20, i)).collect();
    let mut rebound = false;
    let mut next = 0;
    let mut released = 0;
    let start = s.now;
    let ok = s.run_until(Duration::from_secs(30), |s| {
        if !rebound && s.now >= start + Duration::from_millis(100) {
            s.a_port = 41;
            rebound = true;
        }
        while next < messages.len() && s.a.credit(7) > 0 {
            s.a.send(7, messages[next].clone()).unwrap();
            next += 1;
        }
        let got = s.delivered_count();
        if got > released {
            s.b.release(7, (got - released) as u64);
            released = got;
        }
        got == messages.len()
    });
    assert!(ok && rebound);
    for (i, (seq, bytes)) in s.delivered().iter().enumerate() {
        assert_eq!(*seq, i as u64);
        assert!(bytes == &messages[i]);
    }
    let st = s.b.peer_stats("a").unwrap();
    assert_eq!(st.moves, 1, "{st:?}");
    assert_eq!(st.handshakes, 1);
}

/// The interop runner's "long RTT": 750 ms each way. The handshake completes and a transfer
/// is limited by the window (1,024 packets a 1.5 s round trip), not by timers.
#[test]
fn a_750_ms_path_connects_and_moves_a_window_per_round_trip() {
    let mut s = Sim::new(
        LinkProfile {
            latency_ms: 750.0,
            ..Default::default()
        },
        8,
    );
    let now = s.now;
    s.reconfigure(|c| {
        c.peer_timeout = Duration::from_secs(10);
    });
    assert!(s.run_until(Duration::from_secs(10), |s| s.a.is_up("b")
        && s.b.is_up("a")));
    let connected = s.now - now;
    assert!(
        connected < Duration::from_secs(5),
        "connected in {connected:?}"
    );
    let start = s.now;
    // 8 MiB: 7,300 packets, a few round trips of start-up, then about a window per round trip.
    assert!(s.transfer(&[pattern(8 << 20, 1)], Duration::from_secs(120)));
    let rtts = (s.now - start).as_secs_f64() / 1.5;
    let st = s.a.peer_stats("b").unwrap();
    eprintln!("750 ms each way: connected in {connected:?}, 8 MiB in {rtts:.1} round trips");
    assert!(rtts < 14.0, "{rtts:.1} round trips");
    assert_eq!(st.retransmissions, 0, "timers fired on a slow path: {st:?}");
}

/// A path that loses 30% of packets each way does not collapse the sender: the rate model
/// does not shrink on loss, so goodput stays within a factor of the loss-free one.
#[test]
fn thirty_percent_loss_does_not_collapse_the_rate() {
    let run = |loss: f64| {
        let mut s = Sim::new(
            LinkProfile {
                latency_ms: 10.0,
                bandwidth_mbps: Some(100.0),
                loss,
                ..Default::default()
            },
            9,
        );
        assert!(s.run_until(Duration::from_secs(5), |s| s.a.is_up("b") && s.b.is_up("a")));
        let start = s.now;
        let messages: Vec<Vec<u8>> = (0..4).map(|i| pattern(2 << 20, i)).collect();
        assert!(s.transfer(&messages, Duration::from_secs(120)));
        (8 << 20) as f64 * 8.0 / (s.now - start).as_secs_f64() / 1e6
    };
    let clean = run(0.0);
    for loss in [0.2, 0.3] {
        let lossy = run(loss);
        eprintln!("100 Mbit/s, 20 ms: {clean:.1} Mbit/s loss-free, {lossy:.1} at {loss} loss");
        // Random loss is made up for in the rate model (`cc.rs`): BBR v1 ran at 58% of the
        // loss-free rate here at 30%.
        assert!(
            lossy > 0.65 * clean,
            "{lossy:.1} of {clean:.1} Mbit/s at {loss}"
        );
    }
}

/// Two senders through one 50 Mbit/s, 80 ms bottleneck (a 1 MiB router queue) to one
/// receiver, the second starting `offset` after the first: each one's Mbit/s of payload over
/// the last 10 s of 20, and the queue's drops.
fn two_senders(offset: Duration) -> ([f64; 2], u64) {
    let start = Instant::now();
    let rate = LinkProfile {
        latency_ms: 40.0,
        bandwidth_mbps: Some(50.0),
        ..Default::default()
    };
    let plain = LinkProfile {
        latency_ms: 40.0,
        ..Default::default()
    };
    // Sender i sends on edge 7 + i, which the receiver keeps per peer.
    let mut senders: Vec<Endpoint> = (0..2u16)
        .map(|i| {
            let mut c = EndpointConfig::new(&format!("a{i}"), "test-cluster", b"s3cret");
            c.nonce_seed = [10 + i as u8; 32];
            c.peer_timeout = Duration::from_secs(5);
            let mut e = Endpoint::new(c, start);
            e.add_peer("b", addr(B), start);
            e.open_edge(7 + i as u32, "b", EdgeDirection::Send, 8)
                .unwrap();
            e
        })
        .collect();
    let mut b = {
        let mut c = EndpointConfig::new("b", "test-cluster", b"s3cret");
        c.nonce_seed = [5; 32];
        c.peer_timeout = Duration::from_secs(5);
        let mut e = Endpoint::new(c, start);
        for i in 0..2u16 {
            e.add_peer(&format!("a{i}"), addr(10 + i), start);
            e.open_edge(7 + i as u32, &format!("a{i}"), EdgeDirection::Receive, 8)
                .unwrap();
        }
        e
    };
    let mut forward = LinkEmulator::new(rate, 1);
    let mut back: Vec<LinkEmulator> = (0..2).map(|i| LinkEmulator::new(plain, 20 + i)).collect();
    let mut delivered = [Vec::<(Instant, usize)>::new(), Vec::new()];
    let mut released = [0u64; 2];
    let mut now = start;
    let end = start + Duration::from_secs(20);
    let chunk = pattern(256 << 10, 1);
    for _ in 0..5_000_000 {
        if now >= end {
            break;
        }
        for (i, s) in senders.iter_mut().enumerate() {
            s.handle_timeout(now);
            let edge = 7 + i as u32;
            let started = i == 0 || now >= start + offset;
            while started && s.credit(edge) > 0 {
                s.send(edge, chunk.clone()).unwrap();
            }
            while let Some((_, d)) = s.poll_transmit(now) {
                let mut tagged = vec![i as u8];
                tagged.extend_from_slice(&d);
                forward.send(now, tagged);
            }
        }
        b.handle_timeout(now);
        while let Some((to, d)) = b.poll_transmit(now) {
            let i = (to.port() - 10) as usize;
            back[i].send(now, d);
        }
        let mut arrived = false;
        while let Some(d) = forward.poll(now) {
            arrived = true;
            b.handle_datagram(now, addr(10 + d[0] as u16), &d[1..]);
        }
        for (i, link) in back.iter_mut().enumerate() {
            while let Some(d) = link.poll(now) {
                arrived = true;
                senders[i].handle_datagram(now, addr(B), &d);
            }
        }
        while let Some(e) = b.poll_event() {
            if let Event::Message { edge, bytes, .. } = e {
                let i = (edge - 7) as usize;
                delivered[i].push((now, bytes.len()));
                released[i] += 1;
                b.release(edge, 1);
            }
        }
        for s in senders.iter_mut() {
            while s.poll_event().is_some() {}
        }
        let next = senders
            .iter()
            .map(|s| s.poll_timeout())
            .chain([b.poll_timeout(), forward.next_due()])
            .chain(back.iter().map(|l| l.next_due()))
            .flatten()
            .min()
            .unwrap_or(now + Duration::from_millis(10));
        let next = if arrived { now } else { next };
        now = next.clamp(
            now + Duration::from_micros(1),
            now + Duration::from_millis(50),
        );
    }
    let from = end - Duration::from_secs(10);
    let mbps: Vec<f64> = delivered
        .iter()
        .map(|d| {
            d.iter()
                .filter(|(t, _)| *t >= from)
                .map(|(_, n)| *n)
                .sum::<usize>() as f64
                * 8.0
                / 10.0
                / 1e6
        })
        .collect();
    ([mbps[0], mbps[1]], forward.stats().queue_drops)
}

/// The interop runner's "cross traffic" case, the second sender starting 0.5 to 4 s after
/// the first: over the last 10 s of 20 each gets 40-60% of the link, the link stays busy, and
/// the queue overflows little. (BBR v1's windows, proportional to each flow's estimate, kept
/// whatever split the second flow's Startup left: 66-68/32-34 at most offsets; the equal
/// headroom of `cc.rs` evens it out: 46-56%.)
#[test]
fn two_senders_share_a_bottleneck_fairly() {
    for ms in [500, 1000, 1500, 2000, 2500, 3000, 4000] {
        let (mbps, drops) = two_senders(Duration::from_millis(ms));
        let total: f64 = mbps.iter().sum();
        eprintln!(
            "two senders through 50 Mbit/s, 80 ms, the second {ms} ms later: {:.1} and {:.1} Mbit/s of payload over the last 10 s, {drops} queue drops",
            mbps[0], mbps[1]
        );
        assert!(total >= 0.8 * 50.0 * 0.95 * 0.9, "{total:.1} Mbit/s in all");
        for m in &mbps {
            assert!((0.4..=0.6).contains(&(m / total)), "shares {mbps:?}");
        }
        // Of ~99,000 packets; most at the second flow's Startup.
        assert!(drops < 2_500, "{drops} queue drops");
    }
}

/// The interop runner's "key update": keys change every `key_update_packets` packet
/// numbers (2^22 in use, under AES-GCM's 2^23-packet limit; 4,096 here), both ways, under
/// loss and reordering, without a pause or a lost packet, in one session.
#[test]
fn keys_change_under_way_without_a_pause_or_a_loss() {
    let mut s = Sim::new(
        LinkProfile {
            latency_ms: 5.0,
            loss: 0.05,
            reorder: 0.05,
            ..Default::default()
        },
        12,
    );
    s.reconfigure(|c| {
        c.key_update_packets = 4096;
    });
    assert!(s.run_until(Duration::from_secs(2), |s| s.a.is_up("b") && s.b.is_up("a")));
    let messages: Vec<Vec<u8>> = (0..8).map(|i| pattern(2 << 20, i)).collect();
    assert!(s.transfer(&messages, Duration::from_secs(60)));
    for (i, (seq, bytes)) in s.delivered().iter().enumerate() {
        assert_eq!(*seq, i as u64);
        assert!(bytes == &messages[i]);
    }
    let (a, b) = (s.a.peer_stats("b").unwrap(), s.b.peer_stats("a").unwrap());
    let epochs = a.packets_sent / 4096;
    assert!(epochs >= 3, "{a:?}");
    assert_eq!((a.forged, b.forged, a.handshakes), (0, 0, 1), "{a:?} {b:?}");
}

/// A read that takes in a whole window is acknowledged as it goes, every 64 packets
/// (`poll_ack_into`, called by the driver between a read's datagrams), not once at its end:
/// one ACK lost then leaves the sender waiting for nothing.
#[test]
fn a_read_of_a_whole_window_is_acknowledged_as_it_goes() {
    let mut s = Sim::new(LinkProfile::default(), 5);
    s.reconfigure(|c| c.congestion_control = false);
    assert!(s.run_until(Duration::from_secs(5), |s| s.a.is_up("b") && s.b.is_up("a")));
    let chunks = 300;
    s.a.send(7, pattern(chunks * s.a.config().chunk_bytes(), 1))
        .unwrap();
    let now = s.now;
    let mut packets = Vec::new();
    while let Some((_, d)) = s.a.poll_transmit(now) {
        packets.push(d);
    }
    assert!(packets.len() >= chunks, "{} packets", packets.len());
    let mut acks = Vec::new();
    for d in &packets {
        s.b.handle_datagram(now, addr(A), d);
        let mut out = Vec::new();
        while s.b.poll_ack_into(now, 64, &mut out).is_some() {
            acks.push(std::mem::take(&mut out));
        }
    }
    assert_eq!(acks.len(), chunks / 64, "an ACK per 64 packets of the read");
    // Each is an authentic ACK a takes, and none makes a resend anything.
    let before = s.a.peer_stats("b").unwrap().packets_received;
    for ack in &acks {
        s.a.handle_datagram(now, addr(B), ack);
    }
    let st = s.a.peer_stats("b").unwrap();
    assert_eq!(st.packets_received, before + acks.len() as u64);
    assert_eq!(st.retransmissions, 0);
}
