//! Criterion bench of the protocol core's chunk → packet → reassemble path, with no socket:
//! two endpoints hand datagrams to each other in memory. It measures the CPU cost the core
//! adds per byte, the ceiling of what the transport can push on one core.

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use cloudlight_transport::{EdgeDirection, Endpoint, EndpointConfig, Event};
use criterion::{Criterion, Throughput, criterion_group, criterion_main};

fn pair(packet_bytes: usize) -> (Endpoint, Endpoint, Instant) {
    let now = Instant::now();
    let mk = |name: &str, peer: &str, port: u16, seed: u8| {
        let mut c = EndpointConfig::new(name, "bench", b"secret");
        c.nonce_seed = [seed; 32];
        c.max_packet_bytes = packet_bytes;
        let mut e = Endpoint::new(c, now);
        e.add_peer(peer, SocketAddr::from(([127, 0, 0, 1], port)), now);
        e
    };
    let mut a = mk("a", "b", 2, 1);
    let mut b = mk("b", "a", 1, 2);
    a.open_edge(0, "b", EdgeDirection::Send, 1 << 20).unwrap();
    b.open_edge(0, "a", EdgeDirection::Receive, 1 << 20)
        .unwrap();
    pump(&mut a, &mut b, now, |_| false);
    (a, b, now)
}

/// Moves datagrams both ways until `done` says so or nothing moves.
fn pump(
    a: &mut Endpoint,
    b: &mut Endpoint,
    now: Instant,
    mut done: impl FnMut(&Event) -> bool,
) -> bool {
    let (aa, ba) = (
        SocketAddr::from(([127, 0, 0, 1], 1)),
        SocketAddr::from(([127, 0, 0, 1], 2)),
    );
    loop {
        let mut moved = false;
        while let Some((_, d)) = a.poll_transmit(now) {
            b.handle_datagram(now, aa, &d);
            moved = true;
        }
        while let Some((_, d)) = b.poll_transmit(now) {
            a.handle_datagram(now, ba, &d);
            moved = true;
        }
        let mut hit = false;
        while let Some(e) = b.poll_event() {
            hit |= done(&e);
        }
        while a.poll_event().is_some() {}
        if hit {
            return true;
        }
        if !moved {
            return false;
        }
    }
}

fn bench(c: &mut Criterion) {
    let mut g = c.benchmark_group("core_transfer");
    g.measurement_time(Duration::from_secs(5));
    for (packet, size) in [(1200usize, 1usize << 20), (8192, 1 << 20), (1200, 1024)] {
        g.throughput(Throughput::Bytes(size as u64));
        g.bench_function(format!("{size}B_message_{packet}B_packets"), |bench| {
            let (mut a, mut b, mut now) = pair(packet);
            let msg = vec![7u8; size];
            bench.iter(|| {
                now += Duration::from_micros(1);
                a.send(0, msg.clone()).unwrap();
                let ok = pump(&mut a, &mut b, now, |e| matches!(e, Event::Message { .. }));
                assert!(ok);
                b.release(0, 1);
            });
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
