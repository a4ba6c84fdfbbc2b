//! The voxel technique's benchmark descriptor (CloudLight §4.1, Table 2's voxel block and
//! Figure 3): the GI stages (`light_injector` → `octree_filter` → `cone_tracer`, the bounce
//! fed back) shared on `cloud`; per client a `frame_renderer` and a `video_encoder` on
//! `cloud` (the paper's final-frame GPU) and a `video_client` on `home`. The GI cost is paid
//! once for every client; each client's frame and encode are paid per client.

use cloudlight_actors::client::{ClientParams, ClientReport, Params};
use cloudlight_actors::cone_tracer::{ConeTracerParams, ConeTracerReport};
use cloudlight_actors::frame_renderer::{FrameRendererParams, FrameRendererReport};
use cloudlight_actors::light_injector::{InjectorParams, InjectorReport};
use cloudlight_actors::octree_filter::FilterReport;
use cloudlight_actors::video_client::{VideoClientParams, VideoClientReport};
use cloudlight_actors::video_encoder::{EncoderParams, EncoderReport};
use std::path::Path;
use std::time::Instant;

use anyhow::Context;
use cloudlight_render::HdrMap;
use cloudlight_render::metrics::{ImageErrors, compare};
use cloudlight_render::raster::{OneFrame, Raster, ShadowSettings};
use cloudlight_render::video::RateControl;
use cloudlight_render::voxel::{
    BYTES_PER_VOXEL, ConeSettings, DeltaDecoder, DeltaEncoder, Gathered, InjectSettings, Octree,
    TransferSettings, VoxelPass, VoxelSettings, VoxelVolume, Voxelizer, filter, gather, inject,
    leak,
};
use cloudlight_render::{BvhKind, SceneBvh};
use cloudlight_scenes::Scene;
use cloudlight_scenes::glam::Vec3;
use serde::{Deserialize, Serialize};

use super::table::Markdown;
use super::{
    Bench, CLIENT, ClusterOptions, ClusterRun, Placement, QualityCommon, QualityView, ScalingRow,
    ServerCost, Side, StageGraph, Sweep, Technique, frame_and_encode_ms, paper,
};

/// The voxel technique.
pub struct Voxels;

/// The voxel technique's knobs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct VoxelOptions {
    /// Deepest octree level.
    pub max_depth: u32,
    /// Octree memory budget, MiB.
    pub budget_mb: f64,
    /// Light samples per leaf side.
    pub samples: u32,
    /// Period of GI updates, ms.
    pub interval_ms: f64,
    /// Cones leave this many levels above the leaves.
    pub levels_above_leaves: u32,
    /// Cones per side of a gathering voxel.
    pub cones: u32,
    /// Mantissa bits of the deltas.
    pub mantissa_bits: u32,
    /// Updates between key updates.
    pub key_every: u64,
    /// Level the frame renderer looks irradiance up in.
    pub volume_level: u32,
    /// Encoder target bitrate, Mbit/s.
    pub bitrate_mbps: f64,
    /// Seconds between key frames.
    pub keyframe_s: f64,
    /// Frames per second rendered per client (at most).
    pub fps: f64,
    /// Frame width (Table 2: its `--width`).
    pub width: u32,
    /// Frame height (Table 2: its `--height`).
    pub height: u32,
}

impl Default for VoxelOptions {
    fn default() -> Self {
        let (i, c, f) = (
            InjectorParams::default(),
            ConeTracerParams::default(),
            FrameRendererParams::default(),
        );
        VoxelOptions {
            max_depth: i.max_depth,
            budget_mb: i.budget_mb,
            samples: i.samples,
            interval_ms: i.interval_ms,
            levels_above_leaves: c.levels_above_leaves,
            cones: c.cones,
            mantissa_bits: c.mantissa_bits,
            key_every: c.key_every,
            volume_level: f.volume_level,
            bitrate_mbps: 3.0,
            keyframe_s: 2.0,
            fps: 30.0,
            width: 640,
            height: 360,
        }
    }
}

