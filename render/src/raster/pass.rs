//! The pass trait: what a technique's indirect pass sees of the frame ([`IndirectContext`])
//! and implements ([`IndirectPass`]). Each technique's pass lives beside its kernels (the
//! photon splat in `photon::splat`) and owns its pipelines; the raster names none of them.

use glam::Mat4;

use super::targets::{GBufferTargets, clear_pass};
use super::{Raster, RasterError};

/// What a technique's indirect pass sees of the frame.
pub struct IndirectContext<'a> {
    /// Identifies the frame renderer whose targets these are (passes cache bind groups by it).
    pub renderer_id: u64,
    /// Frame width, pixels.
    pub width: u32,
    /// Frame height, pixels.
    pub height: u32,
    /// The camera's clip_from_world.
    pub clip_from_world: Mat4,
    /// The camera's clip_from_view (a perspective projection).
    pub clip_from_view: Mat4,
    /// The camera's view_from_world.
    pub view_from_world: Mat4,
    /// Bounding diagonal of the geometry, meters.
    pub scene_extent_m: f32,
    /// The G-buffer.
    pub gbuffer: &'a GBufferTargets,
    /// The target to write indirect radiance to (`f32` bits, cleared by the pass).
    pub indirect: &'a wgpu::TextureView,
}

/// A technique's pass producing indirect radiance ρ/π · E_indirect for each pixel.
pub trait IndirectPass: Send {
    /// Records the pass into `enc`: it must write (or clear) every pixel of `ctx.indirect`.
    fn encode(
        &mut self,
        raster: &Raster,
        ctx: &IndirectContext<'_>,
        enc: &mut wgpu::CommandEncoder,
    ) -> Result<(), RasterError>;
}

/// No indirect light (direct-only frames).
pub struct NoIndirect;

impl IndirectPass for NoIndirect {
    fn encode(
        &mut self,
        _raster: &Raster,
        ctx: &IndirectContext<'_>,
        enc: &mut wgpu::CommandEncoder,
    ) -> Result<(), RasterError> {
        clear_pass(enc, "no indirect", ctx.indirect);
        Ok(())
    }
}
