//! The H.264 encoder: openh264's raw API (`openh264-sys2`, built from source), driven so that
//! what this project needs is set explicitly.
//!
//! Why the raw API and not `openh264::encoder::Encoder`: that wrapper cannot set the QP of a
//! fixed-QP stream (openh264 takes it from the spatial layer's `iDLayerQp`, which the wrapper
//! leaves at 26), initialises lazily on the first frame, and stamps `encode()` with time 0.
//! Here every frame carries its time in milliseconds, rate control is either a target
//! bitrate (openh264's minimum QP there is 12) or a fixed QP with adaptive quantisation off,
//! key frames come every `keyframe_s` of stream time and on demand, and frame skipping is off
//! unless asked for. Colour is signalled in the VUI: BT.709 matrix and primaries, full range
//! (see [`super::yuv`]).
//!
//! This is the one module of the workspace allowed `unsafe` (the workspace denies it): calls
//! through openh264's C vtable, each with its `SAFETY` reason. Nothing else here is unsafe.
#![allow(unsafe_code)]

use std::os::raw::c_int;
use std::ptr::null_mut;

use openh264_sys2::{
    API, CAMERA_VIDEO_REAL_TIME, CONSTANT_ID, ENCODER_OPTION_DATAFORMAT,
    ENCODER_OPTION_TRACE_LEVEL, ISVCEncoder, ISVCEncoderVtbl, RC_BITRATE_MODE, RC_OFF_MODE,
    SEncParamExt, SFrameBSInfo, SM_SINGLE_SLICE, SSourcePicture, WELS_LOG_QUIET, videoFormatI420,
    videoFrameTypeIDR, videoFrameTypeInvalid, videoFrameTypeSkip,
};

use super::VideoError;
use super::yuv::{Yuv420, check_size};

/// How the encoder spends bits.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RateControl {
    /// A target bitrate, bits per second (QP 12 to 51 as openh264 chooses).
    Bitrate(u32),
    /// One QP for every macroblock of every frame (0 = best, 51 = coarsest).
    FixedQp(u8),
}

/// What an encoder is made with.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct EncoderSettings {
    /// Frame width, pixels (even).
    pub width: u32,
    /// Frame height, pixels (even).
    pub height: u32,
    /// Expected frames per second (rate control divides the bitrate by it).
    pub fps: f32,
    /// Rate control.
    pub rate: RateControl,
    /// Seconds of stream time between key frames (IDR); a client that joins waits at most
    /// this long for its first picture.
    pub keyframe_s: f64,
    /// Let rate control drop frames to meet the bitrate (off: every frame is encoded).
    pub skip_frames: bool,
    /// Encoder threads (1: the calling thread only).
    pub threads: u16,
}

impl Default for EncoderSettings {
    fn default() -> Self {
        EncoderSettings {
            width: 640,
            height: 360,
            fps: 30.0,
            rate: RateControl::Bitrate(3_000_000),
            keyframe_s: 2.0,
            skip_frames: false,
            threads: 1,
        }
    }
}

impl EncoderSettings {
    /// Checks the settings, naming what is wrong.
    pub fn check(&self) -> Result<(), VideoError> {
        check_size(self.width, self.height)?;
        let bad = |m: String| Err(VideoError::Settings(m));
        if !(self.fps.is_finite() && (0.1..=240.0).contains(&self.fps)) {
            return bad(format!("fps {} must be in [0.1, 240]", self.fps));
        }
        match self.rate {
            RateControl::Bitrate(bps) if !(10_000..=200_000_000).contains(&bps) => {
                return bad(format!("bitrate {bps} bit/s must be in [10000, 200000000]"));
            }
            RateControl::FixedQp(q) if q > 51 => {
                return bad(format!("QP {q} must be in [0, 51]"));
            }
            _ => {}
        }
        if !(self.keyframe_s.is_finite() && self.keyframe_s > 0.0 && self.keyframe_s <= 3600.0) {
            return bad(format!(
                "keyframe_s {} must be in (0, 3600] seconds",
                self.keyframe_s
            ));
        }
        if !(1..=16).contains(&self.threads) {
            return bad(format!("threads {} must be in [1, 16]", self.threads));
        }
        Ok(())
    }
}

