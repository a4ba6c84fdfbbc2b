//! Node-to-node links for cut edges, over laminar.
//!
//! - [`wire`]: the packet format (versioned, tagged, decoded without panics).
//! - [`crypto`]: handshake tags, session keys, packet protection and the replay window (what
//!   they protect against is in the crate's README).
//! - [`endpoint`]: the sans-IO protocol core: an authenticated handshake, sealed session
//!   packets, chunking below laminar's fragment limit, bounded reassembly, per-edge ordering,
//!   selective acks and retransmission in a send window, pacing, credits that carry an
//!   edge's capacity across the link, heartbeats, peer loss/restart and stall detection.
//!   Every call takes `now`.
//! - [`emulator`]: a seeded, sans-IO link emulator (latency, jitter, bandwidth, loss,
//!   duplication, reordering) applied per direction per pair of nodes.
//! - [`driver`]: the I/O thread: one per node socket, driving laminar's `manual_poll` with
//!   no fixed sleep (it waits on socket readiness, timers and a waker), bridged to tokio.
//!
//! - [`bench`](mod@bench): two drivers on loopback through the emulator, and a plain UDP blast as the
//!   ceiling (`cloudlight bench transport`).
//!
//! This crate moves opaque, already-encoded edge messages; it never knows about lighting,
//! stages or topologies.

pub mod bench;
pub mod crypto;
pub mod driver;
pub mod emulator;
pub mod endpoint;
mod udp;
pub mod wire;

/// A hash map for keys looked up per packet (foldhash: fast on small keys, seeded per map).
pub(crate) type FastMap<K, V> = std::collections::HashMap<K, V, foldhash::fast::RandomState>;

pub use driver::{Command, Commander, Driver, DriverConfig, DriverHandle, DriverStats};
pub use emulator::{LinkEmulator, LinkProfile};
pub use endpoint::{
    EdgeDirection, EdgeWireStats, Endpoint, EndpointConfig, EndpointStats, Event, PeerStats,
    SendError,
};
