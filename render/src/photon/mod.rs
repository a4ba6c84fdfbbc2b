//! Photon tracing for the photon technique (CloudLight §4.3): which lights emit how many
//! fixed-size batches ([`BatchPlan`]), tracing one batch from one light with the BVH
//! ([`PhotonTracer`]), bit-packing batches for the wire ([`pack`]) and the client's set of
//! the newest batch per (light, slot) ([`store`]).
//!
//! Phases of one iteration:
//! 1. **Lights** ([`photon_lights`]): every punctual light, the sun, and every emissive
//!    object (one light per object) at the scene time, with its power summed over channels.
//! 2. **Budget** ([`BatchPlan::new`]): photons per watt × power → the light's photons, in
//!    as few batches as hold them (none for a light whose share rounds to no photon); each
//!    photon carries Φ_light / (batches × photons per batch).
//! 3. **Trace** ([`PhotonTracer::trace_batch`]): emit from the light, follow diffuse bounces
//!    (cosine sampling, Russian roulette with survival = max albedo, so power stays
//!    unbiased) and store a photon at every hit *after the first* — first hits are direct
//!    light, which the client shades itself (storing them would count it twice).
//!
//! [`PhotonStream`] runs these phases iteration by iteration, keeping each light's current
//! set (only changed lights are traced again): the batcher stage, the benchmarks and the
//! tests all call it.
//!
//! Each photon stores where it landed, the direction it travelled, its power and the radius
//! of its splat. The iteration's reference radius is chosen so that about `photons_per_disk`
//! photons would fall in a disk were they spread evenly over the scene's surfaces:
//! r = √(k·A / (π·N)) — more photons, smaller disks, less blur (the budget trades bias and
//! noise together). Each photon's own radius then follows where photons actually landed
//! ([`density`]): the distance holding `photons_per_disk` of its light's photons, within
//! [`DENSITY_RADIUS_RANGE`] of the reference; a photon walled in on every side along its
//! surface within half its radius keeps its disk inside those walls, a disk that would reach
//! through a wall onto ground a client sees beyond it stops at the wall
//! ([`density::enclose`]), and a disk that overhangs its surface's edge or curve is halved
//! ([`density::fit`]).
//! A light's budget is its share of the watts ([`BatchPlan`]); a sun's watts are those
//! falling on its [`footprint`]. Streams are counter-based per (seed, light, slot,
//! generation, photon), so a batch is the same bytes on any thread count and any node.

pub use cloudlight_scenes::View;
use cloudlight_scenes::{LightState, Scene, WorldTriangle};
use glam::Vec3;
use rayon::prelude::*;

use crate::bvh::SceneBvh;
use crate::sampling::{Rng, basis, cosine_hemisphere, uniform_sphere, uniform_triangle};
use footprint::{Footprint, FootprintCache, Guide};

pub mod compact8;
pub mod density;
pub mod footprint;
pub mod merge;
pub mod pack;
pub mod relax;
pub mod splat;
pub mod store;
pub mod stream;

pub use pack::{BatchHeader, PackError, PackFormat, PackedBatch};
pub use store::{Inserted, Manifest, ManifestLight, PhotonSet};
pub use stream::{
    BatchJob, Iteration, IterationPlan, LightSet, LightYield, PhotonStream, Retrace, TracedBatch,
    trace_iteration,
};

/// Largest batch size accepted (a batch is one message; 10⁷ compact photons are 120 MB).
pub const MAX_BATCH_SIZE: u32 = 10_000_000;

/// What a photon's vector is, and so which surfaces its disk lights on the client.
#[derive(
    Clone, Copy, Debug, Default, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum Receive {
    /// The normal of the surface it landed on (reversed: into the surface): it lights
    /// surfaces whose normal lies within [`crate::photon::splat::SplatSettings::facing`] of
    /// its own. No light crosses an edge onto a surface facing elsewhere (a platform's
    /// top onto its side, a street onto a wall), at the price of the light a disk loses
    /// past its surface's edge. Measured (`bench quality`, relMSE, 160k photons): dungeon
    /// 1.30 → 0.37, city:250000 3.85 → 0.64; Cornell box (10k) 0.0415 → 0.052.
    #[default]
    Normal,
    /// The direction it travelled (the paper's n·ω test): it lights any surface facing
    /// against that direction within the flatten distance, so a floor's photons also light
    /// the foot of a wall — light a closed box's corners need, a leak at game-level scale.
    Direction,
}

