//! Raster on wgpu, headless: the client-side G-buffer (world position, normal, albedo) and
//! direct lighting with shadow maps ([`direct`]), the photon client's screen-space splatting
//! and bilateral upsample ([`splat`]), read back to the CPU.
//!
//! On a GPU-less Linux box wgpu gets an adapter from Mesa's software drivers (Vulkan
//! lavapipe from `mesa-vulkan-drivers`, or EGL/GL llvmpipe from `libegl-mesa0` +
//! `libgl1-mesa-dri`); without any adapter, [`Raster::new`] says what to install.

use cloudlight_scenes::{Camera, Scene, WorldTriangle};
use glam::{Mat4, Vec3, Vec4};
use wgpu::util::DeviceExt;

pub mod direct;
pub mod splat;

pub use direct::ShadowSettings;
pub use splat::{PhotonFrame, SplatSettings};

/// Why the raster cannot run.
#[derive(Debug, thiserror::Error)]
pub enum RasterError {
    /// No adapter at all.
    #[error(
        "no graphics adapter found ({0}); on a machine without a GPU install Mesa's software drivers: \
         `apt-get install mesa-vulkan-drivers` (Vulkan lavapipe) or `apt-get install libegl-mesa0 libgl1-mesa-dri` (GL llvmpipe)"
    )]
    NoAdapter(String),
    /// The adapter refused a device.
    #[error("the graphics adapter refused a device: {0}")]
    Device(String),
    /// More shadow views (6 per point or surface light, 1 per spot or sun) than the device
    /// allows texture layers.
    #[error(
        "{views} shadow views exceed the device's {max} texture layers: use fewer lights or light samples"
    )]
    TooManyShadowViews {
        /// Views needed.
        views: u32,
        /// Device limit.
        max: u32,
    },
    /// Reading results back failed.
    #[error("reading back from the GPU failed: {0}")]
    Readback(String),
}

/// A headless wgpu device.
pub struct Raster {
    device: wgpu::Device,
    queue: wgpu::Queue,
    adapter_info: wgpu::AdapterInfo,
    gbuffer: wgpu::RenderPipeline,
    globals_layout: wgpu::BindGroupLayout,
    shadow: wgpu::RenderPipeline,
    direct_pipeline: wgpu::RenderPipeline,
    direct_layout: wgpu::BindGroupLayout,
    splat: splat::SplatPipelines,
}

/// The G-buffer of one view, on the CPU (row-major from the top).
#[derive(Clone, Debug, PartialEq)]
pub struct GBuffer {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// World position (m) in xyz; w = 1 where a surface was drawn, 0 elsewhere.
    pub position: Vec<Vec4>,
    /// Unit normal facing the camera side.
    pub normal: Vec<Vec3>,
    /// Albedo.
    pub albedo: Vec<Vec3>,
}

impl GBuffer {
    /// A G-buffer from read-back planes: position, normal, albedo (the first three).
    pub(crate) fn from_planes(width: u32, height: u32, planes: &[Vec<Vec4>]) -> Self {
        GBuffer {
            width,
            height,
            position: planes[0].clone(),
            normal: rgb(&planes[1]),
            albedo: rgb(&planes[2]),
        }
    }
}

/// The rgb of a read-back plane.
pub(crate) fn rgb(plane: &[Vec4]) -> Vec<Vec3> {
    plane.iter().map(|v| v.truncate()).collect()
}

/// Vertex layout of the G-buffer pass (must match `VertexIn` in gbuffer.wgsl).
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Vertex {
    position: [f32; 3],
    normal: [f32; 3],
    albedo: [f32; 3],
}

const POSITION_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba32Float;
const NORMAL_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba16Float;
const ALBEDO_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba16Float;

