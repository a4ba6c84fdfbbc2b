//! `irradiance_reconstructor` and `irradiance_raw_reconstructor`: the client side of the
//! irradiance-map technique (CloudLight §4.2), one per client, on the shared client shell
//! ([`crate::client`]).
//!
//! What is its own:
//! - **Decoding on its own thread**: every message goes to a decode thread that the client
//!   owns (the async runtime's workers never decode). `irradiance_reconstructor` takes the
//!   H.264 stream of a `video_encoder` ([`VideoMsg`]: decode, then unpack the HDR packing); a
//!   gap in the stream (units lost upstream) makes it wait for the next key frame rather than
//!   show a corrupt map. `irradiance_raw_reconstructor` takes the f16 map itself
//!   ([`FrameMsg::Hdr`], the raw cut), checked on arrival.
//! - **The temporal filter** (the paper's): each new map is blended over the last in map
//!   space, `shown += blend × (new − shown)`. The time the shown light is valid as of is
//!   blended with the same weight, `valid += blend × (t_new − valid)`: a mixture of maps is as
//!   old as the weighted mean of their ages, so the age the shell reports (scene time now
//!   minus that) counts the filter's lag. `blend = 1` shows each map as it arrives.
//! - **Steady maps**: a map marked steady (a static scene whose map converged; the gatherer
//!   re-sends it every `resend_s`) stays valid until superseded, so while it is the newest
//!   map blended in the age of the light shown is 0, not the time since the last re-send.
//! - **Outage and late join**: the last map stays shown for as long as nothing arrives; the
//!   next map that arrives is blended in. A client joining an H.264 stream late shows light
//!   at its first key frame (at most the encoder's `keyframe_s` later).
//! - **Its pass** ([`LightmapPass`]): the map uploaded once per new map, looked up through the
//!   G-buffer's light-map UVs with bilinear filtering, ρ/π × E beside the client's own direct
//!   light. The shell draws the light map's unwrapped scene ([`unwrapped`], the same atlas
//!   settings as the gatherer's), whose triangles carry those UVs.

use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use cloudlight_render::HdrMap;
use cloudlight_render::lightmap::{AtlasSettings, LightmapPass, unwrapped};
use cloudlight_render::raster::{Raster, RasterError};
use cloudlight_render::video::{Decoder, hdr};
use cloudlight_runtime::{
    CheckParams, EdgeSettings, Latency, Message, Policy, StageRegistry, StageSetup, Stamped, lock,
};
use cloudlight_scenes::Scene;
use cloudlight_scenes::glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::basis_gatherer::TECHNIQUE;
use crate::client::{ClientTechnique, register as register_client};
use crate::video_client::VIDEO_EDGE;
use crate::wire::{FrameMsg, VideoMsg};

/// Default settings of a raw client's input: each map is complete, the newest supersedes.
pub const RAW_EDGE: EdgeSettings = EdgeSettings {
    capacity: 2,
    policy: Policy::Latest,
};

/// The irradiance client's own parameters (beside the shell's). The atlas settings must be
/// the gatherer's: the client unwraps the same scene the same way to draw the map.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct IrradianceClientParams {
    /// Weight of a new map over the one shown (0 < blend ≤ 1; 1: no temporal filter).
    pub blend: f32,
    /// The gatherer's `texels_per_m2`.
    pub texels_per_m2: f64,
    /// The gatherer's `resolution`.
    pub resolution: u32,
    /// The gatherer's `max_resolution`.
    pub max_resolution: u32,
    /// The gatherer's `max_texel_m`.
    pub max_texel_m: f32,
    /// The gatherer's `unwrap_limit_s`.
    pub unwrap_limit_s: f64,
}

impl Default for IrradianceClientParams {
    fn default() -> Self {
        let a = AtlasSettings::default();
        IrradianceClientParams {
            blend: 0.5,
            texels_per_m2: a.texels_per_m2,
            resolution: a.resolution,
            max_resolution: a.max_resolution,
            max_texel_m: a.max_texel_m,
            unwrap_limit_s: a.unwrap_limit_s,
        }
    }
}

