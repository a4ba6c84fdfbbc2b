//! The irradiance-map client's indirect pass ([`LightmapPass`]): the map is uploaded once
//! per new map ([`LightmapPass::set_map`]) as an `Rgba16Float` texture, and each frame a
//! full-screen pass looks it up through the G-buffer's light-map UVs with bilinear filtering
//! and writes ρ/π · E (see `lookup.wgsl`). Pixels whose geometry has no light-map UV, and
//! every pixel before the first map, get no indirect light. The pass owns its pipeline
//! (`LookupPipelines`, built once per device).

use cloudlight_scenes::{Camera, LightState, Scene, WorldTriangle};

use crate::hdr_map::HdrMap;
use crate::raster::pass::{CachedBindGroup, draw_fullscreen, lookup_bind_group};
use crate::raster::pipelines::{
    D2, FRAGMENT, UINT, buffer_entry, fullscreen_pipeline, layout, pipeline_layout, texture_entry,
};
use crate::raster::targets::clear_pass;
use crate::raster::{
    IndirectContext, IndirectPass, OneFrame, Raster, RasterError, ReadFrame, ShadowSettings,
};

/// Must match `LookupParams` in lookup.wgsl.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct LookupParams {
    scale: [f32; 4],
}

/// The lookup pipeline, its layout and the bilinear sampler.
struct LookupPipelines {
    layout: wgpu::BindGroupLayout,
    lookup: wgpu::RenderPipeline,
    sampler: wgpu::Sampler,
}

impl LookupPipelines {
    fn new(raster: &Raster) -> Self {
        let device = &raster.device;
        let shader = device.create_shader_module(wgpu::include_wgsl!("lookup.wgsl"));
        let layout = layout(
            device,
            "lightmap lookup",
            &[
                buffer_entry(0, FRAGMENT, wgpu::BufferBindingType::Uniform),
                texture_entry(1, FRAGMENT, UINT, D2),
                texture_entry(2, FRAGMENT, UINT, D2),
                texture_entry(3, FRAGMENT, UINT, D2),
                texture_entry(
                    4,
                    FRAGMENT,
                    wgpu::TextureSampleType::Float { filterable: true },
                    D2,
                ),
                wgpu::BindGroupLayoutEntry {
                    binding: 5,
                    visibility: FRAGMENT,
                    ty: wgpu::BindingType::Sampler(wgpu::SamplerBindingType::Filtering),
                    count: None,
                },
            ],
        );
        let lookup = fullscreen_pipeline(
            device,
            "lightmap lookup",
            &pipeline_layout(device, "lightmap lookup", &layout),
            &shader,
            ("vs_full", "fs_lookup"),
            raster.formats().exact4,
        );
        let sampler = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("lightmap"),
            address_mode_u: wgpu::AddressMode::ClampToEdge,
            address_mode_v: wgpu::AddressMode::ClampToEdge,
            mag_filter: wgpu::FilterMode::Linear,
            min_filter: wgpu::FilterMode::Linear,
            ..Default::default()
        });
        LookupPipelines {
            layout,
            lookup,
            sampler,
        }
    }
}

/// The map's texture.
struct MapTexture {
    texture: wgpu::Texture,
    view: wgpu::TextureView,
    size: (u32, u32),
}

/// The irradiance-map client's indirect pass.
pub struct LightmapPass {
    pipelines: std::sync::Arc<LookupPipelines>,
    params: wgpu::Buffer,
    map: Option<MapTexture>,
    /// Bumped when the map's texture is made anew (bind groups name its view).
    generation: u64,
    /// The bind group, per frame renderer and map generation.
    bound: CachedBindGroup,
}

impl LightmapPass {
    /// A pass without a map (its pipeline is built once per device of `raster`).
    pub fn new(raster: &Raster) -> Result<Self, RasterError> {
        Ok(LightmapPass {
            pipelines: raster.pipelines_of(LookupPipelines::new)?,
            params: raster.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("lightmap params"),
                size: std::mem::size_of::<LookupParams>() as u64,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }),
            map: None,
            generation: 0,
            bound: CachedBindGroup::default(),
        })
    }

    /// The map shown from now on (irradiance, W/m², as its texels say).
    pub fn set_map(&mut self, raster: &Raster, map: &HdrMap) -> Result<(), RasterError> {
        map.check()
            .map_err(|e| RasterError::BadMap(e.to_string()))?;
        let size = (map.width(), map.height());
        let max = raster.device.limits().max_texture_dimension_2d;
        if size.0 > max || size.1 > max {
            return Err(RasterError::BadMap(format!(
                "a {}×{} map exceeds the device's {max}-texel textures",
                size.0, size.1
            )));
        }
        raster.checked("uploading the light map", || {
            if self.map.as_ref().is_none_or(|m| m.size != size) {
                let texture = raster.device.create_texture(&wgpu::TextureDescriptor {
                    label: Some("light map"),
                    size: wgpu::Extent3d {
                        width: size.0,
                        height: size.1,
                        depth_or_array_layers: 1,
                    },
                    mip_level_count: 1,
                    sample_count: 1,
                    dimension: wgpu::TextureDimension::D2,
                    format: wgpu::TextureFormat::Rgba16Float,
                    usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
                    view_formats: &[],
                });
                let view = texture.create_view(&Default::default());
                self.map = Some(MapTexture {
                    texture,
                    view,
                    size,
                });
                self.generation += 1;
            }
            let m = self.map.as_ref().expect("made above");
            raster.queue.write_texture(
                wgpu::TexelCopyTextureInfo {
                    texture: &m.texture,
                    mip_level: 0,
                    origin: wgpu::Origin3d::ZERO,
                    aspect: wgpu::TextureAspect::All,
                },
                &map.rgba16_bytes(),
                wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(size.0 * 8),
                    rows_per_image: Some(size.1),
                },
                wgpu::Extent3d {
                    width: size.0,
                    height: size.1,
                    depth_or_array_layers: 1,
                },
            );
            let params = LookupParams {
                scale: [map.scale(), 1.0, 0.0, 0.0],
            };
            raster
                .queue
                .write_buffer(&self.params, 0, bytemuck::bytes_of(&params));
            Ok(())
        })
    }

    /// Whether a map has been set.
    pub fn has_map(&self) -> bool {
        self.map.is_some()
    }
}

