//! The targets and attachments every pass shares: [`Target`] (a texture and its view), the
//! G-buffer's targets, cleared attachments and the `view` bind group. Passes (shared and
//! technique) import from here; the frame imports the passes — nothing imports the frame.

use super::Raster;

/// A texture and its default view.
pub struct Target {
    /// The texture.
    pub texture: wgpu::Texture,
    /// Its view.
    pub view: wgpu::TextureView,
}

impl Target {
    pub(crate) fn new(
        raster: &Raster,
        label: &str,
        width: u32,
        height: u32,
        format: wgpu::TextureFormat,
    ) -> Self {
        let texture = raster.device.create_texture(&wgpu::TextureDescriptor {
            label: Some(label),
            size: wgpu::Extent3d {
                width,
                height,
                depth_or_array_layers: 1,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT
                | wgpu::TextureUsages::TEXTURE_BINDING
                | wgpu::TextureUsages::COPY_SRC,
            view_formats: &[],
        });
        let view = texture.create_view(&Default::default());
        Target { texture, view }
    }
}

/// The G-buffer's targets.
pub struct GBufferTargets {
    /// World position (m) and coverage (w = 1 where drawn), `f32` bits.
    pub position: Target,
    /// Unit shading normal facing the camera, four `f16`.
    pub normal: Target,
    /// Albedo, four `f16`.
    pub albedo: Target,
    /// Light-map UV in [0, 1]², two `f32` bits (quiet NaN where the geometry has none).
    pub lightmap_uv: Target,
    /// Depth.
    pub depth: Target,
}

/// A colour attachment loaded as `load` says, then stored.
fn colour(
    view: &wgpu::TextureView,
    load: wgpu::LoadOp<wgpu::Color>,
) -> Option<wgpu::RenderPassColorAttachment<'_>> {
    Some(wgpu::RenderPassColorAttachment {
        view,
        depth_slice: None,
        resolve_target: None,
        ops: wgpu::Operations {
            load,
            store: wgpu::StoreOp::Store,
        },
    })
}

/// A colour attachment cleared to zero, then stored.
pub(crate) fn cleared_colour(
    view: &wgpu::TextureView,
) -> Option<wgpu::RenderPassColorAttachment<'_>> {
    colour(view, wgpu::LoadOp::Clear(wgpu::Color::TRANSPARENT))
}

/// A colour attachment whose content is kept (`LoadOp::Load`), then stored: for a target
/// its pass overwrites wherever a reader will look.
pub(crate) fn loaded_colour(
    view: &wgpu::TextureView,
) -> Option<wgpu::RenderPassColorAttachment<'_>> {
    colour(view, wgpu::LoadOp::Load)
}

/// A depth attachment cleared to the far plane, then stored.
pub(crate) fn cleared_depth(
    view: &wgpu::TextureView,
) -> Option<wgpu::RenderPassDepthStencilAttachment<'_>> {
    Some(wgpu::RenderPassDepthStencilAttachment {
        view,
        depth_ops: Some(wgpu::Operations {
            load: wgpu::LoadOp::Clear(1.0),
            store: wgpu::StoreOp::Store,
        }),
        stencil_ops: None,
    })
}

/// A render pass into one colour target, cleared first, without depth.
pub(crate) fn clear_pass<'e>(
    enc: &'e mut wgpu::CommandEncoder,
    label: &str,
    view: &wgpu::TextureView,
) -> wgpu::RenderPass<'e> {
    colour_pass(enc, label, cleared_colour(view))
}

/// A pass that writes every pixel of `view` with one full-screen triangle and no blending:
/// what the target held is neither cleared nor read (`LoadOp::Load` on a target that is
/// overwritten whole). llvmpipe clears a target by writing it in full before the triangle
/// writes it again: the Cornell frame at 640×360 on lavapipe (`bench client`, six interleaved
/// runs each) 31.1 → 29.0 ms p50, its full-screen passes 0.3–1.2 ms faster each.
pub(crate) fn overwrite_pass<'e>(
    enc: &'e mut wgpu::CommandEncoder,
    label: &str,
    view: &wgpu::TextureView,
) -> wgpu::RenderPass<'e> {
    colour_pass(enc, label, loaded_colour(view))
}

/// A render pass into one colour attachment, without depth.
fn colour_pass<'e>(
    enc: &'e mut wgpu::CommandEncoder,
    label: &str,
    attachment: Option<wgpu::RenderPassColorAttachment<'_>>,
) -> wgpu::RenderPass<'e> {
    enc.begin_render_pass(&wgpu::RenderPassDescriptor {
        label: Some(label),
        color_attachments: &[attachment],
        depth_stencil_attachment: None,
        timestamp_writes: None,
        occlusion_query_set: None,
        multiview_mask: None,
    })
}

/// A bind group of the `view` layout over `buffer` (matrices at [`VIEW_STRIDE`]).
pub(crate) fn view_bind_group(
    raster: &Raster,
    buffer: &wgpu::Buffer,
    label: &str,
) -> wgpu::BindGroup {
    raster.device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some(label),
        layout: &raster.pipelines.view_layout,
        entries: &[wgpu::BindGroupEntry {
            binding: 0,
            resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                buffer,
                offset: 0,
                size: wgpu::BufferSize::new(64),
            }),
        }],
    })
}
