//! Running a [`Plan`]: build and start every stage instance, run until the duration ends,
//! a stop is requested, the pipeline finishes by itself or a stage fails, then drain and stop.
//!
//! Failure policy (no restarts): the first stage that returns an error or panics fails the
//! run. Its name and error are reported, every edge is closed (so producers blocked on it
//! wake up), every other stage is stopped, and `metrics.json` is still written with status
//! `failed`. A normal end drains first: sources stop ticking, queued messages are handled,
//! and only then are actors stopped (each gets `on_stop`).

use std::future::Future;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use ractor::{Actor, ActorRef};
use tokio::sync::mpsc;
use tokio::task::JoinHandle;

use crate::actor::{
    InputEdge, Names, RunEvent, RunSupervisor, StageActor, StageArgs, StageMsg, SupervisorState,
};
use crate::clock::SceneClock;
use crate::control::RunControl;
use crate::edge::Edge;
use crate::metrics::{EdgeSnapshot, MetricsSnapshot, RunStatus, StageMetrics, WireSnapshot};
use crate::net::NodeNet;

mod wiring;
use crate::stage::{InstanceInfo, OutputPort, StageCtx, StageRegistry, StageSetup};
use crate::topology::Plan;
use wiring::wire_edges;

/// A callback given each periodic metrics snapshot.
pub type ProgressFn = Arc<dyn Fn(&MetricsSnapshot) + Send + Sync>;

/// How a run is carried out.
#[derive(Clone)]
pub struct RunOptions {
    /// Run length; `None` uses the topology's `duration_s`, and without one the run lasts
    /// until stopped, failed or finished by itself.
    pub duration: Option<Duration>,
    /// Folder for `metrics.json` (created if missing); `None` writes nothing.
    pub out_dir: Option<PathBuf>,
    /// Run only the instances placed on this node.
    pub only_node: Option<String>,
    /// How often metrics are snapshotted (written and passed to `on_progress`).
    pub metrics_interval: Duration,
    /// How long a normal end waits for queued messages to be handled.
    pub drain_timeout: Duration,
    /// Called with every periodic snapshot (for progress display).
    pub on_progress: Option<ProgressFn>,
    /// Longest wait for peers at start; `None` uses the topology's `connect_timeout_s`.
    pub connect_timeout: Option<Duration>,
    /// What the node of `only_node` listens on, over its topology's `bind` (its peers still
    /// dial its `address`).
    pub bind: Option<std::net::SocketAddr>,
    /// Serve `/metrics` (Prometheus) and `/healthz` on this TCP address
    /// ([`crate::observe`]), from before the peers are awaited until the run ends.
    pub metrics_listen: Option<std::net::SocketAddr>,
}

impl Default for RunOptions {
    fn default() -> Self {
        RunOptions {
            duration: None,
            out_dir: None,
            only_node: None,
            metrics_interval: Duration::from_secs(2),
            drain_timeout: Duration::from_secs(10),
            on_progress: None,
            connect_timeout: None,
            bind: None,
            metrics_listen: None,
        }
    }
}

/// Why a run ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum EndReason {
    /// The run length elapsed.
    Duration,
    /// A stop was requested (Ctrl-C).
    Stopped,
    /// Every stage stopped ticking and every message was handled.
    Finished,
    /// A stage failed.
    Failed,
}

/// What a run leaves behind.
#[derive(Clone, Debug)]
pub struct RunReport {
    /// Why it ended.
    pub end: EndReason,
    /// Final metrics.
    pub metrics: MetricsSnapshot,
    /// Messages still in the pipeline when actors were stopped (0 after a clean drain).
    pub undrained: i64,
    /// Instances whose actors terminated.
    pub stopped: Vec<String>,
    /// Instances started.
    pub started: usize,
    /// Where `metrics.json` was written.
    pub metrics_path: Option<PathBuf>,
}

