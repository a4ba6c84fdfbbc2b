//! Two drivers on loopback, through laminar and real UDP sockets, with the emulator.

use std::net::SocketAddr;
use std::time::Duration;

mod common;

use common::{connect, connect_via, wait_for};

use cloudlight_transport::{
    Command, Driver, DriverConfig, DriverHandle, EdgeDirection, EndpointConfig, Event, LinkProfile,
};

fn start(name: &str, seed: u64) -> DriverHandle {
    common::start(name, "loopback-test", seed)
}

fn pattern(len: usize, salt: u8) -> Vec<u8> {
    (0..len)
        .map(|i| (i as u8).wrapping_mul(13).wrapping_add(salt))
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn messages_of_every_size_cross_a_lossy_emulated_link_intact_and_in_order() {
    let mut a = start("a", 1);
    let mut b = start("b", 2);
    let link = LinkProfile {
        latency_ms: 1.0,
        loss: 0.10,
        duplicate: 0.01,
        reorder: 0.01,
        ..Default::default()
    };
    connect(&a, &b, link, 8).await;
    let sizes = [0usize, 1, 1024, 16 * 1024 + 1, 1 << 20, 8 << 20];
    for (i, &n) in sizes.iter().enumerate() {
        a.command(Command::Send {
            edge: 1,
            bytes: pattern(n, i as u8).into(),
        })
        .await
        .unwrap();
    }
    let got = tokio::time::timeout(Duration::from_secs(120), async {
        let mut got = Vec::new();
        while got.len() < sizes.len() {
            if let Event::Message {
                edge: 1,
                seq,
                bytes,
            } = b.next_event().await.expect("driver alive")
            {
                b.command(Command::Release { edge: 1, n: 1 }).await.unwrap();
                got.push((seq, bytes));
            }
        }
        got
    })
    .await
    .expect("all messages within 120 s");
    for (i, (seq, bytes)) in got.iter().enumerate() {
        assert_eq!(*seq, i as u64);
        assert!(
            *bytes == pattern(sizes[i], i as u8),
            "message {i} of {} bytes differs",
            sizes[i]
        );
    }
    tokio::time::sleep(Duration::from_millis(50)).await;
    let stats = a.stats();
    let (_, peer) = &stats.peers[0];
    assert!(
        peer.retransmissions > 0,
        "10% loss must cause retransmissions: {peer:?}"
    );
    let em = &stats.emulators[0].1;
    assert!(em.lost > 0 && em.duplicated > 0, "{em:?}");
    a.close();
    b.close();
    while a.next_event().await.is_some() {}
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_killed_peer_is_reported_lost_and_a_restarted_one_rejoins() {
    let mut a = start("a", 10);
    let mut b = start("b", 20);
    connect(&a, &b, LinkProfile::default(), 4).await;
    wait_for(&mut a, |e| matches!(e, Event::PeerUp { .. })).await;
    let b_addr = b.local_addr();
    b.abort();
    let t0 = std::time::Instant::now();
    wait_for(&mut a, |e| matches!(e, Event::PeerLost { .. })).await;
    let took = t0.elapsed();
    assert!(
        took < Duration::from_millis(600 + 400),
        "lost after {took:?} with a 600 ms timeout"
    );
    // A new b on the same address, as a restarted process would be.
    let mut c = EndpointConfig::new("b", "loopback-test", b"secret");
    c.peer_timeout = Duration::from_millis(600);
    let b2 = Driver::start(DriverConfig::new(c, b_addr)).unwrap();
    b2.command(Command::AddPeer {
        name: "a".into(),
        addr: a.local_addr(),
        link: LinkProfile::default(),
    })
    .await
    .unwrap();
    b2.command(Command::OpenEdge {
        edge: 1,
        peer: "a".into(),
        direction: EdgeDirection::Receive,
        capacity: 4,
    })
    .await
    .unwrap();
    let e = wait_for(&mut a, |e| matches!(e, Event::PeerRestarted { .. })).await;
    assert!(matches!(e, Event::PeerRestarted { ref peer, .. } if peer == "b"));
    wait_for(&mut a, |e| matches!(e, Event::PeerUp { .. })).await;
    a.command(Command::Send {
        edge: 1,
        bytes: b"again".as_slice().into(),
    })
    .await
    .unwrap();
    let mut b2 = b2;
    let got = wait_for(&mut b2, |e| matches!(e, Event::Message { .. })).await;
    assert_eq!(
        got,
        Event::Message {
            edge: 1,
            seq: 0,
            bytes: b"again".to_vec()
        }
    );
}

/// A relay standing between a and b, as a sniffer on the path would: it forwards every
/// datagram and records those that a sends.
struct Relay {
    addr: SocketAddr,
    recorded: std::sync::Arc<std::sync::Mutex<Vec<Vec<u8>>>>,
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Relay {
    /// Relays between `a` and `b` (their real addresses), for at most 60 s.
    fn start(a: SocketAddr, b: SocketAddr) -> Relay {
        use std::sync::atomic::Ordering;
        let sock = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
        sock.set_read_timeout(Some(Duration::from_millis(20)))
            .unwrap();
        let addr = sock.local_addr().unwrap();
        let recorded = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
        let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let (rec, halt) = (recorded.clone(), stop.clone());
        let thread = std::thread::spawn(move || {
            let started = std::time::Instant::now();
            let mut buf = vec![0u8; 65536];
            while !halt.load(Ordering::SeqCst) && started.elapsed() < Duration::from_secs(60) {
                let Ok((n, from)) = sock.recv_from(&mut buf) else {
                    continue;
                };
                let to = if from == a { b } else { a };
                if from == a {
                    rec.lock().unwrap().push(buf[..n].to_vec());
                }
                let _ = sock.send_to(&buf[..n], to);
            }
        });
        Relay {
            addr,
            recorded,
            stop,
            thread: Some(thread),
        }
    }

    fn recorded(&self) -> Vec<Vec<u8>> {
        self.recorded.lock().unwrap().clone()
    }
}

impl Drop for Relay {
    fn drop(&mut self) {
        self.stop.store(true, std::sync::atomic::Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// a and b talking through a relay; returns both drivers and the relay.
async fn relayed_pair(seed: u64) -> (DriverHandle, DriverHandle, Relay) {
    let mut a = start("a", seed);
    let mut b = start("b", seed + 1);
    let relay = Relay::start(a.local_addr(), b.local_addr());
    connect_via(
        (&a, relay.addr),
        (&b, relay.addr),
        LinkProfile::default(),
        8,
    )
    .await;
    wait_for(&mut a, |e| matches!(e, Event::PeerUp { .. })).await;
    wait_for(&mut b, |e| matches!(e, Event::PeerUp { .. })).await;
    (a, b, relay)
}

async fn send_and_receive(a: &DriverHandle, b: &mut DriverHandle, bytes: &[u8]) {
    a.command(Command::Send {
        edge: 1,
        bytes: bytes.into(),
    })
    .await
    .unwrap();
    let got = wait_for(b, |e| matches!(e, Event::Message { .. })).await;
    assert!(matches!(got, Event::Message { bytes: ref m, .. } if m == bytes));
    b.command(Command::Release { edge: 1, n: 1 }).await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn recorded_and_forged_packets_sent_over_loopback_change_nothing() {
    // An earlier run, recorded on the path.
    let (mut a1, mut b1, relay1) = relayed_pair(40).await;
    send_and_receive(&a1, &mut b1, b"earlier").await;
    let earlier = relay1.recorded();
    a1.close();
    b1.close();
    drop(relay1);
    // This run, recorded too.
    let (a, mut b, relay) = relayed_pair(50).await;
    send_and_receive(&a, &mut b, b"first").await;
    let current = relay.recorded();
    // The attacker replays everything from both runs, and forges each packet of this run
    // with a huge packet number (it knows the session id and the framing, not the key).
    let attacker = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
    let mut sent = 0;
    for d in earlier.iter().chain(&current) {
        let _ = attacker.send_to(d, b.local_addr());
        sent += 1;
        // laminar's 5 bytes, then ours: 4 of header, 8 of session id, 8 of packet number.
        if d.len() > 25 && d[8] >= 10 {
            let mut forged = d.clone();
            forged[17..25].copy_from_slice(&(u64::MAX - sent).to_le_bytes());
            let _ = attacker.send_to(&forged, b.local_addr());
        }
    }
    tokio::time::sleep(Duration::from_millis(300)).await;
    // Nothing restarted, nothing extra was delivered, and the link still works.
    send_and_receive(&a, &mut b, b"second").await;
    let mut unexpected = Vec::new();
    while let Ok(e) = tokio::time::timeout(Duration::from_millis(100), b.next_event()).await {
        match e {
            Some(Event::Credit { .. }) | None => {}
            Some(other) => unexpected.push(other),
        }
    }
    assert!(unexpected.is_empty(), "{unexpected:?}");
    let stats = b.stats();
    let (_, peer) = &stats.peers[0];
    assert_eq!((peer.handshakes, peer.restarts), (1, 0), "{peer:?}");
    assert!(peer.forged > 0, "forgeries counted: {peer:?}");
    assert!(
        stats.endpoint.stale_handshakes + stats.endpoint.unknown_session > 0,
        "{:?}",
        stats.endpoint
    );
    eprintln!(
        "replayed {sent} recorded datagrams; b counted {peer:?} {:?}",
        stats.endpoint
    );
}
