//! One irradiance-map update (CloudLight §4.2, steps 3–4): a texture-space deferred pass.
//!
//! Phases of [`Gatherer::update`]:
//! 1. **Scene** at the update's time: the BVH and the texels' world frames (rebuilt only when
//!    geometry moves).
//! 2. **Direct light in texture space**: E_direct per valid texel from `direct_samples`
//!    light samples with ray-traced shadows ([`DirectLight`]), kept while lights and
//!    geometry are static.
//! 3. **Radiosity**: per texel, the radiance it sends on, B = ρ/π · (E_direct + E_previous),
//!    dilated into the padding. Reading the previous map adds one bounce per update.
//! 4. **Gather**: at each basis centre (or each texel, the paper's naive server), N
//!    cosine-distributed rays from a Hammersley set, traced in Morton order over the sample
//!    square so that consecutive rays leave in neighbouring directions: coherent bundles
//!    ([`coherent_samples`]; on the Cornell box an update is ~10–16% faster than in index
//!    order);
//!    E = (π/N) · Σ B(hit) over front-face hits (back faces and misses add nothing).
//! 5. **Reconstruct**: per texel, E = Σ w_k E_k over its bases, made an [`HdrMap`] (dilated
//!    once, there; the next bounce reads that map).
//!
//! While lights and geometry are static the update converges to a fixed point (a fixed
//! sample set); once an update changes the map by less than [`CONVERGED`] relative, later
//! updates re-gather nothing and hand out the same map.

use std::sync::Arc;
use std::time::Instant;

use glam::Vec3;
use rayon::prelude::*;

use crate::bvh::{BvhKind, SceneBvh};
use crate::direct_light::DirectLight;
use crate::hdr_map::{HdrMap, bilinear};
use crate::sampling::{Rng, basis, cosine_hemisphere};

use super::Lightmap;
use super::texels::hammersley;

/// Relative change of the map's energy below which a static scene's update is final.
pub const CONVERGED: f32 = 1e-4;

/// Where gather rays start.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum GatherMode {
    /// Once per basis, reconstructed per texel (the paper's efficient server).
    #[default]
    Bases,
    /// At every valid texel (the paper's naive server).
    Texels,
}

/// Settings of the gather.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GatherSettings {
    /// Per basis or per texel.
    pub mode: GatherMode,
    /// Rays per basis (the paper: 26k rays for 50 bases).
    pub rays_per_basis: u32,
    /// Rays per texel in [`GatherMode::Texels`].
    pub rays_per_texel: u32,
    /// Light samples per texel for texture-space direct light.
    pub direct_samples: u32,
    /// Seed of the direct-light samples and the gather's sample rotation.
    pub seed: u64,
}

impl Default for GatherSettings {
    fn default() -> Self {
        GatherSettings {
            mode: GatherMode::Bases,
            rays_per_basis: 512,
            rays_per_texel: 64,
            direct_samples: 4,
            seed: 1,
        }
    }
}

/// What one update did.
#[derive(Clone, Debug, PartialEq)]
pub struct Update {
    /// The new map: E_indirect per texel, W·m⁻² per channel, dilated into invalid texels.
    pub map: Arc<HdrMap>,
    /// Scene time the map is valid for, seconds.
    pub time_s: f64,
    /// Gather rays traced (0 when converged).
    pub rays: u64,
    /// Shadow rays of texture-space direct light (0 when kept).
    pub direct_rays: u64,
    /// Points gathered at (bases or texels).
    pub gather_points: usize,
    /// Whether the scene was static and converged, so nothing was re-gathered.
    pub converged: bool,
    /// Wall time of the whole update, seconds.
    pub seconds: f64,
}

/// The light-map server's state across updates: the previous map (for the next bounce)
/// and the direct light while it is valid.
pub struct Gatherer {
    lightmap: Arc<Lightmap>,
    settings: GatherSettings,
    bvh: Option<SceneBvh>,
    frame: (Vec<Vec3>, Vec<Vec3>),
    direct: Option<Vec<Vec3>>,
    /// The last map's texels, which the next bounce reads.
    previous: Vec<Vec3>,
    /// The last map as handed out, and the scene time it is valid for.
    map: (Arc<HdrMap>, f64),
    converged: bool,
    updates: u64,
    /// The gather's sample set in coherent order ([`coherent_samples`]).
    samples: Vec<(f32, f32)>,
}

