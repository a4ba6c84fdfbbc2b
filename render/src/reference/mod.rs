//! The reference path tracer that judges every technique.
//!
//! Diffuse surfaces, cosine-weighted bounces (throughput × albedo), next-event estimation
//! at every vertex towards emissive triangles (chosen by power, uniform on the triangle),
//! point, spot and directional lights, and Russian roulette from the third bounce
//! (q = min(0.95, max throughput channel), unbiased). Without MIS, emitters hit by bounce
//! rays are ignored (their light arrives by NEE). Each (pixel, sample) draws from its own
//! random stream, so images are deterministic and passes can be split at will.
//!
//! Three float images come out, all radiance in W·m⁻²·sr⁻¹ toward the camera:
//! - `direct`: emitters seen by the camera + light from sources reflected once (NEE at the
//!   primary hit) — what a client's own direct lighting computes;
//! - `indirect`: everything else (light that bounced at least twice) = ρ/π·E_indirect at the
//!   primary hit — what the techniques deliver;
//! - `full` = direct + indirect.

use cloudlight_scenes::{Camera, Scene};
use glam::{Vec2, Vec3};
use rayon::prelude::*;

use crate::bvh::{Hit, SceneBvh};
use crate::direct_light::{DirectLight, LightSample};
use crate::sampling::{Rng, basis, cosine_hemisphere};

/// What to render.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RenderSettings {
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// The view.
    pub camera: Camera,
    /// Scene time, seconds.
    pub time_s: f64,
    /// Seed of the random streams.
    pub seed: u64,
    /// Longest path (bounces), a safety bound; Russian roulette ends paths long before.
    pub max_bounces: u32,
    /// Where in its pixel each camera ray passes.
    pub pixel: PixelSampling,
}

/// Where a pixel's camera rays pass through it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum PixelSampling {
    /// Uniformly over the pixel (jittered): the pixel's mean radiance, the image a camera
    /// with a box filter sees — what every technique is judged against.
    #[default]
    Area,
    /// Through its centre only, as a raster that shades one point per pixel (every
    /// client's G-buffer) sees the scene: against the [`PixelSampling::Area`] image, the
    /// error such a client shows even with exact light — the sampling's own floor, not the
    /// light's (silhouettes, a ledge a pixel high, texels smaller than a pixel).
    Centre,
}

/// Accumulated radiance images (sums over samples; divide by `spp`).
#[derive(Clone, Debug, PartialEq)]
pub struct ReferenceImages {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// Samples per pixel accumulated.
    pub spp: u32,
    direct_sum: Vec<Vec3>,
    indirect_sum: Vec<Vec3>,
}

impl ReferenceImages {
    /// Empty images.
    pub fn new(width: u32, height: u32) -> Self {
        let n = (width * height) as usize;
        ReferenceImages {
            width,
            height,
            spp: 0,
            direct_sum: vec![Vec3::ZERO; n],
            indirect_sum: vec![Vec3::ZERO; n],
        }
    }

    fn mean(&self, sum: &[Vec3]) -> Vec<Vec3> {
        let k = 1.0 / self.spp.max(1) as f32;
        sum.iter().map(|v| *v * k).collect()
    }

    /// Direct radiance per pixel (row-major from the top).
    pub fn direct(&self) -> Vec<Vec3> {
        self.mean(&self.direct_sum)
    }

    /// Indirect radiance per pixel.
    pub fn indirect(&self) -> Vec<Vec3> {
        self.mean(&self.indirect_sum)
    }

    /// Full radiance per pixel.
    pub fn full(&self) -> Vec<Vec3> {
        let k = 1.0 / self.spp.max(1) as f32;
        self.direct_sum
            .iter()
            .zip(&self.indirect_sum)
            .map(|(d, i)| (*d + *i) * k)
            .collect()
    }
}

/// Everything a render of one scene at one time needs besides the settings.
pub struct ReferenceRenderer<'a> {
    scene: &'a Scene,
    bvh: &'a SceneBvh,
    direct: DirectLight<'a>,
    eps: f32,
    settings: RenderSettings,
}

