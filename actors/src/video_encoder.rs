//! `video_encoder`: pictures in ([`FrameMsg`]: a client's SDR frame or an HDR light map),
//! H.264 access units out ([`VideoMsg`]), each with its scene time (the stamp), frame index,
//! stream time and key-frame flag — the kernel is `cloudlight_render::video`.
//!
//! Ports and what they drop: [`IN`] defaults to `latest`, 2 deep (a newer picture supersedes
//! one not yet encoded); [`OUT`] feeds decoders, whose edges should be `block` (a dropped
//! P frame corrupts every picture until the next key frame). One encoder may feed many
//! clients (shared content: irradiance maps); a client joining late shows its first picture
//! at the next key frame, at most `keyframe_s` of stream time later. Replicate it per client
//! where pictures are per client (voxels, the full-frame baseline).
//!
//! The encoder is made at the first picture and made again (starting with a key frame) when
//! the picture size changes. HDR maps are packed with `video::hdr` (log₂ luminance in Y,
//! chromaticity in U/V) and the range rides in each message.

use std::time::Instant;

use cloudlight_render::video::{self, EncoderSettings, RateControl, Yuv420, hdr};
use cloudlight_runtime::{
    CheckParams, EdgeSettings, Input, Latency, Policy, Port, Stage, StageCtx, StageKind,
    StageRegistry, StageSetup, check_range,
};
use serde::{Deserialize, Serialize};

use crate::wire::{FrameMsg, VideoMsg};

/// The technique of the video stages (list it in a topology's `techniques`).
pub const TECHNIQUE: &str = "video";

/// Pictures to encode.
pub const IN: Port<FrameMsg> = Port::new("in");

/// Access units, in stream order.
pub const OUT: Port<VideoMsg> = Port::new("out");

/// Default settings of the encoder's input: the newest picture wins.
pub const FRAME_EDGE: EdgeSettings = EdgeSettings {
    capacity: 2,
    policy: Policy::Latest,
};

/// Parameters of `video_encoder`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EncoderParams {
    /// Target bitrate, Mbit/s (default 3; ignored when `qp` is given).
    #[serde(default = "default_mbps")]
    pub bitrate_mbps: f64,
    /// A fixed QP (0–51) instead of a bitrate.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub qp: Option<u8>,
    /// Seconds of stream time between key frames.
    #[serde(default = "default_keyframe")]
    pub keyframe_s: f64,
    /// Frames per second the rate control expects.
    #[serde(default = "default_fps")]
    pub fps: f64,
    /// Let rate control skip frames to hold the bitrate.
    #[serde(default)]
    pub skip_frames: bool,
    /// Encoder threads.
    #[serde(default = "one")]
    pub threads: u16,
}

fn default_mbps() -> f64 {
    3.0
}
fn default_keyframe() -> f64 {
    2.0
}
fn default_fps() -> f64 {
    30.0
}
fn one() -> u16 {
    1
}

impl Default for EncoderParams {
    fn default() -> Self {
        EncoderParams {
            bitrate_mbps: default_mbps(),
            qp: None,
            keyframe_s: default_keyframe(),
            fps: default_fps(),
            skip_frames: false,
            threads: 1,
        }
    }
}

impl CheckParams for EncoderParams {
    fn check(&self) -> Result<(), String> {
        check_range("bitrate_mbps", self.bitrate_mbps, 0.01, 200.0, "Mbit/s")?;
        if let Some(q) = self.qp {
            check_range("qp", q as f64, 0.0, 51.0, "")?;
        }
        check_range("keyframe_s", self.keyframe_s, 0.01, 3600.0, "s")?;
        check_range("fps", self.fps, 0.1, 240.0, "frames/s")?;
        check_range("threads", self.threads as f64, 1.0, 16.0, "")
    }
}

impl EncoderParams {
    fn settings(&self, width: u32, height: u32) -> EncoderSettings {
        EncoderSettings {
            width,
            height,
            fps: self.fps as f32,
            rate: match self.qp {
                Some(q) => RateControl::FixedQp(q),
                None => RateControl::Bitrate((self.bitrate_mbps * 1e6).round() as u32),
            },
            keyframe_s: self.keyframe_s,
            skip_frames: self.skip_frames,
            threads: self.threads,
        }
    }
}

/// What `video_encoder` reports.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct EncoderReport {
    /// One line for people.
    pub summary: String,
    /// Pictures received.
    pub pictures: u64,
    /// Access units sent.
    pub units: u64,
    /// Key frames among them.
    pub key_frames: u64,
    /// Pictures rate control skipped.
    pub skipped: u64,
    /// Bytes of access units sent.
    pub bytes: u64,
    /// Pack + encode time per picture, median and 99th percentile, ms.
    pub encode_ms_p50: f64,
    /// 99th percentile, ms.
    pub encode_ms_p99: f64,
    /// Mbit/s of access units since the first picture.
    pub mbps: f64,
}

