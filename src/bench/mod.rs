//! The benchmark harness: the paper's Table 2, scaling over client counts (Figures 3–5), the
//! speed/accuracy trade and the client's frame, for any technique that provides a
//! [`Technique`] descriptor.
//!
//! A descriptor supplies its stage graph for N clients ([`StageGraph`]: stages shared on
//! `cloud`, stages replicated once per client on `cloud` or `home`, so the cut lies wherever
//! the graph crosses from one to the other), the Table 2 column its stage reports fill, its
//! scaling row, its quality sweep and its client frame. Table 2 and scaling run the graph as a
//! real topology ([`TopologySpec`], checked like a file) in one process — each node on its own
//! UDP socket on loopback — and read the stages' typed reports. The client's frame and the
//! quality sweep call the kernels directly. Every table prints the paper's figure beside ours
//! where the paper has one. Adding a technique to the benchmarks is one descriptor module and
//! one line of [`with_technique`].
//!
//! A technique's knobs are its `Options`, a serde type: the CLI sets them by name
//! (`--set key=value`, or a shortcut flag such as `--photons`) over the defaults, and an
//! unknown knob is an error that lists the known ones ([`options_from`]).
//!
//! The CLI only parses options and prints; everything measured is here, so tests link it.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::Context;
use cloudlight_render::raster::Raster;
use cloudlight_render::{BvhKind, SceneBvh};
use cloudlight_runtime::metrics::EdgeSnapshot;
use cloudlight_runtime::{MetricsSnapshot, RunOptions, TopologySpec};
use cloudlight_scenes::glam::Vec3;
use cloudlight_scenes::{Camera, Scene};
use cloudlight_transport::LinkProfile;
use serde::Serialize;
use serde::de::DeserializeOwned;

use client::{ClientBench, ClientBenchOptions};

pub mod baseline;
pub mod client;
pub mod irradiance;
pub mod paper;
pub mod photons;
pub mod reference_cache;
pub mod table;
pub mod video;
pub mod voxels;

/// Names of the techniques the benchmarks know, implemented or not (the full-frame baseline
/// `photons-video` among them).
pub const TECHNIQUES: [&str; 4] = [
    photons::Photons::NAME,
    baseline::PhotonsVideo::NAME,
    irradiance::Irradiance::NAME,
    voxels::Voxels::NAME,
];

/// Something to do with one technique's descriptor: [`with_technique`] calls
/// [`Visit::visit`] with the descriptor a name stands for.
pub trait Visit {
    /// What it returns.
    type Out;
    /// Does it with technique `T`.
    fn visit<T: Technique>(self) -> Self::Out;
}

/// Calls `v` with the technique named `name`; an error says why when there is none.
pub fn with_technique<V: Visit>(name: &str, v: V) -> anyhow::Result<V::Out> {
    match name {
        photons::Photons::NAME => Ok(v.visit::<photons::Photons>()),
        baseline::PhotonsVideo::NAME => Ok(v.visit::<baseline::PhotonsVideo>()),
        irradiance::Irradiance::NAME => Ok(v.visit::<irradiance::Irradiance>()),
        voxels::Voxels::NAME => Ok(v.visit::<voxels::Voxels>()),
        other => anyhow::bail!(
            "unknown technique `{other}` (one of: {})",
            TECHNIQUES.join(", ")
        ),
    }
}

/// The technique named `name` if its benchmarks exist; otherwise why not.
pub fn require_technique(name: &str) -> anyhow::Result<()> {
    struct Exists;
    impl Visit for Exists {
        type Out = ();
        fn visit<T: Technique>(self) {}
    }
    with_technique(name, Exists)
}

/// What every cluster benchmark sets: the scene, how long, the link, the seed.
#[derive(Clone, Debug, PartialEq)]
pub struct ClusterOptions {
    /// Scene spec.
    pub scene: String,
    /// Run length, seconds.
    pub seconds: f64,
    /// Link between the cloud and the client node (`None`: plain loopback).
    pub link: Option<LinkProfile>,
    /// Run seed.
    pub seed: u64,
}

/// The machinery a Table 2 column uses: the async runtime its cluster runs on and the
/// raster that times the client's pass.
pub struct Bench<'a> {
    /// The runtime.
    pub runtime: &'a tokio::runtime::Runtime,
    /// The raster.
    pub raster: &'a Raster,
}

/// The quality sweep's settings every technique shares.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct QualityCommon {
    /// The view: the index of one of the scene's camera paths or
    /// `px,py,pz:tx,ty,tz[:fov_deg]` ([`cloudlight_scenes::camera`]).
    pub camera: String,
    /// Reference samples per pixel.
    pub spp: u32,
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Updates per second the Mbps assume (capped by the update time).
    pub rate_hz: f64,
    /// Seed of the technique's random streams.
    pub seed: u64,
    /// Frames of the still view the client's image averages, each jittered over its pixels
    /// (1: through their centres).
    pub still_frames: u32,
}

/// A sweep: knobs and the values each takes (the technique says how they combine).
pub type Sweep = Vec<(String, Vec<toml::Value>)>;

