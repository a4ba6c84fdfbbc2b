//! `video_client`: a thin client on the shared client shell ([`crate::client`]) that decodes
//! H.264 access units ([`VideoMsg`]) and shows the pictures — the client of the voxel
//! technique's final frames and of the full-frame streaming baseline.
//!
//! What is its own: decoding (openh264, counted errors, pictures resume at the next key frame
//! after an error or a gap in the unit indices; a client that joins late shows its first
//! picture at the next key frame), the scene time of
//! the newest picture (its light is valid as of then, so the shell's age of indirect light is
//! the age of the picture shown), decode time, bytes, and pictures dropped or undecodable. It
//! renders nothing: the shell shows its pictures (and writes them when asked).
//!
//! Its `in` port defaults to `block`, 16 deep: a dropped unit breaks every picture up to the
//! next key frame.

use std::sync::Arc;
use std::time::Instant;

use cloudlight_render::raster::{NoIndirect, Raster, RasterError};
use cloudlight_render::video::{Decoder, DecoderStats};
use cloudlight_runtime::{CheckParams, EdgeSettings, Policy, StageRegistry, StageSetup, Stamped};
use cloudlight_scenes::Scene;
use serde::{Deserialize, Serialize};

use crate::client::{ClientTechnique, Picture, register as register_client};
use crate::video_encoder::TECHNIQUE;
use crate::wire::VideoMsg;

/// Default settings of a video client's input.
pub const VIDEO_EDGE: EdgeSettings = EdgeSettings {
    capacity: 16,
    policy: Policy::Block,
};

/// The video client's own parameters (none yet, beside the shell's).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VideoClientParams {}

impl CheckParams for VideoClientParams {
    fn check(&self) -> Result<(), String> {
        Ok(())
    }
}

/// The video client's figures in its report.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct VideoClientReport {
    /// What the decoder saw (units, pictures, errors, units dropped waiting for a key frame).
    pub decoder: DecoderStats,
    /// Bytes of access units received.
    pub bytes_received: u64,
    /// Decode time per unit (with the conversion to RGB), median, ms.
    pub decode_ms_p50: f64,
    /// 99th percentile, ms.
    pub decode_ms_p99: f64,
    /// HDR units (light maps), which this client cannot show (an irradiance client can).
    pub hdr_units_ignored: u64,
    /// Breaks in the stream (units missing between two that arrived: an outage, a lost
    /// connection). There is no fallback light: the last picture stays on screen, its age
    /// grows, and decoding resumes at the next key frame.
    pub gaps: u64,
    /// Units missing across those breaks.
    pub units_missed: u64,
}

/// The video technique's part of a client.
pub struct VideoClient {
    decoder: Decoder,
    picture: Option<Arc<Picture>>,
    valid_as_of: Option<f64>,
    bytes: u64,
    hdr_ignored: u64,
    decode: cloudlight_runtime::Latency,
    /// Index of the unit expected next: after a gap (units lost upstream) the decoder waits
    /// for a key frame instead of showing broken pictures.
    next_index: Option<u64>,
    gaps: u64,
    units_missed: u64,
}

impl ClientTechnique for VideoClient {
    type Msg = VideoMsg;
    type Params = VideoClientParams;
    type Pass = NoIndirect;
    type Update = ();
    type Report = VideoClientReport;
    const SHOWS_PICTURES: bool = true;

    fn new(_: &StageSetup, _: &Self::Params, _: &Arc<Scene>) -> anyhow::Result<Self> {
        Ok(VideoClient {
            decoder: Decoder::new()?,
            picture: None,
            valid_as_of: None,
            bytes: 0,
            hdr_ignored: 0,
            decode: cloudlight_runtime::Latency::new(),
            next_index: None,
            gaps: 0,
            units_missed: 0,
        })
    }

    fn on_message(&mut self, stage: &str, msg: &Stamped<VideoMsg>) {
        let unit = &msg.body;
        self.bytes += unit.data.len() as u64;
        if unit.hdr.is_some() {
            self.hdr_ignored += 1;
            return;
        }
        if let Some(expected) = self.next_index.filter(|&n| n != unit.index) {
            self.decoder.lose_sync();
            self.gaps += 1;
            let missed = unit.index.saturating_sub(expected);
            self.units_missed += missed;
            // Logged at 1, 2, 4, 8, ... gaps, as undecodable units are.
            if self.gaps.is_power_of_two() {
                tracing::warn!(
                    stage,
                    expected,
                    got = unit.index,
                    missed,
                    gaps = self.gaps,
                    "gap in the video stream: showing the last picture until the next key frame"
                );
            }
        }
        self.next_index = Some(unit.index + 1);
        let start = Instant::now();
        match self.decoder.decode(&unit.data) {
            Ok(Some(yuv)) => {
                self.picture = Some(Arc::new(Picture {
                    width: yuv.width,
                    height: yuv.height,
                    rgb: yuv.to_rgb8(),
                }));
                // The light's age, not only the picture's: a frame rendered in the cloud
                // shows light that was already old when it was rendered.
                self.valid_as_of = Some(unit.light_s.unwrap_or(msg.scene_time_s));
                self.decode.record(start.elapsed());
            }
            Ok(None) => {}
            Err(e) => {
                // Counted in the report; logged at 1, 2, 4, 8, ... so a flood stays readable.
                let n = self.decoder.stats().errors;
                if n.is_power_of_two() {
                    tracing::warn!(
                        stage,
                        index = unit.index,
                        errors = n,
                        "undecodable unit: {e}"
                    );
                }
            }
        }
    }

    fn valid_as_of(&self) -> Option<f64> {
        self.valid_as_of
    }

    fn new_pass(_: &Raster, _: &Self::Params) -> Result<NoIndirect, RasterError> {
        Ok(NoIndirect)
    }

    fn update(&mut self) -> Option<()> {
        None
    }

    fn apply(_: &mut NoIndirect, _: &Raster, _: ()) -> Result<(), RasterError> {
        Ok(())
    }

    fn picture(&self) -> Option<Arc<Picture>> {
        self.picture.clone()
    }

    fn report(&self) -> VideoClientReport {
        VideoClientReport {
            decoder: self.decoder.stats(),
            bytes_received: self.bytes,
            decode_ms_p50: self.decode.p50_ms(),
            decode_ms_p99: self.decode.p99_ms(),
            hdr_units_ignored: self.hdr_ignored,
            gaps: self.gaps,
            units_missed: self.units_missed,
        }
    }

    fn summary(&self) -> String {
        let s = self.decoder.stats();
        format!(
            "{} units → {} pictures, decode {:.2} ms p50, {} undecodable, {} gaps ({} units missed), {} dropped waiting for a key frame",
            s.units,
            s.pictures,
            self.report().decode_ms_p50,
            s.errors,
            self.gaps,
            self.units_missed,
            s.waiting_for_key
        )
    }

    fn csv_columns() -> &'static str {
        "pictures,decode_errors"
    }

    fn csv_values(&self) -> String {
        let s = self.decoder.stats();
        format!("{},{}", s.pictures, s.errors)
    }
}

/// Registers `video_client`.
pub fn register(registry: &mut StageRegistry) {
    register_client::<VideoClient>(
        registry,
        "video_client",
        TECHNIQUE,
        "decodes H.264 access units and shows the pictures (a thin client)",
        VIDEO_EDGE,
    );
}
