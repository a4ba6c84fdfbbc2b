//! A cache of the reference path tracer's images, keyed by everything that decides them:
//! the scene's whole content (meshes, materials and textures, lights and their motion), the
//! view, the scene time, the size, the samples per pixel, the seed, the bounce bound and
//! [`TRACER_VERSION`]. A reference of a few thousand samples per pixel takes minutes; a
//! quality sweep run again, or an experiment comparing many cuts of one camera path, reads
//! it back instead.
//!
//! Where: `$CLOUDLIGHT_REFERENCE_CACHE` if set (`off` turns the cache off), else
//! `$XDG_CACHE_HOME/cloudlight/reference`, else `~/.cache/cloudlight/reference`. Each entry
//! is `<key>.direct.exr`, `<key>.indirect.exr`, `<key>.indirect_half.exr` (the indirect
//! image of the first half of the samples, which tells the reference's own noise:
//! [`Reference::noise`]) and `<key>.json` (what the key stands for, for people). An entry
//! that cannot be read, lacks a part, or holds another size, is rendered again and
//! overwritten; one that cannot be written is a warning, never a failure.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use cloudlight_render::{PixelSampling, RenderSettings, SceneBvh, image_io};
use cloudlight_scenes::Scene;
use cloudlight_scenes::glam::Vec3;
use sha2::{Digest, Sha256};

/// Changes whenever the reference tracer's output for the same inputs changes, so that no
/// stale image is read back.
pub const TRACER_VERSION: u32 = 1;

/// The reference's two images.
#[derive(Clone, Debug, PartialEq)]
pub struct Reference {
    /// Direct light (and emitters seen directly).
    pub direct: Vec<Vec3>,
    /// Indirect light only.
    pub indirect: Vec<Vec3>,
    /// Indirect light of the first half of the samples (of all of them at 1 spp).
    pub indirect_half: Vec<Vec3>,
    /// Whether it came from the cache.
    pub cached: bool,
}

impl Reference {
    /// Direct plus indirect.
    pub fn full(&self) -> Vec<Vec3> {
        self.direct
            .iter()
            .zip(&self.indirect)
            .map(|(d, i)| *d + *i)
            .collect()
    }

    /// The indirect image's own noise as the error a noiseless technique would show against
    /// it: relMSE of its first half of samples against the whole (their difference is half
    /// the two halves', whose variance is twice the half's, so its expected square is the
    /// whole's variance), over the pixels with light in either. A technique's relMSE cannot
    /// be trusted much below this.
    pub fn noise(&self) -> f64 {
        self.relmse_where_lit(&self.indirect_half)
    }

    /// The error a client that shades each pixel at one point, its centre (every raster's
    /// G-buffer), shows against this image even when its light is exact: relMSE of
    /// `centred`'s indirect image (the same view rendered with
    /// [`PixelSampling::Centre`]) against this one's, over the pixels with light in
    /// either. This image holds each pixel's mean over its area; where a pixel straddles a
    /// silhouette, a fold or texels smaller than it, its centre's light is not that mean.
    /// A technique's relMSE below this is the raster's sampling, not its light. Each pixel
    /// of both images draws the same random numbers, so where the centre and the area see
    /// one surface their paths stay alike and little of their noise
    /// ([`Reference::noise`]) is in it.
    pub fn sampling_floor(&self, centred: &Reference) -> f64 {
        self.relmse_where_lit(&centred.indirect)
    }

    /// relMSE of `image` against the indirect image, over the pixels with light in either.
    fn relmse_where_lit(&self, image: &[Vec3]) -> f64 {
        let lit: Vec<bool> = self
            .indirect
            .iter()
            .zip(image)
            .map(|(a, b)| a.max_element() > 0.0 || b.max_element() > 0.0)
            .collect();
        cloudlight_render::metrics::relmse_normalized(image, &self.indirect, &lit)
    }
}

/// Feeds formatted text straight into a hash (a scene's `Debug` text can be tens of MB).
struct HashWriter<'a>(&'a mut Sha256);

impl std::fmt::Write for HashWriter<'_> {
    fn write_str(&mut self, s: &str) -> std::fmt::Result {
        self.0.update(s.as_bytes());
        Ok(())
    }
}

/// The cache key of a reference of `scene` with `settings` at `spp` samples per pixel: the
/// hex SHA-256 of the scene's complete `Debug` text (floats print exactly) and the rest.
pub fn key(scene: &Scene, settings: &RenderSettings, spp: u32) -> String {
    let mut hasher = Sha256::new();
    let mut w = HashWriter(&mut hasher);
    // Writing into a hash cannot fail.
    let _ = write!(
        w,
        "v{TRACER_VERSION}|{scene:?}|{:?}|{}|{}x{}|{spp}|{}|{}",
        settings.camera,
        settings.time_s.to_bits(),
        settings.width,
        settings.height,
        settings.seed,
        settings.max_bounces
    );
    // Jittered images keep the keys they had before the choice existed.
    if settings.pixel == PixelSampling::Centre {
        let _ = write!(w, "|centre");
    }
    hasher
        .finalize()
        .iter()
        .fold(String::with_capacity(64), |mut s, b| {
            let _ = write!(s, "{b:02x}");
            s
        })
}

