//! `cloudlight bench table2|scaling|quality --technique T`: the paper's measurements for a
//! technique, through the harness of `cloudlight::bench` (one descriptor per technique).

use std::path::PathBuf;
use std::process::ExitCode;

use crate::cli::ranges;

use cloudlight::bench::{
    self, Bench, ClusterOptions, QualityCommon, Sweep, Technique, Visit, default_out,
    with_technique,
};
use cloudlight::render::raster::Raster;
use cloudlight::transport::LinkProfile;

/// A technique's knobs, by name, over its defaults: `--set key=value` and the shortcut flags.
#[derive(clap::Args)]
pub struct Knobs {
    /// Sets a knob of the technique, `key=value` (repeatable); an unknown key is an error that
    /// lists the technique's knobs and their defaults.
    #[arg(long = "set", value_name = "KEY=VALUE", value_parser = bench::parse_knob)]
    set: Vec<(String, toml::Value)>,
    /// Photons per batch (the knob `batch_size`).
    #[arg(long, value_parser = ranges::count::<u32>(1, ranges::MAX_BATCH))]
    batch_size: Option<u32>,
    /// Update (iteration) period, milliseconds (the knob `interval_ms`) [photons: 33].
    #[arg(long, value_parser = ranges::closed(0.0, 3.6e6, "ms"))]
    interval_ms: Option<f64>,
}

impl Knobs {
    /// The knobs as a table, the shortcut flags first and `--set` over them.
    pub fn table(&self) -> toml::Table {
        let mut t = toml::Table::new();
        if let Some(b) = self.batch_size {
            t.insert("batch_size".into(), i64::from(b).into());
        }
        if let Some(ms) = self.interval_ms {
            t.insert("interval_ms".into(), ms.into());
        }
        for (k, v) in &self.set {
            t.insert(k.clone(), v.clone());
        }
        t
    }
}

/// Options of `bench table2`.
#[derive(clap::Args)]
pub struct Table2Args {
    /// Technique: `photons`, `irradiance` (a scene without a light map reads "n/a" with its
    /// reason), or `photons-video` (the photon cut beside the full-frame baseline: each
    /// client's frame rendered and H.264-encoded in the cloud, a thin client decoding it), or
    /// `voxels` (the GI node shared, each client's frame rendered and encoded in the cloud).
    #[arg(long, default_value = "photons")]
    technique: String,
    /// Scenes, comma-separated: `cornell`, `city:N`, a .gltf/.glb file.
    #[arg(long, value_delimiter = ',', default_value = "cornell")]
    scene: Vec<String>,
    /// Photons per iteration, one per scene (the last repeats; the knob `photons`) [default:
    /// 10000].
    #[arg(long, value_delimiter = ',', value_parser = ranges::count::<u64>(1, ranges::MAX_PHOTONS))]
    photons: Vec<u64>,
    #[command(flatten)]
    knobs: Knobs,
    /// Seconds each scene runs.
    #[arg(long, default_value_t = 5.0, value_parser = ranges::above(0.0, 86_400.0, "seconds"))]
    seconds: f64,
    /// Client frame width for the indirect time.
    #[arg(long, default_value_t = 1280, value_parser = ranges::count::<u32>(1, ranges::MAX_FRAME_SIDE))]
    width: u32,
    /// Client frame height for the indirect time.
    #[arg(long, default_value_t = 720, value_parser = ranges::count::<u32>(1, ranges::MAX_FRAME_SIDE))]
    height: u32,
    /// `photons-video` and `voxels`: the encoder's target bitrate, Mbit/s (the knob `bitrate_mbps`)
    /// [default: 3].
    #[arg(long, value_parser = ranges::closed(0.01, 1000.0, "Mbit/s"))]
    bitrate_mbps: Option<f64>,
    /// `photons-video` and `voxels`: frames per second the cloud renders and encodes per client, at most
    /// (the knob `fps`) [default: 30].
    #[arg(long, value_parser = ranges::closed(0.1, 240.0, "fps"))]
    fps: Option<f64>,
    /// Also write the JSON report to this file.
    #[arg(long, value_name = "PATH")]
    json: Option<PathBuf>,
}