/// The shadow pipeline (depth only, sharing the G-buffer's `globals` layout) and the
/// full-screen direct-lighting pipeline with its bind group layout.
fn direct_pipelines(
    device: &wgpu::Device,
    globals_pipeline_layout: &wgpu::PipelineLayout,
) -> (
    wgpu::RenderPipeline,
    wgpu::RenderPipeline,
    wgpu::BindGroupLayout,
) {
    let shadow_shader = device.create_shader_module(wgpu::include_wgsl!("shadow.wgsl"));
    let shadow = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
        label: Some("shadow"),
        layout: Some(globals_pipeline_layout),
        vertex: wgpu::VertexState {
            module: &shadow_shader,
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
        depth_stencil: Some(wgpu::DepthStencilState {
            format: wgpu::TextureFormat::Depth32Float,
            depth_write_enabled: Some(true),
            depth_compare: Some(wgpu::CompareFunction::Less),
            stencil: Default::default(),
            bias: wgpu::DepthBiasState {
                constant: 2,
                slope_scale: 1.5,
                clamp: 0.0,
            },
        }),
        multisample: Default::default(),
        fragment: None,
        multiview_mask: None,
        cache: None,
    });
    let texture = |binding, sample_type, view_dimension| wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::FRAGMENT,
        ty: wgpu::BindingType::Texture {
            sample_type,
            view_dimension,
            multisampled: false,
        },
        count: None,
    };
    let buffer = |binding, ty| wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::FRAGMENT,
        ty: wgpu::BindingType::Buffer {
            ty,
            has_dynamic_offset: false,
            min_binding_size: None,
        },
        count: None,
    };
    let unfilterable = wgpu::TextureSampleType::Float { filterable: false };
    let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some("direct"),
        entries: &[
            texture(0, unfilterable, wgpu::TextureViewDimension::D2),
            texture(1, unfilterable, wgpu::TextureViewDimension::D2),
            texture(2, unfilterable, wgpu::TextureViewDimension::D2),
            texture(
                3,
                wgpu::TextureSampleType::Depth,
                wgpu::TextureViewDimension::D2Array,
            ),
            wgpu::BindGroupLayoutEntry {
                binding: 4,
                visibility: wgpu::ShaderStages::FRAGMENT,
                ty: wgpu::BindingType::Sampler(wgpu::SamplerBindingType::Comparison),
                count: None,
            },
            buffer(5, wgpu::BufferBindingType::Storage { read_only: true }),
            buffer(6, wgpu::BufferBindingType::Storage { read_only: true }),
            buffer(7, wgpu::BufferBindingType::Uniform),
        ],
    });
    let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
        label: Some("direct"),
        bind_group_layouts: &[Some(&layout)],
        immediate_size: 0,
    });
    let shader = device.create_shader_module(wgpu::include_wgsl!("direct.wgsl"));
    let direct = fullscreen_pipeline(
        device,
        "direct",
        &pipeline_layout,
        &shader,
        ("vs_main", "fs_main"),
    );
    (shadow, direct, layout)
}

/// A full-screen pass: vertex entry `vs` draws one triangle over the target, fragment
/// entry `fs` writes one Rgba32Float target without blending.
pub(crate) fn fullscreen_pipeline(
    device: &wgpu::Device,
    label: &str,
    layout: &wgpu::PipelineLayout,
    shader: &wgpu::ShaderModule,
    (vs, fs): (&str, &str),
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
                format: wgpu::TextureFormat::Rgba32Float,
                blend: None,
                write_mask: wgpu::ColorWrites::ALL,
            })],
        }),
        multiview_mask: None,
        cache: None,
    })
}

/// A render pass into one colour target, cleared first, without depth.
pub(crate) fn clear_pass<'e>(
    enc: &'e mut wgpu::CommandEncoder,
    label: &str,
    view: &wgpu::TextureView,
) -> wgpu::RenderPass<'e> {
    enc.begin_render_pass(&wgpu::RenderPassDescriptor {
        label: Some(label),
        color_attachments: &[Some(wgpu::RenderPassColorAttachment {
            view,
            depth_slice: None,
            resolve_target: None,
            ops: wgpu::Operations {
                load: wgpu::LoadOp::Clear(wgpu::Color::TRANSPARENT),
                store: wgpu::StoreOp::Store,
            },
        })],
        depth_stencil_attachment: None,
        timestamp_writes: None,
        occlusion_query_set: None,
        multiview_mask: None,
    })
}

