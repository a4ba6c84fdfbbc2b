//! The I/O driver: one thread per node socket runs the [`Endpoint`].
//!
//! The thread owns a non-blocking UDP socket (4 MiB buffers, registered with mio). It never
//! sleeps a fixed time: it blocks in `mio::Poll` until the socket is readable (or, after a
//! full send buffer, writable), a command arrives (a `mio::Waker`), or the endpoint's or
//! emulators' next timer. Each wake-up takes every queued command, drains the socket in
//! batches, and hands the events over in one go.
//!
//! Two paths move datagrams. By default ([`DriverConfig::batched_io`]) the driver does its own
//! batched I/O (see `udp.rs`): packets are sealed in place into one buffer and leave with UDP
//! GSO, several datagrams per `sendmsg`, and arrive through `recvmmsg` with GRO. With
//! `batched_io` off, laminar moves every datagram: each transport packet is handed to
//! laminar's `ConnectionManager` (driven by `manual_poll`) as an *unreliable* packet no larger
//! than one datagram, so laminar never fragments, never holds packets in flight and never drops
//! a connection for having too many. Both paths frame datagrams with laminar's header, so
//! nodes on different paths talk to each other; reliability is always the endpoint's.
//!
//! The tokio side talks to the thread through a bounded command channel and receives
//! events through a bounded tokio channel. `close` says goodbye to peers and joins the thread.

use std::collections::{HashMap, VecDeque};
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, Sender, TryRecvError, TrySendError};
use laminar::{
    Config as LaminarConfig, ConnectionManager, DatagramSocket, Packet, SocketEvent,
    VirtualConnection,
};
use mio::{Events, Interest, Poll, Token, Waker};

use crate::emulator::{EmulatorStats, LinkEmulator, LinkProfile};
use crate::endpoint::{
    EdgeDirection, EdgeWireStats, Endpoint, EndpointConfig, Event, PeerStats, SendError,
};
use crate::udp::{Inbox, Outbox, laminar_unreliable_header};

const SOCKET: Token = Token(0);
const WAKER: Token = Token(1);
/// Commands waiting for the I/O thread, at most.
pub const COMMAND_CAPACITY: usize = 4096;
/// Events waiting for the tokio side, at most (in batches of at most [`EVENT_BATCH`]).
pub const EVENT_CAPACITY: usize = 4096;
/// Most events handed over at once.
pub const EVENT_BATCH: usize = 256;

/// The tokio side's receiver of a driver's events. The I/O thread hands them over in
/// batches, one per wake-up (one channel operation and one task wake-up for many events);
/// this takes them one at a time.
pub struct EventReceiver {
    rx: tokio::sync::mpsc::Receiver<Vec<Event>>,
    batch: VecDeque<Event>,
}

/// Why [`EventReceiver::try_recv`] returned nothing.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TryRecvEventError {
    /// Nothing waits now.
    Empty,
    /// The driver has stopped.
    Disconnected,
}

impl EventReceiver {
    /// The next event; `None` once the driver has stopped. Cancel-safe.
    pub async fn recv(&mut self) -> Option<Event> {
        if let Some(e) = self.batch.pop_front() {
            return Some(e);
        }
        let batch = self.rx.recv().await?;
        self.batch.extend(batch);
        self.batch.pop_front()
    }

    /// The next event if one is waiting.
    pub fn try_recv(&mut self) -> Result<Event, TryRecvEventError> {
        if let Some(e) = self.batch.pop_front() {
            return Ok(e);
        }
        match self.rx.try_recv() {
            Ok(batch) => {
                self.batch.extend(batch);
                self.batch.pop_front().ok_or(TryRecvEventError::Empty)
            }
            Err(tokio::sync::mpsc::error::TryRecvError::Empty) => Err(TryRecvEventError::Empty),
            Err(tokio::sync::mpsc::error::TryRecvError::Disconnected) => {
                Err(TryRecvEventError::Disconnected)
            }
        }
    }

    fn closed() -> Self {
        let (_, rx) = tokio::sync::mpsc::channel(1);
        EventReceiver {
            rx,
            batch: VecDeque::new(),
        }
    }
}

