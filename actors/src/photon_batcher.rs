//! `photon_batcher`: the cloud side of the photon technique (CloudLight §4.3).
//!
//! Every `interval_ms` it evaluates the scene's lights at the current scene time, re-traces
//! the batches of each light that changed (or every light, with `retrace = "always"`: the
//! paper's continuous tracing), packs each batch and sends it as soon as it is done, then
//! sends a manifest of the complete set. A light's set that has not gone out for `resend_s`
//! is sent again, so that a client that joined late or lost batches to a `latest` edge
//! catches up (a light re-traced meanwhile is not re-sent).
//! One batcher feeds every client: its cost does not depend on their number.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use cloudlight_render::photon::{
    PackFormat, PackedBatch, PhotonSettings, PhotonStream, Receive, TracedBatch,
};
use cloudlight_render::{BvhKind, SceneBvh};
use cloudlight_runtime::stage::show_number;
use cloudlight_runtime::{
    Cadence, CheckParams, EdgeSettings, Input, Latency, NextTick, Policy, Port, Stage, StageCtx,
    StageKind, StageSetup, lock,
};
use cloudlight_scenes::{Scene, View};
use serde::{Deserialize, Serialize};

pub use cloudlight_render::photon::Retrace;

use crate::wire::PhotonMsg;

/// Batches and manifests, in the order they are made.
pub const OUT: Port<PhotonMsg> = Port::new("out");

/// Clients' views (an edge from each client's `view` port): a sun's photons are guided
/// toward what they see ([`BatcherParams::guide_share`]). Optional: without it emission
/// stays uniform over the sun's footprint.
pub const VIEWS: Port<View> = Port::new("views");

/// Default settings of the `views` edge: only a client's newest view matters.
pub const VIEW_EDGE: EdgeSettings = EdgeSettings {
    capacity: 4,
    policy: Policy::Latest,
};

/// A client's view older than this no longer guides emission (the client left or its
/// edge is down).
pub const VIEW_TTL: Duration = Duration::from_secs(2);

/// Technique name of the photon stages.
pub const TECHNIQUE: &str = "photons";

/// Parameters of `photon_batcher`.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BatcherParams {
    /// Photons per iteration over all lights (sets photons per watt from the scene's power
    /// at time 0). Default [`cloudlight_render::photon::DEFAULT_PHOTONS`] (10,000) when
    /// `photons_per_watt` is absent.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub photons: Option<u64>,
    /// Photons per emitted watt (summed over channels); overrides `photons`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub photons_per_watt: Option<f64>,
    /// Photons per batch.
    #[serde(default = "default_batch_size")]
    pub batch_size: u32,
    /// Diffuse bounces stored per path.
    #[serde(default = "default_bounces")]
    pub bounces: u32,
    /// Photons expected in one splat disk (sets the radius).
    #[serde(default = "default_per_disk")]
    pub photons_per_disk: f32,
    /// A fixed splat radius, meters.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub radius_m: Option<f32>,
    /// Each photon's radius from the density of photons around it (ignored with
    /// `radius_m`); false: one radius per iteration.
    #[serde(default = "default_density_radius")]
    pub density_radius: bool,
    /// Refinement passes of a light that stands still (progressive photon mapping): one
    /// more set of fresh photons per iteration until a light holds this many; clients draw
    /// them together with shrinking radii. 1: a still light is traced once. Ignored with
    /// `retrace = "always"`.
    #[serde(default = "default_passes")]
    pub passes: u32,
    /// Period of iterations, milliseconds (an iteration that takes longer is followed at
    /// once by the next).
    #[serde(default = "default_interval")]
    pub interval_ms: f64,
    /// `changed` (default) or `always`.
    #[serde(default)]
    pub retrace: Retrace,
    /// Re-send a light's current set when it has not gone out for this long, seconds
    /// (0: never).
    #[serde(default = "default_resend")]
    pub resend_s: f64,
    /// `compact8` (default: ~6–7 bytes per photon, coded against neighbours), `compact12` or
    /// `wide20`.
    #[serde(default = "default_format")]
    pub format: String,
    /// What each photon carries to tell which surfaces it lights: `normal` (default: its
    /// surface's normal; no light rounds an edge) or `direction` (the direction it
    /// travelled; a closed box's corners get more light, open scenes leak).
    #[serde(default)]
    pub receive: Receive,
    /// Share of a sun's photons sent toward what clients see, when their views arrive on
    /// `views` (0 to 1; 0: uniform over the sun's footprint). Measured on `city:250000`
    /// (`bench quality`, 160k photons): relMSE 0.64 → 0.30.
    #[serde(default = "default_guide_share")]
    pub guide_share: f32,
    /// How far from a surface a client sees the guide looks for the photons that light
    /// it, as a fraction of the scene's half diagonal (0.001 to 1).
    #[serde(default = "default_guide_reach")]
    pub guide_reach: f32,
    /// Rounds of photon relaxation per batch (0 to 64; 0, the default: none): photons pushed
    /// apart on their surfaces before their radii are set (first passes only: refinement
    /// passes of a still light converge by number). Lowers the error where noise
    /// dominates it (the Cornell box at 10k photons: relMSE 0.0371 → 0.0295 at 6 rounds),
    /// raises it where bias does (`city:250000`: 0.180 → 0.234 at 160k photons).
    #[serde(default)]
    pub relax: u32,
    /// Times a disk that overhangs its surface (an edge, a pot, a pillar) is halved at
    /// most, for photons that carry their surface's normal (0 to 8; default 3; 0: never):
    /// the dungeon's courtyard after 32 passes 0.083–0.088 → 0.069–0.072
    /// ([`PhotonSettings::fit`]).
    #[serde(default = "default_fit")]
    pub fit: u32,
    /// Each batch's photons within a cell of this fraction of their radius (receiving
    /// alike) merged into one before packing, 0 to 2 (0: none; default 0.5): the Cornell
    /// box's 10k photons go out as ~3.7k, 62 → 23 KB an update, at the same relMSE within
    /// 1% ([`PhotonSettings::merge`]; the README's "Merging photons").
    #[serde(default = "default_merge")]
    pub merge: f32,
}

