//! Cut edges: the proxies that carry an edge across nodes through the transport.
//!
//! On the producing node, a cut edge is an ordinary [`Edge`] whose consumer is a *sender
//! proxy* task: it takes messages while the edge has credit, encodes them with the port's
//! [`MessageType`] and hands them to the node's transport driver. It keeps each message's
//! [`Delivery`] (and so, under `block`, its permit) until the receiving node grants credit
//! back, i.e. until the remote consumer has finished it: the edge's capacity holds end to
//! end, messages queued here + on the wire + queued or handled there.
//!
//! On the consuming node, the *dispatcher* task decodes each arriving message and pushes it
//! into an ordinary [`Edge`] to the consumer; when the consumer finishes a message (or
//! `latest` drops one) a release hook returns one credit to the producer.
//!
//! Stages never know whether their edge is cut.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use tokio::sync::mpsc::UnboundedSender;

use cloudlight_transport::driver::DriverConfig;
use cloudlight_transport::{
    Command, Commander, Driver, DriverHandle, DriverStats, EdgeDirection, EndpointConfig, Event,
    LinkProfile,
};
use tokio::sync::Notify;
use tokio::task::JoinHandle;

use crate::control::RunControl;
use crate::edge::{Delivery, Edge, TryPushError};
use crate::message::MessageType;
use crate::metrics::{PeerLinkSnapshot, TransportSnapshot};
use crate::topology::TransportSettings;

/// What a node knows about its peers.
#[derive(Default)]
pub(crate) struct PeerBoard {
    state: Mutex<HashMap<String, PeerState>>,
    pub(crate) changed: Notify,
}

#[derive(Clone, Debug, Default)]
pub(crate) struct PeerState {
    pub(crate) up: bool,
    /// It was up, then went silent for the peer timeout (and has not been heard since).
    pub(crate) lost: bool,
    pub(crate) epoch: u64,
    pub(crate) restarts: u64,
    pub(crate) lost_messages: u64,
    /// It said goodbye.
    pub(crate) left: bool,
    /// It runs a different topology.
    pub(crate) mismatch: bool,
}

impl PeerBoard {
    pub(crate) fn get(&self, peer: &str) -> PeerState {
        crate::toolkit::lock(&self.state)
            .get(peer)
            .cloned()
            .unwrap_or_default()
    }

    fn update(&self, peer: &str, f: impl FnOnce(&mut PeerState)) {
        f(crate::toolkit::lock(&self.state)
            .entry(peer.to_string())
            .or_default());
        self.changed.notify_waiters();
    }
}

struct SenderShared {
    capacity: u64,
    granted: AtomicU64,
    generation: AtomicU64,
    peer_lost: AtomicBool,
    notify: Notify,
    /// Messages given up: lost with a restarted peer, or abandoned at shutdown.
    lost: AtomicU64,
    /// Messages over the transport's size limit, dropped (and counted on the edge).
    oversize: AtomicU64,
    /// Messages sent and not yet confirmed consumed (the proxy's `held`).
    held: AtomicU64,
}

struct Receiving {
    edge: Arc<Edge>,
    ty: MessageType,
    released: Arc<AtomicU64>,
}

/// Counters of one cut edge half, beyond the edge's own.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct CutCounters {
    pub(crate) lost: u64,
    pub(crate) refused: u64,
    pub(crate) oversize: u64,
}

/// What a node's transport is started with.
pub(crate) struct NetArgs<'a> {
    pub(crate) node: &'a str,
    pub(crate) addr: SocketAddr,
    pub(crate) cluster: &'a str,
    pub(crate) secret: &'a str,
    pub(crate) epoch_unix_ns: u64,
    pub(crate) settings: &'a TransportSettings,
    pub(crate) seed: u64,
    /// The plan's digest: peers with another one are refused.
    pub(crate) digest: [u8; cloudlight_transport::wire::DIGEST_BYTES],
    /// Where failures of the transport go (they fail the run).
    pub(crate) failures: UnboundedSender<String>,
}

