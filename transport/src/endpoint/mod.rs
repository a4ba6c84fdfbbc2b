//! The sans-IO protocol core: no sockets, no clock — every call takes `now`, and the caller
//! moves datagrams ([`Endpoint::handle_datagram`], [`Endpoint::poll_transmit`]) and wakes it
//! at [`Endpoint::poll_timeout`]. One endpoint serves one node socket and all its peers.
//!
//! - **Handshake** (three messages, see `handshake`): the initiator's HELLO carries a fresh
//!   nonce; the responder's CHALLENGE echoes it with a fresh nonce of its own; the
//!   initiator's CONFIRM echoes that. Each carries the cluster id, both names, the sender's
//!   topology digest and clock epoch, and an HMAC under the shared secret over all of it, so
//!   each side has proof that the other knows the secret *now*: a recorded HELLO, CHALLENGE
//!   or CONFIRM from this or an earlier run completes nothing. Session keys come from the
//!   secret and both nonces (HKDF); the session is bound to the address the peer proved
//!   itself from. A node without a session initiates; a new session that replaces an old one
//!   is a peer restart: both sides reset their edge streams and the messages that were
//!   outstanding are reported lost. Nodes whose topologies differ refuse each other
//!   ([`Event::TopologyMismatch`]).
//! - **Session packets** carry the session id and a packet number, and are sealed with
//!   AES-256-GCM (integrity, and confidentiality when configured); a replay window
//!   refuses numbers seen before. An authentic packet from another address is not obeyed:
//!   the address is challenged and the link moves only when it answers.
//!   PING/PONG heartbeats measure the round trip; a peer silent for `peer_timeout` is
//!   reported lost, and reported up again when heard.
//! - **Messages** of an edge are split into chunks that fit one datagram (laminar never
//!   fragments), each DATA packet gets a packet number, and the receiver acknowledges packet
//!   numbers with every gap of the window (up to 1,024 ranges, QUIC's ACK frame coding),
//!   never a number it did not receive. Packets are declared lost as RFC 9002 does (see
//!   `send.rs`); their chunks are sent again in new packets. At most `window_packets` are
//!   unacknowledged per peer; with `congestion_control` ([`cc`], a BBR-style model) sending
//!   is paced at the measured delivery rate with about two bandwidth-delay products in
//!   flight, and `pacing_bytes_per_s` caps the rate. Data that makes no progress for
//!   `stall_timeout` while the peer answers heartbeats is reported ([`Event::Stalled`]).
//! - **Reassembly** is bounded: a message longer than `max_message_bytes` is refused, all
//!   partial messages of a peer together never hold more than `max_reassembly_bytes`, and a
//!   sequence number beyond the edge's credit is a protocol violation. Complete messages are
//!   delivered per edge in sequence order, exactly once.
//! - **Credits** carry an edge's capacity across the link: the receiving side grants
//!   `released + capacity` (cumulative, so duplicates and loss are harmless, and re-sent with
//!   every heartbeat), and the sending side may only have sent that many messages.

pub mod cc;
mod handshake;
mod noise;
mod recv;
mod send;
mod session;

use std::collections::{HashMap, VecDeque};
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use rand::SeedableRng;
use rand_chacha::ChaCha20Rng;

use crate::crypto::{ReplayWindow, SessionSecrets};
use crate::wire::{self, Body, DIGEST_BYTES, NONCE_BYTES, SESSION_HEADER_BYTES};
use handshake::{Initiation, PendingChallenge};
use noise::Noise;
use recv::{RecvEdge, RecvState};
use send::{SendEdge, SendState};

