//! Voxel cone tracing (CloudLight §4.1): the scene as a sparse voxel octree, lit on the
//! cloud and sampled per voxel into view-independent irradiance.
//!
//! This module holds the kernels; it knows no actors, queues or sockets. So far:
//! - [`voxelize`]: every triangle's exact share of every leaf it crosses;
//! - [`octree`]: the sparse octree built from those shares (sorted Morton codes per level,
//!   children contiguous, inner levels aggregating their children exactly);
//! - [`Voxelizer`]: the octree of a scene at any time, its depth chosen from the scene's
//!   surface and a memory budget, the static objects voxelized once and only moving ones
//!   again;
//! - [`inject`](mod@inject): direct light into the leaves, as anisotropic radiance (six directions);
//! - [`filter`](mod@filter): inner levels from their children, composited front to back per direction;
//! - [`cone`]: per leaf, cones through the filtered levels gather the indirect irradiance on
//!   each side (view-independent; fed back into the injection for another bounce).

pub mod clip;
pub mod cone;
pub mod filter;
pub mod inject;
pub mod leak;
pub mod morton;
pub mod octree;
pub mod pass;
pub mod transfer;
pub mod volume;
pub mod voxelize;

#[cfg(test)]
mod tests;

use cloudlight_scenes::{Scene, WorldTriangle};

pub use cone::{ConeSettings, ConeTracer, Gathered, MAX_CONES, gather};
pub use filter::filter;
pub use inject::{DIRECTIONS, InjectSettings, Injection, VoxelRadiance, inject};
pub use octree::{BYTES_PER_VOXEL, DENSE_LEVELS, Level, Locator, Octree, ParentLink, VoxelSurface};
pub use pass::VoxelPass;
pub use transfer::{
    DeltaDecoder, DeltaEncoder, DeltaError, EncodedUpdate, FULL_PRECISION, TransferSettings,
    VoxelDelta,
};
pub use volume::{DEFAULT_VOLUME_LEVEL, VoxelVolume, values_at};
pub use voxelize::{Fragment, Grid, MAX_DEPTH};

/// How deep an octree may go and how much memory it may take.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VoxelSettings {
    /// Deepest level: leaves are at most 2^max_depth per axis over the scene's largest
    /// extent (the paper: 9, a 512³ grid).
    pub max_depth: u32,
    /// Bytes the octree may take ([`BYTES_PER_VOXEL`] per voxel, all levels); the depth is
    /// reduced until it fits (the paper's Cornell box: 0.13 GB).
    pub budget_bytes: u64,
}

impl Default for VoxelSettings {
    fn default() -> Self {
        VoxelSettings {
            max_depth: 9,
            budget_bytes: 256 << 20,
        }
    }
}

/// The depth at which a probe voxelization (at `probe` levels, `probe_leaves` occupied
/// leaves) predicts the octree to fit `budget_bytes`: surfaces occupy about 4× the leaves
/// per level, and inner levels add a seventh.
fn predicted_depth(probe: u32, probe_leaves: usize, settings: &VoxelSettings) -> u32 {
    let mut depth = probe;
    for d in probe..=settings.max_depth.min(MAX_DEPTH) {
        let leaves = probe_leaves.max(1) as f64 * 4f64.powi((d - probe) as i32);
        let bytes = leaves * 8.0 / 7.0 * BYTES_PER_VOXEL as f64;
        if bytes <= settings.budget_bytes as f64 {
            depth = d;
        } else {
            break;
        }
    }
    depth
}

/// A scene's octree over time: the grid covers the geometry over all scene time, the
/// static objects' leaves are kept, and each [`Voxelizer::octree_at`] voxelizes only the
/// moving objects again.
#[derive(Clone, Debug)]
pub struct Voxelizer {
    grid: Grid,
    static_leaves: Vec<Fragment>,
    movers: Vec<usize>,
}

impl Voxelizer {
    /// Voxelizes `scene`'s static objects at the depth that `settings` allow.
    pub fn new(scene: &Scene, settings: &VoxelSettings) -> Voxelizer {
        let (lo, hi) = scene.swept_bounds();
        let movers: Vec<usize> = (0..scene.objects.len())
            .filter(|&i| scene.objects[i].motion.is_animated())
            .collect();
        let all = scene.triangles_at(0.0);
        let probe = settings.max_depth.min(5);
        let probe_grid = Grid::around(lo, hi, probe);
        let probe_leaves = voxelize::fragments(&all, &scene.materials, &probe_grid).len();
        let mut grid = probe_grid.with_depth(predicted_depth(probe, probe_leaves, settings));
        let statics: Vec<WorldTriangle> = (0..scene.objects.len())
            .filter(|i| !movers.contains(i))
            .flat_map(|i| scene.object_triangles_at(i, 0.0))
            .collect();
        loop {
            let voxelizer = Voxelizer {
                grid,
                static_leaves: voxelize::fragments(&statics, &scene.materials, &grid),
                movers: movers.clone(),
            };
            let bytes = voxelizer.octree_at(scene, 0.0).bytes();
            if bytes <= settings.budget_bytes || grid.depth == 0 {
                return voxelizer;
            }
            grid = grid.with_depth(grid.depth - 1);
        }
    }

    /// The cube the octree subdivides, and its depth.
    pub fn grid(&self) -> Grid {
        self.grid
    }

    /// Indices (into `scene.objects`) of the objects voxelized at every call.
    pub fn moving_objects(&self) -> &[usize] {
        &self.movers
    }

    /// The octree of `scene` at scene time `t_s`.
    pub fn octree_at(&self, scene: &Scene, t_s: f64) -> Octree {
        let moving: Vec<WorldTriangle> = self
            .movers
            .iter()
            .flat_map(|&i| scene.object_triangles_at(i, t_s))
            .collect();
        let leaves = if moving.is_empty() {
            self.static_leaves.clone()
        } else {
            let m = voxelize::fragments(&moving, &scene.materials, &self.grid);
            voxelize::merge(&self.static_leaves, &m)
        };
        Octree::from_leaves(self.grid, &leaves)
    }
}
