//! The shared passes' pipelines and bind-group layouts (G-buffer, shadows, direct, compose),
//! built once per device in the formats the adapter supports ([`Formats`]), and the helpers
//! a technique's pass builds its own pipelines with. Shader layouts are marked in the
//! `.wgsl` files and in the Rust structs that fill them.

use super::Formats;

/// Vertex layout of the G-buffer pass (must match `VertexIn` in gbuffer.wgsl).
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct GBufferVertex {
    pub(crate) position: [f32; 3],
    /// Unit normal, snorm16 (the fourth unused).
    pub(crate) normal: [i16; 4],
    /// Albedo in [0, 1], unorm16 (the fourth unused).
    pub(crate) albedo: [u16; 4],
    /// Light-map UV in [0, 1]², or negative where the triangle has none.
    pub(crate) lightmap: [f32; 2],
    /// Texture UV.
    pub(crate) uv: [f32; 2],
    /// The albedo array's layer (0: untextured, white).
    pub(crate) layer: u32,
}

/// Stride of one view matrix in the views uniform buffer (dynamic offsets are 256-aligned).
pub(crate) const VIEW_STRIDE: u64 = 256;

/// The raster's pipelines.
pub(crate) struct Pipelines {
    /// One `clip_from_world` at a dynamic offset (camera or shadow view).
    pub(crate) view_layout: wgpu::BindGroupLayout,
    pub(crate) gbuffer: wgpu::RenderPipeline,
    /// The G-buffer's albedo textures and their sampler (`raster/albedo.rs`).
    pub(crate) albedo_layout: wgpu::BindGroupLayout,
    pub(crate) shadow: wgpu::RenderPipeline,
    pub(crate) direct_layout: wgpu::BindGroupLayout,
    pub(crate) direct: wgpu::RenderPipeline,
    pub(crate) compose_layout: wgpu::BindGroupLayout,
    pub(crate) compose: wgpu::RenderPipeline,
    pub(crate) accumulate_layout: wgpu::BindGroupLayout,
    pub(crate) accumulate: wgpu::RenderPipeline,
}

pub(crate) fn texture_entry(
    binding: u32,
    visibility: wgpu::ShaderStages,
    sample_type: wgpu::TextureSampleType,
    view_dimension: wgpu::TextureViewDimension,
) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility,
        ty: wgpu::BindingType::Texture {
            sample_type,
            view_dimension,
            multisampled: false,
        },
        count: None,
    }
}

pub(crate) fn buffer_entry(
    binding: u32,
    visibility: wgpu::ShaderStages,
    ty: wgpu::BufferBindingType,
) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility,
        ty: wgpu::BindingType::Buffer {
            ty,
            has_dynamic_offset: false,
            min_binding_size: None,
        },
        count: None,
    }
}

pub(crate) const UINT: wgpu::TextureSampleType = wgpu::TextureSampleType::Uint;
pub(crate) const D2: wgpu::TextureViewDimension = wgpu::TextureViewDimension::D2;
pub(crate) const FRAGMENT: wgpu::ShaderStages = wgpu::ShaderStages::FRAGMENT;

pub(crate) fn layout(
    device: &wgpu::Device,
    label: &str,
    entries: &[wgpu::BindGroupLayoutEntry],
) -> wgpu::BindGroupLayout {
    device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some(label),
        entries,
    })
}

pub(crate) fn pipeline_layout(
    device: &wgpu::Device,
    label: &str,
    group: &wgpu::BindGroupLayout,
) -> wgpu::PipelineLayout {
    device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
        label: Some(label),
        bind_group_layouts: &[Some(group)],
        immediate_size: 0,
    })
}

/// A full-screen pass: vertex entry `vs` draws one triangle over the target, fragment entry
/// `fs` writes one target of `format` without blending.
pub(crate) fn fullscreen_pipeline(
    device: &wgpu::Device,
    label: &str,
    layout: &wgpu::PipelineLayout,
    shader: &wgpu::ShaderModule,
    entries: (&str, &str),
    format: wgpu::TextureFormat,
) -> wgpu::RenderPipeline {
    blended_fullscreen_pipeline(device, label, layout, shader, entries, format, None)
}

