//! Lighting kernels: BVH and ray casting (obvhs), the reference path tracer, photon tracing
//! and packing, light-map atlas/basis/gather, voxelization/octree/injection/cone tracing,
//! raster (wgpu), H.264 with HDR packing, and image error metrics.
//!
//! Nothing is implemented yet: kernels arrive with the scenes/render issue and the
//! techniques. Kernels take explicit inputs (scene, time, seed) and return values; this crate
//! never knows about actors, queues or sockets.