/// A technique as the benchmarks see it.
pub trait Technique: 'static {
    /// Name on the command line.
    const NAME: &'static str;
    /// Its knobs (budget, batch size, interval, ...): every field has a default, and the
    /// CLI sets them by name.
    type Options: Clone + Default + Serialize + DeserializeOwned;
    /// One scene's Table 2 column.
    type Column: Serialize;

    /// The stages of a cluster benchmark. Its per-client stage on `home` is named
    /// [`CLIENT`]: the harness reads the clients' reports from it.
    fn graph(options: &Self::Options) -> anyhow::Result<StageGraph>;

    /// One row of the scaling table, from the stage reports of a run with `clients`.
    fn scaling_row(run: &ClusterRun, clients: usize) -> anyhow::Result<ScalingRow>;

    /// The paper's scaling figure this technique is compared with: (figure, what it shows).
    fn scaling_figure() -> (&'static str, &'static str);

    /// One Table 2 column: the cluster of `cluster` run with one client, and the client's
    /// pass at `size` on the raster.
    fn table2_column(
        bench: &Bench,
        options: &Self::Options,
        cluster: &ClusterOptions,
        size: (u32, u32),
    ) -> anyhow::Result<Self::Column>;

    /// The Table 2 block of `columns`, with the paper's figures beside ours.
    fn table2_markdown(columns: &[Self::Column]) -> String;

    /// What the Table 2 block measured, in a sentence or two (printed under it).
    fn table2_note(options: &Self::Options, size: (u32, u32), adapter: &str) -> String;

    /// The client's frame with the technique's pass alone on the machine.
    fn client_frame(
        raster: &Raster,
        scene: &Scene,
        options: &Self::Options,
        frame: ClientBenchOptions,
    ) -> anyhow::Result<ClientBench> {
        let _ = (raster, scene, options, frame);
        anyhow::bail!("`{}` has no client benchmark (`bench client`)", Self::NAME)
    }

    /// The sweep [`Technique::quality`] runs when none is given.
    fn default_sweep() -> Sweep {
        Vec::new()
    }

    /// The speed/accuracy sweep on `scene`: prints its table and writes `quality.json`,
    /// `quality.png` and the images (EXR, and a PNG beside the reference with its error map)
    /// to `out`; returns the JSON report.
    fn quality(
        raster: &Raster,
        scene: &str,
        common: &QualityCommon,
        options: &Self::Options,
        sweep: &Sweep,
        out: &Path,
    ) -> anyhow::Result<serde_json::Value> {
        let _ = (raster, scene, common, options, sweep, out);
        anyhow::bail!(
            "`{}` has no quality benchmark (`bench quality`)",
            Self::NAME
        )
    }
}

/// Name of the per-client stage on `home` whose reports are the clients'.
pub const CLIENT: &str = "client";

/// Which side of the cut a per-client stage runs on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Side {
    /// The `cloud` node.
    Cloud,
    /// The `home` node (the clients' machine).
    Home,
}

impl Side {
    fn node(self) -> &'static str {
        match self {
            Side::Cloud => "cloud",
            Side::Home => "home",
        }
    }
}

/// How a stage of a [`StageGraph`] is placed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Placement {
    /// One instance on `cloud`, shared by every client: its cost must not grow with them.
    Shared,
    /// One replica per client on this side.
    PerClient(Side),
}

/// One stage of a [`StageGraph`].
#[derive(Clone, Debug, PartialEq)]
pub struct GraphStage {
    /// Stage name.
    pub name: String,
    /// Its kind.
    pub kind: String,
    /// Where it runs.
    pub placement: Placement,
    /// Its `params`.
    pub params: toml::Table,
}

/// A technique's stages for a cluster benchmark, independent of the client count: stages
/// shared on `cloud`, stages replicated per client, and the edges between them (`from[.port]`
/// → `to`; an edge between two per-client stages joins replica *i* to replica *i*, one from
/// a shared stage fans out to every replica).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct StageGraph {
    /// Techniques the topology declares.
    pub techniques: Vec<String>,
    /// The stages.
    pub stages: Vec<GraphStage>,
    /// The edges.
    pub edges: Vec<(String, String)>,
}

/// Stage name of an edge end `stage[.port]`.
fn stage_of(end: &str) -> &str {
    end.split('.').next().unwrap_or(end)
}

impl StageGraph {
    /// An empty graph of these techniques.
    pub fn new(techniques: &[&str]) -> Self {
        StageGraph {
            techniques: techniques.iter().map(|t| t.to_string()).collect(),
            ..StageGraph::default()
        }
    }

    /// Adds a stage.
    pub fn stage(
        mut self,
        name: &str,
        kind: &str,
        placement: Placement,
        params: toml::Table,
    ) -> Self {
        self.stages.push(GraphStage {
            name: name.into(),
            kind: kind.into(),
            placement,
            params,
        });
        self
    }

    /// Adds an edge `from[.port]` → `to`.
    pub fn edge(mut self, from: &str, to: &str) -> Self {
        self.edges.push((from.into(), to.into()));
        self
    }

