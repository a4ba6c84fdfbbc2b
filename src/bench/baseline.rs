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
use cloudlight_actors::photon_reconstructor::{PhotonClientParams, PhotonClientReport};
use cloudlight_actors::video_client::{VideoClientParams, VideoClientReport};
use cloudlight_actors::video_encoder::{EncoderParams, EncoderReport};
use cloudlight_render::raster::Raster;
use cloudlight_runtime::TopologySpec;
use serde::Serialize;

use super::photons::{PhotonColumn, PhotonOptions, Photons, table2_column};
use super::table::Markdown;
use super::{ClusterOptions, Technique, paper, stage_report};

/// Name on the command line.
pub const NAME: &str = "photons-video";

/// The video cut's encoder and frame rate.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct VideoCutOptions {
    /// Encoder target bitrate, Mbit/s.
    pub bitrate_mbps: f64,
    /// Seconds between key frames.
    pub keyframe_s: f64,
    /// Frames per second the cloud renders for the client (at most).
    pub fps: f64,
}

impl Default for VideoCutOptions {
    fn default() -> Self {
        VideoCutOptions {
            bitrate_mbps: 3.0,
            keyframe_s: 2.0,
            fps: 30.0,
        }
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

/// The video cut's topology: `server` (photon batcher), `render` (a photon reconstructor
/// rendering the client's frame) and `encode` on `cloud`, `client` (a `video_client`) on
/// `home`.
pub fn video_topology(
    photons: &PhotonOptions,
    video: &VideoCutOptions,
    cluster: &ClusterOptions,
    (width, height): (u32, u32),
) -> anyhow::Result<TopologySpec> {
    let any_port = "127.0.0.1:0".parse().expect("a valid address");
    let frame = ClientParams {
        width,
        height,
        fps: video.fps,
        ..ClientParams::default()
    };
    let render = Params {
        client: frame.clone(),
        technique: PhotonClientParams::default(),
    };
    let encode = EncoderParams {
        bitrate_mbps: video.bitrate_mbps,
        keyframe_s: video.keyframe_s,
        fps: video.fps,
        ..EncoderParams::default()
    };
    let client = Params {
        client: frame,
        technique: VideoClientParams::default(),
    };
    let mut spec = TopologySpec::new(&[Photons::NAME, "video"], &cluster.scene)
        .node("cloud", any_port)
        .node("home", any_port)
        .stage(
            "server",
            Photons::SERVER_KIND,
            &["cloud"],
            Photons::server_params(photons)?,
        )
        .stage(
            "render",
            Photons::CLIENT_KIND,
            &["cloud"],
            render.to_table()?,
        )
        .stage(
            "encode",
            "video_encoder",
            &["cloud"],
            toml::Table::try_from(encode)?,
        )
        .stage("client", "video_client", &["home"], client.to_table()?)
        .edge("server", "render", None, None)
        .edge("render.frames", "encode", None, None)
        .edge("encode", "client", None, None);
    spec.seed = cluster.seed;
    spec.duration_s = Some(cluster.seconds);
    spec.cluster = format!("{NAME}-bench");
    spec.secret = format!("{NAME}-bench");
    if let Some(link) = cluster.link {
        spec = spec.link("cloud", "home", link);
    }
    Ok(spec)
}

/// Runs the video cut for `cluster.seconds` and reads what its stages reported.
pub fn video_cut(
    runtime: &tokio::runtime::Runtime,
    photons: &PhotonOptions,
    video: &VideoCutOptions,
    cluster: &ClusterOptions,
    size: (u32, u32),
) -> anyhow::Result<VideoCut> {
    let spec = video_topology(photons, video, cluster, size)?;
    let m = super::run_spec(
        runtime,
        &spec,
        &format!("<{NAME} benchmark>"),
        cluster.seconds,
    )?;
    let server: BatcherReport = stage_report(&m, "server")?;
    let render: ClientReport<PhotonClientReport> = stage_report(&m, "render")?;
    let encode: EncoderReport = stage_report(&m, "encode")?;
    let client: ClientReport<VideoClientReport> = stage_report(&m, "client")?;
    let decoder = client.technique.decoder;
    Ok(VideoCut {
        resolution: format!("{}x{}", size.0, size.1),
        iteration_ms: server.iteration_ms_mean,
        frame_ms_p50: render.frame_ms_p50,
        frame_ms_p99: render.frame_ms_p99,
        frames_rendered: render.frames,
        encode_ms_p50: encode.encode_ms_p50,
        encode_ms_p99: encode.encode_ms_p99,
        units: encode.units,
        key_frames: encode.key_frames,
        skipped: encode.skipped,
        wire_mbps: super::wire_mbps(&m),
        payload_mbps: super::payload_mbps(&m),
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

/// Both cuts for each scene of [`super::photons::per_scene`].
#[allow(clippy::too_many_arguments)]
pub fn table2(
    runtime: &tokio::runtime::Runtime,
    raster: &Raster,
    scenes: &[String],
    budgets: &[u64],
    photons: &PhotonOptions,
    video: &VideoCutOptions,
    cluster: &ClusterOptions,
    size: (u32, u32),
) -> anyhow::Result<Vec<BaselineColumn>> {
    super::photons::per_scene(scenes, budgets, photons, cluster)
        .map(|(o, c)| {
            eprintln!(
                "{}: the photon cut ({} photons per iteration) for {} s...",
                c.scene, o.photons, c.seconds
            );
            let photons = table2_column(runtime, raster, &o, &c, size)?;
            eprintln!(
                "{}: the video cut (frames rendered and encoded in the cloud) for {} s...",
                c.scene, c.seconds
            );
            let video = video_cut(runtime, &o, video, &c, size)?;
            Ok(BaselineColumn { photons, video })
        })
        .collect()
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
            format!("photons ({} B each)", p.bytes_per_photon),
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