/// What a driver is started with.
#[derive(Clone, Debug)]
pub struct DriverConfig {
    /// The protocol settings.
    pub endpoint: EndpointConfig,
    /// Address to bind (port 0 picks one; see [`DriverHandle::local_addr`]).
    pub bind: SocketAddr,
    /// Peers: name and address.
    pub peers: Vec<(String, SocketAddr)>,
    /// Emulated link profile of the direction from this node to a peer, by peer name.
    pub links: HashMap<String, LinkProfile>,
    /// Seed of the emulators.
    pub seed: u64,
    /// Socket receive and send buffer size, bytes.
    pub socket_buffer_bytes: usize,
    /// Batched I/O (GSO/GRO, packets sealed in place) instead of laminar's one datagram per
    /// call; see the module documentation.
    pub batched_io: bool,
}

impl DriverConfig {
    /// A driver for `endpoint` bound to `bind`, without peers or emulated links.
    pub fn new(endpoint: EndpointConfig, bind: SocketAddr) -> Self {
        DriverConfig {
            endpoint,
            bind,
            peers: Vec::new(),
            links: HashMap::new(),
            seed: 0,
            socket_buffer_bytes: 4 << 20,
            batched_io: true,
        }
    }
}

/// Requests from the tokio side.
#[derive(Debug)]
pub enum Command {
    /// Open an edge (see [`Endpoint::open_edge`]).
    OpenEdge {
        /// Edge id.
        edge: u32,
        /// Peer name.
        peer: String,
        /// Direction.
        direction: EdgeDirection,
        /// End-to-end capacity.
        capacity: u64,
    },
    /// Declare (or move) a peer, with the emulated profile of the link towards it.
    AddPeer {
        /// Peer name.
        name: String,
        /// Its address.
        addr: SocketAddr,
        /// Emulated profile of the direction towards it (transparent: none).
        link: LinkProfile,
    },
    /// Send an encoded message; held by the driver until the edge has credit.
    Send {
        /// Edge id.
        edge: u32,
        /// The bytes (shared: a message fanned out to many peers is one allocation).
        bytes: Arc<[u8]>,
    },
    /// The local consumer finished `n` messages of a receiving edge.
    Release {
        /// Edge id.
        edge: u32,
        /// Count.
        n: u64,
    },
    /// Say goodbye (saying whether this node's run failed) and stop the thread.
    Close {
        /// The run failed: peers downstream learn that their input ended early.
        failed: bool,
    },
    /// Publish the counters now (see [`DriverHandle::fresh_stats`]).
    Publish,
    /// Stop the thread at once, without goodbyes: peers see a crash (fault injection).
    Abort,
    /// Panic in the I/O thread (fault injection: how a node handles losing its network).
    Panic,
}

/// A snapshot of the driver's counters.
#[derive(Clone, Debug, Default)]
pub struct DriverStats {
    /// Per peer.
    pub peers: Vec<(String, PeerStats)>,
    /// Per edge.
    pub edges: HashMap<u32, EdgeWireStats>,
    /// Handshake packets from strangers or without proof of the secret.
    pub strangers: u64,
    /// Datagrams that did not decode (laminar's framing or ours).
    pub malformed: u64,
    /// Per emulated link (by peer name).
    pub emulators: Vec<(String, EmulatorStats)>,
    /// Messages refused by the endpoint (too large).
    pub refused_sends: u64,
    /// Counters of packets that belong to no peer.
    pub endpoint: crate::endpoint::EndpointStats,
    /// System calls and datagrams of the socket.
    pub io: IoStats,
    /// How many times the thread published these counters.
    pub generation: u64,
    /// Each peer link's congestion controller.
    pub congestion: Vec<(String, crate::endpoint::cc::CongestionStats)>,
}

/// What the socket did: how many datagrams each system call moved.
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct IoStats {
    /// Send calls (`sendmsg` with GSO, or one per datagram on laminar's path).
    pub send_calls: u64,
    /// Datagrams the kernel took.
    pub datagrams_sent: u64,
    /// Receive calls that returned data.
    pub recv_calls: u64,
    /// Datagrams received.
    pub datagrams_received: u64,
    /// Datagrams dropped by a send error other than a full buffer (as a loss on the way).
    pub send_errors: u64,
    /// Times the socket's send buffer was full (the driver then waits until it drains).
    pub send_blocked: u64,
}