    fn find(&self, end: &str) -> anyhow::Result<&GraphStage> {
        let name = stage_of(end);
        self.stages
            .iter()
            .find(|s| s.name == name)
            .with_context(|| format!("edge end `{end}` names no stage of the graph"))
    }

    /// The edges that cross the network (from a stage on `cloud` to one on `home`).
    pub fn cut(&self) -> Vec<&(String, String)> {
        let home = |end: &str| {
            self.find(end)
                .is_ok_and(|s| s.placement == Placement::PerClient(Side::Home))
        };
        self.edges
            .iter()
            .filter(|(from, to)| !home(from) && home(to))
            .collect()
    }

    /// The topology for `clients` clients: shared stages on `cloud`, each per-client stage
    /// replicated `clients` times on its side (with none, the per-client stages and their
    /// edges are left out), the link between `cloud` and `home`.
    pub fn topology(
        &self,
        name: &str,
        cluster: &ClusterOptions,
        clients: usize,
    ) -> anyhow::Result<TopologySpec> {
        let any_port = "127.0.0.1:0".parse().expect("a valid address");
        let techniques: Vec<&str> = self.techniques.iter().map(String::as_str).collect();
        let mut spec = TopologySpec::new(&techniques, &cluster.scene)
            .node("cloud", any_port)
            .node("home", any_port);
        let present = |s: &GraphStage| s.placement == Placement::Shared || clients > 0;
        for s in self.stages.iter().filter(|s| present(s)) {
            let nodes = match s.placement {
                Placement::Shared => vec!["cloud"],
                Placement::PerClient(side) => vec![side.node(); clients],
            };
            spec = spec.stage(&s.name, &s.kind, &nodes, s.params.clone());
        }
        for (from, to) in &self.edges {
            if present(self.find(from)?) && present(self.find(to)?) {
                spec = spec.edge(from, to, None, None);
            }
        }
        spec.seed = cluster.seed;
        spec.duration_s = Some(cluster.seconds);
        spec.cluster = format!("{name}-bench");
        spec.secret = format!("{name}-bench");
        if let Some(link) = cluster.link {
            spec = spec.link("cloud", "home", link);
        }
        Ok(spec)
    }
}

/// The topology of a cluster benchmark of `T` with `clients` clients.
pub fn cluster_topology<T: Technique>(
    options: &T::Options,
    cluster: &ClusterOptions,
    clients: usize,
) -> anyhow::Result<TopologySpec> {
    T::graph(options)?.topology(T::NAME, cluster, clients)
}

/// What one cluster run measured.
pub struct ClusterRun {
    /// The run's final metrics (edges, stages, their reports).
    pub metrics: MetricsSnapshot,
    /// Clients it ran.
    pub clients: usize,
}

impl ClusterRun {
    /// The report stage `name` (one instance) sent last, as `R`.
    pub fn report<R: DeserializeOwned>(&self, name: &str) -> anyhow::Result<R> {
        stage_report(&self.metrics, name)
    }

    /// The reports of the per-client stage `name`, in replica order.
    pub fn per_client<R: DeserializeOwned>(&self, name: &str) -> anyhow::Result<Vec<R>> {
        (0..self.clients)
            .map(|i| stage_report(&self.metrics, &replica_name(name, i, self.clients)))
            .collect()
    }

    /// Total wire megabits per second leaving the cloud (headers and retransmissions in).
    pub fn wire_mbps(&self) -> f64 {
        wire_mbps(&self.metrics)
    }

    /// Total payload megabits per second leaving the cloud.
    pub fn payload_mbps(&self) -> f64 {
        payload_mbps(&self.metrics)
    }
}

/// The cut edges' sending ends (in a benchmark's cluster: what leaves the cloud).
fn sending_edges(m: &MetricsSnapshot) -> impl Iterator<Item = &EdgeSnapshot> {
    m.edges
        .iter()
        .filter(|e| e.wire.is_some() && !e.name.ends_with("(rx)"))
}

/// Total wire megabits per second on the cut edges (headers and retransmissions in).
pub fn wire_mbps(m: &MetricsSnapshot) -> f64 {
    sending_edges(m)
        .filter_map(|e| e.wire.as_ref())
        .map(|w| w.wire_mbps)
        .fold(0.0, |a, b| a + b)
}

/// Total payload megabits per second on the cut edges.
pub fn payload_mbps(m: &MetricsSnapshot) -> f64 {
    sending_edges(m).map(|e| e.mbps).fold(0.0, |a, b| a + b)
}

/// The report stage `name` sent last, as `R`.
pub fn stage_report<R: DeserializeOwned>(m: &MetricsSnapshot, name: &str) -> anyhow::Result<R> {
    let value = m
        .stages
        .iter()
        .find(|s| s.name == name)
        .and_then(|s| s.report.clone())
        .with_context(|| format!("stage `{name}` sent no report"))?;
    serde_json::from_value(value).with_context(|| format!("reading the report of `{name}`"))
}

