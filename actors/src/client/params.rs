//! The parameters every client takes ([`ClientParams`]) and a client's `params` table split
//! between the shell's keys and the technique's ([`Params`]).

use cloudlight_runtime::{CheckParams, check_range};
use cloudlight_scenes::Scene;
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

/// Parameters every client takes; a technique adds its own keys beside them.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ClientParams {
    /// Frame width, pixels.
    #[serde(default = "default_width")]
    pub width: u32,
    /// Frame height, pixels.
    #[serde(default = "default_height")]
    pub height: u32,
    /// Frames per second.
    #[serde(default = "default_fps")]
    pub fps: f64,
    /// Camera path of the scene to follow; default: the replica index, wrapping.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera: Option<usize>,
    /// Render frames (false: keep the technique's state and measure ages only).
    #[serde(default = "yes")]
    pub render: bool,
    /// Write frames as PNGs to `<out>/<instance>/`.
    #[serde(default)]
    pub write_frames: bool,
    /// Write every n-th frame.
    #[serde(default = "one")]
    pub write_every: u64,
    /// Emissive triangles become n² point emitters each for direct light, each with its
    /// own cube of shadow maps ([`DEFAULT_LIGHT_SAMPLES`] by default).
    #[serde(default = "default_light_samples")]
    pub light_samples: u32,
    /// Shadow-map size, texels.
    #[serde(default = "default_shadow_size")]
    pub shadow_size: u32,
    /// Record what the client shows as an H.264 MP4 of this name (in the client's folder of
    /// the run's output, or as given when the run writes none).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub record: Option<String>,
    /// Exposure of the pictures shown, written and recorded, in stops (`2^stops` before
    /// ACES tone mapping); default: chosen from the first frame. A placement experiment
    /// sets one exposure for every cut and the reference, so that their pictures compare.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub exposure_stops: Option<f32>,
    /// Every this many seconds of scene time, the frame shown at that time is written as
    /// `sample_NNNNN.png` with a line in `samples.csv` (the client's folder of the run's
    /// output): a rendering client renders its first frame at or after `k × sample_every_s`
    /// for exactly that time, a client that shows pictures writes the picture it shows then.
    /// What a placement experiment compares with the reference.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sample_every_s: Option<f64>,
    /// While nothing it shows changes (camera, lights, geometry, the technique's light), the
    /// client shows the mean of its frames since, each sampling its pixels at another point
    /// within them: a still view converges to each pixel's mean over its area, as a camera
    /// sees it (`render/src/raster/accumulate.rs`). False: every frame through the pixels'
    /// centres.
    #[serde(default = "yes")]
    pub accumulate: bool,
}

/// The keys of [`ClientParams`] (a test keeps the two in step).
pub const CLIENT_KEYS: [&str; 13] = [
    "width",
    "height",
    "fps",
    "camera",
    "render",
    "write_frames",
    "write_every",
    "light_samples",
    "shadow_size",
    "record",
    "exposure_stops",
    "sample_every_s",
    "accumulate",
];

fn default_width() -> u32 {
    320
}
fn default_height() -> u32 {
    240
}
fn default_fps() -> f64 {
    10.0
}
fn yes() -> bool {
    true
}
fn one() -> u64 {
    1
}
/// The client's default `light_samples`: one emitter per emissive triangle. On a CPU
/// (lavapipe, 2 cores) each emitter's shadow lookup is the largest cost of a frame:
/// the Cornell box's frame at 640×360 is 24–28 ms with 1 (2 emitters) and 34–42 ms with
/// 2 (8 emitters), whose penumbrae are closer to the path tracer's (90th-percentile pixel
/// error 15% against 26%, `raster_direct_light_of_the_cornell_box_matches_the_path_tracer`).
pub const DEFAULT_LIGHT_SAMPLES: u32 = 1;

fn default_light_samples() -> u32 {
    DEFAULT_LIGHT_SAMPLES
}
fn default_shadow_size() -> u32 {
    512
}

