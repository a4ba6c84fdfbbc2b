//! `cloudlight bench transport`: two drivers on loopback exchange messages through the link
//! emulator, and a plain UDP blast of the same bytes in datagrams of the same size measures
//! the ceiling. Users run it to qualify a link profile; it reports whether every message
//! arrived byte-identical and in order, goodput, retransmissions and message round trips.

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use serde::Serialize;

use crate::driver::{Command, Driver, DriverConfig, DriverHandle};
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
}

impl Default for BenchOptions {
    fn default() -> Self {
        BenchOptions {
            size: 1024,
            count: 10_000,
            rtt_rounds: 200,
            link: LinkProfile::default(),
            packet_bytes: 1200,
            capacity: 64,
            window_packets: EndpointConfig::new("", "", b"").window_packets,
            seed: 1,
            time_limit: Duration::from_secs(120),
            udp_baseline: true,
            encrypt: true,
            congestion_control: true,
        }
    }
}

/// What was measured.
#[derive(Clone, Debug, Serialize)]
pub struct BenchReport {
    /// The options.
    pub options: BenchOptions,
    /// Messages sent in the bulk phase.
    pub sent: usize,
    /// Messages delivered in the bulk phase.
    pub delivered: usize,
    /// Whether every one of `count` messages was delivered within the time limit.
    pub complete: bool,
    /// Whether every delivered message equals what was sent (`None`: none arrived, nothing
    /// to judge).
    pub byte_identical: Option<bool>,
    /// Whether messages arrived in sending order, each once (`None`: none arrived).
    pub in_order: Option<bool>,
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
    Driver::start(d)
}

/// One end of the round-trip phase: its driver, events and the credit of its sending edge.
struct Side<'a> {
    handle: &'a DriverHandle,
    events: &'a mut crate::driver::EventReceiver,
    granted: u64,
    sent: u64,
}

impl Side<'_> {
    fn credit(&mut self, edge: u32, event: &Event) {
        if let Event::Credit { edge: e, granted } = *event
            && e == edge
        {
            self.granted = self.granted.max(granted);
        }
    }

    async fn next(&mut self) -> Result<Event, String> {
        self.events
            .recv()
            .await
            .ok_or_else(|| "transport driver stopped".to_string())
    }

    async fn wait_credit(&mut self, edge: u32) -> Result<(), String> {
        while self.sent >= self.granted {
            let e = self.next().await?;
            self.credit(edge, &e);
        }
        Ok(())
    }

    async fn send(&mut self, edge: u32, bytes: Vec<u8>) -> Result<(), String> {
        self.sent += 1;
        self.handle
            .command(Command::Send { edge, bytes })
            .await
            .map_err(|e| e.to_string())
    }

    /// Waits for a message on `edge` (keeping track of credit on `sending`) and releases it.
    async fn receive(&mut self, edge: u32, sending: u32) -> Result<Vec<u8>, String> {
        loop {
            match self.next().await? {
                Event::Message { edge: e, bytes, .. } if e == edge => {
                    self.handle
                        .command(Command::Release { edge, n: 1 })
                        .await
                        .map_err(|e| e.to_string())?;
                    return Ok(bytes);
                }
                other => self.credit(sending, &other),
            }
        }
    }
}