/// Plans `spec` (named `file` in errors) and runs it in this process for `seconds`; the
/// run's final metrics.
pub fn run_spec(
    runtime: &tokio::runtime::Runtime,
    spec: &TopologySpec,
    file: &str,
    seconds: f64,
) -> anyhow::Result<MetricsSnapshot> {
    let registry = cloudlight_actors::registry();
    let plan = spec
        .plan(file, &registry)
        .map_err(|e| anyhow::anyhow!("{e}\n{}", spec.to_toml()))?;
    let report = runtime
        .block_on(cloudlight_runtime::run(
            &plan,
            &registry,
            RunOptions {
                duration: Some(Duration::from_secs_f64(seconds)),
                ..RunOptions::default()
            },
            std::future::pending(),
        ))
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    Ok(report.metrics)
}

/// Name of replica `i` of a stage `name` with `n` replicas.
pub fn replica_name(name: &str, i: usize, n: usize) -> String {
    if n == 1 {
        name.to_string()
    } else {
        format!("{name}[{i}]")
    }
}

/// Runs `T`'s cluster with `clients` clients for `cluster.seconds`.
pub fn run_cluster<T: Technique>(
    runtime: &tokio::runtime::Runtime,
    options: &T::Options,
    cluster: &ClusterOptions,
    clients: usize,
) -> anyhow::Result<ClusterRun> {
    let spec = cluster_topology::<T>(options, cluster, clients)?;
    let file = format!("<{} benchmark>", T::NAME);
    let metrics = run_spec(runtime, &spec, &file, cluster.seconds)?;
    Ok(ClusterRun { metrics, clients })
}

/// `T`'s options: its defaults with `knobs` set over them. A knob the options lack, or a
/// value of the wrong type, is an error naming the knob and listing the known ones.
pub fn options_from<T: Technique>(knobs: &toml::Table) -> anyhow::Result<T::Options> {
    let mut table = toml::Table::try_from(T::Options::default())
        .with_context(|| format!("the default options of `{}`", T::NAME))?;
    for (key, value) in knobs {
        let Some(default) = table.get(key) else {
            anyhow::bail!(
                "`{}` has no knob `{key}` (its knobs: {})",
                T::NAME,
                knobs_help::<T>()
            );
        };
        let value = match (default, value) {
            (toml::Value::Float(_), toml::Value::Integer(i)) => toml::Value::Float(*i as f64),
            _ => value.clone(),
        };
        table.insert(key.clone(), value);
    }
    table.try_into().map_err(|e: toml::de::Error| {
        anyhow::anyhow!(
            "options of `{}`: {} (its knobs: {})",
            T::NAME,
            e.message(),
            knobs_help::<T>()
        )
    })
}

/// `T`'s knobs with their defaults, `key = value, ...`.
pub fn knobs_help<T: Technique>() -> String {
    toml::Table::try_from(T::Options::default())
        .map(|t| {
            t.iter()
                .map(|(k, v)| format!("{k} = {v}"))
                .collect::<Vec<_>>()
                .join(", ")
        })
        .unwrap_or_default()
}

/// Parses a knob `key=value`; the value is TOML (`3`, `2.5`, `true`, `"x"`) or else a
/// bare string.
pub fn parse_knob(s: &str) -> Result<(String, toml::Value), String> {
    let (key, value) = s
        .split_once('=')
        .ok_or_else(|| format!("`{s}` is not `key=value`"))?;
    let key = key.trim();
    if key.is_empty() {
        return Err(format!("`{s}` names no knob"));
    }
    Ok((key.to_string(), parse_value(value.trim())))
}

fn parse_value(s: &str) -> toml::Value {
    format!("v = {s}")
        .parse::<toml::Table>()
        .ok()
        .and_then(|mut t| t.remove("v"))
        .unwrap_or_else(|| toml::Value::String(s.to_string()))
}

/// Parses a sweep `key=v1,v2,...`.
pub fn parse_sweep(s: &str) -> Result<(String, Vec<toml::Value>), String> {
    let (key, values) = s
        .split_once('=')
        .ok_or_else(|| format!("`{s}` is not `key=v1,v2,...`"))?;
    let values: Vec<toml::Value> = values
        .split(',')
        .map(str::trim)
        .filter(|v| !v.is_empty())
        .map(parse_value)
        .collect();
    if key.trim().is_empty() || values.is_empty() {
        return Err(format!("`{s}` names no knob or no value"));
    }
    Ok((key.trim().to_string(), values))
}

/// Every combination of `sweep`'s values set over `knobs`, as `T`'s options, in order (the
/// last knob varies fastest).
pub fn expand<T: Technique>(knobs: &toml::Table, sweep: &Sweep) -> anyhow::Result<Vec<T::Options>> {
    let mut points = vec![knobs.clone()];
    for (key, values) in sweep {
        points = points
            .iter()
            .flat_map(|p| {
                values.iter().map(move |v| {
                    let mut p = p.clone();
                    p.insert(key.clone(), v.clone());
                    p
                })
            })
            .collect();
    }
    points.iter().map(options_from::<T>).collect()
}

