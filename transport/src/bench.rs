//! `cloudlight bench transport`: two drivers on loopback exchange messages through the link
//! emulator, and a plain UDP blast of the same bytes in datagrams of the same size measures
//! the ceiling. Users run it to qualify a link profile; it reports whether every message
//! arrived byte-identical and in order, goodput, retransmissions and message round trips.

use std::collections::{HashMap, VecDeque};
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde::Serialize;

use crate::driver::{Command, Driver, DriverConfig, DriverHandle, EventReceiver};
use crate::emulator::LinkProfile;
use crate::endpoint::{EdgeDirection, EndpointConfig, Event};

/// What to measure.
#[derive(Clone, Debug, Serialize)]
pub struct BenchOptions {
    /// Bytes per message.
    pub size: usize,
    /// Messages in the bulk phase.
    pub count: usize,
    /// Round trips measured after the bulk phase (one message out, one back).
    pub rtt_rounds: usize,
    /// Emulated link, applied in both directions.
    pub link: LinkProfile,
    /// Largest packet handed to laminar.
    pub packet_bytes: usize,
    /// Messages in flight end to end (the edge's capacity).
    pub capacity: u64,
    /// Most unacknowledged packets per peer.
    pub window_packets: usize,
    /// Seed of the emulators.
    pub seed: u64,
    /// Longest the whole bench may take; what has not arrived by then is missing.
    #[serde(skip)]
    pub time_limit: Duration,
    /// Also measure a plain UDP blast of the same bytes.
    pub udp_baseline: bool,
    /// Encrypt packets (they are authenticated either way).
    pub encrypt: bool,
    /// Congestion control on the link.
    pub congestion_control: bool,
    /// What the traffic looks like.
    pub pattern: Pattern,
    /// Receivers (each its own node and socket); the sender fans out to all of them.
    pub clients: usize,
    /// Batched socket I/O (GSO/GRO); off: laminar moves each datagram.
    pub batched_io: bool,
}

/// The bench's traffic.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Pattern {
    /// One sender streams `count` messages to every client as fast as credit allows; then
    /// `rtt_rounds` round trips with the first client.
    #[default]
    Bulk,
    /// Every client sends `count` requests, one at a time, each answered by an echo of the
    /// same size: a message's completion is its round trip.
    RequestResponse,
}

/// The bench's edge capacity for messages of `size` bytes: as many as hold 4 MiB, at least
/// 64. A count of messages is a window of `capacity × size` bytes per credit round trip
/// (which crosses four threads: about 0.2-0.3 ms on two cores), so 64 messages of 1 KiB
/// held a stream to ~250 MB/s.
pub fn default_capacity(size: usize) -> u64 {
    ((4 << 20) / size.max(1) as u64).clamp(64, 1_000_000)
}

impl Default for BenchOptions {
    fn default() -> Self {
        BenchOptions {
            size: 1024,
            count: 10_000,
            rtt_rounds: 200,
            link: LinkProfile::default(),
            packet_bytes: 1200,
            capacity: default_capacity(1024),
            window_packets: EndpointConfig::new("", "", b"").window_packets,
            seed: 1,
            time_limit: Duration::from_secs(120),
            udp_baseline: true,
            encrypt: true,
            congestion_control: true,
            pattern: Pattern::Bulk,
            clients: 1,
            batched_io: true,
        }
    }
}

