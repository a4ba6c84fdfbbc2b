//! The full-frame streaming baseline beside the photon cut (`cloudlight bench table2
//! --technique photons-video`): the same photon light, but each client's frame is rendered and
//! H.264-encoded in the cloud and a thin client only decodes it — the paper's "simple cloud
//! rendering" (section 1.1), the placement every cloud-rendering system is judged against.
//!
//! Per scene two runs of the real stages over loopback: the photon cut (photons cross the
//! network, [`super::photons::table2_column`]) and the video cut (batcher, photon
//! reconstructor and video encoder on `cloud`, a `video_client` on `home`). Every figure is
//! per client: the video cut's server cost grows with the clients, the photon cut's does not.

use cloudlight_actors::client::{ClientParams, ClientReport, Params};
use cloudlight_actors::photon_batcher::BatcherReport;
use cloudlight_actors::photon_reconstructor::PhotonClientReport;
use cloudlight_actors::video_client::{VideoClientParams, VideoClientReport};
use cloudlight_actors::video_encoder::{EncoderParams, EncoderReport};
use serde::{Deserialize, Serialize};

use super::photons::{PhotonColumn, PhotonOptions, Photons, table2_column};
use super::table::Markdown;
use super::{
    Bench, CLIENT, ClusterOptions, ClusterRun, Placement, ScalingRow, ServerCost, Side, StageGraph,
    Technique, frame_and_encode_ms, paper,
};

/// The full-frame baseline: the photon technique with each client's frame rendered and
/// encoded in the cloud.
pub struct PhotonsVideo;

/// The video cut's encoder, frame size and frame rate.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct VideoCutOptions {
    /// Encoder target bitrate, Mbit/s.
    pub bitrate_mbps: f64,
    /// Seconds between key frames.
    pub keyframe_s: f64,
    /// Frames per second the cloud renders for the client (at most).
    pub fps: f64,
    /// Frame width the cloud renders for the client (Table 2: its `--width`).
    pub width: u32,
    /// Frame height (Table 2: its `--height`).
    pub height: u32,
}

impl Default for VideoCutOptions {
    fn default() -> Self {
        VideoCutOptions {
            bitrate_mbps: 3.0,
            keyframe_s: 2.0,
            fps: 30.0,
            width: 640,
            height: 360,
        }
    }
}

/// The baseline's knobs: the photon light's and the video cut's, side by side.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct BaselineOptions {
    /// The photon light.
    #[serde(flatten)]
    pub photons: PhotonOptions,
    /// The video cut.
    #[serde(flatten)]
    pub video: VideoCutOptions,
}

impl Technique for PhotonsVideo {
    const NAME: &'static str = "photons-video";
    type Options = BaselineOptions;
    type Column = BaselineColumn;

