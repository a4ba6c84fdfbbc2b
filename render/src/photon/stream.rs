//! The server side of the photon technique, iteration by iteration ([`PhotonStream`]): the
//! one kernel behind the `photon_batcher` stage, the benchmarks and the tests.
//!
//! Phases of an iteration:
//! 1. **Plan** ([`PhotonStream::plan`]): the lights at the scene time, photons per light
//!    ([`BatchPlan`]), this iteration's splat radius, and which batches to trace: every batch
//!    of a light that is new or changed (or of every light, with [`Retrace::Always`]), and
//!    one more refinement pass of a light that stands still, until it holds
//!    [`PhotonSettings::passes`] of them (progressive photon mapping).
//! 2. **Trace** ([`PhotonStream::trace`]): one batch, traced and packed; independent of the
//!    stream's state, so a caller may run batches on any thread and send each when done.
//! 3. **Commit** ([`PhotonStream::commit`]): a light's new batches replace its set; lights
//!    that vanished were dropped by the plan.
//!
//! Besides, the stream holds each light's current set for late receivers:
//! [`PhotonStream::manifest`] describes it, [`PhotonStream::due_for_resend`] returns the
//! sets that have not gone out for a while (every call takes `now`; the stream reads no
//! clock).

use std::collections::{BTreeMap, HashSet};
use std::sync::Arc;
use std::time::{Duration, Instant};

use cloudlight_scenes::Scene;

use super::Emitter;
use super::pack::BatchHeader;
use super::{
    BatchPlan, Manifest, ManifestLight, PackFormat, PackedBatch, Photon, PhotonLight,
    PhotonSettings, PhotonTracer, View, footprint::FootprintCache, footprint::Guide,
    photon_lights_cached, view_points,
};
use crate::bvh::SceneBvh;

/// When a light's batches are traced again.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Retrace {
    /// Only when the light changed (moved, changed power, appeared).
    #[default]
    Changed,
    /// Every iteration, with fresh random numbers (the paper's continuous stream).
    Always,
}

/// A light's current batch set.
#[derive(Clone, Debug)]
pub struct LightSet {
    /// The light as it was traced.
    pub light: PhotonLight,
    /// Increases each time the light is traced again.
    pub generation: u64,
    /// Its batches by slot, one map per refinement pass (the first is pass 0).
    pub passes: Vec<BTreeMap<u32, PackedBatch>>,
    /// When the set last went out (traced or re-sent).
    pub sent_at: Instant,
}

impl LightSet {
    /// Every batch of every pass.
    pub fn batches(&self) -> impl Iterator<Item = &PackedBatch> {
        self.passes.iter().flat_map(|p| p.values())
    }
}

/// One batch to trace.
#[derive(Clone, Debug, PartialEq)]
pub struct BatchJob {
    /// Index into [`IterationPlan::lights`].
    pub light: usize,
    /// Slot among the light's batches.
    pub slot: u32,
    /// The light's batch count.
    pub slots: u32,
    /// The generation being traced.
    pub generation: u64,
    /// Its refinement pass.
    pub pass: u32,
}

/// What one iteration traces.
#[derive(Clone, Debug)]
pub struct IterationPlan {
    /// Scene time, seconds.
    pub t_s: f64,
    /// Every light emitting at `t_s`.
    pub lights: Vec<PhotonLight>,
    /// Batches per light.
    pub plan: BatchPlan,
    /// The tracer's settings, with this iteration's radius fixed.
    pub settings: PhotonSettings,
    /// The batches to trace, light by light and slot by slot.
    pub jobs: Vec<BatchJob>,
    /// Directional lights' emission toward what clients see, by light id (empty while
    /// the stream knows no view, [`PhotonStream::set_views`]).
    pub guides: BTreeMap<u32, Arc<Guide>>,
    /// The clients' views: disks stop at walls beyond which one of them would see their
    /// light ([`super::density::enclose`]). A set traced before a view moved keeps its
    /// radii until its light is traced again.
    pub views: Vec<View>,
}