/// Bytes a voxel's light takes on the GI node beside its geometry: its anisotropic radiance
/// and opacity (6 × 16) and its gathered irradiance (2 × 12).
const LIGHT_BYTES_PER_VOXEL: u64 = 96 + 24;

impl Technique for Voxels {
    const NAME: &'static str = "voxels";
    type Options = VoxelOptions;
    type Column = VoxelColumn;

    /// `inject`, `filter`, `cones` shared on `cloud` (the bounce fed back); per client
    /// `render` (a `frame_renderer`) and `encode` on `cloud`, `client` (a `video_client`)
    /// on `home`.
    fn graph(o: &VoxelOptions) -> anyhow::Result<StageGraph> {
        let frame = ClientParams {
            width: o.width,
            height: o.height,
            fps: o.fps,
            ..ClientParams::default()
        };
        let inject = InjectorParams {
            max_depth: o.max_depth,
            budget_mb: o.budget_mb,
            samples: o.samples,
            interval_ms: o.interval_ms,
        };
        let cones = ConeTracerParams {
            levels_above_leaves: o.levels_above_leaves,
            cones: o.cones,
            mantissa_bits: o.mantissa_bits,
            key_every: o.key_every,
            ..ConeTracerParams::default()
        };
        let render = Params {
            client: frame.clone(),
            technique: FrameRendererParams {
                max_depth: o.max_depth,
                budget_mb: o.budget_mb,
                volume_level: o.volume_level,
            },
        };
        let encode = EncoderParams {
            bitrate_mbps: o.bitrate_mbps,
            keyframe_s: o.keyframe_s,
            fps: o.fps,
            ..EncoderParams::default()
        };
        let client = Params {
            client: frame,
            technique: VideoClientParams::default(),
        };
        Ok(StageGraph::new(&[Self::NAME, "video"])
            .stage(
                "inject",
                "light_injector",
                Placement::Shared,
                toml::Table::try_from(inject)?,
            )
            .stage(
                "filter",
                "octree_filter",
                Placement::Shared,
                toml::Table::new(),
            )
            .stage(
                "cones",
                "cone_tracer",
                Placement::Shared,
                toml::Table::try_from(cones)?,
            )
            .stage(
                "render",
                "frame_renderer",
                Placement::PerClient(Side::Cloud),
                render.to_table()?,
            )
            .stage(
                "encode",
                "video_encoder",
                Placement::PerClient(Side::Cloud),
                toml::Table::try_from(encode)?,
            )
            .stage(
                CLIENT,
                "video_client",
                Placement::PerClient(Side::Home),
                client.to_table()?,
            )
            .edge("inject", "filter")
            .edge("filter", "cones")
            .edge("cones.bounce", "inject.bounce")
            .edge("cones.out", "render")
            .edge("render.frames", "encode")
            .edge("encode", CLIENT))
    }

    fn scaling_row(run: &ClusterRun, clients: usize) -> anyhow::Result<ScalingRow> {
        let inject: InjectorReport = run.report("inject")?;
        let filter: FilterReport = run.report("filter")?;
        let cones: ConeTracerReport = run.report("cones")?;
        let render: Vec<ClientReport<FrameRendererReport>> = run.per_client("render")?;
        let encode: Vec<EncoderReport> = run.per_client("encode")?;
        let shown: Vec<ClientReport<VideoClientReport>> = run.per_client(CLIENT)?;
        let cost = ServerCost {
            update_ms: inject.inject_ms_mean + filter.filter_ms_p50 + cones.gather_ms_mean,
            kernel_ms: cones.gather_ms_mean,
            updates: cones.updates,
            per_client_ms: frame_and_encode_ms(&render, &encode),
        };
        Ok(ScalingRow::of(run, clients, cost, &shown))
    }

