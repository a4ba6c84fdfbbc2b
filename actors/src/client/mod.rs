//! The client shell every technique's reconstructor runs on.
//!
//! The shell ([`ClientShell`]) owns what all clients share: frame cadence (`fps`), the
//! camera path, the client's own direct light, the frame (a [`FrameRenderer`] that keeps
//! its GPU state), read-back and PNG frames, `frames.csv`, the age of the indirect light
//! shown and the stage report ([`ClientReport`]). A technique ([`ClientTechnique`]) supplies
//! only what is its own: what it does with a received message, the scene time its indirect
//! light is valid as of, the [`IndirectPass`] that draws it, and — when it needs vertex data
//! the topology's scene lacks — the scene the G-buffer draws
//! ([`ClientTechnique::drawn_scene`]: the light map's unwrapped scene with light-map UVs).
//!
//! Per frame: the scene time now; the age of the indirect light (scene time minus the time
//! the technique's light is valid as of); then, when rendering, the technique's update to
//! its pass (e.g. a new photon set), the frame's passes on a blocking thread, and the PNG
//! when this frame is written. With `render = false` a client only keeps its state and
//! measures ages (client-count experiments without a GPU per client).
//!
//! This module never opens sockets or looks at placement.

use std::io::Write;
use std::path::PathBuf;
use std::sync::{Arc, Mutex, OnceLock};
use std::time::Instant;

use cloudlight_render::raster::{
    FrameInputs, FrameRenderer, IndirectPass, Raster, RasterError, Readback, ShadowSettings,
};
use cloudlight_runtime::clock::now_unix_ns;
use cloudlight_runtime::{
    Cadence, CheckParams, EdgeSettings, Input, Latency, Message, NextTick, Port, Stage, StageCtx,
    StageKind, StageSetup, Stamped, lock, parse_params,
};

use crate::the_scene;
use crate::wire::FrameMsg;
use cloudlight_scenes::glam::Vec3;
use cloudlight_scenes::{Camera, LightState, Scene, View, WorldTriangle};
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

mod params;

pub use params::{CLIENT_KEYS, ClientParams, DEFAULT_LIGHT_SAMPLES, MAX_FRAME_PX, Params};

/// The technique's messages.
pub fn input_port<T: ClientTechnique>() -> Port<T::Msg> {
    Port::new("in")
}

/// The frames a rendering client shows (when anything consumes them: a `video_encoder` of
/// the full-frame baseline).
pub const FRAMES: Port<FrameMsg> = Port::new("frames");

/// Where the client looks, sent each frame when anything consumes it (an edge to a
/// server that guides its work toward what clients see, e.g. `photon_batcher.views`).
pub const VIEW: Port<View> = Port::new("view");

