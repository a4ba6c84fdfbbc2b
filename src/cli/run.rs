//! `cloudlight run [TOPOLOGY]` and `cloudlight node TOPOLOGY --node NAME`: run every node of a
//! topology in this process, or one node of it, with a progress bar, then print the metrics
//! table, each stage's summary line and where clients wrote their frames.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::time::{Duration, Instant};

use cloudlight::runtime::topology::SecretSource;
use cloudlight::runtime::{Plan, RunError, RunOptions, RunReport, TopologyErrors};
use cloudlight::{DEFAULT_TOPOLOGY, DEFAULT_TOPOLOGY_NAME};
use indicatif::{ProgressBar, ProgressStyle};

use super::ranges;

/// Options of `run` and `node`.
#[derive(clap::Args)]
pub struct RunArgs {
    /// Run length in seconds (overrides the file's `duration_s`; without either the run lasts
    /// until Ctrl-C or until the pipeline finishes by itself).
    #[arg(long, value_name = "SECONDS", value_parser = ranges::seconds())]
    duration: Option<f64>,
    /// Folder for metrics.json and other run outputs [default: runs/<topology>-<unix time>].
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
    /// Seconds to wait at start for the peers this process's nodes need (overrides the
    /// topology's `[transport] connect_timeout_s`, default 60).
    #[arg(long, value_name = "SECONDS", value_parser = ranges::above(0.0, 86_400.0, "seconds"))]
    connect_timeout: Option<f64>,
    /// Serve `/metrics` (Prometheus text format) and `/healthz` (200 while running with every
    /// peer up, else 503 and why) on this TCP address, e.g. `0.0.0.0:9100`; both show the
    /// newest metrics snapshot (every `--metrics-interval`).
    #[arg(long, value_name = "IP:PORT")]
    metrics_listen: Option<std::net::SocketAddr>,
    /// Seconds between metrics snapshots written during the run.
    #[arg(long, value_name = "SECONDS", default_value_t = 2.0,
          value_parser = ranges::closed(0.01, 3_600.0, "seconds"))]
    metrics_interval: f64,
}

/// `cloudlight run`.
#[derive(clap::Args)]
pub struct RunCommand {
    /// The topology file (TOML); omit it to run the built-in default.
    topology: Option<PathBuf>,
    #[command(flatten)]
    run: RunArgs,
}

/// `cloudlight node`.
#[derive(clap::Args)]
pub struct NodeCommand {
    /// The topology file (TOML).
    topology: PathBuf,
    /// Name of the node to run, as declared in the file.
    #[arg(long)]
    node: String,
    /// Address to listen on (`IP:port`), over the node's `bind` in the file (default: its
    /// `address`): e.g. `0.0.0.0:7200` in a container or behind NAT, while peers dial the
    /// node's `address`.
    #[arg(long, value_name = "IP:PORT")]
    bind: Option<std::net::SocketAddr>,
    /// Read the cluster's secret from this environment variable, over the file's `secret`,
    /// `secret_env` or `secret_file` (e.g. for the examples, which carry none).
    #[arg(long, value_name = "NAME")]
    secret_env: Option<String>,
    #[command(flatten)]
    run: RunArgs,
}

pub fn run(c: RunCommand) -> ExitCode {
    let registry = cloudlight::actors::registry();
    let plan = match &c.topology {
        Some(path) => Plan::load(path, &registry),
        None => {
            eprintln!(
                "No topology given: running the built-in default, the photon technique on the \
                 Cornell box with a moving light: a cloud node traces photons and streams them to two \
                 clients over emulated campus links (examples/topologies/photons-cloud.toml)."
            );
            Plan::from_str(DEFAULT_TOPOLOGY_NAME, DEFAULT_TOPOLOGY, &registry)
        }
    };
    let stem = c
        .topology
        .as_deref()
        .and_then(Path::file_stem)
        .map_or("default".to_string(), |s| s.to_string_lossy().into_owned());
    execute(plan, c.run, None, None, &stem)
}

pub fn node(c: NodeCommand) -> ExitCode {
    let registry = cloudlight::actors::registry();
    let mut plan = Plan::load(&c.topology, &registry);
    if let (Ok(plan), Some(name)) = (&mut plan, &c.secret_env) {
        match std::env::var(name) {
            Ok(secret) if !secret.is_empty() => {
                plan.topology.secret = secret;
                plan.topology.secret_source = SecretSource::Env(name.clone());
                plan.warnings
                    .retain(|w| !w.message.starts_with("no secret"));
            }
            _ => {
                eprintln!(
                    "error: --secret-env: environment variable `{name}` is not set or empty (it holds the cluster's secret)"
                );
                return ExitCode::from(2);
            }
        }
    }
    let stem = c
        .topology
        .file_stem()
        .map_or("node".to_string(), |s| s.to_string_lossy().into_owned());
    execute(plan, c.run, Some(c.node), c.bind, &stem)
}

/// The progress bar of a run of `duration` (a spinner when it has none).
fn progress_bar(duration: Option<Duration>) -> ProgressBar {
    match duration {
        Some(d) => ProgressBar::new(d.as_millis() as u64).with_style(
            ProgressStyle::with_template("{elapsed_precise} [{bar:30}] {percent}% {msg}")
                .expect("valid template")
                .progress_chars("=> "),
        ),
        None => ProgressBar::new_spinner().with_style(
            ProgressStyle::with_template("{elapsed_precise} {spinner} {msg} (Ctrl-C stops)")
                .expect("valid template"),
        ),
    }
}