impl IrradianceClientParams {
    /// The atlas the client draws the map with.
    pub fn atlas_settings(&self) -> AtlasSettings {
        AtlasSettings {
            texels_per_m2: self.texels_per_m2,
            resolution: self.resolution,
            max_resolution: self.max_resolution,
            max_texel_m: self.max_texel_m,
            unwrap_limit_s: self.unwrap_limit_s,
            ..Default::default()
        }
    }
}

impl CheckParams for IrradianceClientParams {
    fn check(&self) -> Result<(), String> {
        if !(self.blend > 0.0 && self.blend <= 1.0) {
            return Err(format!(
                "`blend` = {} must be in (0, 1] (1: no temporal filter)",
                self.blend
            ));
        }
        crate::basis_gatherer::check_atlas(&self.atlas_settings())
    }
}

/// The irradiance client's figures in its report.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct IrradianceClientReport {
    /// Map side the client's atlas expects, texels (width).
    pub map_width: u32,
    /// Height, texels.
    pub map_height: u32,
    /// Messages received.
    pub units_received: u64,
    /// Bytes of them (access units or f16 maps).
    pub bytes_received: u64,
    /// Maps decoded.
    pub maps_decoded: u64,
    /// Maps blended into the one shown.
    pub maps_blended: u64,
    /// Maps of another size than the atlas's (a gatherer with other atlas settings), dropped.
    pub maps_mismatched: u64,
    /// Maps older than the newest blended in, dropped.
    pub maps_stale: u64,
    /// Messages that could not be decoded (or failed their checks).
    pub decode_errors: u64,
    /// H.264 units dropped waiting for a key frame (a late join, or after a gap).
    pub waiting_for_key: u64,
    /// Decode (and unpack) per map, p50, ms.
    pub decode_ms_p50: f64,
    /// p99, ms.
    pub decode_ms_p99: f64,
    /// The temporal filter's weight.
    pub blend: f32,
    /// Bytes the client holds for the map on the GPU (f16 RGBA).
    pub map_bytes: u64,
}

/// A map a message carried, as linear texels.
#[derive(Clone, Debug, PartialEq)]
pub struct DecodedMap {
    /// Width, texels.
    pub width: u32,
    /// Height, texels.
    pub height: u32,
    /// Row-major from the top.
    pub texels: Vec<Vec3>,
}

/// Where maps come from: a message type and how its maps are decoded (on the decode
/// thread, which owns the source).
pub trait MapSource: Send + Sized + 'static {
    /// The messages.
    type Msg: Message + Clone;
    /// A source ready for the first message.
    fn new() -> anyhow::Result<Self>;
    /// Payload bytes of a message.
    fn bytes(msg: &Self::Msg) -> usize;
    /// Whether the message's map stays valid until superseded (a converged static map).
    fn steady(msg: &Self::Msg) -> bool;
    /// The map `msg` completes (`None`: nothing to show yet), or why it cannot be used.
    fn decode(&mut self, msg: &Self::Msg) -> Result<Option<DecodedMap>, String>;
    /// Units dropped waiting for a key frame.
    fn waiting_for_key(&self) -> u64 {
        0
    }
}

/// H.264 light maps from a `video_encoder`.
pub struct H264Maps {
    decoder: Decoder,
    next_index: Option<u64>,
}

impl MapSource for H264Maps {
    type Msg = VideoMsg;

    fn new() -> anyhow::Result<Self> {
        Ok(H264Maps {
            decoder: Decoder::new()?,
            next_index: None,
        })
    }

    fn bytes(msg: &VideoMsg) -> usize {
        msg.data.len()
    }

    fn steady(msg: &VideoMsg) -> bool {
        msg.steady
    }