impl IterationPlan {
    /// The splat radius of this iteration, meters.
    pub fn radius_m(&self) -> f32 {
        self.settings.radius_m.unwrap_or(0.0)
    }
}

/// One traced and packed batch.
#[derive(Clone, Debug)]
pub struct TracedBatch {
    /// The packed batch.
    pub batch: PackedBatch,
    /// Photons stored.
    pub stored: usize,
    /// Photons sent: those stored, merged ([`PhotonSettings::merge`]).
    pub sent: usize,
    /// Time spent tracing.
    pub trace_time: Duration,
    /// Time spent packing.
    pub pack_time: Duration,
}

/// The photon batches of a scene, kept current iteration by iteration.
#[derive(Clone, Debug)]
pub struct PhotonStream {
    settings: PhotonSettings,
    format: PackFormat,
    retrace: Retrace,
    seed: u64,
    sets: BTreeMap<u32, LightSet>,
    iteration: u64,
    footprints: FootprintCache,
    views: Vec<View>,
    /// The views each guided light's current set was traced toward.
    guided: BTreeMap<u32, Vec<View>>,
}

impl PhotonStream {
    /// A stream without batches yet.
    pub fn new(settings: PhotonSettings, format: PackFormat, retrace: Retrace, seed: u64) -> Self {
        PhotonStream {
            settings,
            format,
            retrace,
            seed,
            sets: BTreeMap::new(),
            iteration: 0,
            footprints: FootprintCache::default(),
            views: Vec::new(),
            guided: BTreeMap::new(),
        }
    }

    /// The views of the clients (their cameras now): from the next plan on, directional
    /// lights send [`PhotonSettings::guide_share`] of their photons toward what they see.
    /// Invalid views are ignored; none: uniform emission.
    pub fn set_views(&mut self, views: Vec<View>) {
        self.views = views.into_iter().filter(View::is_valid).collect();
    }

    /// The views emission is guided toward.
    pub fn views(&self) -> &[View] {
        &self.views
    }

    /// The tracer's settings.
    pub fn settings(&self) -> &PhotonSettings {
        &self.settings
    }

    /// The packing.
    pub fn format(&self) -> PackFormat {
        self.format
    }

    /// Iterations planned so far.
    pub fn iteration(&self) -> u64 {
        self.iteration
    }

    /// The current set of each light, by light id.
    pub fn sets(&self) -> &BTreeMap<u32, LightSet> {
        &self.sets
    }

    /// Phase 1: plans an iteration at scene time `t_s` (BVH `bvh` at that time) and drops
    /// the sets of lights that no longer emit.
    pub fn plan(&mut self, scene: &Scene, bvh: &SceneBvh, t_s: f64) -> IterationPlan {
        let lights = photon_lights_cached(scene, t_s, bvh.triangles(), &mut self.footprints);
        let plan = BatchPlan::new(&lights, &self.settings);
        let radius = PhotonTracer::new(scene, bvh, self.settings, &plan, self.seed).radius();
        // A radius the user fixed is every photon's; else it is the reference of the
        // photons' density radii.
        let settings = PhotonSettings {
            radius_m: Some(radius),
            density_radius: self.settings.density_radius && self.settings.radius_m.is_none(),
            ..self.settings
        };
        let live: HashSet<u32> = lights.iter().map(|l| l.id).collect();
        self.sets.retain(|id, _| live.contains(id));
        self.guided.retain(|id, _| live.contains(id));
        let reach = self.reach_m(bvh);
        let guides = self.guides(bvh, &lights, reach);
        self.iteration += 1;
        let mut jobs = Vec::new();
        for (index, light) in lights.iter().enumerate() {
            let slots = plan.batches_of(light.id);
            let current = self.sets.get(&light.id);
            let guided = guides.contains_key(&light.id);
            let changed = current.is_none_or(|s| {
                self.retrace == Retrace::Always
                    || s.light != *light
                    || s.passes.first().map_or(0, |p| p.len() as u32) != slots
                    || match (self.guided.get(&light.id), guided) {
                        (Some(before), true) => views_moved(before, &self.views, reach),
                        (None, false) => false,
                        _ => true,
                    }
            });
            let (generation, pass) = match current {
                Some(s) if !changed => {
                    let held = s.passes.len() as u32;
                    if held >= self.settings.passes.max(1) {
                        continue;
                    }
                    (s.generation, held)
                }
                _ => (current.map_or(1, |s| s.generation + 1), 0),
            };
            if pass == 0 {
                if guided {
                    self.guided.insert(light.id, self.views.clone());
                } else {
                    self.guided.remove(&light.id);
                }
            }
            jobs.extend((0..slots).map(|slot| BatchJob {
                light: index,
                slot,
                slots,
                generation,
                pass,
            }));
        }
        IterationPlan {
            t_s,
            lights,
            plan,
            settings,
            jobs,
            guides,
            views: self.views.clone(),
        }
    }

