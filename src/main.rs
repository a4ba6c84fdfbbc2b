//! `cloudlight`: validate topologies, run them in one process, or run one node of them.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::time::{Duration, Instant};

use clap::{Parser, Subcommand};
use cloudlight::runtime::{Plan, RunError, RunOptions, RunReport, StageRegistry};
use cloudlight::{DEFAULT_TOPOLOGY, DEFAULT_TOPOLOGY_NAME};
use indicatif::{ProgressBar, ProgressStyle};

mod bench_photons;
mod plot;

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
    /// Describe a scene (triangles, bounds, lights, emitted watts) and what each technique
    /// would allocate for it with its default settings: photon batches per light, occupied
    /// voxels per octree level, light-map texels and bases.
    Plan {
        /// Scene: `cornell`, `cornell-animated`, `city:N` or a .gltf/.glb file.
        scene: String,
    },
    /// Render the reference images of a scene with the path tracer: full, direct-only and
    /// indirect-only radiance as OpenEXR, plus tone-mapped PNGs.
    Reference(ReferenceArgs),
    /// Measure parts of the system.
    Bench {
        #[command(subcommand)]
        what: BenchCommand,
    },
}

#[derive(clap::Args)]
struct ReferenceArgs {
    /// Scene: `cornell`, `cornell-animated`, `city:N` or a .gltf/.glb file.
    scene: String,
    /// View: the index of one of the scene's camera paths, or `px,py,pz:tx,ty,tz[:fov_deg]`
    /// (eye and target in meters, vertical field of view in degrees, default 45).
    #[arg(long, default_value = "0", allow_hyphen_values = true)]
    camera: String,
    /// Scene time, seconds.
    #[arg(long, default_value_t = 0.0)]
    time: f64,
    /// Samples per pixel.
    #[arg(long, default_value_t = 256)]
    spp: u32,
    /// Image width, pixels.
    #[arg(long, default_value_t = 512)]
    width: u32,
    /// Image height, pixels.
    #[arg(long, default_value_t = 512)]
    height: u32,
    /// Seed of the random streams.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Output folder for full/direct/indirect .exr and .png.
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
}