/// Settings of the photon tracer.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PhotonSettings {
    /// Photons emitted per watt of emitted power (summed over channels).
    pub photons_per_watt: f64,
    /// Photons per batch (each batch comes from one light).
    pub batch_size: u32,
    /// Diffuse bounces stored per path at most (photons at hits 2 ..= bounces + 1); the
    /// default, 64, leaves ending paths to Russian roulette (a cap of 6 lost ~4% of the
    /// Cornell box's indirect light).
    pub bounces: u32,
    /// Photons expected inside one splat disk; sets the radius. The default, 160, measured
    /// best on the Cornell box at 2.5k-160k photons (40, the paper's Jensen-style count,
    /// left noise that doubled the error).
    pub photons_per_disk: f32,
    /// A fixed splat radius in meters instead of the one from `photons_per_disk`.
    pub radius_m: Option<f32>,
    /// Each photon's radius from the density of stored photons around it ([`density`]);
    /// false: every photon of an iteration gets its reference radius.
    pub density_radius: bool,
    /// Passes of a light that stands still (progressive photon mapping): after the first
    /// set, one more set of fresh photons per iteration until it holds this many, the
    /// client drawing all of them with radii shrinking by [`progressive_radius_scale`].
    /// 1 (the default): a still light is traced once. Each doubling of the passes doubles
    /// the client's splat: each photon goes to the level where its disk spans a few texels,
    /// so it costs about the same at any radius (`bench client --technique photons --set
    /// passes=P`, Cornell 640×360, 10k photons a pass: splat 9.5 / 18.7 / 38.6 / 80 / 156 /
    /// 292 ms p50, whole frame 35 / 44 / 64 / 104 / 176 / 319 ms at P = 1 / 2 / 4 / 8 / 16 /
    /// 32).
    pub passes: u32,
    /// What each photon's vector is: its surface's normal (the default) or the direction
    /// it travelled ([`Receive`]).
    pub receive: Receive,
    /// Share of a directional light's photons sent toward what clients see, when the
    /// stream knows their views ([`PhotonStream::set_views`], [`Footprint::guide`]); the
    /// rest stay uniform over its footprint. 0: no guidance.
    pub guide_share: f32,
    /// How far from a surface a client sees the photons that light it are sought, as a
    /// fraction of the scene's half diagonal.
    pub guide_reach: f32,
    /// Rounds of photon relaxation of each batch before its radii are set ([`relax`]): its
    /// photons pushed apart on their surfaces, so that the random clumps a splat shows as
    /// blotches thin out; a generation's first pass only (refinement passes of a still light
    /// converge by number). 0 (the default): none. It lowers the error where noise dominates
    /// it and raises it where bias does (features finer than the disks): `bench quality`,
    /// relMSE 0 → 6 rounds: Cornell box, 10k photons (`receive = direction`, seeds 1–8)
    /// 0.0371 → 0.0295; the dungeon, 40k / 160k, 0.222 / 0.224 → 0.225 / 0.222;
    /// `city:250000`, 40k / 160k / 640k, 0.174 / 0.180 / 0.068 → 0.193 / 0.234 / 0.111.
    pub relax: u32,
    /// Times a disk that overhangs its surface is halved at most ([`density::fit`]; 0:
    /// never), for photons that carry their surface's normal. `bench quality`, relMSE 0 →
    /// 3: the dungeon's courtyard seen at eye height, 40k photons a pass, after 32 passes
    /// 0.083–0.088 → 0.069–0.072; the Cornell box with `receive = normal`, 10k, seeds 1
    /// and 2, 0.052 / 0.050 → 0.045 / 0.051; the dungeon seen from outside, where thin
    /// faces seen edge-on get a pixel's light each, 0.23–0.25 → 0.23–0.33 (README).
    pub fit: u32,
    /// Each batch's photons within a cell of this fraction of their radius (receiving
    /// alike) are merged into one before it is packed ([`merge`]); 0: none. Fewer photons
    /// on the wire for nearly the same light: `bench quality --technique photons` on the
    /// Cornell box (4096 spp, 128²), 0 → 0.5, 10k photons 61.7 → 23.2 KB an update at
    /// relMSE 0.0493 → 0.0496, 20k 131 → 63 KB at 0.0440 → 0.0438 (README, "Merging
    /// photons").
    pub merge: f32,
}

/// Rays per view along each image axis when finding the surfaces clients see.
pub const VIEW_RAYS: u32 = 48;