fn default_fit() -> u32 {
    PhotonSettings::default().fit
}

fn default_merge() -> f32 {
    PhotonSettings::default().merge
}

fn default_guide_share() -> f32 {
    PhotonSettings::default().guide_share
}
fn default_guide_reach() -> f32 {
    PhotonSettings::default().guide_reach
}

fn default_batch_size() -> u32 {
    10_000
}
fn default_bounces() -> u32 {
    PhotonSettings::default().bounces
}
fn default_per_disk() -> f32 {
    PhotonSettings::default().photons_per_disk
}
fn default_density_radius() -> bool {
    PhotonSettings::default().density_radius
}
fn default_passes() -> u32 {
    PhotonSettings::default().passes
}
fn default_interval() -> f64 {
    33.0
}
fn default_resend() -> f64 {
    1.0
}
fn default_format() -> String {
    PackFormat::Compact8.name().into()
}

impl Default for BatcherParams {
    fn default() -> Self {
        BatcherParams {
            photons: None,
            photons_per_watt: None,
            batch_size: default_batch_size(),
            bounces: default_bounces(),
            photons_per_disk: default_per_disk(),
            radius_m: None,
            density_radius: default_density_radius(),
            passes: default_passes(),
            interval_ms: default_interval(),
            retrace: Retrace::default(),
            resend_s: default_resend(),
            format: default_format(),
            receive: Receive::default(),
            guide_share: default_guide_share(),
            guide_reach: default_guide_reach(),
            relax: 0,
            fit: default_fit(),
            merge: default_merge(),
        }
    }
}