impl DriverStats {
    /// Counters of the link to `peer` (all zero if it is not declared).
    pub fn peer(&self, peer: &str) -> PeerStats {
        self.peers
            .iter()
            .find(|(n, _)| n == peer)
            .map(|(_, p)| *p)
            .unwrap_or_default()
    }
}

/// The driver is gone (closed or its thread failed).
#[derive(Debug, Clone, thiserror::Error)]
#[error("the transport driver has stopped")]
pub struct DriverClosed;

/// A cloneable sender of commands to a driver's I/O thread.
#[derive(Clone)]
pub struct Commander {
    commands: Sender<Command>,
    waker: Arc<Waker>,
    /// True while the I/O thread is (about to be) blocked in `poll`: only then does a new
    /// command need a wake-up system call.
    sleeping: Arc<AtomicBool>,
}

impl Commander {
    /// Queues a command, waiting (asynchronously) while the bounded queue is full.
    pub async fn command(&self, mut cmd: Command) -> Result<(), DriverClosed> {
        loop {
            match self.commands.try_send(cmd) {
                Ok(()) => {
                    self.wake();
                    return Ok(());
                }
                Err(TrySendError::Full(c)) => {
                    cmd = c;
                    tokio::time::sleep(Duration::from_micros(100)).await;
                }
                Err(TrySendError::Disconnected(_)) => return Err(DriverClosed),
            }
        }
    }

    /// Queues a command from synchronous code; fails when the queue is full or closed.
    pub fn try_command(&self, cmd: Command) -> Result<(), DriverClosed> {
        self.commands.try_send(cmd).map_err(|_| DriverClosed)?;
        self.wake();
        Ok(())
    }

    fn wake(&self) {
        if self.sleeping.swap(false, Ordering::SeqCst) {
            let _ = self.waker.wake();
        }
    }
}

/// The tokio side of a running driver.
pub struct DriverHandle {
    commander: Commander,
    events: EventReceiver,
    stats: Arc<Mutex<DriverStats>>,
    failure: Arc<Mutex<Option<String>>>,
    local_addr: SocketAddr,
    thread: Option<JoinHandle<()>>,
}

/// Starts I/O threads.
pub struct Driver;

/// The socket laminar drives. It hands laminar only datagrams that carry laminar's header of
/// an *unreliable, unordered, unfragmented* packet of its protocol version — the only kind
/// this transport sends — so no datagram from anyone makes laminar buffer, reorder or
/// acknowledge anything; everything else is counted and dropped here.
#[derive(Debug)]
struct MioSocket {
    socket: mio::net::UdpSocket,
    filtered: Arc<AtomicU64>,
}

impl DatagramSocket for MioSocket {
    fn send_packet(&mut self, addr: &SocketAddr, payload: &[u8]) -> std::io::Result<usize> {
        self.socket.send_to(payload, *addr)
    }
    fn receive_packet<'a>(
        &mut self,
        buffer: &'a mut [u8],
    ) -> std::io::Result<(&'a [u8], SocketAddr)> {
        let header = laminar_unreliable_header();
        loop {
            let (n, from) = self.socket.recv_from(buffer)?;
            if n >= header.len() && buffer[..header.len()] == header {
                return Ok((&buffer[..n], from));
            }
            self.filtered.fetch_add(1, Ordering::Relaxed);
        }
    }
    fn local_addr(&self) -> std::io::Result<SocketAddr> {
        self.socket.local_addr()
    }
    fn is_blocking_mode(&self) -> bool {
        false
    }
}

fn bind(config: &DriverConfig) -> std::io::Result<std::net::UdpSocket> {
    use socket2::{Domain, Protocol, Socket, Type};
    let s = Socket::new(
        Domain::for_address(config.bind),
        Type::DGRAM,
        Some(Protocol::UDP),
    )?;
    // Best effort: the kernel caps these at its own maximum.
    let _ = s.set_recv_buffer_size(config.socket_buffer_bytes);
    let _ = s.set_send_buffer_size(config.socket_buffer_bytes);
    s.bind(&config.bind.into())?;
    s.set_nonblocking(true)?;
    Ok(s.into())
}