/// Options of `bench scaling`.
#[derive(clap::Args)]
pub struct ScalingArgs {
    /// Technique (`photons`, `irradiance`, `photons-video`, `voxels`).
    #[arg(long, default_value = "photons")]
    technique: String,
    /// Client counts, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "1,2,5,10,20,50", value_parser = ranges::count::<usize>(0, 1000))]
    clients: Vec<usize>,
    /// Scene.
    #[arg(long, default_value = "cornell-animated")]
    scene: String,
    /// Photons per iteration (the knob `photons`) [default: 10000].
    #[arg(long, value_parser = ranges::count::<u64>(1, ranges::MAX_PHOTONS))]
    photons: Option<u64>,
    #[command(flatten)]
    knobs: Knobs,
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
    /// Technique (`photons`: budgets in two packings; `irradiance`: bases, rays per basis and
    /// QP, and per-texel gathering; `voxels`: octree depth, gathering level, delta precision and
    /// QP, with the leak through a thin wall).
    #[arg(long, default_value = "photons")]
    technique: String,
    /// Scene.
    #[arg(long, default_value = "cornell")]
    scene: String,
    /// Photon budgets per iteration, comma-separated (the sweep `photons=...`) [default:
    /// 2500,5000,10000,40000,160000].
    #[arg(long, value_delimiter = ',', value_parser = ranges::count::<u64>(1, ranges::MAX_PHOTONS))]
    budgets: Vec<u64>,
    /// Sweeps a knob, `key=v1,v2,...` (repeatable; the technique says how sweeps combine;
    /// photons: any knob, every combination over the budgets, fronts drawn together;
    /// irradiance: `texels_per_basis`, `rays_per_basis`, `qp`; voxels: `max_depth`,
    /// `levels_above_leaves`, `mantissa_bits`, `qp`; every combination) [default:
    /// the technique's own sweep].
    #[arg(long, value_name = "KEY=V1,V2,...", value_parser = bench::parse_sweep)]
    sweep: Vec<(String, Vec<toml::Value>)>,
    #[command(flatten)]
    knobs: Knobs,
    /// View: the index of one of the scene's camera paths, or `px,py,pz:tx,ty,tz[:fov_deg]`
    /// (eye and target in meters, vertical field of view in degrees, default 45). A glTF
    /// without cameras is seen from outside its bounds; a player's view is inside.
    #[arg(long, default_value = "0", allow_hyphen_values = true)]
    camera: String,
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
    /// The client's image is the mean of this many frames of the still view, each sampling
    /// its pixels at another point within them (the client shell's `accumulate`; 1: one
    /// frame through the pixels' centres).
    #[arg(long, default_value_t = 1, value_parser = ranges::count::<u32>(1, 1024))]
    still_frames: u32,
    /// Seed of the technique's random streams (the reference keeps its own): a difference
    /// between two settings is real when it holds across seeds.
    #[arg(long, default_value_t = 5)]
    seed: u64,
    /// Output folder [default: runs/bench-quality-<time>].
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
}

/// Runs `f` for the technique named `name`: an unknown or unimplemented technique, or
/// anything `f` fails at, is reported and exits 1.
fn dispatch<V: Visit<Out = anyhow::Result<()>>>(name: &str, v: V) -> ExitCode {
    with_technique(name, v)
        .and_then(|r| r)
        .map_or_else(crate::cli::report_error, |()| ExitCode::SUCCESS)
}

struct Table2(Table2Args);