/// What was measured.
#[derive(Clone, Debug, Serialize)]
pub struct BenchReport {
    /// The options.
    pub options: BenchOptions,
    /// Messages sent in the bulk phase (all clients; request-response: answers sent).
    pub sent: usize,
    /// Messages delivered in the bulk phase (all clients; request-response: answers
    /// received).
    pub delivered: usize,
    /// Whether every one of `count` messages (per client) was delivered within the time
    /// limit.
    pub complete: bool,
    /// Whether every delivered message equals what was sent (`None`: none arrived, nothing
    /// to judge).
    pub byte_identical: Option<bool>,
    /// Whether messages arrived in sending order, each once (`None`: none arrived).
    pub in_order: Option<bool>,
    /// Milliseconds until every session was up (the handshakes, before any message; not
    /// part of `elapsed_s`).
    pub connect_ms: f64,
    /// Seconds from the first send to the last delivery.
    pub elapsed_s: f64,
    /// Message bytes delivered per second, MB/s (10⁶ bytes).
    pub goodput_mb_s: f64,
    /// DATA packets sent, retransmissions included.
    pub data_packets: u64,
    /// DATA packets that were retransmissions.
    pub retransmissions: u64,
    /// retransmissions / data_packets.
    pub retransmission_ratio: f64,
    /// Bytes of all packets the sender sent.
    pub wire_bytes: u64,
    /// Median time from handing a bulk message to the transport to its delivery, ms.
    pub completion_ms_p50: f64,
    /// 99th percentile of the same, ms.
    pub completion_ms_p99: f64,
    /// Message round trips measured.
    pub rtt_rounds: usize,
    /// Median message round trip, microseconds.
    pub rtt_p50_us: f64,
    /// 99th percentile message round trip, microseconds.
    pub rtt_p99_us: f64,
    /// The sender's socket: system calls and datagrams.
    pub sender_io: crate::driver::IoStats,
    /// Goodput of each client, MB/s (bulk: what it received; request-response: its
    /// answers).
    pub client_goodput_mb_s: Vec<f64>,
    /// Plain UDP blast of the same bytes (at least 32 MiB) in datagrams of the same size, MB/s.
    pub udp_blast_mb_s: Option<f64>,
    /// goodput / UDP blast.
    pub fraction_of_blast: Option<f64>,
}

/// The bench's messages: message `seq` is a window of one pseudo-random block, starting at
/// an offset that depends on `seq`, with `seq` in its first eight bytes. Making and checking
/// one costs a copy and a comparison, so the bench's own work stays small beside the
/// transport's, and a message delivered in the wrong place, twice or corrupted fails.
struct Patterns {
    block: Vec<u8>,
    len: usize,
}

/// Distinct starting offsets in the block.
const PATTERN_OFFSETS: usize = 4093;

impl Patterns {
    fn new(len: usize) -> Self {
        let mut x: u64 = 0x9E37_79B9_7F4A_7C15;
        let mut block = Vec::with_capacity(len + PATTERN_OFFSETS + 8);
        while block.len() < len + PATTERN_OFFSETS {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            block.extend_from_slice(&x.to_le_bytes());
        }
        Patterns { block, len }
    }

    fn window(&self, seq: u64) -> &[u8] {
        let at = (seq as usize).wrapping_mul(7919) % PATTERN_OFFSETS;
        &self.block[at..at + self.len]
    }

    /// Message `seq`.
    fn make(&self, seq: u64) -> Vec<u8> {
        let mut m = self.window(seq).to_vec();
        let n = m.len().min(8);
        m[..n].copy_from_slice(&seq.to_le_bytes()[..n]);
        m
    }

    /// Whether `bytes` is message `seq`.
    fn matches(&self, seq: u64, bytes: &[u8]) -> bool {
        let n = self.len.min(8);
        bytes.len() == self.len
            && bytes[..n] == seq.to_le_bytes()[..n]
            && bytes[n..] == self.window(seq)[n..]
    }
}

fn start(name: &str, incarnation: u64, opts: &BenchOptions) -> std::io::Result<DriverHandle> {
    let mut c = EndpointConfig::new(name, "bench", b"bench");
    c.max_packet_bytes = opts.packet_bytes;
    c.window_packets = opts.window_packets;
    c.confidential = opts.encrypt;
    c.congestion_control = opts.congestion_control;
    c.max_message_bytes = c.max_message_bytes.max(opts.size);
    let mut d = DriverConfig::new(c, SocketAddr::from(([127, 0, 0, 1], 0)));
    d.seed = opts.seed ^ incarnation;
    d.batched_io = opts.batched_io;
    Driver::start(d)
}

