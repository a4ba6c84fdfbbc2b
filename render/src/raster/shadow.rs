//! Shadow maps: six cube faces for a point light (and for a Lambertian surface emitter), one
//! perspective view for a spot light, one orthographic view for the sun, rendered into one
//! depth array. [`ShadowMaps`] keeps the array between frames and renders it again only when
//! a light or the geometry changed.

use cloudlight_scenes::LightState;
use glam::{Mat4, Vec3};

use super::gbuffer::Chunks;
use super::pipelines::VIEW_STRIDE;
use super::targets::cleared_depth;
use super::{Raster, RasterError};

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

/// Lights the direct pass holds: the length of its uniform `lights` array in direct.wgsl
/// (a uniform array, because llvmpipe reads it faster than a storage buffer). Each takes
/// 80 bytes: 20 KiB in all.
pub const MAX_LIGHTS: usize = 256;

/// Must match `LightGpu` in direct.wgsl.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct LightGpu {
    position: [f32; 4],
    direction: [f32; 4],
    intensity: [f32; 4],
    shadow_right: [f32; 4],
    shadow_up: [f32; 4],
}

/// Must match `Params` in direct.wgsl.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct DirectParams {
    light_count: u32,
    depth_bias: f32,
    normal_offset_m: f32,
    cube_cot: f32,
    near_m: f32,
    far_m: f32,
    cube_lights: u32,
    pad: f32,
}

/// The projection of every cube face of a scene: direct.wgsl's `cube_view` computes a
/// face's shadow coordinates from these three numbers instead of reading its matrix.
#[derive(Clone, Copy, Debug, PartialEq)]
struct CubeProjection {
    fov_rad: f32,
    near_m: f32,
    far_m: f32,
}

impl CubeProjection {
    /// Faces a little wider than 90°, so that their borders overlap; planes from the
    /// scene's bounding radius.
    fn of_bounds(lo: Vec3, hi: Vec3) -> Self {
        let radius = ((hi - lo).length() * 0.5).max(1e-3);
        CubeProjection {
            fov_rad: 92f32.to_radians(),
            near_m: radius * 1e-3,
            far_m: radius * 4.0,
        }
    }

    /// clip_from_world of face `face` (an index into [`CUBE_FACES`]) seen from `eye`.
    fn face(&self, eye: Vec3, face: usize) -> Mat4 {
        let (dir, up) = CUBE_FACES[face];
        perspective_view(eye, dir, up, self.fov_rad, self.near_m, self.far_m)
    }
}

/// Cube-map faces (view direction, up); the order, and the right (direction × up) and up
/// (right × direction) axes of each, are written out in cube_view() in direct.wgsl:
/// +x, −x, +y, −y, +z, −z.
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

fn light_gpu(
    position: Vec3,
    kind: f32,
    direction: Vec3,
    w: f32,
    rgb: Vec3,
    first: usize,
) -> LightGpu {
    LightGpu {
        position: position.extend(kind).to_array(),
        direction: direction.extend(w).to_array(),
        intensity: rgb.extend(first as f32).to_array(),
        shadow_right: [0.0; 4],
        shadow_up: [0.0; 4],
    }
}

impl LightGpu {
    /// Whether the light's shadow is a cube map (a point light or a surface sample).
    fn has_cube(&self) -> bool {
        self.position[3] == 0.0 || self.position[3] == 3.0
    }
}

/// The right and up axes of a look_to view along `dir` (what glam's `look_to_mat4` uses).
fn view_axes(dir: Vec3, up: Vec3) -> (Vec3, Vec3) {
    let right = dir.cross(up).normalize();
    (right, right.cross(dir))
}

/// A light record whose one shadow view looks along `dir` from its `position`: the view's
/// right axis carries the scale from view units to NDC, the up axis the depth scale (0 for
/// a perspective view, whose depth follows the cube faces' near and far planes).
fn with_view_axes(
    mut gpu: LightGpu,
    dir: Vec3,
    up: Vec3,
    scale: f32,
    depth_scale: f32,
) -> LightGpu {
    let (right, up) = view_axes(dir, up);
    gpu.shadow_right = right.extend(scale).to_array();
    gpu.shadow_up = up.extend(depth_scale).to_array();
    gpu
}