/// The stage.
pub struct VideoEncoder {
    params: EncoderParams,
    encoder: Option<video::Encoder>,
    report: EncoderReport,
    encode: Latency,
    started: Option<Instant>,
}

impl VideoEncoder {
    fn new(setup: &StageSetup) -> anyhow::Result<Self> {
        let params: EncoderParams = setup.params()?;
        params
            .check()
            .map_err(|e| anyhow::anyhow!("{}: params: {e}", setup.info.name))?;
        Ok(VideoEncoder {
            params,
            encoder: None,
            report: EncoderReport::default(),
            encode: Latency::new(),
            started: None,
        })
    }

    /// The encoder for pictures of this size (made anew when the size changes).
    fn encoder_for(&mut self, width: u32, height: u32) -> anyhow::Result<&mut video::Encoder> {
        let fits = self
            .encoder
            .as_ref()
            .is_some_and(|e| (e.settings().width, e.settings().height) == (width, height));
        if !fits {
            self.encoder = Some(video::Encoder::new(self.params.settings(width, height))?);
        }
        Ok(self.encoder.as_mut().expect("made above"))
    }

    fn snapshot(&self) -> EncoderReport {
        let elapsed = self.started.map_or(0.0, |s| s.elapsed().as_secs_f64());
        let mut r = self.report.clone();
        r.encode_ms_p50 = self.encode.p50_ms();
        r.encode_ms_p99 = self.encode.p99_ms();
        r.mbps = r.bytes as f64 * 8.0 / elapsed.max(1e-9) / 1e6;
        r.summary = format!(
            "{} pictures → {} units ({} key), {:.2} Mbit/s, encode {:.2} ms p50 / {:.2} ms p99",
            r.pictures, r.units, r.key_frames, r.mbps, r.encode_ms_p50, r.encode_ms_p99
        );
        r
    }
}

#[async_trait::async_trait]
impl Stage for VideoEncoder {
    async fn on_input(&mut self, ctx: &mut StageCtx, input: Input) -> anyhow::Result<()> {
        let msg = input.on(IN)?;
        self.started.get_or_insert_with(Instant::now);
        self.report.pictures += 1;
        let t = Instant::now();
        let (width, height, yuv, range, light_s, steady) = match &msg.body {
            FrameMsg::Sdr {
                width,
                height,
                rgb,
                light_s,
            } => (
                *width,
                *height,
                Yuv420::from_rgb8(*width, *height, rgb)?,
                None,
                *light_s,
                false,
            ),
            FrameMsg::Hdr { map, steady } => {
                map.check()
                    .map_err(|e| anyhow::anyhow!("a light map that does not add up: {e}"))?;
                let packed = hdr::pack(map)?;
                let (w, h) = (map.width(), map.height());
                (w, h, packed.yuv, Some(packed.range), None, *steady)
            }
        };
        let unit = self
            .encoder_for(width, height)?
            .encode(&yuv, msg.scene_time_s)?;
        self.encode.record(t.elapsed());
        let Some(unit) = unit else {
            self.report.skipped += 1;
            return Ok(());
        };
        self.report.units += 1;
        self.report.key_frames += unit.key as u64;
        self.report.bytes += unit.data.len() as u64;
        let out = VideoMsg {
            index: unit.index,
            key: unit.key,
            timestamp_ms: unit.timestamp_ms,
            width,
            height,
            hdr: range,
            light_s,
            steady,
            data: unit.data,
        };
        ctx.send(OUT, msg.scene_time_s, out).await?;
        if self.report.units % 30 == 1 {
            ctx.report(serde_json::to_value(self.snapshot())?);
        }
        Ok(())
    }

    async fn on_stop(&mut self, ctx: &mut StageCtx) -> anyhow::Result<()> {
        ctx.report(serde_json::to_value(self.snapshot())?);
        Ok(())
    }
}

/// Registers `video_encoder`.
pub fn register(registry: &mut StageRegistry) {
    registry.register(
        StageKind::new(
            "video_encoder",
            TECHNIQUE,
            "encodes pictures (SDR frames or HDR light maps) as H.264 access units",
            |s| Ok(Box::new(VideoEncoder::new(s)?)),
        )
        .input(IN, FRAME_EDGE)
        .output(OUT)
        .checked_params::<EncoderParams>(),
    );
}
