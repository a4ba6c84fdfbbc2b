//! The pass trait: what a technique's indirect pass sees of the frame ([`IndirectContext`])
//! and implements ([`IndirectPass`]). Each technique's pass lives beside its kernels (the
//! photon splat in `photon::splat`) and owns its pipelines; the raster names none of them.

use std::cell::RefCell;
use std::time::{Duration, Instant};

use glam::Mat4;

use super::targets::{GBufferTargets, clear_pass, overwrite_pass};
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
    /// In a timed frame, the timer of the pass's steps ([`IndirectContext::step_done`]).
    pub steps: Option<&'a StepTimer>,
}

impl IndirectContext<'_> {
    /// Ends a step of the pass named `name`: in a timed frame, submits what `enc` holds,
    /// waits for it and records its wall time (`bench client` shows each step); else
    /// nothing.
    pub fn step_done(
        &self,
        raster: &Raster,
        enc: &mut wgpu::CommandEncoder,
        name: &'static str,
    ) -> Result<(), RasterError> {
        if let Some(timer) = self.steps {
            raster.submit_so_far(enc)?;
            let mut t = timer.0.borrow_mut();
            let now = Instant::now();
            let elapsed = now - t.0;
            t.0 = now;
            t.1.push((name, elapsed));
        }
        Ok(())
    }
}

/// Wall times of the steps of a technique's pass in one timed frame, from when it began.
pub struct StepTimer(RefCell<(Instant, Vec<(&'static str, Duration)>)>);

impl StepTimer {
    /// A timer whose first step begins now.
    pub(crate) fn start() -> Self {
        StepTimer(RefCell::new((Instant::now(), Vec::new())))
    }

    /// The steps recorded, in order.
    pub(crate) fn finish(self) -> Vec<(&'static str, Duration)> {
        self.0.into_inner().1
    }
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

/// The bind group of a technique's full-screen pass, kept until the frame renderer (whose
/// G-buffer it names) or the pass's own resources (`generation`) change.
#[derive(Default)]
pub(crate) struct CachedBindGroup(Option<(u64, u64, wgpu::BindGroup)>);

impl CachedBindGroup {
    /// The group for `renderer_id` and `generation`, made by `make` when it is not the one kept.
    pub(crate) fn get(
        &mut self,
        renderer_id: u64,
        generation: u64,
        make: impl FnOnce() -> wgpu::BindGroup,
    ) -> &wgpu::BindGroup {
        let current = matches!(&self.0, Some((r, g, _)) if *r == renderer_id && *g == generation);
        if !current {
            self.0 = Some((renderer_id, generation, make()));
        }
        &self.0.as_ref().expect("kept above").2
    }
}

/// Overwrites `ctx.indirect` whole with the full-screen triangle of `pipeline` and `group`.
pub(crate) fn draw_fullscreen(
    enc: &mut wgpu::CommandEncoder,
    label: &str,
    ctx: &IndirectContext<'_>,
    pipeline: &wgpu::RenderPipeline,
    group: &wgpu::BindGroup,
) {
    let mut pass = overwrite_pass(enc, label, ctx.indirect);
    pass.set_pipeline(pipeline);
    pass.set_bind_group(0, group, &[]);
    pass.draw(0..3, 0..1);
}

/// The bind group of a full-screen lookup pass: `params` at binding 0, the texture views
/// `views` at 1, 2, ... in order, and `sampler` after them.
pub(crate) fn lookup_bind_group(
    raster: &Raster,
    label: &str,
    layout: &wgpu::BindGroupLayout,
    params: &wgpu::Buffer,
    views: &[&wgpu::TextureView],
    sampler: &wgpu::Sampler,
) -> wgpu::BindGroup {
    let mut entries = vec![wgpu::BindGroupEntry {
        binding: 0,
        resource: params.as_entire_binding(),
    }];
    for (i, view) in views.iter().enumerate() {
        entries.push(wgpu::BindGroupEntry {
            binding: 1 + i as u32,
            resource: wgpu::BindingResource::TextureView(view),
        });
    }
    entries.push(wgpu::BindGroupEntry {
        binding: 1 + views.len() as u32,
        resource: wgpu::BindingResource::Sampler(sampler),
    });
    raster.device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some(label),
        layout,
        entries: &entries,
    })
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
