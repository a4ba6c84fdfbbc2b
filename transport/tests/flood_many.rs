//! 200,000 datagrams from 97 source ports (as a spoofing attacker's would come) flood a node
//! as fast as one thread sends them, while its real peer keeps sending: the node holds no
//! per-address state for strangers, its memory stays bounded, and every real message
//! arrives, intact and in order. Alone in its test binary so that the resident-memory
//! reading is this test's.

use std::net::UdpSocket;
use std::time::{Duration, Instant};

mod common;

use cloudlight_transport::{Command, Event, LinkProfile};

/// A datagram that looks like the transport's: laminar's unreliable header, then our magic,
/// version and a session packet's kind, then noise.
fn lookalike(i: u32) -> Vec<u8> {
    let v = crc::crc16::checksum_x25(b"laminar-0.1.0").to_be_bytes();
    let mut d = vec![v[0], v[1], 0, 0, 0, b'C', b'L', 4, 10 + (i % 9) as u8];
    d.extend_from_slice(&i.to_le_bytes());
    d.resize(60 + (i as usize * 37) % 1100, (i % 251) as u8);
    d
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flood_from_many_addresses_holds_no_memory_and_spares_the_real_peer() {
    let a = common::start("a", "flood-test", 1);
    let mut b = common::start("b", "flood-test", 2);
    common::connect(&a, &b, LinkProfile::default(), 64).await;
    common::wait_for(&mut b, |e| matches!(e, Event::PeerUp { .. })).await;
    let before = common::rss_bytes();
    let target = b.local_addr();
    let flood = std::thread::spawn(move || {
        let sockets: Vec<UdpSocket> = (0..97)
            .map(|_| UdpSocket::bind("127.0.0.1:0").unwrap())
            .collect();
        let started = Instant::now();
        let mut sent = 0u32;
        while sent < 200_000 && started.elapsed() < Duration::from_secs(60) {
            let s = &sockets[sent as usize % sockets.len()];
            if s.send_to(&lookalike(sent), target).is_ok() {
                sent += 1;
            }
        }
        (sent, started.elapsed())
    });
    // The real peer sends throughout the flood.
    let messages: Vec<Vec<u8>> = (0..400u32)
        .map(|i| (0..1000).map(|k| (k as u32 * 7 + i) as u8).collect())
        .collect();
    let send = {
        let commander = a.commander();
        let messages = messages.clone();
        tokio::spawn(async move {
            for m in messages {
                commander
                    .command(Command::Send {
                        edge: 1,
                        bytes: m.into(),
                    })
                    .await
                    .unwrap();
                tokio::time::sleep(Duration::from_micros(500)).await;
            }
        })
    };
    let mut got = Vec::new();
    let mut peak = 0;
    let deadline = tokio::time::Instant::now() + Duration::from_secs(60);
    while got.len() < messages.len() {
        let e = tokio::time::timeout_at(deadline, b.next_event())
            .await
            .expect("every real message within 60 s")
            .expect("driver alive");
        if let Event::Message { seq, bytes, .. } = e {
            assert_eq!(seq, got.len() as u64);
            got.push(bytes);
            b.command(Command::Release { edge: 1, n: 1 }).await.unwrap();
        }
        peak = peak.max(common::rss_bytes());
    }
    send.await.unwrap();
    let (sent, took) = flood.join().unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;
    peak = peak.max(common::rss_bytes());
    assert!(
        got == messages,
        "the real messages arrive intact and in order"
    );
    let grown = peak.saturating_sub(before);
    assert!(
        grown < 24 << 20,
        "resident memory grew {} MB under the flood",
        grown >> 20
    );
    let stats = b.stats();
    let counted = stats.malformed + stats.strangers + stats.endpoint.unknown_session;
    assert!(counted > 0, "the flood is counted");
    assert!(
        stats.peer("a").refused == 0 && stats.peer("a").forged == 0,
        "nothing of the real peer's refused: {:?}",
        stats.peer("a")
    );
    eprintln!(
        "{sent} datagrams from 97 ports in {:.2} s; {counted} reached the node ({:.0}%, the \
         rest dropped by the kernel), {} receive calls; resident memory +{} kB at peak",
        took.as_secs_f64(),
        100.0 * counted as f64 / sent as f64,
        stats.io.recv_calls,
        grown >> 10,
    );
}