/// [`fullscreen_pipeline`] blending into its target with `blend`.
pub(crate) fn blended_fullscreen_pipeline(
    device: &wgpu::Device,
    label: &str,
    layout: &wgpu::PipelineLayout,
    shader: &wgpu::ShaderModule,
    (vs, fs): (&str, &str),
    format: wgpu::TextureFormat,
    blend: Option<wgpu::BlendState>,
) -> wgpu::RenderPipeline {
    device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
        label: Some(label),
        layout: Some(layout),
        vertex: wgpu::VertexState {
            module: shader,
            entry_point: Some(vs),
            compilation_options: Default::default(),
            buffers: &[],
        },
        primitive: Default::default(),
        depth_stencil: None,
        multisample: Default::default(),
        fragment: Some(wgpu::FragmentState {
            module: shader,
            entry_point: Some(fs),
            compilation_options: Default::default(),
            targets: &[Some(wgpu::ColorTargetState {
                format,
                blend,
                write_mask: wgpu::ColorWrites::ALL,
            })],
        }),
        multiview_mask: None,
        cache: None,
    })
}

pub(crate) fn depth_state(
    format: wgpu::TextureFormat,
    bias: wgpu::DepthBiasState,
) -> wgpu::DepthStencilState {
    wgpu::DepthStencilState {
        format,
        depth_write_enabled: Some(true),
        depth_compare: Some(wgpu::CompareFunction::Less),
        stencil: Default::default(),
        bias,
    }
}

impl Pipelines {
    pub(crate) fn new(device: &wgpu::Device, formats: &Formats) -> Self {
        let view_layout = layout(
            device,
            "view",
            &[wgpu::BindGroupLayoutEntry {
                binding: 0,
                visibility: wgpu::ShaderStages::VERTEX,
                ty: wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Uniform,
                    has_dynamic_offset: true,
                    min_binding_size: wgpu::BufferSize::new(64),
                },
                count: None,
            }],
        );
        let view_pipeline_layout = pipeline_layout(device, "view", &view_layout);
        let albedo_layout = layout(
            device,
            "albedo textures",
            &[
                texture_entry(
                    0,
                    FRAGMENT,
                    wgpu::TextureSampleType::Float { filterable: true },
                    wgpu::TextureViewDimension::D2Array,
                ),
                wgpu::BindGroupLayoutEntry {
                    binding: 1,
                    visibility: FRAGMENT,
                    ty: wgpu::BindingType::Sampler(wgpu::SamplerBindingType::Filtering),
                    count: None,
                },
            ],
        );
        let gbuffer_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("gbuffer"),
            bind_group_layouts: &[Some(&view_layout), Some(&albedo_layout)],
            immediate_size: 0,
        });
        let (gbuffer, shadow) =
            geometry_pipelines(device, formats, &gbuffer_layout, &view_pipeline_layout);
        let (direct_layout, direct) = direct_pipeline(device, formats);
        let compose_layout = layout(
            device,
            "compose",
            &[
                texture_entry(0, FRAGMENT, UINT, D2),
                texture_entry(1, FRAGMENT, UINT, D2),
            ],
        );
        let shader = device.create_shader_module(wgpu::include_wgsl!("compose.wgsl"));
        let compose = fullscreen_pipeline(
            device,
            "compose",
            &pipeline_layout(device, "compose", &compose_layout),
            &shader,
            ("vs_main", "fs_main"),
            formats.exact4,
        );
        let accumulate_layout = layout(
            device,
            "accumulate",
            &[
                texture_entry(0, FRAGMENT, UINT, D2),
                texture_entry(1, FRAGMENT, UINT, D2),
                wgpu::BindGroupLayoutEntry {
                    binding: 2,
                    visibility: FRAGMENT,
                    ty: wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Uniform,
                        has_dynamic_offset: false,
                        min_binding_size: wgpu::BufferSize::new(16),
                    },
                    count: None,
                },
            ],
        );
        let shader = device.create_shader_module(wgpu::include_wgsl!("accumulate.wgsl"));
        let accumulate = fullscreen_pipeline(
            device,
            "accumulate",
            &pipeline_layout(device, "accumulate", &accumulate_layout),
            &shader,
            ("vs_main", "fs_main"),
            formats.exact4,
        );
        Pipelines {
            accumulate_layout,
            accumulate,
            view_layout,
            gbuffer,
            albedo_layout,
            shadow,
            direct_layout,
            direct,
            compose_layout,
            compose,
        }
    }
}

