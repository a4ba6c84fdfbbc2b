//! One client's frame, as named passes in order:
//!
//! 1. **G-buffer**: world position, normal, albedo, light-map UV and depth of the camera's
//!    view;
//! 2. **shadows**: the shadow maps of the frame's lights, only when a light or the geometry
//!    changed since they were last rendered;
//! 3. **direct**: the client's own light, ρ/π · E_direct;
//! 4. **indirect**: the technique's [`IndirectPass`] (photon splatting, a light-map lookup,
//!    …), writing ρ/π · E_indirect;
//! 5. **compose**: direct + indirect;
//! 6. **read-back**: only the targets asked for ([`Readback`]).
//!
//! A [`FrameRenderer`] makes its targets, geometry buffers, uniforms and bind groups once and
//! keeps them between frames; [`FrameRenderer::render`] can time each pass (a submit and a
//! wait after each one) for benchmarks.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use cloudlight_scenes::{Camera, LightState, Scene, WorldTriangle};
use glam::{Mat4, Vec2, Vec3, Vec4};
use wgpu::util::DeviceExt;

use super::accumulate::Accumulation;
use super::albedo::AlbedoTextures;
use super::compose::ComposePass;
use super::direct::DirectPass;
use super::gbuffer::{Chunks, GBufferPass, Geometry};
use super::pass::{IndirectContext, IndirectPass, NoIndirect, StepTimer};
use super::pipelines::GBufferVertex;
use super::readback::{Layout, read_planes, rgb};
use super::shadow::ShadowMaps;
use super::targets::{GBufferTargets, Target};
use super::{GBuffer, Raster, RasterError, ShadowSettings, camera_matrices};

/// Every target of a frame.
struct FrameTargets {
    gbuffer: GBufferTargets,
    /// ρ/π · E_direct, `f32` bits.
    direct: Target,
    /// ρ/π · E_indirect, `f32` bits (the technique's pass writes it).
    indirect: Target,
    /// direct + indirect, `f32` bits.
    composed: Target,
}

/// What a frame shows: its camera and the client's own lights.
#[derive(Clone, Copy, Debug)]
pub struct FrameInputs<'a> {
    /// The view.
    pub camera: Camera,
    /// Lights for direct light (punctual lights and surface emitter samples).
    pub lights: &'a [LightState],
    /// `Some(k)`: frame k of a still view (0 starts it; the caller says when nothing the
    /// frame shows has changed since frame k − 1). The frame samples its pixels at
    /// [`pixel_jitter`]`(k)` and is blended into the view's running mean, which is what is
    /// read back (`raster/accumulate.rs`). `None`: the frame alone, through the pixels'
    /// centres.
    pub still: Option<u32>,
}

/// Sub-pixel offset `k` of a still view's accumulation, pixels from the centre (x right, y
/// down): the centre first (a still view's first frame is the frame of a moving one), then
/// the Halton (2, 3) points 1, 2, … (every prefix spread over the pixel).
pub fn pixel_jitter(k: u32) -> Vec2 {
    if k == 0 {
        return Vec2::ZERO;
    }
    let x = (u64::from(k.reverse_bits()) as f64 / 4_294_967_296.0) as f32;
    Vec2::new(x, crate::sampling::radical_inverse3(k)) - Vec2::splat(0.5)
}

/// Which targets a frame reads back.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Readback {
    /// None (the frame is only shown or timed).
    Nothing,
    /// The G-buffer.
    GBuffer,
    /// The composed radiance (to write a picture).
    Composed,
    /// G-buffer, direct, indirect and composed (tests, quality measurements).
    Everything,
}

/// What a frame read back.
#[derive(Clone, Debug, Default)]
pub struct FrameImages {
    /// The G-buffer.
    pub gbuffer: Option<GBuffer>,
    /// Direct radiance.
    pub direct: Option<Vec<Vec3>>,
    /// Indirect radiance.
    pub indirect: Option<Vec<Vec3>>,
    /// Direct + indirect.
    pub composed: Option<Vec<Vec3>>,
    /// Pass times (zero unless the frame was timed, but `total`).
    pub times: PassTimes,
    /// A still view's radiance: the share of its frames whose sample saw a surface, per
    /// pixel.
    pub coverage: Option<Vec<f32>>,
}

