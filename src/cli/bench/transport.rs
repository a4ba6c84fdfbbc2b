//! `cloudlight bench transport`: two endpoints through the link emulator on loopback,
//! against a plain UDP blast of the same datagrams.

use std::path::PathBuf;
use std::process::ExitCode;

use crate::cli::ranges;

/// Options of `bench transport`.
#[derive(clap::Args)]
pub struct Args {
    /// Bytes per message.
    #[arg(long, default_value_t = 1024, value_parser = ranges::count::<usize>(1, ranges::MAX_MESSAGE_BYTES))]
    size: usize,
    /// Messages in the bulk phase (per client), or requests per client.
    #[arg(long, default_value_t = 10_000, value_parser = ranges::count::<usize>(1, 100_000_000))]
    count: usize,
    /// Traffic: `bulk` (the sender streams to every client) or `request-response` (each
    /// client sends requests one at a time, each echoed back).
    #[arg(long, value_enum, default_value_t = PatternArg::Bulk)]
    pattern: PatternArg,
    /// Receiving nodes, each with its own socket: the sender fans out to all of them.
    #[arg(long, default_value_t = 1, value_parser = ranges::count::<usize>(1, 1000))]
    clients: usize,
    /// Loss probability in [0, 1], applied in both directions.
    #[arg(long, default_value_t = 0.0, value_parser = ranges::probability())]
    loss: f64,
    /// One-way latency, milliseconds.
    #[arg(long, default_value_t = 0.0, value_parser = ranges::closed(0.0, 60_000.0, "ms"))]
    latency_ms: f64,
    /// Latency standard deviation, milliseconds.
    #[arg(long, default_value_t = 0.0, value_parser = ranges::closed(0.0, 60_000.0, "ms"))]
    jitter_ms: f64,
    /// Bandwidth cap per direction, megabits per second (default: none).
    #[arg(long, value_parser = ranges::closed(1e-6, 1e6, "Mbit/s"))]
    bandwidth_mbps: Option<f64>,
    /// Duplication probability in [0, 1].
    #[arg(long, default_value_t = 0.0, value_parser = ranges::probability())]
    duplicate: f64,
    /// Reordering probability in [0, 1].
    #[arg(long, default_value_t = 0.0, value_parser = ranges::probability())]
    reorder: f64,
    /// Largest packet handed to laminar, bytes (the UDP datagram is 5 bytes more).
    #[arg(long, default_value_t = 1200, value_parser = ranges::count::<usize>(128, 65_000))]
    packet_bytes: usize,
    /// Messages in flight end to end (the edge capacity) [default: as many as hold 4 MiB,
    /// at least 64: the window the receiver agrees to hold is bytes, and 64 messages of 1 KiB
    /// are 64 KiB per credit round trip, which limits a stream to ~250 MB/s here]
    #[arg(long, value_parser = ranges::count::<u64>(1, 1_000_000))]
    capacity: Option<u64>,
    /// Most unacknowledged packets per peer (the transport's send window).
    #[arg(long, default_value_t = 1024, value_parser = ranges::count::<usize>(1, 65_536))]
    window: usize,
    /// Message round trips measured after the bulk phase [default: 200, fewer for large
    /// messages so that the round trips move at most 64 MiB each way, at least 5].
    #[arg(long, value_parser = ranges::count::<usize>(1, 1_000_000))]
    rtt_rounds: Option<usize>,
    /// Authenticate packets without encrypting them (what `encrypt = false` does).
    #[arg(long)]
    no_encrypt: bool,
    /// Turn congestion control off (a fixed window, unpaced): what `congestion_control =
    /// false` does.
    #[arg(long)]
    no_congestion_control: bool,
    /// Move datagrams one per system call through laminar (what `batched_io = false` does)
    /// instead of the batched path (UDP GSO/GRO).
    #[arg(long)]
    laminar_io: bool,
    /// Skip the plain UDP blast baseline.
    #[arg(long)]
    no_baseline: bool,
    /// Seed of the link emulators.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Longest the bench may take, seconds; messages not delivered by then are missing.
    #[arg(long, default_value_t = 120.0, value_parser = ranges::above(0.0, 86_400.0, "seconds"))]
    time_limit_s: f64,
    /// Also write the JSON report to this file.
    #[arg(long, value_name = "PATH")]
    json: Option<PathBuf>,
}

/// `--pattern`.
#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum PatternArg {
    Bulk,
    RequestResponse,
}

