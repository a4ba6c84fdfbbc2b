//! Direct light at a surface point: one emissive-triangle sample chosen by power (uniform on
//! the triangle) plus every punctual and directional light, with ray-traced shadows. The
//! reference tracer's next-event estimation and the light-map gatherer's texture-space
//! direct light both call it, so the two agree on what "direct" means.

use cloudlight_scenes::{LightState, Scene};
use glam::Vec3;

use crate::bvh::{RayQuery, SceneBvh};
use crate::sampling::{Rng, uniform_triangle};

/// Emissive triangles of a BVH, ready for power-proportional sampling.
struct Emitters {
    triangles: Vec<u32>,
    cdf: Vec<f32>,
    total: f32,
}

impl Emitters {
    fn new(scene: &Scene, bvh: &SceneBvh) -> Self {
        let mut triangles = Vec::new();
        let mut cdf = Vec::new();
        let mut total = 0.0;
        for (i, t) in bvh.triangles().iter().enumerate() {
            let m = &scene.materials[t.material as usize];
            let area = 0.5 * (t.v[1] - t.v[0]).cross(t.v[2] - t.v[0]).length();
            let power = m.emission.element_sum() * area;
            if power > 0.0 && area.is_finite() {
                total += power;
                triangles.push(i as u32);
                cdf.push(total);
            }
        }
        Emitters {
            triangles,
            cdf,
            total,
        }
    }

    /// A triangle and the probability of having picked it.
    fn pick(&self, u: f32) -> Option<(u32, f32)> {
        if self.triangles.is_empty() {
            return None;
        }
        let x = u * self.total;
        let i = self
            .cdf
            .partition_point(|c| *c <= x)
            .min(self.triangles.len() - 1);
        let lo = if i == 0 { 0.0 } else { self.cdf[i - 1] };
        Some((self.triangles[i], (self.cdf[i] - lo) / self.total))
    }
}

/// The lights of one scene at one time, ready to shade points.
pub struct DirectLight<'a> {
    scene: &'a Scene,
    bvh: &'a SceneBvh,
    emitters: Emitters,
    lights: Vec<LightState>,
    eps: f32,
}

impl<'a> DirectLight<'a> {
    /// The lights of `scene` at `t_s`, whose BVH at that time is `bvh`.
    pub fn new(scene: &'a Scene, bvh: &'a SceneBvh, t_s: f64) -> Self {
        let (lo, hi) = bvh.bounds();
        let extent = (hi - lo).length();
        DirectLight {
            scene,
            bvh,
            emitters: Emitters::new(scene, bvh),
            lights: scene.lights.iter().map(|l| l.at(t_s)).collect(),
            eps: if extent.is_finite() && extent > 0.0 {
                extent * 1e-5
            } else {
                1e-5
            },
        }
    }