impl Visit for Table2 {
    type Out = anyhow::Result<()>;
    fn visit<T: Technique>(self) -> anyhow::Result<()> {
        let a = self.0;
        let mut knobs = a.knobs.table();
        for (key, value) in [("bitrate_mbps", a.bitrate_mbps), ("fps", a.fps)] {
            if let Some(v) = value {
                knobs.entry(key).or_insert(v.into());
            }
        }
        let mut per_scene: Sweep = Vec::new();
        if !a.photons.is_empty() {
            let values = a.photons.iter().map(|&n| (n as i64).into()).collect();
            per_scene.push(("photons".into(), values));
        }
        // Every scene's options are checked before the first one runs.
        for i in 0..a.scene.len() {
            bench::options_from::<T>(&bench::knobs_for_scene(&knobs, &per_scene, i))?;
        }
        let rt = crate::cli::async_runtime()?;
        let raster = Raster::new()?;
        let cluster = ClusterOptions {
            scene: String::new(),
            seconds: a.seconds,
            link: None,
            seed: 1,
        };
        let bench = Bench {
            runtime: &rt,
            raster: &raster,
        };
        let size = (a.width, a.height);
        let columns = bench::table2::<T>(&bench, &a.scene, &knobs, &per_scene, &cluster, size)?;
        println!("{}", T::table2_markdown(&columns));
        let options = bench::options_from::<T>(&knobs)?;
        println!("{}", T::table2_note(&options, size, &raster.describe()));
        let json = serde_json::to_string_pretty(&serde_json::json!({
            "technique": T::NAME,
            "options": options,
            "columns": columns,
        }))?;
        println!("{json}");
        super::write_json(a.json.as_ref(), &json)
    }
}

pub fn table2(a: Table2Args) -> ExitCode {
    dispatch(&a.technique.clone(), Table2(a))
}

struct Scaling(ScalingArgs);

impl Visit for Scaling {
    type Out = anyhow::Result<()>;
    fn visit<T: Technique>(self) -> anyhow::Result<()> {
        let a = self.0;
        if a.clients.is_empty() {
            anyhow::bail!("--clients lists no count");
        }
        let mut knobs = a.knobs.table();
        if let Some(n) = a.photons {
            knobs.entry("photons").or_insert((n as i64).into());
        }
        let options = bench::options_from::<T>(&knobs)?;
        let rt = crate::cli::async_runtime()?;
        let cluster = ClusterOptions {
            scene: a.scene.clone(),
            seconds: a.seconds,
            link: (!a.no_link).then_some(LinkProfile::CAMPUS),
            seed: 1,
        };
        let out = a.out.clone().unwrap_or_else(|| default_out("scaling"));
        bench::scaling::<T>(&rt, &options, &cluster, &a.clients, &out)?;
        Ok(())
    }
}

pub fn scaling(a: ScalingArgs) -> ExitCode {
    dispatch(&a.technique.clone(), Scaling(a))
}

struct Quality(QualityArgs);

impl Visit for Quality {
    type Out = anyhow::Result<()>;
    fn visit<T: Technique>(self) -> anyhow::Result<()> {
        let a = self.0;
        let options = bench::options_from::<T>(&a.knobs.table())?;
        let mut sweep: Sweep = a.sweep.clone();
        if !a.budgets.is_empty() {
            let values = a.budgets.iter().map(|&n| (n as i64).into()).collect();
            sweep.insert(0, ("photons".into(), values));
        }
        if sweep.is_empty() {
            sweep = T::default_sweep();
        }
        let raster = Raster::new()?;
        let common = QualityCommon {
            camera: a.camera.clone(),
            spp: a.spp,
            width: a.width,
            height: a.height,
            rate_hz: a.rate_hz,
            seed: a.seed,
            still_frames: a.still_frames,
        };
        let out = a.out.clone().unwrap_or_else(|| default_out("quality"));
        T::quality(&raster, &a.scene, &common, &options, &sweep, &out)?;
        Ok(())
    }
}

pub fn quality(a: QualityArgs) -> ExitCode {
    dispatch(&a.technique.clone(), Quality(a))
}