impl Driver {
    /// Binds the socket and starts the I/O thread. Must be called inside a tokio runtime
    /// only for the returned handle's async methods; the thread itself is plain.
    pub fn start(config: DriverConfig) -> std::io::Result<DriverHandle> {
        let std_socket = bind(&config)?;
        let local_addr = std_socket.local_addr()?;
        let poll = Poll::new()?;
        let mut socket = mio::net::UdpSocket::from_std(std_socket);
        poll.registry()
            .register(&mut socket, SOCKET, Interest::READABLE)?;
        let waker = Arc::new(Waker::new(poll.registry(), WAKER)?);
        let sleeping = Arc::new(AtomicBool::new(false));
        let (commands, command_rx) = crossbeam_channel::bounded(COMMAND_CAPACITY);
        let (event_tx, events) = tokio::sync::mpsc::channel(EVENT_CAPACITY / EVENT_BATCH);
        let events = EventReceiver {
            rx: events,
            batch: VecDeque::new(),
        };
        let stats = Arc::new(Mutex::new(DriverStats::default()));
        let filtered = Arc::new(AtomicU64::new(0));
        let net = if config.batched_io {
            let state = quinn_udp::UdpSocketState::new((&socket).into())?;
            Net::Batched(Box::new(Batched {
                socket,
                state,
                outbox: Outbox::default(),
                inbox: Inbox::default(),
                writable_wanted: false,
                unread: false,
            }))
        } else {
            let laminar_config = LaminarConfig {
                receive_buffer_max_size: config.endpoint.max_packet_bytes + 64,
                // Laminar keeps a little state per address it hears from or sends to;
                // strangers' expires quickly (peers are heard every heartbeat; laminar's own
                // reliability, which this transport never uses, is all it would forget).
                idle_connection_timeout: (config.endpoint.peer_timeout * 2)
                    .max(Duration::from_secs(5)),
                max_unestablished_connections: 32,
                heartbeat_interval: None,
                ..LaminarConfig::default()
            };
            Net::Laminar(Box::new(ConnectionManager::new(
                MioSocket {
                    socket,
                    filtered: filtered.clone(),
                },
                laminar_config,
            )))
        };
        let thread_stats = stats.clone();
        let thread_sleeping = sleeping.clone();
        let name = format!("transport-{}", config.endpoint.node);
        let failure: Arc<Mutex<Option<String>>> = Arc::default();
        let thread_failure = failure.clone();
        // Held until the failure is written: the event channel closes only after that, so a
        // receiver that sees it closed can read why.
        let keep_open = event_tx.clone();
        let thread = std::thread::Builder::new().name(name).spawn(move || {
            let _keep_open = keep_open;
            let run = std::panic::catch_unwind(std::panic::AssertUnwindSafe(move || {
                let shared = IoShared {
                    stats: thread_stats,
                    sleeping: thread_sleeping,
                    filtered,
                };
                let mut io = Io::new(config, net, poll, (command_rx, event_tx), shared);
                io.run()
            }));
            let why = match run {
                Ok(Ok(())) => return,
                Ok(Err(e)) => format!("I/O error: {e}"),
                Err(panic) => format!("panicked: {}", panic_text(&*panic)),
            };
            tracing::error!("transport thread {why}");
            *thread_failure.lock().unwrap_or_else(|e| e.into_inner()) = Some(why);
        })?;
        Ok(DriverHandle {
            commander: Commander {
                commands,
                waker,
                sleeping,
            },
            events,
            stats,
            failure,
            local_addr,
            thread: Some(thread),
        })
    }
}

impl DriverHandle {
    /// The bound address.
    pub fn local_addr(&self) -> SocketAddr {
        self.local_addr
    }

    /// A cloneable command sender.
    pub fn commander(&self) -> Commander {
        self.commander.clone()
    }

    /// Queues a command, waiting (asynchronously) while the bounded queue is full.
    pub async fn command(&self, cmd: Command) -> Result<(), DriverClosed> {
        self.commander.command(cmd).await
    }