/// Waits until `side` has seen `peers` sessions come up.
async fn wait_up(side: &mut Side, peers: usize) -> Result<(), String> {
    let mut up = 0;
    while up < peers {
        if let Event::PeerUp { .. } = side.next().await? {
            up += 1;
        }
    }
    Ok(())
}

/// Edge ids of client `i`: from the sender to it, and back.
fn edges(i: usize) -> (u32, u32) {
    (1 + 2 * i as u32, 2 + 2 * i as u32)
}

/// One end of a link: its driver, events and the credit of its sending edges.
struct Side {
    handle: DriverHandle,
    events: EventReceiver,
    granted: HashMap<u32, u64>,
    sent: HashMap<u32, u64>,
}

impl Side {
    fn new(mut handle: DriverHandle) -> Self {
        let events = handle.take_events();
        Side {
            handle,
            events,
            granted: HashMap::new(),
            sent: HashMap::new(),
        }
    }

    fn credit(&mut self, event: &Event) {
        if let Event::Credit { edge, granted } = *event {
            let g = self.granted.entry(edge).or_default();
            *g = (*g).max(granted);
        }
    }

    fn has_credit(&self, edge: u32) -> bool {
        self.sent.get(&edge).copied().unwrap_or(0) < self.granted.get(&edge).copied().unwrap_or(0)
    }

    async fn next(&mut self) -> Result<Event, String> {
        let e = self
            .events
            .recv()
            .await
            .ok_or_else(|| "transport driver stopped".to_string())?;
        self.credit(&e);
        Ok(e)
    }

    async fn wait_credit(&mut self, edge: u32) -> Result<(), String> {
        while !self.has_credit(edge) {
            self.next().await?;
        }
        Ok(())
    }

    async fn send(&mut self, edge: u32, bytes: Vec<u8>) -> Result<(), String> {
        *self.sent.entry(edge).or_default() += 1;
        self.handle
            .command(Command::Send {
                edge,
                bytes: bytes.into(),
            })
            .await
            .map_err(|e| e.to_string())
    }

    /// Waits for a message on `edge` and releases it.
    async fn receive(&mut self, edge: u32) -> Result<(u64, Vec<u8>), String> {
        loop {
            if let Event::Message {
                edge: e,
                seq,
                bytes,
            } = self.next().await?
                && e == edge
            {
                self.release(edge, 1).await?;
                return Ok((seq, bytes));
            }
        }
    }

    async fn release(&self, edge: u32, n: u64) -> Result<(), String> {
        self.handle
            .command(Command::Release { edge, n })
            .await
            .map_err(|e| e.to_string())
    }
}

/// What one client saw.
struct ClientTally {
    delivered: usize,
    identical: bool,
    in_order: bool,
    /// Completion time of each message (bulk: handed over to delivered; request-response:
    /// the round trip).
    completions: Vec<Duration>,
    last: Option<Instant>,
}

impl ClientTally {
    /// Nothing seen yet: identical and in order until a message says otherwise.
    fn new() -> Self {
        ClientTally {
            delivered: 0,
            identical: true,
            in_order: true,
            completions: Vec::new(),
            last: None,
        }
    }
}

