//! `photon_reconstructor`: the client reconstructor of the photon technique (CloudLight §4.3), one
//! per client.
//!
//! It keeps the newest batch per (light, slot) ([`PhotonSet`]), and at `fps` renders its
//! frame on wgpu: G-buffer, its own direct light with shadow maps, the photons splatted into
//! a low-resolution buffer and bilaterally upsampled (`Raster::photon_frame`). Per frame it
//! records the frame time, the age of the indirect light shown (scene time now minus the
//! time its photon set is complete and current for) and the photons stored; it can write
//! its frames as PNGs under the run's output folder, and logs every frame (scene time, frame
//! time, age, photons) to `frames.csv` there. With `render = false` it only keeps the set
//! and measures ages (for client-count experiments without a GPU per client).

use std::io::Write;
use std::path::PathBuf;
use std::sync::{Arc, OnceLock};
use std::time::{Duration, Instant};

use cloudlight_render::photon::{Inserted, Photon, PhotonSet};
use cloudlight_render::raster::{Raster, ShadowSettings, SplatSettings};
use cloudlight_runtime::clock::now_unix_ns;
use cloudlight_runtime::{Input, NextTick, Stage, StageCtx, StageKind, StageSetup};
use cloudlight_scenes::{LightState, Scene, WorldTriangle};
use hdrhistogram::Histogram;
use serde::Deserialize;

use crate::photon_batcher::{PHOTON_EDGE, TECHNIQUE};
use crate::wire::PhotonMsg;

/// Parameters of `photon_reconstructor`.
#[derive(Clone, Debug, Deserialize)]
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
    /// Accumulation buffer downsampling per axis (1, 2 or 4).
    #[serde(default = "default_downsample")]
    pub downsample: u32,
    /// Camera path of the scene to follow; default: the replica index, wrapping.
    pub camera: Option<usize>,
    /// Render frames (false: keep photons and measure ages only).
    #[serde(default = "yes")]
    pub render: bool,
    /// Write frames as PNGs to `<out>/<instance>/`.
    #[serde(default)]
    pub write_frames: bool,
    /// Write every n-th frame.
    #[serde(default = "one")]
    pub write_every: u64,
    /// Emissive surfaces become n² × 2 point emitters per triangle for direct light.
    #[serde(default = "default_light_samples")]
    pub light_samples: u32,
    /// Shadow-map size, texels.
    #[serde(default = "default_shadow_size")]
    pub shadow_size: u32,
}

fn default_width() -> u32 {
    320
}
fn default_height() -> u32 {
    240
}
fn default_fps() -> f64 {
    10.0
}
fn default_downsample() -> u32 {
    2
}
fn yes() -> bool {
    true
}
fn one() -> u64 {
    1
}
fn default_light_samples() -> u32 {
    2
}
fn default_shadow_size() -> u32 {
    512
}

/// One raster device per process, shared by every client in it.
fn shared_raster() -> anyhow::Result<Arc<Raster>> {
    static RASTER: OnceLock<Result<Arc<Raster>, String>> = OnceLock::new();
    RASTER
        .get_or_init(|| Raster::new().map(Arc::new).map_err(|e| e.to_string()))
        .clone()
        .map_err(|e| anyhow::anyhow!(e))
}

/// The photon client stage.
pub struct PhotonReconstructor {
    params: ClientParams,
    scene: Arc<Scene>,
    camera: usize,
    raster: Option<Arc<Raster>>,
    set: PhotonSet,
    photons: Arc<Vec<Photon>>,
    photons_version: u64,
    static_triangles: Option<Arc<Vec<WorldTriangle>>>,
    frames_dir: Option<PathBuf>,
    /// `frames.csv`: one line per frame (or age sample when not rendering).
    log: Option<std::io::BufWriter<std::fs::File>>,
    exposure: Option<f32>,
    frames: u64,
    frames_written: u64,
    frame_us: Histogram<u64>,
    age_us: Histogram<u64>,
    age_max_s: f64,
    started: Instant,
    first_indirect_s: Option<f64>,
    bytes_received: u64,
    next_due: Option<Instant>,
}

fn histogram() -> Histogram<u64> {
    Histogram::new(3).expect("3 significant digits is valid")
}

fn ms(h: &Histogram<u64>, q: f64) -> f64 {
    if h.is_empty() {
        0.0
    } else {
        h.value_at_quantile(q) as f64 / 1000.0
    }
}