/// One node's transport: its driver and the proxies of its cut edges.
pub(crate) struct NodeNet {
    pub(crate) node: String,
    driver: DriverHandle,
    commander: Commander,
    pub(crate) board: Arc<PeerBoard>,
    senders: HashMap<u32, (String, Arc<SenderShared>)>,
    receivers: HashMap<u32, (String, Receiving)>,
    refused: Arc<Mutex<HashMap<u32, u64>>>,
    flush: Arc<Notify>,
    tasks: Vec<JoinHandle<()>>,
    failures: UnboundedSender<String>,
    rejoin_timeout: Duration,
    max_message_bytes: usize,
    encoded: Arc<EncodeCache>,
}

/// A message that may be gone, and its encoding.
type Encoded = (std::sync::Weak<dyn std::any::Any + Send + Sync>, Arc<[u8]>);

/// Encodings of the messages a node's sender proxies are sending, shared between them: a
/// message fanned out to many cut edges (one per client) is serialized once, and its bytes
/// are one allocation that every peer's transport state shares. An entry lives while its
/// message does (entries of dropped messages are pruned as new ones come), so the cache
/// holds nothing the proxies and the transport do not hold already.
#[derive(Default)]
pub(crate) struct EncodeCache {
    entries: Mutex<HashMap<usize, Encoded>>,
    /// Encodings made, and encodings reused.
    made: AtomicU64,
    reused: AtomicU64,
}

impl EncodeCache {
    /// `msg`'s encoding by `ty`: made once per message, however many edges send it.
    pub(crate) fn encode(
        &self,
        ty: &MessageType,
        msg: &crate::message::AnyMessage,
    ) -> Result<Arc<[u8]>, crate::codec::CodecError> {
        let key = Arc::as_ptr(msg) as *const () as usize;
        {
            let entries = crate::toolkit::lock(&self.entries);
            // A live weak pointer to the same allocation is this very message (an address
            // is reused only after its message is gone).
            if let Some((weak, bytes)) = entries.get(&key)
                && weak.strong_count() > 0
                && std::ptr::addr_eq(weak.as_ptr(), Arc::as_ptr(msg))
            {
                self.reused.fetch_add(1, Ordering::Relaxed);
                return Ok(bytes.clone());
            }
        }
        let bytes: Arc<[u8]> = ty.encode(msg)?.into();
        self.made.fetch_add(1, Ordering::Relaxed);
        let mut entries = crate::toolkit::lock(&self.entries);
        if entries.len() >= 64 {
            entries.retain(|_, (w, _)| w.strong_count() > 0);
        }
        entries.insert(key, (Arc::downgrade(msg), bytes.clone()));
        Ok(bytes)
    }

    /// (encodings made, encodings reused).
    pub(crate) fn counts(&self) -> (u64, u64) {
        (
            self.made.load(Ordering::Relaxed),
            self.reused.load(Ordering::Relaxed),
        )
    }
}

impl NodeNet {
    /// Binds the node's socket and starts its I/O thread (no peers yet).
    pub(crate) fn bind(args: NetArgs<'_>) -> std::io::Result<NodeNet> {
        let settings = args.settings;
        let mut c = EndpointConfig::new(args.node, args.cluster, args.secret.as_bytes());
        c.epoch = args.epoch_unix_ns;
        c.topology_digest = args.digest;
        c.confidential = settings.encrypt;
        c.congestion_control = settings.congestion_control;
        c.max_packet_bytes = settings.max_packet_bytes;
        c.window_packets = settings.window_packets;
        c.pacing_bytes_per_s = settings.pacing_mbps.map(|m| m * 1e6 / 8.0);
        c.peer_timeout = Duration::from_secs_f64(settings.peer_timeout_ms / 1000.0);
        c.heartbeat_interval = Duration::from_secs_f64(settings.heartbeat_ms / 1000.0);
        c.stall_timeout = Duration::from_secs_f64(settings.stall_timeout_s);
        let max_message_bytes = c.max_message_bytes;
        let mut dc = DriverConfig::new(c, args.addr);
        dc.seed = args.seed;
        dc.batched_io = settings.batched_io;
        let driver = Driver::start(dc)?;
        let commander = driver.commander();
        Ok(NodeNet {
            node: args.node.to_string(),
            driver,
            commander,
            board: Arc::default(),
            senders: HashMap::new(),
            receivers: HashMap::new(),
            refused: Arc::default(),
            flush: Arc::default(),
            tasks: Vec::new(),
            failures: args.failures,
            rejoin_timeout: Duration::from_secs_f64(settings.rejoin_timeout_s),
            max_message_bytes,
            encoded: Arc::default(),
        })
    }

