//! A node's HTTP endpoint for its orchestrator and its monitoring: `/metrics` in Prometheus'
//! text format and `/healthz`.
//!
//! The endpoint serves the run's newest metrics snapshot (the one `metrics.json` holds, taken
//! every metrics interval), never the stages themselves: a scrape reads a shared pointer, so a
//! slow or hostile HTTP client cannot stall a stage. It is bounded: at most
//! [`MAX_CONNECTIONS`] connections at once (more are closed at accept), requests of at most
//! 16 KiB of headers read within 5 s, every connection closed after one answer or 10 s.
//!
//! Metric names (labels in braces):
//! - `cloudlight_stage_handled_total`, `cloudlight_stage_ticks_total`,
//!   `cloudlight_stage_blocked_seconds_total`, `cloudlight_stage_busy_seconds{quantile}`
//!   (`node`, `stage`, `kind`);
//! - `cloudlight_edge_messages_total`, `cloudlight_edge_bytes_total`,
//!   `cloudlight_edge_dropped_total`, `cloudlight_edge_depth` (`node`, `edge`), and on cut
//!   edges `cloudlight_edge_wire_bytes_total`, `cloudlight_edge_retransmissions_total` (with
//!   `peer`);
//! - `cloudlight_peer_up`, `cloudlight_peer_rtt_seconds`,
//!   `cloudlight_peer_retransmissions_total`, `cloudlight_peer_lost_messages_total`,
//!   `cloudlight_peer_restarts_total`, `cloudlight_peer_replayed_total`,
//!   `cloudlight_peer_forged_total` (`node`, `peer`);
//! - `cloudlight_transport_strangers_total`, `cloudlight_transport_malformed_total`,
//!   `cloudlight_transport_unknown_session_total`, `cloudlight_transport_rate_limited_total`,
//!   `cloudlight_transport_encodings_total`, `cloudlight_transport_encodings_reused_total`,
//!   `cloudlight_transport_datagrams_sent_total`, `cloudlight_transport_send_calls_total`
//!   (`node`);
//! - `cloudlight_client_indirect_age_seconds{quantile}`,
//!   `cloudlight_client_frame_seconds{quantile}` (`node`, `stage`: every stage whose report
//!   has `age_ms_p50`, i.e. every client);
//! - `cloudlight_run_up` (1 while running), `cloudlight_run_elapsed_seconds`,
//!   `cloudlight_run_scene_time_seconds`.
//!
//! `/healthz` answers 200 `ok` while the run is running and every peer of this process's
//! nodes is up, else 503 with the reason (starting, a peer not up, the run ended or failed).

use std::collections::HashMap;
use std::convert::Infallible;
use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::AtomicU64;
use std::time::Duration;

use http_body_util::Full;
use hyper::body::Bytes;
use hyper::{Request, Response, StatusCode};
use prometheus_client::encoding::text::encode;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::registry::Registry;
use tokio::sync::{Semaphore, watch};

use crate::metrics::{MetricsSnapshot, RunStatus};

/// Most HTTP connections served at once.
pub const MAX_CONNECTIONS: usize = 16;
/// Longest a connection is served.
const CONNECTION_TIMEOUT: Duration = Duration::from_secs(10);
/// Longest wait for a request's headers.
const HEADER_TIMEOUT: Duration = Duration::from_secs(5);
/// Largest request buffered.
const MAX_REQUEST_BYTES: usize = 16 * 1024;

/// What the endpoint knows of the run.
#[derive(Clone, Debug, Default)]
struct Observed {
    snapshot: Option<Arc<MetricsSnapshot>>,
}

/// The HTTP endpoint of a run: give it each snapshot; it serves until dropped.
pub struct Observer {
    tx: watch::Sender<Observed>,
    addr: SocketAddr,
    task: tokio::task::JoinHandle<()>,
}

impl Drop for Observer {
    fn drop(&mut self) {
        self.task.abort();
    }
}

impl Observer {
    /// Listens on `addr` (TCP) and serves `/metrics` and `/healthz` from the snapshots
    /// [`Observer::publish`] is given. Must be called within a tokio runtime.
    pub async fn serve(addr: SocketAddr) -> std::io::Result<Observer> {
        let listener = tokio::net::TcpListener::bind(addr).await?;
        let addr = listener.local_addr()?;
        let (tx, rx) = watch::channel(Observed::default());
        let task = tokio::spawn(accept(listener, rx));
        tracing::info!(%addr, "serving /metrics and /healthz");
        Ok(Observer { tx, addr, task })
    }

