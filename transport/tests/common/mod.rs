//! Helpers shared by the transport's integration tests: drivers on loopback, joined by one
//! edge, and bounded waits for events.
#![allow(dead_code)]

use std::net::SocketAddr;
use std::time::Duration;

use cloudlight_transport::{
    Command, Driver, DriverConfig, DriverHandle, EdgeDirection, EndpointConfig, Event, LinkProfile,
};

/// A driver named `name` of cluster `cluster` on a free loopback port.
pub fn start(name: &str, cluster: &str, seed: u64) -> DriverHandle {
    let mut c = EndpointConfig::new(name, cluster, b"secret");
    c.peer_timeout = Duration::from_millis(600);
    let mut d = DriverConfig::new(c, SocketAddr::from(([127, 0, 0, 1], 0)));
    d.seed = seed;
    Driver::start(d).unwrap()
}

/// Declares a and b to each other at `a_sees` / `b_sees` (their own addresses, or a relay's)
/// and opens edge 1 from a to b.
pub async fn connect_via(
    (a, a_sees): (&DriverHandle, SocketAddr),
    (b, b_sees): (&DriverHandle, SocketAddr),
    link: LinkProfile,
    capacity: u64,
) {
    for (d, peer, addr) in [(b, "a", b_sees), (a, "b", a_sees)] {
        d.command(Command::AddPeer {
            name: peer.into(),
            addr,
            link,
        })
        .await
        .unwrap();
    }
    for (d, peer, direction) in [
        (a, "b", EdgeDirection::Send),
        (b, "a", EdgeDirection::Receive),
    ] {
        d.command(Command::OpenEdge {
            edge: 1,
            peer: peer.into(),
            direction,
            capacity,
        })
        .await
        .unwrap();
    }
}

/// [`connect_via`] with each side seeing the other's own address.
pub async fn connect(a: &DriverHandle, b: &DriverHandle, link: LinkProfile, capacity: u64) {
    connect_via((a, b.local_addr()), (b, a.local_addr()), link, capacity).await;
}

/// The next event that `want` accepts, within 5 s.
pub async fn wait_for(a: &mut DriverHandle, want: fn(&Event) -> bool) -> Event {
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

/// This process's resident memory, bytes (0 where /proc is not there).
pub fn rss_bytes() -> u64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
        .map_or(0, |kb| kb * 1024)
}