    fn decode(&mut self, msg: &VideoMsg) -> Result<Option<DecodedMap>, String> {
        let Some(range) = msg.hdr else {
            return Err(format!(
                "unit {} is an SDR picture, not a light map",
                msg.index
            ));
        };
        if self.next_index.is_some_and(|n| n != msg.index) {
            self.decoder.lose_sync();
        }
        self.next_index = Some(msg.index + 1);
        match self.decoder.decode(&msg.data) {
            Ok(Some(yuv)) => Ok(Some(DecodedMap {
                width: yuv.width,
                height: yuv.height,
                texels: hdr::unpack(&yuv, range),
            })),
            Ok(None) => Ok(None),
            Err(e) => Err(format!("unit {}: {e}", msg.index)),
        }
    }

    fn waiting_for_key(&self) -> u64 {
        self.decoder.stats().waiting_for_key
    }
}

/// Raw f16 maps ([`FrameMsg::Hdr`]).
pub struct RawMaps;

impl MapSource for RawMaps {
    type Msg = FrameMsg;

    fn new() -> anyhow::Result<Self> {
        Ok(RawMaps)
    }

    fn bytes(msg: &FrameMsg) -> usize {
        match msg {
            FrameMsg::Hdr { map, .. } => map.data_bytes(),
            FrameMsg::Sdr { rgb, .. } => rgb.len(),
        }
    }

    fn steady(msg: &FrameMsg) -> bool {
        matches!(msg, FrameMsg::Hdr { steady: true, .. })
    }

    fn decode(&mut self, msg: &FrameMsg) -> Result<Option<DecodedMap>, String> {
        match msg {
            FrameMsg::Hdr { map, .. } => {
                map.check().map_err(|e| e.to_string())?;
                Ok(Some(DecodedMap {
                    width: map.width(),
                    height: map.height(),
                    texels: map.texels(),
                }))
            }
            FrameMsg::Sdr { .. } => Err("an SDR picture, not a light map".into()),
        }
    }
}

/// The blended map and the decode thread's figures, shared with the client.
#[derive(Default)]
struct Shared {
    /// The map shown (blended) and the scene time it is valid as of.
    shown: Option<(Arc<HdrMap>, f64)>,
    /// The newest map blended in stays valid until superseded (a converged static map).
    steady: bool,
    /// Bumped at each new blend.
    version: u64,
    maps_decoded: u64,
    maps_blended: u64,
    maps_mismatched: u64,
    maps_stale: u64,
    decode_errors: u64,
    waiting_for_key: u64,
    decode: Latency,
}

/// One message for the decode thread.
struct Job<M> {
    time_s: f64,
    body: M,
}

/// The temporal filter: `shown += blend × (new − shown)` (the first map as it is).
struct Blender {
    blend: f32,
    texels: Vec<Vec3>,
    time_s: f64,
    size: (u32, u32),
}

impl Blender {
    /// Blends `map` (valid as of `time_s`) in; the result.
    fn add(&mut self, map: DecodedMap, time_s: f64) -> &[Vec3] {
        if self.texels.is_empty() || self.size != (map.width, map.height) {
            self.texels = map.texels;
            self.time_s = time_s;
            self.size = (map.width, map.height);
        } else {
            let w = self.blend;
            for (shown, new) in self.texels.iter_mut().zip(&map.texels) {
                let new = if new.is_finite() { *new } else { Vec3::ZERO };
                *shown += w * (new - *shown);
            }
            self.time_s += f64::from(w) * (time_s - self.time_s);
        }
        &self.texels
    }
}

