//! Ray casting against a scene's triangles at one scene time.
//!
//! Three layouts: obvhs' compressed wide BVH (CWBVH) and binary BVH2, each with obvhs'
//! traversal, and [`BvhKind::Wide`], the default: eight children per node, built here
//! top-down with the binned SAH and traversed with its own SIMD code ([`WideBvh`]), one ray
//! at a time or, for batches ([`SceneBvh::closest_hits_into`]), in streams of 64 rays of one
//! direction octant. `cloudlight bench rays` measures all three against Embree on the same
//! rays (city:250000, one thread, Mrays/s camera / bounce / random: BVH8 streams 38.5 / 24.6 /
//! 5.6, BVH8 one ray 10.4 / 11.0 / 6.1, obvhs BVH2 9.0 / 8.4 / 2.1, CWBVH 5.1 / 5.5 / 2.8;
//! Embree's best 71.1 / 22.1 / 8.3; builds 0.092 s against Embree MEDIUM's 0.063 s). When
//! objects move the BVH is rebuilt for the new time
//! ([`SceneBvh::at`]).
//!
//! Traversal runs in a normalized frame where the scene's bounding diagonal is 100 units:
//! CWBVH quantizes node boxes, and in absolute units a 0.5 mm scene lost hits (measured: 3%
//! darker images at 1e-3 scale) while a 10 km one lost precision. Hits are reported in
//! meters.

use std::time::Duration;

use cloudlight_scenes::{Scene, WorldTriangle};
use glam::{Vec2, Vec3, Vec3A};
use obvhs::BvhBuildParams;
use obvhs::bvh2::Bvh2;
use obvhs::cwbvh::CwBvh;
use obvhs::ray::{Ray, RayHit};
use obvhs::triangle::Triangle;
use rayon::prelude::*;

mod wide;

pub use wide::{Visits, WideBvh, WideHit, WideRay};

/// Which layout to build and traverse.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum BvhKind {
    /// obvhs' compressed wide BVH (8-wide nodes), obvhs' traversal.
    Cwbvh,
    /// obvhs' binary BVH, obvhs' traversal.
    Bvh2,
    /// Eight children per node, built and traversed here ([`WideBvh`]).
    #[default]
    Wide,
}

enum Tree {
    Cw(CwBvh),
    Bin(Bvh2),
    Wide(WideBvh),
}

/// A ray for batch queries: origin (m), unit direction, largest distance (m).
pub type RayQuery = (Vec3, Vec3, f32);

/// A ray hit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Distance along the (unit) ray direction, meters.
    pub t: f32,
    /// Index into [`SceneBvh::triangles`].
    pub triangle: u32,
    /// Barycentric coordinates (u, v) of the hit (weights of vertices 1 and 2).
    pub uv: Vec2,
}

/// A BVH over a scene's world-space triangles at one scene time.
pub struct SceneBvh {
    triangles: Vec<WorldTriangle>,
    rt: Vec<Triangle>,
    /// bvh_from_world scale.
    scale: f32,
    tree: Tree,
    build_time: Duration,
    bounds: (Vec3, Vec3),
    area_m2: f32,
}

fn rt_triangle(t: &WorldTriangle, scale: f32) -> Triangle {
    Triangle {
        v0: (t.v[0] * scale).into(),
        v1: (t.v[1] * scale).into(),
        v2: (t.v[2] * scale).into(),
    }
}

/// Barycentric weights (of vertices 1 and 2) where `ray` crosses `t`'s plane (Möller–
/// Trumbore). obvhs 0.4's `compute_barycentric` divides by the *unit* normal, so its weights
/// are scaled by twice the triangle's area (measured: texture and light-map lookups landed
/// off their triangles); this is the exact form.
fn barycentric(t: &Triangle, ray: &Ray) -> Vec2 {
    let (e1, e2) = (t.v1 - t.v0, t.v2 - t.v0);
    let p = ray.direction.cross(e2);
    let det = e1.dot(p);
    if det.abs() < f32::MIN_POSITIVE {
        return Vec2::ZERO;
    }
    let s = ray.origin - t.v0;
    let q = s.cross(e1);
    let uv = Vec2::new(s.dot(p), ray.direction.dot(q)) / det;
    uv.clamp(Vec2::ZERO, Vec2::ONE)
}

