//! `photon_batcher`: the cloud side of the photon technique (CloudLight §4.3).
//!
//! Every `interval_ms` it evaluates the scene's lights at the current scene time, re-traces
//! the batches of each light that changed (or every light, with `retrace = "always"`: the
//! paper's continuous tracing), packs each batch and sends it as soon as it is done, then
//! sends a manifest of the complete set. A light's set that has not gone out for `resend_s`
//! is sent again, so that a client that joined late or lost batches to a `latest` edge
//! catches up (a light re-traced meanwhile is not re-sent).
//! One batcher feeds every client: its cost does not depend on their number.

use std::collections::{BTreeMap, HashSet};
use std::sync::Arc;
use std::time::{Duration, Instant};

use cloudlight_render::photon::{
    BatchPlan, Manifest, ManifestLight, PackFormat, PackedBatch, PhotonLight, PhotonSettings,
    PhotonTracer, pack::BatchHeader, photon_lights_in,
};
use cloudlight_render::{BvhKind, SceneBvh};
use cloudlight_runtime::{EdgeSettings, NextTick, Policy, Stage, StageCtx, StageKind, StageSetup};
use cloudlight_scenes::Scene;
use hdrhistogram::Histogram;
use serde::Deserialize;

use crate::wire::PhotonMsg;

/// Technique name of the photon stages.
pub const TECHNIQUE: &str = "photons";

/// When a light's batches are traced again.
#[derive(Clone, Copy, Debug, Default, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum Retrace {
    /// Only when the light changed (moved, changed power, appeared).
    #[default]
    Changed,
    /// Every iteration, with fresh random numbers (the paper's continuous stream).
    Always,
}

/// Parameters of `photon_batcher`.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BatcherParams {
    /// Photons per iteration over all lights (sets photons per watt from the scene's power
    /// at time 0). Default 10,000 when `photons_per_watt` is absent.
    pub photons: Option<u64>,
    /// Photons per emitted watt (summed over channels); overrides `photons`.
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
    pub radius_m: Option<f32>,
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
    /// `compact12` (default) or `wide20`.
    #[serde(default = "default_format")]
    pub format: String,
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
fn default_interval() -> f64 {
    33.0
}
fn default_resend() -> f64 {
    1.0
}
fn default_format() -> String {
    "compact12".into()
}

/// A light's current batch set.
struct LightSet {
    light: PhotonLight,
    generation: u64,
    batches: BTreeMap<u32, PackedBatch>,
    /// When these batches were last sent (traced or re-sent).
    sent_at: Instant,
}

/// Figures the batcher reports.
struct Figures {
    iterations: u64,
    batches_traced: u64,
    photons_emitted: u64,
    photons_stored_last: u64,
    bytes_sent: u64,
    resends: u64,
    trace_us: Histogram<u64>,
    pack_us: Histogram<u64>,
    send_us: Histogram<u64>,
    iteration_us: Histogram<u64>,
    started: Instant,
}

/// The photon batcher stage.
pub struct PhotonBatcher {
    params: BatcherParams,
    scene: Arc<Scene>,
    settings: PhotonSettings,
    format: PackFormat,
    bvh: Option<Arc<SceneBvh>>,
    sets: BTreeMap<u32, LightSet>,
    iteration: u64,
    next_due: Option<Instant>,
    figures: Figures,
}

fn histogram() -> Histogram<u64> {
    Histogram::new(3).expect("3 significant digits is valid")
}

fn ms(h: &Histogram<u64>, q: f64) -> f64 {
    if h.is_empty() {
        0.0
    } else {
        h.value_at_quantile(q) as f64 / 1000.0
    }
}

fn mean_ms(h: &Histogram<u64>) -> f64 {
    if h.is_empty() { 0.0 } else { h.mean() / 1000.0 }
}

impl PhotonBatcher {
    fn new(setup: &StageSetup) -> anyhow::Result<Self> {
        let params: BatcherParams = setup.params()?;
        let format = PackFormat::parse(&params.format).ok_or_else(|| {
            anyhow::anyhow!(
                "format must be `compact12` or `wide20`, not `{}`",
                params.format
            )
        })?;
        if !(params.interval_ms.is_finite() && params.interval_ms >= 0.0) {
            anyhow::bail!("interval_ms must be a non-negative number");
        }
        if params.batch_size == 0 || params.batch_size > cloudlight_render::photon::MAX_BATCH_SIZE {
            anyhow::bail!(
                "batch_size must be in 1..={}",
                cloudlight_render::photon::MAX_BATCH_SIZE
            );
        }
        let scene = Arc::new(cloudlight_scenes::load(&setup.scene)?);
        let mut settings = match (params.photons_per_watt, params.photons) {
            (Some(ppw), _) => PhotonSettings {
                photons_per_watt: ppw,
                batch_size: params.batch_size,
                ..Default::default()
            },
            (None, photons) => {
                PhotonSettings::for_budget(&scene, photons.unwrap_or(10_000), params.batch_size)
            }
        };
        settings.bounces = params.bounces;
        settings.photons_per_disk = params.photons_per_disk;
        settings.radius_m = params.radius_m;
        Ok(PhotonBatcher {
            params,
            scene,
            settings,
            format,
            bvh: None,
            sets: BTreeMap::new(),
            iteration: 0,
            next_due: None,
            figures: Figures {
                iterations: 0,
                batches_traced: 0,
                photons_emitted: 0,
                photons_stored_last: 0,
                bytes_sent: 0,
                resends: 0,
                trace_us: histogram(),
                pack_us: histogram(),
                send_us: histogram(),
                iteration_us: histogram(),
                started: Instant::now(),
            },
        })
    }

