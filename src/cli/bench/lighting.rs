//! `cloudlight bench table2|scaling|quality --technique T`: the paper's measurements for a
//! technique, through the harness of `cloudlight::bench`.

use std::path::PathBuf;
use std::process::ExitCode;

use crate::cli::ranges;

use cloudlight::bench::baseline::{self, VideoCutOptions};
use cloudlight::bench::photons::{PhotonOptions, Photons, QualityOptions};
use cloudlight::bench::{ClusterOptions, default_out, require_technique};
use cloudlight::render::raster::Raster;
use cloudlight::transport::LinkProfile;

/// Options of `bench table2`.
#[derive(clap::Args)]
pub struct Table2Args {
    /// Technique: `photons`, or `photons-video` (the photon cut beside the full-frame
    /// baseline: each client's frame rendered and H.264-encoded in the cloud, a thin client
    /// decoding it); `voxels` and `irradiance` are not implemented yet.
    #[arg(long, default_value = "photons")]
    technique: String,
    /// Scenes, comma-separated: `cornell`, `city:N`, a .gltf/.glb file.
    #[arg(long, value_delimiter = ',', default_value = "cornell")]
    scene: Vec<String>,
    /// Photons per iteration, one per scene (the last repeats).
    #[arg(long, value_delimiter = ',', default_value = "10000", value_parser = ranges::count::<u64>(1, ranges::MAX_PHOTONS))]
    photons: Vec<u64>,
    /// Photons per batch.
    #[arg(long, default_value_t = 10_000, value_parser = ranges::count::<u32>(1, ranges::MAX_BATCH))]
    batch_size: u32,
    /// Iteration period, milliseconds.
    #[arg(long, default_value_t = 33.0, value_parser = ranges::closed(0.0, 3.6e6, "ms"))]
    interval_ms: f64,
    /// Seconds each scene runs.
    #[arg(long, default_value_t = 5.0, value_parser = ranges::above(0.0, 86_400.0, "seconds"))]
    seconds: f64,
    /// Client frame width for the indirect time.
    #[arg(long, default_value_t = 1280, value_parser = ranges::count::<u32>(1, ranges::MAX_FRAME_SIDE))]
    width: u32,
    /// Client frame height for the indirect time.
    #[arg(long, default_value_t = 720, value_parser = ranges::count::<u32>(1, ranges::MAX_FRAME_SIDE))]
    height: u32,
    /// `photons-video`: the encoder's target bitrate, Mbit/s.
    #[arg(long, default_value_t = 3.0, value_parser = ranges::closed(0.01, 1000.0, "Mbit/s"))]
    bitrate_mbps: f64,
    /// `photons-video`: frames per second the cloud renders and encodes per client (at most).
    #[arg(long, default_value_t = 30.0, value_parser = ranges::closed(0.1, 240.0, "fps"))]
    fps: f64,
    /// Also write the JSON report to this file.
    #[arg(long, value_name = "PATH")]
    json: Option<PathBuf>,
}

/// Options of `bench scaling`.
#[derive(clap::Args)]
pub struct ScalingArgs {
    /// Technique (`photons`; `voxels` and `irradiance` are not implemented yet).
    #[arg(long, default_value = "photons")]
    technique: String,
    /// Client counts, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "1,2,5,10,20,50", value_parser = ranges::count::<usize>(0, 1000))]
    clients: Vec<usize>,
    /// Scene.
    #[arg(long, default_value = "cornell-animated")]
    scene: String,
    /// Photons per iteration.
    #[arg(long, default_value_t = 10_000, value_parser = ranges::count::<u64>(1, ranges::MAX_PHOTONS))]
    photons: u64,
    /// Photons per batch.
    #[arg(long, default_value_t = 10_000, value_parser = ranges::count::<u32>(1, ranges::MAX_BATCH))]
    batch_size: u32,
    /// Iteration period, milliseconds.
    #[arg(long, default_value_t = 33.0, value_parser = ranges::closed(0.0, 3.6e6, "ms"))]
    interval_ms: f64,
    /// Seconds per client count.
    #[arg(long, default_value_t = 4.0, value_parser = ranges::above(0.0, 86_400.0, "seconds"))]
    seconds: f64,
    /// Emulate no link (plain loopback) instead of the campus link (5 ms ± 1 ms,
    /// 1 Gbit/s, 0.1% loss).
    #[arg(long)]
    no_link: bool,
    /// Output folder for scaling.json and scaling.png [default: runs/bench-scaling-<time>].
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
}

/// Options of `bench quality`.
#[derive(clap::Args)]
pub struct QualityArgs {
    /// Technique (`photons`; `voxels` and `irradiance` are not implemented yet).
    #[arg(long, default_value = "photons")]
    technique: String,
    /// Scene.
    #[arg(long, default_value = "cornell")]
    scene: String,
    /// Photon budgets per iteration, comma-separated.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "2500,5000,10000,40000,160000",
        value_parser = ranges::count::<u64>(1, ranges::MAX_PHOTONS)
    )]
    budgets: Vec<u64>,
    /// Photons per batch.
    #[arg(long, default_value_t = 10_000, value_parser = ranges::count::<u32>(1, ranges::MAX_BATCH))]
    batch_size: u32,
    /// Reference samples per pixel.
    #[arg(long, default_value_t = 4096, value_parser = ranges::count::<u32>(1, ranges::MAX_SPP))]
    spp: u32,
    /// Image width.
    #[arg(long, default_value_t = 128, value_parser = ranges::count::<u32>(1, 4096))]
    width: u32,
    /// Image height.
    #[arg(long, default_value_t = 128, value_parser = ranges::count::<u32>(1, 4096))]
    height: u32,
    /// Update rate the Mbps column assumes (capped by the update time), Hz.
    #[arg(long, default_value_t = 30.0, value_parser = ranges::closed(0.001, 1e6, "Hz"))]
    rate_hz: f64,
    /// Output folder [default: runs/bench-quality-<time>].
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
}