impl Default for ClientParams {
    fn default() -> Self {
        ClientParams {
            width: default_width(),
            height: default_height(),
            fps: default_fps(),
            camera: None,
            render: true,
            write_frames: false,
            write_every: 1,
            light_samples: default_light_samples(),
            shadow_size: default_shadow_size(),
            record: None,
            exposure_stops: None,
            sample_every_s: None,
            accumulate: true,
        }
    }
}

/// Largest client frame side, pixels (a 8192² RGBA frame and its G-buffer fit any adapter
/// that runs here).
pub const MAX_FRAME_PX: u32 = 8192;

impl CheckParams for ClientParams {
    fn check(&self) -> Result<(), String> {
        let px = MAX_FRAME_PX as f64;
        check_range("width", self.width as f64, 1.0, px, "px")?;
        check_range("height", self.height as f64, 1.0, px, "px")?;
        // At least a frame an hour; at most what a display could show.
        check_range("fps", self.fps, 1.0 / 3600.0, 1000.0, "frames/s")?;
        check_range("write_every", self.write_every as f64, 1.0, 1e9, "frames")?;
        check_range(
            "light_samples",
            self.light_samples as f64,
            1.0,
            64.0,
            "per axis",
        )?;
        check_range("shadow_size", self.shadow_size as f64, 1.0, px, "texels")?;
        if let Some(name) = &self.record {
            if !name.to_ascii_lowercase().ends_with(".mp4") || name.contains('\0') {
                return Err(format!("`record` = {name:?} must name an .mp4 file"));
            }
            cloudlight_render::video::yuv::check_size(self.width, self.height)
                .map_err(|e| format!("`record`: {e}"))?;
        }
        if let Some(stops) = self.exposure_stops {
            check_range("exposure_stops", stops as f64, -64.0, 64.0, "stops")?;
        }
        if let Some(every) = self.sample_every_s {
            check_range("sample_every_s", every, 0.01, 3600.0, "s")?;
        }
        if let Some(c) = self.camera {
            check_range("camera", c as f64, 0.0, 1e6, "(index)")?;
        }
        Ok(())
    }
}

impl ClientParams {
    /// The camera path this client follows: `camera` when given (which the scene must have),
    /// else the replica index, wrapping.
    pub fn camera_index(&self, replica: usize, scene: &Scene) -> Result<usize, String> {
        let cameras = scene.cameras.len().max(1);
        match self.camera {
            Some(c) if c >= cameras => Err(format!(
                "`camera` = {c}, but the scene has {cameras} camera path{} (0 to {})",
                if cameras == 1 { "" } else { "s" },
                cameras - 1
            )),
            Some(c) => Ok(c),
            None => Ok(replica % cameras),
        }
    }
}

/// A client's `params`: the shell's keys and the technique's, from one table.
#[derive(Clone, Debug, PartialEq)]
pub struct Params<P> {
    /// The shell's.
    pub client: ClientParams,
    /// The technique's.
    pub technique: P,
}

impl<'de, P: DeserializeOwned> Deserialize<'de> for Params<P> {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        use serde::de::Error;
        let mut table = toml::Table::deserialize(d)?;
        let shell: toml::Table = CLIENT_KEYS
            .iter()
            .filter_map(|k| table.remove(*k).map(|v| (k.to_string(), v)))
            .collect();
        let client: ClientParams = toml::Value::Table(shell)
            .try_into()
            .map_err(D::Error::custom)?;
        let technique: P = toml::Value::Table(table)
            .try_into()
            .map_err(|e: toml::de::Error| {
                D::Error::custom(format!(
                    "{} (every client also takes: {})",
                    e.message(),
                    CLIENT_KEYS.join(", ")
                ))
            })?;
        Ok(Params { client, technique })
    }
}

impl<P: CheckParams> CheckParams for Params<P> {
    fn check(&self) -> Result<(), String> {
        self.client.check()?;
        self.technique.check()
    }
}

impl<P: Serialize> Params<P> {
    /// The `params` table of a topology (shell and technique keys side by side).
    pub fn to_table(&self) -> Result<toml::Table, toml::ser::Error> {
        let mut t = toml::Table::try_from(&self.client)?;
        t.extend(toml::Table::try_from(&self.technique)?);
        Ok(t)
    }
}