/// Starts the sender ("a") and the clients ("b0", "b1", ...), declares them to each other
/// and opens each client's two edges.
async fn cluster(opts: &BenchOptions) -> Result<(Side, Vec<Side>), String> {
    let io = |e: std::io::Error| e.to_string();
    let closed = |_| "transport driver stopped".to_string();
    let a = start("a", 1, opts).map_err(io)?;
    let mut clients = Vec::with_capacity(opts.clients);
    for i in 0..opts.clients {
        clients.push(start(&format!("b{i}"), 2 + i as u64, opts).map_err(io)?);
    }
    for (i, b) in clients.iter().enumerate() {
        let name = format!("b{i}");
        let (down, up) = edges(i);
        // The client first: a starts its handshake as soon as it knows the client.
        b.command(Command::AddPeer {
            name: "a".into(),
            addr: a.local_addr(),
            link: opts.link,
        })
        .await
        .map_err(closed)?;
        a.command(Command::AddPeer {
            name: name.clone(),
            addr: b.local_addr(),
            link: opts.link,
        })
        .await
        .map_err(closed)?;
        for (h, peer, out, inp) in [(&a, name.as_str(), down, up), (b, "a", up, down)] {
            for (edge, direction) in [(out, EdgeDirection::Send), (inp, EdgeDirection::Receive)] {
                h.command(Command::OpenEdge {
                    edge,
                    peer: peer.into(),
                    direction,
                    capacity: opts.capacity,
                })
                .await
                .map_err(closed)?;
            }
        }
    }
    let mut a = Side::new(a);
    let clients: Vec<Side> = clients.into_iter().map(Side::new).collect();
    for i in 0..opts.clients {
        let (down, _) = edges(i);
        a.granted.insert(down, opts.capacity);
    }
    Ok((a, clients))
}

/// Bulk: `a` sends `count` messages to every client within each edge's credit; each client
/// checks, times and releases what arrives. Returns the sender and each client's tally.
async fn bulk(
    opts: &BenchOptions,
    mut a: Side,
    clients: Vec<Side>,
    patterns: Arc<Patterns>,
    deadline: tokio::time::Instant,
) -> Result<(Side, Vec<(Side, ClientTally)>), String> {
    let n = clients.len();
    // When the sender handed message `seq` to client `i`'s edge.
    let handed: Arc<Vec<Mutex<Vec<Instant>>>> = Arc::new(
        (0..n)
            .map(|_| Mutex::new(Vec::with_capacity(opts.count)))
            .collect(),
    );
    let mut tasks = Vec::with_capacity(n);
    for (i, mut b) in clients.into_iter().enumerate() {
        let (down, _) = edges(i);
        let (patterns, handed, count) = (patterns.clone(), handed.clone(), opts.count);
        tasks.push(tokio::spawn(async move {
            let mut t = ClientTally::new();
            let run = async {
                while t.delivered < count {
                    // Take everything already waiting, then release it with one command.
                    let mut next = Some(b.next().await?);
                    let mut released = 0;
                    while let Some(e) = next {
                        if let Event::Message { edge, seq, bytes } = e
                            && edge == down
                        {
                            let now = Instant::now();
                            t.in_order &= seq == t.delivered as u64;
                            t.identical &= patterns.matches(seq, &bytes);
                            t.delivered += 1;
                            t.last = Some(now);
                            released += 1;
                            let at = handed[i].lock().unwrap_or_else(|e| e.into_inner());
                            if let Some(h) = at.get(seq as usize) {
                                t.completions.push(now.duration_since(*h));
                            }
                        }
                        next = b.events.try_recv().ok();
                        if let Some(e) = &next {
                            b.credit(e);
                        }
                    }
                    if released > 0 {
                        b.release(down, released).await?;
                    }
                }
                Ok::<(), String>(())
            };
            let r = tokio::time::timeout_at(deadline, run).await;
            match r {
                Ok(Err(e)) => Err(e),
                _ => Ok((b, t)),
            }
        }));
    }
    // The sender: round robin over the clients' edges, as far as each one's credit goes.
    let mut sent = vec![0usize; n];
    let send_all = async {
        while sent.iter().any(|&k| k < opts.count) {
            let mut progressed = false;
            for (i, k) in sent.iter_mut().enumerate() {
                let (down, _) = edges(i);
                while *k < opts.count && a.has_credit(down) {
                    a.send(down, patterns.make(*k as u64)).await?;
                    handed[i]
                        .lock()
                        .unwrap_or_else(|e| e.into_inner())
                        .push(Instant::now());
                    *k += 1;
                    progressed = true;
                }
            }
            if !progressed {
                a.next().await?;
            }
        }
        Ok::<(), String>(())
    };
    let out = finish(send_all, tasks, deadline).await?;
    Ok((a, out))
}

