//! The ray-casting benchmark behind `cloudlight bench rays`: BVH build time, and rays per
//! second for coherent camera rays (1280×720 primary rays) and incoherent diffuse-bounce
//! rays (cosine directions from those primary hits), per BVH layout and thread count.

use std::time::Instant;

use cloudlight_scenes::Scene;
use glam::Vec2;
use rayon::prelude::*;

use crate::bvh::{BvhKind, RayQuery, SceneBvh};
use crate::sampling::{Rng, basis, cosine_hemisphere};

/// One measured configuration.
#[derive(Clone, Debug, PartialEq)]
pub struct RayBenchRow {
    /// BVH layout.
    pub kind: BvhKind,
    /// Worker threads.
    pub threads: usize,
    /// BVH build time, seconds (obvhs core build).
    pub build_s: f64,
    /// Coherent camera rays, millions per second.
    pub coherent_mrays_s: f64,
    /// Incoherent diffuse-bounce rays, millions per second.
    pub incoherent_mrays_s: f64,
}

/// The camera rays of a 1280×720 view, and diffuse bounce rays from their hits.
pub fn make_rays(scene: &Scene, bvh: &SceneBvh) -> (Vec<RayQuery>, Vec<RayQuery>) {
    let (w, h) = (1280u32, 720u32);
    let camera = scene
        .cameras
        .first()
        .map(|c| c.at(0.0))
        .expect("the scene has a camera");
    let aspect = w as f32 / h as f32;
    let camera_rays: Vec<RayQuery> = (0..w * h)
        .map(|i| {
            let (x, y) = ((i % w) as f32 + 0.5, (i / w) as f32 + 0.5);
            let ndc = Vec2::new(x / w as f32 * 2.0 - 1.0, 1.0 - y / h as f32 * 2.0);
            (
                camera.position,
                camera.ray_direction(ndc, aspect),
                f32::INFINITY,
            )
        })
        .collect();
    let hits = bvh.closest_hits(&camera_rays);
    let bounce_rays = camera_rays
        .iter()
        .zip(&hits)
        .enumerate()
        .filter_map(|(i, (r, h))| {
            let h = h.as_ref()?;
            let mut n = bvh.geometric_normal(h.triangle);
            if n.dot(r.1) > 0.0 {
                n = -n;
            }
            let mut rng = Rng::new(1, i as u64);
            let (t, b) = basis(n);
            let l = cosine_hemisphere(rng.next_f32(), rng.next_f32());
            let p = r.0 + r.1 * h.t + n * 1e-4;
            Some((p, (t * l.x + b * l.y + n * l.z).normalize(), f32::INFINITY))
        })
        .collect();
    (camera_rays, bounce_rays)
}

fn rate(bvh: &SceneBvh, rays: &[RayQuery], rounds: usize) -> f64 {
    let mut best = f64::INFINITY;
    for _ in 0..rounds {
        let t = Instant::now();
        let hits = rays
            .par_iter()
            .filter(|&&(o, d, m)| bvh.closest_hit(o, d, m).is_some())
            .count();
        std::hint::black_box(hits);
        best = best.min(t.elapsed().as_secs_f64());
    }
    rays.len() as f64 / best / 1e6
}

/// Measures every layout at every thread count (best of `rounds` passes over the rays).
pub fn run(scene: &Scene, threads: &[usize], rounds: usize) -> Vec<RayBenchRow> {
    let mut rows = Vec::new();
    for kind in [BvhKind::Cwbvh, BvhKind::Bvh2] {
        let bvh = SceneBvh::at(scene, 0.0, kind);
        let (coherent, incoherent) = make_rays(scene, &bvh);
        for &n in threads {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(n.max(1))
                .build()
                .expect("a thread pool");
            let (c, i) = pool.install(|| {
                (
                    rate(&bvh, &coherent, rounds),
                    rate(&bvh, &incoherent, rounds),
                )
            });
            rows.push(RayBenchRow {
                kind,
                threads: n,
                build_s: bvh.build_time().as_secs_f64(),
                coherent_mrays_s: c,
                incoherent_mrays_s: i,
            });
        }
    }
    rows
}
