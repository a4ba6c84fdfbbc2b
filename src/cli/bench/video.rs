//! `cloudlight bench video`: H.264 cost and quality of SDR client frames and HDR light maps.

use std::path::PathBuf;
use std::process::ExitCode;

use cloudlight::bench::video::VideoBenchOptions;
use cloudlight::render::raster::Raster;

use crate::cli::ranges;

/// Options of `bench video`.
#[derive(clap::Args)]
pub struct Args {
    /// Scene the client frames show.
    #[arg(long, default_value = "cornell-animated")]
    scene: String,
    /// Frames encoded per size and rate.
    #[arg(long, default_value_t = 30, value_parser = ranges::count::<usize>(1, 10_000))]
    frames: usize,
    /// Only 640x360 (skip 1280x720).
    #[arg(long)]
    small: bool,
    /// HDR light-map side, texels (even).
    #[arg(long, default_value_t = 128, value_parser = ranges::count::<u32>(2, 2048))]
    hdr_size: u32,
    /// Reference samples per texel of the HDR map.
    #[arg(long, default_value_t = 256, value_parser = ranges::count::<u32>(1, 65_536))]
    hdr_spp: u32,
    /// Also write the JSON report to this file.
    #[arg(long, value_name = "PATH")]
    json: Option<PathBuf>,
}

pub fn run(a: Args) -> ExitCode {
    let go = || -> anyhow::Result<()> {
        if a.hdr_size % 2 == 1 {
            anyhow::bail!("--hdr-size must be even (4:2:0 video)");
        }
        let raster = Raster::new()?;
        let mut opts = VideoBenchOptions {
            scene: a.scene.clone(),
            frames: a.frames,
            hdr_size: a.hdr_size,
            hdr_spp: a.hdr_spp,
            ..Default::default()
        };
        if a.small {
            opts.sizes.truncate(1);
        }
        let report = cloudlight::bench::video::run(&raster, &opts)?;
        println!("{}", cloudlight::bench::video::markdown(&report));
        let json = serde_json::to_string_pretty(&report)?;
        println!("{json}");
        super::write_json(a.json.as_ref(), &json)
    };
    go().map_or_else(crate::cli::report_error, |()| ExitCode::SUCCESS)
}