/// A client's task: what it ends with, its side and tally.
type ClientTask = tokio::task::JoinHandle<Result<(Side, ClientTally), String>>;

/// Runs the sender's part `work` until it ends or the deadline passes, then waits for every
/// client's task.
async fn finish(
    work: impl std::future::Future<Output = Result<(), String>>,
    tasks: Vec<ClientTask>,
    deadline: tokio::time::Instant,
) -> Result<Vec<(Side, ClientTally)>, String> {
    if let Ok(r) = tokio::time::timeout_at(deadline, work).await {
        r?;
    }
    let mut out = Vec::with_capacity(tasks.len());
    for t in tasks {
        out.push(t.await.map_err(|e| e.to_string())??);
    }
    Ok(out)
}

/// Request-response: every client sends `count` requests, one at a time; `a` echoes each.
async fn request_response(
    opts: &BenchOptions,
    mut a: Side,
    clients: Vec<Side>,
    patterns: Arc<Patterns>,
    deadline: tokio::time::Instant,
) -> Result<(Side, Vec<(Side, ClientTally)>), String> {
    let n = clients.len();
    let mut tasks = Vec::with_capacity(n);
    for (i, mut b) in clients.into_iter().enumerate() {
        let (down, up) = edges(i);
        b.granted.insert(up, opts.capacity);
        let (patterns, count) = (patterns.clone(), opts.count);
        tasks.push(tokio::spawn(async move {
            let mut t = ClientTally::new();
            let run = async {
                for k in 0..count as u64 {
                    b.wait_credit(up).await?;
                    let t0 = Instant::now();
                    b.send(up, patterns.make(k)).await?;
                    let (seq, bytes) = b.receive(down).await?;
                    let now = Instant::now();
                    t.completions.push(now.duration_since(t0));
                    t.in_order &= seq == k;
                    t.identical &= patterns.matches(k, &bytes);
                    t.delivered += 1;
                    t.last = Some(now);
                }
                Ok::<(), String>(())
            };
            match tokio::time::timeout_at(deadline, run).await {
                Ok(Err(e)) => Err(e),
                _ => Ok((b, t)),
            }
        }));
    }
    // The server echoes every request on the same client's other edge.
    let total = n * opts.count;
    let mut echoed = 0;
    let mut waiting: Vec<VecDeque<Vec<u8>>> = vec![VecDeque::new(); n];
    let serve = async {
        while echoed < total {
            let e = a.next().await?;
            if let Event::Message { edge, bytes, .. } = e
                && edge % 2 == 0
            {
                let i = (edge / 2 - 1) as usize;
                a.release(edge, 1).await?;
                waiting[i].push_back(bytes);
            }
            for (i, q) in waiting.iter_mut().enumerate() {
                let (down, _) = edges(i);
                while !q.is_empty() && a.has_credit(down) {
                    let bytes = q.pop_front().expect("not empty");
                    a.send(down, bytes).await?;
                    echoed += 1;
                }
            }
        }
        Ok::<(), String>(())
    };
    let out = finish(serve, tasks, deadline).await?;
    Ok((a, out))
}

