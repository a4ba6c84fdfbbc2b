//! Direct lighting on the raster: shadow maps (six cube faces for a point light, one
//! perspective view for a spot light, one orthographic view for the sun) rendered into a
//! depth array, then a full-screen pass that shades the G-buffer with every light.

use cloudlight_scenes::{Camera, LightState, Scene, WorldTriangle};
use glam::{Mat4, Vec3};
use wgpu::util::DeviceExt;

use super::{GBuffer, Raster, RasterError};

/// Shadow-map settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ShadowSettings {
    /// Side of each shadow map, texels.
    pub size: u32,
    /// Depth compared against the shadow map is reduced by this (NDC units).
    pub depth_bias: f32,
    /// Shaded points are pushed this far along their normal, as a fraction of the scene's
    /// bounding diagonal.
    pub normal_offset: f32,
}

impl Default for ShadowSettings {
    fn default() -> Self {
        ShadowSettings {
            size: 1024,
            depth_bias: 2e-5,
            normal_offset: 2e-3,
        }
    }
}

/// The GPU targets of one view after the direct pass.
pub(crate) struct DirectView {
    /// G-buffer position, normal and albedo.
    pub(crate) targets: [wgpu::Texture; 3],
    /// Direct radiance (Rgba32Float).
    pub(crate) direct: wgpu::Texture,
    /// Bounding diagonal of the triangles, meters.
    pub(crate) scene_extent: f32,
}

/// Must match `LightGpu` in direct.wgsl.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct LightGpu {
    position: [f32; 4],
    direction: [f32; 4],
    intensity: [f32; 4],
}

/// Must match `Params` in direct.wgsl.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Params {
    light_count: u32,
    depth_bias: f32,
    normal_offset_m: f32,
    pad: f32,
}

/// Cube-map faces (view direction, up); the order matches cube_face() in direct.wgsl:
/// +x, −x, +y, −y, +z, −z. Views are a little wider than 90° so that face borders overlap.
const CUBE_FACES: [(Vec3, Vec3); 6] = [
    (Vec3::X, Vec3::NEG_Y),
    (Vec3::NEG_X, Vec3::NEG_Y),
    (Vec3::Y, Vec3::Z),
    (Vec3::NEG_Y, Vec3::NEG_Z),
    (Vec3::Z, Vec3::NEG_Y),
    (Vec3::NEG_Z, Vec3::NEG_Y),
];

fn perspective_view(eye: Vec3, dir: Vec3, up: Vec3, fov: f32, near: f32, far: f32) -> Mat4 {
    glam::camera::rh::proj::directx::perspective(fov, 1.0, near, far)
        * glam::camera::rh::view::look_to_mat4(eye, dir, up)
}

