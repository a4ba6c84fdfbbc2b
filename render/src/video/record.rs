//! MP4 recordings of what a client shows: pictures encoded with [`Encoder`] and muxed with
//! the `mp4` crate (ISO BMFF, one AVC track, millisecond timescale).
//!
//! The track is made at the first key frame, from its SPS and PPS; samples are the access
//! units in AVCC form (each NAL unit prefixed by its 4-byte length, parameter sets left to
//! the track header). A sample's duration is known when the next picture comes, so one is
//! held back; [`Recorder::finish`] writes it with the nominal frame duration and the index.

use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use super::decoder::nal_payloads;
use super::{EncodedFrame, Encoder, EncoderSettings, VideoError, Yuv420};

/// Records pictures into an MP4 file.
pub struct Recorder {
    path: PathBuf,
    encoder: Encoder,
    writer: Option<mp4::Mp4Writer<BufWriter<File>>>,
    file: Option<BufWriter<File>>,
    pending: Option<EncodedFrame>,
    frame_ms: u32,
    samples: u64,
    first: Option<i64>,
}

fn mp4_error(path: &Path, e: impl std::fmt::Display) -> VideoError {
    VideoError::Codec(format!("recording {}: {e}", path.display()))
}

impl Recorder {
    /// Creates `path` for pictures of the encoder settings' size.
    pub fn create(path: &Path, settings: EncoderSettings) -> Result<Self, VideoError> {
        let file = File::create(path).map_err(|e| mp4_error(path, e))?;
        Ok(Recorder {
            path: path.to_path_buf(),
            frame_ms: (1000.0 / settings.fps).round().max(1.0) as u32,
            encoder: Encoder::new(settings)?,
            writer: None,
            file: Some(BufWriter::new(file)),
            pending: None,
            samples: 0,
            first: None,
        })
    }

    /// Samples written so far.
    pub fn samples(&self) -> u64 {
        self.samples
    }

    /// Encodes and records a picture shown at stream time `time_s`.
    pub fn push(&mut self, picture: &Yuv420, time_s: f64) -> Result<(), VideoError> {
        let Some(unit) = self.encoder.encode(picture, time_s)? else {
            return Ok(());
        };
        if self.writer.is_none() {
            if !unit.key {
                return Ok(()); // cannot happen: an encoder starts with a key frame
            }
            self.start_track(&unit)?;
        }
        if let Some(prev) = self.pending.take() {
            let duration = (unit.timestamp_ms - prev.timestamp_ms).clamp(1, u32::MAX as i64);
            self.write(&prev, duration as u32)?;
        }
        self.pending = Some(unit);
        Ok(())
    }

    fn start_track(&mut self, key: &EncodedFrame) -> Result<(), VideoError> {
        let nals = nal_payloads(&key.data);
        let find = |t: u8| nals.iter().find(|n| n[0] & 0x1f == t).map(|n| n.to_vec());
        let (Some(sps), Some(pps)) = (find(7), find(8)) else {
            return Err(mp4_error(&self.path, "the first key frame has no SPS/PPS"));
        };
        let file = self.file.take().expect("the file is taken once");
        let config = mp4::Mp4Config {
            major_brand: str::parse("isom").expect("a four-character code"),
            minor_version: 512,
            compatible_brands: ["isom", "iso2", "avc1", "mp41"]
                .iter()
                .map(|b| str::parse(b).expect("a four-character code"))
                .collect(),
            timescale: 1000,
        };
        let mut writer =
            mp4::Mp4Writer::write_start(file, &config).map_err(|e| mp4_error(&self.path, e))?;
        let s = self.encoder.settings();
        writer
            .add_track(&mp4::TrackConfig {
                track_type: mp4::TrackType::Video,
                timescale: 1000,
                language: "und".into(),
                media_conf: mp4::MediaConfig::AvcConfig(mp4::AvcConfig {
                    width: s.width as u16,
                    height: s.height as u16,
                    seq_param_set: sps,
                    pic_param_set: pps,
                }),
            })
            .map_err(|e| mp4_error(&self.path, e))?;
        self.writer = Some(writer);
        self.first = Some(key.timestamp_ms);
        Ok(())
    }

    fn write(&mut self, unit: &EncodedFrame, duration_ms: u32) -> Result<(), VideoError> {
        let mut avcc = Vec::with_capacity(unit.data.len());
        for nal in nal_payloads(&unit.data) {
            if matches!(nal[0] & 0x1f, 7 | 8) {
                continue; // parameter sets live in the track header
            }
            avcc.extend_from_slice(&(nal.len() as u32).to_be_bytes());
            avcc.extend_from_slice(nal);
        }
        let start = unit.timestamp_ms - self.first_ms();
        let sample = mp4::Mp4Sample {
            start_time: start.max(0) as u64,
            duration: duration_ms,
            rendering_offset: 0,
            is_sync: unit.key,
            bytes: bytes::Bytes::from(avcc),
        };
        let writer = self.writer.as_mut().expect("a track before samples");
        writer
            .write_sample(1, &sample)
            .map_err(|e| mp4_error(&self.path, e))?;
        self.samples += 1;
        Ok(())
    }

    fn first_ms(&self) -> i64 {
        self.first.unwrap_or(0)
    }

    /// Writes the held-back sample and the index; the file is complete after this.
    pub fn finish(mut self) -> Result<u64, VideoError> {
        if let Some(last) = self.pending.take() {
            self.write(&last, self.frame_ms)?;
        }
        if let Some(mut w) = self.writer.take() {
            w.write_end().map_err(|e| mp4_error(&self.path, e))?;
            use std::io::Write;
            w.into_writer()
                .flush()
                .map_err(|e| mp4_error(&self.path, e))?;
        }
        Ok(self.samples)
    }
}