/// Settings of an endpoint. Durations are wall time; sizes are bytes.
#[derive(Clone, Debug)]
pub struct EndpointConfig {
    /// This node's name.
    pub node: String,
    /// Cluster id; peers of another cluster are strangers.
    pub cluster: String,
    /// Shared secret proving membership (the handshake's HMAC key and the session keys' input).
    pub secret: Vec<u8>,
    /// Digest of this node's topology; peers with another digest are refused.
    pub topology_digest: [u8; DIGEST_BYTES],
    /// Whether session packets are encrypted (they are always authenticated).
    pub confidential: bool,
    /// Seed of the handshake nonces and path tokens: random, new at every start.
    pub nonce_seed: [u8; 32],
    /// Opaque value given to peers in the handshake (the runtime sends its clock epoch).
    pub epoch: u64,
    /// Largest packet handed to laminar (laminar adds 5 bytes of header to the datagram).
    pub max_packet_bytes: usize,
    /// Largest message accepted (default 64 MiB).
    pub max_message_bytes: usize,
    /// Most bytes held by partial messages of one peer.
    pub max_reassembly_bytes: usize,
    /// Most unacknowledged DATA packets per peer.
    pub window_packets: usize,
    /// Sending rate cap per peer, bytes per second; `None` is unpaced.
    pub pacing_bytes_per_s: Option<f64>,
    /// Congestion control on each peer link (see [`cc`]): pace at the measured delivery rate
    /// and keep about two bandwidth-delay products in flight. `pacing_bytes_per_s` caps it.
    pub congestion_control: bool,
    /// Packet numbers each key protects before the next one takes over
    /// ([`crate::crypto::KEY_UPDATE_PACKETS`]; smaller only in tests). At least twice
    /// `window_packets`, so a sender is never more than one key update ahead of its peer.
    pub key_update_packets: u64,
    /// Longest an acknowledgement waits to be sent.
    pub ack_delay: Duration,
    /// An acknowledgement is sent at once after this many packets.
    pub ack_every: u32,
    /// Interval between heartbeats (and credit refreshes).
    pub heartbeat_interval: Duration,
    /// A peer silent this long is reported lost.
    pub peer_timeout: Duration,
    /// Data unacknowledged this long while the peer answers heartbeats is reported stalled.
    pub stall_timeout: Duration,
    /// Interval between handshake attempts.
    pub hello_interval: Duration,
    /// Lower bound of the probe timeout: RFC 9002's timer granularity (1 ms). A higher floor
    /// made every tail loss on a sub-millisecond path (a LAN, loopback) wait for it: 1 MiB at
    /// 20% loss ran at 126 MB/s with 5 ms, 217 MB/s with 1 ms, no spurious retransmission
    /// loss-free.
    pub min_rto: Duration,
    /// Upper bound of the retransmission timeout.
    pub max_rto: Duration,
    /// Handshake answers per second to addresses other than a peer's known one, at most.
    pub challenges_per_s: f64,
}

impl EndpointConfig {
    /// Defaults for node `node` of cluster `cluster` with `secret`; the nonce seed is drawn
    /// from the operating system's randomness.
    pub fn new(node: &str, cluster: &str, secret: &[u8]) -> Self {
        EndpointConfig {
            node: node.to_string(),
            cluster: cluster.to_string(),
            secret: secret.to_vec(),
            topology_digest: [0; DIGEST_BYTES],
            confidential: true,
            nonce_seed: rand::random(),
            epoch: 0,
            max_packet_bytes: 1200,
            max_message_bytes: 64 << 20,
            max_reassembly_bytes: 256 << 20,
            window_packets: 1024,
            pacing_bytes_per_s: None,
            congestion_control: true,
            key_update_packets: crate::crypto::KEY_UPDATE_PACKETS,
            ack_delay: Duration::from_micros(500),
            ack_every: 16,
            heartbeat_interval: Duration::from_millis(100),
            peer_timeout: Duration::from_secs(2),
            stall_timeout: Duration::from_secs(15),
            hello_interval: Duration::from_millis(50),
            min_rto: Duration::from_millis(1),
            max_rto: Duration::from_secs(1),
            challenges_per_s: 50.0,
        }
    }

    /// Payload bytes of one chunk.
    pub fn chunk_bytes(&self) -> usize {
        self.max_packet_bytes
            .saturating_sub(wire::DATA_OVERHEAD)
            .max(1)
    }
}

/// Which way an edge's messages travel from this endpoint.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum EdgeDirection {
    /// This node produces, the peer consumes.
    Send,
    /// The peer produces, this node consumes.
    Receive,
}