/// The shadow views of every light (clip_from_world), and each light's GPU record.
fn shadow_views(lights: &[LightState], lo: Vec3, hi: Vec3) -> (Vec<Mat4>, Vec<LightGpu>) {
    let center = (lo + hi) * 0.5;
    let radius = ((hi - lo).length() * 0.5).max(1e-3);
    let (near, far) = (radius * 1e-3, radius * 4.0);
    let mut views = Vec::new();
    let mut gpu = Vec::new();
    for l in lights {
        let first = views.len() as f32;
        match *l {
            LightState::Point {
                position,
                intensity,
            } => {
                for (dir, up) in CUBE_FACES {
                    views.push(perspective_view(
                        position,
                        dir,
                        up,
                        92f32.to_radians(),
                        near,
                        far,
                    ));
                }
                gpu.push(LightGpu {
                    position: [position.x, position.y, position.z, 0.0],
                    direction: [0.0; 4],
                    intensity: [intensity.x, intensity.y, intensity.z, first],
                });
            }
            LightState::Surface {
                position,
                normal,
                intensity,
            } => {
                // Shadow views from just in front of the emitter, over the whole sphere.
                let eye = position + normal * radius * 1e-3;
                for (dir, up) in CUBE_FACES {
                    views.push(perspective_view(
                        eye,
                        dir,
                        up,
                        92f32.to_radians(),
                        near,
                        far,
                    ));
                }
                gpu.push(LightGpu {
                    position: [eye.x, eye.y, eye.z, 3.0],
                    direction: [normal.x, normal.y, normal.z, 0.0],
                    intensity: [intensity.x, intensity.y, intensity.z, first],
                });
            }
            LightState::Spot {
                position,
                direction,
                cos_cone,
                intensity,
            } => {
                let fov = (2.0 * cos_cone.clamp(-1.0, 1.0).acos() + 0.05).min(170f32.to_radians());
                let up = if direction.y.abs() > 0.9 {
                    Vec3::Z
                } else {
                    Vec3::Y
                };
                views.push(perspective_view(position, direction, up, fov, near, far));
                gpu.push(LightGpu {
                    position: [position.x, position.y, position.z, 1.0],
                    direction: [direction.x, direction.y, direction.z, cos_cone],
                    intensity: [intensity.x, intensity.y, intensity.z, first],
                });
            }
            LightState::Directional {
                direction,
                irradiance,
            } => {
                let d = direction.normalize_or(Vec3::NEG_Y);
                let up = if d.y.abs() > 0.9 { Vec3::Z } else { Vec3::Y };
                let eye = center - d * radius * 2.0;
                let proj = glam::camera::rh::proj::directx::orthographic(
                    -radius,
                    radius,
                    -radius,
                    radius,
                    0.0,
                    radius * 4.0,
                );
                views.push(proj * glam::camera::rh::view::look_to_mat4(eye, d, up));
                gpu.push(LightGpu {
                    position: [0.0, 0.0, 0.0, 2.0],
                    direction: [d.x, d.y, d.z, 0.0],
                    intensity: [irradiance.x, irradiance.y, irradiance.z, first],
                });
            }
        }
    }
    (views, gpu)
}

impl Raster {
    /// The G-buffer and the direct radiance (ρ/π · E_direct, with shadow maps) of the view.
    /// Emissive surfaces are not lights here; turn them into punctual lights first.
    #[allow(clippy::too_many_arguments)]
    pub fn direct(
        &self,
        scene: &Scene,
        triangles: &[WorldTriangle],
        lights: &[LightState],
        camera: &Camera,
        width: u32,
        height: u32,
        shadows: ShadowSettings,
    ) -> Result<(GBuffer, Vec<Vec3>), RasterError> {
        let mut enc = self.device.create_command_encoder(&Default::default());
        let view = self.encode_direct(
            &mut enc, scene, triangles, lights, camera, width, height, shadows,
        )?;
        let planes = self.read_back(
            enc,
            &[
                (&view.targets[0], 16),
                (&view.targets[1], 8),
                (&view.targets[2], 8),
                (&view.direct, 16),
            ],
            width,
            height,
        )?;
        Ok((
            GBuffer::from_planes(width, height, &planes),
            super::rgb(&planes[3]),
        ))
    }