    fn scaling_figure() -> (&'static str, &'static str) {
        paper::VIDEO_SCALING_FIGURE
    }

    fn table2_column(
        bench: &Bench,
        o: &VoxelOptions,
        cluster: &ClusterOptions,
        size: (u32, u32),
    ) -> anyhow::Result<VoxelColumn> {
        let o = VoxelOptions {
            width: size.0,
            height: size.1,
            ..o.clone()
        };
        eprintln!(
            "{}: voxels (depth up to {}, GI every {} ms, frames rendered and encoded in the cloud) for {} s...",
            cluster.scene, o.max_depth, o.interval_ms, cluster.seconds
        );
        let run = super::run_cluster::<Voxels>(bench.runtime, &o, cluster, 1)?;
        let inject: InjectorReport = run.report("inject")?;
        let filter: FilterReport = run.report("filter")?;
        let cones: ConeTracerReport = run.report("cones")?;
        let render: ClientReport<FrameRendererReport> = run.report("render")?;
        let encode: EncoderReport = run.report("encode")?;
        let client: ClientReport<VideoClientReport> = run.report(CLIENT)?;
        let geometry: u64 = inject.bytes_per_level.iter().sum();
        let voxels = geometry / BYTES_PER_VOXEL;
        let scene = cloudlight_scenes::load(&cluster.scene)?;
        Ok(VoxelColumn {
            scene: cluster.scene.clone(),
            paper_scene: paper::SCENES[paper::nearest_scene(scene.triangle_count() as u64)]
                .name
                .into(),
            depth: inject.depth,
            leaves: inject.leaves,
            voxels,
            indirect_ms: inject.inject_ms_p50 + filter.filter_ms_p50 + cones.gather_ms_p50,
            inject_ms: inject.inject_ms_p50,
            filter_ms: filter.filter_ms_p50,
            gather_ms: cones.gather_ms_p50,
            memory_mb: (geometry + voxels * LIGHT_BYTES_PER_VOXEL) as f64 / 1e6,
            delta_kb_per_update: cones.bytes_sent as f64 / cones.updates_sent.max(1) as f64 / 1e3,
            delta_ratio_to_raw: cones.ratio_to_raw,
            gi_to_frame_mbps: cones.bytes_sent as f64 * 8.0 / cluster.seconds / 1e6,
            updates: cones.updates,
            resolution: format!("{}x{}", size.0, size.1),
            frame_ms_p50: render.frame_ms_p50,
            encode_ms_p50: encode.encode_ms_p50,
            server_to_client_mbps: run.wire_mbps(),
            decode_ms_p50: client.technique.decode_ms_p50,
            age_ms_p50: client.age_ms_p50,
            age_ms_p99: client.age_ms_p99,
            pictures: client.technique.decoder.pictures,
        })
    }

    fn table2_markdown(columns: &[VoxelColumn]) -> String {
        markdown(columns)
    }

    fn default_sweep() -> Sweep {
        let ints = |v: &[i64]| v.iter().map(|&x| toml::Value::Integer(x)).collect();
        vec![
            ("max_depth".into(), ints(&[5, 6])),
            ("levels_above_leaves".into(), ints(&[2, 3])),
            ("cones".into(), ints(&[6, 16])),
            ("mantissa_bits".into(), ints(&[8])),
            ("qp".into(), ints(&[24, 36])),
        ]
    }

    fn quality(
        raster: &Raster,
        scene: &str,
        common: &QualityCommon,
        options: &VoxelOptions,
        sweep: &Sweep,
        out: &Path,
    ) -> anyhow::Result<serde_json::Value> {
        quality(raster, scene, common, options, sweep, out)
    }