/// The surfaces `views` see: one point per ray of a `VIEW_RAYS`² grid across each view
/// (rays that meet nothing give none), so each pixel's surface counts alike.
pub fn view_points(bvh: &SceneBvh, views: &[View]) -> Vec<Vec3> {
    let n = VIEW_RAYS;
    views
        .iter()
        .filter(|v| v.is_valid())
        .flat_map(|v| {
            (0..n * n)
                .into_par_iter()
                .filter_map(move |i| {
                    let ndc = glam::Vec2::new(
                        ((i % n) as f32 + 0.5) / n as f32 * 2.0 - 1.0,
                        ((i / n) as f32 + 0.5) / n as f32 * 2.0 - 1.0,
                    );
                    let d = v.camera.ray_direction(ndc, v.aspect);
                    let o = v.camera.position;
                    bvh.closest_hit(o, d, f32::INFINITY).map(|h| o + d * h.t)
                })
                .collect::<Vec<_>>()
        })
        .collect()
}

/// Radius reduction of progressive photon mapping (Knaus & Zwicker 2011): each pass keeps
/// the fraction α of the photons per disk that the previous passes gathered, so bias and
/// variance both vanish as passes grow. Their 2/3 is best as passes tend to infinity; over
/// the tens of passes a still light gets, bias (disks wider than thin faces, steps and
/// ribs) outweighs noise in game levels, and a faster shrink measured better:
/// `bench quality --technique photons`, relMSE, α = 2/3 → 1/2 → 0.4 (→ 0.3), after 32
/// passes unless said, the upsample's σ at 0.001 of the diagonal: the dungeon seen from
/// outside (`--scene assets/dungeon/level-dungeon.gltf --spp 1024 --budgets 80000 --width
/// 640 --height 360`)
/// 0.1370 → 0.1224 → 0.1181 (→ 0.1197), after 128 0.1229 → 0.1155 → 0.1193 (smaller disks
/// light a few hot pixels on thin faces); its courtyard and fountains (40k a pass, 128²,
/// seeds: default, 2, 3) 0.0687 → 0.0662 → 0.0738 and 0.1062 / 0.0978 / 0.1060 → 0.1108 /
/// 0.0976 / 0.1046; `city:250000` (`--budgets 160000 --spp 4096 --width 96 --height 96
/// --set photons_per_disk=40`) 0.0364 → 0.0345; the Cornell box still (`--budgets 20000
/// --spp 4096 --set receive=direction`, 128²) 0.0099 → 0.0100 → 0.0105.
pub const PROGRESSIVE_ALPHA: f32 = 0.5;

/// The factor on every radius when a light's photons are `passes` passes drawn together:
/// r_P² = r_1² · Π_{k=1}^{P−1} (k + α) / (k + 1) (≈ P^(α−1): with P times the photons, a
/// disk holds P^α times as many). Powers are divided by P.
pub fn progressive_radius_scale(passes: u32) -> f32 {
    let area: f64 = (1..passes.max(1))
        .map(|k| (k as f64 + PROGRESSIVE_ALPHA as f64) / (k as f64 + 1.0))
        .product();
    area.sqrt() as f32
}

/// Density radii lie within these multiples of the iteration's reference radius: the
/// smallest keeps a few photons under a disk in the densest corner; the largest is the
/// reference itself (on the Cornell box, disks larger than that where photons are sparse
/// lost more light off the surfaces' edges than they saved in noise).
pub const DENSITY_RADIUS_RANGE: (f32, f32) = (0.15, 1.0);

impl Default for PhotonSettings {
    fn default() -> Self {
        // The paper's Cornell box: 10k photons in one batch (1.415 W summed over channels).
        PhotonSettings {
            photons_per_watt: 7_066.0,
            batch_size: 10_000,
            bounces: 64,
            photons_per_disk: 160.0,
            radius_m: None,
            density_radius: true,
            passes: 1,
            receive: Receive::Normal,
            guide_share: 0.5,
            guide_reach: 0.05,
            relax: 0,
            fit: 3,
            merge: 0.5,
        }
    }
}

/// Photons per iteration when a stage names neither `photons` nor `photons_per_watt`: the
/// paper's Cornell box budget, spread over any scene's lights by their power.
pub const DEFAULT_PHOTONS: u64 = 10_000;