/// One encoded frame: an access unit of Annex-B NAL units (start codes included; the first
/// key frame carries SPS and PPS).
#[derive(Clone, Debug, PartialEq)]
pub struct EncodedFrame {
    /// The access unit.
    pub data: Vec<u8>,
    /// An IDR frame: a decoder can start here.
    pub key: bool,
    /// Stream time, milliseconds (strictly increasing).
    pub timestamp_ms: i64,
    /// Frames given to the encoder before this one.
    pub index: u64,
}

/// The encoder's vtable entries, checked once.
struct Vtbl {
    initialize_ext: unsafe extern "C" fn(*mut ISVCEncoder, *const SEncParamExt) -> c_int,
    get_default_params: unsafe extern "C" fn(*mut ISVCEncoder, *mut SEncParamExt) -> c_int,
    uninitialize: unsafe extern "C" fn(*mut ISVCEncoder) -> c_int,
    encode_frame:
        unsafe extern "C" fn(*mut ISVCEncoder, *const SSourcePicture, *mut SFrameBSInfo) -> c_int,
    force_intra_frame: unsafe extern "C" fn(*mut ISVCEncoder, bool) -> c_int,
    set_option: unsafe extern "C" fn(*mut ISVCEncoder, c_int, *mut std::ffi::c_void) -> c_int,
}

impl Vtbl {
    /// # Safety
    /// `ptr` must be an encoder made by `WelsCreateSVCEncoder`.
    unsafe fn of(ptr: *mut ISVCEncoder) -> Result<Self, VideoError> {
        let missing = || VideoError::Codec("the openh264 encoder's vtable is incomplete".into());
        // SAFETY: the caller gives a live encoder, whose first field is its vtable.
        let v: ISVCEncoderVtbl = unsafe { **ptr };
        Ok(Vtbl {
            initialize_ext: v.InitializeExt.ok_or_else(missing)?,
            get_default_params: v.GetDefaultParams.ok_or_else(missing)?,
            uninitialize: v.Uninitialize.ok_or_else(missing)?,
            encode_frame: v.EncodeFrame.ok_or_else(missing)?,
            force_intra_frame: v.ForceIntraFrame.ok_or_else(missing)?,
            set_option: v.SetOption.ok_or_else(missing)?,
        })
    }
}

/// An H.264 encoder for frames of one size.
pub struct Encoder {
    api: openh264::OpenH264API,
    ptr: *mut ISVCEncoder,
    vtbl: Vtbl,
    settings: EncoderSettings,
    info: Box<SFrameBSInfo>,
    frames: u64,
    last_timestamp_ms: Option<i64>,
    last_key_ms: Option<i64>,
    key_requested: bool,
}

// SAFETY: the encoder is only used through `&mut self`; openh264 encoders may move between
// threads (they keep no thread-local state).
unsafe impl Send for Encoder {}

impl Encoder {
    /// Makes and initialises an encoder.
    pub fn new(settings: EncoderSettings) -> Result<Self, VideoError> {
        settings.check()?;
        let api = openh264::OpenH264API::from_source();
        let mut ptr: *mut ISVCEncoder = null_mut();
        // SAFETY: creating an encoder writes a fresh pointer.
        let rc = unsafe { api.WelsCreateSVCEncoder(&mut ptr) };
        if rc != 0 || ptr.is_null() {
            return Err(VideoError::Codec(format!(
                "WelsCreateSVCEncoder failed ({rc})"
            )));
        }
        // SAFETY: `ptr` was just made by WelsCreateSVCEncoder.
        let vtbl = match unsafe { Vtbl::of(ptr) } {
            Ok(v) => v,
            Err(e) => {
                // SAFETY: destroy what was made.
                unsafe { api.WelsDestroySVCEncoder(ptr) };
                return Err(e);
            }
        };
        let mut encoder = Encoder {
            api,
            ptr,
            vtbl,
            settings,
            info: Box::default(),
            frames: 0,
            last_timestamp_ms: None,
            last_key_ms: None,
            key_requested: false,
        };
        encoder.initialize()?;
        Ok(encoder)
    }