    /// Where it listens.
    pub fn local_addr(&self) -> SocketAddr {
        self.addr
    }

    /// Serves `snapshot` from now on.
    pub fn publish(&self, snapshot: &MetricsSnapshot) {
        let snapshot = Some(Arc::new(snapshot.clone()));
        self.tx.send_modify(|o| o.snapshot = snapshot);
    }
}

async fn accept(listener: tokio::net::TcpListener, rx: watch::Receiver<Observed>) {
    let slots = Arc::new(Semaphore::new(MAX_CONNECTIONS));
    loop {
        let Ok((stream, _)) = listener.accept().await else {
            tokio::time::sleep(Duration::from_millis(50)).await;
            continue;
        };
        // Over the limit: closed at once, nothing read or held.
        let Ok(slot) = slots.clone().try_acquire_owned() else {
            continue;
        };
        let rx = rx.clone();
        tokio::spawn(async move {
            let service = hyper::service::service_fn(move |req: Request<hyper::body::Incoming>| {
                let observed = rx.borrow().clone();
                async move { Ok::<_, Infallible>(respond(&req, &observed)) }
            });
            let conn = hyper::server::conn::http1::Builder::new()
                .timer(hyper_util::rt::TokioTimer::new())
                .header_read_timeout(HEADER_TIMEOUT)
                .max_buf_size(MAX_REQUEST_BYTES)
                .keep_alive(false)
                .serve_connection(hyper_util::rt::TokioIo::new(stream), service);
            let _ = tokio::time::timeout(CONNECTION_TIMEOUT, conn).await;
            drop(slot);
        });
    }
}

fn text(status: StatusCode, content_type: &str, body: String) -> Response<Full<Bytes>> {
    let mut r = Response::new(Full::new(Bytes::from(body)));
    *r.status_mut() = status;
    if let Ok(v) = content_type.parse() {
        r.headers_mut().insert(hyper::header::CONTENT_TYPE, v);
    }
    r
}

fn respond(req: &Request<hyper::body::Incoming>, observed: &Observed) -> Response<Full<Bytes>> {
    if req.method() != hyper::Method::GET {
        return text(
            StatusCode::METHOD_NOT_ALLOWED,
            "text/plain",
            "GET /metrics or /healthz\n".into(),
        );
    }
    match req.uri().path() {
        "/metrics" => text(
            StatusCode::OK,
            "application/openmetrics-text; version=1.0.0; charset=utf-8",
            observed
                .snapshot
                .as_deref()
                .map_or_else(String::new, prometheus_text),
        ),
        "/healthz" => match health(observed.snapshot.as_deref()) {
            Ok(()) => text(StatusCode::OK, "text/plain", "ok\n".into()),
            Err(why) => text(
                StatusCode::SERVICE_UNAVAILABLE,
                "text/plain",
                format!("{why}\n"),
            ),
        },
        _ => text(
            StatusCode::NOT_FOUND,
            "text/plain",
            "not found: GET /metrics or /healthz\n".into(),
        ),
    }
}

/// Whether a run in `snapshot` is healthy: running, and every peer up; else why not.
pub fn health(snapshot: Option<&MetricsSnapshot>) -> Result<(), String> {
    let Some(s) = snapshot else {
        return Err("starting: waiting for peers".into());
    };
    match s.status {
        RunStatus::Running => {}
        RunStatus::Finished => return Err("the run has ended".into()),
        RunStatus::Failed => {
            return Err(format!(
                "the run failed: {}",
                s.failure.as_deref().unwrap_or("(no reason given)")
            ));
        }
    }
    let down: Vec<String> = s
        .transport
        .iter()
        .flat_map(|t| {
            t.peers
                .iter()
                .filter(|p| p.state != "up")
                .map(move |p| format!("node `{}`: peer `{}` is {}", t.node, p.peer, p.state))
        })
        .collect();
    if down.is_empty() {
        Ok(())
    } else {
        Err(down.join("; "))
    }
}

type Labels = Vec<(String, String)>;
type FloatGauge = Gauge<f64, AtomicU64>;
type FloatCounter = Counter<f64, AtomicU64>;

