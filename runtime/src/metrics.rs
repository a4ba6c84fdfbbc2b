//! Run metrics: counters per edge and per stage instance, snapshots written as
//! `metrics.json`, and the summary table printed at the end of a run.
//!
//! Per edge: messages, bytes (encoded size; on an in-process edge this is what the message
//! would cost if the edge were cut), drops, depth and maximum depth, Mbps. Per stage: messages
//! handled, ticks, busy time per handler call (p50/p99/mean; time spent waiting on a full
//! `block` edge is excluded and reported apart as `blocked_s`), and a free-form report that
//! the stage publishes (age of indirect light, photons stored, ...).

use std::path::Path;
use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use comfy_table::{Table, presets::UTF8_FULL_CONDENSED};
use serde::{Deserialize, Serialize};

use crate::toolkit::{Latency, lock};

/// Live counters of one stage instance.
#[derive(Debug)]
pub struct StageMetrics {
    handled: AtomicU64,
    ticks: AtomicU64,
    blocked_ns: AtomicU64,
    busy: Mutex<Latency>,
    report: Mutex<Option<serde_json::Value>>,
}

impl Default for StageMetrics {
    fn default() -> Self {
        StageMetrics {
            handled: AtomicU64::new(0),
            ticks: AtomicU64::new(0),
            blocked_ns: AtomicU64::new(0),
            busy: Mutex::new(Latency::new()),
            report: Mutex::new(None),
        }
    }
}

impl StageMetrics {
    pub(crate) fn record(&self, tick: bool, busy: Duration, blocked: Duration) {
        if tick {
            self.ticks.fetch_add(1, Ordering::Relaxed);
        } else {
            self.handled.fetch_add(1, Ordering::Relaxed);
        }
        self.blocked_ns
            .fetch_add(blocked.as_nanos() as u64, Ordering::Relaxed);
        lock(&self.busy).record(busy);
    }

    pub(crate) fn set_report(&self, value: serde_json::Value) {
        *lock(&self.report) = Some(value);
    }

    /// Messages handled so far.
    pub fn handled(&self) -> u64 {
        self.handled.load(Ordering::Relaxed)
    }

    pub(crate) fn snapshot(&self, name: &str, kind: &str, node: &str) -> StageSnapshot {
        let h = lock(&self.busy);
        StageSnapshot {
            name: name.to_string(),
            kind: kind.to_string(),
            node: node.to_string(),
            handled: self.handled(),
            ticks: self.ticks.load(Ordering::Relaxed),
            busy_p50_ms: h.p50_ms(),
            busy_p99_ms: h.p99_ms(),
            busy_mean_ms: h.mean_ms(),
            blocked_s: self.blocked_ns.load(Ordering::Relaxed) as f64 * 1e-9,
            report: lock(&self.report).clone(),
        }
    }
}

/// One edge at one moment.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct EdgeSnapshot {
    /// `producer.port -> consumer.port`.
    pub name: String,
    /// `block` or `latest`.
    pub policy: String,
    /// Capacity of the edge.
    pub capacity: usize,
    /// Whether producer and consumer sit on different nodes.
    pub cut: bool,
    /// Messages accepted.
    pub messages: u64,
    /// Encoded bytes accepted.
    pub bytes: u64,
    /// Messages dropped by `latest`.
    pub dropped: u64,
    /// Messages queued at the snapshot.
    pub depth: usize,
    /// Largest queue length seen.
    pub max_depth: u64,
    /// Mean megabits per second over the run so far.
    pub mbps: f64,
    /// Transport figures when the edge is cut.
    pub wire: Option<WireSnapshot>,
}

/// What one half of a cut edge costs on the wire.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct WireSnapshot {
    /// The node at the other end.
    pub peer: String,
    /// Whether that peer is up now.
    pub peer_up: bool,
    /// Bytes of DATA packets (headers and retransmissions included) sent or received.
    pub wire_bytes: u64,
    /// `wire_bytes` as megabits per second over the run so far.
    pub wire_mbps: f64,
    /// DATA packets sent again (sending half).
    pub retransmissions: u64,
    /// Smoothed round-trip time to the peer, milliseconds.
    pub rtt_ms: f64,
    /// Messages given up: the peer restarted, or was gone while draining, before confirming
    /// it consumed them (most are lost; one it forwarded just before dying is not). What
    /// arrived end to end is counted where the pipeline ends (e.g. a probe sink's `missing`).
    pub lost: u64,
    /// Incoming messages refused (undecodable, or beyond credit).
    pub refused: u64,
    /// Outgoing messages over the transport's size limit, dropped (sending half).
    #[serde(default)]
    pub oversize: u64,
}