    /// Queues a command from synchronous code; fails when the queue is full or closed.
    pub fn try_command(&self, cmd: Command) -> Result<(), DriverClosed> {
        self.commander.try_command(cmd)
    }

    /// The next event; `None` once the driver has stopped.
    pub async fn next_event(&mut self) -> Option<Event> {
        self.events.recv().await
    }

    /// Splits off the event receiver (for a task that dispatches events).
    pub fn take_events(&mut self) -> EventReceiver {
        std::mem::replace(&mut self.events, EventReceiver::closed())
    }

    /// The latest counters (refreshed by the thread every few milliseconds).
    pub fn stats(&self) -> DriverStats {
        self.stats.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }

    /// Counters published after this call (the thread publishes every 20 ms while busy;
    /// this asks for a snapshot now). Falls back to the latest after a second.
    pub async fn fresh_stats(&self) -> DriverStats {
        let generation = self.stats().generation;
        if self.command(Command::Publish).await.is_err() {
            return self.stats();
        }
        let deadline = Instant::now() + Duration::from_secs(1);
        loop {
            let s = self.stats();
            if s.generation > generation || Instant::now() > deadline {
                return s;
            }
            tokio::time::sleep(Duration::from_millis(1)).await;
        }
    }

    /// Why the I/O thread stopped by itself (an I/O error or a panic), if it did.
    pub fn failure(&self) -> Option<String> {
        self.failure
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }

    /// A shareable view of [`DriverHandle::failure`].
    pub fn failure_slot(&self) -> Arc<Mutex<Option<String>>> {
        self.failure.clone()
    }

    /// Stops the thread without saying goodbye (peers see a crash) and waits for it.
    pub fn abort(&mut self) {
        let _ = self.try_command(Command::Abort);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }

    /// Says goodbye to peers, stops the thread and waits for it.
    pub fn close(&mut self) {
        self.close_with(false);
    }

    /// Says goodbye to peers, telling them whether this node's run `failed`, stops the
    /// thread and waits for it.
    pub fn close_with(&mut self, failed: bool) {
        let _ = self.try_command(Command::Close { failed });
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for DriverHandle {
    fn drop(&mut self) {
        self.close();
    }
}

/// What the I/O thread shares with the handle.
struct IoShared {
    stats: Arc<Mutex<DriverStats>>,
    sleeping: Arc<AtomicBool>,
    filtered: Arc<AtomicU64>,
}

/// How datagrams move (see the module documentation).
enum Net {
    Laminar(Box<ConnectionManager<MioSocket, VirtualConnection>>),
    Batched(Box<Batched>),
}

/// The batched path's socket and buffers.
struct Batched {
    socket: mio::net::UdpSocket,
    state: quinn_udp::UdpSocketState,
    outbox: Outbox,
    inbox: Inbox,
    /// The send buffer was full: registered for writability, nothing new is made until the
    /// outbox drains.
    writable_wanted: bool,
    /// The socket may hold more than one wake-up read (mio is edge-triggered).
    unread: bool,
}

/// Receive calls per wake-up at most, so that sending and timers interleave with a flood.
const RECV_CALLS_PER_WAKE: usize = 16;
/// Packets of one read between acknowledgements sent in its course (one GRO train).
const ACK_EVERY_IN_READ: u32 = 64;
/// Datagrams queued before the outbox is flushed (GSO takes at most 64 per call).
const OUTBOX_FLUSH_AT: usize = 64;

struct Io {
    seed: u64,
    sleeping: Arc<AtomicBool>,
    endpoint: Endpoint,
    net: Net,
    io_stats: IoStats,
    poll: Poll,
    commands: Receiver<Command>,
    events: tokio::sync::mpsc::Sender<Vec<Event>>,
    stats: Arc<Mutex<DriverStats>>,
    emulators: crate::FastMap<SocketAddr, (String, LinkEmulator)>,
    backlog: crate::FastMap<u32, VecDeque<Arc<[u8]>>>,
    pending_events: VecDeque<Event>,
    refused_sends: u64,
    filtered: Arc<AtomicU64>,
    closing: Option<Instant>,
    aborted: bool,
}

fn panic_text(panic: &(dyn std::any::Any + Send)) -> String {
    panic
        .downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| panic.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "(no message)".into())
}

/// Sends the datagram begun at `start` of the outbox to `to`: through its emulated link if it
/// has one (decided in place when the link only loses), else straight out.
fn route(
    outbox: &mut Outbox,
    emulators: &mut crate::FastMap<SocketAddr, (String, LinkEmulator)>,
    now: Instant,
    to: SocketAddr,
    start: usize,
) {
    match emulators.get_mut(&to) {
        Some((_, em)) => match em.pass_now() {
            Some(true) => outbox.commit(to, start),
            Some(false) => outbox.abort(start),
            None => em.send(now, outbox.take(start)),
        },
        None => outbox.commit(to, start),
    }
}

/// A stable hash of a peer name, to give each emulated link its own seed.
fn hash_name(name: &str) -> u64 {
    name.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| {
        (h ^ b as u64).wrapping_mul(0x100_0000_01b3)
    })
}