/// The direct-light pass: G-buffer, shadow maps, lights, parameters → radiance.
fn direct_pipeline(
    device: &wgpu::Device,
    formats: &Formats,
) -> (wgpu::BindGroupLayout, wgpu::RenderPipeline) {
    let direct_layout = layout(
        device,
        "direct",
        &[
            texture_entry(0, FRAGMENT, UINT, D2),
            texture_entry(1, FRAGMENT, UINT, D2),
            texture_entry(2, FRAGMENT, UINT, D2),
            texture_entry(
                3,
                FRAGMENT,
                wgpu::TextureSampleType::Depth,
                wgpu::TextureViewDimension::D2Array,
            ),
            wgpu::BindGroupLayoutEntry {
                binding: 4,
                visibility: FRAGMENT,
                ty: wgpu::BindingType::Sampler(wgpu::SamplerBindingType::Comparison),
                count: None,
            },
            buffer_entry(5, FRAGMENT, wgpu::BufferBindingType::Uniform),
            buffer_entry(6, FRAGMENT, wgpu::BufferBindingType::Uniform),
        ],
    );
    let shader = device.create_shader_module(wgpu::include_wgsl!("direct.wgsl"));
    let direct = fullscreen_pipeline(
        device,
        "direct",
        &pipeline_layout(device, "direct", &direct_layout),
        &shader,
        ("vs_main", "fs_main"),
        formats.exact4,
    );
    (direct_layout, direct)
}

/// The G-buffer pipeline (a view matrix, then the albedo textures) and the depth-only shadow
/// pipeline (a view matrix).
fn geometry_pipelines(
    device: &wgpu::Device,
    formats: &Formats,
    gbuffer_layout: &wgpu::PipelineLayout,
    layout: &wgpu::PipelineLayout,
) -> (wgpu::RenderPipeline, wgpu::RenderPipeline) {
    let target = |format| {
        Some(wgpu::ColorTargetState {
            format,
            blend: None,
            write_mask: wgpu::ColorWrites::ALL,
        })
    };
    let shader = device.create_shader_module(wgpu::include_wgsl!("gbuffer.wgsl"));
    let gbuffer = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
        label: Some("gbuffer"),
        layout: Some(gbuffer_layout),
        vertex: wgpu::VertexState {
            module: &shader,
            entry_point: Some("vs_main"),
            compilation_options: Default::default(),
            buffers: &[Some(wgpu::VertexBufferLayout {
                array_stride: std::mem::size_of::<GBufferVertex>() as u64,
                step_mode: wgpu::VertexStepMode::Vertex,
                attributes: &wgpu::vertex_attr_array![0 => Float32x3, 1 => Snorm16x4, 2 => Unorm16x4, 3 => Float32x2, 4 => Float32x2, 5 => Uint32],
            })],
        },
        primitive: wgpu::PrimitiveState {
            cull_mode: None,
            ..Default::default()
        },
        depth_stencil: Some(depth_state(formats.depth, Default::default())),
        multisample: Default::default(),
        fragment: Some(wgpu::FragmentState {
            module: &shader,
            entry_point: Some("fs_main"),
            compilation_options: Default::default(),
            targets: &[
                target(formats.exact4),
                target(formats.half4),
                target(formats.half4),
                target(formats.exact2),
            ],
        }),
        multiview_mask: None,
        cache: None,
    });
    let shader = device.create_shader_module(wgpu::include_wgsl!("shadow.wgsl"));
    let shadow = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
        label: Some("shadow"),
        layout: Some(layout),
        vertex: wgpu::VertexState {
            module: &shader,
            entry_point: Some("vs_main"),
            compilation_options: Default::default(),
            buffers: &[Some(wgpu::VertexBufferLayout {
                array_stride: 12,
                step_mode: wgpu::VertexStepMode::Vertex,
                attributes: &wgpu::vertex_attr_array![0 => Float32x3],
            })],
        },
        primitive: wgpu::PrimitiveState {
            cull_mode: None,
            ..Default::default()
        },
        depth_stencil: Some(depth_state(
            formats.depth,
            wgpu::DepthBiasState {
                constant: 2,
                slope_scale: 1.5,
                clamp: 0.0,
            },
        )),
        multisample: Default::default(),
        fragment: None,
        multiview_mask: None,
        cache: None,
    });
    (gbuffer, shadow)
}