    fn table2_note(o: &VoxelOptions, (width, height): (u32, u32), adapter: &str) -> String {
        format!(
            "1 client over loopback, {width}x{height}; GI updates every {} ms on 2 CPU cores (octree depth up to {}, cones from {} levels above the leaves, \
             deltas at {} mantissa bits); each client's frame rendered on {adapter} and encoded by openh264 at up to {} fps, {} Mbit/s target. \
             Times are p50; the paper's (GeForce Titan for GI, Quadro K5000 for frames and a hardware encoder) beside ours. \
             Our 'filter' stands where the paper's 'clear' is: a sparse octree built per update has nothing to clear.",
            o.interval_ms,
            o.max_depth,
            o.levels_above_leaves,
            o.mantissa_bits,
            o.fps,
            o.bitrate_mbps
        )
    }
}

/// One scene's voxel column.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct VoxelColumn {
    /// Scene spec.
    pub scene: String,
    /// The paper's scene of the nearest polygon count.
    pub paper_scene: String,
    /// Octree depth.
    pub depth: u32,
    /// Leaves.
    pub leaves: usize,
    /// Voxels, all levels.
    pub voxels: u64,
    /// Indirect update (inject + filter + gather), p50 each, ms.
    pub indirect_ms: f64,
    /// Light injection, p50, ms.
    pub inject_ms: f64,
    /// Octree filter, p50, ms.
    pub filter_ms: f64,
    /// Cone gather, p50, ms.
    pub gather_ms: f64,
    /// Voxel memory on the GI node (geometry and light), MB.
    pub memory_mb: f64,
    /// Deltas per update sent, kB.
    pub delta_kb_per_update: f64,
    /// Delta bytes over raw values.
    pub delta_ratio_to_raw: f64,
    /// GI node → frame renderer, Mbit/s per renderer.
    pub gi_to_frame_mbps: f64,
    /// GI updates.
    pub updates: u64,
    /// Frame size.
    pub resolution: String,
    /// Final frame, p50, ms.
    pub frame_ms_p50: f64,
    /// H.264 encode, p50, ms.
    pub encode_ms_p50: f64,
    /// Server to client, wire, Mbit/s.
    pub server_to_client_mbps: f64,
    /// Thin client's decode, p50, ms.
    pub decode_ms_p50: f64,
    /// Age of the indirect light shown, p50, ms.
    pub age_ms_p50: f64,
    /// p99, ms.
    pub age_ms_p99: f64,
    /// Pictures the thin client decoded.
    pub pictures: u64,
}

/// Table 2's voxel block: one row per figure, ours and the paper's per scene.
pub fn markdown(columns: &[VoxelColumn]) -> String {
    let mut header = vec!["".to_string()];
    for c in columns {
        header.push(format!("{} (ours)", c.scene));
        header.push(format!("paper: {}", c.paper_scene));
    }
    let header: Vec<&str> = header.iter().map(String::as_str).collect();
    let mut t = Markdown::new(&header);
    let paper_cell = |c: &VoxelColumn, row: usize| {
        let scene = paper::SCENES
            .iter()
            .position(|s| s.name == c.paper_scene)
            .unwrap_or(0);
        paper::VOXELS[row].1[scene].to_string()
    };
    type Cell = fn(&VoxelColumn) -> String;
    let rows: [(&str, Option<usize>, Cell); 12] = [
        ("Indirect (GI node)", Some(0), |c| {
            format!("{:.1} ms", c.indirect_ms)
        }),
        ("Light injection", Some(1), |c| {
            format!("{:.1} ms", c.inject_ms)
        }),
        ("Clear (ours: filter)", Some(2), |c| {
            format!("{:.1} ms", c.filter_ms)
        }),
        ("Gather", Some(3), |c| format!("{:.1} ms", c.gather_ms)),
        ("GI voxel memory", Some(4), |c| {
            format!(
                "{:.3} GB (depth {}, {} voxels)",
                c.memory_mb / 1e3,
                c.depth,
                c.voxels
            )
        }),
        ("GI-to-frame bandwidth", Some(5), |c| {
            format!(
                "{:.1} Mbps ({:.0} kB/update, {:.3} of raw)",
                c.gi_to_frame_mbps, c.delta_kb_per_update, c.delta_ratio_to_raw
            )
        }),
        ("Final frame time", Some(6), |c| {
            format!("{:.1} ms ({})", c.frame_ms_p50, c.resolution)
        }),
        ("H.264 encode (per client)", Some(7), |c| {
            format!("{:.1} ms", c.encode_ms_p50)
        }),
        ("Server-to-client bandwidth", Some(8), |c| {
            format!("{:.2} Mbps", c.server_to_client_mbps)
        }),
        ("Client decode", None, |c| {
            format!("{:.1} ms", c.decode_ms_p50)
        }),
        ("Age of indirect p50 / p99", None, |c| {
            format!("{:.0} / {:.0} ms", c.age_ms_p50, c.age_ms_p99)
        }),
        ("GI updates / pictures shown", None, |c| {
            format!("{} / {}", c.updates, c.pictures)
        }),
    ];
    for (name, paper_row, ours) in rows {
        let mut cells = vec![name.to_string()];
        for c in columns {
            cells.push(ours(c));
            cells.push(paper_row.map_or("—".into(), |r| paper_cell(c, r)));
        }
        t.row(cells);
    }
    t.render()
}

