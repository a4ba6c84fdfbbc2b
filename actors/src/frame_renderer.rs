//! `frame_renderer`: the voxel technique's view-dependent stage (CloudLight §4.1), one per
//! client, on the shared client shell ([`crate::client`]). The paper runs it on a second
//! cloud GPU and streams its frames as H.264 (`frames` → `video_encoder` → `video_client`:
//! `voxels-cloud.toml`); placed on the client, the voxel deltas cross the network instead
//! (`voxels-split.toml`).
//!
//! What is its own: it voxelizes the scene as the GI node does (the same `max_depth` and
//! `budget_mb`; the octree at each update's scene time), applies the cone tracer's Haar
//! deltas level by level ([`DeltaDecoder`]: garbage and deltas of another structure are
//! counted and dropped; after a missed delta it waits for the next key update), and its
//! indirect pass looks the voxels' irradiance up per pixel ([`VoxelPass`]) in a volume made
//! of `volume_level` (from the deepest complete level while an update is arriving, so
//! coarse light shows first). Its indirect light is valid as of the scene time of the
//! latest update applied. Everything else — cadence, camera, direct light, frames, ages,
//! the report — is the shell's.

use std::sync::Arc;

use cloudlight_render::raster::{Raster, RasterError};
use cloudlight_render::voxel::{
    DEFAULT_VOLUME_LEVEL, DeltaDecoder, DeltaError, Octree, VoxelPass, VoxelVolume, Voxelizer,
};
use cloudlight_runtime::{CheckParams, StageSetup, Stamped, check_range};
use cloudlight_scenes::Scene;
use serde::{Deserialize, Serialize};

use crate::client::{ClientTechnique, register as register_client};
use crate::cone_tracer::DELTA_EDGE;
use crate::light_injector::{DEFAULT_BUDGET_MB, DEFAULT_MAX_DEPTH, TECHNIQUE, voxel_settings};
use crate::wire::voxel::VoxelDelta;

/// The frame renderer's own parameters (beside the shell's [`crate::client::ClientParams`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FrameRendererParams {
    /// Deepest octree level (as the `light_injector`'s).
    #[serde(default = "default_depth")]
    pub max_depth: u32,
    /// Octree memory budget, MiB (as the `light_injector`'s).
    #[serde(default = "default_budget")]
    pub budget_mb: f64,
    /// The octree level looked up per pixel (a dense 3D texture of 8^level cells × 6 faces).
    #[serde(default = "default_volume_level")]
    pub volume_level: u32,
}

fn default_depth() -> u32 {
    DEFAULT_MAX_DEPTH
}

fn default_budget() -> f64 {
    DEFAULT_BUDGET_MB
}

fn default_volume_level() -> u32 {
    DEFAULT_VOLUME_LEVEL
}

impl Default for FrameRendererParams {
    fn default() -> Self {
        FrameRendererParams {
            max_depth: default_depth(),
            budget_mb: default_budget(),
            volume_level: default_volume_level(),
        }
    }
}

impl CheckParams for FrameRendererParams {
    fn check(&self) -> Result<(), String> {
        voxel_settings(self.max_depth, self.budget_mb)?;
        check_range("volume_level", self.volume_level as f64, 0.0, 7.0, "levels")
    }
}

/// The frame renderer's figures in its report.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FrameRendererReport {
    /// Deltas received.
    pub deltas: u64,
    /// Delta bytes received.
    pub bytes_received: u64,
    /// Updates whose every level arrived.
    pub updates_complete: u64,
    /// Deltas refused as garbage (checksum, lengths, values).
    pub deltas_rejected: u64,
    /// Deltas of another octree structure (settings that differ from the GI node's).
    pub deltas_foreign: u64,
    /// Deltas refused while waiting for a key update after a missed one.
    pub deltas_out_of_sequence: u64,
    /// Volumes uploaded.
    pub volumes: u64,
    /// Level of the latest volume's values (below `volume_level` while an update arrives).
    pub volume_from_level: u32,
}

/// The voxel technique's part of a client.
pub struct FrameRendererClient {
    scene: Arc<Scene>,
    voxelizer: Voxelizer,
    /// The octree and the scene time it is of (all times, for a scene without movers).
    octree: Option<(f64, Arc<Octree>)>,
    decoder: DeltaDecoder,
    volume_level: u32,
    /// Bumped when the decoder's values change; the version uploaded.
    version: u64,
    uploaded: u64,
    report: FrameRendererReport,
}

