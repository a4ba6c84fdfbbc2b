//! `photon_reconstructor`: the client reconstructor of the photon technique (CloudLight §4.3),
//! one per client, on the shared client shell ([`crate::client`]).
//!
//! What is its own: it keeps the newest batch per (light, slot) ([`PhotonSet`], checking
//! each batch's header and checksum on arrival and decoding lazily), its indirect light is
//! valid as of the scene time the set is complete and current for (the manifests), and its
//! indirect pass splats the set's photons into a low-resolution buffer and upsamples them
//! bilaterally ([`PhotonSplatPass`]). The photons are uploaded to the GPU only when the set
//! changed. Everything else — cadence, camera, direct light, frames, `frames.csv`, ages,
//! the report — is the shell's.

use std::sync::Arc;

use cloudlight_render::photon::splat::{MAX_LEVELS, PhotonSplatPass, SplatSettings};
use cloudlight_render::photon::{Inserted, Photon, PhotonSet};
use cloudlight_render::raster::{Raster, RasterError};
use cloudlight_runtime::{StageSetup, Stamped};
use cloudlight_scenes::Scene;
use serde::{Deserialize, Serialize};

use crate::client::{ClientTechnique, register as register_client};
use crate::photon_batcher::{PHOTON_EDGE, TECHNIQUE};
use crate::wire::PhotonMsg;

/// The photon client's own parameters (beside the shell's [`crate::client::ClientParams`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PhotonClientParams {
    /// Accumulation buffer downsampling per axis (1, 2 or 4).
    #[serde(default = "default_downsample")]
    pub downsample: u32,
    /// Accumulation levels, each half the resolution of the one before (1 to 4): a photon
    /// is splatted at the coarsest where its disk spans a few texels.
    #[serde(default = "default_levels")]
    pub levels: u32,
    /// Least radius, in texels of its level, of a photon's disk (0.5 to 64): larger is
    /// smoother and slower.
    #[serde(default = "default_min_texels")]
    pub min_texels: f32,
    /// Splat with a compute shader where the device runs them (true), or rasterise each
    /// photon as a quad (false; the way before, kept to compare).
    #[serde(default = "default_compute")]
    pub compute: bool,
    /// With the compute splat, pixels the finest accumulation level does not stand for (a
    /// ledge a pixel wide, the top row of a wall seen from afar) get its photons at full
    /// resolution instead of a neighbouring surface's light (true), or the upsample alone (false, the
    /// default: see the README's "Edges").
    #[serde(default = "default_edges")]
    pub edges: bool,
    /// Photons within a cell of this fraction of their radius (receiving alike) are merged
    /// into one before they are splatted, 0 to 2 (0: none; default 0.5): what the
    /// batcher's `merge` could not merge, photons of different batches and a still light's
    /// refinement passes (32 passes of the Cornell box's 10k photons splatted as ~7× fewer,
    /// for ~1% more error: the README's "Merging photons").
    #[serde(default = "default_splat_merge")]
    pub splat_merge: f32,
    /// A light that changes every iteration is drawn from its last `window` generations
    /// together, as passes (1 to 64; 1: the newest only): the same bytes, less noise and
    /// smaller disks, the light lagging by (window − 1)/2 iterations on average
    /// (`render/src/photon/store.rs`; the README's "A moving light's window").
    #[serde(default = "one")]
    pub window: u32,
}

fn one() -> u32 {
    1
}

fn default_downsample() -> u32 {
    2
}

fn default_levels() -> u32 {
    SplatSettings::default().levels
}

fn default_min_texels() -> f32 {
    SplatSettings::default().min_texels
}

fn default_compute() -> bool {
    SplatSettings::default().compute
}

fn default_edges() -> bool {
    SplatSettings::default().edges
}

fn default_splat_merge() -> f32 {
    SplatSettings::default().merge
}

impl Default for PhotonClientParams {
    fn default() -> Self {
        PhotonClientParams {
            downsample: default_downsample(),
            levels: default_levels(),
            min_texels: default_min_texels(),
            compute: default_compute(),
            edges: default_edges(),
            splat_merge: default_splat_merge(),
            window: 1,
        }
    }
}

impl PhotonClientParams {
    /// The splat's settings these parameters ask for.
    pub fn splat(&self) -> SplatSettings {
        SplatSettings {
            downsample: self.downsample,
            levels: self.levels,
            min_texels: self.min_texels,
            compute: self.compute,
            edges: self.edges,
            merge: self.splat_merge,
            ..Default::default()
        }
    }
}