/// Gathers fed back into the injection before a quality point is measured: what the
/// pipeline reaches after as many updates of a static scene.
pub const QUALITY_BOUNCES: u32 = 8;

/// The voxel light of `scene` at time 0 with `o`: the octree, its gathered irradiance after
/// [`QUALITY_BOUNCES`] bounces, and the mean update time (inject + filter + gather), ms.
fn solve(scene: &Scene, bvh: &SceneBvh, o: &VoxelOptions, seed: u64) -> (Octree, Gathered, f64) {
    let settings = VoxelSettings {
        max_depth: o.max_depth,
        budget_bytes: (o.budget_mb * 1024.0 * 1024.0) as u64,
    };
    let octree = Voxelizer::new(scene, &settings).octree_at(scene, 0.0);
    let cone = ConeSettings {
        levels_above_leaves: o.levels_above_leaves,
        cones: o.cones,
        ..Default::default()
    };
    let inject_settings = InjectSettings {
        samples: o.samples,
        seed,
    };
    let mut g = Gathered::default();
    let start = Instant::now();
    for bounce in 0..QUALITY_BOUNCES {
        let indirect = (bounce > 0).then_some(g.leaves());
        let injection = inject(&octree, scene, bvh, 0.0, indirect, &inject_settings);
        g = gather(&octree, &filter(&octree, injection.leaves), &cone);
    }
    let ms = start.elapsed().as_secs_f64() * 1e3 / f64::from(QUALITY_BOUNCES);
    (octree, g, ms)
}

/// How the quality sweep codes the client's picture.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Video {
    /// One key frame at a fixed QP.
    Qp(u8),
    /// A second of a still view at a target bitrate (openh264's rate control).
    Mbps(f64),
}

impl Video {
    fn tag(&self) -> String {
        match self {
            Video::Qp(qp) => format!("qp{qp}"),
            Video::Mbps(m) => format!("{m}mbps"),
        }
    }
}

impl std::fmt::Display for Video {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Video::Qp(qp) => write!(f, "QP {qp}"),
            Video::Mbps(m) => write!(f, "{m} Mbps"),
        }
    }
}