/// Why a run could not start or did not end cleanly.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// `only_node` names no node of the topology.
    #[error("node `{0}` is not in the topology")]
    UnknownNode(String),
    /// A node started on its own has cut edges and no secret to share with its peers.
    #[error(
        "node `{0}` is started on its own and its cut edges need the secret every node of the cluster shares: set `secret_env = \"NAME\"` (or `secret_file`, or `secret`) in the topology (`cloudlight run` of the whole topology draws one per run)"
    )]
    NoSecret(String),
    /// The metrics endpoint could not listen (e.g. its address is taken).
    #[error("cannot serve /metrics and /healthz on {addr}: {error}")]
    Metrics {
        /// Address it tried to listen on.
        addr: std::net::SocketAddr,
        /// Why.
        error: String,
    },
    /// A node's transport could not start (e.g. its address is taken).
    #[error("node `{node}` cannot start its transport on {addr}: {error}")]
    Transport {
        /// Node name.
        node: String,
        /// Address it tried to bind.
        addr: std::net::SocketAddr,
        /// Why.
        error: String,
    },
    /// A node's host name does not resolve.
    #[error("{0}")]
    Resolve(String),
    /// A peer address cannot be reached in a multi-process run.
    #[error(
        "node `{node}` needs peer `{peer}`, whose address {addr} has port 0: give fixed ports for multi-process runs"
    )]
    EphemeralPeer {
        /// This node.
        node: String,
        /// The peer.
        peer: String,
        /// Its declared address.
        addr: std::net::SocketAddr,
    },
    /// Peers did not come up in time.
    #[error(
        "peers not reachable after {waited_s:.0} s: {peers} (are their nodes started, with the same topology, cluster and secret?)"
    )]
    PeersUnreachable {
        /// `node -> peer @ address` for each missing peer.
        peers: String,
        /// How long the node waited.
        waited_s: f64,
    },
    /// A stage could not be built or its `on_start` failed.
    #[error("cannot start stage `{stage}`: {error}")]
    Start {
        /// Instance name.
        stage: String,
        /// Why.
        error: String,
    },
    /// A node's transport failed before the run started (e.g. a peer runs another topology).
    #[error("{0}")]
    Link(String),
    /// The network failed while running (a transport thread died, a link stalled, a peer
    /// was lost for good); the run was stopped.
    #[error("{error}")]
    NetworkFailed {
        /// What failed.
        error: String,
        /// What the run left behind.
        report: Box<RunReport>,
    },
    /// A stage failed while running; the run was stopped.
    #[error("stage `{stage}` failed: {error}")]
    StageFailed {
        /// Instance name.
        stage: String,
        /// The error, with its causes.
        error: String,
        /// What the run left behind.
        report: Box<RunReport>,
    },
    /// The output folder could not be written.
    #[error("cannot write run output: {0}")]
    Io(#[from] std::io::Error),
}

/// What stopped a run.
enum Failure {
    /// A stage returned an error or panicked.
    Stage { stage: String, error: String },
    /// A node's transport failed, a link stalled or a peer was lost for good.
    Network(String),
}

impl Failure {
    fn text(&self) -> String {
        match self {
            Failure::Stage { stage, error } => format!("stage `{stage}` failed: {error}"),
            Failure::Network(why) => why.clone(),
        }
    }
}

struct Running {
    name: String,
    kind: String,
    node: String,
    actor: ActorRef<StageMsg>,
    handle: JoinHandle<()>,
    metrics: Arc<StageMetrics>,
}

struct EdgeRun {
    edge: Arc<Edge>,
    cut: bool,
    /// Plan edge index (the transport's edge id) and the node whose transport carries it.
    net: Option<(u32, String)>,
}

/// A started cluster: every local stage instance is running.
pub struct Cluster {
    plan: Plan,
    options: RunOptions,
    clock: SceneClock,
    control: Arc<RunControl>,
    stages: Vec<Running>,
    edges: Vec<EdgeRun>,
    nets: Vec<NodeNet>,
    events: mpsc::UnboundedReceiver<RunEvent>,
    /// Failures reported by the nodes' transports.
    net_failures: mpsc::UnboundedReceiver<String>,
    supervisor: (ActorRef<()>, JoinHandle<()>),
    started: Instant,
    /// The metrics endpoint, when asked for.
    observer: Option<crate::observe::Observer>,
}

