//! Lighting kernels: BVH and ray casting (obvhs), the reference path tracer, and (with later
//! issues) photon tracing and packing, light-map atlas/basis/gather, voxelization/octree/
//! injection/cone tracing, raster (wgpu), H.264 with HDR packing, and image error metrics.
//!
//! Kernels take explicit inputs (scene, time, seed) and return values; this crate never
//! knows about actors, queues or sockets.

pub mod bvh;
pub mod direct_light;
pub mod embree;
pub mod hdr_map;
pub mod image_io;
pub mod lightmap;
pub mod metrics;
pub mod photon;
pub mod plan;
pub mod raster;
pub mod raybench;
pub mod reference;
pub mod sampling;
#[cfg(test)]
mod test_scenes;
pub mod video;
pub mod voxel;

pub use bvh::{BvhKind, Hit, SceneBvh};
pub use hdr_map::HdrMap;
pub use reference::{PixelSampling, ReferenceImages, ReferenceRenderer, RenderSettings, render};

/// Locks `m`, taking the value even if a thread panicked while holding it (the caches this
/// crate keeps stay consistent across a panic). The runtime's stages use `runtime::lock`;
/// kernels do not depend on the runtime.
pub(crate) fn lock<T: ?Sized>(m: &std::sync::Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}