/// What `photon_batcher` reports (its stage report, as JSON).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct BatcherReport {
    /// One line for people.
    pub summary: String,
    /// Iterations done.
    pub iterations: u64,
    /// Lights emitting.
    pub lights: usize,
    /// Generation of each light's current set, by light name.
    pub generations: BTreeMap<String, u64>,
    /// Batches held (one iteration's worth).
    pub batches: usize,
    /// Photons per batch.
    pub batch_size: u32,
    /// Photons per emitted watt.
    pub photons_per_watt: f64,
    /// Batches traced so far.
    pub batches_traced: u64,
    /// Photons emitted so far.
    pub photons_emitted: u64,
    /// Photons stored by the last iteration that traced.
    pub photons_stored: u64,
    /// Photons sent by the last iteration that traced (those stored, merged).
    #[serde(default)]
    pub photons_sent: u64,
    /// Splat radius of the last iteration, meters.
    pub radius_m: f32,
    /// Bytes of packed photons held.
    pub footprint_bytes: usize,
    /// Bytes of data per photon held (Compact8's varies with the batch).
    pub bytes_per_photon: f64,
    /// Photon bytes handed downstream.
    pub bytes_sent: u64,
    /// `bytes_sent` over the run so far, megabits per second.
    pub mbps_sent: f64,
    /// Times a set was re-sent.
    pub resends: u64,
    /// Trace time per batch, p50 and mean, ms.
    pub trace_ms_p50: f64,
    /// Mean trace time per batch, ms.
    pub trace_ms_mean: f64,
    /// Packing time per batch, p50, ms.
    pub pack_ms_p50: f64,
    /// Mean packing time per batch, ms.
    pub pack_ms_mean: f64,
    /// Hand-off time per message downstream, p50, ms.
    pub send_ms_p50: f64,
    /// Mean hand-off time per message, ms.
    pub send_ms_mean: f64,
    /// Iteration time, p50, ms.
    pub iteration_ms_p50: f64,
    /// Iteration time, p99, ms.
    pub iteration_ms_p99: f64,
    /// Mean iteration time, ms.
    pub iteration_ms_mean: f64,
    /// Iterations that ended after the next one was due.
    pub overruns: u64,
    /// Clients whose views guide emission now.
    pub views_in_use: usize,
    /// Views received.
    pub views_received: u64,
    /// Views dropped for numbers out of range.
    pub views_rejected: u64,
}

/// Figures the batcher keeps.
struct Figures {
    iterations: u64,
    batches_traced: u64,
    photons_emitted: u64,
    photons_stored_last: u64,
    photons_sent_last: u64,
    radius_m: f32,
    bytes_sent: u64,
    resends: u64,
    trace: Latency,
    pack: Latency,
    send: Latency,
    iteration: Latency,
    started: Instant,
    views_received: u64,
    views_rejected: u64,
}

/// The photon batcher stage.
pub struct PhotonBatcher {
    params: BatcherParams,
    scene: Arc<Scene>,
    /// The kernel; shared with the blocking threads that plan and trace.
    stream: Arc<Mutex<PhotonStream>>,
    format: PackFormat,
    bvh: Option<Arc<SceneBvh>>,
    cadence: Cadence,
    figures: Figures,
    /// Each client's newest view, by sending instance, and when it came.
    views: BTreeMap<String, (View, Instant)>,
}

impl PhotonBatcher {
    fn new(setup: &StageSetup) -> anyhow::Result<Self> {
        let params: BatcherParams = setup.params()?;
        params
            .check()
            .map_err(|e| anyhow::anyhow!("{}: params: {e}", setup.info.name))?;
        let format = PackFormat::parse(&params.format).expect("checked");
        let scene = Arc::new(cloudlight_scenes::load(&setup.scene)?);
        let settings = params
            .settings_for(&scene)
            .map_err(|e| anyhow::anyhow!("{}: params: {e}", setup.info.name))?;
        let stream = PhotonStream::new(settings, format, params.retrace, setup.seed);
        let cadence = Cadence::every_ms(params.interval_ms);
        Ok(PhotonBatcher {
            params,
            scene,
            stream: Arc::new(Mutex::new(stream)),
            format,
            bvh: None,
            cadence,
            figures: Figures {
                iterations: 0,
                batches_traced: 0,
                photons_emitted: 0,
                photons_stored_last: 0,
                photons_sent_last: 0,
                radius_m: 0.0,
                bytes_sent: 0,
                resends: 0,
                trace: Latency::new(),
                pack: Latency::new(),
                send: Latency::new(),
                iteration: Latency::new(),
                started: Instant::now(),
                views_received: 0,
                views_rejected: 0,
            },
            views: BTreeMap::new(),
        })
    }