#[derive(Subcommand)]
enum BenchCommand {
    /// Two transport endpoints on loopback exchange messages through the link emulator:
    /// delivered, byte-identical, in order, goodput, retransmissions, message round trips,
    /// against a plain UDP blast of the same bytes in datagrams of the same size.
    ///
    /// Prints a table and the JSON report (also written to --json PATH if given).
    Transport(TransportBenchArgs),
    /// Raster on wgpu: G-buffer + direct light with shadow maps of a scene's view at
    /// 1280x720 (median of --rounds frames, after one warm-up).
    Raster {
        /// Scene: `cornell`, `cornell-animated`, `city:N` or a .gltf/.glb file.
        #[arg(long, default_value = "city:100000")]
        scene: String,
        /// Frames timed.
        #[arg(long, default_value_t = 5)]
        rounds: usize,
    },
    /// The paper's Table 2 rows for a technique, one column per scene: batches, photons per
    /// batch, memory footprint, iteration interval, trace, packing and send time,
    /// server-to-client Mbps, photons stored on the client and the client's indirect time.
    ///
    /// Runs the real stages (a cloud node and one client node over loopback) with every
    /// light re-traced each `--interval-ms`, then times the client's splatting on wgpu.
    /// Prints a Markdown table and JSON (also written to --json PATH if given).
    Table2 {
        /// Technique (only `photons` so far).
        #[arg(long, default_value = "photons")]
        technique: String,
        /// Scenes, comma-separated: `cornell`, `city:N`, a .gltf/.glb file.
        #[arg(long, value_delimiter = ',', default_value = "cornell")]
        scene: Vec<String>,
        /// Photons per iteration, one per scene (the last repeats).
        #[arg(long, value_delimiter = ',', default_value = "10000")]
        photons: Vec<u64>,
        /// Photons per batch.
        #[arg(long, default_value_t = 10_000)]
        batch_size: u32,
        /// Iteration period, milliseconds.
        #[arg(long, default_value_t = 33.0)]
        interval_ms: f64,
        /// Seconds each scene runs.
        #[arg(long, default_value_t = 5.0)]
        seconds: f64,
        /// Client frame width for the indirect time.
        #[arg(long, default_value_t = 1280)]
        width: u32,
        /// Client frame height for the indirect time.
        #[arg(long, default_value_t = 720)]
        height: u32,
        /// Also write the JSON report to this file.
        #[arg(long, value_name = "PATH")]
        json: Option<PathBuf>,
    },
    /// Scaling over client counts (the paper's Figure 5): server time per iteration, total
    /// Mbps and age of indirect light for each count, as a table, JSON and a PNG plot.
    Scaling {
        /// Technique (only `photons` so far).
        #[arg(long, default_value = "photons")]
        technique: String,
        /// Client counts, comma-separated.
        #[arg(long, value_delimiter = ',', default_value = "1,2,5,10,20,50")]
        clients: Vec<usize>,
        /// Scene.
        #[arg(long, default_value = "cornell-animated")]
        scene: String,
        /// Photons per iteration.
        #[arg(long, default_value_t = 10_000)]
        photons: u64,
        /// Photons per batch.
        #[arg(long, default_value_t = 10_000)]
        batch_size: u32,
        /// Iteration period, milliseconds.
        #[arg(long, default_value_t = 33.0)]
        interval_ms: f64,
        /// Seconds per client count.
        #[arg(long, default_value_t = 4.0)]
        seconds: f64,
        /// Emulate no link (plain loopback) instead of the campus link (5 ms ± 1 ms,
        /// 1 Gbit/s, 0.1% loss).
        #[arg(long)]
        no_link: bool,
        /// Output folder for scaling.json and scaling.png [default: runs/bench-scaling-<time>].
        #[arg(long, value_name = "DIR")]
        out: Option<PathBuf>,
    },
    /// Speed/accuracy trade over photon budgets: relMSE and HDR-FLIP of the client's
    /// indirect-only buffer against the path tracer's indirect-only image of the same view
    /// and time, with update time and Mbps, for 12- and 20-byte photons; a table, JSON and a
    /// PNG plot.
    Quality {
        /// Technique (only `photons` so far).
        #[arg(long, default_value = "photons")]
        technique: String,
        /// Scene.
        #[arg(long, default_value = "cornell")]
        scene: String,
        /// Photon budgets per iteration, comma-separated.
        #[arg(
            long,
            value_delimiter = ',',
            default_value = "2500,5000,10000,40000,160000"
        )]
        budgets: Vec<u64>,
        /// Photons per batch.
        #[arg(long, default_value_t = 10_000)]
        batch_size: u32,
        /// Reference samples per pixel.
        #[arg(long, default_value_t = 4096)]
        spp: u32,
        /// Image width.
        #[arg(long, default_value_t = 128)]
        width: u32,
        /// Image height.
        #[arg(long, default_value_t = 128)]
        height: u32,
        /// Update rate the Mbps column assumes (capped by the update time), Hz.
        #[arg(long, default_value_t = 30.0)]
        rate_hz: f64,
        /// Output folder [default: runs/bench-quality-<time>].
        #[arg(long, value_name = "DIR")]
        out: Option<PathBuf>,
    },
    /// Ray casting on a scene: BVH build time, and million rays per second for coherent
    /// camera rays (1280x720) and incoherent diffuse-bounce rays, for CWBVH and BVH2 at each
    /// thread count (best of --rounds passes).
    Rays {
        /// Scene: `cornell`, `cornell-animated`, `city:N` or a .gltf/.glb file.
        #[arg(long, default_value = "city:250000")]
        scene: String,
        /// Thread counts, comma-separated.
        #[arg(long, value_delimiter = ',', default_value = "1,2")]
        threads: Vec<usize>,
        /// Passes over the rays; the best is kept.
        #[arg(long, default_value_t = 3)]
        rounds: usize,
    },
}