impl IndirectPass for LightmapPass {
    fn encode(
        &mut self,
        raster: &Raster,
        ctx: &IndirectContext<'_>,
        enc: &mut wgpu::CommandEncoder,
    ) -> Result<(), RasterError> {
        let Some(map) = &self.map else {
            clear_pass(enc, "no light map yet", ctx.indirect);
            return Ok(());
        };
        let group = self.bound.get(ctx.renderer_id, self.generation, || {
            let g = ctx.gbuffer;
            lookup_bind_group(
                raster,
                "lightmap lookup",
                &self.pipelines.layout,
                &self.params,
                &[
                    &g.position.view,
                    &g.albedo.view,
                    &g.lightmap_uv.view,
                    &map.view,
                ],
                &self.pipelines.sampler,
            )
        });
        draw_fullscreen(enc, "lightmap lookup", ctx, &self.pipelines.lookup, group);
        Ok(())
    }
}

/// A one-frame irradiance-map client on `raster`: direct light of `lights` plus the map's
/// indirect light, looked up through the light-map UVs of `scene` (the light map's unwrapped
/// scene, [`super::unwrapped`]) — a [`LightmapPass`] rendered once, everything read back.
#[allow(clippy::too_many_arguments)]
pub fn lightmap_frame(
    raster: &Raster,
    scene: &Scene,
    triangles: &[WorldTriangle],
    lights: &[LightState],
    camera: &Camera,
    (width, height): (u32, u32),
    shadows: ShadowSettings,
    map: &HdrMap,
) -> Result<ReadFrame, RasterError> {
    let mut pass = LightmapPass::new(raster)?;
    pass.set_map(raster, map)?;
    let view = OneFrame::new(scene, triangles, lights, camera, (width, height), shadows);
    raster.read_frame(&view, &mut pass)
}

#[cfg(test)]
mod tests {
    use glam::Vec3;

    use crate::hdr_map::HdrMap;
    use crate::raster::ShadowSettings;
    use crate::raster::tests::on_every_backend;