/// Units of the normalized frame across the scene's bounding diagonal.
const NORMALIZED_EXTENT: f32 = 100.0;

impl SceneBvh {
    /// Builds over `triangles`.
    pub fn build(triangles: Vec<WorldTriangle>, kind: BvhKind) -> Self {
        let mut lo = Vec3::splat(f32::INFINITY);
        let mut hi = Vec3::splat(f32::NEG_INFINITY);
        for t in &triangles {
            for v in t.v.iter().filter(|v| v.is_finite()) {
                lo = lo.min(*v);
                hi = hi.max(*v);
            }
        }
        let extent = (hi - lo).length();
        let scale = if extent.is_finite() && extent > 0.0 {
            NORMALIZED_EXTENT / extent
        } else {
            1.0
        };
        let rt: Vec<Triangle> = triangles.iter().map(|t| rt_triangle(t, scale)).collect();
        let mut build_time = Duration::ZERO;
        let tree = if rt.is_empty() {
            Tree::Bin(Bvh2::default())
        } else {
            match kind {
                BvhKind::Cwbvh => Tree::Cw(obvhs::cwbvh::builder::build_cwbvh_from_tris(
                    &rt,
                    BvhBuildParams::medium_build(),
                    &mut build_time,
                )),
                BvhKind::Bvh2 => Tree::Bin(obvhs::bvh2::builder::build_bvh2_from_tris(
                    &rt,
                    BvhBuildParams::medium_build(),
                    &mut build_time,
                )),
                BvhKind::Wide => {
                    let t = std::time::Instant::now();
                    let w = WideBvh::build(&rt);
                    build_time = t.elapsed();
                    Tree::Wide(w)
                }
            }
        };
        let area_m2 = triangles
            .iter()
            .map(|t| 0.5 * (t.v[1] - t.v[0]).cross(t.v[2] - t.v[0]).length())
            .filter(|a| a.is_finite())
            .sum();
        SceneBvh {
            triangles,
            rt,
            scale,
            tree,
            build_time,
            bounds: (lo, hi),
            area_m2,
        }
    }

    /// Bounds of the (finite) triangle vertices, meters (min, max); infinite when empty.
    pub fn bounds(&self) -> (Vec3, Vec3) {
        self.bounds
    }

    /// Total area of the (finite) triangles, m² (one side).
    pub fn surface_area_m2(&self) -> f32 {
        self.area_m2
    }

    /// The scene's BVH at scene time `t_s`.
    pub fn at(scene: &Scene, t_s: f64, kind: BvhKind) -> Self {
        Self::build(scene.triangles_at(t_s), kind)
    }

    /// The triangles, in the order hits refer to.
    pub fn triangles(&self) -> &[WorldTriangle] {
        &self.triangles
    }

    /// Core build time: obvhs' own figure, or the wide BVH's build from the triangles.
    pub fn build_time(&self) -> Duration {
        self.build_time
    }

    fn ray(&self, origin: Vec3, dir: Vec3, t_max: f32) -> Ray {
        Ray::new(
            Vec3A::from(origin * self.scale),
            Vec3A::from(dir),
            0.0,
            t_max * self.scale,
        )
    }

    fn hit_from(&self, h: WideHit) -> Hit {
        Hit {
            t: h.t / self.scale,
            triangle: h.triangle,
            uv: Vec2::from(h.uv),
        }
    }

    fn wide_ray(&self, origin: Vec3, dir: Vec3, t_max: f32) -> WideRay {
        WideRay {
            o: (origin * self.scale).to_array(),
            d: dir.to_array(),
            t: (0.0, t_max * self.scale),
        }
    }