#[derive(clap::Args)]
struct TransportBenchArgs {
    /// Bytes per message.
    #[arg(long, default_value_t = 1024)]
    size: usize,
    /// Messages in the bulk phase.
    #[arg(long, default_value_t = 10_000)]
    count: usize,
    /// Loss probability in [0, 1], applied in both directions.
    #[arg(long, default_value_t = 0.0)]
    loss: f64,
    /// One-way latency, milliseconds.
    #[arg(long, default_value_t = 0.0)]
    latency_ms: f64,
    /// Latency standard deviation, milliseconds.
    #[arg(long, default_value_t = 0.0)]
    jitter_ms: f64,
    /// Bandwidth cap per direction, megabits per second (default: none).
    #[arg(long)]
    bandwidth_mbps: Option<f64>,
    /// Duplication probability in [0, 1].
    #[arg(long, default_value_t = 0.0)]
    duplicate: f64,
    /// Reordering probability in [0, 1].
    #[arg(long, default_value_t = 0.0)]
    reorder: f64,
    /// Largest packet handed to laminar, bytes (the UDP datagram is 5 bytes more).
    #[arg(long, default_value_t = 1200)]
    packet_bytes: usize,
    /// Messages in flight end to end (the edge capacity).
    #[arg(long, default_value_t = 64)]
    capacity: u64,
    /// Most unacknowledged packets per peer (the transport's send window).
    #[arg(long, default_value_t = 1024)]
    window: usize,
    /// Message round trips measured after the bulk phase.
    #[arg(long, default_value_t = 200)]
    rtt_rounds: usize,
    /// Skip the plain UDP blast baseline.
    #[arg(long)]
    no_baseline: bool,
    /// Seed of the link emulators.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Also write the JSON report to this file.
    #[arg(long, value_name = "PATH")]
    json: Option<PathBuf>,
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
                        "No topology given: running the built-in default, the photon technique on the \
                         Cornell box with a moving light: a cloud node traces photons and streams them to two \
                         clients over emulated campus links (examples/topologies/photons-cloud.toml)."
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
        Command::Bench {
            what: BenchCommand::Transport(args),
        } => bench_transport(args),
        Command::Bench {
            what:
                BenchCommand::Table2 {
                    technique,
                    scene,
                    photons,
                    batch_size,
                    interval_ms,
                    seconds,
                    width,
                    height,
                    json,
                },
        } => photons_only(&technique)
            .and_then(|()| {
                let rt = async_runtime().ok_or_else(|| anyhow::anyhow!("no async runtime"))?;
                bench_photons::table2(
                    &rt,
                    &scene,
                    &photons,
                    batch_size,
                    interval_ms,
                    seconds,
                    width,
                    height,
                    json.as_deref(),
                )
            })
            .map_or_else(report_error, |()| ExitCode::SUCCESS),
        Command::Bench {
            what:
                BenchCommand::Scaling {
                    technique,
                    clients,
                    scene,
                    photons,
                    batch_size,
                    interval_ms,
                    seconds,
                    no_link,
                    out,
                },
        } => photons_only(&technique)
            .and_then(|()| {
                let rt = async_runtime().ok_or_else(|| anyhow::anyhow!("no async runtime"))?;
                let b = bench_photons::ClusterBench {
                    scene,
                    photons,
                    batch_size,
                    interval_ms,
                    seconds,
                    format: cloudlight::render::photon::PackFormat::Compact12,
                    link: if no_link {
                        String::new()
                    } else {
                        bench_photons::CAMPUS_LINK.to_string()
                    },
                };
                let out = out.unwrap_or_else(|| bench_photons::default_out("scaling"));
                bench_photons::scaling(&rt, &b, &clients, &out)
            })
            .map_or_else(report_error, |()| ExitCode::SUCCESS),
        Command::Bench {
            what:
                BenchCommand::Quality {
                    technique,
                    scene,
                    budgets,
                    batch_size,
                    spp,
                    width,
                    height,
                    rate_hz,
                    out,
                },
        } => photons_only(&technique)
            .and_then(|()| {
                let out = out.unwrap_or_else(|| bench_photons::default_out("quality"));
                bench_photons::quality(
                    &scene, &budgets, batch_size, spp, width, height, rate_hz, &out,
                )
            })
            .map_or_else(report_error, |()| ExitCode::SUCCESS),
        Command::Reference(args) => reference(args),
        Command::Plan { scene } => plan(&scene),
        Command::Bench {
            what:
                BenchCommand::Rays {
                    scene,
                    threads,
                    rounds,
                },
        } => bench_rays(&scene, &threads, rounds),
        Command::Bench {
            what: BenchCommand::Raster { scene, rounds },
        } => bench_raster(&scene, rounds),
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
    let Some(runtime) = async_runtime() else {
        return ExitCode::FAILURE;
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
            for stage in &report.metrics.stages {
                let Some(r) = &stage.report else { continue };
                if let Some(summary) = r.get("summary").and_then(|d| d.as_str()) {
                    println!("{}: {summary}", stage.name);
                }
            }
            for stage in &report.metrics.stages {
                let Some(r) = &stage.report else { continue };
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

fn bench_transport(args: TransportBenchArgs) -> ExitCode {
    use cloudlight::transport::LinkProfile;
    use cloudlight::transport::bench::{BenchOptions, run};
    for (name, p) in [
        ("loss", args.loss),
        ("duplicate", args.duplicate),
        ("reorder", args.reorder),
    ] {
        if !(0.0..=1.0).contains(&p) {
            eprintln!("error: --{name} must be in [0, 1], got {p}");
            return ExitCode::from(2);
        }
    }
    if args.latency_ms < 0.0
        || args.jitter_ms < 0.0
        || args.bandwidth_mbps.is_some_and(|b| b <= 0.0)
        || args.packet_bytes < 128
        || args.capacity == 0
    {
        eprintln!(
            "error: latency and jitter must be >= 0, bandwidth > 0, packet bytes >= 128, capacity >= 1"
        );
        return ExitCode::from(2);
    }
    let opts = BenchOptions {
        size: args.size,
        count: args.count,
        rtt_rounds: args.rtt_rounds,
        link: LinkProfile {
            latency_ms: args.latency_ms,
            jitter_ms: args.jitter_ms,
            bandwidth_mbps: args.bandwidth_mbps,
            loss: args.loss,
            duplicate: args.duplicate,
            reorder: args.reorder,
        },
        packet_bytes: args.packet_bytes,
        capacity: args.capacity,
        window_packets: args.window.max(1),
        seed: args.seed,
        udp_baseline: !args.no_baseline,
        ..BenchOptions::default()
    };
    let Some(rt) = async_runtime() else {
        return ExitCode::FAILURE;
    };
    eprintln!(
        "transport bench: {} messages of {} bytes, link {:?}",
        args.count, args.size, opts.link
    );
    let report = match rt.block_on(run(opts)) {
        Ok(r) => r,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::FAILURE;
        }
    };
    let yes = |b: bool| if b { "yes" } else { "NO" }.to_string();
    let mut t = comfy_table::Table::new();
    t.load_preset(comfy_table::presets::UTF8_FULL_CONDENSED)
        .set_header(["measure", "value"]);
    let rows = [
        (
            "messages sent / delivered",
            format!("{} / {}", report.sent, report.delivered),
        ),
        ("byte-identical", yes(report.byte_identical)),
        ("in order", yes(report.in_order)),
        ("goodput MB/s", format!("{:.1}", report.goodput_mb_s)),
        (
            "UDP blast MB/s (same datagrams)",
            report
                .udp_blast_mb_s
                .map_or("-".into(), |b| format!("{b:.1}")),
        ),
        (
            "goodput / blast",
            report
                .fraction_of_blast
                .map_or("-".into(), |f| format!("{:.0}%", f * 100.0)),
        ),
        (
            "retransmission ratio",
            format!("{:.4}", report.retransmission_ratio),
        ),
        (
            "round trip p50 / p99 us",
            format!("{:.0} / {:.0}", report.rtt_p50_us, report.rtt_p99_us),
        ),
    ];
    for (k, v) in rows {
        t.add_row([k.to_string(), v]);
    }
    println!("{t}");
    let json = serde_json::to_string_pretty(&report).expect("report serializes");
    println!("{json}");
    if let Some(path) = args.json
        && let Err(e) = std::fs::write(&path, &json)
    {
        eprintln!("error: cannot write {}: {e}", path.display());
        return ExitCode::FAILURE;
    }
    if report.delivered == report.sent && report.byte_identical && report.in_order {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(4)
    }
}

/// The multi-threaded tokio runtime every command runs on; says why when it cannot start.
/// Benchmarks exist for the photon technique only so far.
fn photons_only(technique: &str) -> anyhow::Result<()> {
    match technique {
        "photons" => Ok(()),
        "voxels" | "irradiance" => anyhow::bail!(
            "technique `{technique}` is not implemented yet; benchmarks exist for `photons`"
        ),
        other => anyhow::bail!("unknown technique `{other}` (photons, voxels, irradiance)"),
    }
}

fn report_error(e: anyhow::Error) -> ExitCode {
    eprintln!("error: {e:#}");
    ExitCode::FAILURE
}

fn async_runtime() -> Option<tokio::runtime::Runtime> {
    match tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
    {
        Ok(r) => Some(r),
        Err(e) => {
            eprintln!("cannot start the async runtime: {e}");
            None
        }
    }
}

/// A camera from `--camera`: an index into the scene's paths, or `eye:target[:fov_deg]`.
fn parse_camera(
    spec: &str,
    scene: &cloudlight::scenes::Scene,
    time_s: f64,
) -> Result<cloudlight::scenes::Camera, String> {
    use cloudlight::scenes::Camera;
    use cloudlight::scenes::glam::Vec3;
    let vec3 = Vec3::from_array;
    if let Ok(i) = spec.parse::<usize>() {
        return scene.cameras.get(i).map(|c| c.at(time_s)).ok_or_else(|| {
            format!(
                "scene `{}` has {} camera paths; --camera {i} is none of them",
                scene.name,
                scene.cameras.len()
            )
        });
    }
    let parts: Vec<&str> = spec.split(':').collect();
    let err = || format!("--camera `{spec}`: expected an index or `px,py,pz:tx,ty,tz[:fov_deg]`");
    if !(2..=3).contains(&parts.len()) {
        return Err(err());
    }
    let point = |s: &str| -> Result<[f32; 3], String> {
        let v: Vec<f32> = s
            .split(',')
            .map(|x| x.trim().parse::<f32>())
            .collect::<Result<_, _>>()
            .map_err(|_| err())?;
        <[f32; 3]>::try_from(v).map_err(|_| err())
    };
    let fov: f32 = parts
        .get(2)
        .map_or(Ok(45.0), |f| f.parse().map_err(|_| err()))?;
    Ok(Camera {
        position: vec3(point(parts[0])?),
        target: vec3(point(parts[1])?),
        up: vec3([0.0, 1.0, 0.0]),
        fov_y_rad: fov.to_radians(),
    })
}

fn reference(args: ReferenceArgs) -> ExitCode {
    use cloudlight::render::{
        BvhKind, ReferenceImages, ReferenceRenderer, RenderSettings, SceneBvh, image_io,
    };
    let scene = match cloudlight::scenes::load(&args.scene) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::from(2);
        }
    };
    let camera = match parse_camera(&args.camera, &scene, args.time) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::from(2);
        }
    };
    if args.width == 0 || args.height == 0 || args.spp == 0 {
        eprintln!("error: width, height and spp must be at least 1");
        return ExitCode::from(2);
    }
    if let Err(e) = std::fs::create_dir_all(&args.out) {
        eprintln!("error: cannot create {}: {e}", args.out.display());
        return ExitCode::FAILURE;
    }
    let t0 = Instant::now();
    let bvh = SceneBvh::at(&scene, args.time, BvhKind::default());
    let settings = RenderSettings {
        width: args.width,
        height: args.height,
        camera,
        time_s: args.time,
        seed: args.seed,
        max_bounces: 256,
    };
    let renderer = ReferenceRenderer::new(&scene, &bvh, settings);
    let mut images = ReferenceImages::new(args.width, args.height);
    let bar = ProgressBar::new(args.spp as u64).with_style(
        ProgressStyle::with_template("{elapsed_precise} [{bar:30}] {pos}/{len} spp, eta {eta}")
            .expect("valid template")
            .progress_chars("=> "),
    );
    let render_start = Instant::now();
    let pass = 4.min(args.spp);
    let mut done = 0;
    while done < args.spp {
        let n = pass.min(args.spp - done);
        renderer.render_pass(&mut images, done, n);
        done += n;
        bar.set_position(done as u64);
    }
    bar.finish_and_clear();
    let render_s = render_start.elapsed().as_secs_f64();
    let full = images.full();
    let stops = image_io::auto_exposure(&full);
    for (name, img) in [
        ("full", full.clone()),
        ("direct", images.direct()),
        ("indirect", images.indirect()),
    ] {
        for r in [
            image_io::write_exr(
                &args.out.join(format!("{name}.exr")),
                args.width,
                args.height,
                &img,
            ),
            image_io::write_png(
                &args.out.join(format!("{name}.png")),
                args.width,
                args.height,
                &img,
                stops,
            ),
        ] {
            if let Err(e) = r {
                eprintln!("error: {e}");
                return ExitCode::FAILURE;
            }
        }
    }
    println!(
        "{}: {}x{} at {} spp, time {} s: rendered in {:.2} s ({:.2} s with BVH build); wrote full, direct and indirect .exr/.png to {}",
        scene.name,
        args.width,
        args.height,
        args.spp,
        args.time,
        render_s,
        t0.elapsed().as_secs_f64(),
        args.out.display()
    );
    ExitCode::SUCCESS
}