/// Knob values that differ per scene of a Table 2 run: scene `i` takes value `i` of each
/// list, the last repeating.
pub fn knobs_for_scene(knobs: &toml::Table, per_scene: &Sweep, i: usize) -> toml::Table {
    let mut k = knobs.clone();
    for (key, values) in per_scene {
        if let Some(v) = values.get(i).or(values.last()) {
            k.insert(key.clone(), v.clone());
        }
    }
    k
}

/// `T`'s Table 2 block: one column per scene (its knobs from [`knobs_for_scene`]).
pub fn table2<T: Technique>(
    bench: &Bench,
    scenes: &[String],
    knobs: &toml::Table,
    per_scene: &Sweep,
    cluster: &ClusterOptions,
    size: (u32, u32),
) -> anyhow::Result<Vec<T::Column>> {
    scenes
        .iter()
        .enumerate()
        .map(|(i, scene)| {
            let options = options_from::<T>(&knobs_for_scene(knobs, per_scene, i))?;
            let cluster = ClusterOptions {
                scene: scene.clone(),
                ..cluster.clone()
            };
            T::table2_column(bench, &options, &cluster, size)
        })
        .collect()
}

/// One row of a scaling benchmark.
#[derive(Clone, Debug, Default, PartialEq, Serialize, serde::Deserialize)]
pub struct ScalingRow {
    /// Clients.
    pub clients: usize,
    /// Server time per update, mean, ms.
    pub server_update_ms: f64,
    /// Of which the lighting kernel (trace, gather, ...), ms.
    pub server_kernel_ms: f64,
    /// Server time paid once per client per frame (a frame rendered and encoded in the
    /// cloud), p50 averaged over clients, ms; `None` where nothing is per client.
    pub server_per_client_ms: Option<f64>,
    /// Updates done.
    pub updates: u64,
    /// Wire megabits per second leaving the cloud.
    pub total_wire_mbps: f64,
    /// Payload megabits per second leaving the cloud.
    pub total_payload_mbps: f64,
    /// Age of indirect light, p50 averaged over clients, ms.
    pub age_ms_p50_mean: f64,
    /// Worst client's age p99, ms.
    pub age_ms_p99_max: f64,
    /// Clients that showed indirect light.
    pub clients_showing_indirect: usize,
}

/// What a scaling row says of the server.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ServerCost {
    /// Time per update, mean, ms.
    pub update_ms: f64,
    /// Of which the lighting kernel, ms.
    pub kernel_ms: f64,
    /// Updates done.
    pub updates: u64,
    /// Server time paid per client frame, ms (`None`: nothing is per client).
    pub per_client_ms: Option<f64>,
}

impl ScalingRow {
    /// The row of `run` with `clients`: the server's figures, the cut's megabits per second
    /// and the ages of the light the clients (`shown`, their reports) showed.
    pub fn of<R>(
        run: &ClusterRun,
        clients: usize,
        server: ServerCost,
        shown: &[cloudlight_actors::client::ClientReport<R>],
    ) -> ScalingRow {
        ScalingRow {
            clients,
            server_update_ms: server.update_ms,
            server_kernel_ms: server.kernel_ms,
            server_per_client_ms: server.per_client_ms,
            updates: server.updates,
            total_wire_mbps: run.wire_mbps(),
            total_payload_mbps: run.payload_mbps(),
            age_ms_p50_mean: mean(shown.iter().map(|c| c.age_ms_p50)),
            age_ms_p99_max: shown.iter().map(|c| c.age_ms_p99).fold(0.0, f64::max),
            clients_showing_indirect: shown.iter().filter(|c| c.indirect_shown).count(),
        }
    }
}

/// A frame rendered and encoded in the cloud per client: frame p50 + encode p50, averaged
/// over the clients (`None` without clients).
pub fn frame_and_encode_ms<R>(
    render: &[cloudlight_actors::client::ClientReport<R>],
    encode: &[cloudlight_actors::video_encoder::EncoderReport],
) -> Option<f64> {
    (!render.is_empty()).then(|| {
        mean(
            render
                .iter()
                .zip(encode)
                .map(|(r, e)| r.frame_ms_p50 + e.encode_ms_p50),
        )
    })
}

/// The mean of `values` (0 when empty).
pub fn mean(values: impl IntoIterator<Item = f64>) -> f64 {
    let (sum, n) = values
        .into_iter()
        .fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
    sum / n.max(1) as f64
}