    /// The closest hit along `dir` (unit) from `origin` within `t_max`.
    pub fn closest_hit(&self, origin: Vec3, dir: Vec3, t_max: f32) -> Option<Hit> {
        if let Tree::Wide(w) = &self.tree {
            let h = w.intersect(&self.wide_ray(origin, dir, t_max), false)?;
            return Some(self.hit_from(h));
        }
        let ray = self.ray(origin, dir, t_max);
        let mut hit = RayHit::none();
        let found = match &self.tree {
            Tree::Cw(b) => b.ray_traverse(ray, &mut hit, |r, id| {
                self.rt[b.primitive_indices[id] as usize].intersect(r)
            }),
            Tree::Bin(b) if b.nodes.is_empty() => false,
            Tree::Bin(b) => b.ray_traverse(ray, &mut hit, |r, id| {
                self.rt[b.primitive_indices[id] as usize].intersect(r)
            }),
            Tree::Wide(_) => unreachable!("handled above"),
        };
        if !found {
            return None;
        }
        let triangle = match &self.tree {
            Tree::Cw(b) => b.primitive_indices[hit.primitive_id as usize],
            Tree::Bin(b) => b.primitive_indices[hit.primitive_id as usize],
            Tree::Wide(_) => unreachable!("handled above"),
        };
        let uv = barycentric(&self.rt[triangle as usize], &ray);
        Some(Hit {
            t: hit.t / self.scale,
            triangle,
            uv,
        })
    }

    /// Whether anything lies along `dir` from `origin` closer than `t_max` (shadow rays).
    pub fn occluded(&self, origin: Vec3, dir: Vec3, t_max: f32) -> bool {
        let ray = self.ray(origin, dir, t_max);
        match &self.tree {
            Tree::Cw(b) => !b.ray_traverse_miss(ray, |r, id| {
                self.rt[b.primitive_indices[id] as usize].intersect(r)
            }),
            Tree::Bin(b) if b.nodes.is_empty() => false,
            Tree::Bin(b) => !b.ray_traverse_miss(ray, |r, id| {
                self.rt[b.primitive_indices[id] as usize].intersect(r)
            }),
            Tree::Wide(w) => w
                .intersect(&self.wide_ray(origin, dir, t_max), true)
                .is_some(),
        }
    }

    /// The wide BVH, when that is the layout.
    pub fn wide(&self) -> Option<&WideBvh> {
        match &self.tree {
            Tree::Wide(w) => Some(w),
            _ => None,
        }
    }

    /// The ray of [`Self::closest_hit`] in the wide BVH's frame, for [`WideBvh`]'s counters.
    pub fn wide_ray_of(&self, origin: Vec3, dir: Vec3, t_max: f32) -> WideRay {
        self.wide_ray(origin, dir, t_max)
    }

