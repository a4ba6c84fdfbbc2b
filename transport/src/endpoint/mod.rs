//! The sans-IO protocol core: no sockets, no clock — every call takes `now`, and the caller
//! moves datagrams ([`Endpoint::handle_datagram`], [`Endpoint::poll_transmit`]) and wakes it
//! at [`Endpoint::poll_timeout`]. One endpoint serves one node socket and all its peers.
//!
//! - **Peers** handshake with HELLO packets carrying the cluster id, both node names, the
//!   sender's incarnation (random per process start) and a truncated HMAC-SHA256 under the
//!   topology's shared secret. A peer is *up* when each side has seen the other's
//!   incarnation. Later packets must carry the peer's incarnation: anything else (strangers,
//!   stale incarnations, bad MACs) is ignored and counted, never delivered. A HELLO with a
//!   new incarnation means the peer restarted: its edge streams reset and the messages that
//!   were outstanding are reported lost. PING/PONG heartbeats measure the round trip; a peer
//!   silent for `peer_timeout` is reported lost, and reported up again when heard.
//! - **Messages** of an edge are split into chunks that fit one datagram (laminar never
//!   fragments), each DATA packet gets a packet number, and the receiver acknowledges packet
//!   numbers with up to 64 ranges. Packets are declared lost three packet numbers behind the
//!   largest acknowledged one, or after the retransmission timeout (`srtt + 4·rttvar`,
//!   doubling on expiry); their chunks are sent again in new packets. At most
//!   `window_packets` are unacknowledged per peer, and sending is paced to
//!   `pacing_bytes_per_s` when set.
//! - **Reassembly** is bounded: a message longer than `max_message_bytes` is refused, all
//!   partial messages of a peer together never hold more than `max_reassembly_bytes`, and a
//!   sequence number beyond the edge's credit is a protocol violation. Complete messages are
//!   delivered per edge in sequence order, exactly once.
//! - **Credits** carry an edge's capacity across the link: the receiving side grants
//!   `released + capacity` (cumulative, so duplicates and loss are harmless, and re-sent with
//!   every heartbeat), and the sending side may only have sent that many messages.

mod handshake;
mod recv;
mod send;

use std::collections::{HashMap, VecDeque};
use std::net::SocketAddr;
use std::time::{Duration, Instant};

use crate::wire::{self, Body};
use recv::{RecvEdge, RecvState};
use send::{SendEdge, SendState};

/// Settings of an endpoint. Durations are wall time; sizes are bytes.
#[derive(Clone, Debug)]
pub struct EndpointConfig {
    /// This node's name.
    pub node: String,
    /// Cluster id; peers of another cluster are strangers.
    pub cluster: String,
    /// Shared secret proving membership (HMAC key).
    pub secret: Vec<u8>,
    /// This process's incarnation: random, non-zero, new at every start.
    pub incarnation: u64,
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
    /// Longest an acknowledgement waits to be sent.
    pub ack_delay: Duration,
    /// An acknowledgement is sent at once after this many packets.
    pub ack_every: u32,
    /// Interval between heartbeats (and credit refreshes).
    pub heartbeat_interval: Duration,
    /// A peer silent this long is reported lost.
    pub peer_timeout: Duration,
    /// Interval between handshake attempts.
    pub hello_interval: Duration,
    /// Lower bound of the retransmission timeout.
    pub min_rto: Duration,
    /// Upper bound of the retransmission timeout.
    pub max_rto: Duration,
}