/// What the endpoint tells its owner.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Event {
    /// The handshake with a peer completed (or a lost peer was heard again).
    PeerUp {
        /// Peer name.
        peer: String,
        /// The peer's handshake value (its clock epoch).
        epoch: u64,
    },
    /// A peer was silent for longer than the timeout.
    PeerLost {
        /// Peer name.
        peer: String,
    },
    /// A peer said goodbye (it is shutting down).
    PeerLeft {
        /// Peer name.
        peer: String,
        /// Its run failed (it said so in its goodbye).
        failed: bool,
    },
    /// A peer proved a new session (it restarted): edge streams were reset on both sides.
    PeerRestarted {
        /// Peer name.
        peer: String,
        /// Messages sent to it that were not acknowledged and are gone.
        lost_messages: u64,
    },
    /// A peer that knows the secret runs a different topology: the link is refused.
    TopologyMismatch {
        /// Peer name.
        peer: String,
    },
    /// Data to a peer that answers heartbeats made no progress for `stall_timeout`.
    Stalled {
        /// Peer name.
        peer: String,
        /// Milliseconds without an acknowledgement of new data.
        waited_ms: u64,
    },
    /// A complete message, in order on its edge.
    Message {
        /// Edge id.
        edge: u32,
        /// Sequence number on the edge.
        seq: u64,
        /// The bytes.
        bytes: Vec<u8>,
    },
    /// The peer acknowledged every chunk of a message.
    Delivered {
        /// Edge id.
        edge: u32,
        /// Sequence number.
        seq: u64,
    },
    /// The peer granted credit: in total `granted` messages may have been sent on the edge
    /// (cumulative; `granted − capacity` messages were finished by the remote consumer).
    Credit {
        /// Edge id.
        edge: u32,
        /// Cumulative grant.
        granted: u64,
    },
}

/// Why [`Endpoint::send`] refused a message.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SendError {
    /// No such edge, or it receives.
    #[error("edge {0} is not a sending edge of this endpoint")]
    NoEdge(u32),
    /// The edge's credit is used up: wait for [`Event::Credit`].
    #[error("edge {0} has no credit")]
    NoCredit(u32),
    /// The message is longer than `max_message_bytes`.
    #[error("message of {0} bytes exceeds the maximum")]
    TooLarge(usize),
}

/// Counters of one peer link.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PeerStats {
    /// Whether the peer is up.
    pub up: bool,
    /// Packets sent to it (all kinds).
    pub packets_sent: u64,
    /// DATA packets sent, first transmissions and retransmissions.
    pub data_packets_sent: u64,
    /// DATA packets that were retransmissions.
    pub retransmissions: u64,
    /// Bytes of all packets sent.
    pub wire_bytes_sent: u64,
    /// Packets received from it and accepted.
    pub packets_received: u64,
    /// Bytes of packets received and accepted.
    pub wire_bytes_received: u64,
    /// Smoothed round-trip time, seconds (0 until measured).
    pub srtt_s: f64,
    /// Authentic DATA refused (beyond credit, over the reassembly bound, unknown edge).
    pub refused: u64,
    /// Packets of its session whose number was seen before (replays, network duplicates).
    pub replayed: u64,
    /// Packets naming its session that failed authentication (forgeries, corruption).
    pub forged: u64,
    /// Sessions completed with it.
    pub handshakes: u64,
    /// Times it restarted (a new session replaced a live one).
    pub restarts: u64,
    /// Messages sent to it that were lost with a restart.
    pub lost_messages: u64,
    /// Times its address moved after answering a path challenge.
    pub moves: u64,
    /// Authentic packets of its session from an address other than its own, not obeyed
    /// (the address is sent a path challenge; a NAT rebinding shows here before a move).
    pub misaddressed: u64,
    /// Handshakes under its name that proved the secret but ran another topology, refused
    /// while its live session stayed (a second deployment sharing the secret).
    pub mismatched: u64,
}

/// Counters of packets that belong to no peer.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct EndpointStats {
    /// Handshake packets from unknown names, other clusters, or without proof of the secret.
    pub strangers: u64,
    /// Datagrams that did not decode.
    pub malformed: u64,
    /// Session packets of no current session (strangers, or a peer's previous session).
    pub unknown_session: u64,
    /// Handshake packets that were valid but stale: a recorded HELLO, CHALLENGE or CONFIRM.
    pub stale_handshakes: u64,
    /// Handshake answers withheld by the rate limit.
    pub rate_limited: u64,
}

/// Per-edge wire counters.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct EdgeWireStats {
    /// Messages sent (send edges) or delivered (receive edges).
    pub messages: u64,
    /// Bytes of DATA packets sent for this edge, headers and retransmissions included.
    pub wire_bytes: u64,
    /// DATA packets of this edge sent again.
    pub retransmissions: u64,
}