    /// Records the shadow, G-buffer and direct-lighting passes into `enc`.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn encode_direct(
        &self,
        enc: &mut wgpu::CommandEncoder,
        scene: &Scene,
        triangles: &[WorldTriangle],
        lights: &[LightState],
        camera: &Camera,
        width: u32,
        height: u32,
        shadows: ShadowSettings,
    ) -> Result<DirectView, RasterError> {
        let d = &self.device;
        let mut lo = Vec3::splat(f32::INFINITY);
        let mut hi = Vec3::splat(f32::NEG_INFINITY);
        for t in triangles {
            for v in t.v {
                lo = lo.min(v);
                hi = hi.max(v);
            }
        }
        if !lo.is_finite() {
            (lo, hi) = (Vec3::ZERO, Vec3::ONE);
        }
        let (views, gpu_lights) = shadow_views(lights, lo, hi);
        let layers = views.len().max(1) as u32;
        let max_layers = d.limits().max_texture_array_layers;
        if layers > max_layers {
            return Err(RasterError::TooManyShadowViews {
                views: layers,
                max: max_layers,
            });
        }
        let shadow_tex = d.create_texture(&wgpu::TextureDescriptor {
            label: Some("shadow maps"),
            size: wgpu::Extent3d {
                width: shadows.size,
                height: shadows.size,
                depth_or_array_layers: layers,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: wgpu::TextureFormat::Depth32Float,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::TEXTURE_BINDING,
            view_formats: &[],
        });
        let positions: Vec<[f32; 3]> = triangles
            .iter()
            .flat_map(|t| t.v.map(|v| v.to_array()))
            .collect();
        let vbuf = (!positions.is_empty()).then(|| {
            d.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("shadow vertices"),
                contents: bytemuck::cast_slice(&positions),
                usage: wgpu::BufferUsages::VERTEX,
            })
        });
        for layer in 0..layers {
            let view = shadow_tex.create_view(&wgpu::TextureViewDescriptor {
                dimension: Some(wgpu::TextureViewDimension::D2),
                base_array_layer: layer,
                array_layer_count: Some(1),
                ..Default::default()
            });
            let matrix = views.get(layer as usize).copied().unwrap_or(Mat4::IDENTITY);
            let bind = self.matrix_bind_group(matrix, "shadow view");
            let mut pass = enc.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("shadow"),
                color_attachments: &[],
                depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                    view: &view,
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
            if let (Some(vbuf), true) = (&vbuf, (layer as usize) < views.len()) {
                pass.set_pipeline(&self.shadow);
                pass.set_bind_group(0, &bind, &[]);
                pass.set_vertex_buffer(0, vbuf.slice(..));
                pass.draw(0..positions.len() as u32, 0..1);
            }
        }
        let targets = self.encode_gbuffer(enc, scene, triangles, camera, width, height);
        let out = d.create_texture(&wgpu::TextureDescriptor {
            label: Some("direct"),
            size: wgpu::Extent3d {
                width,
                height,
                depth_or_array_layers: 1,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: wgpu::TextureFormat::Rgba32Float,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
            view_formats: &[],
        });
        let placeholder = LightGpu {
            position: [0.0; 4],
            direction: [0.0; 4],
            intensity: [0.0; 4],
        };
        let light_data = if gpu_lights.is_empty() {
            vec![placeholder]
        } else {
            gpu_lights.clone()
        };
        let view_data: Vec<[f32; 16]> = if views.is_empty() {
            vec![Mat4::IDENTITY.to_cols_array()]
        } else {
            views.iter().map(|m| m.to_cols_array()).collect()
        };
        let storage = |label, bytes: &[u8]| {
            d.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: bytes,
                usage: wgpu::BufferUsages::STORAGE,
            })
        };
        let lights_buf = storage("lights", bytemuck::cast_slice(&light_data));
        let views_buf = storage("views", bytemuck::cast_slice(&view_data));
        let extent = (hi - lo).length();
        let params = Params {
            light_count: gpu_lights.len() as u32,
            depth_bias: shadows.depth_bias,
            normal_offset_m: shadows.normal_offset * extent,
            pad: 0.0,
        };
        let params_buf = d.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("params"),
            contents: bytemuck::bytes_of(&params),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let sampler = d.create_sampler(&wgpu::SamplerDescriptor {
            compare: Some(wgpu::CompareFunction::LessEqual),
            ..Default::default()
        });
        let tv: Vec<_> = targets
            .iter()
            .map(|t| t.create_view(&Default::default()))
            .collect();
        let shadow_view = shadow_tex.create_view(&wgpu::TextureViewDescriptor {
            dimension: Some(wgpu::TextureViewDimension::D2Array),
            ..Default::default()
        });
        let bind = d.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("direct"),
            layout: &self.direct_layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: wgpu::BindingResource::TextureView(&tv[0]),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wgpu::BindingResource::TextureView(&tv[1]),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: wgpu::BindingResource::TextureView(&tv[2]),
                },
                wgpu::BindGroupEntry {
                    binding: 3,
                    resource: wgpu::BindingResource::TextureView(&shadow_view),
                },
                wgpu::BindGroupEntry {
                    binding: 4,
                    resource: wgpu::BindingResource::Sampler(&sampler),
                },
                wgpu::BindGroupEntry {
                    binding: 5,
                    resource: lights_buf.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 6,
                    resource: views_buf.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 7,
                    resource: params_buf.as_entire_binding(),
                },
            ],
        });
        {
            let out_view = out.create_view(&Default::default());
            let mut pass = super::clear_pass(enc, "direct", &out_view);
            pass.set_pipeline(&self.direct_pipeline);
            pass.set_bind_group(0, &bind, &[]);
            pass.draw(0..3, 0..1);
        }
        Ok(DirectView {
            targets,
            direct: out,
            scene_extent: extent,
        })
    }
}