/// What a technique brings to the client shell.
pub trait ClientTechnique: Send + Sized + 'static {
    /// Messages on the client's `in` port.
    type Msg: Message;
    /// The technique's own parameters (`deny_unknown_fields`).
    type Params: DeserializeOwned + Serialize + CheckParams + Clone + Default + Send + 'static;
    /// The indirect pass.
    type Pass: IndirectPass + 'static;
    /// What changes the pass between frames (made on the async side, applied on the
    /// rendering thread).
    type Update: Send + 'static;
    /// The technique's part of the report (flattened into [`ClientReport`]).
    type Report: Serialize + DeserializeOwned + Default;

    /// The technique's state for a client of `scene`.
    fn new(setup: &StageSetup, params: &Self::Params, scene: &Arc<Scene>) -> anyhow::Result<Self>;

    /// Handles a message from the cloud.
    fn on_message(&mut self, stage: &str, msg: &Stamped<Self::Msg>);

    /// Scene time the indirect light held is valid as of (`None`: none yet).
    fn valid_as_of(&self) -> Option<f64>;

    /// Whether the light held stays valid until superseded (a converged map of a static
    /// scene): its age is 0 whatever [`ClientTechnique::valid_as_of`] says.
    fn is_current(&self) -> bool {
        false
    }

    /// A pass for frames on `raster`.
    fn new_pass(raster: &Raster, params: &Self::Params) -> Result<Self::Pass, RasterError>;

    /// What the pass needs before the next frame, if anything changed.
    fn update(&mut self) -> Option<Self::Update>;

    /// Applies an update to the pass (on the rendering thread).
    fn apply(
        pass: &mut Self::Pass,
        raster: &Raster,
        update: Self::Update,
    ) -> Result<(), RasterError>;

    /// The technique's report.
    fn report(&self) -> Self::Report;

    /// True for techniques whose messages are whole pictures (video): the shell renders
    /// nothing itself (no GPU is used) and shows [`ClientTechnique::picture`] each frame.
    const SHOWS_PICTURES: bool = false;

    /// The scene whose geometry the client draws, when the technique needs vertex data the
    /// topology's scene lacks (the light map's unwrapped scene, whose triangles carry
    /// light-map UVs for the G-buffer); `None`: the topology's scene. It must have the same
    /// surfaces, materials and motion.
    fn drawn_scene(&self) -> Option<Arc<Scene>> {
        None
    }

    /// The newest whole picture, for techniques that show pictures.
    fn picture(&self) -> Option<Arc<Picture>> {
        None
    }

    /// Checks the technique's parameters against the scene at validation (e.g. that the
    /// scene has a light map); the default accepts every scene.
    fn check_scene(params: &Self::Params, scene: &Scene) -> Result<(), String> {
        let _ = (params, scene);
        Ok(())
    }

    /// The technique's part of the one-line summary.
    fn summary(&self) -> String;

    /// Extra `frames.csv` columns (comma-separated header) and their values now.
    fn csv_columns() -> &'static str;

    /// The values of [`ClientTechnique::csv_columns`] now.
    fn csv_values(&self) -> String;
}

/// A whole picture a client shows: sRGB-encoded RGB8, row-major from the top.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Picture {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// 3 bytes per pixel.
    pub rgb: Vec<u8>,
}

/// What every client reports; the technique's fields sit beside the shell's.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ClientReport<R> {
    /// One line for people.
    pub summary: String,
    /// Frames rendered.
    pub frames: u64,
    /// Frames written as PNGs.
    pub frames_written: u64,
    /// Where frames and `frames.csv` go.
    pub frames_dir: Option<String>,
    /// The MP4 recording, when asked for.
    pub recording: Option<String>,
    /// Frames in it (known when the client stops).
    pub frames_recorded: u64,
    /// Frames that ended after the next one was due (the client cannot keep its `fps`).
    pub frames_late: u64,
    /// Frame time, p50, ms.
    pub frame_ms_p50: f64,
    /// Frame time, p99, ms.
    pub frame_ms_p99: f64,
    /// Age of the indirect light shown, p50, ms.
    pub age_ms_p50: f64,
    /// Age, p99, ms.
    pub age_ms_p99: f64,
    /// Largest age, ms.
    pub age_ms_max: f64,
    /// Whether any indirect light has been shown.
    pub indirect_shown: bool,
    /// Seconds from start to the first indirect light.
    pub first_indirect_s: Option<f64>,
    /// Times the shadow maps were rendered.
    pub shadow_renders: u64,
    /// Frames blended into a still view's mean (`accumulate`; a still view's first frame
    /// not counted).
    #[serde(default)]
    pub still_frames: u64,
    /// Samples written ([`ClientParams::sample_every_s`]).
    #[serde(default)]
    pub samples_written: u64,
    /// The exposure of its pictures, stops (set, or chosen from the first frame).
    #[serde(default)]
    pub exposure_stops: Option<f32>,
    /// The technique's figures.
    #[serde(flatten)]
    pub technique: R,
}

/// One raster device per process, shared by every client in it.
fn shared_raster() -> anyhow::Result<Arc<Raster>> {
    static RASTER: OnceLock<Result<Arc<Raster>, String>> = OnceLock::new();
    RASTER
        .get_or_init(|| {
            let r = Raster::new().map(Arc::new).map_err(|e| e.to_string());
            if let Ok(r) = &r {
                tracing::info!("raster on {}", r.describe());
            }
            r
        })
        .clone()
        .map_err(|e| anyhow::anyhow!(e))
}