impl Io {
    fn new(
        config: DriverConfig,
        net: Net,
        poll: Poll,
        (commands, events): (Receiver<Command>, tokio::sync::mpsc::Sender<Vec<Event>>),
        shared: IoShared,
    ) -> Self {
        let IoShared {
            stats,
            sleeping,
            filtered,
        } = shared;
        let now = Instant::now();
        let endpoint = Endpoint::new(config.endpoint, now);
        let emulators = crate::FastMap::default();
        let mut io = Io {
            seed: config.seed,
            sleeping,
            endpoint,
            net,
            io_stats: IoStats::default(),
            poll,
            commands,
            events,
            stats,
            emulators,
            backlog: Default::default(),
            pending_events: VecDeque::new(),
            refused_sends: 0,
            filtered,
            closing: None,
            aborted: false,
        };
        for (name, addr) in config.peers {
            let link = config.links.get(&name).copied().unwrap_or_default();
            io.apply(Command::AddPeer { name, addr, link }, now);
        }
        io
    }

    fn apply(&mut self, cmd: Command, now: Instant) {
        match cmd {
            Command::OpenEdge {
                edge,
                peer,
                direction,
                capacity,
            } => {
                if let Err(e) = self.endpoint.open_edge(edge, &peer, direction, capacity) {
                    tracing::error!(edge, %peer, "cannot open edge: {e}");
                }
            }
            Command::AddPeer { name, addr, link } => {
                self.endpoint.add_peer(&name, addr, now);
                self.emulators.retain(|_, (n, _)| *n != name);
                if !link.is_transparent() {
                    let seed = self.seed ^ hash_name(&name);
                    self.emulators
                        .insert(addr, (name, LinkEmulator::new(link, seed)));
                }
            }
            Command::Send { edge, bytes } => self.backlog.entry(edge).or_default().push_back(bytes),
            Command::Release { edge, n } => self.endpoint.release(edge, n),
            Command::Close { failed } => {
                self.endpoint.close(failed);
                self.closing = Some(now);
            }
            Command::Publish => self.publish(),
            Command::Abort => self.aborted = true,
            Command::Panic => panic!("fault injected by Command::Panic"),
        }
    }

    fn flush_backlog(&mut self) {
        for (&edge, queue) in self.backlog.iter_mut() {
            while let Some(bytes) = queue.pop_front() {
                match self.endpoint.send(edge, bytes) {
                    Ok(_) => {}
                    Err(SendError::NoCredit(_)) => {
                        // Only possible right after a peer restart reset the credit; the
                        // message waits for the next grant.
                        break;
                    }
                    Err(e) => {
                        self.refused_sends += 1;
                        tracing::error!(edge, "message refused: {e}");
                    }
                }
            }
        }
    }

