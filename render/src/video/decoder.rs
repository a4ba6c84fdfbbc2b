//! The H.264 decoder (openh264's, through the `openh264` crate) made safe to feed anything:
//! an access unit that is truncated, reordered or garbled is an error that is counted, never
//! a panic, and after one the decoder shows nothing until the next key frame decodes (it
//! would otherwise show pictures predicted from broken references).

use openh264::decoder::{DecodedYUV, Decoder as H264Decoder, DecoderConfig, Flush};
use openh264::formats::YUVSource;

use super::VideoError;
use super::yuv::{Yuv420, check_size};

/// What the decoder has seen.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct DecoderStats {
    /// Access units given.
    pub units: u64,
    /// Pictures returned.
    pub pictures: u64,
    /// Access units the decoder refused (malformed, truncated, reordered).
    pub errors: u64,
    /// Access units dropped while waiting for a key frame (after an error, or before the
    /// first key frame of a stream joined late).
    pub waiting_for_key: u64,
}

/// A decoder that recovers at key frames.
pub struct Decoder {
    inner: H264Decoder,
    synced: bool,
    stats: DecoderStats,
}

/// NAL units of an Annex-B access unit, without their start codes, in order.
pub fn nal_payloads(unit: &[u8]) -> Vec<&[u8]> {
    openh264::nal_units(unit)
        .filter_map(|nal| {
            // Skip the start code (00 00 01 or 00 00 00 01) to the header byte.
            let start = nal.iter().position(|&b| b == 1)? + 1;
            nal.get(start..).filter(|p| !p.is_empty())
        })
        .collect()
}

/// NAL unit types of an Annex-B access unit, in order.
pub fn nal_types(unit: &[u8]) -> impl Iterator<Item = u8> + '_ {
    nal_payloads(unit).into_iter().map(|nal| nal[0] & 0x1f)
}

/// Whether an access unit holds an IDR slice (NAL type 5): a decoder can start there.
pub fn is_key_unit(unit: &[u8]) -> bool {
    nal_types(unit).any(|t| t == 5)
}

impl Decoder {
    /// A decoder waiting for its first key frame.
    pub fn new() -> Result<Self, VideoError> {
        Ok(Decoder {
            inner: new_inner()?,
            synced: false,
            stats: DecoderStats::default(),
        })
    }

    /// What it has seen so far.
    pub fn stats(&self) -> DecoderStats {
        self.stats
    }

    /// Units were lost upstream (a gap in the stream): what follows is undecodable until the
    /// next key frame, so units are dropped (counted as waiting) until one arrives.
    pub fn lose_sync(&mut self) {
        self.synced = false;
    }

    /// Decodes one access unit: `Ok(Some(picture))` when it completes one, `Ok(None)` when it
    /// needs more data or is waiting for a key frame, `Err` (counted) when the unit is bad.
    ///
    /// A key frame starts afresh: after an error the decoder is made anew for it, and a key
    /// frame that shows nothing (state left by a unit that parsed but was wrong) is decoded
    /// again by a new decoder, so a clean key frame always shows.
    pub fn decode(&mut self, unit: &[u8]) -> Result<Option<Yuv420>, VideoError> {
        self.stats.units += 1;
        let key = is_key_unit(unit);
        if !self.synced && !key {
            self.stats.waiting_for_key += 1;
            return Ok(None);
        }
        let mut fresh = false;
        if key && !self.synced {
            self.inner = new_inner()?;
            fresh = true;
        }
        let mut decoded = decode_guarded(&mut self.inner, unit);
        if key && !fresh && !matches!(decoded, Ok(Some(_))) {
            self.inner = new_inner()?;
            decoded = decode_guarded(&mut self.inner, unit);
        }
        match decoded {
            Ok(picture) => {
                if key {
                    self.synced = true;
                }
                if picture.is_some() {
                    self.stats.pictures += 1;
                }
                Ok(picture)
            }
            Err(e) => {
                self.stats.errors += 1;
                self.synced = false;
                Err(e)
            }
        }
    }
}

fn new_inner() -> Result<H264Decoder, VideoError> {
    let config = DecoderConfig::new().flush_after_decode(Flush::Flush);
    H264Decoder::with_api_config(openh264::OpenH264API::from_source(), config)
        .map_err(|e| VideoError::Codec(format!("cannot make an openh264 decoder: {e}")))
}

/// One call into the decoder, its panics (the wrapper's, on pictures it cannot describe)
/// turned into errors.
fn decode_guarded(inner: &mut H264Decoder, unit: &[u8]) -> Result<Option<Yuv420>, VideoError> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| match inner.decode(unit) {
        Ok(Some(p)) => copy_planes(&p).map(Some),
        Ok(None) => Ok(None),
        Err(e) => Err(VideoError::Decode(e.to_string())),
    }))
    .unwrap_or_else(|_| Err(VideoError::Decode("the decoder wrapper panicked".into())))
}

/// Copies a decoded picture out of the decoder's buffers (tightly packed).
fn copy_planes(p: &DecodedYUV<'_>) -> Result<Yuv420, VideoError> {
    let (w, h) = p.dimensions();
    let (sy, su, sv) = p.strides();
    check_size(w as u32, h as u32).map_err(|e| VideoError::Decode(e.to_string()))?;
    let (cw, ch) = (w / 2, h / 2);
    let plane = |data: &[u8], stride: usize, pw: usize, ph: usize| -> Result<Vec<u8>, VideoError> {
        if stride < pw || data.len() < stride * (ph - 1) + pw {
            return Err(VideoError::Decode(format!(
                "a decoded plane of {} bytes cannot hold {pw}×{ph} at stride {stride}",
                data.len()
            )));
        }
        let mut out = Vec::with_capacity(pw * ph);
        for row in 0..ph {
            out.extend_from_slice(&data[row * stride..row * stride + pw]);
        }
        Ok(out)
    };
    Ok(Yuv420 {
        width: w as u32,
        height: h as u32,
        y: plane(p.y(), sy, w, h)?,
        u: plane(p.u(), su, cw, ch)?,
        v: plane(p.v(), sv, cw, ch)?,
    })
}