/// The shadow views of every light (clip_from_world) in a scene of bounds `lo..hi`, and
/// each light's GPU record.
fn shadow_views(lights: &[LightState], lo: Vec3, hi: Vec3) -> (Vec<Mat4>, Vec<LightGpu>) {
    let center = (lo + hi) * 0.5;
    let radius = ((hi - lo).length() * 0.5).max(1e-3);
    let projection = CubeProjection::of_bounds(lo, hi);
    let (near, far) = (projection.near_m, projection.far_m);
    let mut views = Vec::new();
    let mut gpu = Vec::new();
    let cube = |views: &mut Vec<Mat4>, eye: Vec3| {
        views.extend((0..CUBE_FACES.len()).map(|face| projection.face(eye, face)));
    };
    for l in lights {
        let first = views.len();
        match *l {
            LightState::Point {
                position,
                intensity,
            } => {
                cube(&mut views, position);
                gpu.push(light_gpu(position, 0.0, Vec3::ZERO, 0.0, intensity, first));
            }
            LightState::Surface {
                position,
                normal,
                intensity,
            } => {
                // Shadow views from just in front of the emitter, over the whole sphere.
                let eye = surface_eye(position, normal, lo, hi);
                cube(&mut views, eye);
                gpu.push(light_gpu(eye, 3.0, normal, 0.0, intensity, first));
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
                gpu.push(with_view_axes(
                    light_gpu(position, 1.0, direction, cos_cone, intensity, first),
                    direction,
                    up,
                    1.0 / (fov * 0.5).tan(),
                    0.0,
                ));
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
                gpu.push(with_view_axes(
                    light_gpu(eye, 2.0, d, 0.0, irradiance, first),
                    d,
                    up,
                    1.0 / radius,
                    1.0 / (radius * 4.0),
                ));
            }
        }
    }
    (views, gpu)
}

/// GPU resources sized for one light configuration.
struct ShadowResources {
    layers: u32,
    size: u32,
    _texture: wgpu::Texture,
    layer_views: Vec<wgpu::TextureView>,
    array_view: wgpu::TextureView,
    /// One matrix per layer at [`VIEW_STRIDE`] (the shadow pass's dynamic offsets).
    view_uniforms: wgpu::Buffer,
    view_bind: wgpu::BindGroup,
    /// `array<LightGpu>` of direct.wgsl.
    lights: wgpu::Buffer,
}

/// Whether moving a light from `a` to `b` changes its shadow maps by at least half a
/// texel (`tol_m` of position, `tol_rad` of direction); intensity never matters.
fn moved(a: &LightState, b: &LightState, tol_m: f32, tol_rad: f32) -> bool {
    let turned =
        |x: Vec3, y: Vec3| x.normalize_or_zero().dot(y.normalize_or_zero()) < tol_rad.cos();
    match (*a, *b) {
        (LightState::Point { position: p, .. }, LightState::Point { position: q, .. }) => {
            p.distance(q) > tol_m
        }
        (
            LightState::Surface {
                position: p,
                normal: n,
                ..
            },
            LightState::Surface {
                position: q,
                normal: m,
                ..
            },
        ) => p.distance(q) > tol_m || turned(n, m),
        (
            LightState::Spot {
                position: p,
                direction: d,
                cos_cone: c,
                ..
            },
            LightState::Spot {
                position: q,
                direction: e,
                cos_cone: k,
                ..
            },
        ) => p.distance(q) > tol_m || turned(d, e) || c != k,
        (
            LightState::Directional { direction: d, .. },
            LightState::Directional { direction: e, .. },
        ) => turned(d, e),
        _ => true,
    }
}

/// Shadow views of one light.
fn view_count(light: &LightState) -> usize {
    match light {
        LightState::Point { .. } | LightState::Surface { .. } => 6,
        LightState::Spot { .. } | LightState::Directional { .. } => 1,
    }
}