/// The GPU side of a rendering client, used from blocking threads.
struct Gpu<P> {
    raster: Arc<Raster>,
    frame: FrameRenderer,
    pass: P,
}

/// Where a client writes: `OUT/<instance>/` with `frames.csv`.
struct Output {
    frames_dir: Option<PathBuf>,
    log: Option<std::io::BufWriter<std::fs::File>>,
    /// Where the MP4 recording goes, when asked for.
    record: Option<PathBuf>,
    /// The client's folder and its `samples.csv`, when it writes samples.
    samples: Option<(PathBuf, std::io::BufWriter<std::fs::File>)>,
}

impl Output {
    fn open<T: ClientTechnique>(setup: &StageSetup, params: &ClientParams) -> anyhow::Result<Self> {
        let Some(out) = &setup.out_dir else {
            if params.sample_every_s.is_some() {
                tracing::warn!(
                    stage = %setup.info.name,
                    "`sample_every_s` is set but the run writes no output folder: no samples"
                );
            }
            return Ok(Output {
                frames_dir: None,
                log: None,
                record: params.record.as_ref().map(PathBuf::from),
                samples: None,
            });
        };
        let name = setup.info.name.replace(['[', ']'], "-");
        let dir = out.join(name.trim_end_matches('-'));
        std::fs::create_dir_all(&dir).map_err(|e| {
            anyhow::anyhow!("cannot create the client's folder {}: {e}", dir.display())
        })?;
        let path = dir.join("frames.csv");
        let file = std::fs::File::create(&path)
            .map_err(|e| anyhow::anyhow!("cannot create {}: {e}", path.display()))?;
        let mut log = std::io::BufWriter::new(file);
        writeln!(
            log,
            "frame,scene_time_s,frame_ms,age_ms,{}",
            T::csv_columns()
        )?;
        let shows = params.render || T::SHOWS_PICTURES;
        let samples = match params.sample_every_s {
            Some(_) if shows => {
                let path = dir.join("samples.csv");
                let file = std::fs::File::create(&path)
                    .map_err(|e| anyhow::anyhow!("cannot create {}: {e}", path.display()))?;
                let mut log = std::io::BufWriter::new(file);
                writeln!(log, "sample,scene_time_s,shown_at_s,age_ms,file")?;
                Some((dir.clone(), log))
            }
            _ => None,
        };
        Ok(Output {
            frames_dir: (params.write_frames && shows).then_some(dir.clone()),
            log: Some(log),
            record: params.record.as_ref().map(|name| dir.join(name)),
            samples,
        })
    }
}

/// QP of MP4 recordings: near-transparent for frames people look at.
const RECORD_QP: u8 = 20;

/// Figures the shell keeps.
struct Figures {
    frames: u64,
    frames_written: u64,
    frames_recorded: u64,
    frame: Latency,
    age: Latency,
    age_max_s: f64,
    started: Instant,
    first_indirect_s: Option<f64>,
    shadow_renders: u64,
    still_frames: u64,
    /// Index of the next sample due ([`ClientParams::sample_every_s`]).
    next_sample: u64,
    samples_written: u64,
}

/// A client stage: the shell around technique `T`.
pub struct ClientShell<T: ClientTechnique> {
    params: ClientParams,
    technique: T,
    scene: Arc<Scene>,
    /// What the G-buffer draws: the technique's scene, else `scene`.
    drawn: Arc<Scene>,
    camera: usize,
    gpu: Option<Arc<Mutex<Gpu<T::Pass>>>>,
    /// Static geometry is uploaded once; moving geometry every frame.
    geometry_uploaded: bool,
    /// Surface emitters as point lights, kept while the geometry does not move.
    surface_lights: Option<Arc<Vec<LightState>>>,
    /// The view of scenes without camera paths.
    overview: Camera,
    output: Output,
    exposure: Option<f32>,
    /// The MP4 recording, made at the first frame shown.
    recorder: Option<cloudlight_render::video::Recorder>,
    /// What the last frame showed (camera and lights), to tell a still view.
    last_view: Option<(Camera, Vec<LightState>)>,
    /// The still view's frame number (`ClientParams::accumulate`), while it stands still.
    still: Option<u32>,
    figures: Figures,
    cadence: Cadence,
}