pub fn table2(a: Table2Args) -> ExitCode {
    if a.technique == baseline::NAME {
        return table2_baseline(a);
    }
    let go = || -> anyhow::Result<()> {
        require_technique(&a.technique)?;
        let rt = crate::cli::async_runtime()?;
        let raster = Raster::new()?;
        let options = PhotonOptions {
            batch_size: a.batch_size,
            interval_ms: a.interval_ms,
            ..PhotonOptions::default()
        };
        let cluster = ClusterOptions {
            scene: String::new(),
            seconds: a.seconds,
            link: None,
            seed: 1,
        };
        let columns = cloudlight::bench::photons::table2(
            &rt,
            &raster,
            &a.scene,
            &a.photons,
            &options,
            &cluster,
            (a.width, a.height),
        )?;
        println!("{}", cloudlight::bench::photons::table2_markdown(&columns));
        println!(
            "Iterations every {} ms with every light re-traced (the paper's continuous stream), 1 client over loopback; \
             client indirect at {}x{} on {}. Paper: GeForce Titan cloud, GeForce 670 client.",
            a.interval_ms,
            a.width,
            a.height,
            raster.describe()
        );
        let json = serde_json::to_string_pretty(
            &serde_json::json!({ "technique": "photons", "columns": columns }),
        )?;
        println!("{json}");
        super::write_json(a.json.as_ref(), &json)
    };
    go().map_or_else(crate::cli::report_error, |()| ExitCode::SUCCESS)
}

/// `bench table2 --technique photons-video`.
fn table2_baseline(a: Table2Args) -> ExitCode {
    let go = || -> anyhow::Result<()> {
        let rt = crate::cli::async_runtime()?;
        let raster = Raster::new()?;
        let photons = PhotonOptions {
            batch_size: a.batch_size,
            interval_ms: a.interval_ms,
            ..PhotonOptions::default()
        };
        let video = VideoCutOptions {
            bitrate_mbps: a.bitrate_mbps,
            fps: a.fps,
            ..VideoCutOptions::default()
        };
        let cluster = ClusterOptions {
            scene: String::new(),
            seconds: a.seconds,
            link: None,
            seed: 1,
        };
        let columns = baseline::table2(
            &rt,
            &raster,
            &a.scene,
            &a.photons,
            &photons,
            &video,
            &cluster,
            (a.width, a.height),
        )?;
        println!("{}", baseline::markdown(&columns));
        println!(
            "Per client, 1 client over loopback, {}x{}; photon iterations every {} ms; video at up to {} fps, {} Mbit/s target, \
             openh264 on one core; raster on {}. The photon cut's server cost is shared by every client, the video cut's \
             frame and encode are paid once per client. Paper: GeForce Titan + Quadro K5000 with a hardware encoder.",
            a.width,
            a.height,
            a.interval_ms,
            a.fps,
            a.bitrate_mbps,
            raster.describe()
        );
        let json = serde_json::to_string_pretty(&serde_json::json!({
            "technique": baseline::NAME,
            "video": video,
            "columns": columns,
        }))?;
        println!("{json}");
        super::write_json(a.json.as_ref(), &json)
    };
    go().map_or_else(crate::cli::report_error, |()| ExitCode::SUCCESS)
}

pub fn scaling(a: ScalingArgs) -> ExitCode {
    let go = || -> anyhow::Result<()> {
        require_technique(&a.technique)?;
        if a.clients.is_empty() {
            anyhow::bail!("--clients lists no count");
        }
        let rt = crate::cli::async_runtime()?;
        let options = PhotonOptions {
            photons: a.photons,
            batch_size: a.batch_size,
            interval_ms: a.interval_ms,
            ..PhotonOptions::default()
        };
        let cluster = ClusterOptions {
            scene: a.scene.clone(),
            seconds: a.seconds,
            link: (!a.no_link).then_some(LinkProfile::CAMPUS),
            seed: 1,
        };
        let out = a.out.clone().unwrap_or_else(|| default_out("scaling"));
        cloudlight::bench::scaling::<Photons>(&rt, &options, &cluster, &a.clients, &out)?;
        Ok(())
    };
    go().map_or_else(crate::cli::report_error, |()| ExitCode::SUCCESS)
}

pub fn quality(a: QualityArgs) -> ExitCode {
    let go = || -> anyhow::Result<()> {
        require_technique(&a.technique)?;
        if a.budgets.is_empty() {
            anyhow::bail!("--budgets lists no budget");
        }
        let raster = Raster::new()?;
        let options = QualityOptions {
            budgets: a.budgets.clone(),
            batch_size: a.batch_size,
            spp: a.spp,
            width: a.width,
            height: a.height,
            rate_hz: a.rate_hz,
            seed: 5,
        };
        let out = a.out.clone().unwrap_or_else(|| default_out("quality"));
        cloudlight::bench::photons::quality(&raster, &a.scene, &options, &out)?;
        Ok(())
    };
    go().map_or_else(crate::cli::report_error, |()| ExitCode::SUCCESS)
}