impl PhotonReconstructor {
    fn new(setup: &StageSetup) -> anyhow::Result<Self> {
        let params: ClientParams = setup.params()?;
        if params.width == 0 || params.height == 0 || params.width > 8192 || params.height > 8192 {
            anyhow::bail!("width and height must be in 1..=8192");
        }
        if !(params.fps > 0.0 && params.fps.is_finite()) {
            anyhow::bail!("fps must be a positive number");
        }
        if ![1, 2, 4].contains(&params.downsample) {
            anyhow::bail!("downsample must be 1, 2 or 4");
        }
        let scene = Arc::new(cloudlight_scenes::load(&setup.scene)?);
        let cameras = scene.cameras.len().max(1);
        let camera = params.camera.unwrap_or(setup.info.replica) % cameras;
        let raster = if params.render {
            Some(shared_raster()?)
        } else {
            None
        };
        // Everything this client writes goes to OUT/<instance>/.
        let dir = match &setup.out_dir {
            Some(out) => {
                let name = setup.info.name.replace(['[', ']'], "-");
                let dir = out.join(name.trim_end_matches('-'));
                std::fs::create_dir_all(&dir).map_err(|e| {
                    anyhow::anyhow!("cannot create the client's folder {}: {e}", dir.display())
                })?;
                Some(dir)
            }
            None => None,
        };
        let log = match &dir {
            Some(d) => {
                let path = d.join("frames.csv");
                let file = std::fs::File::create(&path)
                    .map_err(|e| anyhow::anyhow!("cannot create {}: {e}", path.display()))?;
                let mut f = std::io::BufWriter::new(file);
                writeln!(f, "frame,scene_time_s,frame_ms,age_ms,photons_stored")?;
                Some(f)
            }
            None => None,
        };
        let frames_dir = dir.filter(|_| params.write_frames && params.render);
        Ok(PhotonReconstructor {
            params,
            scene,
            camera,
            raster,
            set: PhotonSet::new(),
            photons: Arc::new(Vec::new()),
            photons_version: 0,
            static_triangles: None,
            frames_dir,
            log,
            exposure: None,
            frames: 0,
            frames_written: 0,
            frame_us: histogram(),
            age_us: histogram(),
            age_max_s: 0.0,
            started: Instant::now(),
            first_indirect_s: None,
            bytes_received: 0,
            next_due: None,
        })
    }

    fn report(&self) -> serde_json::Value {
        let stats = self.set.stats();
        let age = if self.age_us.is_empty() {
            "no indirect light shown yet".to_string()
        } else {
            format!(
                "age of indirect light p50 {:.0} ms, max {:.0} ms",
                ms(&self.age_us, 0.5),
                self.age_max_s * 1000.0
            )
        };
        let frames = if self.raster.is_some() {
            format!(
                "{} frames (p50 {:.0} ms), ",
                self.frames,
                ms(&self.frame_us, 0.5)
            )
        } else {
            String::new()
        };
        let summary = format!(
            "{frames}{age}, {} photons in {} batches, {} rejected",
            self.set.photon_count(),
            self.set.batch_count(),
            stats.rejected
        );
        serde_json::json!({
            "summary": summary,
            "frames": self.frames,
            "frames_written": self.frames_written,
            "frames_dir": self.frames_dir.as_ref().map(|d| d.display().to_string()),
            "frame_ms_p50": ms(&self.frame_us, 0.5),
            "frame_ms_p99": ms(&self.frame_us, 0.99),
            "age_ms_p50": ms(&self.age_us, 0.5),
            "age_ms_p99": ms(&self.age_us, 0.99),
            "age_ms_max": self.age_max_s * 1000.0,
            "indirect_shown": self.set.valid_as_of().is_some(),
            "first_indirect_s": self.first_indirect_s,
            "photons_stored": self.set.photon_count(),
            "batches_held": self.set.batch_count(),
            "stored_bytes": self.set.packed_bytes(),
            "bytes_received": self.bytes_received,
            "batches_accepted": stats.accepted,
            "batches_replaced": stats.replaced,
            "batches_stale": stats.stale,
            "batches_rejected": stats.rejected,
            "manifests": stats.manifests,
        })
    }

    /// Samples the age of the indirect light at scene time `t`.
    fn record_age(&mut self, t: f64) {
        if let Some(valid) = self.set.valid_as_of() {
            let age = (t - valid).max(0.0);
            self.age_max_s = self.age_max_s.max(age);
            let _ = self.age_us.record(((age * 1e6) as u64).max(1));
            if self.first_indirect_s.is_none() {
                self.first_indirect_s = Some(self.started.elapsed().as_secs_f64());
            }
        }
    }