/// A live session with a peer.
pub(crate) struct Session {
    secrets: SessionSecrets,
    replay: ReplayWindow,
    /// The initiator's proof was answered by an authentic packet (always true for a responder).
    confirmed: bool,
    /// The nonces, to send CONFIRM again until the responder is heard.
    nonces: ([u8; NONCE_BYTES], [u8; NONCE_BYTES]),
    established: Instant,
    confirm_due: Instant,
}

/// Validation of a new address an authentic packet came from.
struct PathProbe {
    addr: SocketAddr,
    token: u64,
    sent: Instant,
}

pub(crate) struct Peer {
    pub(crate) name: String,
    /// Where packets go: the configured address until a session binds the proven one.
    pub(crate) addr: SocketAddr,
    session: Option<Session>,
    initiation: Option<Initiation>,
    pending: Vec<PendingChallenge>,
    remote_epoch: u64,
    /// A session is confirmed and the peer is not lost.
    up: bool,
    ever_up: bool,
    /// The peer said goodbye: only a new handshake brings it back.
    gone: bool,
    /// A topology mismatch was reported (once).
    mismatch: bool,
    /// A stall was reported since the last progress (once).
    stall_reported: bool,
    hello_due: Instant,
    last_heard: Instant,
    ping_due: Instant,
    path: Option<PathProbe>,
    pub(crate) send: SendState,
    pub(crate) recv: RecvState,
    pub(crate) stats: PeerStats,
}

/// What waits to be sent outside the data flow.
enum Control {
    /// A tagged handshake packet, to an address.
    Raw(SocketAddr, Vec<u8>),
    /// A session body for a peer, sealed when sent (to `to`, or the peer's address).
    Body(usize, Option<SocketAddr>, Body<'static>),
}

/// One node's protocol state machine (see the module documentation).
pub struct Endpoint {
    config: EndpointConfig,
    start: Instant,
    rng: ChaCha20Rng,
    peers: Vec<Peer>,
    sessions: HashMap<u64, usize>,
    send_edges: crate::FastMap<u32, SendEdge>,
    recv_edges: crate::FastMap<u32, RecvEdge>,
    events: VecDeque<Event>,
    control: VecDeque<Control>,
    stats: EndpointStats,
    noise: Noise,
    challenge_tokens: f64,
    challenge_refill: Instant,
    scratch: Vec<u8>,
    closing: bool,
    /// Whose turn it is to send data, and how many packets it sent in this turn.
    data_turn: (usize, usize),
}

/// DATA packets one peer sends in a row before the next peer's turn: long enough for a GSO
/// train (one system call for all of them), short enough to share the socket fairly.
const DATA_BURST: usize = 32;

impl Endpoint {
    /// A new endpoint; `now` starts its clock.
    pub fn new(config: EndpointConfig, now: Instant) -> Self {
        Endpoint {
            rng: ChaCha20Rng::from_seed(config.nonce_seed),
            challenge_tokens: config.challenges_per_s.max(1.0),
            config,
            start: now,
            peers: Vec::new(),
            sessions: HashMap::new(),
            send_edges: Default::default(),
            recv_edges: Default::default(),
            events: VecDeque::new(),
            control: VecDeque::new(),
            stats: EndpointStats::default(),
            noise: Noise::new(now),
            challenge_refill: now,
            scratch: Vec::new(),
            closing: false,
            data_turn: (0, 0),
        }
    }

    /// The configuration.
    pub fn config(&self) -> &EndpointConfig {
        &self.config
    }

    /// Declares a peer this node talks to (or moves a declared one before it has a session);
    /// the handshake starts at the next poll.
    pub fn add_peer(&mut self, name: &str, addr: SocketAddr, now: Instant) {
        if let Some(i) = self.peer_index(name) {
            if self.peers[i].session.is_none() {
                self.peers[i].addr = addr;
            }
            return;
        }
        self.peers.push(Peer {
            name: name.to_string(),
            addr,
            session: None,
            initiation: None,
            pending: Vec::new(),
            remote_epoch: 0,
            up: false,
            ever_up: false,
            gone: false,
            mismatch: false,
            stall_reported: false,
            hello_due: now,
            last_heard: now,
            ping_due: now,
            path: None,
            send: SendState::new(&self.config, now),
            recv: RecvState::default(),
            stats: PeerStats::default(),
        });
    }