    /// The bound address.
    pub(crate) fn local_addr(&self) -> SocketAddr {
        self.driver.local_addr()
    }

    /// Declares a peer and the emulated profile of the link towards it.
    pub(crate) fn add_peer(&self, name: &str, addr: SocketAddr, link: LinkProfile) {
        self.send_now(Command::AddPeer {
            name: name.to_string(),
            addr,
            link,
        });
    }

    fn send_now(&self, cmd: Command) {
        // Setup commands are few and the queue holds thousands.
        if self.commander.try_command(cmd).is_err() {
            tracing::error!(node = %self.node, "transport command queue full or closed during setup");
        }
    }

    /// Carries `edge` (whose consumer is remote) to `peer`.
    pub(crate) fn add_sender(
        &mut self,
        id: u32,
        peer: &str,
        edge: Arc<Edge>,
        ty: MessageType,
        control: Arc<RunControl>,
    ) {
        let capacity = edge.settings().capacity as u64;
        self.send_now(Command::OpenEdge {
            edge: id,
            peer: peer.to_string(),
            direction: EdgeDirection::Send,
            capacity,
        });
        let shared = Arc::new(SenderShared {
            capacity,
            granted: AtomicU64::new(capacity),
            generation: AtomicU64::new(0),
            peer_lost: AtomicBool::new(false),
            notify: Notify::new(),
            lost: AtomicU64::new(0),
            oversize: AtomicU64::new(0),
            held: AtomicU64::new(0),
        });
        let waker = shared.clone();
        edge.set_waker(move || waker.notify.notify_one());
        let task = tokio::spawn(sender_proxy(
            SenderProxy {
                id,
                edge,
                ty,
                shared: shared.clone(),
                max_bytes: self.max_message_bytes,
                encoded: self.encoded.clone(),
            },
            self.commander.clone(),
            control,
        ));
        self.tasks.push(task);
        self.senders.insert(id, (peer.to_string(), shared));
    }

    /// Delivers messages arriving from `peer` on `id` into `edge` (whose consumer is local).
    pub(crate) fn add_receiver(&mut self, id: u32, peer: &str, edge: Arc<Edge>, ty: MessageType) {
        let capacity = edge.settings().capacity as u64;
        self.send_now(Command::OpenEdge {
            edge: id,
            peer: peer.to_string(),
            direction: EdgeDirection::Receive,
            capacity,
        });
        let released = Arc::new(AtomicU64::new(0));
        let (r, flush) = (released.clone(), self.flush.clone());
        edge.set_release_hook(move || {
            r.fetch_add(1, Ordering::SeqCst);
            flush.notify_one();
        });
        self.receivers
            .insert(id, (peer.to_string(), Receiving { edge, ty, released }));
    }

    /// Starts the event dispatcher and the credit flusher; call after every edge is added.
    pub(crate) fn start(&mut self) {
        let events = self.driver.take_events();
        let senders: HashMap<u32, (String, Arc<SenderShared>)> = self.senders.clone();
        let receivers: HashMap<u32, (Arc<Edge>, MessageType)> = self
            .receivers
            .iter()
            .map(|(&id, (_, r))| (id, (r.edge.clone(), r.ty)))
            .collect();
        let releases: Vec<(u32, Arc<AtomicU64>)> = self
            .receivers
            .iter()
            .map(|(&id, (_, r))| (id, r.released.clone()))
            .collect();
        let returns: HashMap<u32, Arc<AtomicU64>> = releases.iter().cloned().collect();
        let watch = Watch {
            node: self.node.clone(),
            board: self.board.clone(),
            failures: self.failures.clone(),
            driver_failure: self.driver.failure_slot(),
            rejoin_timeout: self.rejoin_timeout,
            upstream: self.receivers.values().map(|(p, _)| p.clone()).collect(),
        };
        self.tasks.push(tokio::spawn(dispatch(
            watch,
            events,
            senders,
            receivers,
            returns,
            self.refused.clone(),
            self.flush.clone(),
        )));
        let (commander, flush) = (self.commander.clone(), self.flush.clone());
        self.tasks.push(tokio::spawn(async move {
            loop {
                flush.notified().await;
                for (id, n) in &releases {
                    let n = n.swap(0, Ordering::SeqCst);
                    if n > 0
                        && commander
                            .command(Command::Release { edge: *id, n })
                            .await
                            .is_err()
                    {
                        return;
                    }
                }
            }
        }));
    }