    /// `server` (photon batcher) shared on `cloud`; per client `render` (a photon
    /// reconstructor rendering the client's frame) and `encode` on `cloud`, `client` (a
    /// `video_client`) on `home`.
    fn graph(o: &BaselineOptions) -> anyhow::Result<StageGraph> {
        let v = &o.video;
        let frame = ClientParams {
            width: v.width,
            height: v.height,
            fps: v.fps,
            ..ClientParams::default()
        };
        let encode = EncoderParams {
            bitrate_mbps: v.bitrate_mbps,
            keyframe_s: v.keyframe_s,
            fps: v.fps,
            ..EncoderParams::default()
        };
        let client = Params {
            client: frame.clone(),
            technique: VideoClientParams::default(),
        };
        Ok(StageGraph::new(&[Photons::NAME, "video"])
            .stage(
                "server",
                Photons::SERVER_KIND,
                Placement::Shared,
                Photons::server_params(&o.photons)?,
            )
            .stage(
                "render",
                Photons::CLIENT_KIND,
                Placement::PerClient(Side::Cloud),
                Photons::client_params(&o.photons, frame)?,
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
            .edge("server", "render")
            .edge("render.frames", "encode")
            .edge("encode", CLIENT))
    }

    fn scaling_row(run: &ClusterRun, clients: usize) -> anyhow::Result<ScalingRow> {
        let server: BatcherReport = run.report("server")?;
        let render: Vec<ClientReport<PhotonClientReport>> = run.per_client("render")?;
        let encode: Vec<EncoderReport> = run.per_client("encode")?;
        let shown: Vec<ClientReport<VideoClientReport>> = run.per_client(CLIENT)?;
        let cost = ServerCost {
            update_ms: server.iteration_ms_mean,
            kernel_ms: server.trace_ms_mean * server.batches as f64,
            updates: server.iterations,
            per_client_ms: frame_and_encode_ms(&render, &encode),
        };
        Ok(ScalingRow::of(run, clients, cost, &shown))
    }

    fn scaling_figure() -> (&'static str, &'static str) {
        paper::VIDEO_SCALING_FIGURE
    }

    fn table2_column(
        bench: &Bench,
        o: &BaselineOptions,
        cluster: &ClusterOptions,
        size: (u32, u32),
    ) -> anyhow::Result<BaselineColumn> {
        eprintln!(
            "{}: the photon cut ({} photons per iteration) for {} s...",
            cluster.scene, o.photons.photons, cluster.seconds
        );
        let photons = table2_column(bench, &o.photons, cluster, size)?;
        eprintln!(
            "{}: the video cut (frames rendered and encoded in the cloud) for {} s...",
            cluster.scene, cluster.seconds
        );
        let at_size = BaselineOptions {
            video: VideoCutOptions {
                width: size.0,
                height: size.1,
                ..o.video.clone()
            },
            ..o.clone()
        };
        let video = video_cut(bench.runtime, &at_size, cluster)?;
        Ok(BaselineColumn { photons, video })
    }

    fn table2_markdown(columns: &[BaselineColumn]) -> String {
        markdown(columns)
    }

    fn table2_note(o: &BaselineOptions, (width, height): (u32, u32), adapter: &str) -> String {
        format!(
            "Per client, 1 client over loopback, {width}x{height}; photon iterations every {} ms; video at up to {} fps, {} Mbit/s target, \
             openh264 on one core; raster on {adapter}. The photon cut's server cost is shared by every client, the video cut's \
             frame and encode are paid once per client. Paper: GeForce Titan + Quadro K5000 with a hardware encoder.",
            o.photons.interval_ms, o.video.fps, o.video.bitrate_mbps
        )
    }
}

/// What one client of the video cut cost and saw.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct VideoCut {
    /// Frame size, `WxH`.
    pub resolution: String,
    /// The batcher's iteration time (shared by all clients), mean, ms.
    pub iteration_ms: f64,
    /// The client's frame rendered in the cloud (G-buffer, shadows, direct, photon splat,
    /// compose, read-back), p50 and p99, ms.
    pub frame_ms_p50: f64,
    /// p99, ms.
    pub frame_ms_p99: f64,
    /// Frames rendered for the client.
    pub frames_rendered: u64,
    /// RGB → YUV + encode per frame, p50, ms.
    pub encode_ms_p50: f64,
    /// p99, ms.
    pub encode_ms_p99: f64,
    /// Access units sent, key frames among them, pictures the rate control skipped.
    pub units: u64,
    /// Key frames.
    pub key_frames: u64,
    /// Skipped.
    pub skipped: u64,
    /// Server-to-client wire bandwidth (headers and retransmissions in), Mbit/s.
    pub wire_mbps: f64,
    /// Payload bandwidth, Mbit/s.
    pub payload_mbps: f64,
    /// Decode + YUV → RGB per unit on the thin client, p50 and p99, ms.
    pub decode_ms_p50: f64,
    /// p99, ms.
    pub decode_ms_p99: f64,
    /// Pictures the thin client decoded.
    pub pictures: u64,
    /// Units it could not decode.
    pub decode_errors: u64,
    /// Units dropped waiting for a key frame.
    pub waiting_for_key: u64,
    /// Pictures per second it decoded.
    pub pictures_per_s: f64,
    /// Age of the indirect light it shows (the light's scene time, not the frame's), p50, ms.
    pub age_ms_p50: f64,
    /// p99, ms.
    pub age_ms_p99: f64,
}

/// One scene: the photon cut and the video cut.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct BaselineColumn {
    /// Photons cross the network; the client splats them.
    pub photons: PhotonColumn,
    /// Frames cross the network; the client decodes them.
    pub video: VideoCut,
}