    fn report(&self) -> serde_json::Value {
        let f = &self.figures;
        let elapsed = f.started.elapsed().as_secs_f64().max(1e-9);
        let footprint: usize = self
            .sets
            .values()
            .flat_map(|s| s.batches.values())
            .map(|b| b.data.len())
            .sum();
        let batches: usize = self.sets.values().map(|s| s.batches.len()).sum();
        let generations: serde_json::Map<String, serde_json::Value> = self
            .sets
            .values()
            .map(|s| (s.light.name.clone(), s.generation.into()))
            .collect();
        let summary = format!(
            "{} iterations (p50 {:.1} ms: trace {:.1}, pack {:.2}), {} batches of {} photons, {:.0} kB per set, {:.1} Mbps sent",
            f.iterations,
            ms(&f.iteration_us, 0.5),
            ms(&f.trace_us, 0.5),
            ms(&f.pack_us, 0.5),
            batches,
            self.settings.batch_size,
            footprint as f64 / 1e3,
            f.bytes_sent as f64 * 8.0 / elapsed / 1e6
        );
        serde_json::json!({
            "summary": summary,
            "iterations": f.iterations,
            "lights": self.sets.len(),
            "generations": generations,
            "batches": batches,
            "batch_size": self.settings.batch_size,
            "photons_per_watt": self.settings.photons_per_watt,
            "batches_traced": f.batches_traced,
            "photons_emitted": f.photons_emitted,
            "photons_stored": f.photons_stored_last,
            "footprint_bytes": footprint,
            "bytes_per_photon": self.format.bytes_per_photon(),
            "bytes_sent": f.bytes_sent,
            "mbps_sent": f.bytes_sent as f64 * 8.0 / elapsed / 1e6,
            "resends": f.resends,
            "trace_ms_p50": ms(&f.trace_us, 0.5),
            "trace_ms_mean": mean_ms(&f.trace_us),
            "pack_ms_p50": ms(&f.pack_us, 0.5),
            "pack_ms_mean": mean_ms(&f.pack_us),
            "send_ms_p50": ms(&f.send_us, 0.5),
            "send_ms_mean": mean_ms(&f.send_us),
            "iteration_ms_p50": ms(&f.iteration_us, 0.5),
            "iteration_ms_p99": ms(&f.iteration_us, 0.99),
            "iteration_ms_mean": mean_ms(&f.iteration_us),
        })
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
        ctx.send("out", t, msg).await?;
        let _ = self
            .figures
            .send_us
            .record(start.elapsed().as_micros().max(1) as u64);
        self.figures.bytes_sent += bytes;
        Ok(())
    }

    fn manifest(&self, t: f64) -> Manifest {
        Manifest {
            iteration: self.iteration,
            scene_time_s: t,
            lights: self
                .sets
                .values()
                .map(|s| ManifestLight {
                    light: s.light.id,
                    generation: s.generation,
                    slots: s.batches.len() as u32,
                })
                .collect(),
        }
    }