    /// Each directional light's guide toward the surfaces the views see (within `reach` m).
    fn guides(
        &self,
        bvh: &SceneBvh,
        lights: &[PhotonLight],
        reach: f32,
    ) -> BTreeMap<u32, Arc<Guide>> {
        let share = self.settings.guide_share;
        let directional = lights
            .iter()
            .any(|l| matches!(l.emitter, Emitter::Directional(_)));
        if self.views.is_empty() || share.is_nan() || share <= 0.0 || !directional {
            return BTreeMap::new();
        }
        let points = view_points(bvh, &self.views);
        lights
            .iter()
            .filter_map(|l| match &l.emitter {
                Emitter::Directional(f) => {
                    f.guide(&points, reach, share).map(|g| (l.id, Arc::new(g)))
                }
                _ => None,
            })
            .collect()
    }

    /// How far from what a client sees the guide looks, meters.
    fn reach_m(&self, bvh: &SceneBvh) -> f32 {
        let (lo, hi) = bvh.bounds();
        let half_diag = (hi - lo).length() * 0.5;
        if half_diag.is_finite() {
            half_diag * self.settings.guide_reach
        } else {
            0.0
        }
    }

    /// Phase 2: traces and packs `job` of `plan` (seed `seed`).
    pub fn trace(
        scene: &Scene,
        bvh: &SceneBvh,
        plan: &IterationPlan,
        job: &BatchJob,
        seed: u64,
        format: PackFormat,
    ) -> TracedBatch {
        let light = &plan.lights[job.light];
        let tracer = PhotonTracer::new(scene, bvh, plan.settings, &plan.plan, seed)
            .guided(&plan.guides)
            .seen_from(&plan.views);
        let start = Instant::now();
        let mut photons: Vec<Photon> =
            tracer.trace_pass(light, job.slot, job.slots, job.generation, job.pass);
        let stored = photons.len();
        if plan.settings.merge > 0.0 {
            // A refinement pass is drawn with radii that shrink as passes come: merged
            // within the share of the radius it is drawn at once the light holds all its
            // passes (merged at the traced radius, 32 passes of the Cornell box read 0.0109
            // instead of 0.0100). A first pass is drawn alone until the next comes.
            let cell = match job.pass {
                0 => plan.settings.merge,
                _ => plan.settings.merge * super::progressive_radius_scale(plan.settings.passes),
            };
            photons = super::merge::merge(&photons, cell);
        }
        let trace_time = start.elapsed();
        let start = Instant::now();
        let batch = PackedBatch::pack(
            BatchHeader {
                light: light.id,
                slot: job.slot,
                slots: job.slots,
                generation: job.generation,
                pass: job.pass,
                scene_time_s: plan.t_s,
                emitted: plan.plan.photons_per_batch(light.id),
                receive: plan.settings.receive,
            },
            &photons,
            format,
        );
        TracedBatch {
            batch,
            stored,
            sent: photons.len(),
            trace_time,
            pack_time: start.elapsed(),
        }
    }

