//! `cloudlight bench …`: transport, raster, ray casting, the client's frame, and the paper's
//! Table 2, scaling and quality for a technique.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::Subcommand;

use crate::cli::ranges;

mod client;
mod fronts;
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
    /// The Pareto fronts of saved photon `bench quality` runs (their quality.json) drawn
    /// together in one plot, and their points as a table: before and after a change made
    /// anywhere (another commit's build, other knobs, another seed).
    Fronts(fronts::Args),
    /// H.264 video (openh264, one core): encode and decode ms per frame, Mbps at 30 Hz and
    /// PSNR for SDR client frames at 640x360 and 1280x720 under 3 bitrates and a fixed QP,
    /// and the relative luminance and chroma error of an HDR light map packed into 8-bit
    /// 4:2:0 (alone and coded, per QP); the paper's hardware-encoder figures beside ours.
    Video(video::Args),
    /// Ray casting on a scene: BVH build times and million rays per second on camera rays
    /// (1280x720), a diffuse bounce from each of their hits and 1M random rays in the bounds,
    /// per backend and thread count (median of --passes after a warm-up, the backends taking
    /// their passes and builds in turn so that load on the machine falls on all alike), with
    /// the agreement of every backend's hits with the reference's (Embree one ray at a time
    /// when loaded).
    Rays {
        /// Scene: `cornell`, `cornell-animated`, `city:N` or a .gltf/.glb file.
        #[arg(long, default_value = "city:250000")]
        scene: String,
        /// Thread counts, comma-separated.
        #[arg(long, value_delimiter = ',', default_value = "1,2", value_parser = ranges::count::<usize>(1, 1024))]
        threads: Vec<usize>,
        /// Timed passes over each ray set after one warm-up; the median is reported.
        #[arg(long, alias = "rounds", default_value_t = 5, value_parser = ranges::count::<usize>(1, 1000))]
        passes: usize,
        /// Also cast the same rays with Embree 3 (Debian's libembree-dev, opened at run time;
        /// CLOUDLIGHT_EMBREE names another libembree3.so): one ray at a time, 8-wide packets
        /// and streams, and print our speed as a ratio of Embree's best.
        #[arg(long)]
        against_embree: bool,
        /// Also write the figures as JSON here.
        #[arg(long)]
        json: Option<PathBuf>,
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
        BenchCommand::Fronts(a) => fronts::run(a),
        BenchCommand::Video(a) => video::run(a),
        BenchCommand::Rays {
            scene,
            threads,
            passes,
            against_embree,
            json,
        } => rays::run(&scene, &threads, passes, against_embree, json.as_ref()),
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