impl FrameRendererClient {
    fn octree_at(&mut self, t: f64) -> Arc<Octree> {
        let still = self.voxelizer.moving_objects().is_empty();
        match &self.octree {
            Some((at, o)) if still || *at == t => o.clone(),
            _ => {
                let o = Arc::new(self.voxelizer.octree_at(&self.scene, t));
                self.octree = Some((t, o.clone()));
                o
            }
        }
    }
}

impl ClientTechnique for FrameRendererClient {
    type Msg = VoxelDelta;
    type Params = FrameRendererParams;
    type Pass = VoxelPass;
    type Update = Arc<VoxelVolume>;
    type Report = FrameRendererReport;

    fn new(setup: &StageSetup, params: &Self::Params, scene: &Arc<Scene>) -> anyhow::Result<Self> {
        let settings = voxel_settings(params.max_depth, params.budget_mb)
            .map_err(|e| anyhow::anyhow!("{}: params: {e}", setup.info.name))?;
        Ok(FrameRendererClient {
            voxelizer: Voxelizer::new(scene, &settings),
            scene: scene.clone(),
            octree: None,
            decoder: DeltaDecoder::new(),
            volume_level: params.volume_level,
            version: 0,
            uploaded: 0,
            report: FrameRendererReport::default(),
        })
    }

    fn on_message(&mut self, stage: &str, msg: &Stamped<VoxelDelta>) {
        let delta = &msg.body;
        self.report.deltas += 1;
        self.report.bytes_received += delta.wire_bytes();
        let octree = self.octree_at(delta.scene_time_s);
        match self.decoder.apply(&octree, delta) {
            Ok(()) => {
                self.version += 1;
                if self.decoder.complete() {
                    self.report.updates_complete += 1;
                }
            }
            Err(e) => {
                match e {
                    DeltaError::Gap { .. } => self.report.deltas_out_of_sequence += 1,
                    DeltaError::Structure { .. } => self.report.deltas_foreign += 1,
                    DeltaError::Checksum | DeltaError::Malformed(_) => {
                        self.report.deltas_rejected += 1
                    }
                }
                tracing::debug!(
                    stage,
                    update = delta.update,
                    level = delta.level,
                    "voxel delta refused: {e}"
                );
            }
        }
    }

    fn valid_as_of(&self) -> Option<f64> {
        self.decoder.latest().map(|(_, t)| t)
    }

    fn new_pass(raster: &Raster, _params: &Self::Params) -> Result<VoxelPass, RasterError> {
        VoxelPass::new(raster)
    }

    fn update(&mut self) -> Option<Arc<VoxelVolume>> {
        if self.uploaded == self.version {
            return None;
        }
        let complete = self.decoder.complete_level()?;
        let (_, t) = self.decoder.latest()?;
        let octree = self.octree_at(t);
        self.uploaded = self.version;
        self.report.volume_from_level = complete.min(self.volume_level);
        self.report.volumes += 1;
        Some(Arc::new(VoxelVolume::new(
            &octree,
            self.decoder.levels(),
            complete,
            self.volume_level,
        )))
    }

    fn apply(
        pass: &mut VoxelPass,
        raster: &Raster,
        volume: Arc<VoxelVolume>,
    ) -> Result<(), RasterError> {
        pass.set_volume(raster, &volume)
    }

    fn report(&self) -> FrameRendererReport {
        self.report.clone()
    }

    fn summary(&self) -> String {
        format!(
            "{} voxel updates complete, {} deltas ({:.1} kB), {} refused",
            self.report.updates_complete,
            self.report.deltas,
            self.report.bytes_received as f64 / 1e3,
            self.report.deltas_rejected
                + self.report.deltas_foreign
                + self.report.deltas_out_of_sequence
        )
    }

    fn csv_columns() -> &'static str {
        "voxel_updates,volume_from_level"
    }

    fn csv_values(&self) -> String {
        format!(
            "{},{}",
            self.report.updates_complete, self.report.volume_from_level
        )
    }
}

/// Registers `frame_renderer`.
pub fn register(registry: &mut cloudlight_runtime::StageRegistry) {
    register_client::<FrameRendererClient>(
        registry,
        "frame_renderer",
        TECHNIQUE,
        "applies voxel deltas and renders frames with per-pixel voxel irradiance over its own direct light",
        DELTA_EDGE,
    );
}