/// clip_from_world of a camera (wgpu clip space: y up, z in [0, 1]).
pub fn clip_from_world(camera: &Camera, aspect: f32, near: f32, far: f32) -> Mat4 {
    let clip_from_view =
        glam::camera::rh::proj::directx::perspective(camera.fov_y_rad, aspect, near, far);
    let view_from_world =
        glam::camera::rh::view::look_at_mat4(camera.position, camera.target, camera.up);
    clip_from_view * view_from_world
}

impl Raster {
    /// Opens the first adapter wgpu finds (hardware or Mesa's software drivers).
    pub fn new() -> Result<Raster, RasterError> {
        pollster::block_on(Self::new_async())
    }

    async fn new_async() -> Result<Raster, RasterError> {
        let instance =
            wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let adapter = instance
            .request_adapter(&wgpu::RequestAdapterOptions::default())
            .await
            .map_err(|e| RasterError::NoAdapter(e.to_string()))?;
        let adapter_info = adapter.get_info();
        // Photon splatting accumulates in f32 where the adapter can blend it (f16 loses
        // precision when thousands of photons add up in one pixel).
        let blend32 = adapter
            .features()
            .contains(wgpu::Features::FLOAT32_BLENDABLE);
        let (device, queue) = adapter
            .request_device(&wgpu::DeviceDescriptor {
                label: Some("cloudlight raster"),
                required_features: if blend32 {
                    wgpu::Features::FLOAT32_BLENDABLE
                } else {
                    wgpu::Features::empty()
                },
                ..Default::default()
            })
            .await
            .map_err(|e| RasterError::Device(e.to_string()))?;
        let shader = device.create_shader_module(wgpu::include_wgsl!("gbuffer.wgsl"));
        let globals_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("globals"),
            entries: &[wgpu::BindGroupLayoutEntry {
                binding: 0,
                visibility: wgpu::ShaderStages::VERTEX,
                ty: wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Uniform,
                    has_dynamic_offset: false,
                    min_binding_size: None,
                },
                count: None,
            }],
        });
        let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("gbuffer"),
            bind_group_layouts: &[Some(&globals_layout)],
            immediate_size: 0,
        });
        let target = |format| {
            Some(wgpu::ColorTargetState {
                format,
                blend: None,
                write_mask: wgpu::ColorWrites::ALL,
            })
        };
        let gbuffer = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("gbuffer"),
            layout: Some(&layout),
            vertex: wgpu::VertexState {
                module: &shader,
                entry_point: Some("vs_main"),
                compilation_options: Default::default(),
                buffers: &[Some(wgpu::VertexBufferLayout {
                    array_stride: std::mem::size_of::<Vertex>() as u64,
                    step_mode: wgpu::VertexStepMode::Vertex,
                    attributes: &wgpu::vertex_attr_array![0 => Float32x3, 1 => Float32x3, 2 => Float32x3],
                })],
            },
            primitive: wgpu::PrimitiveState { cull_mode: None, ..Default::default() },
            depth_stencil: Some(wgpu::DepthStencilState {
                format: wgpu::TextureFormat::Depth32Float,
                depth_write_enabled: Some(true),
                depth_compare: Some(wgpu::CompareFunction::Less),
                stencil: Default::default(),
                bias: Default::default(),
            }),
            multisample: Default::default(),
            fragment: Some(wgpu::FragmentState {
                module: &shader,
                entry_point: Some("fs_main"),
                compilation_options: Default::default(),
                targets: &[target(POSITION_FORMAT), target(NORMAL_FORMAT), target(ALBEDO_FORMAT)],
            }),
            multiview_mask: None,
            cache: None,
        });
        let (shadow, direct_pipeline, direct_layout) = direct_pipelines(&device, &layout);
        let splat = splat::SplatPipelines::new(
            &device,
            if blend32 {
                wgpu::TextureFormat::Rgba32Float
            } else {
                wgpu::TextureFormat::Rgba16Float
            },
        );
        Ok(Raster {
            device,
            queue,
            adapter_info,
            gbuffer,
            globals_layout,
            shadow,
            direct_pipeline,
            direct_layout,
            splat,
        })
    }

    /// A bind group holding one matrix in the `globals` layout (camera or shadow view).
    pub(crate) fn matrix_bind_group(&self, matrix: Mat4, label: &str) -> wgpu::BindGroup {
        let buf = self
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: bytemuck::cast_slice(&matrix.to_cols_array()),
                usage: wgpu::BufferUsages::UNIFORM,
            });
        self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some(label),
            layout: &self.globals_layout,
            entries: &[wgpu::BindGroupEntry {
                binding: 0,
                resource: buf.as_entire_binding(),
            }],
        })
    }

    /// The adapter in use (name, backend, device type).
    pub fn adapter(&self) -> &wgpu::AdapterInfo {
        &self.adapter_info
    }

    /// Records the G-buffer pass of `triangles` seen by `camera` into `enc`; returns the
    /// position, normal and albedo targets.
    pub(crate) fn encode_gbuffer(
        &self,
        enc: &mut wgpu::CommandEncoder,
        scene: &Scene,
        triangles: &[WorldTriangle],
        camera: &Camera,
        width: u32,
        height: u32,
    ) -> [wgpu::Texture; 3] {
        let d = &self.device;
        let vertices: Vec<Vertex> = triangles
            .iter()
            .flat_map(|t| {
                let albedo = scene.materials[t.material as usize].albedo.to_array();
                (0..3).map(move |k| Vertex {
                    position: t.v[k].to_array(),
                    normal: t.n[k].to_array(),
                    albedo,
                })
            })
            .collect();
        let (lo, hi) = scene.bounds_at(0.0);
        let far =
            ((hi - lo).length() + (camera.position - (lo + hi) * 0.5).length()).max(1e-3) * 2.0;
        let near = far * 1e-5;
        let globals = clip_from_world(camera, width as f32 / height as f32, near, far);
        let bind = self.matrix_bind_group(globals, "globals");
        let vbuf = (!vertices.is_empty()).then(|| {
            d.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("vertices"),
                contents: bytemuck::cast_slice(&vertices),
                usage: wgpu::BufferUsages::VERTEX,
            })
        });
        let size = wgpu::Extent3d {
            width,
            height,
            depth_or_array_layers: 1,
        };
        let texture = |format, label| {
            d.create_texture(&wgpu::TextureDescriptor {
                label: Some(label),
                size,
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format,
                usage: wgpu::TextureUsages::RENDER_ATTACHMENT
                    | wgpu::TextureUsages::COPY_SRC
                    | wgpu::TextureUsages::TEXTURE_BINDING,
                view_formats: &[],
            })
        };
        let targets = [
            texture(POSITION_FORMAT, "position"),
            texture(NORMAL_FORMAT, "normal"),
            texture(ALBEDO_FORMAT, "albedo"),
        ];
        let depth = texture(wgpu::TextureFormat::Depth32Float, "depth");
        let views: Vec<_> = targets
            .iter()
            .map(|t| t.create_view(&Default::default()))
            .collect();
        let depth_view = depth.create_view(&Default::default());
        {
            let attachments: Vec<_> = views
                .iter()
                .map(|v| {
                    Some(wgpu::RenderPassColorAttachment {
                        view: v,
                        depth_slice: None,
                        resolve_target: None,
                        ops: wgpu::Operations {
                            load: wgpu::LoadOp::Clear(wgpu::Color::TRANSPARENT),
                            store: wgpu::StoreOp::Store,
                        },
                    })
                })
                .collect();
            let mut pass = enc.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("gbuffer"),
                color_attachments: &attachments,
                depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                    view: &depth_view,
                    depth_ops: Some(wgpu::Operations {
                        load: wgpu::LoadOp::Clear(1.0),
                        store: wgpu::StoreOp::Store,
                    }),
                    stencil_ops: None,
                }),
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
            if let Some(vbuf) = &vbuf {
                pass.set_pipeline(&self.gbuffer);
                pass.set_bind_group(0, &bind, &[]);
                pass.set_vertex_buffer(0, vbuf.slice(..));
                pass.draw(0..vertices.len() as u32, 0..1);
            }
        }
        targets
    }

    /// Rasterizes the G-buffer of `triangles` seen by `camera` and reads it back.
    pub fn gbuffer(
        &self,
        scene: &Scene,
        triangles: &[WorldTriangle],
        camera: &Camera,
        width: u32,
        height: u32,
    ) -> Result<GBuffer, RasterError> {
        let mut enc = self.device.create_command_encoder(&Default::default());
        let targets = self.encode_gbuffer(&mut enc, scene, triangles, camera, width, height);
        let planes = self.read_back(
            enc,
            &targets
                .each_ref()
                .map(|t| (t, if t.format() == POSITION_FORMAT { 16 } else { 8 })),
            width,
            height,
        )?;
        Ok(GBuffer::from_planes(width, height, &planes))
    }

    /// Submits `enc` with copies of `textures` (Rgba32Float: 16 bytes per pixel, Rgba16Float:
    /// 8) and returns their pixels.
    pub(crate) fn read_back(
        &self,
        mut enc: wgpu::CommandEncoder,
        textures: &[(&wgpu::Texture, u32)],
        width: u32,
        height: u32,
    ) -> Result<Vec<Vec<Vec4>>, RasterError> {
        let d = &self.device;
        let size = wgpu::Extent3d {
            width,
            height,
            depth_or_array_layers: 1,
        };
        // Read the three targets back (rows padded to 256 bytes).
        let mut readbacks = Vec::new();
        for &(t, bytes_per_px) in textures {
            let row = (width * bytes_per_px).div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT)
                * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
            let buf = d.create_buffer(&wgpu::BufferDescriptor {
                label: Some("readback"),
                size: (row * height) as u64,
                usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
                mapped_at_creation: false,
            });
            enc.copy_texture_to_buffer(
                t.as_image_copy(),
                wgpu::TexelCopyBufferInfo {
                    buffer: &buf,
                    layout: wgpu::TexelCopyBufferLayout {
                        offset: 0,
                        bytes_per_row: Some(row),
                        rows_per_image: Some(height),
                    },
                },
                size,
            );
            readbacks.push((buf, row, bytes_per_px));
        }
        self.queue.submit([enc.finish()]);
        let mut planes = Vec::new();
        for (buf, row, bpp) in &readbacks {
            let slice = buf.slice(..);
            slice.map_async(wgpu::MapMode::Read, |_| {});
            d.poll(wgpu::PollType::Wait {
                submission_index: None,
                timeout: None,
            })
            .map_err(|e| RasterError::Readback(e.to_string()))?;
            let data = slice
                .get_mapped_range()
                .map_err(|e| RasterError::Readback(e.to_string()))?;
            let mut px = Vec::with_capacity((width * height) as usize);
            for y in 0..height as usize {
                let r = &data[y * *row as usize..][..(width * bpp) as usize];
                if *bpp == 16 {
                    px.extend(r.chunks_exact(16).map(|c| {
                        let f: &[f32] = bytemuck::cast_slice(c);
                        Vec4::new(f[0], f[1], f[2], f[3])
                    }));
                } else {
                    px.extend(r.chunks_exact(8).map(|c| {
                        let h =
                            |i: usize| half::f16::from_le_bytes([c[2 * i], c[2 * i + 1]]).to_f32();
                        Vec4::new(h(0), h(1), h(2), h(3))
                    }));
                }
            }
            drop(data);
            buf.unmap();
            planes.push(px);
        }
        Ok(planes)
    }
}

#[cfg(test)]
mod tests;