/// The bench's options, or why they are not valid.
fn options(args: &Args) -> Result<cloudlight::transport::bench::BenchOptions, String> {
    use cloudlight::transport::LinkProfile;
    use cloudlight::transport::bench::BenchOptions;
    // Every number was range-checked by its flag's parser.
    Ok(BenchOptions {
        size: args.size,
        count: args.count,
        rtt_rounds: args
            .rtt_rounds
            .unwrap_or_else(|| ((64 << 20) / args.size.max(1)).clamp(5, 200)),
        link: LinkProfile {
            latency_ms: args.latency_ms,
            jitter_ms: args.jitter_ms,
            bandwidth_mbps: args.bandwidth_mbps,
            loss: args.loss,
            duplicate: args.duplicate,
            reorder: args.reorder,
        },
        packet_bytes: args.packet_bytes,
        capacity: args
            .capacity
            .unwrap_or_else(|| cloudlight_transport::bench::default_capacity(args.size)),
        window_packets: args.window.max(1),
        seed: args.seed,
        udp_baseline: !args.no_baseline,
        encrypt: !args.no_encrypt,
        congestion_control: !args.no_congestion_control,
        time_limit: std::time::Duration::from_secs_f64(args.time_limit_s),
        pattern: match args.pattern {
            PatternArg::Bulk => cloudlight::transport::bench::Pattern::Bulk,
            PatternArg::RequestResponse => cloudlight::transport::bench::Pattern::RequestResponse,
        },
        clients: args.clients,
        batched_io: !args.laminar_io,
    })
}

/// The report as a two-column table.
fn table(report: &cloudlight::transport::bench::BenchReport) -> comfy_table::Table {
    let yes = |b: bool| if b { "yes" } else { "NO" }.to_string();
    let judged = |b: Option<bool>| b.map_or("– (none delivered)".to_string(), yes);
    let mut t = crate::cli::table(["measure", "value"]);
    let rows = [
        (
            "messages delivered / offered",
            format!(
                "{} / {}",
                report.delivered,
                report.options.count * report.options.clients
            ),
        ),
        ("all delivered", yes(report.complete)),
        (
            "byte-identical (of those delivered)",
            judged(report.byte_identical),
        ),
        ("in order (of those delivered)", judged(report.in_order)),
        ("sessions up after ms", format!("{:.1}", report.connect_ms)),
        ("goodput MB/s", format!("{:.1}", report.goodput_mb_s)),
        (
            "per client MB/s, min / max",
            format!(
                "{:.1} / {:.1}",
                report
                    .client_goodput_mb_s
                    .iter()
                    .copied()
                    .fold(f64::INFINITY, f64::min),
                report
                    .client_goodput_mb_s
                    .iter()
                    .copied()
                    .fold(0.0, f64::max)
            ),
        ),
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
            "message completion p50 / p99 ms",
            format!(
                "{:.2} / {:.2}",
                report.completion_ms_p50, report.completion_ms_p99
            ),
        ),
        (
            "round trip p50 / p99 us",
            format!("{:.0} / {:.0}", report.rtt_p50_us, report.rtt_p99_us),
        ),
    ];
    for (k, v) in rows {
        t.add_row([k.to_string(), v]);
    }
    t
}

pub fn run(args: Args) -> ExitCode {
    let opts = match options(&args) {
        Ok(o) => o,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::from(2);
        }
    };
    let rt = match crate::cli::async_runtime() {
        Ok(r) => r,
        Err(e) => return crate::cli::report_error(e),
    };
    eprintln!(
        "transport bench: {:?}, {} client(s), {} messages of {} bytes each, link {:?}",
        opts.pattern, opts.clients, args.count, args.size, opts.link
    );
    let interrupted = async {
        if tokio::signal::ctrl_c().await.is_err() {
            std::future::pending::<()>().await;
        }
    };
    let outcome = rt.block_on(async {
        tokio::select! {
            r = cloudlight::transport::bench::run(opts) => Some(r),
            _ = interrupted => None,
        }
    });
    let report = match outcome {
        Some(Ok(r)) => r,
        Some(Err(e)) => {
            eprintln!("error: {e}");
            return ExitCode::FAILURE;
        }
        None => {
            eprintln!("interrupted");
            return ExitCode::from(130);
        }
    };
    println!("{}", table(&report));
    let json = serde_json::to_string_pretty(&report).expect("report serializes");
    println!("{json}");
    if let Err(e) = super::write_json(args.json.as_ref(), &json) {
        return crate::cli::report_error(e);
    }
    let intact = report.byte_identical == Some(true) && report.in_order == Some(true);
    if report.complete && intact {
        ExitCode::SUCCESS
    } else {
        eprintln!(
            "error: {} of {} messages delivered{}{}",
            report.delivered,
            report.options.count,
            match report.byte_identical {
                Some(false) => ", some damaged",
                _ => "",
            },
            match report.in_order {
                Some(false) => ", out of order",
                _ => "",
            },
        );
        ExitCode::from(4)
    }
}