    fn initialize(&mut self) -> Result<(), VideoError> {
        let s = self.settings;
        let mut p = SEncParamExt::default();
        // SAFETY: the encoder is live; the struct is written by the call.
        check(
            unsafe { (self.vtbl.get_default_params)(self.ptr, &mut p) },
            "GetDefaultParams",
        )?;
        p.iUsageType = CAMERA_VIDEO_REAL_TIME;
        p.iPicWidth = s.width as c_int;
        p.iPicHeight = s.height as c_int;
        p.fMaxFrameRate = s.fps;
        p.iSpatialLayerNum = 1;
        p.iTemporalLayerNum = 1;
        p.uiIntraPeriod = 0; // key frames are forced by stream time instead
        p.eSpsPpsIdStrategy = CONSTANT_ID;
        p.bEnableFrameSkip = s.skip_frames;
        p.iMultipleThreadIdc = s.threads;
        p.iLoopFilterDisableIdc = 0;
        p.bEnableDenoise = false;
        let layer = &mut p.sSpatialLayers[0];
        layer.iVideoWidth = s.width as c_int;
        layer.iVideoHeight = s.height as c_int;
        layer.fFrameRate = s.fps;
        layer.sSliceArgument.uiSliceMode = SM_SINGLE_SLICE;
        layer.sSliceArgument.uiSliceNum = 1;
        layer.bVideoSignalTypePresent = true;
        layer.uiVideoFormat = 5; // unspecified
        layer.bFullRange = true;
        layer.bColorDescriptionPresent = true;
        layer.uiColorPrimaries = 1; // BT.709
        layer.uiTransferCharacteristics = 13; // IEC 61966-2-1 (sRGB)
        layer.uiColorMatrix = 1; // BT.709
        match s.rate {
            RateControl::Bitrate(bps) => {
                p.iRCMode = RC_BITRATE_MODE;
                p.iTargetBitrate = bps as c_int;
                p.iMaxBitrate = bps as c_int;
                layer.iSpatialBitrate = bps as c_int;
                layer.iMaxSpatialBitrate = bps as c_int;
                p.iMinQp = 12;
                p.iMaxQp = 51;
            }
            RateControl::FixedQp(q) => {
                p.iRCMode = RC_OFF_MODE;
                p.bEnableAdaptiveQuant = false;
                p.iMinQp = q as c_int;
                p.iMaxQp = q as c_int;
                layer.iDLayerQp = q as c_int;
            }
        }
        let mut trace: c_int = WELS_LOG_QUIET;
        let mut format: c_int = videoFormatI420;
        // SAFETY: the encoder is live, the parameters are a complete struct, and options take
        // a pointer to an int that outlives the call. Quiet first, so that initialising does
        // not print openh264's warnings (e.g. that a bitrate without frame skipping is a
        // target, not a cap: wanted here).
        unsafe {
            check(
                (self.vtbl.set_option)(
                    self.ptr,
                    ENCODER_OPTION_TRACE_LEVEL,
                    (&mut trace as *mut c_int).cast(),
                ),
                "SetOption(TRACE_LEVEL)",
            )?;
            check((self.vtbl.initialize_ext)(self.ptr, &p), "InitializeExt")?;
            check(
                (self.vtbl.set_option)(
                    self.ptr,
                    ENCODER_OPTION_DATAFORMAT,
                    (&mut format as *mut c_int).cast(),
                ),
                "SetOption(DATAFORMAT)",
            )?;
        }
        Ok(())
    }

    /// The settings it was made with.
    pub fn settings(&self) -> &EncoderSettings {
        &self.settings
    }

    /// Makes the next frame a key frame.
    pub fn request_key_frame(&mut self) {
        self.key_requested = true;
    }