/// One point of the voxel quality sweep.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct VoxelPoint {
    /// Octree depth reached.
    pub depth: u32,
    /// Cones leave this many levels above the leaves.
    pub levels_above_leaves: u32,
    /// Cones per side of a gathering voxel.
    pub cones: u32,
    /// Mantissa bits of the deltas.
    pub mantissa_bits: u32,
    /// How the client's picture was coded: `QP n` or `n Mbps` (rate control).
    pub video: String,
    /// Voxels, all levels.
    pub voxels: u64,
    /// Update time (inject + filter + gather), mean, ms.
    pub update_ms: f64,
    /// A key update's deltas, kB.
    pub delta_kbytes: f64,
    /// GI node → frame renderer, Mbit/s: a key update per update at the rate.
    pub gi_mbps: f64,
    /// The indirect picture through H.264, kB per frame: a key frame at a QP, the mean
    /// frame of a second at a bitrate.
    pub video_kbytes: f64,
    /// Server → client, Mbit/s: at a QP a key frame per update at the rate (an upper
    /// bound); at a bitrate what the rate control spent.
    pub video_mbps: f64,
    /// The frame renderer's indirect light against the reference, before H.264.
    pub before: ImageErrors,
    /// The same through H.264 as `video` says.
    pub after: ImageErrors,
    /// Light leaking through a wall 4 mm thick, per unit of the lit side's.
    pub leak: f64,
}

