//! The compose pass: the frame's radiance, direct + the technique's indirect.

use super::Raster;
use super::targets::{Target, overwrite_pass};

/// The compose pass of one client: its bind group over the direct and indirect targets.
pub(crate) struct ComposePass {
    bind: wgpu::BindGroup,
}

impl ComposePass {
    pub(crate) fn new(raster: &Raster, direct: &Target, indirect: &Target) -> Self {
        let bind = raster.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("compose"),
            layout: &raster.pipelines.compose_layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: wgpu::BindingResource::TextureView(&direct.view),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wgpu::BindingResource::TextureView(&indirect.view),
                },
            ],
        });
        ComposePass { bind }
    }

    /// Records the pass into `out`.
    pub(crate) fn encode(
        &self,
        raster: &Raster,
        enc: &mut wgpu::CommandEncoder,
        out: &wgpu::TextureView,
    ) {
        let mut pass = overwrite_pass(enc, "compose", out);
        pass.set_pipeline(&raster.pipelines.compose);
        pass.set_bind_group(0, &self.bind, &[]);
        pass.draw(0..3, 0..1);
    }
}