/// What of a shadow view is drawn: a surface emitter lights only the half-space in front of
/// it (direct.wgsl's `unshadowed` is zero behind it), so of its cube faces only the part
/// that looks into that half-space matters — one face of six for an emitter facing along an
/// axis, half of four others. The rest of a face keeps whatever depth it held, which
/// nothing reads with a weight.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Drawn {
    Whole,
    /// Texels `x..x + w`, rows `y..y + h` (the scissor of the view's pass).
    Rect {
        x: u32,
        y: u32,
        w: u32,
        h: u32,
    },
    Nothing,
}

/// Texels around the part of a view in front of an emitter that are drawn too: the direct
/// pass's comparison sampler filters a 2×2 footprint.
const FRONT_MARGIN_TEXELS: f32 = 2.0;

/// The part of view `clip_from_world` (a perspective view from `eye`, `size`² texels) that
/// looks into the half-space in front of the plane through `eye` with normal `normal`.
fn front_part(clip_from_world: Mat4, eye: Vec3, normal: Vec3, size: u32) -> Drawn {
    let world_from_clip = clip_from_world.inverse();
    // At one NDC depth a perspective view's points are affine in NDC x and y, so the plane's
    // side is too: clip the view's square by it along its edges.
    let corners = [(-1.0f32, -1.0f32), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)];
    let side =
        |(u, v): (f32, f32)| normal.dot(world_from_clip.project_point3(Vec3::new(u, v, 0.5)) - eye);
    let g = corners.map(side);
    if g.iter().all(|g| *g > 0.0) {
        return Drawn::Whole;
    }
    let (mut lo, mut hi) = (
        glam::Vec2::splat(f32::INFINITY),
        glam::Vec2::splat(f32::NEG_INFINITY),
    );
    for i in 0..4 {
        let (a, b) = (corners[i], corners[(i + 1) % 4]);
        let (ga, gb) = (g[i], g[(i + 1) % 4]);
        let mut take = |p: glam::Vec2| {
            lo = lo.min(p);
            hi = hi.max(p);
        };
        if ga > 0.0 {
            take(glam::Vec2::new(a.0, a.1));
        }
        if (ga > 0.0) != (gb > 0.0) {
            let t = ga / (ga - gb);
            take(glam::Vec2::new(
                a.0 + (b.0 - a.0) * t,
                a.1 + (b.1 - a.1) * t,
            ));
        }
    }
    if lo.x > hi.x {
        return Drawn::Nothing;
    }
    // NDC to texels: x right, rows down (direct.wgsl's `lit`).
    let texels = size as f32;
    let margin = FRONT_MARGIN_TEXELS;
    let x0 = ((lo.x + 1.0) * 0.5 * texels - margin)
        .floor()
        .clamp(0.0, texels) as u32;
    let x1 = ((hi.x + 1.0) * 0.5 * texels + margin)
        .ceil()
        .clamp(0.0, texels) as u32;
    let y0 = ((1.0 - hi.y) * 0.5 * texels - margin)
        .floor()
        .clamp(0.0, texels) as u32;
    let y1 = ((1.0 - lo.y) * 0.5 * texels + margin)
        .ceil()
        .clamp(0.0, texels) as u32;
    if x0 == 0 && y0 == 0 && x1 == size && y1 == size {
        return Drawn::Whole;
    }
    Drawn::Rect {
        x: x0,
        y: y0,
        w: x1 - x0,
        h: y1 - y0,
    }
}

/// What of each of a light's views (`views`, its own) is drawn.
fn drawn_parts(light: &LightState, views: &[Mat4], lo: Vec3, hi: Vec3, size: u32) -> Vec<Drawn> {
    match *light {
        LightState::Surface {
            position, normal, ..
        } => {
            let eye = surface_eye(position, normal, lo, hi);
            views
                .iter()
                .map(|v| front_part(*v, eye, normal, size))
                .collect()
        }
        _ => vec![Drawn::Whole; views.len()],
    }
}

/// Where a surface emitter's shadow views look from: just in front of it.
fn surface_eye(position: Vec3, normal: Vec3, lo: Vec3, hi: Vec3) -> Vec3 {
    let radius = ((hi - lo).length() * 0.5).max(1e-3);
    position + normal * radius * 1e-3
}