    fn publish(&self) {
        let mut s = self.stats.lock().unwrap_or_else(|e| e.into_inner());
        s.peers = self
            .endpoint
            .peer_names()
            .map(|n| {
                (
                    n.to_string(),
                    self.endpoint.peer_stats(n).unwrap_or_default(),
                )
            })
            .collect();
        s.edges = self
            .endpoint
            .edge_ids()
            .filter_map(|e| Some((e, self.endpoint.edge_stats(e)?)))
            .collect();
        s.endpoint = self.endpoint.stats();
        s.strangers = self.endpoint.strangers();
        s.malformed = self.endpoint.malformed() + self.filtered.load(Ordering::Relaxed);
        s.emulators = self
            .emulators
            .values()
            .map(|(n, e)| (n.clone(), e.stats()))
            .collect();
        s.refused_sends = self.refused_sends;
        s.io = self.io_stats;
        s.congestion = self
            .endpoint
            .peer_names()
            .filter_map(|n| Some((n.to_string(), self.endpoint.congestion(n)?)))
            .collect();
        s.generation += 1;
    }

    /// Feeds what the socket holds to the endpoint.
    fn receive(&mut self, now: Instant) -> std::io::Result<()> {
        let Io {
            net,
            endpoint,
            io_stats,
            filtered,
            emulators,
            ..
        } = self;
        match net {
            Net::Laminar(manager) => {
                manager.manual_poll(now);
                while let Ok(ev) = manager.event_receiver().try_recv() {
                    if let SocketEvent::Packet(p) = ev {
                        io_stats.datagrams_received += 1;
                        endpoint.handle_datagram(now, p.addr(), p.payload());
                    }
                }
            }
            Net::Batched(b) => {
                let mut dropped = 0;
                b.unread = true;
                let Batched {
                    socket,
                    state,
                    outbox,
                    inbox,
                    ..
                } = &mut **b;
                for _ in 0..RECV_CALLS_PER_WAKE {
                    match inbox.recv(state, socket, &mut dropped, |from, d| {
                        endpoint.handle_datagram(now, from, d);
                        // Acknowledge as the read goes, not once at its end.
                        loop {
                            let (start, buf) = outbox.begin();
                            match endpoint.poll_ack_into(now, ACK_EVERY_IN_READ, buf) {
                                None => {
                                    outbox.abort(start);
                                    break;
                                }
                                Some(to) => route(outbox, emulators, now, to, start),
                            }
                        }
                    }) {
                        Ok(n) => {
                            io_stats.recv_calls += 1;
                            io_stats.datagrams_received += n as u64;
                        }
                        Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                            b.unread = false;
                            break;
                        }
                        Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                        // An ICMP error of an earlier send, or a peer gone: nothing to read.
                        Err(e) if e.kind() == std::io::ErrorKind::ConnectionRefused => {}
                        Err(e) => return Err(e),
                    }
                }
                filtered.fetch_add(dropped, Ordering::Relaxed);
            }
        }
        Ok(())
    }

    /// Sends the outbox; on a full socket buffer, waits for writability.
    fn flush(&mut self) -> std::io::Result<()> {
        let Net::Batched(b) = &mut self.net else {
            return Ok(());
        };
        let (done, result) = b.outbox.flush(b.state.max_gso_segments(), |t| {
            b.state.try_send((&b.socket).into(), t)
        });
        self.io_stats.send_calls += done.calls;
        self.io_stats.datagrams_sent += done.datagrams;
        self.io_stats.send_errors += done.errors;
        let blocked = result.is_err();
        if blocked {
            self.io_stats.send_blocked += 1;
        }
        if blocked != b.writable_wanted {
            let interest = if blocked {
                Interest::READABLE | Interest::WRITABLE
            } else {
                Interest::READABLE
            };
            self.poll
                .registry()
                .reregister(&mut b.socket, SOCKET, interest)?;
            b.writable_wanted = blocked;
        }
        Ok(())
    }

    /// Moves what the endpoint and the emulators have to send towards the socket.
    fn transmit(&mut self, now: Instant) -> std::io::Result<()> {
        match &mut self.net {
            Net::Laminar(manager) => {
                let sender = manager.event_sender().clone();
                while let Some((addr, datagram)) = self.endpoint.poll_transmit(now) {
                    match self.emulators.get_mut(&addr) {
                        Some((_, em)) => em.send(now, datagram),
                        None => {
                            self.io_stats.send_calls += 1;
                            self.io_stats.datagrams_sent += 1;
                            let _ = sender.send(Packet::unreliable(addr, datagram));
                        }
                    }
                }
                for (addr, (_, em)) in self.emulators.iter_mut() {
                    while let Some(d) = em.poll(now) {
                        self.io_stats.send_calls += 1;
                        self.io_stats.datagrams_sent += 1;
                        let _ = sender.send(Packet::unreliable(*addr, d));
                    }
                }
                manager.manual_poll(now);
                Ok(())
            }
            Net::Batched(_) => {
                loop {
                    let Net::Batched(b) = &mut self.net else {
                        unreachable!()
                    };
                    if b.writable_wanted {
                        // The socket is full: what is not made yet waits in the endpoint.
                        return Ok(());
                    }
                    let (start, buf) = b.outbox.begin();
                    match self.endpoint.poll_transmit_into(now, buf) {
                        None => {
                            b.outbox.abort(start);
                            break;
                        }
                        Some(to) => route(&mut b.outbox, &mut self.emulators, now, to, start),
                    }
                    if b.outbox.len() >= OUTBOX_FLUSH_AT {
                        self.flush()?;
                    }
                }
                if let Net::Batched(b) = &mut self.net {
                    for (addr, (_, em)) in self.emulators.iter_mut() {
                        while let Some(d) = em.poll(now) {
                            b.outbox.push(*addr, &d);
                        }
                    }
                }
                self.flush()
            }
        }
    }

    fn run(&mut self) -> std::io::Result<()> {
        let mut events = Events::with_capacity(64);
        let mut last_publish = Instant::now();
        loop {
            let now = Instant::now();
            loop {
                match self.commands.try_recv() {
                    Ok(cmd) => self.apply(cmd, now),
                    Err(TryRecvError::Empty) => break,
                    Err(TryRecvError::Disconnected) => {
                        if self.closing.is_none() {
                            self.apply(Command::Close { failed: false }, now);
                        }
                        break;
                    }
                }
            }
            if self.aborted {
                return Ok(());
            }
            self.receive(now)?;
            self.endpoint.handle_timeout(now);
            self.flush_backlog();
            self.transmit(now)?;
            while let Some(e) = self.endpoint.poll_event() {
                self.pending_events.push_back(e);
            }
            while !self.pending_events.is_empty() {
                let n = self.pending_events.len().min(EVENT_BATCH);
                let Ok(permit) = self.events.try_reserve() else {
                    if self.events.is_closed() {
                        self.pending_events.clear();
                    }
                    break;
                };
                permit.send(self.pending_events.drain(..n).collect());
            }
            if now.duration_since(last_publish) >= Duration::from_millis(20) {
                self.publish();
                last_publish = now;
            }
            if let Some(since) = self.closing {
                // Give the goodbyes (and emulated delays) a moment, then stop.
                let emulated = self.emulators.values().any(|(_, e)| !e.is_empty());
                if !emulated || now.duration_since(since) > Duration::from_millis(200) {
                    self.publish();
                    return Ok(());
                }
            }
            let mut deadline = self.endpoint.poll_timeout();
            for (_, em) in self.emulators.values() {
                if let Some(d) = em.next_due() {
                    deadline = Some(deadline.map_or(d, |x| x.min(d)));
                }
            }
            let mut timeout = deadline.map_or(Duration::from_millis(50), |d| {
                d.saturating_duration_since(Instant::now())
            });
            if !self.pending_events.is_empty() || self.closing.is_some() {
                timeout = timeout.min(Duration::from_millis(1));
            }
            if matches!(&self.net, Net::Batched(b) if b.unread) {
                timeout = Duration::ZERO;
            }
            timeout = timeout.min(Duration::from_millis(50));
            // Announce the sleep, then look once more: a command queued before the flag was
            // set found no sleeper to wake.
            self.sleeping.store(true, Ordering::SeqCst);
            if !self.commands.is_empty() {
                timeout = Duration::ZERO;
            }
            let polled = self.poll.poll(&mut events, Some(timeout));
            self.sleeping.store(false, Ordering::SeqCst);
            match polled {
                Ok(()) => {}
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(e),
            }
        }
    }
}