/// Runs the video cut for `cluster.seconds` and reads what its stages reported.
pub fn video_cut(
    runtime: &tokio::runtime::Runtime,
    o: &BaselineOptions,
    cluster: &ClusterOptions,
) -> anyhow::Result<VideoCut> {
    let run = super::run_cluster::<PhotonsVideo>(runtime, o, cluster, 1)?;
    let server: BatcherReport = run.report("server")?;
    let render: ClientReport<PhotonClientReport> = run.report("render")?;
    let encode: EncoderReport = run.report("encode")?;
    let client: ClientReport<VideoClientReport> = run.report(CLIENT)?;
    let decoder = client.technique.decoder;
    Ok(VideoCut {
        resolution: format!("{}x{}", o.video.width, o.video.height),
        iteration_ms: server.iteration_ms_mean,
        frame_ms_p50: render.frame_ms_p50,
        frame_ms_p99: render.frame_ms_p99,
        frames_rendered: render.frames,
        encode_ms_p50: encode.encode_ms_p50,
        encode_ms_p99: encode.encode_ms_p99,
        units: encode.units,
        key_frames: encode.key_frames,
        skipped: encode.skipped,
        wire_mbps: run.wire_mbps(),
        payload_mbps: run.payload_mbps(),
        decode_ms_p50: client.technique.decode_ms_p50,
        decode_ms_p99: client.technique.decode_ms_p99,
        pictures: decoder.pictures,
        decode_errors: decoder.errors,
        waiting_for_key: decoder.waiting_for_key,
        pictures_per_s: decoder.pictures as f64 / cluster.seconds,
        age_ms_p50: client.age_ms_p50,
        age_ms_p99: client.age_ms_p99,
    })
}

/// Per scene, one row per placement and the paper's final-frame row, as Markdown.
pub fn markdown(columns: &[BaselineColumn]) -> String {
    let mut t = Markdown::new(&[
        "scene",
        "placement",
        "crosses the network",
        "server per client",
        "server shared",
        "Mbps per client (wire)",
        "client per frame",
        "age of indirect p50 / p99",
        "pictures/s at the client",
    ]);
    for c in columns {
        let (p, v) = (&c.photons, &c.video);
        t.row(vec![
            p.scene.clone(),
            "photons: client splats".into(),
            format!("photons ({:.1} B each)", p.bytes_per_photon),
            "—".into(),
            format!("{:.1} ms / iteration", p.iteration_interval_ms),
            format!("{:.1}", p.server_to_client_mbps),
            format!(
                "{:.1} ms indirect at {} (+ its own direct light)",
                p.client_indirect_ms, p.client_resolution
            ),
            format!("{:.0} / {:.0} ms", p.age_ms_p50, p.age_ms_p99),
            "(renders its own)".into(),
        ]);
        t.row(vec![
            p.scene.clone(),
            "photons-video: cloud renders + encodes".into(),
            format!(
                "H.264 ({} units, {} key, {} skipped)",
                v.units, v.key_frames, v.skipped
            ),
            format!(
                "{:.1} ms frame + {:.1} ms encode (p50)",
                v.frame_ms_p50, v.encode_ms_p50
            ),
            format!("{:.1} ms / iteration", v.iteration_ms),
            format!("{:.2}", v.wire_mbps),
            format!(
                "{:.2} ms decode (p50; {} undecodable)",
                v.decode_ms_p50, v.decode_errors
            ),
            format!("{:.0} / {:.0} ms", v.age_ms_p50, v.age_ms_p99),
            format!("{:.1}", v.pictures_per_s),
        ]);
        let scene = paper::SCENES
            .iter()
            .position(|s| s.name == p.paper_scene)
            .unwrap_or(0);
        let cell = |row: usize| paper::VIDEO_FRAMES[row].1[scene];
        t.row(vec![
            format!("paper: {}", p.paper_scene),
            "voxels: final frames as video (HW encoder)".into(),
            "H.264".into(),
            format!("{} frame + {} encode", cell(0), cell(1)),
            "(voxel GI)".into(),
            cell(2).trim_end_matches(" Mbps").into(),
            "≈1 ms decode (1080p)".into(),
            "—".into(),
            "—".into(),
        ]);
    }
    t.render()
}