/// Wall time of each pass of one frame (a submit and a wait after each when timed).
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct PassTimes {
    /// G-buffer.
    pub gbuffer: Duration,
    /// Shadow maps (zero when they were kept).
    pub shadows: Duration,
    /// Direct light.
    pub direct: Duration,
    /// The technique's indirect pass.
    pub indirect: Duration,
    /// Its steps, as the pass names them ([`IndirectContext::step_done`]; none where it
    /// names none).
    pub indirect_steps: Vec<(&'static str, Duration)>,
    /// Compose.
    pub compose: Duration,
    /// A still view's accumulation (zero without one).
    pub accumulate: Duration,
    /// Read-back (or the final wait when nothing is read).
    pub readback: Duration,
    /// The whole frame, from the first command to the end of the read-back.
    pub total: Duration,
    /// Whether the shadow maps were rendered this frame.
    pub shadows_rendered: bool,
}

/// One view to render once, on a frame renderer made for it (tests, references and
/// one-off measurements; a client keeps its [`FrameRenderer`]).
#[derive(Clone, Copy)]
pub struct OneFrame<'a> {
    /// The scene (materials).
    pub scene: &'a Scene,
    /// Its triangles.
    pub triangles: &'a [WorldTriangle],
    /// Lights of the direct pass.
    pub lights: &'a [LightState],
    /// The view.
    pub camera: Camera,
    /// Frame width, pixels.
    pub width: u32,
    /// Frame height, pixels.
    pub height: u32,
    /// Shadow maps.
    pub shadows: ShadowSettings,
    /// Frames averaged, each sampling its pixels at the next [`pixel_jitter`] (1: once,
    /// through the pixels' centres).
    pub samples: u32,
}

impl<'a> OneFrame<'a> {
    /// `scene`'s `triangles` lit by `lights`, seen from `camera` at `width × height`.
    pub fn new(
        scene: &'a Scene,
        triangles: &'a [WorldTriangle],
        lights: &'a [LightState],
        camera: &Camera,
        (width, height): (u32, u32),
        shadows: ShadowSettings,
    ) -> Self {
        OneFrame {
            scene,
            triangles,
            lights,
            camera: *camera,
            width,
            height,
            shadows,
            samples: 1,
        }
    }

    /// The same view, `samples` jittered frames averaged ([`OneFrame::samples`]).
    pub fn with_samples(self, samples: u32) -> Self {
        OneFrame {
            samples: samples.max(1),
            ..self
        }
    }
}

impl Raster {
    /// Renders `view` once with `indirect` as the technique's pass and reads back `readback`.
    pub fn render_once(
        &self,
        view: &OneFrame<'_>,
        indirect: &mut dyn IndirectPass,
        readback: Readback,
    ) -> Result<FrameImages, RasterError> {
        let mut frame = FrameRenderer::new(self, view.width, view.height, view.shadows)?;
        frame.set_geometry(self, view.scene, view.triangles)?;
        let inputs = FrameInputs {
            camera: view.camera,
            lights: view.lights,
            still: None,
        };
        frame.render(self, &inputs, indirect, readback, false)
    }
}

/// Times passes when asked: after each pass, submits what was recorded, waits, and starts a
/// new encoder.
struct PassTimer {
    timed: bool,
    mark: Instant,
}

impl PassTimer {
    fn lap(
        &mut self,
        raster: &Raster,
        enc: &mut wgpu::CommandEncoder,
        slot: &mut Duration,
    ) -> Result<(), RasterError> {
        if self.timed {
            raster.submit_so_far(enc)?;
            *slot = self.mark.elapsed();
            self.mark = Instant::now();
        }
        Ok(())
    }
}

/// Distinguishes frame renderers (their targets) for passes that cache bind groups.
static NEXT_RENDERER: AtomicU64 = AtomicU64::new(1);