impl PhotonSettings {
    /// Settings for `scene` from a budget as a stage takes it: `photons_per_watt` when given,
    /// else `photons` per iteration ([`DEFAULT_PHOTONS`] when absent) spread over the
    /// lights by power ([`Self::for_budget`]).
    pub fn for_stage_budget(
        scene: &Scene,
        photons: Option<u64>,
        photons_per_watt: Option<f64>,
        batch_size: u32,
    ) -> Self {
        match photons_per_watt {
            Some(photons_per_watt) => PhotonSettings {
                photons_per_watt,
                batch_size,
                ..Default::default()
            },
            None => Self::for_budget(scene, photons.unwrap_or(DEFAULT_PHOTONS), batch_size),
        }
    }

    /// Settings whose photons per watt give about `photons` photons per iteration in `scene`.
    pub fn for_budget(scene: &Scene, photons: u64, batch_size: u32) -> Self {
        let watts: f64 = photon_lights(scene, 0.0).iter().map(|l| l.watts()).sum();
        PhotonSettings {
            photons_per_watt: if watts > 0.0 {
                photons as f64 / watts
            } else {
                0.0
            },
            batch_size,
            ..Default::default()
        }
    }
}

/// Where and how a light emits photons.
#[derive(Clone, Debug, PartialEq)]
pub enum Emitter {
    /// A point or spot light at `position`; `cos_cone` = −1 for a point light.
    Punctual {
        /// Position, meters.
        position: Vec3,
        /// Cone axis (unit).
        axis: Vec3,
        /// Cosine of the cone half-angle.
        cos_cone: f32,
    },
    /// Parallel light over the scene's footprint as the light sees it.
    Directional(std::sync::Arc<Footprint>),
    /// An emissive object: Lambertian emission from its triangles' front sides, chosen by
    /// area.
    Surface {
        /// World-space triangles.
        triangles: Vec<[Vec3; 3]>,
        /// Cumulative areas, m².
        cdf: Vec<f32>,
    },
}

impl Emitter {
    /// Every [`Self::kind`], in the order reports list them.
    pub const KINDS: [&'static str; 4] = ["directional", "point", "spot", "surface"];

    /// `directional`, `point`, `spot` or `surface` ([`Self::KINDS`]): for reports.
    pub fn kind(&self) -> &'static str {
        match self {
            Emitter::Punctual { cos_cone, .. } if *cos_cone <= -1.0 => "point",
            Emitter::Punctual { .. } => "spot",
            Emitter::Directional(_) => "directional",
            Emitter::Surface { .. } => "surface",
        }
    }
}

/// One light as the photon tracer sees it at one scene time.
#[derive(Clone, Debug, PartialEq)]
pub struct PhotonLight {
    /// Stable identity: index into the scene's lights, then `lights.len() + object index`
    /// for emissive objects.
    pub id: u32,
    /// Name, for reports.
    pub name: String,
    /// Emitted power per channel, watts.
    pub power_w: Vec3,
    /// Emission geometry.
    pub emitter: Emitter,
}

impl PhotonLight {
    /// Watts summed over channels (what the photon budget counts).
    pub fn watts(&self) -> f64 {
        self.power_w.element_sum() as f64
    }
}

/// The scene's lights at `t_s` as photon emitters (lights that emit nothing, or reach no
/// geometry, are left out).
pub fn photon_lights(scene: &Scene, t_s: f64) -> Vec<PhotonLight> {
    photon_lights_in(scene, t_s, &scene.triangles_at(t_s))
}

/// [`photon_lights`] when the scene's triangles at `t_s` are at hand (e.g. its BVH's).
pub fn photon_lights_in(scene: &Scene, t_s: f64, triangles: &[WorldTriangle]) -> Vec<PhotonLight> {
    photon_lights_cached(scene, t_s, triangles, &mut FootprintCache::default())
}