    fn peer_index(&self, name: &str) -> Option<usize> {
        self.peers.iter().position(|p| p.name == name)
    }

    /// Opens an edge to or from `peer` with end-to-end `capacity` (messages).
    pub fn open_edge(
        &mut self,
        edge: u32,
        peer: &str,
        direction: EdgeDirection,
        capacity: u64,
    ) -> Result<(), String> {
        let p = self
            .peer_index(peer)
            .ok_or_else(|| format!("unknown peer `{peer}`"))?;
        if self.send_edges.contains_key(&edge) || self.recv_edges.contains_key(&edge) {
            return Err(format!("edge {edge} is already open"));
        }
        match direction {
            EdgeDirection::Send => {
                self.send_edges.insert(edge, SendEdge::new(p, capacity));
            }
            EdgeDirection::Receive => {
                self.recv_edges.insert(edge, RecvEdge::new(p, capacity));
            }
        }
        Ok(())
    }

    /// Whether the handshake with `peer` is complete and it is not lost.
    pub fn is_up(&self, peer: &str) -> bool {
        self.peer_index(peer).is_some_and(|i| self.peers[i].up)
    }

    /// The handshake value `peer` sent (its clock epoch), once a session exists.
    pub fn peer_epoch(&self, peer: &str) -> Option<u64> {
        let p = &self.peers[self.peer_index(peer)?];
        p.session.as_ref().map(|_| p.remote_epoch)
    }

    /// Counters of the link to `peer`.
    pub fn peer_stats(&self, peer: &str) -> Option<PeerStats> {
        let p = &self.peers[self.peer_index(peer)?];
        Some(PeerStats {
            up: p.up,
            ..p.stats
        })
    }

    /// Wire counters of an edge.
    pub fn edge_stats(&self, edge: u32) -> Option<EdgeWireStats> {
        self.send_edges
            .get(&edge)
            .map(|e| e.stats)
            .or_else(|| self.recv_edges.get(&edge).map(|e| e.stats))
    }

    /// Names of the declared peers.
    pub fn peer_names(&self) -> impl Iterator<Item = &str> {
        self.peers.iter().map(|p| p.name.as_str())
    }

    /// Ids of the open edges.
    pub fn edge_ids(&self) -> impl Iterator<Item = u32> + '_ {
        self.send_edges
            .keys()
            .chain(self.recv_edges.keys())
            .copied()
    }

    /// Counters of packets that belong to no peer.
    pub fn stats(&self) -> EndpointStats {
        self.stats
    }

    /// Handshake packets from strangers or without proof, ignored.
    pub fn strangers(&self) -> u64 {
        self.stats.strangers
    }

    /// Datagrams that did not decode.
    pub fn malformed(&self) -> u64 {
        self.stats.malformed
    }

    /// Bytes held by partial messages from `peer` (bounded by `max_reassembly_bytes`).
    pub fn reassembly_bytes(&self, peer: &str) -> usize {
        self.peer_index(peer)
            .map_or(0, |i| self.peers[i].recv.reassembly_bytes())
    }

    /// Messages that may be sent on `edge` now.
    pub fn credit(&self, edge: u32) -> u64 {
        self.send_edges.get(&edge).map_or(0, |e| e.available())
    }

    /// Queues a message on a sending edge; it goes out once the peer is up. The bytes are
    /// shared, not copied: one encoding of a message fanned out to many peers is held once.
    pub fn send(&mut self, edge: u32, data: impl Into<Arc<[u8]>>) -> Result<u64, SendError> {
        let data = data.into();
        if data.len() > self.config.max_message_bytes {
            return Err(SendError::TooLarge(data.len()));
        }
        let chunk = self.config.chunk_bytes();
        let e = self
            .send_edges
            .get_mut(&edge)
            .ok_or(SendError::NoEdge(edge))?;
        if e.available() == 0 {
            return Err(SendError::NoCredit(edge));
        }
        let seq = e.sent;
        e.sent += 1;
        e.stats.messages += 1;
        let peer = e.peer;
        self.peers[peer].send.queue_message(edge, seq, data, chunk);
        Ok(seq)
    }