/// Runs the bench (see the module documentation).
pub async fn run(opts: BenchOptions) -> Result<BenchReport, String> {
    if opts.clients == 0 {
        return Err("the bench needs at least one client".into());
    }
    let connect_t = Instant::now();
    let deadline = tokio::time::Instant::now() + opts.time_limit;
    let (mut a, mut clients) = cluster(&opts).await?;
    // The clock starts once every session is up: a handshake that lost its HELLOs (50 ms
    // apart) would otherwise count against the goodput of the transfer.
    let connecting = async {
        wait_up(&mut a, clients.len()).await?;
        for b in &mut clients {
            wait_up(b, 1).await?;
        }
        Ok::<(), String>(())
    };
    match tokio::time::timeout_at(deadline, connecting).await {
        Ok(r) => r?,
        // Reported as what it is: nothing delivered within the time limit.
        Err(_) => tracing::warn!("the sessions did not come up within the time limit"),
    }
    let connect_ms = connect_t.elapsed().as_secs_f64() * 1e3;
    let patterns = Arc::new(Patterns::new(opts.size));
    let start_t = Instant::now();
    let (mut a, tallies) = match opts.pattern {
        Pattern::Bulk => bulk(&opts, a, clients, patterns.clone(), deadline).await?,
        Pattern::RequestResponse => {
            request_response(&opts, a, clients, patterns.clone(), deadline).await?
        }
    };
    let elapsed_of = |t: &ClientTally| {
        t.last
            .map_or(1e-9, |l| l.duration_since(start_t).as_secs_f64())
            .max(1e-9)
    };
    let elapsed_s = tallies
        .iter()
        .map(|(_, t)| elapsed_of(t))
        .fold(1e-9, f64::max);
    let stats = a.handle.fresh_stats().await;
    let (mut data_packets, mut retransmissions, mut wire_bytes) = (0, 0, 0);
    for (_, p) in &stats.peers {
        data_packets += p.data_packets_sent;
        retransmissions += p.retransmissions;
        wire_bytes += p.wire_bytes_sent;
    }
    let delivered: usize = tallies.iter().map(|(_, t)| t.delivered).sum();
    let complete = tallies.iter().all(|(_, t)| t.delivered == opts.count);
    let client_goodput_mb_s = tallies
        .iter()
        .map(|(_, t)| (t.delivered * opts.size) as f64 / elapsed_of(t) / 1e6)
        .collect();
    let mut completions: Vec<Duration> = tallies
        .iter()
        .flat_map(|(_, t)| t.completions.iter().copied())
        .collect();

    // Round trips after a complete bulk phase (never past the deadline): a sends one
    // message to the first client, which echoes it back.
    let mut rtts = Vec::with_capacity(opts.rtt_rounds);
    let sent = a.sent.values().sum::<u64>() as usize;
    let (mut clients, tallies): (Vec<Side>, Vec<ClientTally>) = tallies.into_iter().unzip();
    let rounds = if opts.pattern == Pattern::Bulk && complete {
        opts.rtt_rounds
    } else {
        0
    };
    if let Some(b) = clients.first_mut() {
        let (down, up) = edges(0);
        b.granted.entry(up).or_insert(opts.capacity);
        let round_trips = async {
            for round in 0..rounds {
                a.wait_credit(down).await?;
                let t0 = Instant::now();
                a.send(down, patterns.make((opts.count + round) as u64))
                    .await?;
                let (_, echo) = b.receive(down).await?;
                b.wait_credit(up).await?;
                b.send(up, echo).await?;
                a.receive(up).await?;
                rtts.push(t0.elapsed());
            }
            Ok::<(), String>(())
        };
        match tokio::time::timeout_at(deadline, round_trips).await {
            Ok(r) => r?,
            Err(_) => tracing::warn!("round-trip phase cut short by the time limit"),
        }
    }
    if opts.pattern == Pattern::RequestResponse {
        rtts = completions.clone();
    }
    a.handle.close();
    for b in &mut clients {
        b.handle.close();
    }
    rtts.sort();
    completions.sort();
    let quantile = |v: &[Duration], p: f64| {
        v.get(((v.len() as f64 * p) as usize).min(v.len().saturating_sub(1)))
            .map_or(0.0, |d| d.as_secs_f64())
    };
    let q = |p: f64| quantile(&rtts, p) * 1e6;
    let goodput = (delivered * opts.size) as f64 / elapsed_s / 1e6;
    let blast = if opts.udp_baseline {
        // Datagrams as large as the transport's: a message's chunk plus its header, plus
        // laminar's 5 bytes.
        let datagram = (opts.size + crate::wire::DATA_OVERHEAD).min(opts.packet_bytes) + 5;
        // At least 32 MiB, so that a small transfer still measures the steady rate rather
        // than a burst into the socket buffer.
        let total = (opts.count * opts.size * opts.clients).max(32 << 20);
        Some(udp_blast(total, datagram).map_err(|e| e.to_string())?)
    } else {
        None
    };
    Ok(BenchReport {
        sent,
        delivered,
        complete,
        byte_identical: (delivered > 0).then(|| tallies.iter().all(|t| t.identical)),
        in_order: (delivered > 0).then(|| tallies.iter().all(|t| t.in_order)),
        connect_ms,
        elapsed_s,
        goodput_mb_s: goodput,
        data_packets,
        retransmissions,
        retransmission_ratio: if data_packets > 0 {
            retransmissions as f64 / data_packets as f64
        } else {
            0.0
        },
        wire_bytes,
        completion_ms_p50: quantile(&completions, 0.5) * 1e3,
        completion_ms_p99: quantile(&completions, 0.99) * 1e3,
        rtt_rounds: rtts.len(),
        rtt_p50_us: q(0.5),
        rtt_p99_us: q(0.99),
        client_goodput_mb_s,
        sender_io: stats.io,
        udp_blast_mb_s: blast,
        fraction_of_blast: blast.map(|b| goodput / b),
        options: opts,
    })
}