/// [`photon_lights_in`], directional lights' footprints kept in `cache` while the scene's
/// geometry does not move.
pub fn photon_lights_cached(
    scene: &Scene,
    t_s: f64,
    triangles: &[WorldTriangle],
    cache: &mut FootprintCache,
) -> Vec<PhotonLight> {
    let static_geometry = !scene.has_moving_geometry();
    let (mut lo, mut hi) = (Vec3::INFINITY, Vec3::NEG_INFINITY);
    for t in triangles
        .iter()
        .filter(|t| t.v.iter().all(|p| p.is_finite()))
    {
        for p in t.v {
            lo = lo.min(p);
            hi = hi.max(p);
        }
    }
    let half_diag = if lo.is_finite() && hi.is_finite() {
        ((hi - lo).length() * 0.5).max(1e-6)
    } else {
        1.0
    };
    let mut out = Vec::new();
    for (i, light) in scene.lights.iter().enumerate() {
        let footprint = |d: Vec3| cache.get(d, triangles, static_geometry);
        let Some((power_w, emitter)) = emitter_of(light.at(t_s), half_diag, footprint) else {
            continue;
        };
        if power_w.max_element() > 0.0 && power_w.is_finite() {
            out.push(PhotonLight {
                id: i as u32,
                name: light.name.clone(),
                power_w,
                emitter,
            });
        }
    }
    // Emissive objects: one light each.
    for (k, object) in scene.objects.iter().enumerate() {
        let emission = scene.materials[object.material as usize].emission;
        if emission.max_element() <= 0.0 || !emission.is_finite() {
            continue;
        }
        if let Some(light) = surface_light(
            (scene.lights.len() + k) as u32,
            &object.name,
            emission,
            &scene.object_triangles_at(k, t_s),
        ) {
            out.push(light);
        }
    }
    out
}

/// The emitted power (per channel, watts) and the emission geometry of a light's state, in
/// a scene of half-diagonal `half_diag` (m) whose footprint along a direction `footprint`
/// gives; `None` for a directional light with no geometry to reach.
fn emitter_of(
    state: LightState,
    half_diag: f32,
    footprint: impl FnOnce(Vec3) -> Option<std::sync::Arc<Footprint>>,
) -> Option<(Vec3, Emitter)> {
    Some(match state {
        LightState::Point {
            position,
            intensity,
        } => (
            intensity * 4.0 * std::f32::consts::PI,
            Emitter::Punctual {
                position,
                axis: Vec3::Z,
                cos_cone: -1.0,
            },
        ),
        LightState::Spot {
            position,
            direction,
            cos_cone,
            intensity,
        } => (
            intensity * std::f32::consts::TAU * (1.0 - cos_cone),
            Emitter::Punctual {
                position,
                axis: direction,
                cos_cone,
            },
        ),
        LightState::Surface {
            position,
            normal,
            intensity,
        } => (
            intensity * std::f32::consts::PI,
            Emitter::Surface {
                triangles: vec![tiny_triangle(position, normal, half_diag * 1e-4)],
                cdf: vec![1.0],
            },
        ),
        LightState::Directional {
            direction,
            irradiance,
        } => {
            let footprint = footprint(direction)?;
            (
                irradiance * footprint.area_m2(),
                Emitter::Directional(footprint),
            )
        }
    })
}

fn tiny_triangle(position: Vec3, normal: Vec3, size: f32) -> [Vec3; 3] {
    let (t, b) = basis(normal.normalize_or(Vec3::Y));
    [position, position + t * size, position + b * size]
}

fn surface_light(
    id: u32,
    name: &str,
    emission: Vec3,
    tris: &[WorldTriangle],
) -> Option<PhotonLight> {
    let mut cdf = Vec::new();
    let mut kept = Vec::new();
    let mut total = 0.0f32;
    for t in tris {
        let area = 0.5 * (t.v[1] - t.v[0]).cross(t.v[2] - t.v[0]).length();
        if area > 0.0 && area.is_finite() {
            total += area;
            cdf.push(total);
            kept.push(t.v);
        }
    }
    (total > 0.0).then(|| PhotonLight {
        id,
        name: name.to_string(),
        power_w: emission * std::f32::consts::PI * total,
        emitter: Emitter::Surface {
            triangles: kept,
            cdf,
        },
    })
}

/// One light's share of an iteration.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LightBatches {
    /// Light id.
    pub id: u32,
    /// Batches.
    pub batches: u32,
    /// Photons emitted per batch.
    pub photons: u32,
}

/// How many batches of how many photons each light emits per iteration.
#[derive(Clone, Debug, PartialEq)]
pub struct BatchPlan {
    /// Photons per batch at most.
    pub batch_size: u32,
    /// The lights with photons to emit, in light order.
    pub batches: Vec<LightBatches>,
}