impl<T: ClientTechnique> ClientShell<T> {
    fn new(setup: &StageSetup) -> anyhow::Result<Self> {
        let params: Params<T::Params> = setup.params()?;
        params
            .check()
            .map_err(|e| anyhow::anyhow!("{}: params: {e}", setup.info.name))?;
        let scene = Arc::new(cloudlight_scenes::load(&setup.scene)?);
        let camera = params
            .client
            .camera_index(setup.info.replica, &scene)
            .map_err(anyhow::Error::msg)?;
        let technique = T::new(setup, &params.technique, &scene)?;
        let gpu = if params.client.render && !T::SHOWS_PICTURES {
            let raster = shared_raster()?;
            let frame = FrameRenderer::new(
                &raster,
                params.client.width,
                params.client.height,
                ShadowSettings {
                    size: params.client.shadow_size,
                    ..Default::default()
                },
            )?;
            let pass = T::new_pass(&raster, &params.technique)?;
            Some(Arc::new(Mutex::new(Gpu {
                raster,
                frame,
                pass,
            })))
        } else {
            None
        };
        let output = Output::open::<T>(setup, &params.client)?;
        let overview = scene.overview_camera();
        let drawn = technique.drawn_scene().unwrap_or_else(|| scene.clone());
        let cadence = Cadence::hz(params.client.fps);
        let exposure = params.client.exposure_stops;
        Ok(ClientShell {
            params: params.client,
            technique,
            scene,
            drawn,
            camera,
            gpu,
            geometry_uploaded: false,
            surface_lights: None,
            overview,
            output,
            exposure,
            recorder: None,
            last_view: None,
            still: None,
            figures: Figures {
                frames: 0,
                frames_written: 0,
                frames_recorded: 0,
                frame: Latency::new(),
                age: Latency::new(),
                age_max_s: 0.0,
                started: Instant::now(),
                first_indirect_s: None,
                shadow_renders: 0,
                still_frames: 0,
                next_sample: 1,
                samples_written: 0,
            },
            cadence,
        })
    }

    fn report(&self) -> ClientReport<T::Report> {
        let f = &self.figures;
        let age = if f.age.is_empty() {
            "no indirect light shown yet".to_string()
        } else {
            format!(
                "age of indirect light p50 {:.0} ms, max {:.0} ms",
                f.age.p50_ms(),
                f.age_max_s * 1000.0
            )
        };
        let frames = if self.gpu.is_some() || T::SHOWS_PICTURES {
            format!("{} frames (p50 {:.0} ms), ", f.frames, f.frame.p50_ms())
        } else {
            String::new()
        };
        ClientReport {
            summary: format!("{frames}{age}, {}", self.technique.summary()),
            frames: f.frames,
            frames_written: f.frames_written,
            frames_dir: self
                .output
                .frames_dir
                .as_ref()
                .map(|d| d.display().to_string()),
            recording: self.output.record.as_ref().map(|p| p.display().to_string()),
            frames_recorded: f.frames_recorded,
            frames_late: self.cadence.overruns(),
            frame_ms_p50: f.frame.p50_ms(),
            frame_ms_p99: f.frame.p99_ms(),
            age_ms_p50: f.age.p50_ms(),
            age_ms_p99: f.age.p99_ms(),
            age_ms_max: f.age_max_s * 1000.0,
            indirect_shown: self.technique.valid_as_of().is_some(),
            first_indirect_s: f.first_indirect_s,
            shadow_renders: f.shadow_renders,
            still_frames: f.still_frames,
            samples_written: f.samples_written,
            exposure_stops: self.exposure,
            technique: self.technique.report(),
        }
    }

