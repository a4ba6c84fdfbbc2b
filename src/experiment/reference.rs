//! The reference an experiment's clients are compared with: the path tracer's full image
//! (direct and indirect light) of client 0's view at a scene time, read from or stored in the
//! reference cache ([`crate::bench::reference_cache`]), and its picture at the experiment's
//! one exposure.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use anyhow::Context;
use cloudlight_render::metrics::{self, ImageErrors, PIXELS_PER_DEGREE};
use cloudlight_render::{BvhKind, RenderSettings, SceneBvh};
use cloudlight_scenes::glam::Vec3;
use cloudlight_scenes::{Camera, Scene};

use super::Measure;
use crate::bench::reference_cache;

/// Seed of every reference an experiment renders (the cache key includes it).
const SEED: u64 = 77;

/// One reference frame.
pub struct Frame {
    /// Radiance.
    pub hdr: Vec<Vec3>,
    /// Pixels that see an emitter, or border one: clients draw reflected light only, so
    /// these are left out of every comparison.
    pub emitters: Vec<bool>,
    /// Its picture at the experiment's exposure (sRGB8 RGB).
    pub rgb: Vec<u8>,
    /// Whether it came from the cache.
    pub cached: bool,
}

/// References of one scene and camera, at the experiment's size and samples per pixel.
pub struct References {
    scene: Scene,
    /// The BVH of the static scene (rebuilt per time when geometry moves).
    bvh: Option<SceneBvh>,
    measure: Measure,
    cache: Option<PathBuf>,
    /// Exposure of every picture, stops.
    pub exposure: f32,
    frames: HashMap<u64, Frame>,
    /// Pictures written.
    written: std::collections::HashSet<PathBuf>,
}

/// A scene time as a key (microseconds).
fn key(t: f64) -> u64 {
    (t.max(0.0) * 1e6).round() as u64
}

/// The exposure (stops) that maps the log-average luminance of `hdr` (emitters left out) to
/// middle grey, 0.18: it follows the scene's light, so pictures do not change when every
/// light is scaled.
fn exposure(hdr: &[Vec3], emitters: &[bool]) -> f32 {
    let lum = |v: &Vec3| 0.2126 * v.x + 0.7152 * v.y + 0.0722 * v.z;
    let (sum, n) = hdr
        .iter()
        .zip(emitters)
        .filter(|(v, e)| !**e && lum(v) > 0.0 && lum(v).is_finite())
        .fold((0.0f64, 0usize), |(s, n), (v, _)| {
            (s + (lum(v) as f64).ln(), n + 1)
        });
    if n == 0 {
        return 0.0;
    }
    let key = (sum / n as f64).exp();
    (0.18 / key).log2() as f32
}

/// Pixels whose centre sees an emissive triangle from `camera`, grown by one pixel.
fn emitter_mask(scene: &Scene, bvh: &SceneBvh, camera: &Camera, w: u32, h: u32) -> Vec<bool> {
    use cloudlight_scenes::glam::Vec2;
    let aspect = w as f32 / h as f32;
    let (wu, hu) = (w as usize, h as usize);
    let hits: Vec<bool> = (0..wu * hu)
        .map(|i| {
            let (x, y) = ((i % wu) as f32 + 0.5, (i / wu) as f32 + 0.5);
            let ndc = Vec2::new(x / w as f32 * 2.0 - 1.0, 1.0 - y / h as f32 * 2.0);
            bvh.closest_hit(
                camera.position,
                camera.ray_direction(ndc, aspect),
                f32::INFINITY,
            )
            .is_some_and(|hit| {
                let material = bvh.triangles()[hit.triangle as usize].material as usize;
                scene
                    .materials
                    .get(material)
                    .is_some_and(|m| m.is_emissive())
            })
        })
        .collect();
    (0..wu * hu)
        .map(|i| {
            let (x, y) = ((i % wu) as i64, (i / wu) as i64);
            (-1..=1).any(|dy| {
                (-1..=1).any(|dx| {
                    let (nx, ny) = (x + dx, y + dy);
                    (0..wu as i64).contains(&nx)
                        && (0..hu as i64).contains(&ny)
                        && hits[ny as usize * wu + nx as usize]
                })
            })
        })
        .collect()
}

impl References {
    /// References of `scene` measured as `measure` says; the exposure of every picture is
    /// chosen from the reference at `exposure_time_s` (so it scales with the scene's light:
    /// pictures, and every error taken from them, do not change when every light is scaled).
    pub fn new(scene: Scene, measure: &Measure, exposure_time_s: f64) -> Self {
        let bvh =
            (!scene.has_moving_geometry()).then(|| SceneBvh::at(&scene, 0.0, BvhKind::default()));
        let mut refs = References {
            scene,
            bvh,
            measure: measure.clone(),
            cache: reference_cache::dir(),
            exposure: 0.0,
            frames: HashMap::new(),
            written: Default::default(),
        };
        let (hdr, _, emitters) = refs.radiance(exposure_time_s);
        refs.exposure = exposure(&hdr, &emitters);
        refs
    }

    /// Client 0's camera at `t` (the overview when the scene has no camera paths).
    fn camera(&self, t: f64) -> Camera {
        match self.scene.cameras.first() {
            Some(c) => c.at(t),
            None => self.scene.overview_camera(),
        }
    }

