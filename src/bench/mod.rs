//! The benchmark harness: the paper's Table 2, scaling over client counts (Figures 3–5) and
//! the speed/accuracy trade, for any technique that provides a [`Technique`] descriptor.
//!
//! Table 2 and scaling run real topologies ([`TopologySpec`], checked like files) in one
//! process — a `cloud` node with the technique's server stage and a `home` node with its
//! clients, each node on its own UDP socket on loopback — and read the stages' typed
//! reports. The client's frame and the quality sweep call the kernels directly. Every table
//! prints the paper's figure beside ours where the paper has one.
//!
//! The CLI only parses options and prints; everything measured is here, so tests link it.

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::Context;
use cloudlight_runtime::metrics::EdgeSnapshot;
use cloudlight_runtime::{MetricsSnapshot, RunOptions, TopologySpec};
use cloudlight_transport::LinkProfile;
use serde::Serialize;
use serde::de::DeserializeOwned;

pub mod baseline;
pub mod client;
pub mod paper;
pub mod photons;
pub mod table;
pub mod video;

/// Names of the techniques the benchmarks know, implemented or not.
pub const TECHNIQUES: [&str; 3] = ["photons", "irradiance", "voxels"];

/// The technique named `name` if its benchmarks exist; otherwise why not.
pub fn require_technique(name: &str) -> anyhow::Result<()> {
    match name {
        photons::Photons::NAME => Ok(()),
        n if TECHNIQUES.contains(&n) => {
            anyhow::bail!("technique `{n}` is not implemented yet; benchmarks exist for `photons`")
        }
        baseline::NAME => anyhow::bail!(
            "`{}` (the full-frame baseline) is measured by `bench table2` only",
            baseline::NAME
        ),
        other => anyhow::bail!(
            "unknown technique `{other}` (one of: {})",
            TECHNIQUES.join(", ")
        ),
    }
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

/// A technique as the benchmarks see it.
pub trait Technique {
    /// Name on the command line.
    const NAME: &'static str;
    /// Stage kind computing the lighting in the cloud: one instance, `server` on `cloud`;
    /// its cost must not grow with the number of clients.
    const SERVER_KIND: &'static str;
    /// Stage kind replicated once per client: `client` on `home`.
    const CLIENT_KIND: &'static str;
    /// The server's report.
    type ServerReport: DeserializeOwned;
    /// A client's report.
    type ClientReport: DeserializeOwned;
    /// The technique's knobs (budget, batch size, interval, ...).
    type Options: Clone + Serialize;

    /// The server's `params`.
    fn server_params(options: &Self::Options) -> anyhow::Result<toml::Table>;

    /// The clients' `params` (clients of cluster benchmarks measure, they do not render).
    fn client_params(options: &Self::Options) -> anyhow::Result<toml::Table>;

    /// One row of the scaling table.
    fn scaling_row(run: &ClusterRun<Self>, clients: usize) -> ScalingRow;
}

/// The topology of a cluster benchmark: the server on `cloud`, `clients` replicas of the
/// client on `home` (none: the server alone), the link between the nodes.
pub fn cluster_topology<T: Technique>(
    options: &T::Options,
    cluster: &ClusterOptions,
    clients: usize,
) -> anyhow::Result<TopologySpec> {
    let any_port = "127.0.0.1:0".parse().expect("a valid address");
    let mut spec = TopologySpec::new(&[T::NAME], &cluster.scene)
        .node("cloud", any_port)
        .node("home", any_port)
        .stage(
            "server",
            T::SERVER_KIND,
            &["cloud"],
            T::server_params(options)?,
        );
    spec.seed = cluster.seed;
    spec.duration_s = Some(cluster.seconds);
    spec.cluster = format!("{}-bench", T::NAME);
    spec.secret = format!("{}-bench", T::NAME);
    if clients > 0 {
        let homes = vec!["home"; clients];
        spec = spec
            .stage("client", T::CLIENT_KIND, &homes, T::client_params(options)?)
            .edge("server", "client", None, None);
    }
    if let Some(link) = cluster.link {
        spec = spec.link("cloud", "home", link);
    }
    Ok(spec)
}

/// What one cluster run measured.
pub struct ClusterRun<T: Technique + ?Sized> {
    /// The server's report.
    pub server: T::ServerReport,
    /// Each client's report, in replica order.
    pub clients: Vec<T::ClientReport>,
    /// The run's final metrics (edges, stages).
    pub metrics: MetricsSnapshot,
}

impl<T: Technique + ?Sized> ClusterRun<T> {
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
        .sum()
}

/// Total payload megabits per second on the cut edges.
pub fn payload_mbps(m: &MetricsSnapshot) -> f64 {
    sending_edges(m).map(|e| e.mbps).sum()
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

/// Runs the cluster of [`cluster_topology`] for `cluster.seconds` and reads its reports.
pub fn run_cluster<T: Technique>(
    runtime: &tokio::runtime::Runtime,
    options: &T::Options,
    cluster: &ClusterOptions,
    clients: usize,
) -> anyhow::Result<ClusterRun<T>> {
    let spec = cluster_topology::<T>(options, cluster, clients)?;
    let file = format!("<{} benchmark>", T::NAME);
    let m = run_spec(runtime, &spec, &file, cluster.seconds)?;
    let clients = (0..clients)
        .map(|i| stage_report(&m, &replica_name("client", i, clients)))
        .collect::<anyhow::Result<_>>()?;
    Ok(ClusterRun {
        server: stage_report(&m, "server")?,
        clients,
        metrics: m,
    })
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
        rows.push(T::scaling_row(&run, n));
    }
    let mut t = table::Markdown::new(&[
        "clients",
        "server ms / update",
        "kernel ms",
        "total Mbps (wire)",
        "age p50 ms (mean over clients)",
        "age p99 ms (worst)",
        "clients showing indirect",
    ]);
    for r in &rows {
        t.row(vec![
            r.clients.to_string(),
            format!("{:.2}", r.server_update_ms),
            format!("{:.2}", r.server_kernel_ms),
            format!("{:.1}", r.total_wire_mbps),
            format!("{:.0}", r.age_ms_p50_mean),
            format!("{:.0}", r.age_ms_p99_max),
            r.clients_showing_indirect.to_string(),
        ]);
    }
    println!("{}", t.render());
    println!(
        "paper ({}): {}",
        paper::SCALING_FIGURE.0,
        paper::SCALING_FIGURE.1
    );
    let report = serde_json::json!({
        "technique": T::NAME,
        "cluster": { "scene": cluster.scene, "seconds": cluster.seconds, "link": cluster.link, "seed": cluster.seed },
        "options": options,
        "rows": rows,
        "paper": paper::SCALING_FIGURE.1,
    });
    let json = out.join("scaling.json");
    std::fs::write(&json, serde_json::to_string_pretty(&report)?)
        .with_context(|| format!("writing {}", json.display()))?;
    let series = |f: fn(&ScalingRow) -> f64| -> Vec<(f64, f64)> {
        rows.iter().map(|r| (r.clients as f64, f(r))).collect()
    };
    let png = crate::plot::lines(
        &out.join("scaling.png"),
        &format!("{}, {}: cost per client count", T::NAME, cluster.scene),
        "clients",
        &[
            ("server ms per update", series(|r| r.server_update_ms)),
            ("total Mbps (wire)", series(|r| r.total_wire_mbps)),
            (
                "age of indirect light, p50 ms",
                series(|r| r.age_ms_p50_mean),
            ),
        ],
    )?;
    println!("wrote {} and {}", json.display(), png.display());
    Ok(rows)
}

/// Default output folder of a benchmark: `runs/bench-<name>-<unix time>`.
pub fn default_out(name: &str) -> PathBuf {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    PathBuf::from("runs").join(format!("bench-{name}-{secs}"))
}