fn bench_rays(scene: &str, threads: &[usize], rounds: usize) -> ExitCode {
    let t = Instant::now();
    let scene = match cloudlight::scenes::load(scene) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::from(2);
        }
    };
    eprintln!(
        "{}: {} triangles, generated in {:.2} s",
        scene.name,
        scene.triangle_count(),
        t.elapsed().as_secs_f64()
    );
    let rows = cloudlight::render::raybench::run(&scene, threads, rounds.max(1));
    let mut table = comfy_table::Table::new();
    table
        .load_preset(comfy_table::presets::UTF8_FULL_CONDENSED)
        .set_header([
            "BVH",
            "threads",
            "build s",
            "coherent Mrays/s",
            "incoherent Mrays/s",
        ]);
    let mut json = Vec::new();
    for r in &rows {
        table.add_row([
            format!("{:?}", r.kind),
            r.threads.to_string(),
            format!("{:.3}", r.build_s),
            format!("{:.2}", r.coherent_mrays_s),
            format!("{:.2}", r.incoherent_mrays_s),
        ]);
        json.push(serde_json::json!({
            "bvh": format!("{:?}", r.kind), "threads": r.threads, "build_s": r.build_s,
            "coherent_mrays_s": r.coherent_mrays_s, "incoherent_mrays_s": r.incoherent_mrays_s,
        }));
    }
    println!("{table}");
    println!(
        "{}",
        serde_json::json!({ "scene": scene.name, "triangles": scene.triangle_count(), "rows": json })
    );
    ExitCode::SUCCESS
}