impl Cluster {
    /// Builds and starts every instance of the plan (or of `options.only_node`), waits until
    /// all have run `on_start`, then gives each its first tick.
    pub async fn start(
        plan: &Plan,
        registry: &StageRegistry,
        options: RunOptions,
    ) -> Result<Cluster, RunError> {
        let mut plan = plan.clone();
        if let Some(n) = &options.only_node
            && plan.topology.node(n).is_none()
        {
            return Err(RunError::UnknownNode(n.clone()));
        }
        let t = &mut plan.topology;
        if t.secret.is_empty() && !t.insecure && plan.edges.iter().any(|e| e.cut) {
            // Every node in this process: a secret nobody else knows serves them all. A node
            // on its own cannot agree on one with its peers.
            if let Some(n) = &options.only_node {
                return Err(RunError::NoSecret(n.clone()));
            }
            t.secret = cloudlight_transport::crypto::random_secret();
            t.secret_source = crate::topology::SecretSource::Drawn;
        }
        // The endpoint first: an address in use fails the run before anything starts, and
        // the orchestrator hears "starting" while the peers are awaited.
        let observer = match options.metrics_listen {
            Some(addr) => Some(crate::observe::Observer::serve(addr).await.map_err(|e| {
                RunError::Metrics {
                    addr,
                    error: e.to_string(),
                }
            })?),
            None => None,
        };
        let only_node = options.only_node.clone();
        let local = |i: usize| {
            only_node
                .as_ref()
                .is_none_or(|n| &plan.instances[i].node == n)
        };
        let control = Arc::new(RunControl::default());
        let (failures, mut net_failures) = mpsc::unbounded_channel();
        let (edges, nets, clock) = wire_edges(
            &plan,
            &local,
            &control,
            &options,
            failures,
            &mut net_failures,
        )
        .await?;

        let (tx, events) = mpsc::unbounded_channel();
        let names: Names = Arc::default();
        let supervisor = Actor::spawn(
            None,
            RunSupervisor,
            SupervisorState {
                names: names.clone(),
                events: tx,
            },
        )
        .await
        .map_err(|e| RunError::Start {
            stage: "<supervisor>".into(),
            error: e.to_string(),
        })?;

        let mut cluster = Cluster {
            plan: plan.clone(),
            options,
            clock,
            control: control.clone(),
            stages: Vec::new(),
            edges: Vec::new(),
            nets,
            events,
            net_failures,
            supervisor,
            started: Instant::now(),
            observer,
        };
        for (idx, inst) in plan.instances.iter().enumerate() {
            if !local(idx) {
                continue;
            }
            let kind = registry.get(&inst.kind).expect("plan checked every kind");
            let info = InstanceInfo {
                name: Arc::from(inst.name.as_str()),
                stage: inst.stage.clone(),
                kind: inst.kind.clone(),
                node: inst.node.clone(),
                replica: inst.replica,
                replicas: inst.replicas,
            };
            let decl = plan
                .topology
                .stage(&inst.stage)
                .expect("instances come from stages");
            let setup = StageSetup {
                info: info.clone(),
                scene: plan.topology.scene.clone(),
                seed: plan.topology.seed,
                params: decl.params.clone(),
                out_dir: cluster.options.out_dir.clone(),
            };
            let fail = |error: String| RunError::Start {
                stage: inst.name.clone(),
                error,
            };
            let stage = match kind.build(&setup) {
                Ok(s) => s,
                Err(e) => {
                    cluster.abort().await;
                    return Err(fail(format!("{e:#}")));
                }
            };
            let outputs = kind
                .outputs
                .iter()
                .map(|port| OutputPort {
                    name: port.name,
                    ty: port.ty,
                    edges: plan
                        .edges
                        .iter()
                        .zip(&edges)
                        .filter(|(e, _)| e.from == idx && e.from_port == port.name)
                        .filter_map(|(_, w)| w.producer.clone())
                        .collect(),
                    next_seq: 0,
                })
                .collect();
            let inputs = plan
                .edges
                .iter()
                .zip(&edges)
                .filter(|(e, _)| e.to == idx)
                .filter_map(|(e, w)| {
                    w.consumer.clone().map(|edge| InputEdge {
                        edge,
                        port: Arc::from(e.to_port),
                        from: Arc::from(plan.instances[e.from].name.as_str()),
                    })
                })
                .collect();
            let metrics = Arc::new(StageMetrics::default());
            let ctx = StageCtx {
                info,
                seed: plan.topology.seed,
                clock,
                control: control.clone(),
                outputs,
                metrics: metrics.clone(),
                blocked: Duration::ZERO,
            };
            let spawned = Actor::spawn_linked(
                None,
                StageActor,
                StageArgs { stage, ctx, inputs },
                cluster.supervisor.0.get_cell(),
            )
            .await;
            match spawned {
                Ok((actor, handle)) => {
                    crate::toolkit::lock(&names)
                        .insert(actor.get_id(), Arc::from(inst.name.as_str()));
                    cluster.stages.push(Running {
                        name: inst.name.clone(),
                        kind: inst.kind.clone(),
                        node: inst.node.clone(),
                        actor,
                        handle,
                        metrics,
                    });
                }
                Err(e) => {
                    cluster.abort().await;
                    return Err(fail(e.to_string()));
                }
            }
        }
        cluster.edges = edges.into_iter().flat_map(|w| w.runs).collect();
        cluster.started = Instant::now();
        for s in &cluster.stages {
            let _ = s.actor.cast(StageMsg::Tick);
        }
        tracing::info!(
            stages = cluster.stages.len(),
            edges = cluster.edges.len(),
            "cluster started"
        );
        Ok(cluster)
    }