    /// The seed batches are traced with.
    pub fn seed(&self) -> u64 {
        self.seed
    }

    /// Phase 3: `light`'s batches of `generation`, pass `pass`, are all traced (sent at
    /// `now`): pass 0 replaces its set, a later pass of the same generation joins it.
    pub fn commit(
        &mut self,
        light: PhotonLight,
        generation: u64,
        pass: u32,
        batches: BTreeMap<u32, PackedBatch>,
        now: Instant,
    ) {
        if pass > 0
            && let Some(set) = self.sets.get_mut(&light.id)
            && set.generation == generation
            && set.passes.len() as u32 == pass
        {
            set.passes.push(batches);
            set.sent_at = now;
            return;
        }
        self.sets.insert(
            light.id,
            LightSet {
                light,
                generation,
                passes: vec![batches],
                sent_at: now,
            },
        );
    }

    /// The complete set as of scene time `t_s`.
    pub fn manifest(&self, t_s: f64) -> Manifest {
        Manifest {
            iteration: self.iteration,
            scene_time_s: t_s,
            lights: self
                .sets
                .values()
                .map(|s| ManifestLight {
                    light: s.light.id,
                    generation: s.generation,
                    slots: s.passes.first().map_or(0, |p| p.len() as u32),
                    passes: s.passes.len() as u32,
                })
                .collect(),
        }
    }

    /// The batches of every set that has not gone out for `period` by `now`; they count as
    /// sent at `now`.
    pub fn due_for_resend(&mut self, period: Duration, now: Instant) -> Vec<PackedBatch> {
        self.sets
            .values_mut()
            .filter(|s| now.saturating_duration_since(s.sent_at) >= period)
            .flat_map(|s| {
                s.sent_at = now;
                s.batches().cloned().collect::<Vec<_>>()
            })
            .collect()
    }

    /// Bytes of packed photons held (the server's memory footprint).
    pub fn footprint_bytes(&self) -> usize {
        self.sets
            .values()
            .flat_map(LightSet::batches)
            .map(|b| b.data.len())
            .sum()
    }

    /// Bytes of photon data per photon held (the format's size when none is held).
    pub fn bytes_per_photon(&self) -> f64 {
        let held: u64 = self
            .sets
            .values()
            .flat_map(LightSet::batches)
            .map(|b| u64::from(b.count))
            .sum();
        if held == 0 {
            return self.format.bytes_per_photon() as f64;
        }
        self.footprint_bytes() as f64 / held as f64
    }

    /// Batches held.
    pub fn batch_count(&self) -> usize {
        self.sets.values().flat_map(LightSet::batches).count()
    }

    /// One whole iteration on this thread: plan, trace every job, commit.
    pub fn iterate(&mut self, scene: &Scene, bvh: &SceneBvh, t_s: f64) -> Iteration {
        let plan = self.plan(scene, bvh, t_s);
        let mut batches = Vec::with_capacity(plan.jobs.len());
        let (mut trace_time, mut pack_time) = (Duration::ZERO, Duration::ZERO);
        let (mut stored, mut sent) = (0, 0);
        let mut per_light: BTreeMap<(usize, u64, u32), BTreeMap<u32, PackedBatch>> =
            BTreeMap::new();
        let mut yields: BTreeMap<usize, LightYield> = BTreeMap::new();
        for job in &plan.jobs {
            let traced = Self::trace(scene, bvh, &plan, job, self.seed, self.format);
            trace_time += traced.trace_time;
            pack_time += traced.pack_time;
            stored += traced.stored;
            sent += traced.sent;
            let light = &plan.lights[job.light];
            let y = yields.entry(job.light).or_insert_with(|| LightYield {
                id: light.id,
                name: light.name.clone(),
                kind: light.emitter.kind().to_string(),
                emitted: 0,
                stored: 0,
            });
            y.emitted += u64::from(plan.plan.photons_per_batch(light.id));
            y.stored += traced.stored as u64;
            per_light
                .entry((job.light, job.generation, job.pass))
                .or_default()
                .insert(job.slot, traced.batch.clone());
            batches.push(traced.batch);
        }
        let now = Instant::now();
        for ((index, generation, pass), set) in per_light {
            self.commit(plan.lights[index].clone(), generation, pass, set, now);
        }
        Iteration {
            radius: plan.radius_m(),
            plan: plan.plan,
            batches,
            stored,
            sent,
            lights: yields.into_values().collect(),
            trace_time,
            pack_time,
        }
    }
}