    fn publish(&self, ctx: &StageCtx) {
        ctx.report(serde_json::to_value(self.report()).unwrap_or_default());
    }

    /// The scene time the indirect light shown at `t` is valid as of: `t` itself while it
    /// stays valid until superseded ([`ClientTechnique::is_current`]).
    fn light_time(&self, t: f64) -> Option<f64> {
        let valid = self.technique.valid_as_of()?;
        Some(if self.technique.is_current() {
            t
        } else {
            valid
        })
    }

    /// Samples the age of the indirect light at scene time `t`.
    fn record_age(&mut self, t: f64) {
        if let Some(valid) = self.light_time(t) {
            let f = &mut self.figures;
            let age = (t - valid).max(0.0);
            f.age_max_s = f.age_max_s.max(age);
            f.age.record_s(age);
            if f.first_indirect_s.is_none() {
                f.first_indirect_s = Some(f.started.elapsed().as_secs_f64());
            }
        }
    }

    /// The camera at `t` (a view of the whole scene when it has no camera paths).
    fn camera_at(&self, t: f64) -> Camera {
        match self.scene.cameras.get(self.camera) {
            Some(c) => c.at(t),
            None => self.overview,
        }
    }

    /// The client's own lights at `t`: punctual lights and the surface emitters' samples.
    async fn lights_at(&mut self, t: f64) -> anyhow::Result<Vec<LightState>> {
        let samples = match &self.surface_lights {
            Some(s) => s.clone(),
            None => {
                let (scene, n) = (self.scene.clone(), self.params.light_samples);
                let s = Arc::new(
                    tokio::task::spawn_blocking(move || scene.surface_light_samples(t, n)).await?,
                );
                if !self.scene.has_moving_geometry() {
                    self.surface_lights = Some(s.clone());
                }
                s
            }
        };
        Ok(self.scene.direct_lights(t, &samples))
    }

    /// Renders (and maybe writes) the frame for scene time `t`; returns its time in ms, and
    /// the composed frame when `keep` (to send it on).
    async fn render(
        &mut self,
        t: f64,
        keep: bool,
    ) -> anyhow::Result<Option<(f64, Option<Arc<Vec<Vec3>>>)>> {
        let Some(gpu) = self.gpu.clone() else {
            return Ok(None);
        };
        let geometry: Option<Arc<Vec<WorldTriangle>>> =
            if !self.geometry_uploaded || self.drawn.has_moving_geometry() {
                let s = self.drawn.clone();
                self.geometry_uploaded = true;
                Some(Arc::new(
                    tokio::task::spawn_blocking(move || s.triangles_at(t)).await?,
                ))
            } else {
                None
            };
        let update = self.technique.update();
        let lights = self.lights_at(t).await?;
        let camera = self.camera_at(t);
        // A still view: nothing the frame shows changed since the last one (the first such
        // frame starts the mean again, through the pixels' centres).
        let view = (camera, lights.clone());
        let unchanged =
            update.is_none() && geometry.is_none() && self.last_view.as_ref() == Some(&view);
        self.still = (self.params.accumulate && unchanged)
            .then(|| self.still.map_or(0, |k| k.saturating_add(1)));
        self.last_view = Some(view);
        if self.still.is_some_and(|k| k > 0) {
            self.figures.still_frames += 1;
        }
        let still = self.still;
        let write = self.output.frames_dir.is_some()
            && self.figures.frames.is_multiple_of(self.params.write_every);
        let scene = self.drawn.clone();
        let start = Instant::now();
        let (images, shadow_renders) = tokio::task::spawn_blocking(move || {
            let mut g = lock(&gpu);
            let Gpu {
                raster,
                frame,
                pass,
            } = &mut *g;
            if let Some(u) = update {
                T::apply(pass, raster, u)?;
            }
            if let Some(tris) = geometry {
                frame.set_geometry(raster, &scene, &tris)?;
            }
            let inputs = FrameInputs {
                camera,
                lights: &lights,
                still,
            };
            let readback = if write || keep {
                Readback::Composed
            } else {
                Readback::Nothing
            };
            let images = frame.render(raster, &inputs, pass, readback, false)?;
            Ok::<_, RasterError>((images, frame.shadow_renders()))
        })
        .await??;
        let frame_time = start.elapsed();
        self.figures.shadow_renders = shadow_renders;
        self.figures.frame.record(frame_time);
        self.figures.frames += 1;
        let composed = images.composed.map(Arc::new);
        if let Some(image) = &composed {
            self.exposure
                .get_or_insert_with(|| cloudlight_render::image_io::auto_exposure(image));
        }
        if let (Some(dir), Some(image), true) = (&self.output.frames_dir, &composed, write) {
            let stops = self.exposure.unwrap_or(0.0);
            let path = dir.join(format!("frame_{:05}.png", self.figures.frames_written));
            let (w, h, image) = (self.params.width, self.params.height, image.clone());
            tokio::task::spawn_blocking(move || {
                cloudlight_render::image_io::write_png(&path, w, h, &image, stops)
            })
            .await??;
            self.figures.frames_written += 1;
        }
        Ok(Some((
            frame_time.as_secs_f64() * 1000.0,
            composed.filter(|_| keep),
        )))
    }

