//! The G-buffer pass: world position, normal, albedo and light-map UV of the nearest surface
//! per pixel, from
//! the geometry uploaded once ([`Geometry`]), drawing only the chunks of triangles the view's
//! frustum reaches ([`Chunks`]).

use cloudlight_scenes::WorldTriangle;
use glam::{Mat4, Vec3};

use super::Raster;
use super::pipelines::VIEW_STRIDE;
use super::targets::{
    GBufferTargets, cleared_colour, cleared_depth, loaded_colour, view_bind_group,
};

/// The geometry as the G-buffer and shadow passes draw it.
#[derive(Default)]
pub(crate) struct Geometry {
    pub(crate) gbuffer: Option<wgpu::Buffer>,
    /// The scene's albedo textures (uploaded with the geometry the first time).
    pub(crate) albedo: Option<super::albedo::AlbedoTextures>,
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
        self.runs(
            (0..self.bounds.len()).filter(|&i| Self::in_frustum(clip_from_world, self.bounds[i])),
        )
    }

    /// [`Self::visible`], the chunk nearest to `eye` first (by the distance from `eye` to
    /// its box): the depth test then rejects what nearer chunks hide before it is shaded.
    pub(crate) fn visible_near_first(
        &self,
        clip_from_world: Mat4,
        eye: Vec3,
    ) -> Vec<std::ops::Range<u32>> {
        let mut near: Vec<(f32, usize)> = (0..self.bounds.len())
            .filter(|&i| Self::in_frustum(clip_from_world, self.bounds[i]))
            .map(|i| {
                let (lo, hi) = self.bounds[i];
                (eye.clamp(lo, hi).distance_squared(eye), i)
            })
            .collect();
        near.sort_by(|a, b| a.0.total_cmp(&b.0));
        self.runs(near.into_iter().map(|(_, i)| i))
    }

    /// The vertex ranges of `chunks` in their order, a chunk that continues the one before
    /// merged into it.
    fn runs(&self, chunks: impl Iterator<Item = usize>) -> Vec<std::ops::Range<u32>> {
        let mut runs: Vec<std::ops::Range<u32>> = Vec::new();
        let per = CHUNK_TRIANGLES as u32 * 3;
        for i in chunks {
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

    /// Records the pass: `geometry` seen through `clip` (clip_from_world) from `eye` →
    /// `targets`, nearest chunks first.
    pub(crate) fn encode(
        &self,
        raster: &Raster,
        enc: &mut wgpu::CommandEncoder,
        targets: &GBufferTargets,
        geometry: &Geometry,
        clip: Mat4,
        eye: Vec3,
    ) {
        raster
            .queue
            .write_buffer(&self.camera, 0, bytemuck::cast_slice(&clip.to_cols_array()));
        let g = targets;
        let mut pass = enc.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("gbuffer"),
            // Only the position (whose w says whether a surface was drawn) and the depth are
            // cleared: every reader of the others, on the GPU and in the read-back, looks at
            // a pixel's w first, and llvmpipe writes a cleared target in full (Cornell
            // 640×360 on lavapipe: the G-buffer pass ~0.4 ms faster).
            color_attachments: &[
                cleared_colour(&g.position.view),
                loaded_colour(&g.normal.view),
                loaded_colour(&g.albedo.view),
                loaded_colour(&g.lightmap_uv.view),
            ],
            depth_stencil_attachment: cleared_depth(&g.depth.view),
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        if let (Some(vbuf), Some(albedo)) = (&geometry.gbuffer, &geometry.albedo) {
            pass.set_pipeline(&raster.pipelines.gbuffer);
            pass.set_bind_group(0, &self.bind, &[0]);
            pass.set_bind_group(1, &albedo.bind, &[]);
            pass.set_vertex_buffer(0, vbuf.slice(..));
            for run in geometry.culled.visible_near_first(clip, eye) {
                pass.draw(run, 0..1);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use cloudlight_scenes::{Camera, WorldTriangle};
    use glam::{Vec2, Vec3};

    use super::{CHUNK_TRIANGLES, Chunks};

    /// Chunks of small triangles along a line, chunk `c` around x = 10·c (c = 0..8).
    fn row() -> Vec<WorldTriangle> {
        (0..8 * CHUNK_TRIANGLES)
            .map(|i| {
                let x = 10.0 * (i / CHUNK_TRIANGLES) as f32;
                WorldTriangle {
                    v: [
                        Vec3::new(x, 0.0, 0.0),
                        Vec3::new(x + 1.0, 0.0, 0.0),
                        Vec3::new(x, 1.0, 0.0),
                    ],
                    n: [Vec3::Z; 3],
                    uv: [Vec2::ZERO; 3],
                    lightmap_uv: [Vec2::ZERO; 3],
                    material: 0,
                }
            })
            .collect()
    }

    #[test]
    fn the_near_first_order_draws_what_the_frustum_sees_nearest_chunk_first() {
        let chunks = Chunks::new(&row());
        // Between chunks 5 and 6, looking down −x: chunks 0–5 in view, 6 and 7 behind.
        let camera = Camera {
            position: Vec3::new(55.0, 0.5, 2.0),
            target: Vec3::new(0.0, 0.5, 0.0),
            up: Vec3::Y,
            fov_y_rad: 1.0,
        };
        let (clip_from_view, view_from_world) =
            crate::raster::camera_matrices(&camera, 1.0, 0.1, 1000.0);
        let clip = clip_from_view * view_from_world;
        let per = CHUNK_TRIANGLES as u32 * 3;
        assert_eq!(chunks.visible(clip), vec![0..6 * per]);
        let near = chunks.visible_near_first(clip, camera.position);
        let order: Vec<u32> = near.iter().map(|r| r.start / per).collect();
        assert_eq!(order, vec![5, 4, 3, 2, 1, 0]);
        assert!(near.iter().all(|r| r.end - r.start == per));
    }
}
