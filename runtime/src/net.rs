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
    pub(crate) epoch: u64,
    pub(crate) restarts: u64,
    pub(crate) lost_messages: u64,
    /// It said goodbye.
    pub(crate) left: bool,
}

impl PeerBoard {
    pub(crate) fn get(&self, peer: &str) -> PeerState {
        self.state
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .get(peer)
            .cloned()
            .unwrap_or_default()
    }

    fn update(&self, peer: &str, f: impl FnOnce(&mut PeerState)) {
        f(self
            .state
            .lock()
            .unwrap_or_else(|e| e.into_inner())
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
}

impl NodeNet {
    /// Binds the node's socket and starts its I/O thread (no peers yet).
    pub(crate) fn bind(
        node: &str,
        addr: SocketAddr,
        cluster: &str,
        secret: &str,
        epoch_unix_ns: u64,
        settings: &TransportSettings,
        seed: u64,
    ) -> std::io::Result<NodeNet> {
        let incarnation = (crate::clock::now_unix_ns()
            ^ ((std::process::id() as u64) << 40)
            ^ seed.rotate_left(17))
            | 1;
        let mut c = EndpointConfig::new(node, cluster, secret.as_bytes(), incarnation);
        c.epoch = epoch_unix_ns;
        c.max_packet_bytes = settings.max_packet_bytes;
        c.window_packets = settings.window_packets;
        c.pacing_bytes_per_s = settings.pacing_mbps.map(|m| m * 1e6 / 8.0);
        c.peer_timeout = Duration::from_secs_f64(settings.peer_timeout_ms / 1000.0);
        c.heartbeat_interval = Duration::from_secs_f64(settings.heartbeat_ms / 1000.0);
        let mut dc = DriverConfig::new(c, addr);
        dc.seed = seed;
        let driver = Driver::start(dc)?;
        let commander = driver.commander();
        Ok(NodeNet {
            node: node.to_string(),
            driver,
            commander,
            board: Arc::default(),
            senders: HashMap::new(),
            receivers: HashMap::new(),
            refused: Arc::default(),
            flush: Arc::default(),
            tasks: Vec::new(),
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
        });
        let waker = shared.clone();
        edge.set_waker(move || waker.notify.notify_one());
        let task = tokio::spawn(sender_proxy(
            id,
            edge,
            ty,
            shared.clone(),
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
        self.tasks.push(tokio::spawn(dispatch(
            self.node.clone(),
            events,
            senders,
            receivers,
            returns,
            self.board.clone(),
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

    /// Extra counters of a cut edge half.
    pub(crate) fn cut_counters(&self, id: u32) -> CutCounters {
        CutCounters {
            lost: self
                .senders
                .get(&id)
                .map_or(0, |(_, s)| s.lost.load(Ordering::SeqCst)),
            refused: self
                .refused
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .get(&id)
                .copied()
                .unwrap_or(0),
        }
    }

    /// Peer of a cut edge half.
    pub(crate) fn peer_of(&self, id: u32) -> Option<&str> {
        self.senders
            .get(&id)
            .map(|(p, _)| p.as_str())
            .or_else(|| self.receivers.get(&id).map(|(p, _)| p.as_str()))
    }

    /// Wakes the sender proxies (e.g. when the run starts draining).
    pub(crate) fn poke(&self) {
        for (_, s) in self.senders.values() {
            s.notify.notify_one();
        }
    }

    /// Stops the proxies and the driver (saying goodbye to peers).
    pub(crate) fn shutdown(&mut self) {
        for t in self.tasks.drain(..) {
            t.abort();
        }
        self.driver.close();
    }
}

async fn sender_proxy(
    id: u32,
    edge: Arc<Edge>,
    ty: MessageType,
    shared: Arc<SenderShared>,
    commander: Commander,
    control: Arc<RunControl>,
) {
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
            match ty.encode(d.message()) {
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
        shared.notify.notified().await;
    }
}

#[allow(clippy::too_many_arguments)]
async fn dispatch(
    node: String,
    mut events: tokio::sync::mpsc::Receiver<Event>,
    senders: HashMap<u32, (String, Arc<SenderShared>)>,
    receivers: HashMap<u32, (Arc<Edge>, MessageType)>,
    returns: HashMap<u32, Arc<AtomicU64>>,
    board: Arc<PeerBoard>,
    refused: Arc<Mutex<HashMap<u32, u64>>>,
    flush: Arc<Notify>,
) {
    let refuse = |id: u32, why: String| {
        tracing::error!(%node, edge = id, "incoming message refused: {why}");
        *refused
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .entry(id)
            .or_default() += 1;
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
            Event::PeerUp { peer, epoch } => {
                tracing::info!(%node, %peer, "peer up");
                for (p, s) in senders.values() {
                    if *p == peer {
                        s.peer_lost.store(false, Ordering::SeqCst);
                    }
                }
                board.update(&peer, |s| {
                    s.up = true;
                    s.left = false;
                    s.epoch = epoch;
                });
            }
            Event::PeerLeft { peer } => {
                tracing::info!(%node, %peer, "peer left");
                for (p, s) in senders.values() {
                    if *p == peer {
                        s.peer_lost.store(true, Ordering::SeqCst);
                        s.notify.notify_one();
                    }
                }
                board.update(&peer, |s| {
                    s.up = false;
                    s.left = true;
                });
            }
            Event::PeerLost { peer } => {
                tracing::warn!(%node, %peer, "peer lost");
                for (p, s) in senders.values() {
                    if *p == peer {
                        s.peer_lost.store(true, Ordering::SeqCst);
                        s.notify.notify_one();
                    }
                }
                board.update(&peer, |s| s.up = false);
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
        }
    }
}
