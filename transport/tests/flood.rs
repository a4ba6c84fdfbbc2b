//! A stranger floods a node with 200,000 datagrams (laminar "reliable ordered" packets that
//! laminar would buffer, and garbage): the node's memory stays bounded, everything is
//! counted, and the link to its real peer keeps working. Alone in its test binary so that
//! the resident-memory reading is this test's.

use std::net::UdpSocket;
use std::time::{Duration, Instant};

mod common;

use cloudlight_transport::{Command, Event, LinkProfile};

/// A laminar packet of delivery `Reliable`, ordering `Ordered`, with a gap before it so that
/// laminar would hold it for the missing ones.
fn laminar_reliable_ordered(i: u32) -> Vec<u8> {
    let v = crc::crc16::checksum_x25(b"laminar-0.1.0").to_be_bytes();
    let mut d = vec![v[0], v[1], 0, 1, 2];
    d.extend_from_slice(&(i as u16).to_be_bytes()); // sequence
    d.extend_from_slice(&0u16.to_be_bytes()); // ack sequence
    d.extend_from_slice(&0u32.to_be_bytes()); // ack field
    d.extend_from_slice(&(1000 + i as u16 % 60_000).to_be_bytes()); // arranging id
    d.push(7); // stream
    d.resize(1100, 0xAB);
    d
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stranger_flood_is_counted_and_holds_no_memory() {
    let a = common::start("a", "flood-test", 1);
    let mut b = common::start("b", "flood-test", 2);
    common::connect(&a, &b, LinkProfile::default(), 4).await;
    common::wait_for(&mut b, |e| matches!(e, Event::PeerUp { .. })).await;
    let before = common::rss_bytes();
    let attacker = UdpSocket::bind("127.0.0.1:0").unwrap();
    let target = b.local_addr();
    let started = Instant::now();
    let mut sent = 0u32;
    while sent < 200_000 && started.elapsed() < Duration::from_secs(60) {
        let d = if sent % 4 == 3 {
            vec![(sent % 251) as u8; 1 + (sent % 1200) as usize]
        } else {
            laminar_reliable_ordered(sent)
        };
        if attacker.send_to(&d, target).is_ok() {
            sent += 1;
        }
        if sent.is_multiple_of(2_000) {
            // Let the node drain its socket rather than the kernel drop most of the flood.
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
    }
    tokio::time::sleep(Duration::from_millis(300)).await;
    let grown = common::rss_bytes().saturating_sub(before);
    let stats = b.stats();
    assert!(
        grown < 24 << 20,
        "resident memory grew {} MB under the flood",
        grown >> 20
    );
    assert!(
        stats.malformed > 100_000,
        "flood datagrams are counted: {}",
        stats.malformed
    );
    a.command(Command::Send {
        edge: 1,
        bytes: b"still here".as_slice().into(),
    })
    .await
    .unwrap();
    let got = tokio::time::timeout(Duration::from_secs(5), async {
        loop {
            if let Some(Event::Message { bytes, .. }) = b.next_event().await {
                return bytes;
            }
        }
    })
    .await
    .expect("the real peer still gets through");
    assert_eq!(got, b"still here");
    eprintln!(
        "{sent} datagrams in {:.2} s; resident memory +{} kB; counted malformed {}",
        started.elapsed().as_secs_f64(),
        grown >> 10,
        stats.malformed
    );
}