/// The decode thread: decodes each job, blends each map in and publishes the result.
fn decode_loop<S: MapSource>(
    mut source: S,
    jobs: mpsc::Receiver<Job<S::Msg>>,
    shared: Arc<Mutex<Shared>>,
    expected: (u32, u32),
    blend: f32,
    stage: String,
) {
    let mut blender = Blender {
        blend,
        texels: Vec::new(),
        time_s: 0.0,
        size: (0, 0),
    };
    // Scene time of the newest map blended in: an older one is stale.
    let mut newest_s: Option<f64> = None;
    let warn = |n: u64, what: &str| {
        // Logged at 1, 2, 4, 8, ... so that a flood stays readable.
        if n.is_power_of_two() {
            tracing::warn!(stage, count = n, "{what}");
        }
    };
    while let Ok(job) = jobs.recv() {
        let start = Instant::now();
        let decoded = source.decode(&job.body);
        let steady = S::steady(&job.body);
        let decode_time = start.elapsed();
        let waiting = source.waiting_for_key();
        let map = match decoded {
            Ok(Some(map)) => map,
            Ok(None) => {
                lock(&shared).waiting_for_key = waiting;
                continue;
            }
            Err(e) => {
                let mut s = lock(&shared);
                s.decode_errors += 1;
                s.waiting_for_key = waiting;
                warn(s.decode_errors, &format!("light map dropped: {e}"));
                continue;
            }
        };
        if (map.width, map.height) != expected {
            let mut s = lock(&shared);
            s.maps_decoded += 1;
            s.waiting_for_key = waiting;
            s.decode.record(decode_time);
            s.maps_mismatched += 1;
            warn(
                s.maps_mismatched,
                &format!(
                    "a {}×{} light map where this client's atlas is {}×{}: are the client's atlas settings the gatherer's?",
                    map.width, map.height, expected.0, expected.1
                ),
            );
            continue;
        }
        if newest_s.is_some_and(|t| job.time_s < t) {
            let mut s = lock(&shared);
            s.maps_decoded += 1;
            s.decode.record(decode_time);
            s.maps_stale += 1;
            continue;
        }
        newest_s = Some(job.time_s);
        let (w, h) = (map.width, map.height);
        let texels = blender.add(map, job.time_s);
        let shown = HdrMap::new(w, h, texels, &[]).map(Arc::new);
        // One lock for the map and its counts: a report never sees one without the other.
        let mut s = lock(&shared);
        s.maps_decoded += 1;
        s.waiting_for_key = waiting;
        s.decode.record(decode_time);
        let shown = match shown {
            Ok(m) => m,
            Err(e) => {
                s.decode_errors += 1;
                tracing::warn!(stage, "blended map refused: {e}");
                continue;
            }
        };
        s.shown = Some((shown, blender.time_s));
        s.steady = steady;
        s.version += 1;
        s.maps_blended += 1;
    }
}

/// The irradiance technique's part of a client, its maps from `S`.
pub struct IrradianceClient<S: MapSource> {
    jobs: Option<mpsc::Sender<Job<S::Msg>>>,
    shared: Arc<Mutex<Shared>>,
    applied: u64,
    units: u64,
    bytes: u64,
    drawn: Arc<Scene>,
    size: (u32, u32),
    blend: f32,
}

impl<S: MapSource> ClientTechnique for IrradianceClient<S> {
    type Msg = S::Msg;
    type Params = IrradianceClientParams;
    type Pass = LightmapPass;
    type Update = Arc<HdrMap>;
    type Report = IrradianceClientReport;

    fn new(setup: &StageSetup, params: &Self::Params, scene: &Arc<Scene>) -> anyhow::Result<Self> {
        let (drawn, atlas) = unwrapped(scene, &params.atlas_settings()).map_err(|e| {
            anyhow::anyhow!(
                "{}: {} has no irradiance map (n/a): {e}",
                setup.info.name,
                scene.name
            )
        })?;
        let size = (atlas.width, atlas.height);
        let shared = Arc::new(Mutex::new(Shared::default()));
        let (tx, rx) = mpsc::channel();
        let source = S::new()?;
        let (thread_shared, blend, stage) =
            (shared.clone(), params.blend, setup.info.name.to_string());
        std::thread::Builder::new()
            .name(format!("{}-decode", setup.info.name))
            .spawn(move || decode_loop(source, rx, thread_shared, size, blend, stage))?;
        Ok(IrradianceClient {
            jobs: Some(tx),
            shared,
            applied: 0,
            units: 0,
            bytes: 0,
            drawn,
            size,
            blend: params.blend,
        })
    }

    fn on_message(&mut self, stage: &str, msg: &Stamped<S::Msg>) {
        self.units += 1;
        self.bytes += S::bytes(&msg.body) as u64;
        let job = Job {
            time_s: msg.scene_time_s,
            body: msg.body.clone(),
        };
        if let Some(jobs) = &self.jobs
            && jobs.send(job).is_err()
        {
            tracing::error!(stage, "the light-map decode thread has stopped");
            self.jobs = None;
        }
    }