    /// Closest hits of `rays` into `out` (as long), on this thread. The BVH8 traverses
    /// groups of 64 (`STREAM`) rays together ([`WideBvh::intersect_stream`]): the rays
    /// of each direction octant, in the order given; order rays so that neighbours share
    /// their paths.
    pub fn closest_hits_into(&self, rays: &[RayQuery], out: &mut [Option<Hit>]) {
        let Tree::Wide(w) = &self.tree else {
            for (o, &(p, d, t)) in out.iter_mut().zip(rays) {
                *o = self.closest_hit(p, d, t);
            }
            return;
        };
        // Streams do not span direction octants (a one-octant stream culls with a frustum
        // and tests eight rays per step).
        let octants: Vec<u8> = rays
            .iter()
            .map(|(_, d, _)| {
                let neg = d.to_array().map(|c| u8::from(c.is_sign_negative()));
                neg[0] | neg[1] << 1 | neg[2] << 2
            })
            .collect();
        let runs = 1 + octants.windows(2).filter(|p| p[0] != p[1]).count();
        let mut wide_rays = Vec::with_capacity(rays.len());
        let mut hits = vec![None; rays.len()];
        if runs * wide::STREAM <= 2 * rays.len() {
            // Long runs of one octant (camera rays, a batch's first segments): streams
            // over each run in place, no reordering (measured on city:250000's camera rays,
            // one thread, alternating binaries: 43.0-43.2 -> 45.5-46.7 Mrays/s).
            wide_rays.extend(rays.iter().map(|&(o, d, t)| self.wide_ray(o, d, t)));
            let mut at = 0;
            while at < rays.len() {
                let end = at
                    + octants[at..]
                        .iter()
                        .take_while(|&&k| k == octants[at])
                        .count();
                w.intersect_stream(&wide_rays[at..end], &mut hits[at..end]);
                at = end;
            }
            for (o, h) in out.iter_mut().zip(&hits) {
                *o = h.map(|h| self.hit_from(h));
            }
            return;
        }
        // Mixed octants: the rays by octant (a stable counting sort), then streams of
        // neighbours within each (measured on city:250000's bounce rays, one thread: 15-16
        // -> 21 Mrays/s).
        let mut start = [0usize; 9];
        for &k in &octants {
            start[usize::from(k) + 1] += 1;
        }
        for k in 0..8 {
            start[k + 1] += start[k];
        }
        let mut order = vec![0u32; rays.len()];
        let mut next = start;
        for (i, &k) in octants.iter().enumerate() {
            order[next[usize::from(k)]] = i as u32;
            next[usize::from(k)] += 1;
        }
        wide_rays.extend(order.iter().map(|&i| {
            let (o, d, t) = rays[i as usize];
            self.wide_ray(o, d, t)
        }));
        for k in 0..8 {
            let span = start[k]..start[k + 1];
            w.intersect_stream(&wide_rays[span.clone()], &mut hits[span]);
        }
        for (&i, h) in order.iter().zip(&hits) {
            out[i as usize] = h.map(|h| self.hit_from(h));
        }
    }

    /// Closest hits of many rays `(origin, unit direction, t_max)`, in parallel, in
    /// streams where neighbouring rays share their paths ([`Self::closest_hits_into`]).
    pub fn closest_hits(&self, rays: &[RayQuery]) -> Vec<Option<Hit>> {
        let mut out = vec![None; rays.len()];
        rays.par_chunks(16 * wide::STREAM)
            .zip(out.par_chunks_mut(16 * wide::STREAM))
            .for_each(|(r, o)| self.closest_hits_into(r, o));
        out
    }

    /// Occlusion of many rays, in parallel; the BVH8 takes them several at a time in turns
    /// ([`WideBvh::intersect_many`]).
    pub fn occluded_batch(&self, rays: &[RayQuery]) -> Vec<bool> {
        let mut out = vec![false; rays.len()];
        rays.par_chunks(16 * wide::STREAM)
            .zip(out.par_chunks_mut(16 * wide::STREAM))
            .for_each(|(r, o)| self.occluded_into(r, o));
        out
    }

    /// Occlusion of `rays` into `out` (as long), on this thread.
    pub fn occluded_into(&self, rays: &[RayQuery], out: &mut [bool]) {
        let Tree::Wide(w) = &self.tree else {
            for (o, &(p, d, t)) in out.iter_mut().zip(rays) {
                *o = self.occluded(p, d, t);
            }
            return;
        };
        let wide_rays: Vec<WideRay> = rays
            .iter()
            .map(|&(o, d, t)| self.wide_ray(o, d, t))
            .collect();
        let mut hits = vec![None; rays.len()];
        w.intersect_many(&wide_rays, true, &mut hits);
        for (o, h) in out.iter_mut().zip(hits) {
            *o = h.is_some();
        }
    }