/// One client's frame state: targets, geometry, camera, shadow maps and the passes' bind
/// groups, made once and kept.
pub struct FrameRenderer {
    id: u64,
    width: u32,
    height: u32,
    targets: FrameTargets,
    geometry: Geometry,
    gbuffer: GBufferPass,
    shadows: ShadowMaps,
    direct: DirectPass,
    compose: ComposePass,
    /// A still view's running means (made at its first frame).
    still: Option<Accumulation>,
    /// Whether a still view accumulates direct and indirect radiance too, not only the
    /// composed frame.
    still_all: bool,
}

impl FrameRenderer {
    /// Targets for `width × height` frames on `raster`.
    pub fn new(
        raster: &Raster,
        width: u32,
        height: u32,
        shadows: ShadowSettings,
    ) -> Result<Self, RasterError> {
        let max = raster.device.limits().max_texture_dimension_2d;
        if width == 0 || height == 0 || width > max || height > max {
            return Err(RasterError::BadSize { width, height, max });
        }
        raster.checked("creating a frame's targets", || {
            let f = raster.formats();
            let target = |label, format| Target::new(raster, label, width, height, format);
            let targets = FrameTargets {
                gbuffer: GBufferTargets {
                    position: target("gbuffer position", f.exact4),
                    normal: target("gbuffer normal", f.half4),
                    albedo: target("gbuffer albedo", f.half4),
                    lightmap_uv: target("gbuffer light-map uv", f.exact2),
                    depth: target("gbuffer depth", f.depth),
                },
                direct: target("direct radiance", f.exact4),
                indirect: target("indirect radiance", f.exact4),
                composed: target("composed radiance", f.exact4),
            };
            let compose = ComposePass::new(raster, &targets.direct, &targets.indirect);
            Ok(FrameRenderer {
                id: NEXT_RENDERER.fetch_add(1, Ordering::Relaxed),
                width,
                height,
                targets,
                geometry: Geometry::default(),
                gbuffer: GBufferPass::new(raster),
                shadows: ShadowMaps::new(raster, shadows),
                direct: DirectPass::new(raster),
                compose,
                still: None,
                still_all: false,
            })
        })
    }

    /// Whether a still view ([`FrameInputs::still`]) accumulates its direct and indirect
    /// radiance too (to read them back), not only the composed frame (default: not).
    pub fn accumulate_every_image(&mut self, all: bool) {
        if all != self.still_all {
            self.still_all = all;
            self.still = None;
        }
    }

    /// Frame width, pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Frame height, pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Frames that rendered shadow maps.
    pub fn shadow_renders(&self) -> u64 {
        self.shadows.renders
    }

    /// Shadow views rendered in all (each point light has six, a spot light or the sun one).
    pub fn shadow_views_rendered(&self) -> u64 {
        self.shadows.views_rendered
    }