impl BatchPlan {
    /// Each light's budget follows its power: photons_per_watt × watts (rounded), in as few
    /// batches of at most `batch_size` as hold it, split evenly. A light whose share rounds
    /// to no photon gets no batch (its light is below what the budget resolves); one whose
    /// share is below a batch gets one smaller batch instead of a whole one.
    pub fn new(lights: &[PhotonLight], settings: &PhotonSettings) -> Self {
        let batch_size = settings.batch_size.clamp(1, MAX_BATCH_SIZE);
        let batches = lights
            .iter()
            .filter_map(|l| {
                let photons = (l.watts() * settings.photons_per_watt.max(0.0)).round();
                if photons.is_nan() || photons < 1.0 {
                    return None;
                }
                let photons = photons.min(1e6 * batch_size as f64);
                let batches = (photons / batch_size as f64).ceil().max(1.0);
                Some(LightBatches {
                    id: l.id,
                    batches: batches as u32,
                    photons: ((photons / batches).round() as u32).clamp(1, batch_size),
                })
            })
            .collect();
        BatchPlan {
            batch_size,
            batches,
        }
    }

    fn of(&self, id: u32) -> Option<&LightBatches> {
        self.batches.iter().find(|b| b.id == id)
    }

    /// Batches of light `id` (0 if it has none).
    pub fn batches_of(&self, id: u32) -> u32 {
        self.of(id).map_or(0, |b| b.batches)
    }

    /// Photons per batch of light `id` (0 if it has none).
    pub fn photons_per_batch(&self, id: u32) -> u32 {
        self.of(id).map_or(0, |b| b.photons)
    }

    /// Photons light `id` emits in one iteration.
    pub fn photons_of(&self, id: u32) -> u64 {
        self.of(id)
            .map_or(0, |b| b.batches as u64 * b.photons as u64)
    }

    /// Batches in one iteration.
    pub fn total_batches(&self) -> u64 {
        self.batches.iter().map(|b| b.batches as u64).sum()
    }

    /// Photons emitted in one iteration.
    pub fn total_photons(&self) -> u64 {
        self.batches
            .iter()
            .map(|b| b.batches as u64 * b.photons as u64)
            .sum()
    }
}

/// One stored photon.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Photon {
    /// Where it landed, meters.
    pub position: Vec3,
    /// A unit vector into the surface: the surface's normal reversed, or the direction it
    /// travelled (`receive`).
    pub direction: Vec3,
    /// Power per channel, watts.
    pub power: Vec3,
    /// Splat radius, meters.
    pub radius: f32,
    /// What `direction` is, and so which surfaces the photon lights.
    pub receive: Receive,
}

/// Traces batches of one scene at one scene time.
pub struct PhotonTracer<'a> {
    scene: &'a Scene,
    bvh: &'a SceneBvh,
    settings: PhotonSettings,
    seed: u64,
    eps: f32,
    radius: f32,
    plan: BatchPlan,
    guides: &'a std::collections::BTreeMap<u32, std::sync::Arc<Guide>>,
    views: &'a [View],
}

/// No guides.
static NO_GUIDES: std::collections::BTreeMap<u32, std::sync::Arc<Guide>> =
    std::collections::BTreeMap::new();

impl<'a> PhotonTracer<'a> {
    /// A tracer for `scene` (whose BVH at the scene time is `bvh`) emitting `plan`'s photons
    /// per iteration (which sets the splat radius).
    pub fn new(
        scene: &'a Scene,
        bvh: &'a SceneBvh,
        settings: PhotonSettings,
        plan: &BatchPlan,
        seed: u64,
    ) -> Self {
        let (lo, hi) = bvh.bounds();
        let extent = (hi - lo).length();
        let extent = if extent.is_finite() && extent > 0.0 {
            extent
        } else {
            1.0
        };
        let radius = settings
            .radius_m
            .unwrap_or_else(|| {
                let n = plan.total_photons().max(1) as f32;
                (settings.photons_per_disk.max(1.0) * bvh.surface_area_m2()
                    / (std::f32::consts::PI * n))
                    .sqrt()
            })
            .clamp(extent * 1e-4, extent * 0.25);
        PhotonTracer {
            scene,
            bvh,
            settings,
            seed,
            eps: extent * 1e-5,
            radius,
            plan: plan.clone(),
            guides: &NO_GUIDES,
            views: &[],
        }
    }

    /// This tracer with directional lights' emission guided by `guides` (by light id).
    pub fn guided(
        self,
        guides: &'a std::collections::BTreeMap<u32, std::sync::Arc<Guide>>,
    ) -> Self {
        PhotonTracer { guides, ..self }
    }

