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
    a_events: Vec<Event>,
    b_events: Vec<Event>,
}

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
    let mut c = EndpointConfig::new(name, "test-cluster", secret, incarnation);
    c.epoch = incarnation * 10;
    c.peer_timeout = Duration::from_millis(500);
    let mut e = Endpoint::new(c, now);
    e.add_peer(peer, addr(peer_port), now);
    e
}

impl Sim {
    fn new(profile: LinkProfile, seed: u64) -> Sim {
        let now = Instant::now();
        let mut a = endpoint("a", "b", B, 11, b"s3cret", now);
        let mut b = endpoint("b", "a", A, 22, b"s3cret", now);
        a.open_edge(7, "b", EdgeDirection::Send, 4).unwrap();
        b.open_edge(7, "a", EdgeDirection::Receive, 4).unwrap();
        Sim {
            a,
            b,
            ab: LinkEmulator::new(profile, seed),
            ba: LinkEmulator::new(profile, seed ^ 0xFFFF),
            now,
            b_dead: false,
            a_events: Vec::new(),
            b_events: Vec::new(),
        }
    }

    /// Moves every datagram and timer due now, then advances virtual time to the next one.
    fn step(&mut self) {
        let now = self.now;
        self.a.handle_timeout(now);
        self.b.handle_timeout(now);
        while let Some((_, d)) = self.a.poll_transmit(now) {
            self.ab.send(now, d);
        }
        while let Some((_, d)) = self.b.poll_transmit(now) {
            if !self.b_dead {
                self.ba.send(now, d);
            }
        }
        while let Some(d) = self.ab.poll(now) {
            if !self.b_dead {
                self.b.handle_datagram(now, addr(A), &d);
            }
        }
        while let Some(d) = self.ba.poll(now) {
            self.a.handle_datagram(now, addr(B), &d);
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

#[test]
fn forged_and_malformed_data_is_refused_without_big_allocations() {
    let mut s = Sim::new(LinkProfile::default(), 1);
    assert!(s.run_until(Duration::from_secs(1), |s| s.b.is_up("a")));
    let inc = 11; // a's incarnation: the packets look like they come from a
    let forged = [
        crate::wire::encode_data(inc, 1000, 7, 0, u32::MAX, 0, &[0; 10]), // over the size bound
        crate::wire::encode_data(inc, 1001, 7, 0, 100, 5, &[0; 10]),      // chunk out of range
        crate::wire::encode_data(inc, 1002, 7, 99, 10, 0, &[0; 10]),      // beyond credit
        crate::wire::encode_data(inc, 1003, 99, 0, 10, 0, &[0; 10]),      // unknown edge
        crate::wire::encode_data(inc, 1004, 7, 0, 10, 0, &[0; 3]),        // wrong chunk length
    ];
    let now = s.now;
    for f in &forged {
        s.b.handle_datagram(now, addr(A), f);
    }
    assert_eq!(s.b.peer_stats("a").unwrap().refused, 5);
    s.b.handle_datagram(
        now,
        addr(9),
        &crate::wire::encode_data(inc, 1, 7, 0, 1, 0, &[1]),
    );
    assert_eq!(
        s.b.strangers(),
        1,
        "a packet from an unknown address is a stranger's"
    );
    s.b.handle_datagram(
        now,
        addr(A),
        &crate::wire::encode_data(5, 1, 7, 0, 1, 0, &[1]),
    );
    assert_eq!(
        s.b.strangers(),
        2,
        "a packet with a stale incarnation is refused"
    );
    s.b.handle_datagram(now, addr(A), b"garbage");
    assert_eq!(s.b.malformed(), 1);
    assert!(s.delivered().is_empty());
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
        prop_assert!(s.run_until(Duration::from_secs(1), |s| s.b.is_up("a")));
        for (i, (edge, seq, len, chunk, payload)) in packets.into_iter().enumerate() {
            let d = crate::wire::encode_data(11, 10_000 + i as u64, edge, seq, len, chunk, &payload);
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