    /// Shows the technique's newest picture (techniques that show pictures): counts it as a
    /// frame and writes it when asked; returns the time this took in ms.
    async fn show_picture(&mut self) -> anyhow::Result<Option<f64>> {
        let Some(picture) = self.technique.picture() else {
            return Ok(None);
        };
        let start = Instant::now();
        let write = self.output.frames_dir.is_some()
            && self.figures.frames.is_multiple_of(self.params.write_every);
        if let (Some(dir), true) = (&self.output.frames_dir, write) {
            let path = dir.join(format!("frame_{:05}.png", self.figures.frames_written));
            tokio::task::spawn_blocking(move || {
                image::RgbImage::from_raw(picture.width, picture.height, picture.rgb.clone())
                    .ok_or_else(|| anyhow::anyhow!("a picture of the wrong size"))?
                    .save(&path)
                    .map_err(|e| anyhow::anyhow!("cannot write {}: {e}", path.display()))
            })
            .await??;
            self.figures.frames_written += 1;
        }
        self.figures.frames += 1;
        let shown = start.elapsed();
        self.figures.frame.record(shown);
        Ok(Some(shown.as_secs_f64() * 1000.0))
    }

    /// Adds the picture shown at `t` to the MP4 recording (made at the first one).
    fn record(&mut self, picture: &Picture, t: f64) -> anyhow::Result<()> {
        use cloudlight_render::video::{EncoderSettings, RateControl, Recorder, Yuv420};
        let Some(path) = &self.output.record else {
            return Ok(());
        };
        if self.recorder.is_none() {
            let settings = EncoderSettings {
                width: picture.width,
                height: picture.height,
                fps: self.params.fps.clamp(0.1, 240.0) as f32,
                rate: RateControl::FixedQp(RECORD_QP),
                keyframe_s: 2.0,
                ..Default::default()
            };
            self.recorder = Some(Recorder::create(path, settings)?);
        }
        let yuv = Yuv420::from_rgb8(picture.width, picture.height, &picture.rgb)?;
        self.recorder.as_mut().expect("made above").push(&yuv, t)?;
        Ok(())
    }

    /// The sample due at `t`, if any: the newest multiple `k × sample_every_s` at or before
    /// `t` not sampled yet, as (k, its scene time).
    fn due_sample(&mut self, t: f64) -> Option<(u64, f64)> {
        let every = self.params.sample_every_s?;
        self.output.samples.as_ref()?;
        let k = (t / every + 1e-9).floor().max(0.0) as u64;
        if k < self.figures.next_sample {
            return None;
        }
        self.figures.next_sample = k + 1;
        Some((k, k as f64 * every))
    }