    /// Fault injection for tests of failure handling: makes node `node`'s transport thread
    /// panic. Returns whether this process runs that node's transport.
    #[doc(hidden)]
    pub fn inject_transport_panic(&self, node: &str) -> bool {
        self.nets
            .iter()
            .find(|n| n.node == node)
            .map(|n| n.inject_panic())
            .is_some()
    }

    /// The run-wide scene clock.
    pub fn clock(&self) -> SceneClock {
        self.clock
    }

    /// Current metrics.
    pub fn snapshot(&self, status: RunStatus, failure: Option<String>) -> MetricsSnapshot {
        let elapsed_s = self.started.elapsed().as_secs_f64();
        let net_stats: Vec<_> = self
            .nets
            .iter()
            .map(|n| (n.node.clone(), n.stats()))
            .collect();
        let edges = self
            .edges
            .iter()
            .map(|r| {
                let wire = r.net.as_ref().and_then(|(id, node)| {
                    let net = self.nets.iter().find(|n| &n.node == node)?;
                    let (_, stats) = net_stats.iter().find(|(n, _)| n == node)?;
                    let peer = net.peer_of(*id)?.to_string();
                    let w = stats.edges.get(id).copied().unwrap_or_default();
                    let p = stats.peer(&peer);
                    let extra = net.cut_counters(*id);
                    let oversize = extra.oversize;
                    Some(WireSnapshot {
                        peer,
                        peer_up: p.up,
                        wire_bytes: w.wire_bytes,
                        wire_mbps: if elapsed_s > 0.0 {
                            w.wire_bytes as f64 * 8.0 / elapsed_s / 1e6
                        } else {
                            0.0
                        },
                        retransmissions: w.retransmissions,
                        rtt_ms: p.srtt_s * 1000.0,
                        lost: extra.lost,
                        refused: extra.refused,
                        oversize,
                    })
                });
                let c = r.edge.counters();
                let bytes = c.bytes.load(std::sync::atomic::Ordering::Relaxed);
                EdgeSnapshot {
                    name: r.edge.name().to_string(),
                    policy: r.edge.settings().policy.to_string(),
                    capacity: r.edge.settings().capacity,
                    cut: r.cut,
                    messages: c.messages.load(std::sync::atomic::Ordering::Relaxed),
                    bytes,
                    dropped: c.dropped.load(std::sync::atomic::Ordering::Relaxed),
                    depth: r.edge.depth(),
                    max_depth: c.max_depth.load(std::sync::atomic::Ordering::Relaxed),
                    mbps: if elapsed_s > 0.0 {
                        bytes as f64 * 8.0 / elapsed_s / 1e6
                    } else {
                        0.0
                    },
                    wire,
                }
            })
            .collect();
        let stages = self
            .stages
            .iter()
            .map(|s| s.metrics.snapshot(&s.name, &s.kind, &s.node))
            .collect();
        let transport = self
            .nets
            .iter()
            .zip(&net_stats)
            .map(|(n, (_, stats))| n.snapshot(stats))
            .collect();
        MetricsSnapshot {
            status,
            elapsed_s,
            scene_time_s: self.clock.scene_time_s(),
            failure,
            edges,
            stages,
            transport,
        }
    }