    /// Renders (and maybe writes) the frame for scene time `t`; returns its time in ms.
    async fn render(&mut self, t: f64) -> anyhow::Result<Option<f64>> {
        let Some(raster) = self.raster.clone() else {
            return Ok(None);
        };
        if self.photons_version != self.set.version() {
            self.photons = Arc::new(self.set.photons().copied().collect());
            self.photons_version = self.set.version();
        }
        let scene = self.scene.clone();
        let triangles = match &self.static_triangles {
            Some(t) => t.clone(),
            None => {
                let s = scene.clone();
                let tris = Arc::new(tokio::task::spawn_blocking(move || s.triangles_at(t)).await?);
                if !scene.has_moving_geometry() {
                    self.static_triangles = Some(tris.clone());
                }
                tris
            }
        };
        let photons = self.photons.clone();
        let p = self.params.clone();
        let camera = self.camera;
        let start = Instant::now();
        let frame =
            tokio::task::spawn_blocking(move || {
                let mut lights: Vec<LightState> = scene.lights.iter().map(|l| l.at(t)).collect();
                lights.extend(scene.surface_light_samples(t, p.light_samples));
                let cam = scene.cameras.get(camera).map(|c| c.at(t)).unwrap_or(
                    cloudlight_scenes::Camera {
                        position: glam_fallback_eye(&scene),
                        target: glam_fallback_target(&scene),
                        up: cloudlight_scenes::glam::Vec3::Y,
                        fov_y_rad: 1.0,
                    },
                );
                raster.photon_frame(
                    &scene,
                    &triangles,
                    &lights,
                    &cam,
                    p.width,
                    p.height,
                    ShadowSettings {
                        size: p.shadow_size,
                        ..Default::default()
                    },
                    &photons,
                    SplatSettings {
                        downsample: p.downsample,
                        ..Default::default()
                    },
                )
            })
            .await??;
        let frame_time = start.elapsed();
        let _ = self.frame_us.record(frame_time.as_micros().max(1) as u64);
        self.frames += 1;
        if let Some(dir) = &self.frames_dir
            && (self.frames - 1).is_multiple_of(self.params.write_every.max(1))
        {
            let image = frame.combined();
            let stops = *self
                .exposure
                .get_or_insert_with(|| cloudlight_render::image_io::auto_exposure(&image));
            let path = dir.join(format!("frame_{:05}.png", self.frames_written));
            let (w, h) = (self.params.width, self.params.height);
            tokio::task::spawn_blocking(move || {
                cloudlight_render::image_io::write_png(&path, w, h, &image, stops)
            })
            .await??;
            self.frames_written += 1;
        }
        Ok(Some(frame_time.as_secs_f64() * 1000.0))
    }
}

/// A view of the whole scene for scenes without cameras.
fn glam_fallback_eye(scene: &Scene) -> cloudlight_scenes::glam::Vec3 {
    let (lo, hi) = scene.bounds_at(0.0);
    if !(lo.is_finite() && hi.is_finite()) {
        return cloudlight_scenes::glam::Vec3::new(0.0, 0.0, 3.0);
    }
    (lo + hi) * 0.5 + cloudlight_scenes::glam::Vec3::new(0.0, 0.0, (hi - lo).length())
}

fn glam_fallback_target(scene: &Scene) -> cloudlight_scenes::glam::Vec3 {
    let (lo, hi) = scene.bounds_at(0.0);
    if lo.is_finite() && hi.is_finite() {
        (lo + hi) * 0.5
    } else {
        cloudlight_scenes::glam::Vec3::ZERO
    }
}

#[async_trait::async_trait]
impl Stage for PhotonReconstructor {
    async fn on_start(&mut self, ctx: &mut StageCtx) -> anyhow::Result<()> {
        self.started = Instant::now();
        ctx.report(self.report());
        Ok(())
    }

    async fn on_input(&mut self, ctx: &mut StageCtx, input: Input) -> anyhow::Result<()> {
        let msg = input.get::<PhotonMsg>()?;
        match &msg.body {
            PhotonMsg::Batch(b) => {
                self.bytes_received += b.data.len() as u64;
                if let Inserted::Rejected(e) = self.set.insert(b) {
                    tracing::warn!(
                        stage = ctx.name(),
                        light = b.header.light,
                        slot = b.header.slot,
                        "photon batch rejected: {e}"
                    );
                }
            }
            PhotonMsg::Manifest(m) => self.set.apply_manifest(m.clone()),
        }
        Ok(())
    }

    async fn on_tick(&mut self, ctx: &mut StageCtx) -> anyhow::Result<NextTick> {
        if ctx.is_stopping() {
            return Ok(NextTick::Never);
        }
        let due = *self.next_due.get_or_insert_with(Instant::now);
        let t = ctx.clock().scene_time_at_s(now_unix_ns());
        self.record_age(t);
        let frame_ms = self.render(t).await?;
        if let Some(log) = &mut self.log {
            let age = self.set.valid_as_of().map_or(String::new(), |v| {
                format!("{:.3}", (t - v).max(0.0) * 1000.0)
            });
            let ms = frame_ms.map_or(String::new(), |m| format!("{m:.3}"));
            writeln!(
                log,
                "{},{t:.4},{ms},{age},{}",
                self.frames,
                self.set.photon_count()
            )?;
        }
        ctx.report(self.report());
        let interval = Duration::from_secs_f64(1.0 / self.params.fps);
        let now = Instant::now();
        let next = (due + interval).max(now);
        self.next_due = Some(next);
        Ok(NextTick::After(next - now))
    }

    async fn on_stop(&mut self, ctx: &mut StageCtx) -> anyhow::Result<()> {
        if let Some(log) = &mut self.log {
            log.flush()?;
        }
        ctx.report(self.report());
        Ok(())
    }
}

/// Registers `photon_reconstructor`.
pub fn register(registry: &mut cloudlight_runtime::StageRegistry) {
    registry.register(
        StageKind::new(
            "photon_reconstructor",
            TECHNIQUE,
            "keeps the newest photon batch per (light, slot), splats them over its own direct light, measures the age of indirect light",
            |s| Ok(Box::new(PhotonReconstructor::new(s)?)),
        )
        .input::<PhotonMsg>("in", PHOTON_EDGE)
        .params::<ClientParams>(),
    );
}