fn plan(scene: &str) -> ExitCode {
    use cloudlight::render::plan::{PlanSettings, plan};
    let scene = match cloudlight::scenes::load(scene) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::from(2);
        }
    };
    let settings = PlanSettings::default();
    let p = plan(&scene, &settings);
    let (lo, hi) = p.bounds;
    println!(
        "scene {}: {} triangles, {:.3} m² of surface{}",
        scene.name,
        p.triangles,
        p.area_m2,
        if p.animated { ", animated" } else { "" }
    );
    println!(
        "bounds [{:.3}, {:.3}, {:.3}] .. [{:.3}, {:.3}, {:.3}] m",
        lo.x, lo.y, lo.z, hi.x, hi.y, hi.z
    );
    println!(
        "emitted power (lights and emissive surfaces, directional excluded): {:.4} / {:.4} / {:.4} W (R/G/B)",
        p.emitted_w.x, p.emitted_w.y, p.emitted_w.z
    );
    for l in &scene.lights {
        println!(
            "  light {}: {:?}, {:.4} W",
            l.name,
            l.kind,
            l.power_w.element_sum()
        );
    }
    let mut t = comfy_table::Table::new();
    t.load_preset(comfy_table::presets::UTF8_FULL_CONDENSED)
        .set_header([
            "photons: light",
            "W (sum of channels)",
            "photons",
            "batches",
        ]);
    for l in &p.lights {
        t.add_row([
            l.name.clone(),
            format!("{:.4}", l.power_w),
            l.photons.to_string(),
            l.batches.to_string(),
        ]);
    }
    println!(
        "photons ({} per W, {} per batch):\n{t}",
        settings.photons_per_watt, settings.batch_size
    );
    let mut v = comfy_table::Table::new();
    v.load_preset(comfy_table::presets::UTF8_FULL_CONDENSED)
        .set_header(["voxels: level", "grid", "occupied", "of grid"]);
    for (l, n) in p.voxels_per_level.iter().enumerate() {
        let cells = 1u64 << (3 * l);
        v.add_row([
            l.to_string(),
            format!("{0}³", 1u64 << l),
            n.to_string(),
            format!("{:.3}%", *n as f64 / cells as f64 * 100.0),
        ]);
    }
    println!("voxels (leaf {:.4} m):\n{v}", p.leaf_voxel_m);
    println!(
        "irradiance maps at the Cornell density ({:.0} texels per m²): {} texels (about {}²), {} bases of {:.0} texels; \
         a 1024² atlas would give each texel {:.4} m²",
        settings.texels_per_m2,
        p.lightmap_texels,
        (p.lightmap_texels as f64).sqrt().ceil(),
        p.bases,
        settings.texels_per_basis,
        p.area_m2 / (1024.0 * 1024.0)
    );
    ExitCode::SUCCESS
}