    /// Interpolated shading normal at a hit (unit).
    pub fn shading_normal(&self, hit: &Hit) -> Vec3 {
        let t = &self.triangles[hit.triangle as usize];
        let w = Vec3::new(1.0 - hit.uv.x - hit.uv.y, hit.uv.x, hit.uv.y);
        (t.n[0] * w.x + t.n[1] * w.y + t.n[2] * w.z)
            .normalize_or(self.geometric_normal(hit.triangle))
    }

    /// Geometric normal of a triangle (unit, counter-clockwise front).
    pub fn geometric_normal(&self, triangle: u32) -> Vec3 {
        let t = &self.triangles[triangle as usize];
        (t.v[1] - t.v[0]).cross(t.v[2] - t.v[0]).normalize_or_zero()
    }

    /// Texture coordinates at a hit.
    pub fn hit_uv(&self, hit: &Hit) -> Vec2 {
        let t = &self.triangles[hit.triangle as usize];
        t.uv[0] * (1.0 - hit.uv.x - hit.uv.y) + t.uv[1] * hit.uv.x + t.uv[2] * hit.uv.y
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampling::Rng;

    fn brute_force(tris: &[WorldTriangle], o: Vec3, d: Vec3, t_max: f32) -> Option<(f32, u32)> {
        let ray = Ray::new(o.into(), d.into(), 0.0, t_max);
        let mut best: Option<(f32, u32)> = None;
        for (i, t) in tris.iter().enumerate() {
            let h = rt_triangle(t, 1.0).intersect(&ray);
            if h < t_max && best.is_none_or(|(b, _)| h < b) {
                best = Some((h, i as u32));
            }
        }
        best
    }

    fn agree_with_brute_force(scene: &Scene, kind: BvhKind, rays: usize) {
        agree_on_triangles(scene.triangles_at(0.0), scene.bounds_at(0.0), kind, rays);
    }

    fn agree_on_triangles(
        triangles: Vec<WorldTriangle>,
        bounds: (Vec3, Vec3),
        kind: BvhKind,
        rays: usize,
    ) {
        let bvh = SceneBvh::build(triangles, kind);
        // Origins inside the bounds, 1% away from the walls. A ray starting within
        // micrometers of a surface is the self-intersection case integrators avoid with an
        // origin offset, and CWBVH's quantized boxes may miss hits at t < 1e-4 there, so
        // rays whose first hit is closer than 1 mm are skipped.
        let (lo, hi) = bounds;
        let (lo, hi) = (lo + (hi - lo) * 0.01, hi - (hi - lo) * 0.01);
        // A millimeter of the scene's diagonal: see above.
        let near = 1e-3 * (hi - lo).length() / 1.7;
        let mut rng = Rng::new(7, 0);
        let mut cast = Vec::with_capacity(rays);
        for i in 0..rays {
            let o = lo + (hi - lo) * Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32());
            let d = crate::sampling::uniform_sphere(rng.next_f32(), rng.next_f32());
            cast.push((o, d, f32::INFINITY));
            let expect = brute_force(bvh.triangles(), o, d, f32::INFINITY);
            if expect.is_some_and(|(t, _)| t < near) {
                continue; // origin within a millimeter of a surface: see above
            }
            let got = bvh.closest_hit(o, d, f32::INFINITY);
            match (expect, got) {
                (None, None) => {}
                (Some((t, _)), Some(h)) => assert!(
                    (t - h.t).abs() <= 1e-4 * t.max(near * 1e3),
                    "{kind:?} ray {i}: {t} vs {}",
                    h.t
                ),
                (e, g) => panic!("ray {i} from {o} along {d}: brute force {e:?}, BVH {g:?}"),
            }
            if let Some((t, _)) = expect {
                assert!(
                    bvh.occluded(o, d, t * 1.001),
                    "{kind:?} ray {i}: hit at {t} not seen as occluding"
                );
                assert!(
                    !bvh.occluded(o, d, t * 0.999),
                    "{kind:?} ray {i}: occluded before the hit at {t}"
                );
            }
        }
        // The batch path (streams for the BVH8) answers the same.
        batch_agrees_with_single(&bvh, &cast);
    }