    /// Whether a peer run by another process sends to this node and has not said goodbye:
    /// more messages may arrive (a peer that is merely silent may come back). Peers in
    /// `local` run in this process and finish with it.
    pub(crate) fn has_live_upstream(&self, local: &[String]) -> bool {
        self.receivers
            .values()
            .any(|(peer, _)| !local.contains(peer) && !self.board.get(peer).left)
    }

    /// Upstream peers (those that send to this node) that are lost now.
    pub(crate) fn lost_upstream(&self) -> Vec<String> {
        let mut v: Vec<String> = self
            .receivers
            .values()
            .map(|(p, _)| p.clone())
            .filter(|p| self.board.get(p).lost)
            .collect();
        v.sort();
        v.dedup();
        v
    }

    /// Peers this node needs (the other ends of its cut edges).
    pub(crate) fn needed_peers(&self) -> Vec<String> {
        let mut v: Vec<String> = self
            .senders
            .values()
            .map(|(p, _)| p.clone())
            .chain(self.receivers.values().map(|(p, _)| p.clone()))
            .collect();
        v.sort();
        v.dedup();
        v
    }

    /// Transport counters.
    pub(crate) fn stats(&self) -> DriverStats {
        self.driver.stats()
    }

    /// The node's transport counters, per peer with the link's state.
    pub(crate) fn snapshot(&self, stats: &DriverStats) -> TransportSnapshot {
        let peers = self
            .needed_peers()
            .into_iter()
            .map(|peer| {
                let b = self.board.get(&peer);
                let p = stats.peer(&peer);
                let state = if b.mismatch {
                    "mismatch"
                } else if b.up {
                    "up"
                } else if b.left {
                    "left"
                } else if b.lost {
                    "lost"
                } else {
                    "connecting"
                };
                PeerLinkSnapshot {
                    peer,
                    state: state.into(),
                    rtt_ms: p.srtt_s * 1000.0,
                    handshakes: p.handshakes,
                    restarts: p.restarts,
                    lost_messages: p.lost_messages,
                    retransmissions: p.retransmissions,
                    refused: p.refused,
                    replayed: p.replayed,
                    forged: p.forged,
                    moves: p.moves,
                    misaddressed: p.misaddressed,
                    mismatched: p.mismatched,
                }
            })
            .collect();
        let e = stats.endpoint;
        TransportSnapshot {
            node: self.node.clone(),
            strangers: e.strangers,
            malformed: stats.malformed,
            unknown_session: e.unknown_session,
            stale_handshakes: e.stale_handshakes,
            rate_limited: e.rate_limited,
            encodings: self.encoded.counts().0,
            encodings_reused: self.encoded.counts().1,
            datagrams_sent: stats.io.datagrams_sent,
            send_calls: stats.io.send_calls,
            peers,
        }
    }

    /// Extra counters of a cut edge half.
    pub(crate) fn cut_counters(&self, id: u32) -> CutCounters {
        CutCounters {
            lost: self
                .senders
                .get(&id)
                .map_or(0, |(_, s)| s.lost.load(Ordering::SeqCst)),
            refused: crate::toolkit::lock(&self.refused)
                .get(&id)
                .copied()
                .unwrap_or(0),
            oversize: self
                .senders
                .get(&id)
                .map_or(0, |(_, s)| s.oversize.load(Ordering::SeqCst)),
        }
    }