/// Where the cache lives, or `None` when it is turned off.
pub fn dir() -> Option<PathBuf> {
    match std::env::var_os("CLOUDLIGHT_REFERENCE_CACHE") {
        Some(v) if v == "off" => None,
        Some(v) if !v.is_empty() => Some(PathBuf::from(v)),
        _ => {
            let base = std::env::var_os("XDG_CACHE_HOME")
                .filter(|v| !v.is_empty())
                .map(PathBuf::from)
                .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cache")))?;
            Some(base.join("cloudlight").join("reference"))
        }
    }
}

/// The reference of `scene` (its BVH `bvh`) with `settings` at `spp` samples per pixel:
/// read from the cache in `dir` when there, else rendered (and stored when `dir` is given).
pub fn reference(
    scene: &Scene,
    bvh: &SceneBvh,
    settings: RenderSettings,
    spp: u32,
    dir: Option<&Path>,
) -> Reference {
    let k = key(scene, &settings, spp);
    let pixels = settings.width as usize * settings.height as usize;
    let path = |dir: &Path, part: &str| dir.join(format!("{k}.{part}"));
    if let Some(dir) = dir {
        let read = |part: &str| {
            image_io::read_exr(&path(dir, part))
                .ok()
                .filter(|(w, h, img)| {
                    (*w, *h) == (settings.width, settings.height) && img.len() == pixels
                })
                .map(|(_, _, img)| img)
        };
        if let (Some(direct), Some(indirect), Some(indirect_half)) = (
            read("direct.exr"),
            read("indirect.exr"),
            read("indirect_half.exr"),
        ) {
            return Reference {
                direct,
                indirect,
                indirect_half,
                cached: true,
            };
        }
    }
    // The first half of the samples, kept, then the rest added: every sample has its own
    // random stream, so the whole is the image of one pass of `spp`.
    let renderer = cloudlight_render::ReferenceRenderer::new(scene, bvh, settings);
    let mut images = cloudlight_render::ReferenceImages::new(settings.width, settings.height);
    let half = (spp / 2).max(1);
    renderer.render_pass(&mut images, 0, half);
    let indirect_half = images.indirect();
    if spp > half {
        renderer.render_pass(&mut images, half, spp - half);
    }
    let out = Reference {
        direct: images.direct(),
        indirect: images.indirect(),
        indirect_half,
        cached: false,
    };
    if let Some(dir) = dir {
        let about = serde_json::json!({
            "scene": scene.name, "camera": format!("{:?}", settings.camera),
            "time_s": settings.time_s, "width": settings.width, "height": settings.height,
            "spp": spp, "seed": settings.seed, "max_bounces": settings.max_bounces,
            "tracer_version": TRACER_VERSION, "pixel": format!("{:?}", settings.pixel),
        });
        // Each file is written under a name of this process and renamed into place, so a
        // reader (another benchmark, a parallel test) never sees half of one.
        let (w, h) = (settings.width, settings.height);
        let temp = |part: &str| dir.join(format!("{k}.{part}.{}.tmp.exr", std::process::id()));
        let store = |part: &str, img: &[Vec3]| -> Result<(), String> {
            let t = temp(part);
            image_io::write_exr(&t, w, h, img).map_err(|e| e.to_string())?;
            std::fs::rename(&t, path(dir, part)).map_err(|e| e.to_string())
        };
        let stored = std::fs::create_dir_all(dir)
            .map_err(|e| e.to_string())
            .and_then(|()| store("direct.exr", &out.direct))
            .and_then(|()| store("indirect.exr", &out.indirect))
            .and_then(|()| store("indirect_half.exr", &out.indirect_half))
            .and_then(|()| {
                std::fs::write(path(dir, "json"), about.to_string()).map_err(|e| e.to_string())
            });
        if let Err(e) = stored {
            tracing::warn!(dir = %dir.display(), "the reference was not cached: {e}");
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use cloudlight_render::BvhKind;

    fn settings(scene: &Scene) -> RenderSettings {
        RenderSettings {
            width: 12,
            height: 8,
            camera: scene.cameras[0].at(0.0),
            time_s: 0.0,
            seed: 5,
            max_bounces: 8,
            pixel: Default::default(),
        }
    }

    #[test]
    fn a_reference_is_rendered_once_then_read_back_and_any_change_is_another_key() {
        let dir = tempfile::tempdir().unwrap();
        let scene = cloudlight_scenes::load("cornell").unwrap();
        let bvh = SceneBvh::at(&scene, 0.0, BvhKind::default());
        let s = settings(&scene);
        let first = reference(&scene, &bvh, s, 4, Some(dir.path()));
        assert!(!first.cached);
        let again = reference(&scene, &bvh, s, 4, Some(dir.path()));
        assert!(again.cached);
        assert_eq!(again.indirect, first.indirect);
        assert_eq!(again.direct, first.direct);
        assert!(first.indirect.iter().any(|v| v.max_element() > 0.0));
        // Everything that decides the image is in the key.
        let k = key(&scene, &s, 4);
        assert_eq!(k.len(), 64);
        assert_ne!(key(&scene, &s, 8), k, "spp");
        assert_ne!(key(&scene, &RenderSettings { seed: 6, ..s }, 4), k, "seed");
        assert_ne!(
            key(&scene, &RenderSettings { time_s: 0.5, ..s }, 4),
            k,
            "time"
        );
        assert_ne!(
            key(&scene, &RenderSettings { width: 13, ..s }, 4),
            k,
            "size"
        );
        let centred = RenderSettings {
            pixel: PixelSampling::Centre,
            ..s
        };
        assert_ne!(key(&scene, &centred, 4), k, "pixel sampling");
        let mut brighter = scene.clone();
        brighter.materials[0].albedo *= 0.99;
        assert_ne!(key(&brighter, &s, 4), k, "a material");
        let mut hotter = scene.clone();
        for m in hotter
            .materials
            .iter_mut()
            .filter(|m| m.emission.max_element() > 0.0)
        {
            m.emission *= 2.0;
        }
        assert_ne!(key(&hotter, &s, 4), k, "the emitters");
        // A damaged entry is rendered again and replaced.
        std::fs::write(
            dir.path().join(format!("{k}.indirect.exr")),
            b"not an image",
        )
        .unwrap();
        let repaired = reference(&scene, &bvh, s, 4, Some(dir.path()));
        assert!(!repaired.cached);
        assert_eq!(repaired.indirect, first.indirect);
        assert!(reference(&scene, &bvh, s, 4, Some(dir.path())).cached);
        // Without a folder nothing is kept.
        assert!(!reference(&scene, &bvh, s, 4, None).cached);
    }

    #[test]
    fn the_reference_tells_its_own_noise_which_falls_as_samples_grow() {
        let dir = tempfile::tempdir().unwrap();
        let scene = cloudlight_scenes::load("cornell").unwrap();
        let bvh = SceneBvh::at(&scene, 0.0, BvhKind::default());
        let s = RenderSettings {
            width: 16,
            height: 16,
            ..settings(&scene)
        };
        // Rendered in two halves, the whole is the image of one pass.
        let r = reference(&scene, &bvh, s, 8, Some(dir.path()));
        let whole = cloudlight_render::render(&scene, &bvh, s, 8);
        assert_eq!(r.indirect, whole.indirect());
        assert_eq!(r.direct, whole.direct());
        assert_eq!(
            r.indirect_half,
            cloudlight_render::render(&scene, &bvh, s, 4).indirect()
        );
        let again = reference(&scene, &bvh, s, 8, Some(dir.path()));
        assert!(again.cached);
        assert_eq!(again.noise(), r.noise());
        // Noise variance goes as 1/spp: 8× the samples, several times less noise.
        let more = reference(&scene, &bvh, s, 64, None);
        assert!(r.noise() > 0.0 && more.noise() > 0.0);
        assert!(
            more.noise() < r.noise() / 3.0,
            "{} vs {}",
            more.noise(),
            r.noise()
        );
        // At one sample the half is the whole: no noise can be told.
        assert_eq!(reference(&scene, &bvh, s, 1, None).noise(), 0.0);
    }

    #[test]
    fn the_sampling_floor_is_the_noise_on_a_plain_wall_and_more_where_pixels_straddle_edges() {
        let scene = cloudlight_scenes::load("cornell").unwrap();
        let bvh = SceneBvh::at(&scene, 0.0, BvhKind::default());
        let floor = |camera: &str| {
            let area = RenderSettings {
                width: 24,
                height: 24,
                camera: cloudlight_scenes::camera(&scene, camera, 0.0).unwrap(),
                ..settings(&scene)
            };
            let centred = RenderSettings {
                pixel: PixelSampling::Centre,
                ..area
            };
            let r = reference(&scene, &bvh, area, 64, None);
            (
                r.sampling_floor(&reference(&scene, &bvh, centred, 64, None)),
                r.noise(),
            )
        };
        // Only the back wall in view: one surface, evenly lit at the scale of a pixel, and
        // the same random numbers for both images: far below their noise (0.045).
        let (wall, wall_noise) = floor("0.28,0.45,0.3:0.28,0.45,1:20");
        // The whole box in 24² pixels: its edges, the blocks' silhouettes (0.24).
        let (whole, whole_noise) = floor("0");
        eprintln!("wall {wall} (noise {wall_noise}), whole {whole} (noise {whole_noise})");
        assert!(wall < 0.2 * wall_noise, "wall {wall}, noise {wall_noise}");
        assert!(
            whole > 10.0 * wall && whole > 2.0 * whole_noise,
            "whole {whole}, noise {whole_noise}, wall {wall}"
        );
    }
}
