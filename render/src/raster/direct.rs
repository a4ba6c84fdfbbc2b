//! The direct-light pass: a full-screen pass that shades the G-buffer with every light and
//! its shadow maps ([`super::shadow`]) into the frame's direct radiance (ρ/π · E_direct).
//! Emissive surfaces are not lights here; turn them into punctual lights first
//! (`Scene::surface_light_samples`).

use super::Raster;
use super::shadow::ShadowMaps;
use super::targets::GBufferTargets;

/// The direct pass of one client: its bind group is made once per shadow-map generation.
pub(crate) struct DirectPass {
    sampler: wgpu::Sampler,
    bind: Option<(u64, wgpu::BindGroup)>,
}

impl DirectPass {
    pub(crate) fn new(raster: &Raster) -> Self {
        DirectPass {
            sampler: raster.device.create_sampler(&wgpu::SamplerDescriptor {
                label: Some("shadow comparison"),
                compare: Some(wgpu::CompareFunction::LessEqual),
                mag_filter: wgpu::FilterMode::Linear,
                min_filter: wgpu::FilterMode::Linear,
                ..Default::default()
            }),
            bind: None,
        }
    }

    /// Records the pass: G-buffer + shadow maps → `out`.
    pub(crate) fn encode(
        &mut self,
        raster: &Raster,
        enc: &mut wgpu::CommandEncoder,
        gbuffer: &GBufferTargets,
        shadows: &ShadowMaps,
        out: &wgpu::TextureView,
    ) {
        let Some((depth, lights, params)) = shadows.bindings() else {
            return;
        };
        if self
            .bind
            .as_ref()
            .is_none_or(|(g, _)| *g != shadows.generation)
        {
            let tex = |binding, view| wgpu::BindGroupEntry {
                binding,
                resource: wgpu::BindingResource::TextureView(view),
            };
            let group = raster.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("direct"),
                layout: &raster.pipelines.direct_layout,
                entries: &[
                    tex(0, &gbuffer.position.view),
                    tex(1, &gbuffer.normal.view),
                    tex(2, &gbuffer.albedo.view),
                    tex(3, depth),
                    wgpu::BindGroupEntry {
                        binding: 4,
                        resource: wgpu::BindingResource::Sampler(&self.sampler),
                    },
                    wgpu::BindGroupEntry {
                        binding: 5,
                        resource: lights.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 6,
                        resource: params.as_entire_binding(),
                    },
                ],
            });
            self.bind = Some((shadows.generation, group));
        }
        let (_, group) = self.bind.as_ref().expect("just made");
        let mut pass = super::targets::overwrite_pass(enc, "direct", out);
        pass.set_pipeline(&raster.pipelines.direct);
        pass.set_bind_group(0, group, &[]);
        pass.draw(0..3, 0..1);
    }
}
