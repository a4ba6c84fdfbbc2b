//! `cone_tracer`: the last stage of the voxel technique's GI node (CloudLight §4.1): for each
//! filtered update, cones from every voxel gather a view-independent irradiance per side
//! ([`gather`]; intermediate levels where the surface is flat, finer where it is not), which
//! goes
//! - back to `light_injector` on [`BOUNCE`] (the next update reflects it: one more bounce
//!   per update), and
//! - to every frame renderer on [`OUT`] as Haar deltas from the parent level, root level
//!   first, only voxels whose coefficients changed, at `mantissa_bits` of precision, with a
//!   key update every `key_every` ([`DeltaEncoder`]). One gather serves every client.
//!
//! Ports: in [`IN`] (FilteredMsg, `latest`), out [`OUT`] (VoxelDelta, one per level;
//! every delta matters, so its edges should `block`), out [`BOUNCE`] (BounceMsg).

use cloudlight_render::voxel::{
    ConeSettings, DeltaEncoder, FULL_PRECISION, MAX_CONES, TransferSettings, gather, transfer,
};
use cloudlight_runtime::{
    CheckParams, EdgeSettings, Input, Latency, Policy, Port, Stage, StageCtx, StageKind,
    StageSetup, check_range,
};
use serde::{Deserialize, Serialize};

use crate::light_injector::TECHNIQUE;
use crate::wire::voxel::{BounceMsg, FilteredMsg, VoxelDelta};

/// Every level's voxels.
pub const IN: Port<FilteredMsg> = Port::new("in");
/// The gathered irradiance as deltas, one per level, root first.
pub const OUT: Port<VoxelDelta> = Port::new("out");
/// The leaves' gathered irradiance, for the next injection.
pub const BOUNCE: Port<BounceMsg> = Port::new("bounce");

/// What `block` edges of deltas default to.
pub const DELTA_EDGE: EdgeSettings = EdgeSettings {
    capacity: 64,
    policy: Policy::Block,
};

/// Parameters of `cone_tracer`.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ConeTracerParams {
    /// Cones leave from voxels this many levels above the leaves where the surface is flat.
    pub levels_above_leaves: u32,
    /// Below this flatness, finer voxels gather instead.
    pub refine_below_flatness: f32,
    /// Cones per side of a gathering voxel (6: the classic 60° set; 1 to 64).
    pub cones: u32,
    /// Mantissa bits of the sent irradiance (23: exact).
    pub mantissa_bits: u32,
    /// Every this many updates all voxels are sent (0: only the first).
    pub key_every: u64,
}

impl Default for ConeTracerParams {
    fn default() -> Self {
        let (c, t) = (ConeSettings::default(), TransferSettings::default());
        ConeTracerParams {
            levels_above_leaves: c.levels_above_leaves,
            refine_below_flatness: c.refine_below_flatness,
            cones: c.cones,
            mantissa_bits: t.mantissa_bits,
            key_every: t.key_every,
        }
    }
}

impl CheckParams for ConeTracerParams {
    fn check(&self) -> Result<(), String> {
        check_range(
            "levels_above_leaves",
            self.levels_above_leaves as f64,
            0.0,
            8.0,
            "levels",
        )?;
        check_range(
            "cones",
            self.cones as f64,
            1.0,
            f64::from(MAX_CONES),
            "cones",
        )?;
        check_range(
            "refine_below_flatness",
            self.refine_below_flatness as f64,
            0.0,
            1.0,
            "",
        )?;
        check_range(
            "mantissa_bits",
            self.mantissa_bits as f64,
            1.0,
            FULL_PRECISION as f64,
            "bits",
        )?;
        check_range("key_every", self.key_every as f64, 0.0, 1e9, "updates")
    }
}

/// What `cone_tracer` reports.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ConeTracerReport {
    /// One line for people.
    pub summary: String,
    /// Updates gathered.
    pub updates: u64,
    /// Updates that sent deltas (the others changed nothing).
    pub updates_sent: u64,
    /// Key updates sent.
    pub key_updates: u64,
    /// Voxels that traced cones in the latest update.
    pub voxels_gathered: u64,
    /// Voxel samples of the latest update.
    pub samples: u64,
    /// Gather time, p50 / p99 / mean, ms.
    pub gather_ms_p50: f64,
    /// p99, ms.
    pub gather_ms_p99: f64,
    /// Mean, ms.
    pub gather_ms_mean: f64,
    /// Encoding time, p50, ms.
    pub encode_ms_p50: f64,
    /// Deltas sent.
    pub deltas_sent: u64,
    /// Bytes of deltas sent, in all.
    pub bytes_sent: u64,
    /// Bytes the same updates' values would have taken raw (six f32 per voxel).
    pub raw_bytes: u64,
    /// Bytes sent over raw bytes.
    pub ratio_to_raw: f64,
    /// Voxels sent, in all.
    pub voxels_sent: u64,
    /// Voxels in the octrees of the updates sent, in all.
    pub voxels: u64,
}