/// One node's transport at one moment: what it refused and what its peer links did.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, Default)]
pub struct TransportSnapshot {
    /// The node.
    pub node: String,
    /// Handshake packets from unknown names, other clusters, or without proof of the secret.
    pub strangers: u64,
    /// Datagrams that did not decode (laminar framing other than ours, or our format).
    pub malformed: u64,
    /// Packets naming no current session (strangers, or a peer's previous session).
    pub unknown_session: u64,
    /// Valid but stale handshake packets (recorded ones replayed).
    pub stale_handshakes: u64,
    /// Handshake answers withheld by the rate limit.
    pub rate_limited: u64,
    /// Messages serialized for cut edges (once per message, however many edges send it).
    #[serde(default)]
    pub encodings: u64,
    /// Sends that reused a message's serialization (fan-out to several cut edges).
    #[serde(default)]
    pub encodings_reused: u64,
    /// Datagrams the node sent.
    #[serde(default)]
    pub datagrams_sent: u64,
    /// System calls that sent datagrams (several per call with UDP GSO).
    #[serde(default)]
    pub send_calls: u64,
    /// Per peer.
    pub peers: Vec<PeerLinkSnapshot>,
}

/// One peer link of a node.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, Default)]
pub struct PeerLinkSnapshot {
    /// The peer.
    pub peer: String,
    /// `up`, `lost`, `left`, `mismatch` (another topology) or `connecting`.
    pub state: String,
    /// Smoothed round trip, milliseconds.
    pub rtt_ms: f64,
    /// Sessions completed.
    pub handshakes: u64,
    /// Restarts of the peer (a new session replaced a live one).
    pub restarts: u64,
    /// Messages lost with restarts.
    pub lost_messages: u64,
    /// DATA packets sent again.
    pub retransmissions: u64,
    /// Authentic DATA refused.
    pub refused: u64,
    /// Packets whose number was seen before (replays, network duplicates).
    pub replayed: u64,
    /// Packets naming the session that failed authentication.
    pub forged: u64,
    /// Address moves after a path challenge.
    pub moves: u64,
    /// Authentic packets from an address other than the peer's, not obeyed.
    #[serde(default)]
    pub misaddressed: u64,
    /// Nodes of another topology under the peer's name, refused while its session was live.
    #[serde(default)]
    pub mismatched: u64,
}

/// One stage instance at one moment.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct StageSnapshot {
    /// Instance name (`stage` or `stage[i]` for replicas).
    pub name: String,
    /// Stage kind.
    pub kind: String,
    /// Node the instance runs on.
    pub node: String,
    /// Input messages handled.
    pub handled: u64,
    /// Ticks run.
    pub ticks: u64,
    /// Median busy time per handler call, milliseconds.
    pub busy_p50_ms: f64,
    /// 99th percentile busy time per handler call, milliseconds.
    pub busy_p99_ms: f64,
    /// Mean busy time per handler call, milliseconds.
    pub busy_mean_ms: f64,
    /// Total time spent waiting on full `block` edges, seconds.
    pub blocked_s: f64,
    /// What the stage itself reports (technique-specific).
    pub report: Option<serde_json::Value>,
}

/// Where a run stands.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum RunStatus {
    /// Still running.
    Running,
    /// Drained and stopped normally.
    Finished,
    /// Stopped because a stage failed.
    Failed,
}