    fn metrics_path(&self) -> Option<PathBuf> {
        self.options
            .out_dir
            .as_ref()
            .map(|d| d.join("metrics.json"))
    }

    fn write_metrics(&self, snap: &MetricsSnapshot) -> std::io::Result<()> {
        if let Some(o) = &self.observer {
            o.publish(snap);
        }
        if let Some(path) = self.metrics_path() {
            if let Some(dir) = path.parent() {
                std::fs::create_dir_all(dir)?;
            }
            snap.write_json(&path)?;
        }
        Ok(())
    }

    /// Runs until the duration ends, `stop` resolves, the pipeline finishes or a stage
    /// fails; then drains (unless failed), stops every actor and writes final metrics.
    pub async fn run(mut self, stop: impl Future<Output = ()>) -> Result<RunReport, RunError> {
        let duration =
            self.options
                .duration
                .or(self.plan.topology.duration_s.map(Duration::from_secs_f64));
        let deadline = duration.map(|d| tokio::time::Instant::now() + d);
        let mut failure: Option<Failure> = None;
        let mut metrics_tick = tokio::time::interval(self.options.metrics_interval);
        metrics_tick.tick().await;
        let mut poll = tokio::time::interval(Duration::from_millis(10));
        tokio::pin!(stop);
        self.write_metrics(&self.snapshot(RunStatus::Running, None))?;
        let mut end = loop {
            tokio::select! {
                _ = async { match deadline { Some(d) => tokio::time::sleep_until(d).await, None => std::future::pending().await } } => break EndReason::Duration,
                _ = &mut stop => break EndReason::Stopped,
                Some(ev) = self.events.recv() => {
                    if let RunEvent::Failed { stage, error } = ev {
                        failure = Some(Failure::Stage { stage: stage.to_string(), error });
                        break EndReason::Failed;
                    }
                }
                Some(why) = self.net_failures.recv() => {
                    failure = Some(Failure::Network(why));
                    break EndReason::Failed;
                }
                _ = metrics_tick.tick() => {
                    let snap = self.snapshot(RunStatus::Running, None);
                    self.write_metrics(&snap)?;
                    if let Some(p) = &self.options.on_progress { p(&snap); }
                }
                _ = poll.tick() => {
                    let local: Vec<String> = self.nets.iter().map(|n| n.node.clone()).collect();
                    if self.control.is_finished() && !self.nets.iter().any(|n| n.has_live_upstream(&local)) {
                        break EndReason::Finished;
                    }
                }
            }
        };
        // A network failure reported in the same instant as the end it caused (an upstream
        // peer that left after failing also ends this node's input) must not be lost to the
        // order `select!` happened to pick: the failure is sent before the peer is marked
        // gone, so it is already queued here (seen in CI: exit 0 instead of 5).
        if end == EndReason::Finished
            && let Ok(why) = self.net_failures.try_recv()
        {
            failure = Some(Failure::Network(why));
            end = EndReason::Failed;
        }
        tracing::info!(?end, "run ending");
        self.control.begin_stopping();
        for n in &self.nets {
            n.poke();
        }
        if end != EndReason::Failed
            && let Some(f) = self.drain().await
        {
            failure = Some(f);
            end = EndReason::Failed;
        }
        if failure.is_none() {
            failure = self.lost_upstream().map(Failure::Network);
        }
        if failure.is_none() {
            let snap = self.snapshot(RunStatus::Running, None);
            failure = undelivered_cut_edges(&snap).map(Failure::Network);
        }
        let undrained = self.control.pending();
        if let Some(f) = &failure {
            tracing::error!("{}; stopping the run", f.text());
        }
        let stopped = self.stop_all(failure.is_some()).await;
        let (status, fail_text) = match &failure {
            Some(f) => (RunStatus::Failed, Some(f.text())),
            None => (RunStatus::Finished, None),
        };
        let metrics = self.snapshot(status, fail_text);
        self.write_metrics(&metrics)?;
        let report = RunReport {
            end,
            metrics,
            undrained,
            stopped,
            started: self.stages.len(),
            metrics_path: self.metrics_path(),
        };
        self.supervisor.0.stop(None);
        match failure {
            Some(Failure::Stage { stage, error }) => Err(RunError::StageFailed {
                stage,
                error,
                report: Box::new(report),
            }),
            Some(Failure::Network(error)) => Err(RunError::NetworkFailed {
                error,
                report: Box::new(report),
            }),
            None => Ok(report),
        }
    }