    const KINDS: [BvhKind; 3] = [BvhKind::Cwbvh, BvhKind::Bvh2, BvhKind::Wide];

    #[test]
    fn every_layout_agrees_with_brute_force_on_the_cornell_box() {
        let s = cloudlight_scenes::builtin("cornell").unwrap();
        for kind in KINDS {
            agree_with_brute_force(&s, kind, 4000);
        }
    }

    #[test]
    fn every_layout_agrees_with_brute_force_on_a_city() {
        let s = cloudlight_scenes::builtin("city:20000").unwrap();
        for kind in KINDS {
            agree_with_brute_force(&s, kind, 300);
        }
    }

    #[test]
    fn a_half_millimeter_scene_and_a_ten_kilometer_one_keep_their_hits() {
        // The Cornell box (0.55 m across) scaled to 0.5 mm and to 10 km.
        let s = cloudlight_scenes::builtin("cornell").unwrap();
        let (lo, hi) = s.bounds_at(0.0);
        for size in [5e-4, 1e4] {
            let k = size / (hi - lo).max_element();
            let tris: Vec<WorldTriangle> = s
                .triangles_at(0.0)
                .into_iter()
                .map(|mut t| {
                    t.v = t.v.map(|v| v * k);
                    t
                })
                .collect();
            for kind in KINDS {
                agree_on_triangles(tris.clone(), (lo * k, hi * k), kind, 1500);
            }
        }
    }

    /// Batch results agree with one ray at a time: the same distance, and the same triangle
    /// unless two are hit at that distance.
    fn batch_agrees_with_single(bvh: &SceneBvh, rays: &[RayQuery]) {
        let mut batch = vec![None; rays.len()];
        bvh.closest_hits_into(rays, &mut batch);
        for (i, (&(o, d, t), b)) in rays.iter().zip(&batch).enumerate() {
            let one = bvh.closest_hit(o, d, t);
            match (one, b) {
                (None, None) => {}
                (Some(a), Some(b)) => {
                    assert_eq!(a.t, b.t, "ray {i}");
                    assert!(a.triangle == b.triangle || a.t == b.t, "ray {i}");
                    assert!((a.uv - b.uv).abs().max_element() < 1e-6 || a.triangle != b.triangle);
                }
                (a, b) => panic!("ray {i} from {o} along {d}: one ray {a:?}, batch {b:?}"),
            }
        }
        // Shadow rays: the batch sees what single rays see.
        let shadow: Vec<RayQuery> = rays
            .iter()
            .zip(&batch)
            .enumerate()
            .map(|(i, (&(o, d, t), b))| match b {
                // Stop half the hit rays just short of their hit, half just past it.
                Some(h) if i % 2 == 0 => (o, d, h.t * 0.999),
                Some(h) => (o, d, h.t * 1.001),
                None => (o, d, t),
            })
            .collect();
        let occluded = bvh.occluded_batch(&shadow);
        for (i, (&(o, d, t), &b)) in shadow.iter().zip(&occluded).enumerate() {
            assert_eq!(bvh.occluded(o, d, t), b, "shadow ray {i}");
        }
    }