    /// The box (lower, upper corner, meters) around the emissive triangles; inverted
    /// (lower > upper) when there are none.
    pub fn emitter_box(&self) -> (Vec3, Vec3) {
        let tris = self.bvh.triangles();
        self.emitters
            .triangles
            .iter()
            .flat_map(|&t| tris[t as usize].v)
            .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), v| {
                (lo.min(v), hi.max(v))
            })
    }

    /// How far off a surface a ray starts, meters (1e-5 of the scene's diagonal).
    pub fn eps(&self) -> f32 {
        self.eps
    }

    /// Whether anything emits (emissive triangles or lights).
    pub fn any(&self) -> bool {
        !self.emitters.triangles.is_empty() || !self.lights.is_empty()
    }

    /// Irradiance E at `x` (unit normal `n`, W·m⁻² per channel) from one emitter sample and
    /// every punctual and directional light, with ray-traced shadows (unbiased).
    pub fn irradiance(&self, x: Vec3, n: Vec3, rng: &mut Rng) -> Vec3 {
        let mut lit = Vec::new();
        self.samples(x, n, rng, &mut lit);
        let blocked: Vec<bool> = lit
            .iter()
            .map(|s| self.bvh.occluded(s.ray.0, s.ray.1, s.ray.2))
            .collect();
        Self::sum_clear(&lit, &blocked)
    }

    /// Whether each term's shadow ray is blocked, `lit` being the terms of many points'
    /// estimates ([`Self::samples`]): the rays are cast together, light by light, since rays
    /// to one light from neighbouring points share their paths ([`SceneBvh::occluded_into`];
    /// measured on the reference render of city:250000, `--spp 16`, 640×360: 2.7-2.8 s one at
    /// a time, 2.3-2.5 s light by light, 2.7-3.4 s point by point).
    pub fn blocked(&self, lit: &[LightSample]) -> Vec<bool> {
        let mut order: Vec<usize> = (0..lit.len()).collect();
        order.sort_by_key(|&i| lit[i].light);
        let rays: Vec<RayQuery> = order.iter().map(|&i| lit[i].ray).collect();
        let mut sorted = vec![false; lit.len()];
        self.bvh.occluded_into(&rays, &mut sorted);
        let mut blocked = vec![false; lit.len()];
        for (&i, &b) in order.iter().zip(&sorted) {
            blocked[i] = b;
        }
        blocked
    }

    /// The sum of the terms `lit` whose shadow rays are clear (`blocked` as from
    /// [`Self::blocked`]), in order: one point's irradiance.
    pub fn sum_clear(lit: &[LightSample], blocked: &[bool]) -> Vec3 {
        lit.iter()
            .zip(blocked)
            .filter(|(_, b)| !**b)
            .fold(Vec3::ZERO, |e, (l, _)| e + l.e)
    }

    /// The terms of [`Self::irradiance`] at `x` that light it where their shadow rays are
    /// clear, appended to `out` in the order they are summed: for callers that cast many
    /// points' shadow rays together ([`SceneBvh::occluded_into`]). Draws the same random
    /// numbers as `irradiance`.
    pub fn samples(&self, x: Vec3, n: Vec3, rng: &mut Rng, out: &mut Vec<LightSample>) {
        let (u0, u1, u2) = (rng.next_f32(), rng.next_f32(), rng.next_f32());
        if let Some((ti, p_tri)) = self.emitters.pick(u0) {
            let t = &self.bvh.triangles()[ti as usize];
            let b = uniform_triangle(u1, u2);
            let y = t.v[0] * (1.0 - b.x - b.y) + t.v[1] * b.x + t.v[2] * b.y;
            let cross = (t.v[1] - t.v[0]).cross(t.v[2] - t.v[0]);
            let area = 0.5 * cross.length();
            let ny = cross / (2.0 * area);
            let to = y - x;
            let dist2 = to.length_squared();
            let w = to / dist2.sqrt();
            let (cx, cy) = (n.dot(w), -ny.dot(w));
            if cx > 0.0 && cy > 0.0 {
                let le = self.scene.materials[t.material as usize].emission;
                out.push(LightSample {
                    light: 0,
                    ray: (x, w, dist2.sqrt() * (1.0 - 1e-4)),
                    e: le * cx * cy / dist2 * area / p_tri,
                });
            }
        }
        for (k, l) in self.lights.iter().enumerate() {
            let sample = match *l {
                LightState::Point {
                    position,
                    intensity,
                } => self.punctual(x, n, position, intensity, None),
                LightState::Spot {
                    position,
                    direction,
                    cos_cone,
                    intensity,
                } => self.punctual(x, n, position, intensity, Some((direction, cos_cone))),
                LightState::Surface {
                    position,
                    normal,
                    intensity,
                } => {
                    let cos_light = (x - position).normalize_or_zero().dot(normal).max(0.0);
                    self.punctual(x, n, position, intensity * cos_light, None)
                }
                LightState::Directional {
                    direction,
                    irradiance,
                } => {
                    let w = -direction;
                    let c = n.dot(w);
                    (c > 0.0).then(|| ((x, w, f32::INFINITY), irradiance * c))
                }
            };
            out.extend(sample.map(|(ray, e)| LightSample {
                light: k as u32 + 1,
                ray,
                e,
            }));
        }
    }

    fn punctual(
        &self,
        x: Vec3,
        n: Vec3,
        p: Vec3,
        intensity: Vec3,
        cone: Option<(Vec3, f32)>,
    ) -> Option<(RayQuery, Vec3)> {
        let to = p - x;
        let dist2 = to.length_squared();
        let w = to / dist2.sqrt();
        let c = n.dot(w);
        if c <= 0.0 || cone.is_some_and(|(axis, cos_cone)| (-w).dot(axis) < cos_cone) {
            return None;
        }
        Some(((x, w, dist2.sqrt() * (1.0 - 1e-4)), intensity * c / dist2))
    }
}

/// One term of the direct irradiance at a point: what it adds where its shadow ray is clear.
#[derive(Clone, Copy, Debug)]
pub struct LightSample {
    /// Which light: 0 the emitter sample, `1 + i` the scene's light `i`.
    pub light: u32,
    /// The shadow ray: origin, unit direction, length.
    pub ray: RayQuery,
    /// Irradiance, W·m⁻² per channel.
    pub e: Vec3,
}