    /// Uploads the geometry the frames draw (once for a static scene; again whenever it
    /// moves). Triangles take their albedo from `scene`'s materials, a textured one times
    /// its texture where each pixel sees it (`raster/albedo.rs`; the textures are
    /// uploaded the first time, and again only for a scene with other textures).
    pub fn set_geometry(
        &mut self,
        raster: &Raster,
        scene: &Scene,
        triangles: &[WorldTriangle],
    ) -> Result<(), RasterError> {
        if !self
            .geometry
            .albedo
            .as_ref()
            .is_some_and(|a| a.holds(scene))
        {
            let textures = raster.checked("uploading textures", || {
                Ok(AlbedoTextures::new(raster, scene))
            })?;
            self.geometry.albedo = Some(textures);
        }
        let albedo_maps = self.geometry.albedo.as_ref().expect("uploaded above");
        let mut lo = Vec3::splat(f32::INFINITY);
        let mut hi = Vec3::splat(f32::NEG_INFINITY);
        let mut shaded = Vec::with_capacity(triangles.len() * 3);
        let mut positions = Vec::with_capacity(triangles.len() * 3);
        for t in triangles {
            let albedo = scene
                .materials
                .get(t.material as usize)
                .map_or(Vec3::ZERO, |m| m.albedo);
            let albedo = unorm16(albedo);
            let layer = albedo_maps.layer(t.material);
            // A triangle whose three light-map UVs are all zero has none (WorldTriangle's
            // convention for meshes without them).
            let has_lightmap = t.lightmap_uv.iter().any(|uv| *uv != glam::Vec2::ZERO);
            for k in 0..3 {
                lo = lo.min(t.v[k]);
                hi = hi.max(t.v[k]);
                shaded.push(GBufferVertex {
                    position: t.v[k].to_array(),
                    normal: snorm16(t.n[k]),
                    albedo,
                    lightmap: if has_lightmap {
                        t.lightmap_uv[k].to_array()
                    } else {
                        [-1.0; 2]
                    },
                    uv: t.uv[k].to_array(),
                    layer,
                });
                positions.push(t.v[k].to_array());
            }
        }
        if !(lo.is_finite() && hi.is_finite()) {
            (lo, hi) = (Vec3::ZERO, Vec3::ONE);
        }
        raster.checked("uploading geometry", || {
            let upload = |label, bytes: &[u8], old: Option<wgpu::Buffer>| {
                if bytes.is_empty() {
                    return None;
                }
                match old {
                    Some(b) if b.size() == bytes.len() as u64 => {
                        raster.queue.write_buffer(&b, 0, bytes);
                        Some(b)
                    }
                    _ => Some(raster.device.create_buffer_init(
                        &wgpu::util::BufferInitDescriptor {
                            label: Some(label),
                            contents: bytes,
                            usage: wgpu::BufferUsages::VERTEX | wgpu::BufferUsages::COPY_DST,
                        },
                    )),
                }
            };
            let g = &mut self.geometry;
            g.gbuffer = upload(
                "gbuffer vertices",
                bytemuck::cast_slice(&shaded),
                g.gbuffer.take(),
            );
            g.shadow = upload(
                "shadow vertices",
                bytemuck::cast_slice(&positions),
                g.shadow.take(),
            );
            g.vertices = positions.len() as u32;
            g.bounds = (lo, hi);
            g.culled = Chunks::new(triangles);
            g.version += 1;
            Ok(())
        })
    }

    /// The camera's clip_from_view and view_from_world for this geometry (near and far
    /// planes from its bounds).
    fn camera_matrices(&self, camera: &Camera) -> (Mat4, Mat4) {
        let (lo, hi) = self.geometry.bounds;
        let far =
            ((hi - lo).length() + (camera.position - (lo + hi) * 0.5).length()).max(1e-3) * 2.0;
        let aspect = self.width as f32 / self.height as f32;
        camera_matrices(camera, aspect, far * 1e-5, far)
    }

    /// Renders one frame: G-buffer → shadows → direct → `indirect` → compose → read-back of
    /// `readback`. With `timed`, each pass is submitted and waited for on its own and timed.
    pub fn render(
        &mut self,
        raster: &Raster,
        inputs: &FrameInputs<'_>,
        indirect: &mut dyn IndirectPass,
        readback: Readback,
        timed: bool,
    ) -> Result<FrameImages, RasterError> {
        raster.checked("rendering a frame", || {
            let start = Instant::now();
            let mut times = PassTimes::default();
            let mut timer = PassTimer { timed, mark: start };
            let mut enc = raster.device.create_command_encoder(&Default::default());
            let (clip_from_view, view_from_world) = self.camera_matrices(&inputs.camera);
            // The point of pixel (x, y) moves to (x + ½ + jx, y + ½ + jy): the image moves the
            // other way, in clip space scaled by w (near plane, P00 and P11 unchanged).
            let jitter = inputs.still.map_or(Vec2::ZERO, pixel_jitter);
            let shift = Vec3::new(
                -2.0 * jitter.x / self.width as f32,
                2.0 * jitter.y / self.height as f32,
                0.0,
            );
            let clip_from_view = Mat4::from_translation(shift) * clip_from_view;
            let clip = clip_from_view * view_from_world;
            self.gbuffer.encode(
                raster,
                &mut enc,
                &self.targets.gbuffer,
                &self.geometry,
                clip,
                inputs.camera.position,
            );
            timer.lap(raster, &mut enc, &mut times.gbuffer)?;
            let g = &self.geometry;
            times.shadows_rendered = self.shadows.update(
                raster,
                &mut enc,
                inputs.lights,
                g.shadow.as_ref().map(|b| (b, &g.culled)),
                g.version,
                g.bounds,
            )?;
            timer.lap(raster, &mut enc, &mut times.shadows)?;
            self.direct.encode(
                raster,
                &mut enc,
                &self.targets.gbuffer,
                &self.shadows,
                &self.targets.direct.view,
            );
            timer.lap(raster, &mut enc, &mut times.direct)?;
            let (lo, hi) = self.geometry.bounds;
            let steps = timed.then(StepTimer::start);
            let ctx = IndirectContext {
                renderer_id: self.id,
                width: self.width,
                height: self.height,
                clip_from_world: clip,
                clip_from_view,
                view_from_world,
                scene_extent_m: (hi - lo).length(),
                gbuffer: &self.targets.gbuffer,
                indirect: &self.targets.indirect.view,
                steps: steps.as_ref(),
            };
            indirect.encode(raster, &ctx, &mut enc)?;
            timer.lap(raster, &mut enc, &mut times.indirect)?;
            times.indirect_steps = steps.map(StepTimer::finish).unwrap_or_default();
            self.compose
                .encode(raster, &mut enc, &self.targets.composed.view);
            timer.lap(raster, &mut enc, &mut times.compose)?;
            if let Some(frame) = inputs.still {
                let t = &self.targets;
                let still = self.still.get_or_insert_with(|| {
                    let mut images = vec![&t.composed];
                    if self.still_all {
                        images.extend([&t.direct, &t.indirect]);
                    }
                    let size = (self.width, self.height);
                    Accumulation::new(raster, &images, size)
                });
                still.encode(raster, &mut enc, frame);
                timer.lap(raster, &mut enc, &mut times.accumulate)?;
            }
            let mut images = self.read_back(raster, enc, readback, inputs.still.is_some())?;
            times.readback = timer.mark.elapsed();
            times.total = start.elapsed();
            images.times = times;
            Ok(images)
        })
    }