/// Runs the bench (see the module documentation).
pub async fn run(opts: BenchOptions) -> Result<BenchReport, String> {
    let io = |e: std::io::Error| e.to_string();
    let mut a = start("a", 1, &opts).map_err(io)?;
    let mut b = start("b", 2, &opts).map_err(io)?;
    let closed = |_| "transport driver stopped".to_string();
    // b first: a starts its handshake as soon as it knows b, and b should know a by then.
    b.command(Command::AddPeer {
        name: "a".into(),
        addr: a.local_addr(),
        link: opts.link,
    })
    .await
    .map_err(closed)?;
    a.command(Command::AddPeer {
        name: "b".into(),
        addr: b.local_addr(),
        link: opts.link,
    })
    .await
    .map_err(closed)?;
    for (h, peer, out, inp) in [(&a, "b", 1, 2), (&b, "a", 2, 1)] {
        h.command(Command::OpenEdge {
            edge: out,
            peer: peer.into(),
            direction: EdgeDirection::Send,
            capacity: opts.capacity,
        })
        .await
        .map_err(closed)?;
        h.command(Command::OpenEdge {
            edge: inp,
            peer: peer.into(),
            direction: EdgeDirection::Receive,
            capacity: opts.capacity,
        })
        .await
        .map_err(closed)?;
    }
    let deadline = tokio::time::Instant::now() + opts.time_limit;
    let patterns = Patterns::new(opts.size);

    // Bulk: a sends `count` messages on edge 1 within the credit; b checks and releases.
    let mut granted = opts.capacity;
    let mut sent = 0usize;
    let mut delivered = 0usize;
    let mut identical = true;
    let mut in_order = true;
    let mut b_events = b.take_events();
    let mut a_events = a.take_events();
    let start_t = Instant::now();
    let mut last_delivery = start_t;
    // When each bulk message was handed over, and how long it took to arrive.
    let mut handed = Vec::with_capacity(opts.count);
    let mut completions = Vec::with_capacity(opts.count);
    while delivered < opts.count {
        while sent < opts.count && (sent as u64) < granted {
            a.command(Command::Send {
                edge: 1,
                bytes: patterns.make(sent as u64),
            })
            .await
            .map_err(closed)?;
            handed.push(Instant::now());
            sent += 1;
        }
        tokio::select! {
            ev = b_events.recv() => {
                // Take everything already waiting, then release it with one command.
                let mut released = 0;
                let mut next = ev;
                loop {
                    match next {
                        Some(Event::Message { edge: 1, seq, bytes }) => {
                            in_order &= seq == delivered as u64;
                            identical &= patterns.matches(seq, &bytes);
                            delivered += 1;
                            released += 1;
                            last_delivery = Instant::now();
                            if let Some(t) = handed.get(seq as usize) {
                                completions.push(last_delivery.duration_since(*t));
                            }
                        }
                        Some(_) => {}
                        None => return Err("receiver stopped".into()),
                    }
                    match b_events.try_recv() {
                        Ok(e) => next = Some(e),
                        Err(_) => break,
                    }
                }
                if released > 0 {
                    b.command(Command::Release { edge: 1, n: released }).await.map_err(closed)?;
                }
            }
            ev = a_events.recv() => match ev {
                Some(Event::Credit { edge: 1, granted: g }) => granted = granted.max(g),
                Some(_) => {}
                None => return Err("sender stopped".into()),
            },
            _ = tokio::time::sleep_until(deadline) => break,
        }
    }
    let elapsed_s = last_delivery
        .duration_since(start_t)
        .as_secs_f64()
        .max(1e-9);
    tokio::time::sleep(Duration::from_millis(20)).await;
    let stats = a.stats();
    let peer = stats.peers.first().map(|(_, p)| *p).unwrap_or_default();

    // Round trips: a sends one message, b echoes it back on edge 2.
    let mut a_side = Side {
        handle: &a,
        events: &mut a_events,
        granted,
        sent: sent as u64,
    };
    let mut b_side = Side {
        handle: &b,
        events: &mut b_events,
        granted: opts.capacity,
        sent: 0,
    };
    let mut rtts = Vec::with_capacity(opts.rtt_rounds);
    // Only after a complete bulk phase, and never past the deadline: a link that lost the
    // bulk phase would otherwise keep the bench waiting for an echo forever.
    let rounds = if delivered == opts.count {
        opts.rtt_rounds
    } else {
        0
    };
    let round_trips = async {
        for round in 0..rounds {
            a_side.wait_credit(1).await?;
            let t0 = Instant::now();
            a_side.send(1, patterns.make(round as u64)).await?;
            let echo = b_side.receive(1, 2).await?;
            b_side.wait_credit(2).await?;
            b_side.send(2, echo).await?;
            a_side.receive(2, 1).await?;
            rtts.push(t0.elapsed());
        }
        Ok::<(), String>(())
    };
    match tokio::time::timeout_at(deadline, round_trips).await {
        Ok(r) => r?,
        Err(_) => tracing::warn!("round-trip phase cut short by the time limit"),
    }
    a.close();
    b.close();
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
        Some(udp_blast((opts.count * opts.size).max(32 << 20), datagram).map_err(io)?)
    } else {
        None
    };
    Ok(BenchReport {
        sent: opts.count.min(sent),
        delivered,
        complete: delivered == opts.count,
        byte_identical: (delivered > 0).then_some(identical),
        in_order: (delivered > 0).then_some(in_order),
        elapsed_s,
        goodput_mb_s: goodput,
        data_packets: peer.data_packets_sent,
        retransmissions: peer.retransmissions,
        retransmission_ratio: if peer.data_packets_sent > 0 {
            peer.retransmissions as f64 / peer.data_packets_sent as f64
        } else {
            0.0
        },
        wire_bytes: peer.wire_bytes_sent,
        completion_ms_p50: quantile(&completions, 0.5) * 1e3,
        completion_ms_p99: quantile(&completions, 0.99) * 1e3,
        rtt_rounds: rtts.len(),
        rtt_p50_us: q(0.5),
        rtt_p99_us: q(0.99),
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