/// The shadow maps of one client, kept between frames: each light's views are rendered again
/// only when that light moved (by half a texel or more) or the geometry changed.
pub struct ShadowMaps {
    settings: ShadowSettings,
    resources: Option<ShadowResources>,
    /// Per light: the state its maps were rendered for.
    rendered: Vec<Option<LightState>>,
    /// The view matrices the maps hold, per layer.
    views: Vec<Mat4>,
    /// What of each layer was drawn last (its pass's scissor).
    drawn: Vec<Drawn>,
    /// Geometry version and bounds the maps were rendered with.
    geometry: Option<(u64, Vec3, Vec3)>,
    params: wgpu::Buffer,
    /// Bumped whenever the resources are re-created (the direct pass re-binds them).
    pub(crate) generation: u64,
    /// Frames that rendered any shadow view.
    pub renders: u64,
    /// Shadow views rendered in all.
    pub views_rendered: u64,
}

impl ShadowMaps {
    pub(crate) fn new(raster: &Raster, settings: ShadowSettings) -> Self {
        ShadowMaps {
            settings,
            resources: None,
            rendered: Vec::new(),
            views: Vec::new(),
            drawn: Vec::new(),
            geometry: None,
            params: raster.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("direct params"),
                size: std::mem::size_of::<DirectParams>() as u64,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }),
            generation: 0,
            renders: 0,
            views_rendered: 0,
        }
    }

    fn resources(&mut self, raster: &Raster, layers: u32) -> bool {
        let size = self
            .settings
            .size
            .clamp(1, raster.device.limits().max_texture_dimension_2d);
        let fits = self
            .resources
            .as_ref()
            .is_some_and(|r| r.layers == layers && r.size == size);
        if !fits {
            self.generation += 1;
            self.resources = Some(ShadowResources::new(raster, layers, size));
        }
        !fits
    }

    /// Brings the maps up to date for `lights` (geometry `vertices`, version
    /// `geometry_version`, bounds `lo..hi`), recording the views to render into `enc`;
    /// returns whether any view was rendered.
    pub(crate) fn update(
        &mut self,
        raster: &Raster,
        enc: &mut wgpu::CommandEncoder,
        lights: &[LightState],
        vertices: Option<(&wgpu::Buffer, &Chunks)>,
        geometry_version: u64,
        (lo, hi): (Vec3, Vec3),
    ) -> Result<bool, RasterError> {
        let (views, gpu_lights) = shadow_views(lights, lo, hi);
        // wgpu's GL backend guesses a texture's target from its size: one layer becomes a
        // 2D texture and a multiple of six square layers a cube map, neither of which a
        // 2D-array view can sample. Keep at least two layers, and a spare one after a
        // multiple of six.
        let mut layers = views.len().max(2) as u32;
        if layers.is_multiple_of(6) {
            layers += 1;
        }
        let max = raster.device.limits().max_texture_array_layers;
        if layers > max {
            return Err(RasterError::TooManyShadowViews { views: layers, max });
        }
        if lights.len() > MAX_LIGHTS {
            return Err(RasterError::TooManyLights {
                lights: lights.len(),
                max: MAX_LIGHTS,
            });
        }
        let layout_changed = self.rendered.len() != lights.len()
            || self
                .rendered
                .iter()
                .zip(lights)
                .any(|(r, l)| r.as_ref().is_none_or(|r| view_count(r) != view_count(l)));
        let recreated = self.resources(raster, layers);
        if recreated || layout_changed || self.geometry != Some((geometry_version, lo, hi)) {
            self.rendered = vec![None; lights.len()];
            self.views = views.clone();
            self.drawn = vec![Drawn::Whole; views.len()];
            self.geometry = Some((geometry_version, lo, hi));
        }
        let texel = 0.5 / self.settings.size.max(1) as f32;
        let (tol_m, tol_rad) = ((hi - lo).length() * texel, texel);
        let mut dirty = Vec::new();
        let mut first = 0;
        for (i, light) in lights.iter().enumerate() {
            let n = view_count(light);
            if self.rendered[i]
                .as_ref()
                .is_none_or(|r| moved(r, light, tol_m, tol_rad))
            {
                self.views[first..first + n].copy_from_slice(&views[first..first + n]);
                let size = self.resources.as_ref().map_or(1, |r| r.size);
                self.drawn[first..first + n].copy_from_slice(&drawn_parts(
                    light,
                    &views[first..first + n],
                    lo,
                    hi,
                    size,
                ));
                self.rendered[i] = Some(*light);
                dirty.extend(first..first + n);
            }
            first += n;
        }
        self.write_buffers(raster, &gpu_lights, (lo, hi));
        self.render_layers(raster, enc, &dirty, vertices);
        self.views_rendered += dirty.len() as u64;
        self.renders += u64::from(!dirty.is_empty());
        Ok(!dirty.is_empty())
    }

    /// Records the shadow pass of each of `layers`.
    fn render_layers(
        &self,
        raster: &Raster,
        enc: &mut wgpu::CommandEncoder,
        layers: &[usize],
        vertices: Option<(&wgpu::Buffer, &Chunks)>,
    ) {
        let Some(r) = self.resources.as_ref() else {
            return;
        };
        for &layer in layers {
            if self.drawn[layer] == Drawn::Nothing {
                continue;
            }
            let mut pass = enc.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("shadow"),
                color_attachments: &[],
                depth_stencil_attachment: cleared_depth(&r.layer_views[layer]),
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
            if let Drawn::Rect { x, y, w, h } = self.drawn[layer] {
                pass.set_scissor_rect(x, y, w, h);
            }
            if let Some((vbuf, chunks)) = vertices {
                pass.set_pipeline(&raster.pipelines.shadow);
                pass.set_bind_group(0, &r.view_bind, &[(layer as u64 * VIEW_STRIDE) as u32]);
                pass.set_vertex_buffer(0, vbuf.slice(..));
                for run in chunks.visible(self.views[layer]) {
                    pass.draw(run, 0..1);
                }
            }
        }
    }

    /// Writes the view matrices the maps hold, the lights and the direct pass's parameters.
    fn write_buffers(&self, raster: &Raster, gpu_lights: &[LightGpu], (lo, hi): (Vec3, Vec3)) {
        let cube = CubeProjection::of_bounds(lo, hi);
        // Cube lights first: the direct pass loops over each kind of shadow separately.
        let mut ordered = gpu_lights.to_vec();
        ordered.sort_by_key(|l| !l.has_cube());
        let cube_lights = ordered.iter().filter(|l| l.has_cube()).count() as u32;
        let params = DirectParams {
            light_count: gpu_lights.len() as u32,
            depth_bias: self.settings.depth_bias,
            normal_offset_m: self.settings.normal_offset * (hi - lo).length(),
            cube_cot: 1.0 / (cube.fov_rad * 0.5).tan(),
            near_m: cube.near_m,
            far_m: cube.far_m,
            cube_lights,
            pad: 0.0,
        };
        raster
            .queue
            .write_buffer(&self.params, 0, bytemuck::bytes_of(&params));
        let Some(r) = &self.resources else { return };
        let mut uniforms = vec![0u8; (VIEW_STRIDE * r.layers as u64) as usize];
        for (i, m) in self.views.iter().enumerate() {
            let at = i * VIEW_STRIDE as usize;
            uniforms[at..at + 64].copy_from_slice(bytemuck::cast_slice(&m.to_cols_array()));
        }
        raster.queue.write_buffer(&r.view_uniforms, 0, &uniforms);
        if !gpu_lights.is_empty() {
            raster
                .queue
                .write_buffer(&r.lights, 0, bytemuck::cast_slice(&ordered));
        }
    }

    /// The bindings the direct pass reads: the depth array, lights and parameters.
    pub(crate) fn bindings(&self) -> Option<(&wgpu::TextureView, &wgpu::Buffer, &wgpu::Buffer)> {
        self.resources
            .as_ref()
            .map(|r| (&r.array_view, &r.lights, &self.params))
    }
}

