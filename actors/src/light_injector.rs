//! `light_injector`: the first stage of the voxel technique's GI node (CloudLight §4.1).
//!
//! At start it voxelizes the scene (depth from `max_depth` and `budget_mb`, the static
//! objects once). Every `interval_ms` it takes the octree at the current scene time (the
//! moving objects voxelized again), injects the direct light of every light into the
//! leaves with ray-traced shadows ([`inject`](fn@cloudlight_render::voxel::inject)), adding the previous update's gathered
//! irradiance from `cone_tracer` (its `bounce` output, when wired back: one more bounce
//! per update), and sends the leaves' anisotropic radiance with the octree to
//! `octree_filter`.
//!
//! Ports: in [`BOUNCE`] (BounceMsg, `latest`), out [`OUT`] (InjectedMsg).

use std::sync::Arc;

use cloudlight_render::voxel::{
    InjectSettings, Octree, VoxelSettings, Voxelizer, inject, transfer,
};
use cloudlight_render::{BvhKind, SceneBvh};
use cloudlight_runtime::{
    Cadence, CheckParams, EdgeSettings, Input, Latency, NextTick, Policy, Port, Stage, StageCtx,
    StageKind, StageSetup, Stamped, check_range,
};
use cloudlight_scenes::Scene;
use serde::{Deserialize, Serialize};

use crate::wire::voxel::{BounceMsg, InjectedMsg};

/// Technique name of the voxel stages.
pub const TECHNIQUE: &str = "voxels";

/// The leaves' light, one message per update.
pub const OUT: Port<InjectedMsg> = Port::new("out");

/// The previous update's gathered irradiance.
pub const BOUNCE: Port<BounceMsg> = Port::new("bounce");

/// Octree depth and memory a voxel stage voxelizes with (the injector's and every frame
/// renderer's must agree: a frame renderer refuses deltas of another structure).
pub const DEFAULT_MAX_DEPTH: u32 = 6;
/// Default memory budget of the octree, MiB.
pub const DEFAULT_BUDGET_MB: f64 = 256.0;

/// The octree settings of `max_depth` and `budget_mb`, checked.
pub fn voxel_settings(max_depth: u32, budget_mb: f64) -> Result<VoxelSettings, String> {
    check_range(
        "max_depth",
        max_depth as f64,
        1.0,
        cloudlight_render::voxel::MAX_DEPTH as f64,
        "levels",
    )?;
    check_range("budget_mb", budget_mb, 1.0, 65_536.0, "MiB")?;
    Ok(VoxelSettings {
        max_depth,
        budget_bytes: (budget_mb * 1024.0 * 1024.0) as u64,
    })
}

/// Parameters of `light_injector`.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct InjectorParams {
    /// Deepest octree level (the paper: 9).
    pub max_depth: u32,
    /// Memory the octree may take, MiB (the depth shrinks until it fits).
    pub budget_mb: f64,
    /// Light samples per side of a leaf.
    pub samples: u32,
    /// Period of updates, milliseconds (an update that takes longer is followed at once).
    pub interval_ms: f64,
}

impl Default for InjectorParams {
    fn default() -> Self {
        InjectorParams {
            max_depth: DEFAULT_MAX_DEPTH,
            budget_mb: DEFAULT_BUDGET_MB,
            samples: InjectSettings::default().samples,
            interval_ms: 50.0,
        }
    }
}

impl CheckParams for InjectorParams {
    fn check(&self) -> Result<(), String> {
        voxel_settings(self.max_depth, self.budget_mb)?;
        check_range("samples", self.samples as f64, 1.0, 1024.0, "samples")?;
        check_range("interval_ms", self.interval_ms, 0.0, 3.6e6, "ms")
    }
}

/// What `light_injector` reports.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct InjectorReport {
    /// One line for people.
    pub summary: String,
    /// Updates sent.
    pub updates: u64,
    /// Octree depth.
    pub depth: u32,
    /// Leaves of the latest octree.
    pub leaves: usize,
    /// Bytes of the latest octree's geometry per level, root first.
    pub bytes_per_level: Vec<u64>,
    /// Objects voxelized again at every update.
    pub moving_objects: usize,
    /// Updates that added the previous bounce.
    pub bounces_applied: u64,
    /// Bounces that did not fit the octree (its structure changed), dropped.
    pub bounces_stale: u64,
    /// Injection time (voxelizing movers included), p50 / p99 / mean, ms.
    pub inject_ms_p50: f64,
    /// p99, ms.
    pub inject_ms_p99: f64,
    /// Mean, ms.
    pub inject_ms_mean: f64,
    /// Updates that ended after the next one was due.
    pub overruns: u64,
}

/// The light injector stage.
pub struct LightInjector {
    scene: Arc<Scene>,
    voxelizer: Arc<Voxelizer>,
    /// The octree and BVH of a scene that does not move, made once.
    fixed: Option<(Arc<Octree>, Arc<SceneBvh>)>,
    settings: InjectSettings,
    bounce: Option<Arc<Stamped<BounceMsg>>>,
    cadence: Cadence,
    latency: Latency,
    report: InjectorReport,
}