/// The scaling table over `counts` clients; writes `scaling.json` and `scaling.png` to
/// `out` and returns the rows.
pub fn scaling<T: Technique>(
    runtime: &tokio::runtime::Runtime,
    options: &T::Options,
    cluster: &ClusterOptions,
    counts: &[usize],
    out: &Path,
) -> anyhow::Result<Vec<ScalingRow>> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let mut rows = Vec::new();
    for &n in counts {
        eprintln!("{n} clients: running for {} s...", cluster.seconds);
        let run = run_cluster::<T>(runtime, options, cluster, n)?;
        rows.push(T::scaling_row(&run, n)?);
    }
    let per_client = rows.iter().any(|r| r.server_per_client_ms.is_some());
    // Figure 3's question: what a client costs the server, its share of the common work
    // beside what is its own.
    let shared = |r: &ScalingRow| r.server_update_ms / r.clients.max(1) as f64;
    let mut header = vec![
        "clients",
        "server ms / update",
        "kernel ms",
        "shared ms per client",
    ];
    if per_client {
        header.push("server ms per client frame (p50)");
    }
    header.extend([
        "total Mbps (wire)",
        "age p50 ms (mean over clients)",
        "age p99 ms (worst)",
        "clients showing indirect",
    ]);
    let mut t = table::Markdown::new(&header);
    for r in &rows {
        let mut cells = vec![
            r.clients.to_string(),
            format!("{:.2}", r.server_update_ms),
            format!("{:.2}", r.server_kernel_ms),
            if r.clients == 0 {
                "—".into()
            } else {
                format!("{:.2}", shared(r))
            },
        ];
        if per_client {
            cells.push(
                r.server_per_client_ms
                    .map_or("—".into(), |ms| format!("{ms:.2}")),
            );
        }
        cells.extend([
            format!("{:.1}", r.total_wire_mbps),
            format!("{:.0}", r.age_ms_p50_mean),
            format!("{:.0}", r.age_ms_p99_max),
            r.clients_showing_indirect.to_string(),
        ]);
        t.row(cells);
    }
    println!("{}", t.render());
    let (figure, shows) = T::scaling_figure();
    println!("paper ({figure}): {shows}");
    let report = serde_json::json!({
        "technique": T::NAME,
        "cluster": { "scene": cluster.scene, "seconds": cluster.seconds, "link": cluster.link, "seed": cluster.seed },
        "options": options,
        "rows": rows,
        "paper": shows,
    });
    let json = out.join("scaling.json");
    std::fs::write(&json, serde_json::to_string_pretty(&report)?)
        .with_context(|| format!("writing {}", json.display()))?;
    let series = |f: fn(&ScalingRow) -> f64| -> Vec<(f64, f64)> {
        rows.iter().map(|r| (r.clients as f64, f(r))).collect()
    };
    let mut lines = vec![
        ("server ms per update", series(|r| r.server_update_ms)),
        ("total Mbps (wire)", series(|r| r.total_wire_mbps)),
        (
            "age of indirect light, p50 ms",
            series(|r| r.age_ms_p50_mean),
        ),
    ];
    let with_clients: Vec<&ScalingRow> = rows.iter().filter(|r| r.clients > 0).collect();
    lines.push((
        "shared server ms per client (update / clients)",
        with_clients
            .iter()
            .map(|r| (r.clients as f64, shared(r)))
            .collect(),
    ));
    if per_client {
        lines.push((
            "server ms per client frame",
            series(|r| r.server_per_client_ms.unwrap_or(0.0)),
        ));
    }
    let png = crate::plot::lines(
        &out.join("scaling.png"),
        &format!("{}, {}: cost per client count", T::NAME, cluster.scene),
        "clients",
        &lines,
    )?;
    println!("wrote {} and {}", json.display(), png.display());
    Ok(rows)
}

/// A Table 2 row of a technique's block: its label, the paper's row it stands beside
/// (`None`: the polygon count, from [`paper::SCENES`]) and how a column fills it.
pub struct Row<C> {
    /// Label.
    pub label: &'static str,
    /// Index into the paper's block, or `None` for the polygon count.
    pub paper: Option<usize>,
    /// Our cell.
    pub cell: fn(&C) -> String,
}

/// A technique's Table 2 block: our columns (named by `scene`), each followed by the paper's
/// column for its scene (`paper_scene`, a name of [`paper::SCENES`]) from `block`.
pub fn beside_paper<C>(
    title: &str,
    columns: &[C],
    scene: fn(&C) -> (&str, &str),
    rows: &[Row<C>],
    block: &[(&str, [&str; 6])],
) -> String {
    let mut header = vec![title.to_string()];
    for c in columns {
        let (ours, theirs) = scene(c);
        header.push(ours.to_string());
        header.push(format!("paper: {theirs}"));
    }
    let header_refs: Vec<&str> = header.iter().map(String::as_str).collect();
    let mut t = table::Markdown::new(&header_refs);
    for row in rows {
        let mut cells = vec![row.label.to_string()];
        for c in columns {
            cells.push((row.cell)(c));
            let theirs = scene(c).1;
            let s = paper::SCENES
                .iter()
                .position(|s| s.name == theirs)
                .unwrap_or(0);
            cells.push(match row.paper {
                None => paper::SCENES[s].polygons.to_string(),
                Some(r) => block.get(r).map_or("", |b| b.1[s]).to_string(),
            });
        }
        t.row(cells);
    }
    t.render()
}