fn labels(pairs: &[(&str, &str)]) -> Labels {
    pairs
        .iter()
        .map(|(k, v)| (k.to_string(), v.to_string()))
        .collect()
}

/// Counter and gauge families registered under their names, filled from one snapshot.
#[derive(Default)]
struct Families {
    counters: Vec<(&'static str, &'static str, Family<Labels, FloatCounter>)>,
    gauges: Vec<(&'static str, &'static str, Family<Labels, FloatGauge>)>,
    /// Gauges without labels.
    plain: Vec<(&'static str, &'static str, FloatGauge)>,
}

impl Families {
    fn plain_gauge(&mut self, name: &'static str, help: &'static str, v: f64) {
        let g = FloatGauge::default();
        g.set(v);
        self.plain.push((name, help, g));
    }

    fn counter(&mut self, name: &'static str, help: &'static str, l: &Labels, v: f64) {
        let i = match self.counters.iter().position(|(n, _, _)| *n == name) {
            Some(i) => i,
            None => {
                self.counters.push((name, help, Family::default()));
                self.counters.len() - 1
            }
        };
        self.counters[i].2.get_or_create(l).inc_by(v.max(0.0));
    }

    fn gauge(&mut self, name: &'static str, help: &'static str, l: &Labels, v: f64) {
        let i = match self.gauges.iter().position(|(n, _, _)| *n == name) {
            Some(i) => i,
            None => {
                self.gauges.push((name, help, Family::default()));
                self.gauges.len() - 1
            }
        };
        self.gauges[i].2.get_or_create(l).set(v);
    }
}