    /// Writes `picture` as sample `k` of scene time `ts`, shown at `t`.
    async fn write_sample(
        &mut self,
        k: u64,
        ts: f64,
        t: f64,
        picture: Picture,
    ) -> anyhow::Result<()> {
        let age = self.light_time(ts).map_or(String::new(), |v| {
            format!("{:.3}", (ts - v).max(0.0) * 1000.0)
        });
        let Some((dir, _)) = &self.output.samples else {
            return Ok(());
        };
        let name = format!("sample_{k:05}.png");
        let path = dir.join(&name);
        tokio::task::spawn_blocking(move || {
            image::RgbImage::from_raw(picture.width, picture.height, picture.rgb)
                .ok_or_else(|| anyhow::anyhow!("a picture of the wrong size"))?
                .save(&path)
                .map_err(|e| anyhow::anyhow!("cannot write {}: {e}", path.display()))
        })
        .await??;
        let Some((_, log)) = &mut self.output.samples else {
            return Ok(());
        };
        writeln!(log, "{k},{ts:.4},{t:.4},{age},{name}")?;
        self.figures.samples_written += 1;
        Ok(())
    }

    fn log_frame(&mut self, t: f64, frame_ms: Option<f64>) -> anyhow::Result<()> {
        let age = self.light_time(t).map_or(String::new(), |v| {
            format!("{:.3}", (t - v).max(0.0) * 1000.0)
        });
        let Some(log) = &mut self.output.log else {
            return Ok(());
        };
        let ms = frame_ms.map_or(String::new(), |m| format!("{m:.3}"));
        writeln!(
            log,
            "{},{t:.4},{ms},{age},{}",
            self.figures.frames,
            self.technique.csv_values()
        )?;
        Ok(())
    }
}

#[async_trait::async_trait]
impl<T: ClientTechnique> Stage for ClientShell<T> {
    async fn on_start(&mut self, ctx: &mut StageCtx) -> anyhow::Result<()> {
        self.figures.started = Instant::now();
        self.publish(ctx);
        Ok(())
    }

    async fn on_input(&mut self, ctx: &mut StageCtx, input: Input) -> anyhow::Result<()> {
        let msg = input.on(input_port::<T>())?;
        self.technique.on_message(ctx.name(), &msg);
        Ok(())
    }

    async fn on_tick(&mut self, ctx: &mut StageCtx) -> anyhow::Result<NextTick> {
        if ctx.is_stopping() {
            return Ok(NextTick::Never);
        }
        self.cadence.begin();
        let t = ctx.clock().scene_time_at_s(now_unix_ns());
        self.record_age(t);
        if ctx.has_consumers(VIEW) {
            let view = View {
                camera: self.camera_at(t),
                aspect: self.params.width as f32 / self.params.height.max(1) as f32,
            };
            ctx.send(VIEW, t, view).await?;
        }
        let recording = self.output.record.is_some();
        let sample = self.due_sample(t);
        let frame_ms = if T::SHOWS_PICTURES {
            let ms = self.show_picture().await?;
            if let (true, Some(picture)) = (recording && ms.is_some(), self.technique.picture()) {
                self.record(&picture, t)?;
            }
            if let (Some((k, ts)), Some(picture)) = (sample, self.technique.picture()) {
                self.write_sample(k, ts, t, Picture::clone(&picture))
                    .await?;
            }
            ms
        } else {
            let send = ctx.has_consumers(FRAMES);
            // A sample's frame is rendered for the sample's time (at most a frame earlier).
            let t = sample.map_or(t, |(_, ts)| ts);
            match self
                .render(t, send || recording || sample.is_some())
                .await?
            {
                Some((ms, Some(image))) => {
                    let stops = self.exposure.unwrap_or(0.0);
                    let rgb = tokio::task::spawn_blocking(move || {
                        cloudlight_render::metrics::tonemap(&image, stops)
                    })
                    .await?;
                    let picture = Picture {
                        width: self.params.width,
                        height: self.params.height,
                        rgb,
                    };
                    if recording {
                        self.record(&picture, t)?;
                    }
                    if let Some((k, ts)) = sample {
                        self.write_sample(k, ts, t, picture.clone()).await?;
                    }
                    if send {
                        let Picture { width, height, rgb } = picture;
                        let light_s = self.light_time(t);
                        let frame = FrameMsg::Sdr {
                            width,
                            height,
                            rgb,
                            light_s,
                        };
                        ctx.send(FRAMES, t, frame).await?;
                    }
                    Some(ms)
                }
                other => other.map(|(ms, _)| ms),
            }
        };
        self.log_frame(t, frame_ms)?;
        let next = self.cadence.end_tick();
        self.publish(ctx);
        Ok(next)
    }