    /// This tracer with disks that stop at walls beyond which one of `views` would see
    /// their light ([`density::enclose`]).
    pub fn seen_from(self, views: &'a [View]) -> Self {
        PhotonTracer { views, ..self }
    }

    /// The splat radius of this iteration's photons, meters.
    pub fn radius(&self) -> f32 {
        self.radius
    }

    /// Traces batch `slot` of `light` (of `slots` batches) for its `generation`: emits the
    /// plan's photons per batch of that light and returns those stored.
    pub fn trace_batch(
        &self,
        light: &PhotonLight,
        slot: u32,
        slots: u32,
        generation: u64,
    ) -> Vec<Photon> {
        self.trace_pass(light, slot, slots, generation, 0)
    }

    /// [`Self::trace_batch`] for refinement pass `pass` of the generation: other random
    /// numbers (pass 0 is `trace_batch`'s), the same budget and radii.
    pub fn trace_pass(
        &self,
        light: &PhotonLight,
        slot: u32,
        slots: u32,
        generation: u64,
        pass: u32,
    ) -> Vec<Photon> {
        let n = self.plan.photons_per_batch(light.id);
        if n == 0 {
            return Vec::new();
        }
        let emitted_total = n as f32 * slots.max(1) as f32;
        let power = light.power_w / emitted_total;
        let stream = (light.id as u64) << 44
            ^ (slot as u64) << 24
            ^ generation.wrapping_mul(0x9E37)
            ^ u64::from(pass).wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
        const CHUNK: u32 = 1024;
        // Each stored photon and its surface's normal (what relaxation moves it along).
        let (photons, normals): (Vec<Vec<Photon>>, Vec<Vec<Vec3>>) = (0..n.div_ceil(CHUNK))
            .into_par_iter()
            .map(|c| {
                let mut out = (Vec::new(), Vec::new());
                for i in c * CHUNK..((c + 1) * CHUNK).min(n) {
                    let mut rng = Rng::new(self.seed ^ stream, i as u64);
                    self.trace_one(light, power, &mut rng, &mut out);
                }
                out
            })
            .unzip();
        let (mut photons, normals) = (photons.concat(), normals.concat());
        // Only a generation's first pass: refinement passes of a still light converge to
        // the reference by their number (relaxing each of them too kept a floor of bias:
        // Cornell box, 20k photons a pass, relMSE after 32 passes 0.0141 against 0.0098).
        if pass == 0 {
            relax::relax(
                &mut photons,
                &normals,
                self.bvh,
                self.settings.relax,
                self.eps,
            );
        }
        if self.settings.density_radius {
            let (lo, hi) = DENSITY_RADIUS_RANGE;
            density::assign(
                &mut photons,
                self.settings.photons_per_disk,
                slots,
                (self.radius * lo, self.radius * hi),
            );
        }
        // Not below the batch's smallest radius, which sets its packing's position step.
        let least = photons
            .iter()
            .map(|p| p.radius)
            .fold(f32::INFINITY, f32::min);
        density::enclose(
            &mut photons,
            &normals,
            self.bvh,
            self.eps,
            least,
            self.views,
        );
        density::fit(
            &mut photons,
            &normals,
            self.bvh,
            self.eps,
            least,
            self.settings.fit,
            density::Receiving::default(),
        );
        photons
    }