/// Everything `metrics.json` holds.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct MetricsSnapshot {
    /// Where the run stands.
    pub status: RunStatus,
    /// Wall seconds since the run started.
    pub elapsed_s: f64,
    /// Scene time at the snapshot, seconds.
    pub scene_time_s: f64,
    /// The failure that stopped the run, if any.
    pub failure: Option<String>,
    /// Every edge of the nodes run in this process.
    pub edges: Vec<EdgeSnapshot>,
    /// Every stage instance of the nodes run in this process.
    pub stages: Vec<StageSnapshot>,
    /// The transport of every node run in this process that has cut edges.
    #[serde(default)]
    pub transport: Vec<TransportSnapshot>,
}

impl MetricsSnapshot {
    /// Writes the snapshot as pretty JSON, atomically (temporary file, then rename).
    pub fn write_json(&self, path: &Path) -> std::io::Result<()> {
        let tmp = path.with_extension("json.tmp");
        std::fs::write(&tmp, serde_json::to_vec_pretty(self)?)?;
        std::fs::rename(tmp, path)
    }

    /// The summary tables printed at the end of a run.
    pub fn table(&self) -> String {
        let mut stages = Table::new();
        stages.load_preset(UTF8_FULL_CONDENSED).set_header([
            "stage",
            "kind",
            "node",
            "handled",
            "ticks",
            "busy p50 ms",
            "busy p99 ms",
            "blocked s",
        ]);
        for s in &self.stages {
            stages.add_row([
                s.name.clone(),
                s.kind.clone(),
                s.node.clone(),
                s.handled.to_string(),
                s.ticks.to_string(),
                format!("{:.3}", s.busy_p50_ms),
                format!("{:.3}", s.busy_p99_ms),
                format!("{:.3}", s.blocked_s),
            ]);
        }
        let mut edges = Table::new();
        edges.load_preset(UTF8_FULL_CONDENSED).set_header([
            "edge",
            "policy/cap",
            "peer",
            "messages",
            "MB",
            "Mbps",
            "dropped",
            "max depth",
            "wire Mbps",
            "retx",
            "rtt ms",
        ]);
        for e in &self.edges {
            let w =
                |f: &dyn Fn(&WireSnapshot) -> String| e.wire.as_ref().map_or("-".to_string(), f);
            edges.add_row([
                e.name.clone(),
                format!("{}/{}", e.policy, e.capacity),
                w(&|w| format!("{}{}", w.peer, if w.peer_up { "" } else { " (down)" })),
                e.messages.to_string(),
                format!("{:.3}", e.bytes as f64 / 1e6),
                format!("{:.3}", e.mbps),
                e.dropped.to_string(),
                e.max_depth.to_string(),
                w(&|w| format!("{:.3}", w.wire_mbps)),
                w(&|w| w.retransmissions.to_string()),
                w(&|w| format!("{:.3}", w.rtt_ms)),
            ]);
        }
        let mut text = format!(
            "run {:?} after {:.2} s (scene time {:.2} s)\n{stages}\n{edges}",
            self.status, self.elapsed_s, self.scene_time_s
        );
        if !self.transport.is_empty() {
            text.push('\n');
            text.push_str(&self.transport_table().to_string());
        }
        text
    }

    /// Per node and peer: link state, restarts, losses, and everything refused.
    fn transport_table(&self) -> Table {
        let mut t = Table::new();
        t.load_preset(UTF8_FULL_CONDENSED).set_header([
            "node",
            "peer",
            "state",
            "rtt ms",
            "sessions",
            "restarts",
            "msgs lost",
            "retx",
            "refused",
            "replayed",
            "forged",
            "strangers / malformed / no session / stale / limited",
        ]);
        for n in &self.transport {
            let node_row = format!(
                "{} / {} / {} / {} / {}",
                n.strangers, n.malformed, n.unknown_session, n.stale_handshakes, n.rate_limited
            );
            for p in &n.peers {
                t.add_row([
                    n.node.clone(),
                    p.peer.clone(),
                    p.state.clone(),
                    format!("{:.3}", p.rtt_ms),
                    p.handshakes.to_string(),
                    p.restarts.to_string(),
                    p.lost_messages.to_string(),
                    p.retransmissions.to_string(),
                    p.refused.to_string(),
                    p.replayed.to_string(),
                    p.forged.to_string(),
                    node_row.clone(),
                ]);
            }
        }
        t
    }
}
