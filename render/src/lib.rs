//! Lighting kernels: BVH and ray casting (obvhs), the reference path tracer, and (with later
//! issues) photon tracing and packing, light-map atlas/basis/gather, voxelization/octree/
//! injection/cone tracing, raster (wgpu), H.264 with HDR packing, and image error metrics.
//!
//! Kernels take explicit inputs (scene, time, seed) and return values; this crate never
//! knows about actors, queues or sockets.

pub mod bvh;
pub mod direct_light;
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
pub mod video;

pub use bvh::{BvhKind, Hit, SceneBvh};
pub use hdr_map::HdrMap;
pub use reference::{ReferenceImages, ReferenceRenderer, RenderSettings, render};
