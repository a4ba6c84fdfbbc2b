//! `cloudlight`: validate topologies, run them in one process, or run one node of them.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::time::{Duration, Instant};

use clap::{Parser, Subcommand};
use cloudlight::runtime::{Plan, RunError, RunOptions, RunReport, StageRegistry};
use cloudlight::{DEFAULT_TOPOLOGY, DEFAULT_TOPOLOGY_NAME};
use indicatif::{ProgressBar, ProgressStyle};

/// CloudLight-rs: indirect lighting computed on cloud nodes and streamed to clients.
///
/// Logs go to stderr; set RUST_LOG (e.g. RUST_LOG=debug) to change what is shown.
#[derive(Parser)]
#[command(version, about, long_about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Check a topology file and print where each stage runs and which edges are cut.
    ///
    /// Exits 0 when the file is valid; otherwise prints every problem found, each with file,
    /// line and key, and exits 2.
    Validate {
        /// The topology file (TOML).
        topology: PathBuf,
    },
    /// Run every node of a topology in this process, then print per-stage and per-edge
    /// metrics and write them to OUT/metrics.json.
    ///
    /// Without TOPOLOGY a built-in default runs (see the README). Ctrl-C stops the run
    /// cleanly: sources stop, queued messages are handled, metrics are written.
    Run {
        /// The topology file (TOML); omit it to run the built-in default.
        topology: Option<PathBuf>,
        #[command(flatten)]
        run: RunArgs,
    },
    /// Run only the stages placed on one node of a topology (one process per node).
    Node {
        /// The topology file (TOML).
        topology: PathBuf,
        /// Name of the node to run, as declared in the file.
        #[arg(long)]
        node: String,
        #[command(flatten)]
        run: RunArgs,
    },
    /// List the stage kinds topology files may name, with their ports and message types.
    Kinds,
}

#[derive(clap::Args)]
struct RunArgs {
    /// Run length in seconds (overrides the file's `duration_s`; without either the run lasts
    /// until Ctrl-C or until the pipeline finishes by itself).
    #[arg(long, value_name = "SECONDS")]
    duration: Option<f64>,
    /// Folder for metrics.json and other run outputs [default: runs/<topology>-<unix time>].
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
    /// Seconds to wait at start for the peers this process's nodes need (overrides the
    /// topology's `[transport] connect_timeout_s`, default 60).
    #[arg(long, value_name = "SECONDS")]
    connect_timeout: Option<f64>,
    /// Seconds between metrics snapshots written during the run.
    #[arg(long, value_name = "SECONDS", default_value_t = 2.0)]
    metrics_interval: f64,
}

fn main() -> ExitCode {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| {
        tracing_subscriber::EnvFilter::new(
            "warn,cloudlight=info,cloudlight_runtime=info,cloudlight_actors=info",
        )
    });
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    let registry = cloudlight::actors::registry();
    match cli.command {
        Command::Validate { topology } => match Plan::load(&topology, &registry) {
            Ok(plan) => {
                println!("{}", plan.summary());
                for w in &plan.warnings {
                    eprintln!("warning: {w}");
                }
                println!("valid");
                ExitCode::SUCCESS
            }
            Err(errors) => {
                eprintln!("{errors}");
                ExitCode::from(2)
            }
        },
        Command::Run { topology, run } => {
            let plan = match &topology {
                Some(path) => Plan::load(path, &registry),
                None => {
                    eprintln!(
                        "No topology given: running the built-in default, the probe pipeline on one node \
                         (examples/topologies/probe-local.toml). No lighting technique is implemented yet; \
                         once the photon technique exists, the default becomes photons on the Cornell box."
                    );
                    Plan::from_str(DEFAULT_TOPOLOGY_NAME, DEFAULT_TOPOLOGY, &registry)
                }
            };
            let stem = topology
                .as_deref()
                .and_then(Path::file_stem)
                .map_or("default".to_string(), |s| s.to_string_lossy().into_owned());
            execute(plan, &registry, run, None, &stem)
        }
        Command::Node {
            topology,
            node,
            run,
        } => {
            let plan = Plan::load(&topology, &registry);
            let stem = topology
                .file_stem()
                .map_or("node".to_string(), |s| s.to_string_lossy().into_owned());
            execute(plan, &registry, run, Some(node), &stem)
        }
        Command::Kinds => {
            for k in registry.kinds() {
                println!("{} (technique {}): {}", k.name, k.technique, k.summary);
                for p in &k.inputs {
                    let d = p.default.expect("inputs have defaults");
                    println!(
                        "  in  {:<12} {} [default {} {}]",
                        p.name,
                        p.ty.name(),
                        d.policy,
                        d.capacity
                    );
                }
                for p in &k.outputs {
                    println!("  out {:<12} {}", p.name, p.ty.name());
                }
            }
            ExitCode::SUCCESS
        }
    }
}

fn execute(
    plan: Result<Plan, cloudlight::runtime::TopologyErrors>,
    registry: &StageRegistry,
    args: RunArgs,
    only_node: Option<String>,
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
        eprintln!("warning: {w}");
    }
    let duration = args
        .duration
        .or(plan.topology.duration_s)
        .map(Duration::from_secs_f64);
    let out = args.out.unwrap_or_else(|| {
        let secs = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs());
        let node = only_node
            .as_deref()
            .map_or(String::new(), |n| format!("-{n}"));
        PathBuf::from("runs").join(format!("{stem}{node}-{secs}"))
    });
    let bar = match duration {
        Some(d) => ProgressBar::new(d.as_millis() as u64).with_style(
            ProgressStyle::with_template("{elapsed_precise} [{bar:30}] {percent}% {msg}")
                .expect("valid template")
                .progress_chars("=> "),
        ),
        None => ProgressBar::new_spinner().with_style(
            ProgressStyle::with_template("{elapsed_precise} {spinner} {msg} (Ctrl-C stops)")
                .expect("valid template"),
        ),
    };
    let progress_bar = bar.clone();
    let options = RunOptions {
        duration,
        out_dir: Some(out.clone()),
        only_node,
        connect_timeout: args.connect_timeout.map(Duration::from_secs_f64),
        metrics_interval: Duration::from_secs_f64(args.metrics_interval.max(0.1)),
        on_progress: Some(Arc::new(move |snap| {
            let handled: u64 = snap.stages.iter().map(|s| s.handled).sum();
            let dropped: u64 = snap.edges.iter().map(|e| e.dropped).sum();
            progress_bar.set_message(format!("{handled} messages handled, {dropped} dropped"));
        })),
        ..RunOptions::default()
    };
    let runtime = match tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
    {
        Ok(r) => r,
        Err(e) => {
            eprintln!("cannot start the async runtime: {e}");
            return ExitCode::FAILURE;
        }
    };
    let result: Result<RunReport, RunError> = runtime.block_on(async {
        let ticker_bar = bar.clone();
        let start = Instant::now();
        let ticker = tokio::spawn(async move {
            loop {
                ticker_bar.set_position(start.elapsed().as_millis() as u64);
                ticker_bar.tick();
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        });
        let stop = async {
            if tokio::signal::ctrl_c().await.is_err() {
                std::future::pending::<()>().await;
            }
            eprintln!("stopping: draining queued messages...");
        };
        let r = cloudlight::runtime::run(&plan, registry, options, stop).await;
        ticker.abort();
        r
    });
    bar.finish_and_clear();
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
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