    fn valid_as_of(&self) -> Option<f64> {
        lock(&self.shared).shown.as_ref().map(|(_, t)| *t)
    }

    fn is_current(&self) -> bool {
        lock(&self.shared).steady
    }

    fn new_pass(raster: &Raster, _: &Self::Params) -> Result<LightmapPass, RasterError> {
        LightmapPass::new(raster)
    }

    fn update(&mut self) -> Option<Arc<HdrMap>> {
        let s = lock(&self.shared);
        if s.version == self.applied {
            return None;
        }
        self.applied = s.version;
        s.shown.as_ref().map(|(map, _)| map.clone())
    }

    fn apply(
        pass: &mut LightmapPass,
        raster: &Raster,
        map: Arc<HdrMap>,
    ) -> Result<(), RasterError> {
        pass.set_map(raster, &map)
    }

    fn drawn_scene(&self) -> Option<Arc<Scene>> {
        Some(self.drawn.clone())
    }

    fn check_scene(params: &Self::Params, scene: &Scene) -> Result<(), String> {
        unwrapped(scene, &params.atlas_settings())
            .map(|_| ())
            .map_err(|e| format!("{} has no irradiance map (n/a): {e}", scene.name))
    }

    fn report(&self) -> IrradianceClientReport {
        let s = lock(&self.shared);
        IrradianceClientReport {
            map_width: self.size.0,
            map_height: self.size.1,
            units_received: self.units,
            bytes_received: self.bytes,
            maps_decoded: s.maps_decoded,
            maps_blended: s.maps_blended,
            maps_mismatched: s.maps_mismatched,
            maps_stale: s.maps_stale,
            decode_errors: s.decode_errors,
            waiting_for_key: s.waiting_for_key,
            decode_ms_p50: s.decode.p50_ms(),
            decode_ms_p99: s.decode.p99_ms(),
            blend: self.blend,
            map_bytes: self.size.0 as u64 * self.size.1 as u64 * 8,
        }
    }

    fn summary(&self) -> String {
        let r = self.report();
        format!(
            "{} of {} maps blended ({}×{}, blend {}), decode {:.2} ms p50, {} undecodable, {} mismatched",
            r.maps_blended,
            r.units_received,
            r.map_width,
            r.map_height,
            r.blend,
            r.decode_ms_p50,
            r.decode_errors,
            r.maps_mismatched
        )
    }

    fn csv_columns() -> &'static str {
        "maps_blended"
    }

    fn csv_values(&self) -> String {
        lock(&self.shared).maps_blended.to_string()
    }
}