/// The view a quality sweep measures (any technique): the scene's first camera at time 0, the reference's
/// indirect light.
pub struct QualityView {
    /// The scene.
    pub scene: Scene,
    /// Its BVH at time 0.
    pub bvh: SceneBvh,
    /// The camera.
    pub camera: Camera,
    /// The path tracer's indirect-only radiance.
    pub reference: Vec<Vec3>,
    /// Seconds the reference took (reading it back from [`reference_cache`] included).
    pub reference_s: f64,
    /// Whether it came from the cache.
    pub reference_cached: bool,
    /// The reference's own noise: the relMSE a noiseless technique would show against it
    /// ([`reference_cache::Reference::noise`]).
    pub reference_noise: f64,
    /// The error a client shading each pixel's centre with exact light shows against the
    /// reference ([`reference_cache::Reference::sampling_floor`]): below it, a technique's
    /// relMSE is the raster's sampling, not its light.
    pub sampling_floor: f64,
    /// Image width and height, pixels.
    pub size: (u32, u32),
}

impl QualityView {
    /// [`Self::new`] with the view, size and samples of `common`.
    pub fn of(scene: Scene, common: &QualityCommon) -> anyhow::Result<Self> {
        Self::new(
            scene,
            &common.camera,
            common.width,
            common.height,
            common.spp,
        )
    }

    /// The reference of `scene` seen from `view` (an index into its camera paths or
    /// `eye:target[:fov_deg]`, [`cloudlight_scenes::camera`]) at `width × height`, `spp`
    /// samples per pixel: rendered, or read back from the reference cache
    /// ([`reference_cache::dir`]).
    pub fn new(
        scene: Scene,
        view: &str,
        width: u32,
        height: u32,
        spp: u32,
    ) -> anyhow::Result<Self> {
        let camera = cloudlight_scenes::camera(&scene, view, 0.0).map_err(anyhow::Error::msg)?;
        let bvh = SceneBvh::at(&scene, 0.0, BvhKind::default());
        eprintln!(
            "reference: {width}x{height}, {spp} spp, indirect only, camera {view} (eye {:.2}, target {:.2}, \
             {:.0}° high)...",
            camera.position,
            camera.target,
            camera.fov_y_rad.to_degrees()
        );
        let start = Instant::now();
        let settings = cloudlight_render::RenderSettings {
            width,
            height,
            camera,
            time_s: 0.0,
            seed: 77,
            max_bounces: 64,
            pixel: cloudlight_render::PixelSampling::Area,
        };
        let cache = reference_cache::dir();
        let reference = reference_cache::reference(&scene, &bvh, settings, spp, cache.as_deref());
        // The same view through each pixel's centre, as a client's raster shades it.
        let centred = cloudlight_render::RenderSettings {
            pixel: cloudlight_render::PixelSampling::Centre,
            ..settings
        };
        let centred = reference_cache::reference(&scene, &bvh, centred, spp, cache.as_deref());
        let reference_s = start.elapsed().as_secs_f64();
        let reference_noise = reference.noise();
        let sampling_floor = reference.sampling_floor(&centred);
        eprintln!(
            "reference {} in {reference_s:.1} s; its own noise, relMSE {reference_noise:.4} (what a noiseless \
             technique would show against it); the raster's sampling floor, relMSE {sampling_floor:.4} (what a \
             client shading each pixel's centre with exact light would show: the reference holds each pixel's \
             mean over its area)",
            if reference.cached && centred.cached {
                "read from the cache"
            } else {
                "rendered"
            }
        );
        Ok(QualityView {
            scene,
            bvh,
            camera,
            reference: reference.indirect,
            reference_s,
            reference_cached: reference.cached && centred.cached,
            reference_noise,
            sampling_floor,
            size: (width, height),
        })
    }
}

impl QualityView {
    /// Writes the reference as `out/reference_indirect.exr`.
    pub fn write_reference(&self, out: &Path) -> anyhow::Result<()> {
        let (w, h) = self.size;
        cloudlight_render::image_io::write_exr(
            &out.join("reference_indirect.exr"),
            w,
            h,
            &self.reference,
        )?;
        Ok(())
    }

    /// Writes a technique's indirect image of this view as `out/NAME.exr`, and `out/NAME.png`:
    /// it beside the reference, and where its error lies (each pixel's relMSE term over the
    /// pixels where either image has light — those that see geometry, but for the ones
    /// dark in both, which add nothing; [`crate::plot::comparison`]). `title` heads its panel.
    pub fn write_image(
        &self,
        out: &Path,
        name: &str,
        image: &[Vec3],
        title: &str,
    ) -> anyhow::Result<()> {
        let (w, h) = self.size;
        cloudlight_render::image_io::write_exr(&out.join(format!("{name}.exr")), w, h, image)?;
        let lit: Vec<bool> = image
            .iter()
            .zip(&self.reference)
            .map(|(a, b)| a.max_element() > 0.0 || b.max_element() > 0.0)
            .collect();
        let map = cloudlight_render::metrics::relmse_map(image, &self.reference, &lit);
        crate::plot::comparison(
            &out.join(format!("{name}.png")),
            self.size,
            image,
            &self.reference,
            &map,
            [title, "reference", "relMSE per pixel, 0.001 to 10 (log)"],
        )?;
        Ok(())
    }
}