impl ShadowResources {
    fn new(raster: &Raster, layers: u32, size: u32) -> Self {
        let d = &raster.device;
        let texture = d.create_texture(&wgpu::TextureDescriptor {
            label: Some("shadow maps"),
            size: wgpu::Extent3d {
                width: size,
                height: size,
                depth_or_array_layers: layers,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: raster.formats().depth,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::TEXTURE_BINDING,
            view_formats: &[],
        });
        let layer_views = (0..layers)
            .map(|layer| {
                texture.create_view(&wgpu::TextureViewDescriptor {
                    dimension: Some(wgpu::TextureViewDimension::D2),
                    base_array_layer: layer,
                    array_layer_count: Some(1),
                    ..Default::default()
                })
            })
            .collect();
        let array_view = texture.create_view(&wgpu::TextureViewDescriptor {
            dimension: Some(wgpu::TextureViewDimension::D2Array),
            ..Default::default()
        });
        let buffer = |label, size: u64, usage| {
            d.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size,
                usage: usage | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            })
        };
        let view_uniforms = buffer(
            "shadow view matrices",
            VIEW_STRIDE * layers as u64,
            wgpu::BufferUsages::UNIFORM,
        );
        let view_bind = super::targets::view_bind_group(raster, &view_uniforms, "shadow views");
        let lights = buffer(
            "lights",
            (std::mem::size_of::<LightGpu>() * MAX_LIGHTS) as u64,
            wgpu::BufferUsages::UNIFORM,
        );
        ShadowResources {
            layers,
            size,
            _texture: texture,
            layer_views,
            array_view,
            view_uniforms,
            view_bind,
            lights,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_surface_emitters_cube_faces_are_drawn_only_where_they_look_in_front_of_it() {
        let (lo, hi) = (Vec3::ZERO, Vec3::ONE);
        let size = 256;
        let down = LightState::Surface {
            position: Vec3::new(0.5, 0.9, 0.5),
            normal: Vec3::NEG_Y,
            intensity: Vec3::ONE,
        };
        let (views, _) = shadow_views(&[down], lo, hi);
        let drawn = drawn_parts(&down, &views, lo, hi, size);
        // +x, −x, +y, −y, +z, −z: the face looking up sees only behind the emitter, the one
        // looking down only in front; each side face (whose up is −y) is drawn above its
        // middle row.
        assert_eq!(drawn[2], Drawn::Nothing);
        assert_eq!(drawn[3], Drawn::Whole);
        for face in [0, 1, 4, 5] {
            let Drawn::Rect { x, y, w, h } = drawn[face] else {
                panic!("face {face}: {:?}", drawn[face]);
            };
            assert_eq!((x, w), (0, size), "face {face}");
            // Rows from the top to the middle (and the margin).
            assert!(y == 0 && (128..=130).contains(&h), "face {face}: {y}+{h}");
        }
        // A tilted emitter: every face is drawn where, and only where, it looks in front.
        let normal = Vec3::new(0.3, -0.6, -0.7).normalize();
        let tilted = LightState::Surface {
            position: Vec3::new(0.5, 0.9, 0.5),
            normal,
            intensity: Vec3::ONE,
        };
        let (views, _) = shadow_views(&[tilted], lo, hi);
        let eye = surface_eye(Vec3::new(0.5, 0.9, 0.5), normal, lo, hi);
        for (face, (view, part)) in views
            .iter()
            .zip(drawn_parts(&tilted, &views, lo, hi, size))
            .enumerate()
        {
            let world_from_clip = view.inverse();
            for ty in 0..size {
                for tx in 0..size {
                    let ndc = Vec3::new(
                        (tx as f32 + 0.5) / size as f32 * 2.0 - 1.0,
                        1.0 - (ty as f32 + 0.5) / size as f32 * 2.0,
                        0.5,
                    );
                    let front = normal.dot(world_from_clip.project_point3(ndc) - eye) > 0.0;
                    let inside = match part {
                        Drawn::Whole => true,
                        Drawn::Nothing => false,
                        Drawn::Rect { x, y, w, h } => {
                            (x..x + w).contains(&tx) && (y..y + h).contains(&ty)
                        }
                    };
                    assert!(!front || inside, "face {face}: texel {tx},{ty} in front");
                }
            }
        }
        // Point lights and a light in front of the whole view are drawn whole.
        let point = LightState::Point {
            position: Vec3::splat(0.5),
            intensity: Vec3::ONE,
        };
        let (views, _) = shadow_views(&[point], lo, hi);
        assert!(
            drawn_parts(&point, &views, lo, hi, size)
                .iter()
                .all(|d| *d == Drawn::Whole)
        );
    }
}