    /// Sources no longer tick: lets every queued message be handled, up to the drain
    /// timeout; a failure meanwhile ends the drain.
    async fn drain(&mut self) -> Option<Failure> {
        let drain_deadline = tokio::time::Instant::now() + self.options.drain_timeout;
        let mut poll = tokio::time::interval(Duration::from_millis(10));
        loop {
            if self.control.is_drained() {
                return None;
            }
            if tokio::time::Instant::now() >= drain_deadline {
                tracing::warn!(pending = self.control.pending(), "drain timed out");
                return None;
            }
            tokio::select! {
                Some(ev) = self.events.recv() => {
                    if let RunEvent::Failed { stage, error } = ev {
                        return Some(Failure::Stage { stage: stage.to_string(), error });
                    }
                }
                Some(why) = self.net_failures.recv() => return Some(Failure::Network(why)),
                _ = poll.tick() => {}
            }
        }
    }

    /// A node whose upstream peer is lost at the end got only part of what was sent.
    fn lost_upstream(&self) -> Option<String> {
        let lost: Vec<String> = self
            .nets
            .iter()
            .flat_map(|n| {
                n.lost_upstream()
                    .into_iter()
                    .map(move |p| format!("node `{}`: upstream peer `{p}` is lost", n.node))
            })
            .collect();
        (!lost.is_empty())
            .then(|| format!("{} (the run ended without it coming back)", lost.join("; ")))
    }

    /// Closes every edge and stops every actor, then the transports (telling peers whether
    /// the run `failed`); returns the instances that terminated.
    async fn stop_all(&mut self, failed: bool) -> Vec<String> {
        if self.control.pending() != 0 {
            // Producers may be blocked on consumers that will never run again.
            for e in &self.edges {
                e.edge.close();
            }
        }
        for s in &self.stages {
            s.actor.stop(None);
        }
        let mut stopped = Vec::new();
        for s in &mut self.stages {
            match tokio::time::timeout(Duration::from_secs(5), &mut s.handle).await {
                Ok(_) => stopped.push(s.name.clone()),
                Err(_) => {
                    tracing::warn!(stage = %s.name, "did not stop within 5 s; killing it");
                    s.actor.kill();
                    if tokio::time::timeout(Duration::from_secs(1), &mut s.handle)
                        .await
                        .is_ok()
                    {
                        stopped.push(s.name.clone());
                    }
                }
            }
        }
        for e in &self.edges {
            e.edge.close();
        }
        for n in &mut self.nets {
            n.shutdown(failed);
        }
        stopped
    }

    async fn abort(&mut self) {
        self.control.begin_stopping();
        self.stop_all(true).await;
        self.supervisor.0.stop(None);
    }
}

/// Cut edges whose sending half got messages and delivered none of them (each too large for
/// the transport, or lost with its peer): a run that carried nothing across a cut has not
/// succeeded.
fn undelivered_cut_edges(snap: &MetricsSnapshot) -> Option<String> {
    let bad: Vec<String> = snap
        .edges
        .iter()
        .filter(|e| e.cut && !e.name.ends_with(" (rx)"))
        .filter_map(|e| {
            let w = e.wire.as_ref()?;
            (e.messages > 0 && w.oversize + w.lost >= e.messages).then(|| {
                format!(
                    "cut edge `{}` delivered none of its {} messages ({} over the transport's \
                     message limit, {} lost with peer `{}`)",
                    e.name, e.messages, w.oversize, w.lost, w.peer
                )
            })
        })
        .collect();
    (!bad.is_empty()).then(|| bad.join("; "))
}

/// Starts `plan` and runs it to the end (see [`Cluster::run`]).
pub async fn run(
    plan: &Plan,
    registry: &StageRegistry,
    options: RunOptions,
    stop: impl Future<Output = ()>,
) -> Result<RunReport, RunError> {
    Cluster::start(plan, registry, options)
        .await?
        .run(stop)
        .await
}