    /// Peer of a cut edge half.
    pub(crate) fn peer_of(&self, id: u32) -> Option<&str> {
        self.senders
            .get(&id)
            .map(|(p, _)| p.as_str())
            .or_else(|| self.receivers.get(&id).map(|(p, _)| p.as_str()))
    }

    /// Fault injection: makes the transport's I/O thread panic.
    pub(crate) fn inject_panic(&self) {
        let _ = self.commander.try_command(Command::Panic);
    }

    /// Wakes the sender proxies (e.g. when the run starts draining).
    pub(crate) fn poke(&self) {
        for (_, s) in self.senders.values() {
            s.notify.notify_one();
        }
    }

    /// Stops the proxies and the driver (saying goodbye to peers, and whether this node's
    /// run `failed`). Messages still unconfirmed (a failed run, a drain that timed out) are
    /// given up and counted as `lost`.
    pub(crate) fn shutdown(&mut self, failed: bool) {
        for t in self.tasks.drain(..) {
            t.abort();
        }
        for (peer, s) in self.senders.values() {
            let held = s.held.swap(0, Ordering::SeqCst);
            if held > 0 {
                s.lost.fetch_add(held, Ordering::SeqCst);
                tracing::warn!(node = %self.node, %peer, held, "run ended with messages unconfirmed; given up");
            }
        }
        self.driver.close_with(failed);
    }
}

/// What a sender proxy carries.
struct SenderProxy {
    id: u32,
    edge: Arc<Edge>,
    ty: MessageType,
    shared: Arc<SenderShared>,
    /// The transport's message size limit.
    max_bytes: usize,
    /// The node's shared encodings.
    encoded: Arc<EncodeCache>,
}

async fn sender_proxy(proxy: SenderProxy, commander: Commander, control: Arc<RunControl>) {
    let SenderProxy {
        id,
        edge,
        ty,
        shared,
        max_bytes,
        encoded,
    } = proxy;
    let mut held: std::collections::VecDeque<Delivery> = std::collections::VecDeque::new();
    let mut sent: u64 = 0;
    let mut finished: u64 = 0;
    let mut generation = shared.generation.load(Ordering::SeqCst);
    loop {
        let g = shared.generation.load(Ordering::SeqCst);
        if g != generation {
            // The peer restarted: what it held is gone, its credit starts afresh.
            shared.lost.fetch_add(held.len() as u64, Ordering::SeqCst);
            if !held.is_empty() {
                tracing::warn!(
                    edge = edge.name(),
                    lost = held.len(),
                    "peer restarted; messages in flight were lost"
                );
            }
            held.clear();
            sent = 0;
            finished = 0;
            generation = g;
        }
        let granted = shared.granted.load(Ordering::SeqCst);
        while finished < granted.saturating_sub(shared.capacity) && held.pop_front().is_some() {
            finished += 1;
        }
        if control.is_stopping() && shared.peer_lost.load(Ordering::SeqCst) && !held.is_empty() {
            tracing::warn!(
                edge = edge.name(),
                abandoned = held.len(),
                "peer gone while draining; giving up its messages"
            );
            shared.lost.fetch_add(held.len() as u64, Ordering::SeqCst);
            finished += held.len() as u64;
            held.clear();
        }
        let mut emptied = false;
        while sent < granted {
            let Some(d) = edge.pop() else {
                emptied = true;
                break;
            };
            match encoded.encode(&ty, d.message()) {
                Ok(bytes) if bytes.len() > max_bytes => {
                    // Dropping the delivery returns its credit; the drop is counted.
                    let n = shared.oversize.fetch_add(1, Ordering::SeqCst) + 1;
                    edge.counters().dropped.fetch_add(1, Ordering::Relaxed);
                    if n == 1 || n.is_multiple_of(100) {
                        tracing::error!(
                            edge = edge.name(),
                            bytes = bytes.len(),
                            max_bytes,
                            dropped = n,
                            "message too large for the transport: dropped"
                        );
                    }
                }
                Ok(bytes) => {
                    if commander
                        .command(Command::Send { edge: id, bytes })
                        .await
                        .is_err()
                    {
                        return;
                    }
                    sent += 1;
                    held.push_back(d);
                }
                Err(e) => tracing::error!(edge = edge.name(), "cannot encode message: {e}"),
            }
        }
        if emptied {
            edge.rearm();
        }
        shared.held.store(held.len() as u64, Ordering::SeqCst);
        shared.notify.notified().await;
    }
}

