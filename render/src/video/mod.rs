//! H.264 video: SDR frames (RGB8) and HDR light maps in 8-bit 4:2:0, over openh264.
//!
//! - [`yuv`]: I420 planes; RGB8 ↔ YUV with the BT.709 matrix, full range.
//! - [`encoder`]: openh264's encoder through its raw API: a target bitrate or a fixed QP,
//!   every frame stamped with its time, key frames every `keyframe_s` and on demand, frame
//!   skipping only when asked.
//! - [`decoder`]: openh264's decoder, fed anything without panicking: bad access units are
//!   counted errors and the decoder resumes at the next key frame.
//! - [`hdr`]: log₂ luminance in Y and chromaticity in U/V, the range beside the stream; the
//!   error that packing (and packing with encoding) adds.
//!
//! Kernels only: no actors, no sockets. The stages that use them live in `cloudlight-actors`.

pub mod decoder;
pub mod encoder;
pub mod hdr;
pub mod measure;
pub mod record;
pub mod yuv;

#[cfg(test)]
mod tests;

pub use decoder::{Decoder, DecoderStats, is_key_unit};
pub use encoder::{EncodedFrame, Encoder, EncoderSettings, RateControl};
pub use hdr::{HdrError, HdrRange, Packed};
pub use record::Recorder;
pub use yuv::{FrameError, Yuv420, psnr};

/// Why video could not be encoded or decoded.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum VideoError {
    /// A frame of a size or length the codec cannot take.
    #[error(transparent)]
    Frame(#[from] FrameError),
    /// Settings out of range.
    #[error("video settings: {0}")]
    Settings(String),
    /// openh264 refused a call.
    #[error("{0}")]
    Codec(String),
    /// An access unit could not be decoded.
    #[error("undecodable access unit: {0}")]
    Decode(String),
}