impl EndpointConfig {
    /// Defaults for node `node` of cluster `cluster` with `secret`.
    pub fn new(node: &str, cluster: &str, secret: &[u8], incarnation: u64) -> Self {
        EndpointConfig {
            node: node.to_string(),
            cluster: cluster.to_string(),
            secret: secret.to_vec(),
            incarnation: incarnation.max(1),
            epoch: 0,
            max_packet_bytes: 1200,
            max_message_bytes: 64 << 20,
            max_reassembly_bytes: 256 << 20,
            window_packets: 1024,
            pacing_bytes_per_s: None,
            ack_delay: Duration::from_micros(500),
            ack_every: 16,
            heartbeat_interval: Duration::from_millis(100),
            peer_timeout: Duration::from_secs(2),
            hello_interval: Duration::from_millis(50),
            min_rto: Duration::from_millis(5),
            max_rto: Duration::from_secs(1),
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
    },
    /// A peer came back with a new incarnation: edge streams were reset.
    PeerRestarted {
        /// Peer name.
        peer: String,
        /// Messages sent to it that were not acknowledged and are gone.
        lost_messages: u64,
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
    /// Packets refused (malformed, beyond credit, over the reassembly bound).
    pub refused: u64,
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

pub(crate) struct Peer {
    pub(crate) name: String,
    pub(crate) addr: SocketAddr,
    remote_incarnation: u64,
    remote_epoch: u64,
    /// We have seen them and they have seen us.
    up: bool,
    ever_up: bool,
    /// The peer said goodbye: only a new handshake brings it back.
    gone: bool,
    reply_hello: bool,
    hello_due: Instant,
    last_heard: Instant,
    ping_due: Instant,
    pub(crate) send: SendState,
    pub(crate) recv: RecvState,
    pub(crate) stats: PeerStats,
}

/// One node's protocol state machine (see the module documentation).
pub struct Endpoint {
    config: EndpointConfig,
    start: Instant,
    peers: Vec<Peer>,
    by_addr: HashMap<SocketAddr, usize>,
    send_edges: HashMap<u32, SendEdge>,
    recv_edges: HashMap<u32, RecvEdge>,
    events: VecDeque<Event>,
    control: VecDeque<(usize, Vec<u8>)>,
    strangers: u64,
    malformed: u64,
    closing: bool,
}

impl Endpoint {
    /// A new endpoint; `now` starts its clock.
    pub fn new(config: EndpointConfig, now: Instant) -> Self {
        Endpoint {
            config,
            start: now,
            peers: Vec::new(),
            by_addr: HashMap::new(),
            send_edges: HashMap::new(),
            recv_edges: HashMap::new(),
            events: VecDeque::new(),
            control: VecDeque::new(),
            strangers: 0,
            malformed: 0,
            closing: false,
        }
    }

    /// The configuration.
    pub fn config(&self) -> &EndpointConfig {
        &self.config
    }

    /// Declares a peer this node talks to; the handshake starts at the next poll.
    pub fn add_peer(&mut self, name: &str, addr: SocketAddr, now: Instant) {
        if let Some(i) = self.peer_index(name) {
            self.by_addr.remove(&self.peers[i].addr);
            self.peers[i].addr = addr;
            self.by_addr.insert(addr, i);
            return;
        }
        self.by_addr.insert(addr, self.peers.len());
        self.peers.push(Peer {
            name: name.to_string(),
            addr,
            remote_incarnation: 0,
            remote_epoch: 0,
            up: false,
            ever_up: false,
            gone: false,
            reply_hello: false,
            hello_due: now,
            last_heard: now,
            ping_due: now,
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

    /// The handshake value `peer` sent (its clock epoch), once known.
    pub fn peer_epoch(&self, peer: &str) -> Option<u64> {
        let p = &self.peers[self.peer_index(peer)?];
        (p.remote_incarnation != 0).then_some(p.remote_epoch)
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

    /// Packets from unknown senders, stale incarnations or with bad proofs, ignored.
    pub fn strangers(&self) -> u64 {
        self.strangers
    }

    /// Datagrams that did not decode.
    pub fn malformed(&self) -> u64 {
        self.malformed
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

    /// Queues a message on a sending edge; it goes out once the peer is up.
    pub fn send(&mut self, edge: u32, data: Vec<u8>) -> Result<u64, SendError> {
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

    /// Says goodbye to every peer (sent at the next polls).
    pub fn close(&mut self) {
        self.closing = true;
        for i in 0..self.peers.len() {
            let bye = Body::Bye.encode(self.config.incarnation);
            self.control.push_back((i, bye));
        }
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
        let packet = match wire::decode(datagram) {
            Ok(p) => p,
            Err(e) => {
                self.malformed += 1;
                tracing::debug!(%from, error = %e, "malformed datagram");
                return;
            }
        };
        if let Body::Hello {
            cluster,
            from: name,
            to,
            epoch,
            seen,
            reply,
            mac,
        } = &packet.body
        {
            self.handle_hello(
                now,
                from,
                packet.incarnation,
                cluster,
                name,
                to,
                *epoch,
                *seen,
                *reply,
                mac,
            );
            return;
        }
        let Some(&p) = self.by_addr.get(&from) else {
            self.strangers += 1;
            return;
        };
        if packet.incarnation != self.peers[p].remote_incarnation || packet.incarnation == 0 {
            self.strangers += 1;
            return;
        }
        let peer = &mut self.peers[p];
        peer.last_heard = now;
        if peer.gone {
            // It said goodbye: stragglers are ignored; a new handshake revives it.
            return;
        }
        peer.stats.packets_received += 1;
        peer.stats.wire_bytes_received += datagram.len() as u64;
        if !peer.up && peer.ever_up && !matches!(packet.body, Body::Bye) {
            peer.up = true;
            let ev = Event::PeerUp {
                peer: peer.name.clone(),
                epoch: peer.remote_epoch,
            };
            self.events.push_back(ev);
        }
        match packet.body {
            Body::Data {
                pn,
                edge,
                seq,
                len,
                chunk,
                payload,
            } => {
                recv::on_data(self, p, now, pn, edge, seq, len, chunk, payload);
            }
            Body::Ack { ranges } => send::on_ack(self, p, now, &ranges),
            Body::Credit { grants } => {
                for (edge, granted) in grants {
                    if let Some(e) = self.send_edges.get_mut(&edge)
                        && e.peer == p
                        && granted > e.granted
                    {
                        e.granted = granted;
                        self.events.push_back(Event::Credit { edge, granted });
                    }
                }
            }
            Body::Ping { t_us } => {
                let pong = Body::Pong { t_us }.encode(self.config.incarnation);
                self.control.push_back((p, pong));
            }
            Body::Pong { t_us } => {
                let rtt = Duration::from_micros(self.now_us(now).saturating_sub(t_us));
                self.peers[p].send.rtt_sample(rtt, &self.config);
                self.peers[p].stats.srtt_s = self.peers[p].send.srtt().as_secs_f64();
            }
            Body::Bye => {
                self.peers[p].gone = true;
                self.peers[p].up = false;
                self.events.push_back(Event::PeerLeft {
                    peer: self.peers[p].name.clone(),
                });
            }
            Body::Hello { .. } => unreachable!("handled above"),
        }
    }

    /// Runs timers due at `now`: loss detection, heartbeats, peer timeouts, handshakes.
    pub fn handle_timeout(&mut self, now: Instant) {
        for p in 0..self.peers.len() {
            send::detect_losses(self, p, now);
            let peer = &mut self.peers[p];
            if peer.up && now.saturating_duration_since(peer.last_heard) > self.config.peer_timeout
            {
                peer.up = false;
                tracing::warn!(peer = %peer.name, "peer silent for {:?}: lost", self.config.peer_timeout);
                self.events.push_back(Event::PeerLost {
                    peer: peer.name.clone(),
                });
            }
        }
    }

    /// Next datagram to send, if any may be sent at `now`.
    pub fn poll_transmit(&mut self, now: Instant) -> Option<(SocketAddr, Vec<u8>)> {
        if let Some((p, bytes)) = self.control.pop_front() {
            return Some(self.account(p, bytes));
        }
        if self.closing {
            return None;
        }
        for p in 0..self.peers.len() {
            let peer = &self.peers[p];
            if peer.reply_hello || (!peer.up && now >= peer.hello_due) {
                let reply = peer.reply_hello;
                let hello = self.hello(p, reply);
                let peer = &mut self.peers[p];
                peer.reply_hello = false;
                if !reply {
                    peer.hello_due = now + self.config.hello_interval;
                }
                return Some(self.account(p, hello));
            }
            if let Some(ack) = recv::poll_ack(self, p, now) {
                return Some(self.account(p, ack));
            }
            let peer = &mut self.peers[p];
            if peer.remote_incarnation != 0 && peer.ever_up && now >= peer.ping_due {
                peer.ping_due = now + self.config.heartbeat_interval;
                peer.recv.credit_dirty = true;
                let ping = Body::Ping {
                    t_us: self.now_us(now),
                }
                .encode(self.config.incarnation);
                return Some(self.account(p, ping));
            }
            if let Some(credit) = recv::poll_credit(self, p) {
                return Some(self.account(p, credit));
            }
        }
        // Data last, round robin over peers.
        let n = self.peers.len();
        for k in 0..n {
            let p = (self.data_cursor() + k) % n;
            if let Some(d) = send::poll_data(self, p, now) {
                return Some(self.account(p, d));
            }
        }
        None
    }

    fn data_cursor(&self) -> usize {
        // Rotate by packets sent so that peers share the socket fairly.
        self.peers
            .iter()
            .map(|p| p.stats.packets_sent as usize)
            .sum::<usize>()
    }

    fn account(&mut self, p: usize, bytes: Vec<u8>) -> (SocketAddr, Vec<u8>) {
        let peer = &mut self.peers[p];
        peer.stats.packets_sent += 1;
        peer.stats.wire_bytes_sent += bytes.len() as u64;
        (peer.addr, bytes)
    }

    /// When the endpoint next needs [`Endpoint::handle_timeout`] or [`Endpoint::poll_transmit`].
    pub fn poll_timeout(&self) -> Option<Instant> {
        let mut t: Option<Instant> = None;
        let mut at = |x: Instant| t = Some(t.map_or(x, |y| y.min(x)));
        for peer in &self.peers {
            if !peer.up {
                at(peer.hello_due);
            } else {
                at(peer.last_heard + self.config.peer_timeout);
            }
            if peer.ever_up && peer.remote_incarnation != 0 {
                at(peer.ping_due);
            }
            if let Some(x) = peer.recv.ack_due {
                at(x);
            }
            if let Some(x) = peer.send.next_timer(&self.config) {
                at(x);
            }
        }
        t
    }
}

#[cfg(test)]
mod tests;
