//! `cloudlight bench …`: transport, raster, ray casting, the client's frame, and the paper's
//! Table 2, scaling and quality for a technique.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::Subcommand;

use crate::cli::ranges;

mod client;
mod lighting;
mod raster;
mod rays;
mod transport;
mod video;

#[derive(Subcommand)]
pub enum BenchCommand {
    /// Two transport endpoints on loopback exchange messages through the link emulator:
    /// delivered, byte-identical, in order, goodput, retransmissions, message round trips,
    /// against a plain UDP blast of the same bytes in datagrams of the same size.
    ///
    /// Prints a table and the JSON report (also written to --json PATH if given).
    Transport(transport::Args),
    /// Raster on wgpu: one cold G-buffer + direct-light frame with shadow maps of a scene's
    /// view at 1280x720 (targets and uploads included; median of --rounds frames, after one
    /// warm-up). `bench client` measures the steady state.
    Raster {
        /// Scene: `cornell`, `cornell-animated`, `city:N` or a .gltf/.glb file.
        #[arg(long, default_value = "city:100000")]
        scene: String,
        /// Frames timed.
        #[arg(long, default_value_t = 5, value_parser = ranges::count::<usize>(1, 1000))]
        rounds: usize,
    },
    /// A technique's client frame alone on the machine: frame time p50/p99, whole and split
    /// by pass (G-buffer, shadows, direct, the technique's indirect pass, compose,
    /// read-back), as a table and JSON.
    Client(client::Args),
    /// The paper's Table 2 rows for a technique, one column per scene, each beside the
    /// paper's figures for the scene of the nearest polygon count.
    ///
    /// Runs the real stages (a cloud node and one client node over loopback) with every
    /// light re-traced each `--interval-ms`, then times the client's indirect pass on wgpu.
    /// Prints a Markdown table and JSON (also written to --json PATH if given).
    Table2(lighting::Table2Args),
    /// Scaling over client counts (the paper's Figures 3–5): server time per update, total
    /// Mbps and age of indirect light for each count, as a table, JSON and a PNG plot.
    Scaling(lighting::ScalingArgs),
    /// Speed/accuracy trade over budgets: scale-invariant relMSE, HDR-FLIP and the energy
    /// ratio of the client's indirect light against the path tracer's indirect-only image of
    /// the same view and time, with update time and Mbps; a table, JSON and a Pareto plot.
    Quality(lighting::QualityArgs),
    /// H.264 video (openh264, one core): encode and decode ms per frame, Mbps at 30 Hz and
    /// PSNR for SDR client frames at 640x360 and 1280x720 under 3 bitrates and a fixed QP,
    /// and the relative luminance and chroma error of an HDR light map packed into 8-bit
    /// 4:2:0 (alone and coded, per QP); the paper's hardware-encoder figures beside ours.
    Video(video::Args),
    /// Ray casting on a scene: BVH build time, and million rays per second for coherent
    /// camera rays (1280x720) and incoherent diffuse-bounce rays, for CWBVH and BVH2 at each
    /// thread count (best of --rounds passes).
    Rays {
        /// Scene: `cornell`, `cornell-animated`, `city:N` or a .gltf/.glb file.
        #[arg(long, default_value = "city:250000")]
        scene: String,
        /// Thread counts, comma-separated.
        #[arg(long, value_delimiter = ',', default_value = "1,2", value_parser = ranges::count::<usize>(1, 1024))]
        threads: Vec<usize>,
        /// Passes over the rays; the best is kept.
        #[arg(long, default_value_t = 3, value_parser = ranges::count::<usize>(1, 1000))]
        rounds: usize,
    },
}

pub fn run(what: BenchCommand) -> ExitCode {
    match what {
        BenchCommand::Transport(a) => transport::run(a),
        BenchCommand::Raster { scene, rounds } => raster::run(&scene, rounds),
        BenchCommand::Client(a) => client::run(a),
        BenchCommand::Table2(a) => lighting::table2(a),
        BenchCommand::Scaling(a) => lighting::scaling(a),
        BenchCommand::Quality(a) => lighting::quality(a),
        BenchCommand::Video(a) => video::run(a),
        BenchCommand::Rays {
            scene,
            threads,
            rounds,
        } => rays::run(&scene, &threads, rounds),
    }
}

/// Writes `json` to `path` when one was asked for.
fn write_json(path: Option<&PathBuf>, json: &str) -> anyhow::Result<()> {
    if let Some(p) = path {
        std::fs::write(p, json)
            .map_err(|e| anyhow::anyhow!("cannot write {}: {e}", p.display()))?;
    }
    Ok(())
}