impl<'a> ReferenceRenderer<'a> {
    /// Prepares a render of `scene` (whose BVH at `settings.time_s` is `bvh`).
    pub fn new(scene: &'a Scene, bvh: &'a SceneBvh, settings: RenderSettings) -> Self {
        let direct = DirectLight::new(scene, bvh, settings.time_s);
        ReferenceRenderer {
            scene,
            bvh,
            eps: direct.eps(),
            direct,
            settings,
        }
    }

    /// Adds samples `first_sample .. first_sample + count` of every pixel to `images`.
    ///
    /// A row's paths advance together, one bounce at a time, their rays cast as a batch
    /// ([`SceneBvh::closest_hits_into`]: camera rays of neighbouring pixels in streams,
    /// bounces sorted by octant), then the shadow rays of every path's next-event estimate
    /// at that bounce ([`SceneBvh::occluded_into`]): each path keeps its own random
    /// sequence, so the result is that of tracing the paths one by one.
    pub fn render_pass(&self, images: &mut ReferenceImages, first_sample: u32, count: u32) {
        let s = self.settings;
        let width = s.width as usize;
        // Paths of one row in flight at once, a pixel's samples in order.
        let per_pixel = count.max(1) as usize;
        let pixels_per_batch = (PATHS_PER_BATCH / per_pixel).max(1);
        images
            .direct_sum
            .par_chunks_mut(width)
            .zip(images.indirect_sum.par_chunks_mut(width))
            .enumerate()
            .for_each(|(y, (direct_row, indirect_row))| {
                let mut paths = Vec::new();
                let mut queries = Vec::new();
                let mut hits = Vec::new();
                let mut alive = Vec::new();
                let mut lit = Vec::new();
                let mut vertices = Vec::new();
                for x0 in (0..width).step_by(pixels_per_batch) {
                    let x1 = (x0 + pixels_per_batch).min(width);
                    paths.clear();
                    for x in x0..x1 {
                        for k in first_sample..first_sample + count {
                            paths.push(self.camera_path(x, y, k));
                        }
                    }
                    alive.clear();
                    alive.extend(0..paths.len());
                    for bounce in 0..s.max_bounces {
                        if alive.is_empty() {
                            break;
                        }
                        queries.clear();
                        queries.extend(alive.iter().map(|&i| {
                            let p: &Path = &paths[i];
                            (p.o, p.d, f32::INFINITY)
                        }));
                        hits.clear();
                        hits.resize(queries.len(), None);
                        self.bvh.closest_hits_into(&queries, &mut hits);
                        let mut next = 0;
                        lit.clear();
                        vertices.clear();
                        for j in 0..alive.len() {
                            let i = alive[j];
                            if let Some(hit) = hits[j]
                                && self.step(
                                    &mut paths[i],
                                    i,
                                    bounce,
                                    &hit,
                                    &mut lit,
                                    &mut vertices,
                                )
                            {
                                alive[next] = i;
                                next += 1;
                            }
                        }
                        alive.truncate(next);
                        // This bounce's shadow rays, together.
                        let blocked = self.direct.blocked(&lit);
                        for v in &vertices {
                            let terms = v.samples.clone();
                            let e = DirectLight::sum_clear(&lit[terms.clone()], &blocked[terms]);
                            v.add(&mut paths[v.path], e);
                        }
                    }
                    for p in &paths {
                        direct_row[p.x] += p.direct;
                        indirect_row[p.x] += p.indirect;
                    }
                }
            });
        images.spp += count;
    }

    /// Sample `k` of pixel (`x`, `y`): its camera ray (jittered in the pixel, or through its
    /// centre: [`RenderSettings::pixel`]), and its random sequence.
    fn camera_path(&self, x: usize, y: usize, k: u32) -> Path {
        let s = &self.settings;
        let pixel = (y * s.width as usize + x) as u64;
        let mut rng = Rng::new(s.seed, pixel * 1_000_003 + k as u64);
        // Drawn either way, so that a pixel's random sequence is the same for both.
        let jitter = Vec2::new(rng.next_f32(), rng.next_f32());
        let jitter = match s.pixel {
            PixelSampling::Area => jitter,
            PixelSampling::Centre => Vec2::splat(0.5),
        };
        let ndc = Vec2::new(
            ((x as f32 + jitter.x) / s.width as f32) * 2.0 - 1.0,
            1.0 - ((y as f32 + jitter.y) / s.height as f32) * 2.0,
        );
        Path {
            o: s.camera.position,
            d: s.camera
                .ray_direction(ndc, s.width as f32 / s.height as f32),
            throughput: Vec3::ONE,
            direct: Vec3::ZERO,
            indirect: Vec3::ZERO,
            rng,
            x,
        }
    }

