//! The G-buffer pass: world position, normal, albedo and light-map UV of the nearest surface
//! per pixel, from
//! the geometry uploaded once ([`Geometry`]), drawing only the chunks of triangles the view's
//! frustum reaches ([`Chunks`]).

use cloudlight_scenes::WorldTriangle;
use glam::{Mat4, Vec3};

use super::Raster;
use super::pipelines::VIEW_STRIDE;
use super::targets::{GBufferTargets, cleared_colour, cleared_depth, view_bind_group};

/// The geometry as the G-buffer and shadow passes draw it.
#[derive(Default)]
pub(crate) struct Geometry {
    pub(crate) gbuffer: Option<wgpu::Buffer>,
    pub(crate) shadow: Option<wgpu::Buffer>,
    pub(crate) vertices: u32,
    pub(crate) bounds: (Vec3, Vec3),
    pub(crate) version: u64,
    pub(crate) culled: Chunks,
}

/// Triangles in consecutive chunks with their bounds, so that a view draws only the chunks
/// its frustum reaches (scenes list an object's triangles together, so chunks are compact).
#[derive(Clone, Debug, Default)]
pub(crate) struct Chunks {
    /// Per chunk: bounds (min, max).
    bounds: Vec<(Vec3, Vec3)>,
    vertices: u32,
}

/// Triangles per culling chunk.
const CHUNK_TRIANGLES: usize = 256;

impl Chunks {
    pub(crate) fn new(triangles: &[WorldTriangle]) -> Self {
        let bounds = triangles
            .chunks(CHUNK_TRIANGLES)
            .map(|c| {
                c.iter().flat_map(|t| t.v).fold(
                    (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
                    |(lo, hi), v| (lo.min(v), hi.max(v)),
                )
            })
            .collect();
        Chunks {
            bounds,
            vertices: triangles.len() as u32 * 3,
        }
    }

    /// Whether a box can be seen by `clip_from_world` (false only when all eight corners are
    /// outside one clip plane).
    fn in_frustum(clip_from_world: Mat4, (lo, hi): (Vec3, Vec3)) -> bool {
        if !(lo.is_finite() && hi.is_finite()) {
            return true;
        }
        let mut outside = [true; 6];
        for k in 0..8 {
            let corner = Vec3::new(
                if k & 1 == 0 { lo.x } else { hi.x },
                if k & 2 == 0 { lo.y } else { hi.y },
                if k & 4 == 0 { lo.z } else { hi.z },
            );
            let c = clip_from_world * corner.extend(1.0);
            let inside = [
                c.x >= -c.w,
                c.x <= c.w,
                c.y >= -c.w,
                c.y <= c.w,
                c.z >= 0.0,
                c.z <= c.w,
            ];
            for (o, i) in outside.iter_mut().zip(inside) {
                *o &= !i;
            }
        }
        !outside.iter().any(|o| *o)
    }

    /// The vertex ranges `clip_from_world` may see, neighbouring chunks merged.
    pub(crate) fn visible(&self, clip_from_world: Mat4) -> Vec<std::ops::Range<u32>> {
        let mut runs: Vec<std::ops::Range<u32>> = Vec::new();
        let per = CHUNK_TRIANGLES as u32 * 3;
        for (i, b) in self.bounds.iter().enumerate() {
            if !Self::in_frustum(clip_from_world, *b) {
                continue;
            }
            let (start, end) = (i as u32 * per, ((i as u32 + 1) * per).min(self.vertices));
            match runs.last_mut() {
                Some(r) if r.end == start => r.end = end,
                _ => runs.push(start..end),
            }
        }
        runs
    }
}

/// The G-buffer pass of one client: its camera uniform and bind group.
pub(crate) struct GBufferPass {
    camera: wgpu::Buffer,
    bind: wgpu::BindGroup,
}

impl GBufferPass {
    pub(crate) fn new(raster: &Raster) -> Self {
        let camera = raster.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("camera"),
            size: VIEW_STRIDE,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let bind = view_bind_group(raster, &camera, "camera");
        GBufferPass { camera, bind }
    }

    /// Records the pass: `geometry` seen through `clip` (clip_from_world) → `targets`.
    pub(crate) fn encode(
        &self,
        raster: &Raster,
        enc: &mut wgpu::CommandEncoder,
        targets: &GBufferTargets,
        geometry: &Geometry,
        clip: Mat4,
    ) {
        raster
            .queue
            .write_buffer(&self.camera, 0, bytemuck::cast_slice(&clip.to_cols_array()));
        let g = targets;
        let mut pass = enc.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("gbuffer"),
            color_attachments: &[
                cleared_colour(&g.position.view),
                cleared_colour(&g.normal.view),
                cleared_colour(&g.albedo.view),
                cleared_colour(&g.lightmap_uv.view),
            ],
            depth_stencil_attachment: cleared_depth(&g.depth.view),
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        if let Some(vbuf) = &geometry.gbuffer {
            pass.set_pipeline(&raster.pipelines.gbuffer);
            pass.set_bind_group(0, &self.bind, &[0]);
            pass.set_vertex_buffer(0, vbuf.slice(..));
            for run in geometry.culled.visible(clip) {
                pass.draw(run, 0..1);
            }
        }
    }
}