fn bench_raster(scene: &str, rounds: usize) -> ExitCode {
    use cloudlight::render::raster::{Raster, ShadowSettings};
    let scene = match cloudlight::scenes::load(scene) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::from(2);
        }
    };
    let raster = match Raster::new() {
        Ok(r) => r,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::FAILURE;
        }
    };
    let tris = scene.triangles_at(0.0);
    let mut lights: Vec<_> = scene.lights.iter().map(|l| l.at(0.0)).collect();
    lights.extend(scene.surface_light_samples(0.0, 2));
    let camera = scene.cameras[0].at(0.0);
    let mut times = Vec::new();
    for i in 0..=rounds.max(1) {
        let t = Instant::now();
        if let Err(e) = raster.direct(
            &scene,
            &tris,
            &lights,
            &camera,
            1280,
            720,
            ShadowSettings::default(),
        ) {
            eprintln!("error: {e}");
            return ExitCode::FAILURE;
        }
        if i > 0 {
            times.push(t.elapsed().as_secs_f64() * 1000.0);
        }
    }
    times.sort_by(f64::total_cmp);
    let info = raster.adapter();
    println!(
        "{}: {} triangles, {} lights, 1280x720 G-buffer + direct with {}² shadow maps on {} ({:?}): median {:.1} ms per frame (min {:.1}, max {:.1}; includes upload and read-back)",
        scene.name,
        tris.len(),
        lights.len(),
        ShadowSettings::default().size,
        info.name,
        info.backend,
        times[times.len() / 2],
        times[0],
        times[times.len() - 1]
    );
    ExitCode::SUCCESS
}