    /// Encodes `frame` at stream time `time_s`. Stamps are milliseconds, kept strictly
    /// increasing (a time that goes back is moved 1 ms after the previous one). `None` when
    /// rate control skipped the frame (only with `skip_frames`).
    pub fn encode(
        &mut self,
        frame: &Yuv420,
        time_s: f64,
    ) -> Result<Option<EncodedFrame>, VideoError> {
        let s = self.settings;
        if (frame.width, frame.height) != (s.width, s.height) {
            return Err(VideoError::Settings(format!(
                "a {}×{} frame given to a {}×{} encoder",
                frame.width, frame.height, s.width, s.height
            )));
        }
        if !time_s.is_finite() {
            return Err(VideoError::Settings(format!(
                "frame time {time_s} s is not finite"
            )));
        }
        let wanted = (time_s * 1000.0).round().clamp(-9e15, 9e15) as i64;
        let ts = match self.last_timestamp_ms {
            Some(prev) if wanted <= prev => prev + 1,
            _ => wanted,
        };
        let keyframe_ms = (s.keyframe_s * 1000.0).round() as i64;
        let due = self.last_key_ms.is_none_or(|k| ts - k >= keyframe_ms);
        if due || self.key_requested {
            // SAFETY: the encoder is live.
            check(
                unsafe { (self.vtbl.force_intra_frame)(self.ptr, true) },
                "ForceIntraFrame",
            )?;
            self.key_requested = false;
        }
        let cw = frame.chroma_width() as c_int;
        let picture = SSourcePicture {
            iColorFormat: videoFormatI420,
            iStride: [frame.width as c_int, cw, cw, 0],
            // openh264 only reads the planes.
            pData: [
                frame.y.as_ptr().cast_mut(),
                frame.u.as_ptr().cast_mut(),
                frame.v.as_ptr().cast_mut(),
                null_mut(),
            ],
            iPicWidth: frame.width as c_int,
            iPicHeight: frame.height as c_int,
            uiTimeStamp: ts,
            bPsnrY: false,
            bPsnrU: false,
            bPsnrV: false,
        };
        // SAFETY: the picture's planes are as large as its size and strides say (checked by
        // `Yuv420`'s construction); the info struct is ours.
        check(
            unsafe { (self.vtbl.encode_frame)(self.ptr, &picture, &mut *self.info) },
            "EncodeFrame",
        )?;
        let index = self.frames;
        self.frames += 1;
        self.last_timestamp_ms = Some(ts);
        let kind = self.info.eFrameType;
        if kind == videoFrameTypeSkip || kind == videoFrameTypeInvalid {
            return Ok(None);
        }
        let key = kind == videoFrameTypeIDR;
        if key {
            self.last_key_ms = Some(ts);
        }
        Ok(Some(EncodedFrame {
            data: self.collect_nals(),
            key,
            timestamp_ms: ts,
            index,
        }))
    }

    /// The access unit's bytes: every layer's NAL units in order.
    fn collect_nals(&self) -> Vec<u8> {
        let info = &*self.info;
        let mut out = Vec::with_capacity(info.iFrameSizeInBytes.max(0) as usize);
        for layer in &info.sLayerInfo[..info.iLayerNum.clamp(0, 128) as usize] {
            let nals = layer.iNalCount.max(0) as usize;
            if nals == 0 || layer.pBsBuf.is_null() || layer.pNalLengthInByte.is_null() {
                continue;
            }
            // SAFETY: openh264 gives `iNalCount` lengths, and a buffer holding their sum.
            let lengths = unsafe { std::slice::from_raw_parts(layer.pNalLengthInByte, nals) };
            let total: usize = lengths.iter().map(|&l| l.max(0) as usize).sum();
            let bytes = unsafe { std::slice::from_raw_parts(layer.pBsBuf, total) };
            out.extend_from_slice(bytes);
        }
        out
    }
}

impl Drop for Encoder {
    fn drop(&mut self) {
        // SAFETY: the encoder is live until here and never used after.
        unsafe {
            (self.vtbl.uninitialize)(self.ptr);
            self.api.WelsDestroySVCEncoder(self.ptr);
        }
    }
}

fn check(rc: c_int, what: &str) -> Result<(), VideoError> {
    if rc == 0 {
        Ok(())
    } else {
        Err(VideoError::Codec(format!("openh264 {what} failed ({rc})")))
    }
}