    /// One iteration: re-trace what changed, send it, send the manifest.
    async fn iterate(&mut self, ctx: &mut StageCtx) -> anyhow::Result<()> {
        let started = Instant::now();
        let t = ctx.scene_time_s();
        let bvh = self.bvh_at(t).await?;
        let scene = self.scene.clone();
        let lights = {
            let bvh = bvh.clone();
            tokio::task::spawn_blocking(move || photon_lights_in(&scene, t, bvh.bounds())).await?
        };
        let plan = BatchPlan::new(&lights, &self.settings);
        let radius = {
            let (scene, bvh, settings, plan) =
                (self.scene.clone(), bvh.clone(), self.settings, plan.clone());
            tokio::task::spawn_blocking(move || {
                PhotonTracer::new(&scene, &bvh, settings, &plan, 0).radius()
            })
            .await?
        };
        let settings = PhotonSettings {
            radius_m: Some(radius),
            ..self.settings
        };
        self.iteration += 1;
        let mut stored = 0u64;
        let live: HashSet<u32> = lights.iter().map(|l| l.id).collect();
        self.sets.retain(|id, _| live.contains(id));
        for light in lights {
            let slots = plan.batches_of(light.id);
            let changed = match self.sets.get(&light.id) {
                None => true,
                Some(s) => {
                    self.params.retrace == Retrace::Always
                        || s.light != light
                        || s.batches.len() as u32 != slots
                }
            };
            if !changed {
                continue;
            }
            let generation = self.sets.get(&light.id).map_or(1, |s| s.generation + 1);
            let mut batches = BTreeMap::new();
            for slot in 0..slots {
                if ctx.is_stopping() {
                    return Ok(());
                }
                let (scene, bvh, light_c, format) =
                    (self.scene.clone(), bvh.clone(), light.clone(), self.format);
                let seed = ctx.seed();
                let plan_c = plan.clone();
                let (batch, trace, pack, count) = tokio::task::spawn_blocking(move || {
                    let tracer = PhotonTracer::new(&scene, &bvh, settings, &plan_c, seed);
                    let start = Instant::now();
                    let photons = tracer.trace_batch(&light_c, slot, slots, generation);
                    let trace = start.elapsed();
                    let start = Instant::now();
                    let batch = PackedBatch::pack(
                        BatchHeader {
                            light: light_c.id,
                            slot,
                            slots,
                            generation,
                            scene_time_s: t,
                            emitted: settings.batch_size,
                        },
                        &photons,
                        format,
                    );
                    (batch, trace, start.elapsed(), photons.len())
                })
                .await?;
                let _ = self
                    .figures
                    .trace_us
                    .record(trace.as_micros().max(1) as u64);
                let _ = self.figures.pack_us.record(pack.as_micros().max(1) as u64);
                self.figures.batches_traced += 1;
                self.figures.photons_emitted += settings.batch_size as u64;
                stored += count as u64;
                self.send(ctx, t, PhotonMsg::Batch(batch.clone())).await?;
                batches.insert(slot, batch);
            }
            self.sets.insert(
                light.id,
                LightSet {
                    light,
                    generation,
                    batches,
                    sent_at: Instant::now(),
                },
            );
        }
        if stored > 0 {
            self.figures.photons_stored_last = stored;
        }
        let manifest = self.manifest(t);
        self.send(ctx, t, PhotonMsg::Manifest(manifest)).await?;
        // Re-send the sets that have not gone out for `resend_s` (lights re-traced since
        // went out anyway).
        if self.params.resend_s > 0.0 {
            let period = Duration::from_secs_f64(self.params.resend_s);
            let due: Vec<PackedBatch> = self
                .sets
                .values_mut()
                .filter(|s| s.sent_at.elapsed() >= period)
                .flat_map(|s| {
                    s.sent_at = Instant::now();
                    s.batches.values().cloned().collect::<Vec<_>>()
                })
                .collect();
            if !due.is_empty() {
                self.figures.resends += 1;
                for b in due {
                    self.send(ctx, t, PhotonMsg::Batch(b)).await?;
                }
                let manifest = self.manifest(t);
                self.send(ctx, t, PhotonMsg::Manifest(manifest)).await?;
            }
        }
        self.figures.iterations += 1;
        let _ = self
            .figures
            .iteration_us
            .record(started.elapsed().as_micros().max(1) as u64);
        Ok(())
    }
}

#[async_trait::async_trait]
impl Stage for PhotonBatcher {
    async fn on_start(&mut self, ctx: &mut StageCtx) -> anyhow::Result<()> {
        self.figures.started = Instant::now();
        ctx.report(self.report());
        Ok(())
    }

    async fn on_tick(&mut self, ctx: &mut StageCtx) -> anyhow::Result<NextTick> {
        if ctx.is_stopping() {
            return Ok(NextTick::Never);
        }
        let due = *self.next_due.get_or_insert_with(Instant::now);
        self.iterate(ctx).await?;
        ctx.report(self.report());
        let interval = Duration::from_secs_f64(self.params.interval_ms / 1000.0);
        // Keep the cadence; after an overrun, go on from now instead of bursting.
        let now = Instant::now();
        let next = (due + interval).max(now);
        self.next_due = Some(next);
        Ok(NextTick::After(next - now))
    }

    async fn on_stop(&mut self, ctx: &mut StageCtx) -> anyhow::Result<()> {
        ctx.report(self.report());
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

/// Registers `photon_batcher`.
pub fn register(registry: &mut cloudlight_runtime::StageRegistry) {
    registry.register(
        StageKind::new(
            "photon_batcher",
            TECHNIQUE,
            "traces photon batches per light (re-tracing lights that change) and streams them packed",
            |s| Ok(Box::new(PhotonBatcher::new(s)?)),
        )
        .output::<PhotonMsg>("out")
        .params::<BatcherParams>(),
    );
}