/// Whether `now` differs from the views `before` a set was guided toward enough to trace
/// it again: another count of views, an eye moved by more than a quarter of the guide's
/// reach, or a view turned by more than 10°. (Smaller moves keep the set: its photons are
/// unbiased whatever they were guided toward, only less dense where the client now looks;
/// a progressive light keeps refining.)
fn views_moved(before: &[View], now: &[View], reach_m: f32) -> bool {
    let forward = |v: &View| (v.camera.target - v.camera.position).normalize_or_zero();
    before.len() != now.len()
        || before.iter().zip(now).any(|(a, b)| {
            a.camera.position.distance(b.camera.position) > 0.25 * reach_m
                || forward(a).dot(forward(b)) < 10f32.to_radians().cos()
        })
}

/// One whole iteration, traced and packed (what benchmarks and tests measure).
#[derive(Clone, Debug)]
pub struct Iteration {
    /// Batches per light.
    pub plan: BatchPlan,
    /// Splat radius, meters.
    pub radius: f32,
    /// The packed batches, in light and slot order.
    pub batches: Vec<PackedBatch>,
    /// Photons stored.
    pub stored: usize,
    /// Photons sent: those stored, merged ([`PhotonSettings::merge`]).
    pub sent: usize,
    /// Photons emitted and stored by each light traced, in light order.
    pub lights: Vec<LightYield>,
    /// Time spent tracing (and merging).
    pub trace_time: Duration,
    /// Time spent packing.
    pub pack_time: Duration,
}

/// What one light emitted and stored in an iteration: how much of its tracing lands where
/// photons are kept (a sun's emission over its footprint, a lamp's over what is around it).
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct LightYield {
    /// Light id.
    pub id: u32,
    /// Its name.
    pub name: String,
    /// What kind of emitter it is ([`Emitter::kind`]).
    pub kind: String,
    /// Photons emitted (every pass traced).
    pub emitted: u64,
    /// Photons stored.
    pub stored: u64,
}

impl LightYield {
    /// Photons stored per photon emitted (0 for a light that emitted none).
    pub fn stored_per_emitted(&self) -> f64 {
        self.stored as f64 / self.emitted.max(1) as f64
    }
}

impl Iteration {
    /// Bytes of photon data (the batches' payloads).
    pub fn data_bytes(&self) -> usize {
        self.batches.iter().map(|b| b.data.len()).sum()
    }

    /// Every photon, decoded from the packed batches (as a client sees them).
    pub fn unpacked(&self) -> Vec<Photon> {
        self.batches
            .iter()
            .flat_map(|b| b.unpack().unwrap_or_default())
            .collect()
    }
}

/// Traces and packs every batch of every light of `scene` at `t_s` (BVH `bvh`): one
/// iteration of a fresh [`PhotonStream`].
pub fn trace_iteration(
    scene: &Scene,
    bvh: &SceneBvh,
    t_s: f64,
    settings: PhotonSettings,
    seed: u64,
    format: PackFormat,
) -> Iteration {
    PhotonStream::new(settings, format, Retrace::Always, seed).iterate(scene, bvh, t_s)
}