/// A plain UDP blast on loopback: `total_bytes` in datagrams of `datagram_bytes`, sent as
/// fast as the socket takes them, 4 MiB buffers. Returns the MB/s received (10⁶ bytes/s,
/// counting only bytes that arrived).
pub fn udp_blast(total_bytes: usize, datagram_bytes: usize) -> std::io::Result<f64> {
    use socket2::{Domain, Protocol, Socket, Type};
    let mk = || -> std::io::Result<std::net::UdpSocket> {
        let s = Socket::new(Domain::IPV4, Type::DGRAM, Some(Protocol::UDP))?;
        let _ = s.set_recv_buffer_size(4 << 20);
        let _ = s.set_send_buffer_size(4 << 20);
        s.bind(&SocketAddr::from(([127, 0, 0, 1], 0)).into())?;
        Ok(s.into())
    };
    let (rx, tx) = (mk()?, mk()?);
    rx.set_read_timeout(Some(Duration::from_millis(100)))?;
    let to = rx.local_addr()?;
    let datagrams = total_bytes.div_ceil(datagram_bytes).max(1);
    let receiver = std::thread::spawn(move || {
        let mut buf = vec![0u8; 65536];
        let (mut got, mut first, mut last) = (0usize, None, Instant::now());
        while let Ok(n) = rx.recv(&mut buf) {
            first.get_or_insert_with(Instant::now);
            got += n;
            last = Instant::now();
        }
        (
            got,
            first.map_or(0.0, |f| last.duration_since(f).as_secs_f64()),
        )
    });
    let payload = vec![0x5au8; datagram_bytes];
    for _ in 0..datagrams {
        let _ = tx.send_to(&payload, to);
    }
    let (got, secs) = receiver
        .join()
        .map_err(|_| std::io::Error::other("receiver panicked"))?;
    Ok(if secs > 0.0 {
        got as f64 / secs / 1e6
    } else {
        0.0
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bench_messages_differ_and_a_wrong_or_corrupted_one_fails_its_check() {
        for len in [0, 3, 8, 9, 1024, 10_000] {
            let p = Patterns::new(len);
            for seq in [0u64, 1, 2, 4093, 1 << 40] {
                let m = p.make(seq);
                assert_eq!(m.len(), len);
                assert!(p.matches(seq, &m));
                if len > 0 {
                    assert!(!p.matches(seq + 1, &m), "len {len} seq {seq}");
                    let mut bad = m.clone();
                    bad[len - 1] ^= 1;
                    assert!(!p.matches(seq, &bad));
                }
            }
            assert!(!p.matches(0, &vec![0; len + 1]));
        }
        let p = Patterns::new(1024);
        assert_ne!(p.make(1)[8..], p.make(2)[8..]);
    }
}