    fn report(&self) -> BatcherReport {
        let f = &self.figures;
        let stream = lock(&self.stream);
        let elapsed = f.started.elapsed().as_secs_f64().max(1e-9);
        let footprint = stream.footprint_bytes();
        let batches = stream.batch_count();
        let settings = *stream.settings();
        let mbps_sent = f.bytes_sent as f64 * 8.0 / elapsed / 1e6;
        BatcherReport {
            summary: format!(
                "{} iterations (p50 {:.1} ms: trace {:.1}, pack {:.2}), {} batches of {} photons ({} stored, {} sent, last iteration), {:.0} kB per set, {:.1} Mbps sent",
                f.iterations,
                f.iteration.p50_ms(),
                f.trace.p50_ms(),
                f.pack.p50_ms(),
                batches,
                settings.batch_size,
                f.photons_stored_last,
                f.photons_sent_last,
                footprint as f64 / 1e3,
                mbps_sent
            ),
            iterations: f.iterations,
            lights: stream.sets().len(),
            generations: stream
                .sets()
                .values()
                .map(|s| (s.light.name.clone(), s.generation))
                .collect(),
            batches,
            batch_size: settings.batch_size,
            photons_per_watt: settings.photons_per_watt,
            batches_traced: f.batches_traced,
            photons_emitted: f.photons_emitted,
            photons_stored: f.photons_stored_last,
            photons_sent: f.photons_sent_last,
            radius_m: f.radius_m,
            footprint_bytes: footprint,
            bytes_per_photon: stream.bytes_per_photon(),
            bytes_sent: f.bytes_sent,
            mbps_sent,
            resends: f.resends,
            trace_ms_p50: f.trace.p50_ms(),
            trace_ms_mean: f.trace.mean_ms(),
            pack_ms_p50: f.pack.p50_ms(),
            pack_ms_mean: f.pack.mean_ms(),
            send_ms_p50: f.send.p50_ms(),
            send_ms_mean: f.send.mean_ms(),
            iteration_ms_p50: f.iteration.p50_ms(),
            iteration_ms_p99: f.iteration.p99_ms(),
            iteration_ms_mean: f.iteration.mean_ms(),
            overruns: self.cadence.overruns(),
            views_in_use: stream.views().len(),
            views_received: f.views_received,
            views_rejected: f.views_rejected,
        }
    }

    fn publish(&self, ctx: &StageCtx) {
        ctx.report(serde_json::to_value(self.report()).unwrap_or_default());
    }

    /// The BVH at scene time `t`: built once for static geometry, again each iteration when
    /// objects move (on a blocking thread: a million triangles take half a second).
    async fn bvh_at(&mut self, t: f64) -> anyhow::Result<Arc<SceneBvh>> {
        if let Some(b) = &self.bvh
            && !self.scene.has_moving_geometry()
        {
            return Ok(b.clone());
        }
        let scene = self.scene.clone();
        let b = Arc::new(
            tokio::task::spawn_blocking(move || SceneBvh::at(&scene, t, BvhKind::default()))
                .await?,
        );
        self.bvh = Some(b.clone());
        Ok(b)
    }

    async fn send(&mut self, ctx: &mut StageCtx, t: f64, msg: PhotonMsg) -> anyhow::Result<()> {
        let bytes = match &msg {
            PhotonMsg::Batch(b) => b.data.len() as u64,
            PhotonMsg::Manifest(_) => 0,
        };
        let start = Instant::now();
        ctx.send(OUT, t, msg).await?;
        self.figures.send.record(start.elapsed());
        self.figures.bytes_sent += bytes;
        Ok(())
    }

    fn count(&mut self, traced: &TracedBatch) {
        let f = &mut self.figures;
        f.trace.record(traced.trace_time);
        f.pack.record(traced.pack_time);
        f.batches_traced += 1;
        f.photons_emitted += traced.batch.header.emitted as u64;
    }