/// Registers `irradiance_reconstructor` (H.264 maps) and `irradiance_raw_reconstructor`
/// (f16 maps).
pub fn register(registry: &mut StageRegistry) {
    register_client::<IrradianceClient<H264Maps>>(
        registry,
        "irradiance_reconstructor",
        TECHNIQUE,
        "decodes H.264 irradiance maps, blends them over time and shows them through the light-map UVs beside its own direct light",
        VIDEO_EDGE,
    );
    register_client::<IrradianceClient<RawMaps>>(
        registry,
        "irradiance_raw_reconstructor",
        TECHNIQUE,
        "takes raw f16 irradiance maps, blends them over time and shows them through the light-map UVs beside its own direct light",
        RAW_EDGE,
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    fn constant(v: f32) -> DecodedMap {
        DecodedMap {
            width: 2,
            height: 1,
            texels: vec![Vec3::splat(v); 2],
        }
    }

    #[test]
    fn blending_converges_to_a_constant_map_and_follows_a_step_at_its_rate() {
        let mut b = Blender {
            blend: 0.25,
            texels: Vec::new(),
            time_s: 0.0,
            size: (0, 0),
        };
        // The first map is shown as it is.
        assert_eq!(b.add(constant(2.0), 1.0)[0], Vec3::splat(2.0));
        assert_eq!(b.time_s, 1.0);
        // A constant map stays constant.
        for k in 0..10 {
            assert_eq!(b.add(constant(2.0), 1.0 + k as f64)[0], Vec3::splat(2.0));
        }
        // A step to 6: after n maps the gap is (1 − 0.25)ⁿ of the step.
        let mut t = 11.0;
        for n in 1..=20 {
            t += 1.0;
            let shown = b.add(constant(6.0), t)[0].x;
            let want = 6.0 - 4.0 * 0.75f32.powi(n);
            assert!((shown - want).abs() < 1e-4, "map {n}: {shown} vs {want}");
        }
        // The time it is valid as of lags the newest map by what the filter holds back:
        // with maps 1 s apart, (1 − w) / w = 3 s.
        assert!((t - b.time_s - 3.0).abs() < 0.01, "lag {}", t - b.time_s);
        // Non-finite texels blend in as 0, never as NaN.
        let mut bad = constant(1.0);
        bad.texels[0] = Vec3::NAN;
        assert!(b.add(bad, t + 1.0).iter().all(|c| c.is_finite()));
    }

    #[test]
    fn a_gap_in_the_h264_stream_waits_for_the_next_key_frame() {
        use cloudlight_render::video::{Encoder, EncoderSettings, RateControl};
        let (w, h) = (32u32, 16u32);
        let map = |k: f32| {
            let texels: Vec<Vec3> = (0..w * h)
                .map(|i| Vec3::new(1.0 + (i % w) as f32 * k, 2.0, 0.5))
                .collect();
            HdrMap::new(w, h, &texels, &[]).unwrap()
        };
        // Key frames every 4 pictures at 10 per second.
        let mut enc = Encoder::new(EncoderSettings {
            width: w,
            height: h,
            fps: 10.0,
            rate: RateControl::FixedQp(20),
            keyframe_s: 0.4,
            ..Default::default()
        })
        .unwrap();
        let units: Vec<VideoMsg> = (0..9u64)
            .map(|i| {
                let packed = hdr::pack(&map(0.01 * i as f32)).unwrap();
                let u = enc.encode(&packed.yuv, i as f64 / 10.0).unwrap().unwrap();
                VideoMsg {
                    index: i,
                    key: u.key,
                    timestamp_ms: i as i64 * 100,
                    width: w,
                    height: h,
                    hdr: Some(packed.range),
                    light_s: None,
                    steady: false,
                    data: u.data,
                }
            })
            .collect();
        let keys: Vec<u64> = units.iter().filter(|u| u.key).map(|u| u.index).collect();
        assert_eq!(keys, [0, 4, 8], "the stream's key frames");
        let mut source = H264Maps::new().unwrap();
        let shown = |s: &mut H264Maps, u: &VideoMsg| s.decode(u).unwrap().is_some();
        assert!(shown(&mut source, &units[0]) && shown(&mut source, &units[1]));
        // Unit 2 is lost: 3 refers to it, so 3 and the P frames after it are not shown...
        for u in &units[3..4] {
            assert!(!shown(&mut source, u), "unit {}", u.index);
        }
        assert_eq!(source.waiting_for_key(), 1);
        // ...until the key frame at 4, after which every unit shows again.
        for u in &units[4..] {
            assert!(shown(&mut source, u), "unit {}", u.index);
        }
        assert_eq!(source.waiting_for_key(), 1);
        // An SDR picture is refused, not shown.
        let sdr = VideoMsg {
            hdr: None,
            ..units[0].clone()
        };
        assert!(source.decode(&sdr).unwrap_err().contains("SDR"));
    }

    #[test]
    fn the_client_and_the_gatherer_unwrap_alike_by_default() {
        let c = IrradianceClientParams::default();
        let g = crate::basis_gatherer::GathererParams::default();
        assert_eq!(c.atlas_settings(), g.lightmap_settings().atlas);
        assert!(c.check().is_ok());
        for blend in [0.0, -1.0, 1.5, f32::NAN] {
            let p = IrradianceClientParams {
                blend,
                ..Default::default()
            };
            assert!(p.check().unwrap_err().contains("blend"), "{blend}");
        }
    }
}