    fn read_back(
        &self,
        raster: &Raster,
        enc: wgpu::CommandEncoder,
        which: Readback,
        still: bool,
    ) -> Result<FrameImages, RasterError> {
        let t = &self.targets;
        // A still view's images are its running means (composed first, then direct and
        // indirect where they are accumulated).
        let means = self.still.as_ref().filter(|_| still);
        let own = [&t.composed, &t.direct, &t.indirect];
        let mean = |i: usize| &means.and_then(|m| m.mean(i)).unwrap_or(own[i]).texture;
        let g = &t.gbuffer;
        let gbuffer = [
            (&g.position.texture, Layout::Exact4),
            (&g.normal.texture, Layout::Half4),
            (&g.albedo.texture, Layout::Half4),
            (&g.lightmap_uv.texture, Layout::Exact2),
        ];
        let radiance = [
            (mean(1), Layout::Exact4),
            (mean(2), Layout::Exact4),
            (mean(0), Layout::Exact4),
        ];
        let list: Vec<(&wgpu::Texture, Layout)> = match which {
            Readback::Nothing => Vec::new(),
            Readback::GBuffer => gbuffer.to_vec(),
            Readback::Composed => vec![radiance[2]],
            Readback::Everything => gbuffer.iter().chain(&radiance).copied().collect(),
        };
        if list.is_empty() {
            raster.submit_and_wait(enc)?;
            return Ok(FrameImages::default());
        }
        let (w, h) = (self.width, self.height);
        let mut planes = read_planes(raster, enc, &list, w, h)?.into_iter();
        let mut images = FrameImages::default();
        if matches!(which, Readback::GBuffer | Readback::Everything) {
            let mut next = || planes.next().unwrap_or_default();
            let position = next();
            // The pass clears only the position: elsewhere a pixel that sees no surface
            // holds what an earlier frame left there.
            let seen = |plane: Vec<Vec4>| -> Vec<Vec4> {
                plane
                    .into_iter()
                    .zip(&position)
                    .map(|(v, p)| if p.w > 0.5 { v } else { Vec4::ZERO })
                    .collect()
            };
            let (normal, albedo, uv) = (seen(next()), seen(next()), seen(next()));
            images.gbuffer = Some(GBuffer {
                width: w,
                height: h,
                normal: rgb(&normal),
                albedo: rgb(&albedo),
                lightmap_uv: uv.iter().map(|p| p.truncate().truncate()).collect(),
                position,
            });
        }
        if which == Readback::Everything {
            images.direct = planes.next().map(|p| rgb(&p));
            images.indirect = planes.next().map(|p| rgb(&p));
        }
        if let Some(composed) = planes.next() {
            if means.is_some() {
                images.coverage = Some(composed.iter().map(|v| v.w).collect());
            }
            images.composed = Some(rgb(&composed));
        }
        Ok(images)
    }
}