    /// One bounce of path `index` at `hit`: emission seen directly, the terms of the
    /// next-event estimate (appended to `lit`, their vertex to `vertices`, for the caller to
    /// cast their shadow rays and add what is lit), then (unless Russian roulette ends it)
    /// the next direction. Whether the path goes on.
    fn step(
        &self,
        path: &mut Path,
        index: usize,
        bounce: u32,
        hit: &Hit,
        lit: &mut Vec<LightSample>,
        vertices: &mut Vec<Vertex>,
    ) -> bool {
        let (o, d) = (path.o, path.d);
        let tri = &self.bvh.triangles()[hit.triangle as usize];
        let material = &self.scene.materials[tri.material as usize];
        let ng = self.bvh.geometric_normal(hit.triangle);
        let front = ng.dot(d) < 0.0;
        if bounce == 0 && front {
            path.direct += material.emission;
        }
        // Two-sided diffuse: shade with the normal facing the incoming ray.
        let mut n = self.bvh.shading_normal(hit);
        let ng = if front { ng } else { -ng };
        if n.dot(ng) < 0.0 {
            n = -n;
        }
        let albedo = material.albedo
            * material
                .texture
                .as_ref()
                .map_or(Vec3::ONE, |t| t.sample(self.bvh.hit_uv(hit)));
        let x = o + d * hit.t + ng * self.eps;
        let first = lit.len();
        self.direct.samples(x, n, &mut path.rng, lit);
        vertices.push(Vertex {
            path: index,
            samples: first..lit.len(),
            albedo,
            throughput: (bounce > 0).then_some(path.throughput),
        });
        // Bounce.
        if bounce >= 2 {
            let q = path.throughput.max_element().min(0.95);
            if path.rng.next_f32() >= q {
                return false;
            }
            path.throughput /= q;
        }
        path.throughput *= albedo;
        if path.throughput.max_element() <= 0.0 {
            return false;
        }
        let (t, b) = basis(n);
        let l = cosine_hemisphere(path.rng.next_f32(), path.rng.next_f32());
        path.d = (t * l.x + b * l.y + n * l.z).normalize();
        path.o = x;
        true
    }
}

/// Paths of one row traced together: whole pixels, at least one.
const PATHS_PER_BATCH: usize = 4096;

/// A path vertex's next-event estimate, waiting on its shadow rays: reflected radiance
/// `albedo / π × Σ lit terms`, added to the path's direct light (the first vertex) or,
/// times the path's throughput there, to its indirect light.
struct Vertex {
    path: usize,
    /// Its terms in the bounce's `lit`.
    samples: std::ops::Range<usize>,
    albedo: Vec3,
    /// The path's throughput at the vertex; `None` at the first.
    throughput: Option<Vec3>,
}

impl Vertex {
    /// Adds the estimate to `path`, given `e`, the irradiance of the terms whose shadow rays
    /// are clear.
    fn add(&self, path: &mut Path, e: Vec3) {
        let nee = self.albedo / std::f32::consts::PI * e;
        match self.throughput {
            None => path.direct += nee,
            Some(t) => path.indirect += t * nee,
        }
    }
}

/// One camera path in flight.
struct Path {
    o: Vec3,
    d: Vec3,
    throughput: Vec3,
    direct: Vec3,
    indirect: Vec3,
    rng: Rng,
    /// Pixel column.
    x: usize,
}

/// Renders `spp` samples per pixel in one go.
pub fn render(
    scene: &Scene,
    bvh: &SceneBvh,
    settings: RenderSettings,
    spp: u32,
) -> ReferenceImages {
    let r = ReferenceRenderer::new(scene, bvh, settings);
    let mut images = ReferenceImages::new(settings.width, settings.height);
    r.render_pass(&mut images, 0, spp);
    images
}

#[cfg(test)]
mod tests;