    fn trace_one(
        &self,
        light: &PhotonLight,
        power: Vec3,
        rng: &mut Rng,
        (out, normals): &mut (Vec<Photon>, Vec<Vec3>),
    ) {
        let guide = self.guides.get(&light.id).map(|g| &**g);
        let Some((mut o, mut d, weight)) = emit(&light.emitter, guide, rng, self.eps) else {
            return;
        };
        let mut power = power * weight;
        for depth in 0..=self.settings.bounces {
            let Some(hit) = self.bvh.closest_hit(o, d, f32::INFINITY) else {
                return;
            };
            let tri = &self.bvh.triangles()[hit.triangle as usize];
            let material = &self.scene.materials[tri.material as usize];
            let ng = self.bvh.geometric_normal(hit.triangle);
            // An emitting surface emits and reflects from its front; its back is the
            // fixture, which absorbs. (The Cornell box's light hangs 0.8 mm under the
            // ceiling: photons that slipped into that slit bounced between the ceiling and
            // the light's back, stored at every bounce with millimetre disks where no camera
            // sees them — 80 of 418k photons, too few to move the error measurably.)
            if ng.dot(d) > 0.0 && material.emission.max_element() > 0.0 {
                return;
            }
            let ng = if ng.dot(d) < 0.0 { ng } else { -ng };
            let mut n = self.bvh.shading_normal(&hit);
            if n.dot(ng) < 0.0 {
                n = -n;
            }
            let x = o + d * hit.t;
            if depth >= 1 {
                out.push(Photon {
                    position: x,
                    direction: match self.settings.receive {
                        Receive::Normal => -n,
                        Receive::Direction => d,
                    },
                    power,
                    radius: self.radius,
                    receive: self.settings.receive,
                });
                normals.push(ng);
            }
            if depth == self.settings.bounces {
                return;
            }
            let albedo = material.albedo
                * material
                    .texture
                    .as_ref()
                    .map_or(Vec3::ONE, |t| t.sample(self.bvh.hit_uv(&hit)));
            if depth == 0 && matches!(light.emitter, Emitter::Directional(_)) {
                // A sun's photon always leaves its first hit (which stores nothing), its
                // power times the albedo: roulette there killed most of them before they
                // stored anything (city:250000 stored 11% of what it emitted, 25% now; the
                // dungeon's error per byte fell 20–30%; on the Cornell box's area light the
                // same rule cost more in bytes than it gave).
                if albedo.max_element() <= 0.0 {
                    return;
                }
                power *= albedo;
            } else {
                // Russian roulette: survive with the largest albedo channel.
                let q = albedo.max_element().min(1.0);
                if q <= 0.0 || rng.next_f32() >= q {
                    return;
                }
                power *= albedo / q;
            }
            let (t, b) = basis(n);
            let l = cosine_hemisphere(rng.next_f32(), rng.next_f32());
            d = (t * l.x + b * l.y + n * l.z).normalize();
            o = x + ng * self.eps;
        }
    }
}

/// Origin and unit direction of one emitted photon, and the factor on its power (1 but
/// where `guide` drew it).
fn emit(
    emitter: &Emitter,
    guide: Option<&Guide>,
    rng: &mut Rng,
    eps: f32,
) -> Option<(Vec3, Vec3, f32)> {
    if let (Emitter::Directional(footprint), Some(guide)) = (emitter, guide) {
        let (o, weight) =
            footprint.sample_guided(guide, rng.next_f32(), rng.next_f32(), rng.next_f32());
        return Some((o, footprint.direction, weight));
    }
    let (o, d) = emit_uniform(emitter, rng, eps)?;
    Some((o, d, 1.0))
}

/// Origin and unit direction of one photon emitted with the light's own distribution.
fn emit_uniform(emitter: &Emitter, rng: &mut Rng, eps: f32) -> Option<(Vec3, Vec3)> {
    match emitter {
        Emitter::Punctual {
            position,
            axis,
            cos_cone,
        } => {
            let (u1, u2) = (rng.next_f32(), rng.next_f32());
            if *cos_cone <= -1.0 {
                return Some((*position, uniform_sphere(u1, u2)));
            }
            // Uniform in the cone: cos θ uniform in [cos_cone, 1].
            let z = 1.0 - u1 * (1.0 - cos_cone);
            let r = (1.0 - z * z).max(0.0).sqrt();
            let phi = std::f32::consts::TAU * u2;
            let (t, b) = basis(*axis);
            Some((
                *position,
                t * (r * phi.cos()) + b * (r * phi.sin()) + *axis * z,
            ))
        }
        Emitter::Directional(footprint) => Some((
            footprint.sample(rng.next_f32(), rng.next_f32(), rng.next_f32()),
            footprint.direction,
        )),
        Emitter::Surface { triangles, cdf } => {
            let total = *cdf.last()?;
            let x = rng.next_f32() * total;
            let i = cdf.partition_point(|c| *c <= x).min(triangles.len() - 1);
            let v = triangles[i];
            let bary = uniform_triangle(rng.next_f32(), rng.next_f32());
            let p = v[0] * (1.0 - bary.x - bary.y) + v[1] * bary.x + v[2] * bary.y;
            let n = (v[1] - v[0]).cross(v[2] - v[0]).normalize_or(Vec3::Y);
            let (t, b) = basis(n);
            let l = cosine_hemisphere(rng.next_f32(), rng.next_f32());
            let d = (t * l.x + b * l.y + n * l.z).normalize();
            Some((p + n * eps, d))
        }
    }
}

#[cfg(test)]
mod tests;
