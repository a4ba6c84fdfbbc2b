//! The ray-casting benchmark behind `cloudlight bench rays`: BVH build time, and rays per
//! second on three ray sets (1280×720 camera rays, a cosine bounce from each of their hits,
//! 1M random rays inside the bounds), per backend and thread count, with the hits of every
//! backend checked against a reference backend's in the same run. `--against-embree` adds
//! Embree 3 on the same triangles and rays: one ray at a time, 8-wide packets and streams.

use std::time::{Duration, Instant};

use cloudlight_scenes::Scene;
use glam::{Vec2, Vec3};
use rayon::prelude::*;

use crate::bvh::{BvhKind, RayQuery, SceneBvh};
use crate::embree::{Embree, EmbreeScene};
use crate::sampling::{Rng, basis, cosine_hemisphere, uniform_sphere};

/// Rays handed to a worker at once (a multiple of 8, Embree's packet width).
const CHUNK: usize = 1024;

/// A way of casting rays.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Backend {
    /// The project's [`SceneBvh`] in this layout, one ray at a time.
    Obvhs(BvhKind),
    /// The project's BVH8, consecutive groups of 64 rays traversed together.
    OursStreams,
    /// Embree 3, `rtcIntersect1`.
    EmbreeOne,
    /// Embree 3, `rtcIntersect8` over consecutive groups of eight rays.
    EmbreePackets,
    /// Embree 3, `rtcIntersect1M` over chunks of rays (coherent flag on camera rays).
    EmbreeStream,
}

impl Backend {
    /// Short name for tables.
    pub fn name(self) -> &'static str {
        match self {
            Backend::Obvhs(BvhKind::Bvh2) => "obvhs BVH2",
            Backend::Obvhs(BvhKind::Cwbvh) => "obvhs CWBVH",
            Backend::Obvhs(BvhKind::Wide) => "BVH8 (ours)",
            Backend::OursStreams => "BVH8 streams (ours)",
            Backend::EmbreeOne => "Embree 1 ray",
            Backend::EmbreePackets => "Embree packets of 8",
            Backend::EmbreeStream => "Embree streams",
        }
    }

    /// Whether this is the yardstick rather than the project's own code.
    pub fn is_embree(self) -> bool {
        !matches!(self, Backend::Obvhs(_) | Backend::OursStreams)
    }
}

/// One ray set.
pub struct RaySet {
    /// `camera`, `bounce` or `random`.
    pub name: &'static str,
    /// Whether neighbouring rays are coherent (the target is then 0.5× Embree, else 0.8×).
    pub coherent: bool,
    /// The rays, meters.
    pub rays: Vec<RayQuery>,
}

/// One measured configuration.
#[derive(Clone, Debug, PartialEq)]
pub struct RayBenchRow {
    /// How the rays were cast.
    pub backend: Backend,
    /// Which ray set.
    pub rays: &'static str,
    /// Worker threads.
    pub threads: usize,
    /// Median of the timed passes, million rays per second.
    pub mrays_s: f64,
    /// Fastest and slowest pass, million rays per second.
    pub range: (f64, f64),
    /// Fraction of rays whose result matches the reference backend's (both miss, or both hit
    /// with t within 1e-4 relative).
    pub agreement: f64,
}

/// A build of one backend at one thread count.
#[derive(Clone, Debug, PartialEq)]
pub struct BuildRow {
    /// A backend's name or `Embree MEDIUM`.
    pub what: &'static str,
    /// Build threads.
    pub threads: usize,
    /// Seconds.
    pub seconds: f64,
}