    #[test]
    fn rays_taking_turns_agree_with_one_at_a_time() {
        // Random rays (spread: the BVH8 takes them in turns) in runs shorter and longer
        // than the turns, with t_max stopping some short.
        let s = cloudlight_scenes::builtin("city:20000").unwrap();
        let bvh = SceneBvh::at(&s, 0.0, BvhKind::Wide);
        assert!(
            bvh.wide().unwrap().takes_turns(),
            "a tree too small to take turns"
        );
        let cornell = SceneBvh::at(
            &cloudlight_scenes::builtin("cornell").unwrap(),
            0.0,
            BvhKind::Wide,
        );
        assert!(!cornell.wide().unwrap().takes_turns());
        let (lo, hi) = bvh.bounds();
        let mut rng = Rng::new(5, 0);
        let rays: Vec<RayQuery> = (0..300)
            .map(|i| {
                let o = lo + (hi - lo) * Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32());
                let d = crate::sampling::uniform_sphere(rng.next_f32(), rng.next_f32());
                (o, d, if i % 3 == 0 { 20.0 } else { f32::INFINITY })
            })
            .collect();
        let mut hits = 0;
        for n in [1, 2, 7, 8, 9, 15, 16, 17, 33, 300] {
            batch_agrees_with_single(&bvh, &rays[..n]);
            let mut occluded = vec![false; n];
            bvh.occluded_into(&rays[..n], &mut occluded);
            for (i, (&(o, d, t), &b)) in rays.iter().zip(&occluded).enumerate() {
                assert_eq!(bvh.occluded(o, d, t), b, "{n} rays: ray {i}");
                hits += usize::from(b);
            }
        }
        assert!(hits > 50, "{hits} occluded: the rays must hit something");
    }

    #[test]
    fn streams_agree_with_single_rays_and_brute_force() {
        let s = cloudlight_scenes::builtin("city:20000").unwrap();
        let bvh = SceneBvh::at(&s, 0.0, BvhKind::Wide);
        let mut rng = Rng::new(11, 0);
        let (lo, hi) = bvh.bounds();
        // Coherent: a camera's rays in rows; incoherent: random; mixed lengths, a partial
        // last stream, and t_max that stops some rays short.
        let camera = s.cameras[0].at(0.0);
        let mut rays: Vec<RayQuery> = (0..64 * 40 + 13)
            .map(|i| {
                let (x, y) = ((i % 80) as f32 / 80.0, (i / 80) as f32 / 40.0);
                let ndc = glam::Vec2::new(x * 2.0 - 1.0, 1.0 - y * 2.0);
                let t_max = if i % 7 == 0 { 30.0 } else { f32::INFINITY };
                (
                    camera.position,
                    camera.ray_direction(ndc, 16.0 / 9.0),
                    t_max,
                )
            })
            .collect();
        rays.extend((0..2000).map(|_| {
            let o = lo + (hi - lo) * Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32());
            let d = crate::sampling::uniform_sphere(rng.next_f32(), rng.next_f32());
            (o, d, f32::INFINITY)
        }));
        // The camera's rays alone come in long runs of one octant (streamed in place), with
        // the random ones mixed (reordered by octant first).
        batch_agrees_with_single(&bvh, &rays[..64 * 40 + 13]);
        batch_agrees_with_single(&bvh, &rays);
        let hits = rays
            .iter()
            .filter(|r| bvh.closest_hit(r.0, r.1, r.2).is_some())
            .count();
        assert!(
            hits > rays.len() / 4 && hits < rays.len(),
            "{hits} of {}",
            rays.len()
        );
        // Brute force on a sample (single rays agree with it in the tests above).
        for (i, &(o, d, t)) in rays.iter().enumerate().step_by(23) {
            let mut one = vec![None];
            bvh.closest_hits_into(&[(o, d, t)], &mut one);
            let expect = brute_force(bvh.triangles(), o, d, t);
            assert_eq!(
                one[0].map(|h| h.triangle).is_some(),
                expect.is_some(),
                "ray {i}"
            );
        }
        // Other layouts answer batches one ray at a time.
        let bin = SceneBvh::at(&s, 0.0, BvhKind::Bvh2);
        batch_agrees_with_single(&bin, &rays[..500]);
    }

    #[test]
    fn the_wide_bvh_holds_every_triangle_once_and_visits_less_than_its_sah_bound() {
        let s = cloudlight_scenes::builtin("city:20000").unwrap();
        let bvh = SceneBvh::at(&s, 0.0, BvhKind::Wide);
        let w = bvh.wide().unwrap();
        let (nodes, blocks) = w.size();
        assert!(
            nodes > 0 && blocks * 4 >= bvh.triangles().len(),
            "{nodes} {blocks}"
        );
        let mut ids = w.triangle_ids();
        ids.sort_unstable();
        let all: Vec<u32> = (0..bvh.triangles().len() as u32).collect();
        assert!(ids == all, "every triangle exactly once");
        // Random rays through the root box: with early exit, fewer visits than the SAH's
        // expectation without it (a broken tree or traversal visits more).
        let (lo, hi) = bvh.bounds();
        let mut rng = Rng::new(5, 0);
        let mut v = Visits::default();
        let n = 2000;
        for _ in 0..n {
            let o = lo + (hi - lo) * Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32());
            let d = crate::sampling::uniform_sphere(rng.next_f32(), rng.next_f32());
            w.intersect_counted(&bvh.wide_ray_of(o, d, f32::INFINITY), &mut v);
        }
        let (sah_nodes, sah_blocks) = w.sah_visits();
        let per_ray = (v.nodes as f64 / n as f64, v.blocks as f64 / n as f64);
        assert!(
            per_ray.0 >= 1.0 && per_ray.0 < sah_nodes,
            "{per_ray:?} vs {sah_nodes}"
        );
        assert!(per_ray.1 < sah_blocks, "{per_ray:?} vs {sah_blocks}");
    }

    #[test]
    fn hit_barycentrics_reproduce_the_hit_point() {
        // Texture, normal and light-map lookups interpolate with these weights: the point
        // they give must be where the ray hit.
        let scene = cloudlight_scenes::builtin("cornell").unwrap();
        let bvh = SceneBvh::at(&scene, 0.0, BvhKind::Bvh2);
        let mut rng = Rng::new(3, 4);
        let mut checked = 0;
        for _ in 0..500 {
            let o = Vec3::new(0.278, 0.274, 0.28)
                + (Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) - 0.5) * 0.2;
            let d = crate::sampling::uniform_sphere(rng.next_f32(), rng.next_f32());
            let Some(h) = bvh.closest_hit(o, d, f32::INFINITY) else {
                continue;
            };
            let t = &bvh.triangles()[h.triangle as usize];
            let p = t.v[0] * (1.0 - h.uv.x - h.uv.y) + t.v[1] * h.uv.x + t.v[2] * h.uv.y;
            assert!(p.distance(o + d * h.t) < 1e-4, "{p} vs {}", o + d * h.t);
            checked += 1;
        }
        assert!(checked > 400);
    }

    #[test]
    fn degenerate_triangles_are_harmless() {
        let z = Vec3::ZERO;
        let tri = |v: [Vec3; 3]| WorldTriangle {
            v,
            n: [Vec3::Y; 3],
            uv: [Vec2::ZERO; 3],
            lightmap_uv: [Vec2::ZERO; 3],
            material: 0,
        };
        let tris = vec![
            tri([z, z, z]),
            tri([z, Vec3::X, Vec3::X * 2.0]),
            tri([
                Vec3::new(-1.0, 1.0, -1.0),
                Vec3::new(-1.0, 1.0, 1.0),
                Vec3::new(1.0, 1.0, 0.0),
            ]),
        ];
        for kind in KINDS {
            let bvh = SceneBvh::build(tris.clone(), kind);
            let h = bvh
                .closest_hit(Vec3::new(0.0, 0.0, 0.0), Vec3::Y, 10.0)
                .expect("hits the real triangle");
            assert_eq!(h.triangle, 2);
            assert!((h.t - 1.0).abs() < 1e-6);
            assert!(
                bvh.closest_hit(Vec3::new(5.0, -1.0, 0.0), Vec3::Y, 10.0)
                    .is_none()
            );
        }
        let empty = SceneBvh::build(Vec::new(), BvhKind::default());
        assert!(empty.closest_hit(Vec3::ZERO, Vec3::Y, 1.0).is_none());
        assert!(!empty.occluded(Vec3::ZERO, Vec3::Y, 1.0));
    }
}