/// What the dispatcher needs to watch peers and report failures.
struct Watch {
    node: String,
    board: Arc<PeerBoard>,
    failures: UnboundedSender<String>,
    driver_failure: Arc<Mutex<Option<String>>>,
    rejoin_timeout: Duration,
    /// Peers that send to this node.
    upstream: Vec<String>,
}

impl Watch {
    fn fail(&self, why: String) {
        tracing::error!(node = %self.node, "{why}");
        let _ = self.failures.send(format!("node `{}`: {why}", self.node));
    }

    /// A lost peer that is not back within the rejoin timeout fails the run.
    fn expect_rejoin(&self, peer: String) {
        let (board, failures, node) =
            (self.board.clone(), self.failures.clone(), self.node.clone());
        let wait = self.rejoin_timeout;
        tokio::spawn(async move {
            tokio::time::sleep(wait).await;
            let s = board.get(&peer);
            if s.lost && !s.left {
                let why = format!(
                    "peer `{peer}` was lost and has not come back within {:.1} s",
                    wait.as_secs_f64()
                );
                tracing::error!(%node, "{why}");
                let _ = failures.send(format!("node `{node}`: {why}"));
            }
        });
    }
}

async fn dispatch(
    watch: Watch,
    mut events: cloudlight_transport::driver::EventReceiver,
    senders: HashMap<u32, (String, Arc<SenderShared>)>,
    receivers: HashMap<u32, (Arc<Edge>, MessageType)>,
    returns: HashMap<u32, Arc<AtomicU64>>,
    refused: Arc<Mutex<HashMap<u32, u64>>>,
    flush: Arc<Notify>,
) {
    let node = watch.node.clone();
    let refuse = |id: u32, why: String| {
        tracing::error!(%node, edge = id, "incoming message refused: {why}");
        *crate::toolkit::lock(&refused).entry(id).or_default() += 1;
        // Return its credit so that the producer is not stuck.
        if let Some(r) = returns.get(&id) {
            r.fetch_add(1, Ordering::SeqCst);
            flush.notify_one();
        }
    };
    while let Some(event) = events.recv().await {
        match event {
            Event::Message {
                edge: id, bytes, ..
            } => {
                let Some((edge, ty)) = receivers.get(&id) else {
                    tracing::error!(%node, edge = id, "message on an edge this node does not receive");
                    continue;
                };
                match ty.decode(&bytes) {
                    Ok(msg) => match edge.try_push(msg, bytes.len()) {
                        Ok(()) => {}
                        Err(TryPushError::Closed) => {}
                        Err(TryPushError::Full) => {
                            refuse(id, "edge full: the producer exceeded its credit".into())
                        }
                    },
                    Err(e) => refuse(id, format!("cannot decode: {e}")),
                }
            }
            Event::Credit { edge, granted } => {
                if let Some((_, s)) = senders.get(&edge) {
                    s.granted.fetch_max(granted, Ordering::SeqCst);
                    s.notify.notify_one();
                }
            }
            Event::Delivered { .. } => {}
            other => on_peer_event(&watch, &senders, other),
        }
    }
    // The driver never closes its events while the node runs: its thread died.
    let why = crate::toolkit::lock(&watch.driver_failure)
        .clone()
        .unwrap_or_else(|| "stopped".into());
    watch.fail(format!(
        "the transport thread failed ({why}); this node has no network"
    ));
}

/// Marks the senders towards `peer` lost (or not) and wakes them.
fn mark_senders(senders: &HashMap<u32, (String, Arc<SenderShared>)>, peer: &str, lost: bool) {
    for (p, s) in senders.values() {
        if p == peer {
            s.peer_lost.store(lost, Ordering::SeqCst);
            s.notify.notify_one();
        }
    }
}