impl Raster {
    /// One view rendered with `indirect` as the technique's pass, everything read back: once
    /// through the pixels' centres, or with [`OneFrame::samples`] above 1 as a still view's
    /// accumulation of that many frames ([`FrameInputs::still`]): each pixel the mean over
    /// its area, as a camera sees it, but for what no neighbour shows (`raster/accumulate.rs`).
    /// The G-buffer is the last frame's; `coverage` counts every frame's.
    pub fn read_frame(
        &self,
        view: &OneFrame<'_>,
        indirect: &mut dyn IndirectPass,
    ) -> Result<ReadFrame, RasterError> {
        let mut frame = FrameRenderer::new(self, view.width, view.height, view.shadows)?;
        frame.set_geometry(self, view.scene, view.triangles)?;
        let still = view.samples > 1;
        frame.accumulate_every_image(still);
        let mut images = FrameImages::default();
        for k in 0..view.samples.max(1) {
            let inputs = FrameInputs {
                camera: view.camera,
                lights: view.lights,
                still: still.then_some(k),
            };
            let last = k + 1 >= view.samples;
            let readback = if last {
                Readback::Everything
            } else {
                Readback::Nothing
            };
            images = frame.render(self, &inputs, indirect, readback, false)?;
        }
        ReadFrame::from_images(images)
    }

    /// The G-buffer and the direct radiance (ρ/π · E_direct, with shadow maps) of one view
    /// (rendered once: [`Raster::render_once`]).
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
        let view = OneFrame::new(scene, triangles, lights, camera, (width, height), shadows);
        let f = self.read_frame(&view, &mut NoIndirect)?;
        Ok((f.gbuffer, f.direct))
    }
}

/// A client frame read back ([`Raster::read_frame`]).
#[derive(Clone, Debug)]
pub struct ReadFrame {
    /// The G-buffer.
    pub gbuffer: GBuffer,
    /// Direct radiance (the client's own lights).
    pub direct: Vec<Vec3>,
    /// Indirect radiance from the technique's pass (ρ/π · E_indirect).
    pub indirect: Vec<Vec3>,
    /// Share of each pixel's frames that saw a surface (0 or 1 from one frame).
    pub coverage: Vec<f32>,
}

impl ReadFrame {
    fn from_images(images: FrameImages) -> Result<ReadFrame, RasterError> {
        match (images.gbuffer, images.direct, images.indirect) {
            (Some(gbuffer), Some(direct), Some(indirect)) => Ok(ReadFrame {
                coverage: images.coverage.unwrap_or_else(|| {
                    (0..gbuffer.position.len())
                        .map(|i| if gbuffer.covered(i) { 1.0 } else { 0.0 })
                        .collect()
                }),
                gbuffer,
                direct,
                indirect,
            }),
            _ => Err(RasterError::Readback("the frame was not read back".into())),
        }
    }

    /// Direct + indirect radiance.
    pub fn combined(&self) -> Vec<Vec3> {
        self.direct
            .iter()
            .zip(&self.indirect)
            .map(|(d, i)| *d + *i)
            .collect()
    }
}

/// RGB in [0, 1] as unorm16 (the fourth component 0).
fn unorm16(c: Vec3) -> [u16; 4] {
    let q = |c: f32| (c.clamp(0.0, 1.0) * 65535.0).round() as u16;
    [q(c.x), q(c.y), q(c.z), 0]
}

/// A unit vector as snorm16 (the fourth component 0).
fn snorm16(n: Vec3) -> [i16; 4] {
    let q = |c: f32| (c.clamp(-1.0, 1.0) * 32767.0).round() as i16;
    [q(n.x), q(n.y), q(n.z), 0]
}