/// The `n` Hammersley points of the unit square in Morton (Z-curve) order: consecutive
/// samples map to neighbouring directions on the hemisphere, so a point's rays run as
/// coherent bundles (each ray's traversal finds the nodes of the one before it in cache).
pub fn coherent_samples(n: u32) -> Vec<(f32, f32)> {
    fn spread(v: u32) -> u64 {
        let mut x = u64::from(v & 0xFFFF);
        x = (x | (x << 8)) & 0x00FF_00FF;
        x = (x | (x << 4)) & 0x0F0F_0F0F;
        x = (x | (x << 2)) & 0x3333_3333;
        (x | (x << 1)) & 0x5555_5555
    }
    let quantize = |u: f32| (u.clamp(0.0, 1.0) * 65535.0) as u32;
    let mut s: Vec<(u64, (f32, f32))> = (0..n)
        .map(|i| {
            let (u1, u2) = hammersley(i, n);
            (spread(quantize(u1)) | (spread(quantize(u2)) << 1), (u1, u2))
        })
        .collect();
    s.sort_unstable_by_key(|e| e.0);
    s.into_iter().map(|e| e.1).collect()
}

impl Gatherer {
    /// A gatherer over a baked light map, starting from a black map.
    pub fn new(lightmap: Arc<Lightmap>, settings: GatherSettings) -> Self {
        let t = &lightmap.texels;
        let previous = vec![Vec3::ZERO; t.valid.len()];
        let map = HdrMap::new(t.width, t.height, &previous, &t.valid)
            .expect("a baked light map's sides and coverage agree");
        Gatherer {
            map: (Arc::new(map), 0.0),
            frame: (t.positions.clone(), t.normals.clone()),
            lightmap,
            settings,
            bvh: None,
            direct: None,
            previous,
            converged: false,
            updates: 0,
            samples: coherent_samples(match settings.mode {
                GatherMode::Bases => settings.rays_per_basis,
                GatherMode::Texels => settings.rays_per_texel,
            }),
        }
    }

    /// The light map gathered over.
    pub fn lightmap(&self) -> &Arc<Lightmap> {
        &self.lightmap
    }

    /// The latest map.
    pub fn map(&self) -> &Arc<HdrMap> {
        &self.map.0
    }

    /// Computes the map for scene time `t_s` (one more bounce than the last).
    pub fn update(&mut self, t_s: f64) -> Update {
        let start = Instant::now();
        let scene = &self.lightmap.scene;
        let moving_geometry = scene.has_moving_geometry();
        let moving_lights = scene.is_animated() && !moving_geometry;
        let is_static = !scene.is_animated();
        if is_static && self.converged {
            self.map.1 = t_s;
            return self.finish(start, 0, 0, 0, true);
        }
        // 1. Scene.
        if self.bvh.is_none() || moving_geometry {
            let bvh = SceneBvh::at(scene, t_s, BvhKind::default());
            if moving_geometry {
                self.frame = self.lightmap.texels.frame_at(bvh.triangles());
            }
            self.bvh = Some(bvh);
        }
        let bvh = self.bvh.as_ref().expect("built above");
        // 2. Direct light.
        let mut direct_rays = 0;
        if self.direct.is_none() || moving_geometry || moving_lights {
            let (e, rays) = direct_map(
                &self.lightmap,
                bvh,
                &self.frame,
                t_s,
                &self.settings,
                self.updates,
            );
            self.direct = Some(e);
            direct_rays = rays;
        }
        // 3. Radiosity.
        let radiosity = self.radiosity();
        // 4–5. Gather and reconstruct.
        let (texels, rays, points) = self.gather(bvh, &radiosity);
        let t = &self.lightmap.texels;
        let map = HdrMap::from_plan(&self.lightmap.dilation, &texels)
            .expect("a baked light map's sides and coverage agree");
        // The next bounce reads the map as clients get it (dilated once, in the map).
        let texels = map.texels();
        let (old, new) = (energy(&self.previous, &t.valid), energy(&texels, &t.valid));
        self.converged = is_static && (new - old).abs() <= CONVERGED * new.max(f32::MIN_POSITIVE);
        self.previous = texels;
        self.map = (Arc::new(map), t_s);
        self.finish(start, rays, direct_rays, points, false)
    }

    fn finish(
        &mut self,
        start: Instant,
        rays: u64,
        direct_rays: u64,
        points: usize,
        converged: bool,
    ) -> Update {
        self.updates += 1;
        Update {
            map: self.map.0.clone(),
            time_s: self.map.1,
            rays,
            direct_rays,
            gather_points: points,
            converged,
            seconds: start.elapsed().as_secs_f64(),
        }
    }