    /// The full radiance at `t`, whether it came from the cache, and the emitter mask.
    fn radiance(&self, t: f64) -> (Vec<Vec3>, bool, Vec<bool>) {
        let m = &self.measure;
        let camera = self.camera(t);
        let settings = RenderSettings {
            width: m.width,
            height: m.height,
            camera,
            time_s: t,
            seed: SEED,
            max_bounces: 64,
            pixel: Default::default(),
        };
        let moving;
        let bvh = match &self.bvh {
            Some(b) => b,
            None => {
                moving = SceneBvh::at(&self.scene, t, BvhKind::default());
                &moving
            }
        };
        let r = reference_cache::reference(
            &self.scene,
            bvh,
            settings,
            m.reference_spp,
            self.cache.as_deref(),
        );
        let emitters = emitter_mask(&self.scene, bvh, &camera, m.width, m.height);
        (r.full(), r.cached, emitters)
    }

    /// The reference frame at scene time `t`.
    pub fn at(&mut self, t: f64) -> &Frame {
        let k = key(t);
        if !self.frames.contains_key(&k) {
            let (hdr, cached, emitters) = self.radiance(t);
            let rgb = metrics::tonemap(&hdr, self.exposure);
            self.frames.insert(
                k,
                Frame {
                    hdr,
                    emitters,
                    rgb,
                    cached,
                },
            );
        }
        &self.frames[&k]
    }

    /// Writes the reference picture at `t` into `dir` (once per [`References`]: an earlier
    /// invocation's may have another exposure) and returns its path.
    pub fn picture(&mut self, t: f64, dir: &Path) -> anyhow::Result<PathBuf> {
        let path = dir.join(format!(
            "reference_{:07}ms.png",
            (t * 1000.0).round() as u64
        ));
        if self.written.insert(path.clone()) {
            let (w, h) = (self.measure.width, self.measure.height);
            let frame = self.at(t);
            image::RgbImage::from_raw(w, h, frame.rgb.clone())
                .context("a reference of the wrong size")?
                .save(&path)
                .with_context(|| format!("writing {}", path.display()))?;
        }
        Ok(path)
    }

    /// The errors of a client's picture `rgb` (at the experiment's exposure) against the
    /// reference at `t`: relMSE of the radiance the picture shows (mapped back through the
    /// exposure and the tone curve) over pixels that see light and are saturated in neither
    /// picture, the energy ratio over the same pixels, and LDR-FLIP of the two pictures as
    /// a viewer sees them. Pixels of emitters (and their borders) are left out: clients draw
    /// reflected light only (for FLIP they are the reference's in both pictures).
    pub fn compare(&mut self, rgb: &[u8], t: f64) -> anyhow::Result<ImageErrors> {
        let (w, h) = (self.measure.width, self.measure.height);
        let exposure = self.exposure;
        let frame = self.at(t);
        anyhow::ensure!(
            rgb.len() == frame.rgb.len(),
            "the client's picture is not {w}x{h}"
        );
        let (shown, saturated) = metrics::untonemap(rgb, exposure);
        let (_, ref_saturated) = metrics::untonemap(&frame.rgb, exposure);
        let mask: Vec<bool> = (0..shown.len())
            .map(|i| {
                !saturated[i]
                    && !ref_saturated[i]
                    && !frame.emitters[i]
                    && frame.hdr[i].max_element() > 0.0
            })
            .collect();
        let mut seen = rgb.to_vec();
        for (i, e) in frame.emitters.iter().enumerate() {
            if *e {
                seen[3 * i..3 * i + 3].copy_from_slice(&frame.rgb[3 * i..3 * i + 3]);
            }
        }
        let map = metrics::relmse_map(&shown, &frame.hdr, &mask);
        Ok(ImageErrors {
            relmse: metrics::relmse_of_map(&map, &mask),
            flip: metrics::flip_ldr(&seen, &frame.rgb, w, h, PIXELS_PER_DEGREE).mean,
            energy_ratio: metrics::energy_ratio(&shown, &frame.hdr, &mask),
            pixels: mask.iter().filter(|m| **m).count(),
            worst_share: metrics::worst_share(&map, &mask, metrics::WORST_PIXELS),
        })
    }

    /// Records the reference's video of the camera path from 0 to `duration_s` at the
    /// experiment's `reference_fps` into `path` (MP4); `progress` is told of each frame.
    pub fn video(
        &mut self,
        duration_s: f64,
        path: &Path,
        mut progress: impl FnMut(usize, usize),
    ) -> anyhow::Result<()> {
        use cloudlight_render::video::{EncoderSettings, RateControl, Recorder, Yuv420};
        let (w, h) = (self.measure.width, self.measure.height);
        let fps = self.measure.reference_fps;
        let n = (duration_s * fps).floor() as usize + 1;
        let mut recorder = Recorder::create(
            path,
            EncoderSettings {
                width: w,
                height: h,
                fps: fps as f32,
                rate: RateControl::FixedQp(20),
                keyframe_s: 2.0,
                ..Default::default()
            },
        )?;
        for i in 0..n {
            progress(i, n);
            let t = i as f64 / fps;
            let yuv = Yuv420::from_rgb8(w, h, &self.at(t).rgb)?;
            recorder.push(&yuv, t)?;
        }
        recorder.finish()?;
        Ok(())
    }
}