/// What a run measured.
pub struct RayBenchReport {
    /// Ray counts per set.
    pub sets: Vec<(&'static str, usize)>,
    /// Builds.
    pub builds: Vec<BuildRow>,
    /// Casting rates.
    pub rows: Vec<RayBenchRow>,
    /// Which backend the agreement is measured against.
    pub reference: Backend,
    /// Where Embree was asked for but could not be used: why.
    pub embree_unavailable: Option<String>,
    /// Work per ray of the BVH8 per ray set.
    pub work: Vec<WorkRow>,
    /// The BVH8's SAH terms: expected inner-node and leaf-block visits of a line through the
    /// root box, without early exit; and its size (inner nodes, leaf blocks).
    pub sah: ((f64, f64), (usize, usize)),
}

/// Work one ray set asks of the BVH8, per ray.
#[derive(Clone, Debug, PartialEq)]
pub struct WorkRow {
    /// Ray set.
    pub rays: &'static str,
    /// Inner nodes visited (eight box tests each), mean per ray.
    pub nodes: f64,
    /// Blocks of four triangles tested, mean per ray.
    pub blocks: f64,
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

/// `n` rays from uniform points inside `bounds` in uniform directions, unbounded.
pub fn random_rays(bounds: (Vec3, Vec3), n: usize) -> Vec<RayQuery> {
    let (lo, hi) = bounds;
    let mut rng = Rng::new(2, 0);
    (0..n)
        .map(|_| {
            let o = lo + (hi - lo) * Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32());
            let d = uniform_sphere(rng.next_f32(), rng.next_f32());
            (o, d, f32::INFINITY)
        })
        .collect()
}

/// The three ray sets of the benchmark.
pub fn ray_sets(scene: &Scene, bvh: &SceneBvh) -> Vec<RaySet> {
    let (camera, bounce) = make_rays(scene, bvh);
    vec![
        RaySet {
            name: "camera",
            coherent: true,
            rays: camera,
        },
        RaySet {
            name: "bounce",
            coherent: false,
            rays: bounce,
        },
        RaySet {
            name: "random",
            coherent: false,
            rays: random_rays(bvh.bounds(), 1_000_000),
        },
    ]
}

type Hits = Vec<Option<(f32, u32)>>;

/// A built backend that can cast a chunk of rays.
enum Caster<'a> {
    Obvhs(&'a SceneBvh),
    Streams(&'a SceneBvh),
    Embree(&'a EmbreeScene<'a>, Backend),
}

impl Caster<'_> {
    fn cast(&self, rays: &[RayQuery], coherent: bool, out: &mut [Option<(f32, u32)>]) {
        match self {
            Caster::Obvhs(b) => {
                for (o, &(p, d, t)) in out.iter_mut().zip(rays) {
                    *o = b.closest_hit(p, d, t).map(|h| (h.t, h.triangle));
                }
            }
            Caster::Streams(b) => {
                let mut hits = vec![None; rays.len()];
                b.closest_hits_into(rays, &mut hits);
                for (o, h) in out.iter_mut().zip(hits) {
                    *o = h.map(|h| (h.t, h.triangle));
                }
            }
            Caster::Embree(e, Backend::EmbreeOne) => {
                for (o, r) in out.iter_mut().zip(rays) {
                    *o = e.closest_hit(r);
                }
            }
            Caster::Embree(e, Backend::EmbreePackets) => e.closest_hits_packets(rays, out),
            Caster::Embree(e, _) => e.closest_hits_stream(rays, coherent, out),
        }
    }
}

/// One pass over `rays` in parallel chunks, timed.
fn pass(caster: &Caster, set: &RaySet, out: &mut Hits) -> Duration {
    let t = Instant::now();
    set.rays
        .par_chunks(CHUNK)
        .zip(out.par_chunks_mut(CHUNK))
        .for_each(|(r, o)| caster.cast(r, set.coherent, o));
    t.elapsed()
}

/// Whether two results of `ray` are the same: both miss, or both hit with t within 1e-4
/// relative or within two float steps of the origin's largest coordinate (measured: rays
/// starting 1.4 km from the city's corner differ by up to 1.7e-4 m between kernels, one step
/// of their coordinates).
fn agree(ray: &RayQuery, a: &Option<(f32, u32)>, b: &Option<(f32, u32)>) -> bool {
    match (a, b) {
        (None, None) => true,
        (Some((s, _)), Some((t, _))) => {
            let steps = 2.0 * ray.0.abs().max_element() * f32::EPSILON;
            (s - t).abs() <= 1e-4 * s.abs().max(t.abs()) + steps
        }
        _ => false,
    }
}

/// Fraction of `rays` whose results in `a` and `b` agree.
pub fn agreement(rays: &[RayQuery], a: &[Option<(f32, u32)>], b: &[Option<(f32, u32)>]) -> f64 {
    let same = rays
        .iter()
        .zip(a.iter().zip(b))
        .filter(|(r, (x, y))| agree(r, x, y))
        .count();
    same as f64 / a.len().max(1) as f64
}

/// Median and range of `values`.
fn median_range(mut values: Vec<f64>) -> (f64, (f64, f64)) {
    values.sort_by(f64::total_cmp);
    (
        values[values.len() / 2],
        (values[0], values[values.len() - 1]),
    )
}

/// Median and range of `passes` timed passes of each caster after one warm-up each, million
/// rays per second. The passes go round the casters (one of each, then again), so a burst of
/// load on this shared machine falls on every backend alike and their ratios hold.
fn measure(
    casters: &[(Backend, Caster)],
    set: &RaySet,
    passes: usize,
) -> Vec<(f64, (f64, f64), Hits)> {
    let mut outs: Vec<Hits> = casters.iter().map(|_| vec![None; set.rays.len()]).collect();
    for ((_, caster), out) in casters.iter().zip(&mut outs) {
        pass(caster, set, out);
    }
    let mut rates = vec![Vec::new(); casters.len()];
    for _ in 0..passes.max(1) {
        for (((_, caster), out), rates) in casters.iter().zip(&mut outs).zip(&mut rates) {
            rates.push(set.rays.len() as f64 / pass(caster, set, out).as_secs_f64() / 1e6);
        }
    }
    rates
        .into_iter()
        .zip(outs)
        .map(|(r, out)| {
            let (median, range) = median_range(r);
            (median, range, out)
        })
        .collect()
}

/// Measures every backend on every ray set at every thread count: the median of `passes`
/// timed passes after a warm-up, the backends taking their passes in turn (builds too: the
/// median of `passes`). `progress` hears of each row as it is measured.
pub fn run(
    scene: &Scene,
    threads: &[usize],
    passes: usize,
    against_embree: bool,
    mut progress: impl FnMut(&RayBenchRow),
) -> RayBenchReport {
    let triangles = scene.triangles_at(0.0);
    let pools: Vec<(usize, rayon::ThreadPool)> = threads
        .iter()
        .map(|&n| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(n.max(1))
                .build()
                .expect("a thread pool");
            (n, pool)
        })
        .collect();
    // Builds: each backend `passes` times at each thread count, round by round (as the
    // rays' passes), the median reported; the first round's trees cast the rays.
    let kinds = [BvhKind::Bvh2, BvhKind::Cwbvh, BvhKind::Wide];
    let mut build_times = vec![Vec::new(); kinds.len() * pools.len()];
    let mut bvhs = Vec::new();
    for round in 0..passes.max(1) {
        for (k, kind) in kinds.iter().enumerate() {
            for (p, (n, pool)) in pools.iter().enumerate() {
                let bvh = pool.install(|| SceneBvh::build(triangles.clone(), *kind));
                build_times[k * pools.len() + p].push(bvh.build_time().as_secs_f64());
                if round == 0 && *n == threads[0] {
                    bvhs.push((*kind, bvh));
                }
            }
        }
    }
    let mut builds = Vec::new();
    for (k, kind) in kinds.iter().enumerate() {
        for (p, (n, _)) in pools.iter().enumerate() {
            builds.push(BuildRow {
                what: Backend::Obvhs(*kind).name(),
                threads: *n,
                seconds: median_range(build_times[k * pools.len() + p].clone()).0,
            });
        }
    }
    let sets = ray_sets(scene, &bvhs[0].1);
    let embree = if against_embree {
        Some(Embree::load())
    } else {
        None
    };
    let embree_unavailable = match &embree {
        Some(Err(e)) => Some(e.clone()),
        _ => None,
    };
    let embree = embree.and_then(Result::ok);
    // One Embree scene per thread count (its build threads), kept for the rays at that count.
    let mut embree_scenes = Vec::new();
    let mut embree_error = embree_unavailable;
    if let Some(e) = &embree {
        // One thread count's builds after another: Embree's tasking is process-wide, and a
        // one-thread device built after a two-thread one measured the two-thread time.
        let mut times = vec![Vec::new(); pools.len()];
        'counts: for (p, (n, pool)) in pools.iter().enumerate() {
            for round in 0..passes.max(1) {
                match pool.install(|| e.scene(&triangles, *n)) {
                    Ok(s) => {
                        times[p].push(s.build_time.as_secs_f64());
                        if round == 0 {
                            embree_scenes.push((*n, s));
                        }
                    }
                    Err(err) => {
                        embree_error = Some(err);
                        embree_scenes.clear();
                        break 'counts;
                    }
                }
            }
        }
        if !embree_scenes.is_empty() {
            for (p, (n, _)) in pools.iter().enumerate() {
                builds.push(BuildRow {
                    what: "Embree MEDIUM",
                    threads: *n,
                    seconds: median_range(times[p].clone()).0,
                });
            }
        }
    }
    let reference = if embree_scenes.is_empty() {
        Backend::Obvhs(BvhKind::Bvh2)
    } else {
        Backend::EmbreeOne
    };
    // Reference hits: one pass of the reference backend per set.
    let reference_hits: Vec<Hits> = sets
        .iter()
        .map(|set| {
            let caster = match embree_scenes.first() {
                Some((_, s)) => Caster::Embree(s, Backend::EmbreeOne),
                None => Caster::Obvhs(&bvhs[0].1),
            };
            let mut out = vec![None; set.rays.len()];
            pass(&caster, set, &mut out);
            out
        })
        .collect();
    let mut rows = Vec::new();
    for (n, pool) in &pools {
        let mut casters: Vec<(Backend, Caster)> = bvhs
            .iter()
            .map(|(k, b)| (Backend::Obvhs(*k), Caster::Obvhs(b)))
            .collect();
        let wide = bvhs.iter().find(|(k, _)| *k == BvhKind::Wide);
        casters.extend(wide.map(|(_, b)| (Backend::OursStreams, Caster::Streams(b))));
        if let Some((_, s)) = embree_scenes.iter().find(|(m, _)| m == n) {
            for b in [
                Backend::EmbreeOne,
                Backend::EmbreePackets,
                Backend::EmbreeStream,
            ] {
                casters.push((b, Caster::Embree(s, b)));
            }
        }
        for (set, reference) in sets.iter().zip(&reference_hits) {
            let measured = pool.install(|| measure(&casters, set, passes));
            for ((backend, _), (mrays_s, range, out)) in casters.iter().zip(measured) {
                let row = RayBenchRow {
                    backend: *backend,
                    rays: set.name,
                    threads: *n,
                    mrays_s,
                    range,
                    agreement: agreement(&set.rays, &out, reference),
                };
                progress(&row);
                rows.push(row);
            }
        }
    }
    let wide = bvhs
        .iter()
        .find_map(|(_, b)| b.wide().map(|w| (b, w)))
        .expect("the BVH8 is built");
    let work = sets
        .iter()
        .map(|set| {
            let mut v = crate::bvh::Visits::default();
            for &(o, d, t) in &set.rays {
                wide.1
                    .intersect_counted(&wide.0.wide_ray_of(o, d, t), &mut v);
            }
            let n = set.rays.len().max(1) as f64;
            WorkRow {
                rays: set.name,
                nodes: v.nodes as f64 / n,
                blocks: v.blocks as f64 / n,
            }
        })
        .collect();
    RayBenchReport {
        work,
        sah: (wide.1.sah_visits(), wide.1.size()),
        sets: sets.iter().map(|s| (s.name, s.rays.len())).collect(),
        builds,
        rows,
        reference,
        embree_unavailable: embree_error,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn embree_agrees_with_obvhs_where_installed() {
        let Ok(embree) = Embree::load() else {
            eprintln!("Embree 3 not installed: nothing to compare");
            return;
        };
        let scene = cloudlight_scenes::builtin("city:5000").unwrap();
        let bvh = SceneBvh::at(&scene, 0.0, BvhKind::default());
        let es = embree.scene(bvh.triangles(), 1).expect("builds");
        let rays = random_rays(bvh.bounds(), 3000);
        let ours: Hits = rays
            .iter()
            .map(|&(o, d, t)| bvh.closest_hit(o, d, t).map(|h| (h.t, h.triangle)))
            .collect();
        let one: Hits = rays.iter().map(|r| es.closest_hit(r)).collect();
        let mut packets = vec![None; rays.len()];
        es.closest_hits_packets(&rays, &mut packets);
        let mut stream = vec![None; rays.len()];
        es.closest_hits_stream(&rays, false, &mut stream);
        let agree = |a: &Hits, b: &Hits| agreement(&rays, a, b);
        assert!(agree(&ours, &one) > 0.999, "{}", agree(&ours, &one));
        assert_eq!(agree(&one, &packets), 1.0);
        assert_eq!(agree(&one, &stream), 1.0);
        for (r, h) in rays.iter().zip(&one).take(500) {
            if let Some((t, _)) = h {
                assert!(es.occluded(&(r.0, r.1, t * 1.001)));
                assert!(!es.occluded(&(r.0, r.1, t * 0.999)));
            }
        }
    }
}
