//! The photon client's frame: direct light with shadow maps, photons splatted in screen
//! space into a low-resolution additive buffer, a joint-bilateral upsample to indirect
//! radiance, read back as direct + indirect (see `splat.wgsl` for the kernel).

use cloudlight_scenes::{Camera, LightState, Scene, WorldTriangle};
use glam::Vec3;
use wgpu::util::DeviceExt;

use super::{GBuffer, Raster, RasterError, ShadowSettings, clip_from_world};
use crate::photon::Photon;

/// Splatting settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SplatSettings {
    /// Accumulation buffer is this many times smaller per axis (1, 2 or 4).
    pub downsample: u32,
    /// A surface point farther than `flatten × r` from a photon's plane along its own
    /// normal does not receive it (keeps light from leaking around corners and thin walls).
    pub flatten: f32,
    /// Plane-distance scale of the upsample's depth weight, as a fraction of the scene's
    /// bounding diagonal.
    pub depth_sigma: f32,
    /// Exponent of the upsample's normal weight.
    pub normal_power: f32,
}

impl Default for SplatSettings {
    fn default() -> Self {
        SplatSettings {
            downsample: 2,
            flatten: 0.3,
            depth_sigma: 0.005,
            normal_power: 8.0,
        }
    }
}

/// One client frame.
#[derive(Clone, Debug)]
pub struct PhotonFrame {
    /// The G-buffer.
    pub gbuffer: GBuffer,
    /// Direct radiance (the client's own lights).
    pub direct: Vec<Vec3>,
    /// Indirect radiance from the photons (ρ/π · E_indirect).
    pub indirect: Vec<Vec3>,
}

impl PhotonFrame {
    /// Direct + indirect radiance.
    pub fn combined(&self) -> Vec<Vec3> {
        self.direct
            .iter()
            .zip(&self.indirect)
            .map(|(d, i)| *d + *i)
            .collect()
    }
}

/// Must match `PhotonIn` in splat.wgsl.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct SplatPhoton {
    position_radius: [f32; 4],
    power: [f32; 4],
    direction: [f32; 4],
}

/// Must match `SplatParams` in splat.wgsl.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct SplatParams {
    clip_from_world: [f32; 16],
    sizes: [f32; 4],
    settings: [f32; 4],
}

/// The splat and upsample pipelines and their layout.
pub(crate) struct SplatPipelines {
    layout: wgpu::BindGroupLayout,
    splat: wgpu::RenderPipeline,
    upsample: wgpu::RenderPipeline,
    accum_format: wgpu::TextureFormat,
}

impl SplatPipelines {
    /// `accum_format` must be blendable (Rgba32Float needs `FLOAT32_BLENDABLE`).
    pub(crate) fn new(device: &wgpu::Device, accum_format: wgpu::TextureFormat) -> Self {
        let shader = device.create_shader_module(wgpu::include_wgsl!("splat.wgsl"));
        let texture = |binding| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::FRAGMENT,
            ty: wgpu::BindingType::Texture {
                sample_type: wgpu::TextureSampleType::Float { filterable: false },
                view_dimension: wgpu::TextureViewDimension::D2,
                multisampled: false,
            },
            count: None,
        };
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("splat"),
            entries: &[
                wgpu::BindGroupLayoutEntry {
                    binding: 0,
                    visibility: wgpu::ShaderStages::VERTEX_FRAGMENT,
                    ty: wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Uniform,
                        has_dynamic_offset: false,
                        min_binding_size: None,
                    },
                    count: None,
                },
                texture(1),
                texture(2),
                texture(3),
                texture(4),
            ],
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("splat"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let additive = wgpu::BlendComponent {
            src_factor: wgpu::BlendFactor::One,
            dst_factor: wgpu::BlendFactor::One,
            operation: wgpu::BlendOperation::Add,
        };
        let splat = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("splat"),
            layout: Some(&pipeline_layout),
            vertex: wgpu::VertexState {
                module: &shader,
                entry_point: Some("vs_splat"),
                compilation_options: Default::default(),
                buffers: &[Some(wgpu::VertexBufferLayout {
                    array_stride: std::mem::size_of::<SplatPhoton>() as u64,
                    step_mode: wgpu::VertexStepMode::Instance,
                    attributes: &wgpu::vertex_attr_array![0 => Float32x4, 1 => Float32x4, 2 => Float32x4],
                })],
            },
            primitive: wgpu::PrimitiveState {
                cull_mode: None,
                ..Default::default()
            },
            depth_stencil: None,
            multisample: Default::default(),
            fragment: Some(wgpu::FragmentState {
                module: &shader,
                entry_point: Some("fs_splat"),
                compilation_options: Default::default(),
                targets: &[Some(wgpu::ColorTargetState {
                    format: accum_format,
                    blend: Some(wgpu::BlendState {
                        color: additive,
                        alpha: additive,
                    }),
                    write_mask: wgpu::ColorWrites::ALL,
                })],
            }),
            multiview_mask: None,
            cache: None,
        });
        let upsample = super::fullscreen_pipeline(
            device,
            "upsample",
            &pipeline_layout,
            &shader,
            ("vs_full", "fs_upsample"),
        );
        SplatPipelines {
            layout,
            splat,
            upsample,
            accum_format,
        }
    }
}

