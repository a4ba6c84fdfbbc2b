//! `cloudlight bench client --technique T`: the client's frame split by pass.

use std::path::PathBuf;
use std::process::ExitCode;

use crate::cli::ranges;

use cloudlight::bench::client::ClientBenchOptions;
use cloudlight::bench::{self, Technique, Visit};
use cloudlight::render::raster::Raster;

/// Options of `bench client`.
#[derive(clap::Args)]
pub struct Args {
    /// Technique (`photons`, `irradiance`; `voxels` has none yet: its client only decodes).
    #[arg(long, default_value = "photons")]
    technique: String,
    /// Scene: `cornell`, `cornell-animated`, `city:N` or a .gltf/.glb file.
    #[arg(long, default_value = "cornell")]
    scene: String,
    /// Frame width, pixels.
    #[arg(long, default_value_t = 640, value_parser = ranges::count::<u32>(1, ranges::MAX_FRAME_SIDE))]
    width: u32,
    /// Frame height, pixels.
    #[arg(long, default_value_t = 360, value_parser = ranges::count::<u32>(1, ranges::MAX_FRAME_SIDE))]
    height: u32,
    /// Frames timed (whole, then split by pass).
    #[arg(long, default_value_t = 30, value_parser = ranges::count::<usize>(1, 100_000))]
    frames: usize,
    /// Scene time advances 1/fps per frame (lights move as the scene's animation says).
    #[arg(long, default_value_t = 30.0, value_parser = ranges::closed(1.0 / 3600.0, 1000.0, "frames/s"))]
    fps: f64,
    /// Photons splatted: one iteration of this budget (the knob `photons`; with `--set
    /// passes=P`, P passes of it drawn together as a still light's) [default: 10000].
    #[arg(long, value_parser = ranges::count::<u64>(1, ranges::MAX_PHOTONS))]
    photons: Option<u64>,
    /// Emissive triangles become n² point emitters each (the client's knob `light_samples`).
    #[arg(long, default_value_t = cloudlight_actors::client::DEFAULT_LIGHT_SAMPLES, value_parser = ranges::count::<u32>(1, 64))]
    light_samples: u32,
    /// Shadow-map side, texels.
    #[arg(long, default_value_t = 512, value_parser = ranges::count::<u32>(1, ranges::MAX_FRAME_SIDE))]
    shadow_size: u32,
    /// A still view (camera and lights unchanged since the frame before) accumulates its
    /// jittered frames, as the client shell does by default (its `accumulate`); `false`:
    /// every frame alone.
    #[arg(long, default_value_t = true, action = clap::ArgAction::Set)]
    accumulate: bool,
    /// Photon accumulation buffer downsampling per axis, 1, 2 or 4 (the knob `downsample`)
    /// [default: 2, the client's].
    #[arg(long, value_parser = clap::builder::TypedValueParser::map(
        clap::builder::PossibleValuesParser::new(["1", "2", "4"]),
        |s| s.parse::<u32>().expect("one of the listed values")))]
    downsample: Option<u32>,
    /// Sets a knob of the technique, `key=value` (repeatable).
    #[arg(long = "set", value_name = "KEY=VALUE", value_parser = bench::parse_knob)]
    set: Vec<(String, toml::Value)>,
    /// Also write the JSON report to this file.
    #[arg(long, value_name = "PATH")]
    json: Option<PathBuf>,
}

/// The targets of TARGETS.md for a client frame on lavapipe (2 cores), and the paper's.
fn target_line(technique: &str, scene: &str, width: u32, height: u32) -> String {
    let target = match (scene, width, height) {
        ("cornell" | "cornell-animated", 640, 360) => "target <= 33 ms p50 (lavapipe, 2 cores)",
        ("city:250000", 640, 360) => "target <= 100 ms p50 (lavapipe, 2 cores)",
        _ => {
            "no target set for this scene and size (TARGETS.md: Cornell 640x360 <= 33 ms, city:250000 <= 100 ms)"
        }
    };
    let paper = match technique {
        "photons" => "8 ms local device indirect time (GeForce 670, Cornell box)",
        "irradiance" => {
            "no local device time in Table 2 (the client decodes the map in ≈1 ms and looks it up)"
        }
        _ => "no figure for this technique",
    };
    format!("{target}; paper: {paper}")
}

struct Frame(Args);

impl Visit for Frame {
    type Out = anyhow::Result<()>;
    fn visit<T: Technique>(self) -> anyhow::Result<()> {
        let a = self.0;
        let mut knobs = toml::Table::new();
        if let Some(n) = a.photons {
            knobs.insert("photons".into(), (n as i64).into());
        }
        if let Some(d) = a.downsample {
            knobs.insert("downsample".into(), i64::from(d).into());
        }
        knobs.extend(a.set.iter().cloned());
        let technique = bench::options_from::<T>(&knobs)?;
        let scene = cloudlight::scenes::load(&a.scene)?;
        let raster = Raster::new()?;
        let options = ClientBenchOptions {
            width: a.width,
            height: a.height,
            frames: a.frames,
            fps: a.fps,
            light_samples: a.light_samples,
            shadow_size: a.shadow_size,
            accumulate: a.accumulate,
        };
        eprintln!(
            "rendering {} + {} frames at {}x{} on {}...",
            a.frames,
            a.frames,
            a.width,
            a.height,
            raster.describe()
        );
        let mut r = T::client_frame(&raster, &scene, &technique, options)?;
        // Right after the frames, so that both see the machine at the same speed.
        r.anchor = Some(bench::client::raster_anchor(&raster, 10)?);
        println!(
            "{}: {} triangles, {} lights, {}, {}x{} on {}; shadow maps rendered in {} of {} split frames",
            r.scene,
            r.triangles,
            r.lights,
            r.indirect,
            a.width,
            a.height,
            r.adapter,
            r.frames_with_shadows,
            a.frames
        );
        println!("{}", r.table());
        println!("{}", target_line(T::NAME, &a.scene, a.width, a.height));
        if let Some(line) = r.anchor_line() {
            println!("{line}");
        }
        let json = serde_json::to_string_pretty(&r)?;
        println!("{json}");
        super::write_json(a.json.as_ref(), &json)
    }
}

pub fn run(a: Args) -> ExitCode {
    bench::with_technique(&a.technique.clone(), Frame(a))
        .and_then(|r| r)
        .map_or_else(crate::cli::report_error, |()| ExitCode::SUCCESS)
}