/// Each flag's range: finite, and convertible to a wall-clock duration and deadline.
fn default_out(stem: &str, only_node: Option<&str>) -> PathBuf {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    let node = only_node.map_or(String::new(), |n| format!("-{n}"));
    PathBuf::from("runs").join(format!("{stem}{node}-{secs}"))
}

fn execute(
    plan: Result<Plan, TopologyErrors>,
    args: RunArgs,
    only_node: Option<String>,
    bind: Option<std::net::SocketAddr>,
    stem: &str,
) -> ExitCode {
    let plan = match plan {
        Ok(p) => p,
        Err(errors) => {
            eprintln!("{errors}");
            return ExitCode::from(2);
        }
    };
    for w in &plan.warnings {
        // The whole topology in one process draws its own secret: nothing to warn about.
        if only_node.is_none() && w.message.starts_with("no secret") {
            continue;
        }
        eprintln!("warning: {w}");
    }
    let duration = args
        .duration
        .or(plan.topology.duration_s)
        .map(Duration::from_secs_f64);
    let out = args
        .out
        .unwrap_or_else(|| default_out(stem, only_node.as_deref()));
    let bar = progress_bar(duration);
    let progress_bar = bar.clone();
    let options = RunOptions {
        duration,
        out_dir: Some(out.clone()),
        only_node,
        bind,
        metrics_listen: args.metrics_listen,
        connect_timeout: args.connect_timeout.map(Duration::from_secs_f64),
        metrics_interval: Duration::from_secs_f64(args.metrics_interval),
        on_progress: Some(Arc::new(move |snap| {
            let handled: u64 = snap.stages.iter().map(|s| s.handled).sum();
            let dropped: u64 = snap.edges.iter().map(|e| e.dropped).sum();
            progress_bar.set_message(format!("{handled} messages handled, {dropped} dropped"));
        })),
        ..RunOptions::default()
    };
    let runtime = match super::async_runtime() {
        Ok(r) => r,
        Err(e) => return super::report_error(e),
    };
    let result = runtime.block_on(run_with_progress(&plan, options, bar.clone()));
    bar.finish_and_clear();
    print_result(result, &out)
}

async fn run_with_progress(
    plan: &Plan,
    options: RunOptions,
    bar: ProgressBar,
) -> Result<RunReport, RunError> {
    let registry = cloudlight::actors::registry();
    let start = Instant::now();
    let ticker = tokio::spawn(async move {
        loop {
            bar.set_position(start.elapsed().as_millis() as u64);
            bar.tick();
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    });
    let stop = async {
        if tokio::signal::ctrl_c().await.is_err() {
            std::future::pending::<()>().await;
        }
        eprintln!("stopping: draining queued messages...");
    };
    let r = cloudlight::runtime::run(plan, &registry, options, stop).await;
    ticker.abort();
    r
}

fn print_result(result: Result<RunReport, RunError>, out: &Path) -> ExitCode {
    match result {
        Ok(report) => {
            println!("{}", report.metrics.table());
            println!(
                "run ended ({:?}); {} of {} stages stopped cleanly; metrics: {}",
                report.end,
                report.stopped.len(),
                report.started,
                out.join("metrics.json").display()
            );
            print_stage_lines(&report);
            ExitCode::SUCCESS
        }
        Err(RunError::StageFailed {
            stage,
            error,
            report,
        }) => {
            println!("{}", report.metrics.table());
            eprintln!("error: stage `{stage}` failed: {error}");
            eprintln!(
                "the run was stopped; metrics: {}",
                out.join("metrics.json").display()
            );
            ExitCode::from(3)
        }
        Err(RunError::NetworkFailed { error, report }) => {
            println!("{}", report.metrics.table());
            eprintln!("error: {error}");
            eprintln!(
                "the run was stopped; metrics: {}",
                out.join("metrics.json").display()
            );
            ExitCode::from(5)
        }
        // The network failed before the run could start: exit 5, as when it fails later.
        Err(e @ (RunError::Link(_) | RunError::PeersUnreachable { .. })) => {
            eprintln!("error: {e}");
            ExitCode::from(5)
        }
        // Bad input, found before anything started: exit 2, as `validate` would.
        Err(e @ RunError::NoSecret(_)) => {
            eprintln!("error: {e}");
            ExitCode::from(2)
        }
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}

/// Each stage's summary line, then where clients wrote their frames.
fn print_stage_lines(report: &RunReport) {
    let reports = || {
        report
            .metrics
            .stages
            .iter()
            .filter_map(|s| s.report.as_ref().map(|r| (s, r)))
    };
    for (stage, r) in reports() {
        if let Some(summary) = r.get("summary").and_then(|d| d.as_str()) {
            println!("{}: {summary}", stage.name);
        }
    }
    for (stage, r) in reports() {
        if let Some(dir) = r.get("frames_dir").and_then(|d| d.as_str()) {
            println!(
                "frames of {}: {} ({} PNGs)",
                stage.name,
                dir,
                r.get("frames_written")
                    .and_then(|n| n.as_u64())
                    .unwrap_or(0)
            );
        }
    }
}