    /// One iteration of the kernel: plan, trace each batch on a blocking thread and send it
    /// as soon as it is packed, commit each light's set, send the manifest; then re-send the
    /// sets that have not gone out for `resend_s`.
    async fn iterate(&mut self, ctx: &mut StageCtx) -> anyhow::Result<()> {
        let started = Instant::now();
        let t = ctx.scene_time_s();
        let bvh = self.bvh_at(t).await?;
        self.views.retain(|_, (_, at)| at.elapsed() < VIEW_TTL);
        lock(&self.stream).set_views(self.views.values().map(|(v, _)| *v).collect());
        let (stream, scene) = (self.stream.clone(), self.scene.clone());
        let bvh_c = bvh.clone();
        let plan = Arc::new(
            tokio::task::spawn_blocking(move || lock(&stream).plan(&scene, &bvh_c, t)).await?,
        );
        self.figures.radius_m = plan.radius_m();
        let (seed, format) = (ctx.seed(), self.format);
        let (mut stored, mut sent) = (0u64, 0u64);
        let mut done: BTreeMap<(usize, u32), BTreeMap<u32, PackedBatch>> = BTreeMap::new();
        for (k, job) in plan.jobs.iter().enumerate() {
            if ctx.is_stopping() {
                return Ok(());
            }
            let (scene, bvh, plan_c) = (self.scene.clone(), bvh.clone(), plan.clone());
            let traced = tokio::task::spawn_blocking(move || {
                PhotonStream::trace(&scene, &bvh, &plan_c, &plan_c.jobs[k], seed, format)
            })
            .await?;
            self.count(&traced);
            stored += traced.stored as u64;
            sent += traced.sent as u64;
            self.send(ctx, t, PhotonMsg::Batch(traced.batch.clone()))
                .await?;
            let set = done.entry((job.light, job.pass)).or_default();
            set.insert(job.slot, traced.batch);
            if set.len() as u32 == job.slots {
                let batches = done.remove(&(job.light, job.pass)).unwrap_or_default();
                lock(&self.stream).commit(
                    plan.lights[job.light].clone(),
                    job.generation,
                    job.pass,
                    batches,
                    Instant::now(),
                );
            }
        }
        if stored > 0 {
            self.figures.photons_stored_last = stored;
            self.figures.photons_sent_last = sent;
        }
        let manifest = lock(&self.stream).manifest(t);
        self.send(ctx, t, PhotonMsg::Manifest(manifest)).await?;
        if self.params.resend_s > 0.0 {
            let period = Duration::from_secs_f64(self.params.resend_s);
            let due = lock(&self.stream).due_for_resend(period, Instant::now());
            if !due.is_empty() {
                self.figures.resends += 1;
                for b in due {
                    self.send(ctx, t, PhotonMsg::Batch(b)).await?;
                }
                let manifest = lock(&self.stream).manifest(t);
                self.send(ctx, t, PhotonMsg::Manifest(manifest)).await?;
            }
        }
        self.figures.iterations += 1;
        self.figures.iteration.record(started.elapsed());
        Ok(())
    }
}

#[async_trait::async_trait]
impl Stage for PhotonBatcher {
    async fn on_start(&mut self, ctx: &mut StageCtx) -> anyhow::Result<()> {
        self.figures.started = Instant::now();
        self.publish(ctx);
        Ok(())
    }

    async fn on_input(&mut self, ctx: &mut StageCtx, input: Input) -> anyhow::Result<()> {
        let view = input.on(VIEWS)?;
        self.figures.views_received += 1;
        if view.body.is_valid() {
            self.views
                .insert(input.from().to_string(), (view.body, Instant::now()));
        } else {
            self.figures.views_rejected += 1;
            tracing::warn!(
                stage = ctx.name(),
                from = input.from(),
                "view dropped: numbers out of range"
            );
        }
        Ok(())
    }

    async fn on_tick(&mut self, ctx: &mut StageCtx) -> anyhow::Result<NextTick> {
        if ctx.is_stopping() {
            return Ok(NextTick::Never);
        }
        self.cadence.begin();
        self.iterate(ctx).await?;
        let next = self.cadence.end_tick();
        self.publish(ctx);
        Ok(next)
    }

    async fn on_stop(&mut self, ctx: &mut StageCtx) -> anyhow::Result<()> {
        self.publish(ctx);
        Ok(())
    }
}

/// Default settings of edges into a photon client: `latest`, deep enough for a few
/// iterations of batches — a slow client gets newer batches instead of slowing the batcher
/// down for everyone, and the periodic re-send fills what it missed.
pub const PHOTON_EDGE: EdgeSettings = EdgeSettings {
    capacity: 64,
    policy: Policy::Latest,
};

/// Most photons per iteration: what one iteration's sets can hold in memory (about 50 bytes
/// a stored photon, several bounces each) with room to spare on a 24 GiB machine.
pub const MAX_PHOTONS: u64 = 10_000_000;
/// Most photons per batch: one batch is one message (12–20 bytes a photon), well inside the
/// transport's message limit.
pub const MAX_BATCH_PHOTONS: u32 = 1_000_000;