    /// The consumer of a receiving edge finished `n` more messages: grant as much credit.
    pub fn release(&mut self, edge: u32, n: u64) {
        if let Some(e) = self.recv_edges.get_mut(&edge) {
            e.released = (e.released + n).min(e.next_seq);
            self.peers[e.peer].recv.credit_dirty = true;
        }
    }

    /// Says goodbye to every peer with a session (sent at the next polls), telling them
    /// whether this node's run `failed`.
    pub fn close(&mut self, failed: bool) {
        self.closing = true;
        for i in 0..self.peers.len() {
            if self.peers[i].session.is_some() {
                self.control
                    .push_back(Control::Body(i, None, Body::Bye { failed }));
            }
        }
    }

    /// The congestion controller's state of the link to `peer`.
    pub fn congestion(&self, peer: &str) -> Option<cc::CongestionStats> {
        let p = self.peer_index(peer)?;
        Some(self.peers[p].send.congestion().stats())
    }

    /// Next event, if any.
    pub fn poll_event(&mut self) -> Option<Event> {
        self.events.pop_front()
    }

    fn now_us(&self, now: Instant) -> u64 {
        now.saturating_duration_since(self.start).as_micros() as u64
    }

    /// Feeds one received datagram.
    pub fn handle_datagram(&mut self, now: Instant, from: SocketAddr, datagram: &[u8]) {
        match wire::decode(datagram) {
            Err(e) => {
                self.stats.malformed += 1;
                self.noise
                    .note(now, "malformed datagram", || format!("from {from}: {e}"));
            }
            Ok(wire::Packet::Handshake {
                message,
                tagged,
                tag,
            }) => self.handle_handshake(now, from, &message, tagged, tag),
            Ok(wire::Packet::Session(packet)) => {
                self.handle_session(now, from, &packet, datagram.len())
            }
        }
    }

    /// Runs timers due at `now`: loss detection, stalls, heartbeats, peer timeouts.
    pub fn handle_timeout(&mut self, now: Instant) {
        for p in 0..self.peers.len() {
            send::detect_losses(self, p, now);
            let config = &self.config;
            let peer = &mut self.peers[p];
            if peer.up && now.saturating_duration_since(peer.last_heard) > config.peer_timeout {
                peer.up = false;
                tracing::warn!(peer = %peer.name, "peer silent for {:?}: lost", config.peer_timeout);
                self.events.push_back(Event::PeerLost {
                    peer: peer.name.clone(),
                });
            }
            if let Some(waited) = peer.send.stalled_for(now)
                && peer.up
                && waited > config.stall_timeout
                && !peer.stall_reported
            {
                peer.stall_reported = true;
                tracing::error!(peer = %peer.name, "no data acknowledged for {waited:?} while the peer answers");
                self.events.push_back(Event::Stalled {
                    peer: peer.name.clone(),
                    waited_ms: waited.as_millis() as u64,
                });
            }
            self.expire_handshakes(p, now);
        }
        self.noise.flush(now);
    }

    /// Seals a session body for peer `p` onto the end of `out` (`false` without a session).
    fn seal_onto(&mut self, p: usize, body: &Body<'_>, out: &mut Vec<u8>) -> bool {
        let peer = &mut self.peers[p];
        let Some(session) = peer.session.as_ref() else {
            return false;
        };
        let pn = peer.send.take_pn();
        let start = out.len();
        body.encode_onto(out, session.secrets.id, pn);
        session
            .secrets
            .send
            .seal_in(pn, out, start, SESSION_HEADER_BYTES);
        true
    }

    /// Next datagram to send, if any may be sent at `now`.
    pub fn poll_transmit(&mut self, now: Instant) -> Option<(SocketAddr, Vec<u8>)> {
        let mut out = Vec::new();
        let to = self.poll_transmit_into(now, &mut out)?;
        Some((to, out))
    }