    /// B = ρ/π · (E_direct + E_previous) per texel, dilated.
    fn radiosity(&self) -> Vec<Vec3> {
        let lm = &self.lightmap;
        let direct = self.direct.as_deref().unwrap_or_default();
        let b: Vec<Vec3> = (0..lm.albedo.len())
            .into_par_iter()
            .map(|i| {
                if !lm.texels.valid[i] {
                    return Vec3::ZERO;
                }
                let e = direct.get(i).copied().unwrap_or_default() + self.previous[i];
                lm.albedo[i] * e / std::f32::consts::PI
            })
            .collect();
        lm.dilated(b)
    }

    fn gather(&self, bvh: &SceneBvh, radiosity: &[Vec3]) -> (Vec<Vec3>, u64, usize) {
        let lm = &self.lightmap;
        let (pos, nrm) = &self.frame;
        let eps = lm.texels.texel_m * 1e-2;
        let (w, h) = (lm.texels.width, lm.texels.height);
        let gather_at = |texel: usize, rays: u32| -> Vec3 {
            let (x, n) = (pos[texel], nrm[texel]);
            let (t, b) = basis(n);
            // A fixed rotation per point decorrelates neighbours' sample sets.
            let mut rng = Rng::new(self.settings.seed, texel as u64);
            let (r1, r2) = (rng.next_f32(), rng.next_f32());
            let mut sum = Vec3::ZERO;
            for &(u1, u2) in &self.samples {
                let l = cosine_hemisphere((u1 + r1).fract(), (u2 + r2).fract());
                let d = (t * l.x + b * l.y + n * l.z).normalize();
                if let Some(hit) = bvh.closest_hit(x + n * eps, d, f32::INFINITY)
                    && bvh.geometric_normal(hit.triangle).dot(d) < 0.0
                {
                    let tri = &bvh.triangles()[hit.triangle as usize];
                    let (bu, bv) = (hit.uv.x, hit.uv.y);
                    let uv = tri.lightmap_uv[0] * (1.0 - bu - bv)
                        + tri.lightmap_uv[1] * bu
                        + tri.lightmap_uv[2] * bv;
                    sum += bilinear(radiosity, w, h, uv);
                }
            }
            sum * (std::f32::consts::PI / rays.max(1) as f32)
        };
        match self.settings.mode {
            GatherMode::Bases => {
                let n = self.settings.rays_per_basis;
                let per_basis: Vec<Vec3> = lm
                    .bases
                    .bases
                    .par_iter()
                    .map(|b| gather_at(b.texel as usize, n))
                    .collect();
                let rays = per_basis.len() as u64 * n as u64;
                (lm.bases.reconstruct(&per_basis), rays, per_basis.len())
            }
            GatherMode::Texels => {
                let n = self.settings.rays_per_texel;
                let texels: Vec<Vec3> = (0..lm.texels.valid.len())
                    .into_par_iter()
                    .map(|i| {
                        if lm.texels.valid[i] {
                            gather_at(i, n)
                        } else {
                            Vec3::ZERO
                        }
                    })
                    .collect();
                let points = lm.texels.valid_count();
                (texels, points as u64 * n as u64, points)
            }
        }
    }
}

/// Mean of the valid texels' channel sums.
fn energy(texels: &[Vec3], valid: &[bool]) -> f32 {
    let (sum, n) = texels
        .iter()
        .zip(valid)
        .filter(|(_, v)| **v)
        .fold((0.0f64, 0u64), |(s, n), (e, _)| {
            (s + e.element_sum() as f64, n + 1)
        });
    (sum / n.max(1) as f64) as f32
}

/// Texture-space direct irradiance (W·m⁻²) of every valid texel, and the shadow rays spent.
fn direct_map(
    lm: &Lightmap,
    bvh: &SceneBvh,
    frame: &(Vec<Vec3>, Vec<Vec3>),
    t_s: f64,
    s: &GatherSettings,
    update: u64,
) -> (Vec<Vec3>, u64) {
    let light = DirectLight::new(&lm.scene, bvh, t_s);
    let samples = s.direct_samples.max(1);
    let eps = light.eps().max(lm.texels.texel_m * 1e-3);
    let seed = s.seed ^ update.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    let e: Vec<Vec3> = (0..lm.texels.valid.len())
        .into_par_iter()
        .map(|i| {
            if !lm.texels.valid[i] || !light.any() {
                return Vec3::ZERO;
            }
            let (x, n) = (frame.0[i], frame.1[i]);
            let mut rng = Rng::new(seed, i as u64);
            let sum: Vec3 = (0..samples)
                .map(|_| light.irradiance(x + n * eps, n, &mut rng))
                .sum();
            let e = sum / samples as f32;
            if e.is_finite() {
                e.max(Vec3::ZERO)
            } else {
                Vec3::ZERO
            }
        })
        .collect();
    let lights = lm.scene.lights.len() as u64 + 1;
    (e, lm.texels.valid_count() as u64 * samples as u64 * lights)
}