/// The voxel quality sweep: for each octree depth, gathering level and delta precision,
/// the frame renderer's indirect light (after [`QUALITY_BOUNCES`] bounces, through the
/// deltas and the volume lookup) against the path tracer's indirect image, before H.264 and
/// through it at each QP or bitrate; the update time, the bytes, the leak through a thin wall.
pub fn quality(
    raster: &Raster,
    scene_spec: &str,
    common: &QualityCommon,
    options: &VoxelOptions,
    sweep: &Sweep,
    out: &Path,
) -> anyhow::Result<serde_json::Value> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let mut videos = Vec::new();
    let mut gi_sweep = Sweep::new();
    for (key, values) in sweep {
        match key.as_str() {
            "qp" => {
                for v in values {
                    let qp = v
                        .as_integer()
                        .filter(|q| (0..=51).contains(q))
                        .with_context(|| format!("QP `{v}` is not a whole number 0 to 51"))?;
                    videos.push(Video::Qp(qp as u8));
                }
            }
            "bitrate_mbps" => {
                for v in values {
                    let mbps = v
                        .as_float()
                        .or_else(|| v.as_integer().map(|i| i as f64))
                        .filter(|m| (0.01..=200.0).contains(m))
                        .with_context(|| format!("bitrate `{v}` is not 0.01 to 200 Mbit/s"))?;
                    videos.push(Video::Mbps(mbps));
                }
            }
            "max_depth"
            | "levels_above_leaves"
            | "cones"
            | "mantissa_bits"
            | "samples"
            | "volume_level" => gi_sweep.push((key.clone(), values.clone())),
            other => anyhow::bail!(
                "the voxel quality sweep varies `max_depth`, `levels_above_leaves`, `cones`, `mantissa_bits`, `samples`, `volume_level`, `qp` and `bitrate_mbps`, not `{other}`"
            ),
        }
    }
    if videos.is_empty() {
        videos.push(Video::Qp(24));
    }
    let knobs = toml::Table::try_from(options)?;
    let settings = super::expand::<Voxels>(&knobs, &gi_sweep)?;
    let scene = cloudlight_scenes::load(scene_spec)?;
    let view = QualityView::of(scene, common)?;
    let (w, h) = (common.width, common.height);
    view.write_reference(out)?;
    let walled = leak::thin_wall_scene(0.004);
    let walled_bvh = SceneBvh::at(&walled, 0.0, BvhKind::default());
    let shadows = ShadowSettings {
        size: 16,
        ..Default::default()
    };
    let tris = view.scene.triangles_at(0.0);
    let mut pass = VoxelPass::new(raster)?;
    let mut points = Vec::new();
    for o in &settings {
        let start = Instant::now();
        let (octree, g, update_ms) = solve(&view.scene, &view.bvh, o, common.seed);
        let (walled_octree, walled_g, _) = solve(&walled, &walled_bvh, o, common.seed);
        let leak = leak::leak(&walled_octree, &walled_g);
        let mut encoder = DeltaEncoder::new(TransferSettings {
            mantissa_bits: o.mantissa_bits,
            key_every: 0,
        });
        let update = encoder.encode(&octree, &g, 0.0);
        let mut decoder = DeltaDecoder::new();
        for d in &update.deltas {
            decoder.apply(&octree, d)?;
        }
        let volume = VoxelVolume::new(&octree, decoder.levels(), octree.depth(), o.volume_level);
        pass.set_volume(raster, &volume)?;
        let frame = OneFrame::new(&view.scene, &tris, &[], &view.camera, (w, h), shadows)
            .with_samples(common.still_frames);
        let f = raster.read_frame(&frame, &mut pass)?;
        let mask: Vec<bool> = f.coverage.iter().map(|&c| c > 0.0).collect();
        let before = compare(&f.indirect, &view.reference, &mask, w, h);
        let tag = format!(
            "d{}_a{}_c{}_m{}",
            octree.depth(),
            o.levels_above_leaves,
            o.cones,
            o.mantissa_bits
        );
        view.write_image(out, &format!("indirect_{tag}"), &f.indirect, &tag)?;
        let rate = common.rate_hz.min(1000.0 / update_ms.max(1e-3));
        let picture = HdrMap::new(w, h, &f.indirect, &mask)?;
        for video in &videos {
            let (coded, key_bytes) = match *video {
                Video::Qp(qp) => super::irradiance::through_h264(&picture, qp)?,
                // A second of a still view under rate control: the mean frame.
                Video::Mbps(mbps) => super::irradiance::through_h264_at(
                    &picture,
                    RateControl::Bitrate((mbps * 1e6) as u32),
                    common.rate_hz.round().max(1.0) as u32,
                    common.rate_hz,
                )?,
            };
            let image: Vec<Vec3> = coded.texels();
            view.write_image(
                out,
                &format!("indirect_{tag}_{}", video.tag()),
                &image,
                &format!("{tag}, {}", video.tag()),
            )?;
            points.push(VoxelPoint {
                depth: octree.depth(),
                levels_above_leaves: o.levels_above_leaves,
                cones: o.cones,
                mantissa_bits: o.mantissa_bits,
                video: video.to_string(),
                voxels: update.voxels,
                update_ms,
                delta_kbytes: update.bytes as f64 / 1e3,
                gi_mbps: update.bytes as f64 * 8.0 * rate / 1e6,
                video_kbytes: key_bytes as f64 / 1e3,
                video_mbps: key_bytes as f64 * 8.0 / 1e6
                    * match video {
                        Video::Qp(_) => rate,
                        Video::Mbps(_) => common.rate_hz,
                    },
                before,
                after: compare(&image, &view.reference, &mask, w, h),
                leak,
            });
        }
        eprintln!(
            "{tag}: {} voxels, {update_ms:.1} ms/update, {:.1} kB of deltas, relMSE {:.4}, leak {leak:.3} ({:.1} s)",
            update.voxels,
            update.bytes as f64 / 1e3,
            before.relmse,
            start.elapsed().as_secs_f64()
        );
    }
    println!("{}", quality_markdown(&points));
    println!(
        "relMSE of the frame renderer's indirect radiance ({w}x{h}, the volume lookup) against the path tracer's indirect image \
         ({} spp) of the same view, both divided by the reference's mean luminance over pixels that see geometry, after {QUALITY_BOUNCES} \
         bounces of a static scene at time 0; \"after\" adds H.264 at the QP (the indirect image as the client would see it in the \
         picture), at a QP (one key frame) or a bitrate (a second of the still view under openh264's rate control, the last frame \
         shown). Mbps: a key update (deltas) or key frame (QP) per update at {} Hz or as fast as the update allows; at a bitrate, the mean of the second's frames. Leak: the \
         light voxels give the dark half of a box split by a 4 mm wall, per unit of the lit half's. Paper's Cornell box: 19 ms, \
         2.8 Gbps GI-to-frame, 3 Mbps video.",
        common.spp, common.rate_hz
    );
    let report = serde_json::json!({ "technique": Voxels::NAME, "scene": scene_spec, "common": common,
        "options": options, "reference_seconds": view.reference_s, "reference_noise": view.reference_noise, "sampling_floor": view.sampling_floor, "points": points });
    let json = out.join("quality.json");
    std::fs::write(&json, serde_json::to_string_pretty(&report)?)
        .with_context(|| format!("writing {}", json.display()))?;
    let png = quality_plot(
        &out.join("quality.png"),
        scene_spec,
        &points,
        view.sampling_floor,
    )?;
    println!("wrote {} and {}", json.display(), png.display());
    Ok(report)
}