impl BatcherParams {
    /// The photon tracer's settings for `scene`: the budget from `photons` or
    /// `photons_per_watt` and the scene's lights, which must come to at most [`MAX_PHOTONS`]
    /// per iteration.
    pub fn settings_for(&self, scene: &cloudlight_scenes::Scene) -> Result<PhotonSettings, String> {
        let mut settings = PhotonSettings::for_stage_budget(
            scene,
            self.photons,
            self.photons_per_watt,
            self.batch_size,
        );
        settings.bounces = self.bounces;
        settings.photons_per_disk = self.photons_per_disk;
        settings.radius_m = self.radius_m;
        settings.density_radius = self.density_radius;
        settings.passes = self.passes;
        settings.receive = self.receive;
        settings.guide_share = self.guide_share;
        settings.guide_reach = self.guide_reach;
        settings.relax = self.relax;
        settings.fit = self.fit;
        settings.merge = self.merge;
        let lights = cloudlight_render::photon::photon_lights(scene, 0.0);
        let per_iteration =
            cloudlight_render::photon::BatchPlan::new(&lights, &settings).total_photons();
        if per_iteration > MAX_PHOTONS {
            return Err(format!(
                "`photons_per_watt` = {} gives {per_iteration} photons per iteration for this scene's {:.3} W, more than {MAX_PHOTONS}",
                show_number(settings.photons_per_watt),
                lights.iter().map(|l| l.watts()).sum::<f64>(),
            ));
        }
        Ok(settings)
    }
}

impl cloudlight_runtime::CheckParams for BatcherParams {
    fn check(&self) -> Result<(), String> {
        use cloudlight_runtime::check_range;
        if PackFormat::parse(&self.format).is_none() {
            return Err(format!(
                "`format` must be {}, not `{}`",
                PackFormat::NAMES,
                self.format
            ));
        }
        if let Some(n) = self.photons {
            check_range("photons", n as f64, 1.0, MAX_PHOTONS as f64, "photons")?;
        }
        if let Some(p) = self.photons_per_watt {
            check_range("photons_per_watt", p, 1e-6, 1e9, "photons per watt")?;
        }
        check_range(
            "batch_size",
            self.batch_size as f64,
            1.0,
            MAX_BATCH_PHOTONS as f64,
            "photons",
        )?;
        check_range("bounces", self.bounces as f64, 0.0, 64.0, "bounces")?;
        check_range("passes", self.passes as f64, 1.0, 1024.0, "passes")?;
        check_range("relax", self.relax as f64, 0.0, 64.0, "rounds")?;
        check_range("fit", self.fit as f64, 0.0, 8.0, "halvings")?;
        check_range("merge", self.merge as f64, 0.0, 2.0, "radii")?;
        check_range(
            "photons_per_disk",
            self.photons_per_disk as f64,
            0.01,
            1e6,
            "photons",
        )?;
        if let Some(r) = self.radius_m {
            check_range("radius_m", r as f64, 1e-6, 1e4, "m")?;
        }
        check_range(
            "guide_share",
            self.guide_share as f64,
            0.0,
            1.0,
            "(a share of the photons)",
        )?;
        check_range(
            "guide_reach",
            self.guide_reach as f64,
            1e-3,
            1.0,
            "of the scene's half diagonal",
        )?;
        check_range("interval_ms", self.interval_ms, 0.0, 3.6e6, "ms")?;
        check_range("resend_s", self.resend_s, 0.0, 86_400.0, "s")
    }
}

/// Registers `photon_batcher`.
pub fn register(registry: &mut cloudlight_runtime::StageRegistry) {
    registry.register(
        StageKind::new(
            "photon_batcher",
            TECHNIQUE,
            "traces photon batches per light (re-tracing lights that change) and streams them packed",
            |s| Ok(Box::new(PhotonBatcher::new(s)?)),
        )
        .optional_input(VIEWS, VIEW_EDGE)
        .output(OUT)
        .checked_params::<BatcherParams>()
        .scene_check(|table, scene| {
            let params: BatcherParams = cloudlight_runtime::parse_params(table)?;
            params.settings_for(crate::the_scene(scene)?).map(|_| ())
        }),
    );
}