    /// Appends the next datagram to send at `now` to `out` and returns where it goes; `out`
    /// is untouched when there is none. Packets are encoded and sealed in place there, so a
    /// driver that batches datagrams copies each payload once on its way to the socket.
    pub fn poll_transmit_into(&mut self, now: Instant, out: &mut Vec<u8>) -> Option<SocketAddr> {
        let start = out.len();
        while let Some(c) = self.control.pop_front() {
            match c {
                Control::Raw(to, bytes) => {
                    out.extend_from_slice(&bytes);
                    return Some(to);
                }
                Control::Body(p, to, body) => {
                    if self.seal_onto(p, &body, out) {
                        let to = to.unwrap_or(self.peers[p].addr);
                        return Some(self.account(p, to, out.len() - start));
                    }
                }
            }
        }
        if self.closing {
            return None;
        }
        for p in 0..self.peers.len() {
            if let Some((to, bytes)) = self.poll_handshake(p, now) {
                out.extend_from_slice(&bytes);
                return Some(to);
            }
            if self.peers[p].session.as_ref().is_none_or(|s| !s.confirmed) {
                continue;
            }
            if let Some(ack) = recv::poll_ack(self, p, now) {
                return self.seal_to_peer(p, &ack, out);
            }
            let peer = &mut self.peers[p];
            if now >= peer.ping_due {
                peer.ping_due = now + self.config.heartbeat_interval;
                peer.recv.credit_dirty = true;
                let ping = Body::Ping {
                    t_us: self.now_us(now),
                };
                return self.seal_to_peer(p, &ping, out);
            }
            if let Some(credit) = recv::poll_credit(self, p) {
                return self.seal_to_peer(p, &credit, out);
            }
        }
        // Data last, round robin over peers in bursts of `DATA_BURST` packets.
        let n = self.peers.len();
        for k in 0..n {
            let p = (self.data_turn.0 + k) % n;
            if send::poll_data(self, p, now, out) {
                let burst = if k == 0 { self.data_turn.1 + 1 } else { 1 };
                self.data_turn = if burst >= DATA_BURST {
                    ((p + 1) % n, 0)
                } else {
                    (p, burst)
                };
                let to = self.peers[p].addr;
                return Some(self.account(p, to, out.len() - start));
            }
        }
        None
    }

    /// Appends an acknowledgement to a peer from which `every` packets (at least
    /// `ack_every`) arrived since the last to `out`, and returns where it goes. A driver
    /// calls it between the datagrams of one read, so that a read of a whole window is
    /// acknowledged as it is taken in, several times, rather than once at its end: one lost
    /// ACK then costs nothing, where a single one lost left the sender waiting for its probe
    /// timeout, and the sender learns of losses while the read goes on.
    pub fn poll_ack_into(
        &mut self,
        now: Instant,
        every: u32,
        out: &mut Vec<u8>,
    ) -> Option<SocketAddr> {
        let every = every.max(self.config.ack_every);
        for p in 0..self.peers.len() {
            let peer = &self.peers[p];
            if peer.recv.unacked < every || peer.session.as_ref().is_none_or(|s| !s.confirmed) {
                continue;
            }
            if let Some(ack) = recv::poll_ack(self, p, now) {
                return self.seal_to_peer(p, &ack, out);
            }
        }
        None
    }

    fn seal_to_peer(&mut self, p: usize, body: &Body<'_>, out: &mut Vec<u8>) -> Option<SocketAddr> {
        let start = out.len();
        if !self.seal_onto(p, body, out) {
            return None;
        }
        let to = self.peers[p].addr;
        Some(self.account(p, to, out.len() - start))
    }

    fn account(&mut self, p: usize, to: SocketAddr, bytes: usize) -> SocketAddr {
        let peer = &mut self.peers[p];
        peer.stats.packets_sent += 1;
        peer.stats.wire_bytes_sent += bytes as u64;
        to
    }

    /// When the endpoint next needs [`Endpoint::handle_timeout`] or [`Endpoint::poll_transmit`].
    pub fn poll_timeout(&self) -> Option<Instant> {
        let mut t: Option<Instant> = None;
        let mut at = |x: Instant| t = Some(t.map_or(x, |y| y.min(x)));
        at(self.noise.next_flush());
        for peer in &self.peers {
            match &peer.session {
                None => at(peer.hello_due),
                Some(s) if !s.confirmed => at(s.confirm_due),
                Some(_) => {
                    at(peer.ping_due);
                    if peer.up {
                        at(peer.last_heard + self.config.peer_timeout);
                    }
                }
            }
            if let Some(x) = peer.recv.ack_due {
                at(x);
            }
            if let Some(x) = peer.send.next_timer(&self.config, peer.up) {
                at(x);
            }
            if let Some(x) = peer.send.stall_deadline(&self.config)
                && !peer.stall_reported
            {
                at(x);
            }
        }
        t
    }
}

#[cfg(test)]
mod tests;