/// Default output folder of a benchmark: `runs/bench-<name>-<unix time>`.
pub fn default_out(name: &str) -> PathBuf {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    PathBuf::from("runs").join(format!("bench-{name}-{secs}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn knobs_parse_as_toml_values_or_bare_strings() {
        assert_eq!(
            parse_knob("photons=40000").unwrap(),
            ("photons".into(), toml::Value::Integer(40000))
        );
        assert_eq!(
            parse_knob(" interval_ms = 2.5").unwrap(),
            ("interval_ms".into(), toml::Value::Float(2.5))
        );
        assert_eq!(
            parse_knob("format=Wide20").unwrap().1,
            toml::Value::String("Wide20".into())
        );
        assert!(parse_knob("photons").is_err());
        assert!(parse_knob("=3").is_err());
        let (k, v) = parse_sweep("photons=1,2, 3").unwrap();
        assert_eq!((k.as_str(), v.len()), ("photons", 3));
        assert!(parse_sweep("photons=").is_err());
    }

    #[test]
    fn options_take_known_knobs_and_name_unknown_ones() {
        use photons::{PhotonOptions, Photons};
        let mut knobs = toml::Table::new();
        knobs.insert("photons".into(), toml::Value::Integer(123));
        // An integer where the option is a float is taken as that float.
        knobs.insert("interval_ms".into(), toml::Value::Integer(50));
        let o = options_from::<Photons>(&knobs).unwrap();
        assert_eq!(
            o,
            PhotonOptions {
                photons: 123,
                interval_ms: 50.0,
                ..PhotonOptions::default()
            }
        );
        knobs.insert("bases".into(), toml::Value::Integer(3));
        let e = options_from::<Photons>(&knobs).unwrap_err().to_string();
        assert!(
            e.contains("no knob `bases`") && e.contains("batch_size = "),
            "{e}"
        );
        let mut wrong = toml::Table::new();
        wrong.insert("photons".into(), toml::Value::String("many".into()));
        let e = options_from::<Photons>(&wrong).unwrap_err().to_string();
        assert!(e.contains("photons"), "{e}");
    }

    #[test]
    fn a_sweep_expands_to_every_combination_in_order() {
        use photons::Photons;
        let sweep: Sweep = vec![
            ("photons".into(), vec![1.into(), 2.into()]),
            ("batch_size".into(), vec![5.into(), 6.into(), 7.into()]),
        ];
        let points = expand::<Photons>(&toml::Table::new(), &sweep).unwrap();
        let got: Vec<(u64, u32)> = points.iter().map(|o| (o.photons, o.batch_size)).collect();
        assert_eq!(got, [(1, 5), (1, 6), (1, 7), (2, 5), (2, 6), (2, 7)]);
        let per_scene: Sweep = vec![("photons".into(), vec![10.into(), 20.into()])];
        let k = |i| knobs_for_scene(&toml::Table::new(), &per_scene, i)["photons"].clone();
        assert_eq!([k(0), k(1), k(5)], [10.into(), 20.into(), 20.into()]);
    }

    #[test]
    fn a_graph_places_shared_stages_once_and_per_client_stages_per_client() {
        let cluster = ClusterOptions {
            scene: "cornell".into(),
            seconds: 1.0,
            link: Some(LinkProfile::CAMPUS),
            seed: 3,
        };
        let g = StageGraph::new(&["photons", "video"])
            .stage(
                "server",
                "photon_batcher",
                Placement::Shared,
                toml::Table::new(),
            )
            .stage(
                "render",
                "photon_reconstructor",
                Placement::PerClient(Side::Cloud),
                toml::Table::new(),
            )
            .stage(
                "encode",
                "video_encoder",
                Placement::PerClient(Side::Cloud),
                toml::Table::new(),
            )
            .stage(
                "client",
                "video_client",
                Placement::PerClient(Side::Home),
                toml::Table::new(),
            )
            .edge("server", "render")
            .edge("render.frames", "encode")
            .edge("encode", "client");
        assert_eq!(g.cut(), [&("encode".to_string(), "client".to_string())]);
        let reg = cloudlight_actors::registry();
        let plan = g
            .topology("t", &cluster, 3)
            .unwrap()
            .plan("<t>", &reg)
            .unwrap_or_else(|e| panic!("{e}"));
        let on = |node: &str| {
            plan.instances
                .iter()
                .filter(|i| i.node == node)
                .map(|i| i.name.as_str())
                .collect::<Vec<_>>()
        };
        assert_eq!(
            on("cloud"),
            [
                "server",
                "render[0]",
                "render[1]",
                "render[2]",
                "encode[0]",
                "encode[1]",
                "encode[2]"
            ]
        );
        assert_eq!(on("home"), ["client[0]", "client[1]", "client[2]"]);
        // Three to three joins replica i to i; one to three fans out.
        assert_eq!(plan.edges.len(), 9);
        assert_eq!(plan.edges.iter().filter(|e| e.cut).count(), 3);
        let alone = g.topology("t", &cluster, 0).unwrap();
        let plan = alone.plan("<t>", &reg).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(plan.instances.len(), 1);
        assert!(plan.edges.is_empty());
        let broken = g.clone().edge("nowhere", "client");
        let e = broken.topology("t", &cluster, 1).unwrap_err().to_string();
        assert!(e.contains("`nowhere`"), "{e}");
    }
}
