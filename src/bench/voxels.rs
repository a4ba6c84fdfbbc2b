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
use cloudlight_render::voxel::BYTES_PER_VOXEL;
use serde::{Deserialize, Serialize};

use super::table::Markdown;
use super::{
    Bench, CLIENT, ClusterOptions, ClusterRun, Placement, ScalingRow, Side, StageGraph, Technique,
    mean, paper,
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
        Ok(ScalingRow {
            clients,
            server_update_ms: inject.inject_ms_mean + filter.filter_ms_p50 + cones.gather_ms_mean,
            server_kernel_ms: cones.gather_ms_mean,
            server_per_client_ms: (clients > 0).then(|| {
                mean(
                    render
                        .iter()
                        .zip(&encode)
                        .map(|(r, e)| r.frame_ms_p50 + e.encode_ms_p50),
                )
            }),
            updates: cones.updates,
            total_wire_mbps: run.wire_mbps(),
            total_payload_mbps: run.payload_mbps(),
            age_ms_p50_mean: mean(shown.iter().map(|c| c.age_ms_p50)),
            age_ms_p99_max: shown.iter().map(|c| c.age_ms_p99).fold(0.0, f64::max),
            clients_showing_indirect: shown.iter().filter(|c| c.indirect_shown).count(),
        })
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
