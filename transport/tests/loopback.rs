//! Two drivers on loopback, through laminar and real UDP sockets, with the emulator.

use std::net::SocketAddr;
use std::time::Duration;

use cloudlight_transport::{
    Command, Driver, DriverConfig, DriverHandle, EdgeDirection, EndpointConfig, Event, LinkProfile,
};

fn start(name: &str, seed: u64) -> DriverHandle {
    let mut c = EndpointConfig::new(name, "loopback-test", b"secret");
    c.peer_timeout = Duration::from_millis(600);
    let mut d = DriverConfig::new(c, SocketAddr::from(([127, 0, 0, 1], 0)));
    d.seed = seed;
    Driver::start(d).unwrap()
}

async fn connect(a: &DriverHandle, b: &DriverHandle, link: LinkProfile, capacity: u64) {
    a.command(Command::AddPeer {
        name: "b".into(),
        addr: b.local_addr(),
        link,
    })
    .await
    .unwrap();
    b.command(Command::AddPeer {
        name: "a".into(),
        addr: a.local_addr(),
        link,
    })
    .await
    .unwrap();
    a.command(Command::OpenEdge {
        edge: 1,
        peer: "b".into(),
        direction: EdgeDirection::Send,
        capacity,
    })
    .await
    .unwrap();
    b.command(Command::OpenEdge {
        edge: 1,
        peer: "a".into(),
        direction: EdgeDirection::Receive,
        capacity,
    })
    .await
    .unwrap();
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
            bytes: pattern(n, i as u8),
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

async fn wait_for(a: &mut DriverHandle, want: fn(&Event) -> bool) -> Event {
    let fut = async {
        loop {
            let e = a.next_event().await.expect("driver alive");
            if want(&e) {
                return e;
            }
        }
    };
    tokio::time::timeout(Duration::from_secs(5), fut)
        .await
        .expect("event within 5 s")
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
        bytes: b"again".to_vec(),
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