/// The quality table.
pub fn quality_markdown(points: &[VoxelPoint]) -> String {
    let mut t = Markdown::new(&[
        "depth",
        "gather levels up",
        "cones",
        "mantissa bits",
        "voxels",
        "update ms",
        "deltas kB",
        "GI→frame Mbps",
        "video",
        "video kB/frame",
        "video Mbps",
        "relMSE before",
        "relMSE after",
        "FLIP after",
        "energy",
        "leak",
    ]);
    for p in points {
        t.row(vec![
            p.depth.to_string(),
            p.levels_above_leaves.to_string(),
            p.cones.to_string(),
            p.mantissa_bits.to_string(),
            p.voxels.to_string(),
            format!("{:.1}", p.update_ms),
            format!("{:.1}", p.delta_kbytes),
            format!("{:.1}", p.gi_mbps),
            p.video.clone(),
            format!("{:.1}", p.video_kbytes),
            format!("{:.2}", p.video_mbps),
            format!("{:.4}", p.before.relmse),
            format!("{:.4}", p.after.relmse),
            format!("{:.3}", p.after.flip),
            format!("{:.3}", p.before.energy_ratio),
            format!("{:.3}", p.leak),
        ]);
    }
    t.render()
}

fn quality_plot(
    path: &Path,
    scene: &str,
    points: &[VoxelPoint],
    floor: f64,
) -> anyhow::Result<std::path::PathBuf> {
    use crate::plot::{Floor, Marker, ParetoPanel, Series};
    let mut depths: Vec<u32> = points.iter().map(|p| p.depth).collect();
    depths.sort_unstable();
    depths.dedup();
    let video = points.first().map(|p| p.video.clone()).unwrap_or_default();
    let series = |x: fn(&VoxelPoint) -> f64| -> Vec<Series> {
        depths
            .iter()
            .map(|&d| Series {
                label: format!("depth {d} (before H.264)"),
                points: points
                    .iter()
                    .filter(|p| p.depth == d && p.video == video)
                    .map(|p| {
                        (
                            x(p),
                            p.before.relmse,
                            format!(
                                "↑{} {}c {}b",
                                p.levels_above_leaves, p.cones, p.mantissa_bits
                            ),
                        )
                    })
                    .collect(),
            })
            .collect()
    };
    crate::plot::pareto(
        path,
        &format!("Voxels, {scene}: error against GI-to-frame bandwidth and update time"),
        &[
            ParetoPanel {
                x_label: "GI-to-frame Mbps (a key update per update)".into(),
                y_label: "relMSE (scale-invariant)".into(),
                series: series(|p| p.gi_mbps),
                marker: None,
                floor: Some(Floor::sampling(floor)),
            },
            ParetoPanel {
                x_label: "update ms (inject + filter + gather)".into(),
                y_label: "relMSE (scale-invariant)".into(),
                series: series(|p| p.update_ms),
                marker: Some(Marker {
                    x: 19.0,
                    label: "paper: 19 ms per update (Cornell box)".into(),
                }),
                floor: Some(Floor::sampling(floor)),
            },
        ],
    )
}