fn on_peer_event(watch: &Watch, senders: &HashMap<u32, (String, Arc<SenderShared>)>, event: Event) {
    let (node, board) = (&watch.node, &watch.board);
    match event {
        Event::PeerUp { peer, epoch } => {
            tracing::info!(%node, %peer, "peer up");
            mark_senders(senders, &peer, false);
            board.update(&peer, |s| {
                s.up = true;
                s.lost = false;
                s.left = false;
                s.epoch = epoch;
            });
        }
        Event::PeerLeft { peer, failed } => {
            tracing::info!(%node, %peer, failed, "peer left");
            if failed && watch.upstream.contains(&peer) {
                // Its part of the pipeline stopped early: what this node got is not the run's
                // output, whatever the way its upstream died (a crash is `lost`, see above).
                watch.fail(format!(
                    "upstream peer `{peer}` stopped because its run failed (see its log and \
                     metrics.json): this node's input ended early"
                ));
            }
            mark_senders(senders, &peer, true);
            board.update(&peer, |s| {
                s.up = false;
                s.lost = false;
                s.left = true;
            });
        }
        Event::PeerLost { peer } => {
            tracing::warn!(%node, %peer, "peer lost");
            mark_senders(senders, &peer, true);
            board.update(&peer, |s| {
                s.up = false;
                s.lost = true;
            });
            watch.expect_rejoin(peer);
        }
        Event::PeerRestarted {
            peer,
            lost_messages,
        } => {
            tracing::warn!(%node, %peer, lost_messages, "peer restarted");
            for (p, s) in senders.values() {
                if *p == peer {
                    s.granted.store(s.capacity, Ordering::SeqCst);
                    s.generation.fetch_add(1, Ordering::SeqCst);
                    s.notify.notify_one();
                }
            }
            board.update(&peer, |s| {
                s.up = false;
                s.restarts += 1;
                s.lost_messages += lost_messages;
            });
        }
        Event::TopologyMismatch { peer } => {
            board.update(&peer, |s| s.mismatch = true);
            watch.fail(format!(
                "peer `{peer}` runs a different topology (nodes, stages, edges, ports or \
                 policies differ): start every node from the same file"
            ));
        }
        Event::Stalled { peer, waited_ms } => watch.fail(format!(
            "the link to peer `{peer}` stalled: no data acknowledged for {:.1} s while it \
             answers heartbeats",
            waited_ms as f64 / 1000.0
        )),
        Event::Message { .. } | Event::Credit { .. } | Event::Delivered { .. } => {}
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::message::{AnyMessage, Stamped};

    fn message(seq: u64) -> AnyMessage {
        Arc::new(Stamped {
            scene_time_s: 0.0,
            produced_unix_ns: 0,
            seq,
            body: vec![seq as u8; 1000],
        })
    }

    #[test]
    fn a_message_fanned_out_to_many_edges_is_serialized_once() {
        let cache = EncodeCache::default();
        let ty = MessageType::of::<Vec<u8>>();
        let m = message(1);
        let first = cache.encode(&ty, &m).unwrap();
        for _ in 0..9 {
            let again = cache.encode(&ty, &m.clone()).unwrap();
            assert!(Arc::ptr_eq(&first, &again), "one allocation shared");
        }
        assert_eq!(cache.counts(), (1, 9));
        assert_eq!(&first[..], &ty.encode(&m).unwrap()[..]);
        // An equal message is another message.
        let twin = message(1);
        assert!(!Arc::ptr_eq(&first, &cache.encode(&ty, &twin).unwrap()));
        // Messages that are gone leave nothing behind, and a new message (perhaps at a
        // freed address) gets its own bytes.
        drop((m, twin));
        for seq in 2..300 {
            let m = message(seq);
            let bytes = cache.encode(&ty, &m).unwrap();
            assert_eq!(&bytes[..], &ty.encode(&m).unwrap()[..]);
        }
        assert_eq!(cache.counts().0, 2 + 298);
        assert!(crate::toolkit::lock(&cache.entries).len() <= 64);
    }
}
