//! What video costs and loses, measured the same way by tests and `cloudlight bench video`:
//! HDR light maps through packing alone and through packing + H.264, SDR frames through
//! H.264, per rate setting.

use std::time::Instant;

use super::hdr::{self, HdrError};
use super::{Decoder, Encoder, EncoderSettings, RateControl, VideoError, Yuv420, psnr};
use crate::hdr_map::HdrMap;

/// An HDR map from the reference path tracer: the indirect light of `scene` seen from its
/// first camera, `size`² texels at `spp` samples — a stand-in for a light map (the
/// irradiance technique's texel maps do not exist yet) with a light map's dynamic range.
pub fn reference_map(scene: &cloudlight_scenes::Scene, size: u32, spp: u32) -> HdrMap {
    let bvh = crate::SceneBvh::at(scene, 0.0, crate::BvhKind::default());
    let camera = scene
        .cameras
        .first()
        .map_or_else(|| scene.overview_camera(), |c| c.at(0.0));
    let settings = crate::RenderSettings {
        width: size,
        height: size,
        camera,
        time_s: 0.0,
        seed: 1,
        max_bounces: 16,
        pixel: Default::default(),
    };
    let images = crate::render(scene, &bvh, settings, spp);
    HdrMap::new(size, size, &images.indirect(), &[]).expect("one texel per pixel")
}

/// One rate setting's figures for an HDR map: a key frame and the P frame after it.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct HdrCodecFigures {
    /// The rate setting.
    pub rate: RateControl,
    /// Error of packing alone.
    pub packing: HdrError,
    /// Error after packing, encoding and decoding the key frame.
    pub key: HdrError,
    /// Error of the P frame that follows (the same map again).
    pub next: HdrError,
    /// Bytes of the key frame.
    pub key_bytes: usize,
    /// Bytes of the P frame.
    pub next_bytes: usize,
}

/// Packs, encodes and decodes `img` twice with `rate`.
pub fn hdr_codec(img: &HdrMap, rate: RateControl) -> Result<HdrCodecFigures, VideoError> {
    let packed = hdr::pack(img)?;
    let packing = hdr::error(img, &hdr::unpack(&packed.yuv, packed.range), packed.range);
    let mut enc = Encoder::new(EncoderSettings {
        width: img.width(),
        height: img.height(),
        fps: 30.0,
        rate,
        keyframe_s: 60.0,
        ..Default::default()
    })?;
    let mut dec = Decoder::new()?;
    let mut round = |t: f64| -> Result<(HdrError, usize), VideoError> {
        let unit = enc
            .encode(&packed.yuv, t)?
            .ok_or_else(|| VideoError::Codec("a frame was skipped".into()))?;
        let picture = dec
            .decode(&unit.data)?
            .ok_or_else(|| VideoError::Decode("no picture from a complete unit".into()))?;
        let decoded = hdr::unpack(&picture, packed.range);
        Ok((hdr::error(img, &decoded, packed.range), unit.data.len()))
    };
    let (key, key_bytes) = round(0.0)?;
    let (next, next_bytes) = round(1.0 / 30.0)?;
    Ok(HdrCodecFigures {
        rate,
        packing,
        key,
        next,
        key_bytes,
        next_bytes,
    })
}

/// One rate setting's figures for a stream of SDR frames.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SdrCodecFigures {
    /// The rate setting.
    pub rate: RateControl,
    /// Frame size, pixels.
    pub width: u32,
    /// Frame height, pixels.
    pub height: u32,
    /// Frames encoded.
    pub frames: usize,
    /// Encode time per frame, median, milliseconds (one thread).
    pub encode_ms_p50: f64,
    /// Decode time per frame, median, milliseconds.
    pub decode_ms_p50: f64,
    /// Megabits per second at 30 frames per second.
    pub mbps_at_30hz: f64,
    /// Mean luma PSNR, dB.
    pub psnr_y_db: f64,
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(0.0)
}

/// Encodes and decodes `frames` (RGB8, all of one size) at 30 Hz with `rate`, timing both.
pub fn sdr_codec(
    width: u32,
    height: u32,
    frames: &[Vec<u8>],
    rate: RateControl,
) -> Result<SdrCodecFigures, VideoError> {
    let mut enc = Encoder::new(EncoderSettings {
        width,
        height,
        fps: 30.0,
        rate,
        keyframe_s: 2.0,
        ..Default::default()
    })?;
    let mut dec = Decoder::new()?;
    let (mut enc_ms, mut dec_ms, mut psnrs) = (Vec::new(), Vec::new(), Vec::new());
    let mut bytes = 0usize;
    for (i, rgb) in frames.iter().enumerate() {
        let yuv = Yuv420::from_rgb8(width, height, rgb)?;
        let t = Instant::now();
        let unit = enc
            .encode(&yuv, i as f64 / 30.0)?
            .ok_or_else(|| VideoError::Codec("a frame was skipped".into()))?;
        enc_ms.push(t.elapsed().as_secs_f64() * 1e3);
        bytes += unit.data.len();
        let t = Instant::now();
        let picture = dec
            .decode(&unit.data)?
            .ok_or_else(|| VideoError::Decode("no picture from a complete unit".into()))?;
        dec_ms.push(t.elapsed().as_secs_f64() * 1e3);
        psnrs.push(psnr(&yuv.y, &picture.y).min(99.0));
    }
    let n = frames.len().max(1) as f64;
    Ok(SdrCodecFigures {
        rate,
        width,
        height,
        frames: frames.len(),
        encode_ms_p50: median(enc_ms),
        decode_ms_p50: median(dec_ms),
        mbps_at_30hz: bytes as f64 * 8.0 * 30.0 / n / 1e6,
        psnr_y_db: psnrs.iter().sum::<f64>() / n,
    })
}