    async fn on_stop(&mut self, ctx: &mut StageCtx) -> anyhow::Result<()> {
        if let Some(log) = &mut self.output.log {
            log.flush()?;
        }
        if let Some((_, log)) = &mut self.output.samples {
            log.flush()?;
        }
        if let (Some(recorder), Some(path)) = (self.recorder.take(), &self.output.record) {
            let frames = recorder.finish()?;
            self.figures.frames_recorded = frames;
            tracing::info!(stage = ctx.name(), frames, path = %path.display(), "recording written");
        }
        self.publish(ctx);
        Ok(())
    }
}

/// Registers a client kind `name` of technique `T` (stage technique `technique`), with its
/// `in` port's default edge settings.
pub fn register<T: ClientTechnique>(
    registry: &mut cloudlight_runtime::StageRegistry,
    name: &str,
    technique: &str,
    summary: &str,
    edge: EdgeSettings,
) {
    registry.register(
        StageKind::new(name, technique, summary, |s| {
            Ok(Box::new(ClientShell::<T>::new(s)?))
        })
        .input(input_port::<T>(), edge)
        .output(FRAMES)
        .output(VIEW)
        .checked_params::<Params<T::Params>>()
        .scene_check(|table, scene| {
            let params: Params<T::Params> = parse_params(table)?;
            let scene = the_scene(scene)?;
            params.client.camera_index(0, scene)?;
            T::check_scene(&params.technique, scene)
        }),
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn client_keys_are_the_fields_of_client_params() {
        let table = toml::Table::try_from(ClientParams {
            camera: Some(1),
            record: Some("c.mp4".into()),
            exposure_stops: Some(1.5),
            sample_every_s: Some(1.0),
            ..Default::default()
        })
        .unwrap();
        let mut keys: Vec<&str> = table.keys().map(String::as_str).collect();
        keys.sort_unstable();
        let mut expected = CLIENT_KEYS.to_vec();
        expected.sort_unstable();
        assert_eq!(keys, expected);
    }

    #[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
    #[serde(deny_unknown_fields)]
    struct Own {
        #[serde(default)]
        knob: u32,
    }

    impl CheckParams for Own {
        fn check(&self) -> Result<(), String> {
            Ok(())
        }
    }

    #[test]
    fn params_split_between_shell_and_technique_and_unknown_keys_are_errors() {
        let p: Params<Own> = toml::from_str("width = 64\nknob = 3\nfps = 2.0").unwrap();
        assert_eq!(p.client.width, 64);
        assert_eq!(p.client.fps, 2.0);
        assert_eq!(p.technique, Own { knob: 3 });
        let table = p.to_table().unwrap();
        assert_eq!(table["knob"].as_integer(), Some(3));
        let again: Params<Own> = toml::Value::Table(table).try_into().unwrap();
        assert_eq!(again, p);
        let e = toml::from_str::<Params<Own>>("widht = 64")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("widht") && e.contains("every client also takes"),
            "{e}"
        );
        // Values are checked by `CheckParams` (what the stage kind runs), not by parsing.
        let p: Params<Own> = toml::from_str("fps = 0.0").unwrap();
        let e = p.check().unwrap_err();
        assert!(e.contains("`fps` = 0 is out of range"), "{e}");
    }
}