impl Raster {
    /// A client frame: direct light of `lights` plus the indirect light of `photons`.
    #[allow(clippy::too_many_arguments)]
    pub fn photon_frame(
        &self,
        scene: &Scene,
        triangles: &[WorldTriangle],
        lights: &[LightState],
        camera: &Camera,
        width: u32,
        height: u32,
        shadows: ShadowSettings,
        photons: &[Photon],
        splat: SplatSettings,
    ) -> Result<PhotonFrame, RasterError> {
        let d = &self.device;
        let ds = splat.downsample.clamp(1, 8);
        let (low_w, low_h) = (width.div_ceil(ds).max(1), height.div_ceil(ds).max(1));
        let mut enc = d.create_command_encoder(&Default::default());
        let view = self.encode_direct(
            &mut enc, scene, triangles, lights, camera, width, height, shadows,
        )?;
        let (lo, hi) = scene.bounds_at(0.0);
        let far =
            ((hi - lo).length() + (camera.position - (lo + hi) * 0.5).length()).max(1e-3) * 2.0;
        let clip = clip_from_world(camera, width as f32 / height as f32, far * 1e-5, far);
        let params = SplatParams {
            clip_from_world: clip.to_cols_array(),
            sizes: [width as f32, height as f32, low_w as f32, low_h as f32],
            settings: [
                ds as f32,
                splat.flatten,
                (splat.depth_sigma * view.scene_extent).max(1e-6),
                splat.normal_power,
            ],
        };
        let params_buf = d.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("splat params"),
            contents: bytemuck::bytes_of(&params),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let texture = |w, h, format, label| {
            d.create_texture(&wgpu::TextureDescriptor {
                label: Some(label),
                size: wgpu::Extent3d {
                    width: w,
                    height: h,
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
            })
        };
        let pipes = &self.splat;
        let accum = texture(low_w, low_h, pipes.accum_format, "photon accumulation");
        let indirect = texture(
            width,
            height,
            wgpu::TextureFormat::Rgba32Float,
            "indirect radiance",
        );
        let tv: Vec<_> = view
            .targets
            .iter()
            .chain([&accum])
            .map(|t| t.create_view(&Default::default()))
            .collect();
        // The splat pass reads the accumulation binding too; bind the albedo there instead
        // (it is not read by fs_splat) so that the target is not bound twice.
        let bind = |accum_view: &wgpu::TextureView| {
            d.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("splat"),
                layout: &pipes.layout,
                entries: &[
                    wgpu::BindGroupEntry {
                        binding: 0,
                        resource: params_buf.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 1,
                        resource: wgpu::BindingResource::TextureView(&tv[0]),
                    },
                    wgpu::BindGroupEntry {
                        binding: 2,
                        resource: wgpu::BindingResource::TextureView(&tv[1]),
                    },
                    wgpu::BindGroupEntry {
                        binding: 3,
                        resource: wgpu::BindingResource::TextureView(&tv[2]),
                    },
                    wgpu::BindGroupEntry {
                        binding: 4,
                        resource: wgpu::BindingResource::TextureView(accum_view),
                    },
                ],
            })
        };
        let instances: Vec<SplatPhoton> = photons
            .iter()
            .filter(|p| {
                p.position.is_finite()
                    && p.power.is_finite()
                    && p.radius > 0.0
                    && p.radius.is_finite()
            })
            .map(|p| SplatPhoton {
                position_radius: p.position.extend(p.radius).to_array(),
                power: p.power.extend(0.0).to_array(),
                direction: p.direction.extend(0.0).to_array(),
            })
            .collect();
        let instance_buf = (!instances.is_empty()).then(|| {
            d.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("photons"),
                contents: bytemuck::cast_slice(&instances),
                usage: wgpu::BufferUsages::VERTEX,
            })
        });
        {
            let dummy = texture(1, 1, pipes.accum_format, "unused");
            let dummy_view = dummy.create_view(&Default::default());
            let bind_splat = bind(&dummy_view);
            let mut pass = super::clear_pass(&mut enc, "splat", &tv[3]);
            if let Some(buf) = &instance_buf {
                pass.set_pipeline(&pipes.splat);
                pass.set_bind_group(0, &bind_splat, &[]);
                pass.set_vertex_buffer(0, buf.slice(..));
                pass.draw(0..6, 0..instances.len() as u32);
            }
        }
        {
            let bind_up = bind(&tv[3]);
            let out_view = indirect.create_view(&Default::default());
            let mut pass = super::clear_pass(&mut enc, "upsample", &out_view);
            pass.set_pipeline(&pipes.upsample);
            pass.set_bind_group(0, &bind_up, &[]);
            pass.draw(0..3, 0..1);
        }
        let planes = self.read_back(
            enc,
            &[
                (&view.targets[0], 16),
                (&view.targets[1], 8),
                (&view.targets[2], 8),
                (&view.direct, 16),
                (&indirect, 16),
            ],
            width,
            height,
        )?;
        Ok(PhotonFrame {
            gbuffer: GBuffer::from_planes(width, height, &planes),
            direct: super::rgb(&planes[3]),
            indirect: super::rgb(&planes[4]),
        })
    }
}