impl cloudlight_runtime::CheckParams for PhotonClientParams {
    fn check(&self) -> Result<(), String> {
        if ![1, 2, 4].contains(&self.downsample) {
            return Err(format!(
                "`downsample` = {} must be 1, 2 or 4",
                self.downsample
            ));
        }
        if !(1..=MAX_LEVELS).contains(&self.levels) {
            return Err(format!(
                "`levels` = {} must be 1 to {MAX_LEVELS}",
                self.levels
            ));
        }
        cloudlight_runtime::check_range("min_texels", self.min_texels as f64, 0.5, 64.0, "texels")?;
        cloudlight_runtime::check_range("splat_merge", self.splat_merge as f64, 0.0, 2.0, "radii")?;
        cloudlight_runtime::check_range("window", self.window as f64, 1.0, 64.0, "generations")
    }
}

/// The photon client's figures in its report.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PhotonClientReport {
    /// Photons held.
    pub photons_stored: usize,
    /// Batches held.
    pub batches_held: usize,
    /// Packed bytes held (the client's memory for photons).
    pub stored_bytes: usize,
    /// Photon bytes received.
    pub bytes_received: u64,
    /// Batches accepted.
    pub batches_accepted: u64,
    /// Batches that replaced an older one of the same slot.
    pub batches_replaced: u64,
    /// Batches older than the one held, dropped.
    pub batches_stale: u64,
    /// Batches that failed their checks, dropped.
    pub batches_rejected: u64,
    /// Manifests applied.
    pub manifests: u64,
}

/// The photon technique's part of a client.
pub struct PhotonClient {
    set: PhotonSet,
    uploaded_version: Option<u64>,
    bytes_received: u64,
}

impl ClientTechnique for PhotonClient {
    type Msg = PhotonMsg;
    type Params = PhotonClientParams;
    type Pass = PhotonSplatPass;
    type Update = Arc<Vec<Photon>>;
    type Report = PhotonClientReport;

    fn new(
        _setup: &StageSetup,
        params: &Self::Params,
        _scene: &Arc<Scene>,
    ) -> anyhow::Result<Self> {
        Ok(PhotonClient {
            set: PhotonSet::with_window(params.window),
            uploaded_version: None,
            bytes_received: 0,
        })
    }

    fn on_message(&mut self, stage: &str, msg: &Stamped<PhotonMsg>) {
        match &msg.body {
            PhotonMsg::Batch(b) => {
                self.bytes_received += b.data.len() as u64;
                if let Inserted::Rejected(e) = self.set.insert(b) {
                    tracing::warn!(
                        stage,
                        light = b.header.light,
                        slot = b.header.slot,
                        "photon batch rejected: {e}"
                    );
                }
            }
            PhotonMsg::Manifest(m) => self.set.apply_manifest(m.clone()),
        }
    }

    fn valid_as_of(&self) -> Option<f64> {
        self.set.valid_as_of()
    }

    fn new_pass(raster: &Raster, params: &Self::Params) -> Result<PhotonSplatPass, RasterError> {
        PhotonSplatPass::new(raster, params.splat())
    }

    fn update(&mut self) -> Option<Arc<Vec<Photon>>> {
        let version = self.set.version();
        if self.uploaded_version == Some(version) {
            return None;
        }
        self.uploaded_version = Some(version);
        Some(Arc::new(self.set.photons().collect()))
    }

    fn apply(
        pass: &mut PhotonSplatPass,
        raster: &Raster,
        photons: Arc<Vec<Photon>>,
    ) -> Result<(), RasterError> {
        pass.set_photons(raster, &photons)
    }

    fn report(&self) -> PhotonClientReport {
        let stats = self.set.stats();
        PhotonClientReport {
            photons_stored: self.set.photon_count(),
            batches_held: self.set.batch_count(),
            stored_bytes: self.set.packed_bytes(),
            bytes_received: self.bytes_received,
            batches_accepted: stats.accepted,
            batches_replaced: stats.replaced,
            batches_stale: stats.stale,
            batches_rejected: stats.rejected,
            manifests: stats.manifests,
        }
    }

    fn summary(&self) -> String {
        format!(
            "{} photons in {} batches, {} rejected",
            self.set.photon_count(),
            self.set.batch_count(),
            self.set.stats().rejected
        )
    }

    fn csv_columns() -> &'static str {
        "photons_stored"
    }

    fn csv_values(&self) -> String {
        self.set.photon_count().to_string()
    }
}

/// Registers `photon_reconstructor`.
pub fn register(registry: &mut cloudlight_runtime::StageRegistry) {
    register_client::<PhotonClient>(
        registry,
        "photon_reconstructor",
        TECHNIQUE,
        "keeps the newest photon batch per (light, slot), splats them over its own direct light, measures the age of indirect light",
        PHOTON_EDGE,
    );
}