impl LightInjector {
    fn new(setup: &StageSetup) -> anyhow::Result<Self> {
        let params: InjectorParams = setup.params()?;
        params
            .check()
            .map_err(|e| anyhow::anyhow!("{}: params: {e}", setup.info.name))?;
        let scene = Arc::new(cloudlight_scenes::load(&setup.scene)?);
        let settings =
            voxel_settings(params.max_depth, params.budget_mb).map_err(anyhow::Error::msg)?;
        let voxelizer = Arc::new(Voxelizer::new(&scene, &settings));
        let still = voxelizer.moving_objects().is_empty();
        let fixed = still.then(|| {
            (
                Arc::new(voxelizer.octree_at(&scene, 0.0)),
                Arc::new(SceneBvh::at(&scene, 0.0, BvhKind::default())),
            )
        });
        Ok(LightInjector {
            report: InjectorReport {
                depth: voxelizer.grid().depth,
                moving_objects: voxelizer.moving_objects().len(),
                ..Default::default()
            },
            scene,
            voxelizer,
            fixed,
            settings: InjectSettings {
                samples: params.samples,
                seed: setup.seed,
            },
            bounce: None,
            cadence: Cadence::every_ms(params.interval_ms),
            latency: Latency::new(),
        })
    }

    fn publish(&mut self, ctx: &StageCtx) {
        let r = &mut self.report;
        r.inject_ms_p50 = self.latency.p50_ms();
        r.inject_ms_p99 = self.latency.p99_ms();
        r.inject_ms_mean = self.latency.mean_ms();
        r.overruns = self.cadence.overruns();
        r.summary = format!(
            "{} updates (p50 {:.1} ms), {} leaves at depth {}, {:.1} MiB of octree, {} bounces applied",
            r.updates,
            r.inject_ms_p50,
            r.leaves,
            r.depth,
            r.bytes_per_level.iter().sum::<u64>() as f64 / (1 << 20) as f64,
            r.bounces_applied
        );
        ctx.report(serde_json::to_value(&self.report).unwrap_or_default());
    }

    async fn update(&mut self, ctx: &mut StageCtx) -> anyhow::Result<()> {
        let t = ctx.scene_time_s();
        let (scene, voxelizer, fixed) = (
            self.scene.clone(),
            self.voxelizer.clone(),
            self.fixed.clone(),
        );
        let (bounce, settings) = (self.bounce.clone(), self.settings);
        let (octree, injection, applied, seconds) = tokio::task::spawn_blocking(move || {
            let start = std::time::Instant::now();
            let (octree, bvh) = fixed.unwrap_or_else(|| {
                (
                    Arc::new(voxelizer.octree_at(&scene, t)),
                    Arc::new(SceneBvh::at(&scene, t, BvhKind::default())),
                )
            });
            let structure = transfer::structure_of(&octree);
            let indirect = bounce
                .as_ref()
                .filter(|b| {
                    b.body.structure == structure && b.body.leaves.len() == octree.leaves().len()
                })
                .map(|b| b.body.leaves.as_slice());
            let applied = match (&bounce, indirect) {
                (None, _) => None,
                (Some(_), found) => Some(found.is_some()),
            };
            let injection = inject(&octree, &scene, &bvh, t, indirect, &settings);
            (octree, injection, applied, start.elapsed().as_secs_f64())
        })
        .await?;
        match applied {
            Some(true) => self.report.bounces_applied += 1,
            Some(false) => self.report.bounces_stale += 1,
            None => {}
        }
        self.latency.record_s(seconds);
        self.report.leaves = octree.leaves().len();
        self.report.bytes_per_level = octree.bytes_per_level();
        let msg = InjectedMsg {
            update: self.report.updates,
            octree,
            leaves: injection.leaves,
        };
        ctx.send(OUT, t, msg).await?;
        self.report.updates += 1;
        Ok(())
    }
}

#[async_trait::async_trait]
impl Stage for LightInjector {
    async fn on_start(&mut self, ctx: &mut StageCtx) -> anyhow::Result<()> {
        self.publish(ctx);
        Ok(())
    }

    async fn on_tick(&mut self, ctx: &mut StageCtx) -> anyhow::Result<NextTick> {
        if ctx.is_stopping() {
            return Ok(NextTick::Never);
        }
        self.cadence.begin();
        self.update(ctx).await?;
        let next = self.cadence.end_tick();
        self.publish(ctx);
        Ok(next)
    }

    async fn on_input(&mut self, _ctx: &mut StageCtx, input: Input) -> anyhow::Result<()> {
        self.bounce = Some(input.on(BOUNCE)?);
        Ok(())
    }

    async fn on_stop(&mut self, ctx: &mut StageCtx) -> anyhow::Result<()> {
        self.publish(ctx);
        Ok(())
    }
}

/// Registers `light_injector`.
pub fn register(registry: &mut cloudlight_runtime::StageRegistry) {
    registry.register(
        StageKind::new(
            "light_injector",
            TECHNIQUE,
            "voxelizes the scene and injects direct light (plus the previous bounce) into the octree's leaves",
            |s| Ok(Box::new(LightInjector::new(s)?)),
        )
        .input(
            BOUNCE,
            EdgeSettings {
                capacity: 2,
                policy: Policy::Latest,
            },
        )
        .output(OUT)
        .checked_params::<InjectorParams>(),
    );
}