/// `snapshot` in Prometheus' text format.
pub fn prometheus_text(snapshot: &MetricsSnapshot) -> String {
    let mut f = Families::default();
    f.plain_gauge(
        "cloudlight_run_up",
        "1 while the run is running",
        f64::from(u8::from(snapshot.status == RunStatus::Running)),
    );
    f.plain_gauge(
        "cloudlight_run_elapsed_seconds",
        "Wall seconds since the run started",
        snapshot.elapsed_s,
    );
    f.plain_gauge(
        "cloudlight_run_scene_time_seconds",
        "Scene time now",
        snapshot.scene_time_s,
    );
    let node_of: HashMap<&str, &str> = snapshot
        .stages
        .iter()
        .map(|s| (s.name.as_str(), s.node.as_str()))
        .collect();
    for s in &snapshot.stages {
        let l = labels(&[("node", &s.node), ("stage", &s.name), ("kind", &s.kind)]);
        f.counter(
            "cloudlight_stage_handled",
            "Input messages a stage handled",
            &l,
            s.handled as f64,
        );
        f.counter(
            "cloudlight_stage_ticks",
            "Ticks a stage ran",
            &l,
            s.ticks as f64,
        );
        f.counter(
            "cloudlight_stage_blocked_seconds",
            "Time a stage waited on full block edges",
            &l,
            s.blocked_s,
        );
        for (q, ms) in [("0.5", s.busy_p50_ms), ("0.99", s.busy_p99_ms)] {
            let mut lq = l.clone();
            lq.push(("quantile".into(), q.into()));
            f.gauge(
                "cloudlight_stage_busy_seconds",
                "Busy time per handler call",
                &lq,
                ms / 1000.0,
            );
        }
        if let Some(r) = &s.report {
            let num = |k: &str| r.get(k).and_then(serde_json::Value::as_f64);
            let l = labels(&[("node", &s.node), ("stage", &s.name)]);
            for (name, help, keys) in [
                (
                    "cloudlight_client_indirect_age_seconds",
                    "Age of the indirect light a client shows",
                    ["age_ms_p50", "age_ms_p99"],
                ),
                (
                    "cloudlight_client_frame_seconds",
                    "A client's time per frame",
                    ["frame_ms_p50", "frame_ms_p99"],
                ),
            ] {
                for (q, key) in [("0.5", keys[0]), ("0.99", keys[1])] {
                    if let (Some(ms), Some(_)) = (num(key), num("age_ms_p50")) {
                        let mut lq = l.clone();
                        lq.push(("quantile".into(), q.into()));
                        f.gauge(name, help, &lq, ms / 1000.0);
                    }
                }
            }
        }
    }
    for e in &snapshot.edges {
        // An edge is counted on the node of the end this process runs: the sending stage,
        // or the receiving one for the receiving half of a cut edge (`... (rx)`).
        let name = e.name.trim_end_matches(" (rx)");
        let (from, to) = name.split_once(" -> ").unwrap_or((name, name));
        let instance = |end: &str| end.rsplit_once('.').map_or(end, |(s, _)| s).to_string();
        let end = if e.name.ends_with(" (rx)") {
            instance(to)
        } else {
            instance(from)
        };
        let node = node_of.get(end.as_str()).copied().unwrap_or("");
        let l = labels(&[("node", node), ("edge", &e.name)]);
        f.counter(
            "cloudlight_edge_messages",
            "Messages through an edge",
            &l,
            e.messages as f64,
        );
        f.counter(
            "cloudlight_edge_bytes",
            "Encoded bytes through an edge",
            &l,
            e.bytes as f64,
        );
        f.counter(
            "cloudlight_edge_dropped",
            "Messages an edge dropped",
            &l,
            e.dropped as f64,
        );
        f.gauge(
            "cloudlight_edge_depth",
            "Messages queued on an edge",
            &l,
            e.depth as f64,
        );
        if let Some(w) = &e.wire {
            let l = labels(&[("node", node), ("edge", &e.name), ("peer", &w.peer)]);
            f.counter(
                "cloudlight_edge_wire_bytes",
                "Bytes a cut edge put on the wire",
                &l,
                w.wire_bytes as f64,
            );
            f.counter(
                "cloudlight_edge_retransmissions",
                "Packets a cut edge sent again",
                &l,
                w.retransmissions as f64,
            );
        }
    }
    for t in &snapshot.transport {
        let l = labels(&[("node", &t.node)]);
        for (name, help, v) in [
            (
                "cloudlight_transport_strangers",
                "Handshake packets from strangers or without proof",
                t.strangers,
            ),
            (
                "cloudlight_transport_malformed",
                "Packets that are not the protocol's",
                t.malformed,
            ),
            (
                "cloudlight_transport_unknown_session",
                "Session packets of no current session",
                t.unknown_session,
            ),
            (
                "cloudlight_transport_rate_limited",
                "Handshake answers withheld by the rate limit",
                t.rate_limited,
            ),
            (
                "cloudlight_transport_encodings",
                "Messages serialized for cut edges (once however many edges send one)",
                t.encodings,
            ),
            (
                "cloudlight_transport_encodings_reused",
                "Sends that reused a message's serialization (fan-out)",
                t.encodings_reused,
            ),
            (
                "cloudlight_transport_datagrams_sent",
                "Datagrams sent",
                t.datagrams_sent,
            ),
            (
                "cloudlight_transport_send_calls",
                "System calls that sent datagrams (several datagrams each with UDP GSO)",
                t.send_calls,
            ),
        ] {
            f.counter(name, help, &l, v as f64);
        }
        for p in &t.peers {
            let l = labels(&[("node", &t.node), ("peer", &p.peer)]);
            f.gauge(
                "cloudlight_peer_up",
                "1 while a peer is up",
                &l,
                f64::from(u8::from(p.state == "up")),
            );
            f.gauge(
                "cloudlight_peer_rtt_seconds",
                "Round trip to a peer",
                &l,
                p.rtt_ms / 1000.0,
            );
            for (name, help, v) in [
                (
                    "cloudlight_peer_retransmissions",
                    "Packets sent again to a peer",
                    p.retransmissions,
                ),
                (
                    "cloudlight_peer_lost_messages",
                    "Messages lost with a peer's sessions",
                    p.lost_messages,
                ),
                (
                    "cloudlight_peer_restarts",
                    "Times a peer restarted",
                    p.restarts,
                ),
                (
                    "cloudlight_peer_replayed",
                    "Packets from a peer seen before",
                    p.replayed,
                ),
                (
                    "cloudlight_peer_forged",
                    "Packets claiming a peer's session that failed their tag",
                    p.forged,
                ),
                (
                    "cloudlight_peer_misaddressed",
                    "Authentic packets of a peer's session from another address, not obeyed",
                    p.misaddressed,
                ),
                (
                    "cloudlight_peer_mismatched",
                    "Nodes of another topology under a live peer's name, refused",
                    p.mismatched,
                ),
            ] {
                f.counter(name, help, &l, v as f64);
            }
        }
    }
    let mut registry = Registry::default();
    for (name, help, family) in f.counters {
        registry.register(name, help, family);
    }
    for (name, help, family) in f.gauges {
        registry.register(name, help, family);
    }
    for (name, help, gauge) in f.plain {
        registry.register(name, help, gauge);
    }
    let mut out = String::new();
    if encode(&mut out, &registry).is_err() {
        out.clear();
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::metrics::{PeerLinkSnapshot, StageSnapshot, TransportSnapshot};

    fn snapshot(peer_state: &str) -> MetricsSnapshot {
        MetricsSnapshot {
            status: RunStatus::Running,
            elapsed_s: 3.5,
            scene_time_s: 3.4,
            failure: None,
            edges: Vec::new(),
            stages: vec![StageSnapshot {
                name: "client[0]".into(),
                kind: "photon_reconstructor".into(),
                node: "home".into(),
                handled: 42,
                ticks: 7,
                busy_p50_ms: 2.0,
                busy_p99_ms: 9.0,
                busy_mean_ms: 3.0,
                blocked_s: 0.25,
                report: Some(serde_json::json!({
                    "age_ms_p50": 35.0, "age_ms_p99": 60.0,
                    "frame_ms_p50": 50.0, "frame_ms_p99": 80.0
                })),
            }],
            transport: vec![TransportSnapshot {
                node: "home".into(),
                strangers: 3,
                peers: vec![PeerLinkSnapshot {
                    peer: "cloud".into(),
                    state: peer_state.into(),
                    rtt_ms: 10.0,
                    forged: 2,
                    ..PeerLinkSnapshot::default()
                }],
                ..TransportSnapshot::default()
            }],
        }
    }

    #[test]
    fn the_text_parses_as_prometheus_and_holds_the_snapshot() {
        let text = prometheus_text(&snapshot("up"));
        let lines = text.lines().map(|l| Ok(l.to_string()));
        let scrape = prometheus_parse::Scrape::parse(lines).expect("Prometheus text");
        let value = |name: &str, pairs: &[(&str, &str)]| -> f64 {
            let s = scrape
                .samples
                .iter()
                .find(|s| {
                    s.metric == name && pairs.iter().all(|(k, v)| s.labels.get(k) == Some(*v))
                })
                .unwrap_or_else(|| panic!("no {name} {pairs:?} in:\n{text}"));
            match s.value {
                prometheus_parse::Value::Counter(v)
                | prometheus_parse::Value::Gauge(v)
                | prometheus_parse::Value::Untyped(v) => v,
                ref other => panic!("{name}: {other:?}"),
            }
        };
        let stage = [("node", "home"), ("stage", "client[0]")];
        assert_eq!(value("cloudlight_stage_handled_total", &stage), 42.0);
        assert_eq!(
            value("cloudlight_stage_blocked_seconds_total", &stage),
            0.25
        );
        let age = [
            ("node", "home"),
            ("stage", "client[0]"),
            ("quantile", "0.99"),
        ];
        assert_eq!(value("cloudlight_client_indirect_age_seconds", &age), 0.06);
        let peer = [("node", "home"), ("peer", "cloud")];
        assert_eq!(value("cloudlight_peer_up", &peer), 1.0);
        assert_eq!(value("cloudlight_peer_forged_total", &peer), 2.0);
        assert_eq!(value("cloudlight_peer_rtt_seconds", &peer), 0.01);
        assert_eq!(
            value("cloudlight_transport_strangers_total", &[("node", "home")]),
            3.0
        );
        assert_eq!(value("cloudlight_run_elapsed_seconds", &[]), 3.5);
    }

    #[test]
    fn health_is_ok_only_while_running_with_every_peer_up_and_says_why_not() {
        assert_eq!(health(Some(&snapshot("up"))), Ok(()));
        assert!(health(None).unwrap_err().contains("starting"));
        let lost = health(Some(&snapshot("lost"))).unwrap_err();
        assert!(lost.contains("peer `cloud` is lost"), "{lost}");
        let mut ended = snapshot("up");
        ended.status = RunStatus::Failed;
        ended.failure = Some("stage `x` failed".into());
        assert!(
            health(Some(&ended))
                .unwrap_err()
                .contains("stage `x` failed")
        );
    }
}
