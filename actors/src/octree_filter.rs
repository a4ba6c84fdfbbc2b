//! `octree_filter`: the second stage of the voxel technique's GI node (CloudLight §4.1):
//! each inner voxel's anisotropic radiance and opacity from its children, composited front
//! to back per direction ([`filter`](fn@cloudlight_render::voxel::filter)), for every update `light_injector` sends.
//!
//! Ports: in [`IN`] (InjectedMsg, `latest`: a newer update supersedes one not yet
//! filtered), out [`OUT`] (FilteredMsg).

use cloudlight_render::voxel::filter;
use cloudlight_runtime::{
    CheckParams, EdgeSettings, Input, Latency, Policy, Port, Stage, StageCtx, StageKind, StageSetup,
};
use serde::{Deserialize, Serialize};

use crate::light_injector::TECHNIQUE;
use crate::wire::voxel::{FilteredMsg, InjectedMsg};

/// The leaves' light.
pub const IN: Port<InjectedMsg> = Port::new("in");
/// Every level's voxels.
pub const OUT: Port<FilteredMsg> = Port::new("out");

/// Parameters of `octree_filter` (none yet).
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FilterParams {}

impl CheckParams for FilterParams {
    fn check(&self) -> Result<(), String> {
        Ok(())
    }
}

/// What `octree_filter` reports.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FilterReport {
    /// One line for people.
    pub summary: String,
    /// Updates filtered.
    pub updates: u64,
    /// Messages whose leaves did not match their octree, dropped.
    pub malformed: u64,
    /// Voxels of the latest update (all levels).
    pub voxels: usize,
    /// Filter time, p50 / p99, ms.
    pub filter_ms_p50: f64,
    /// p99, ms.
    pub filter_ms_p99: f64,
}

/// The octree filter stage.
pub struct OctreeFilter {
    latency: Latency,
    report: FilterReport,
}

impl OctreeFilter {
    fn publish(&mut self, ctx: &StageCtx) {
        let r = &mut self.report;
        r.filter_ms_p50 = self.latency.p50_ms();
        r.filter_ms_p99 = self.latency.p99_ms();
        r.summary = format!(
            "{} updates (p50 {:.1} ms), {} voxels, {} malformed",
            r.updates, r.filter_ms_p50, r.voxels, r.malformed
        );
        ctx.report(serde_json::to_value(&self.report).unwrap_or_default());
    }
}

#[async_trait::async_trait]
impl Stage for OctreeFilter {
    async fn on_start(&mut self, ctx: &mut StageCtx) -> anyhow::Result<()> {
        self.publish(ctx);
        Ok(())
    }

    async fn on_input(&mut self, ctx: &mut StageCtx, input: Input) -> anyhow::Result<()> {
        let msg = input.on(IN)?;
        if msg.body.leaves.len() != msg.body.octree.leaves().len() {
            self.report.malformed += 1;
            tracing::warn!(
                stage = ctx.name(),
                "injected leaves do not match their octree: dropped"
            );
            return Ok(());
        }
        let m = msg.clone();
        let (levels, seconds) = tokio::task::spawn_blocking(move || {
            let start = std::time::Instant::now();
            let levels = filter(&m.body.octree, m.body.leaves.clone());
            (levels, start.elapsed().as_secs_f64())
        })
        .await?;
        self.latency.record_s(seconds);
        self.report.updates += 1;
        self.report.voxels = levels.iter().map(Vec::len).sum();
        let out = FilteredMsg {
            update: msg.body.update,
            octree: msg.body.octree.clone(),
            levels,
        };
        ctx.send(OUT, msg.scene_time_s, out).await?;
        self.publish(ctx);
        Ok(())
    }

    async fn on_stop(&mut self, ctx: &mut StageCtx) -> anyhow::Result<()> {
        self.publish(ctx);
        Ok(())
    }
}

/// Registers `octree_filter`.
pub fn register(registry: &mut cloudlight_runtime::StageRegistry) {
    registry.register(
        StageKind::new(
            "octree_filter",
            TECHNIQUE,
            "filters the injected leaves up the octree (anisotropic, front to back per direction)",
            |s: &StageSetup| {
                let params: FilterParams = s.params()?;
                params.check().map_err(anyhow::Error::msg)?;
                Ok(Box::new(OctreeFilter {
                    latency: Latency::new(),
                    report: FilterReport::default(),
                }))
            },
        )
        .input(
            IN,
            EdgeSettings {
                capacity: 2,
                policy: Policy::Latest,
            },
        )
        .output(OUT)
        .checked_params::<FilterParams>(),
    );
}