/// The cone tracer stage.
pub struct ConeTracer {
    cone: ConeSettings,
    encoder: DeltaEncoder,
    gather: Latency,
    encode: Latency,
    report: ConeTracerReport,
}

impl ConeTracer {
    fn new(setup: &StageSetup) -> anyhow::Result<Self> {
        let params: ConeTracerParams = setup.params()?;
        params
            .check()
            .map_err(|e| anyhow::anyhow!("{}: params: {e}", setup.info.name))?;
        Ok(ConeTracer {
            cone: ConeSettings {
                levels_above_leaves: params.levels_above_leaves,
                refine_below_flatness: params.refine_below_flatness,
                cones: params.cones,
                ..Default::default()
            },
            encoder: DeltaEncoder::new(TransferSettings {
                mantissa_bits: params.mantissa_bits,
                key_every: params.key_every,
            }),
            gather: Latency::new(),
            encode: Latency::new(),
            report: ConeTracerReport::default(),
        })
    }

    fn publish(&mut self, ctx: &StageCtx) {
        let r = &mut self.report;
        r.gather_ms_p50 = self.gather.p50_ms();
        r.gather_ms_p99 = self.gather.p99_ms();
        r.gather_ms_mean = self.gather.mean_ms();
        r.encode_ms_p50 = self.encode.p50_ms();
        r.ratio_to_raw = r.bytes_sent as f64 / r.raw_bytes.max(1) as f64;
        r.summary = format!(
            "{} updates (gather p50 {:.1} ms from {} voxels), {} sent ({} key), {:.1} kB per update sent, {:.3} of raw",
            r.updates,
            r.gather_ms_p50,
            r.voxels_gathered,
            r.updates_sent,
            r.key_updates,
            r.bytes_sent as f64 / r.updates_sent.max(1) as f64 / 1e3,
            r.ratio_to_raw
        );
        ctx.report(serde_json::to_value(&self.report).unwrap_or_default());
    }
}

#[async_trait::async_trait]
impl Stage for ConeTracer {
    async fn on_start(&mut self, ctx: &mut StageCtx) -> anyhow::Result<()> {
        self.publish(ctx);
        Ok(())
    }

    async fn on_input(&mut self, ctx: &mut StageCtx, input: Input) -> anyhow::Result<()> {
        let msg = input.on(IN)?;
        let t = msg.scene_time_s;
        let levels_fit = msg.body.levels.len() == msg.body.octree.levels.len()
            && msg
                .body
                .levels
                .iter()
                .zip(&msg.body.octree.levels)
                .all(|(v, l)| v.len() == l.len());
        if !levels_fit {
            tracing::warn!(
                stage = ctx.name(),
                "filtered levels do not match their octree: dropped"
            );
            return Ok(());
        }
        let (m, cone) = (msg.clone(), self.cone);
        let (gathered, seconds) = tokio::task::spawn_blocking(move || {
            let start = std::time::Instant::now();
            let g = gather(&m.body.octree, &m.body.levels, &cone);
            (g, start.elapsed().as_secs_f64())
        })
        .await?;
        self.gather.record_s(seconds);
        self.report.updates += 1;
        self.report.voxels_gathered = gathered.gathered;
        self.report.samples = gathered.samples;
        let octree = &msg.body.octree;
        let start = std::time::Instant::now();
        let update = self.encoder.encode(octree, &gathered, t);
        self.encode.record(start.elapsed());
        let bounce = BounceMsg {
            update: msg.body.update,
            structure: transfer::structure_of(octree),
            leaves: gathered.leaves().to_vec(),
        };
        ctx.send(BOUNCE, t, bounce).await?;
        if !update.deltas.is_empty() {
            self.report.updates_sent += 1;
            self.report.key_updates += u64::from(update.deltas[0].key);
            self.report.bytes_sent += update.bytes;
            self.report.raw_bytes += update.raw_bytes;
            self.report.voxels_sent += update.voxels_sent;
            self.report.voxels += update.voxels;
            for delta in update.deltas {
                ctx.send(OUT, t, delta).await?;
                self.report.deltas_sent += 1;
            }
        }
        self.publish(ctx);
        Ok(())
    }

    async fn on_stop(&mut self, ctx: &mut StageCtx) -> anyhow::Result<()> {
        self.publish(ctx);
        Ok(())
    }
}

/// Registers `cone_tracer`.
pub fn register(registry: &mut cloudlight_runtime::StageRegistry) {
    registry.register(
        StageKind::new(
            "cone_tracer",
            TECHNIQUE,
            "gathers view-independent irradiance per voxel with cones and streams it as Haar deltas",
            |s| Ok(Box::new(ConeTracer::new(s)?)),
        )
        .input(
            IN,
            EdgeSettings {
                capacity: 2,
                policy: Policy::Latest,
            },
        )
        .output(OUT)
        .output(BOUNCE)
        .checked_params::<ConeTracerParams>(),
    );
}