    /// A smooth map: a gradient over the texels times `k`, so that a bilinear lookup is
    /// nearly exact whatever the sampler's weight precision.
    fn gradient(w: u32, h: u32, k: f32) -> HdrMap {
        let texels: Vec<Vec3> = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f32 / w as f32, (i / w) as f32 / h as f32);
                Vec3::new(1.0 + x, 2.0 - y, 0.5 + 0.5 * x * y) * k
            })
            .collect();
        HdrMap::new(w, h, &texels, &[]).unwrap()
    }

    #[test]
    fn the_lookup_shows_albedo_over_pi_times_the_bilinear_map_at_every_pixel() {
        let cornell = cloudlight_scenes::builtin("cornell").unwrap();
        let (scene, atlas) = super::super::unwrapped(&cornell, &Default::default()).unwrap();
        let scene = &*scene;
        let tris = scene.triangles_at(0.0);
        let camera = cornell.cameras[0].camera;
        let size = (48u32, 40u32);
        let shadows = ShadowSettings {
            size: 16,
            ..Default::default()
        };
        on_every_backend(|raster| {
            // Scale-invariant: the same relative answer for any light unit.
            for k in [1e-6f32, 1.0, 1e6] {
                let map = gradient(atlas.width, atlas.height, k);
                let f =
                    super::lightmap_frame(raster, scene, &tris, &[], &camera, size, shadows, &map)
                        .unwrap();
                let (mut checked, mut worst) = (0, 0.0f32);
                for i in 0..f.indirect.len() {
                    let got = f.indirect[i];
                    assert!(got.is_finite(), "pixel {i}: {got}");
                    let Some(uv) = f.gbuffer.lightmap_uv_at(i) else {
                        assert_eq!(got, Vec3::ZERO, "pixel {i} has no light-map UV");
                        continue;
                    };
                    let want = f.gbuffer.albedo[i] / std::f32::consts::PI * map.sample(uv);
                    let err = ((got - want).abs() / want.max(Vec3::splat(1e-30 * k))).max_element();
                    worst = worst.max(err);
                    checked += 1;
                }
                eprintln!("k = {k}: {checked} pixels, worst relative error {worst:.2e}");
                assert!(checked > (size.0 * size.1) as usize * 2 / 3, "{checked}");
                assert!(worst < 1e-2, "k = {k}: worst relative error {worst}");
            }
            // The topology's own scene has no light-map UVs: no indirect light, anywhere.
            let map = gradient(atlas.width, atlas.height, 1.0);
            let plain = cornell.triangles_at(0.0);
            let f =
                super::lightmap_frame(raster, &cornell, &plain, &[], &camera, size, shadows, &map)
                    .unwrap();
            assert!(f.indirect.iter().all(|c| *c == Vec3::ZERO));
            // Before any map, a pass draws nothing.
            let mut pass = super::LightmapPass::new(raster).unwrap();
            assert!(!pass.has_map());
            let view = crate::raster::OneFrame {
                scene,
                triangles: &tris,
                lights: &[],
                camera,
                width: size.0,
                height: size.1,
                shadows,
                samples: 1,
            };
            let f = raster.read_frame(&view, &mut pass).unwrap();
            assert!(f.indirect.iter().all(|c| *c == Vec3::ZERO));
        });
    }

    /// The client's indirect image of a converged Cornell map, shown as it is (the raw cut)
    /// and through H.264 at `qp`, against the path tracer's indirect image of the same view.
    #[test]
    fn a_converged_cornell_map_shows_the_reference_indirect_light_raw_and_through_h264() {
        use crate::lightmap::{GatherSettings, Gatherer, Lightmap};
        use crate::video::{Decoder, Encoder, EncoderSettings, RateControl, hdr};
        let cornell = cloudlight_scenes::builtin("cornell").unwrap();
        let lm = Lightmap::cached(&cornell, &Default::default()).unwrap();
        let mut g = Gatherer::new(lm.clone(), GatherSettings::default());
        let mut updates = 0;
        while !g.update(0.0).converged {
            updates += 1;
            assert!(updates < 64, "the static box converges");
        }
        let raw = g.map().clone();
        let packed = hdr::pack(&raw).unwrap();
        let mut enc = Encoder::new(EncoderSettings {
            width: raw.width(),
            height: raw.height(),
            rate: RateControl::FixedQp(16),
            ..Default::default()
        })
        .unwrap();
        let unit = enc.encode(&packed.yuv, 0.0).unwrap().unwrap();
        let picture = Decoder::new().unwrap().decode(&unit.data).unwrap().unwrap();
        let decoded = hdr::unpack(&picture, packed.range);
        let h264 = HdrMap::new(raw.width(), raw.height(), &decoded, &[]).unwrap();
        let camera = cornell.cameras[0].at(0.0);
        let (w, h) = (48u32, 48u32);
        let bvh = crate::SceneBvh::at(&cornell, 0.0, crate::BvhKind::default());
        let settings = crate::RenderSettings {
            width: w,
            height: h,
            camera,
            time_s: 0.0,
            seed: 77,
            max_bounces: 64,
            pixel: Default::default(),
        };
        let reference = crate::render(&cornell, &bvh, settings, 256).indirect();
        let shadows = ShadowSettings {
            size: 16,
            ..Default::default()
        };
        let tris = lm.scene.triangles_at(0.0);
        on_every_backend(|raster| {
            let errors = |map: &HdrMap| {
                let f = super::lightmap_frame(
                    raster,
                    &lm.scene,
                    &tris,
                    &[],
                    &camera,
                    (w, h),
                    shadows,
                    map,
                )
                .unwrap();
                let mask: Vec<bool> = (0..f.indirect.len())
                    .map(|i| f.gbuffer.covered(i))
                    .collect();
                crate::metrics::compare(&f.indirect, &reference, &mask, w, h)
            };
            let (r, v) = (errors(&raw), errors(&h264));
            eprintln!(
                "after {updates} updates: raw {r:?}; H.264 QP 16 ({} B) {v:?}",
                unit.data.len()
            );
            // Measured with 45 quadratic bases: 0.043 raw, 0.044 through H.264 (energy
            // 0.993), much of it the 256-spp reference's noise; one value per basis gave
            // 0.174 (its bases smooth the corners the path tracer darkens).
            assert!(r.relmse < 0.065, "raw: {r:?}");
            assert!((0.95..1.05).contains(&r.energy_ratio), "raw: {r:?}");
            // H.264 at QP 16 adds next to nothing.
            assert!(
                v.relmse < r.relmse * 1.05 + 0.005,
                "H.264 {v:?} against raw {r:?}"
            );
            assert!(
                (v.energy_ratio / r.energy_ratio - 1.0).abs() < 0.02,
                "{v:?} {r:?}"
            );
        });
    }
}
