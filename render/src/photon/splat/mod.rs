//! The photon technique's indirect pass ([`PhotonSplatPass`]): photons splatted in screen
//! space into low-resolution additive buffers, then a joint-bilateral upsample to indirect
//! radiance (see `splat.wgsl` for the kernel).
//!
//! **Levels**: a splat's cost is the texels its disk covers, and indirect light is smooth
//! at the scale of a disk, so each photon goes to the coarsest of [`SplatSettings::levels`]
//! buffers (each half the resolution of the one before) where its disk still spans
//! [`SplatSettings::min_texels`] texels of radius: a disk costs about the same wherever it
//! lies and however large it is. Each level first gets a *guide* (each texel's surface point
//! and normal, read from the G-buffer once a frame, so a splat reads one small texel); the
//! levels are then folded, coarsest first, into the next finer one by a bilateral upsample
//! at that level's resolution, and only the finest is upsampled to the frame. Passes in a
//! frame: guides, splats (one per level), folds, upsample.
//!
//! **Compute splat** (the default where the device runs compute shaders,
//! [`SplatSettings::compute`]): one invocation per photon walks its disk's texels at its
//! level and adds to integer sums with atomics (fixed point, stochastic rounding); each
//! level is then resolved into its buffer with the coarser one folded in. llvmpipe's
//! rasteriser pays ~2 µs of set-up per quad whatever its size; the compute splat pays per
//! texel (Cornell, 10k photons, 640×360, lavapipe: indirect pass 42 → 20 ms, frame 52 →
//! 31 ms), and its integer sums lose nothing to a half-precision buffer (GL llvmpipe). It
//! reads each texel's surface from its level's guide, one load per texel (the guides are
//! copied into the layers of one array, so one dispatch serves every level; reading the
//! G-buffer's position and normal instead, two loads, made the splat ~20% slower).
//! The photons are uploaded once per set
//! ([`PhotonSplatPass::set_photons`]), not once per frame. The pass owns its pipelines
//! (`SplatPipelines`, built once per device); the shared raster knows nothing of photons.

use cloudlight_scenes::{Camera, LightState, Scene, WorldTriangle};

use super::Photon;
use crate::raster::pipelines::{
    D2, FRAGMENT, UINT, blended_fullscreen_pipeline, buffer_entry, fullscreen_pipeline, layout,
    pipeline_layout, texture_entry,
};
use crate::raster::targets::{clear_pass, overwrite_pass};
use crate::raster::{
    IndirectContext, IndirectPass, OneFrame, Raster, RasterError, ShadowSettings, Target,
};

/// Must match `PhotonIn` in splat.wgsl.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct SplatPhoton {
    position_radius: [f32; 4],
    power: [f32; 4],
    direction: [f32; 4],
}

/// The guide pipeline (each level's surface from the G-buffer), the splat pipeline
/// (instanced quads, additive into a level), the collapse pipeline (a level folded into the
/// next finer one, additive) and the upsample pipeline, sharing one layout.
struct SplatPipelines {
    layout: wgpu::BindGroupLayout,
    guide: wgpu::RenderPipeline,
    splat: wgpu::RenderPipeline,
    collapse: wgpu::RenderPipeline,
    upsample: wgpu::RenderPipeline,
    /// The compute splat and its resolve, where the device runs compute shaders.
    compute: Option<ComputePipelines>,
}

/// The compute splat (photons added in fixed point into one storage buffer, one dispatch
/// for every level), the resolve of each level into its accumulation buffer, and the edges:
/// marking the pixels no level's upsample stands for, and the upsample that reads their
/// full-resolution sums.
struct ComputePipelines {
    layout: wgpu::BindGroupLayout,
    splat: wgpu::ComputePipeline,
    /// Level 0's photons added to the edge pixels (after `edges`, beside `splat`).
    splat_edges: wgpu::ComputePipeline,
    resolve: wgpu::RenderPipeline,
    edges: wgpu::ComputePipeline,
    upsample: wgpu::RenderPipeline,
}

impl SplatPipelines {
    fn new(raster: &Raster) -> Self {
        let (device, formats) = (&raster.device, raster.formats());
        let shader = device.create_shader_module(wgpu::include_wgsl!("splat.wgsl"));
        let compute = raster.supports_compute();
        let mut entries = vec![
            buffer_entry(
                0,
                wgpu::ShaderStages::VERTEX_FRAGMENT,
                wgpu::BufferBindingType::Uniform,
            ),
            texture_entry(1, FRAGMENT, UINT, D2),
            texture_entry(2, FRAGMENT, UINT, D2),
            texture_entry(3, FRAGMENT, UINT, D2),
            texture_entry(4, FRAGMENT, ACCUM, D2),
            texture_entry(5, FRAGMENT, UINT, D2),
            texture_entry(6, FRAGMENT, UINT, D2),
        ];
        if compute {
            entries.extend([
                buffer_entry(7, FRAGMENT, READ_ONLY),
                texture_entry(10, FRAGMENT, ACCUM, D2),
                texture_entry(11, FRAGMENT, UINT, D2),
            ]);
        }
        let layout = layout(device, "splat", &entries);
        let pipeline_layout = pipeline_layout(device, "splat", &layout);
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
                topology: wgpu::PrimitiveTopology::TriangleStrip,
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
                    format: formats.accum,
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
        let upsample = fullscreen_pipeline(
            device,
            "upsample",
            &pipeline_layout,
            &shader,
            ("vs_full", "fs_upsample"),
            formats.exact4,
        );
        let guide = fullscreen_pipeline(
            device,
            "splat guide",
            &pipeline_layout,
            &shader,
            ("vs_full", "fs_guide"),
            formats.exact4,
        );
        let collapse = blended_fullscreen_pipeline(
            device,
            "splat collapse",
            &pipeline_layout,
            &shader,
            ("vs_full", "fs_collapse"),
            formats.accum,
            Some(wgpu::BlendState {
                color: additive,
                alpha: additive,
            }),
        );
        let compute = compute.then(|| {
            let cs = wgpu::ShaderStages::COMPUTE;
            let compute_layout = crate::raster::pipelines::layout(
                device,
                "compute splat",
                &[
                    buffer_entry(0, cs, wgpu::BufferBindingType::Uniform),
                    texture_entry(1, cs, UINT, D2),
                    texture_entry(2, cs, UINT, D2),
                    buffer_entry(8, cs, READ_ONLY),
                    texture_entry(12, cs, UINT, wgpu::TextureViewDimension::D2Array),
                    buffer_entry(9, cs, wgpu::BufferBindingType::Storage { read_only: false }),
                ],
            );
            let compute_pipeline_layout =
                crate::raster::pipelines::pipeline_layout(device, "compute splat", &compute_layout);
            let compute_pipeline = |label, entry_point| {
                device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                    label: Some(label),
                    layout: Some(&compute_pipeline_layout),
                    module: &shader,
                    entry_point: Some(entry_point),
                    compilation_options: Default::default(),
                    cache: None,
                })
            };
            let splat = compute_pipeline("compute splat", "cs_splat");
            let splat_edges = compute_pipeline("compute splat of edges", "cs_splat_edges");
            let edges = compute_pipeline("splat edges", "cs_edges");
            let upsample = fullscreen_pipeline(
                device,
                "upsample with edges",
                &pipeline_layout,
                &shader,
                ("vs_full", "fs_upsample_edges"),
                formats.exact4,
            );
            let resolve = fullscreen_pipeline(
                device,
                "splat resolve",
                &pipeline_layout,
                &shader,
                ("vs_full", "fs_resolve"),
                formats.accum,
            );
            ComputePipelines {
                layout: compute_layout,
                splat,
                splat_edges,
                resolve,
                edges,
                upsample,
            }
        });
        SplatPipelines {
            layout,
            guide,
            splat,
            collapse,
            upsample,
            compute,
        }
    }
}

const READ_ONLY: wgpu::BufferBindingType = wgpu::BufferBindingType::Storage { read_only: true };

/// Workgroup size of `cs_splat`.
const WORKGROUP: u32 = 64;

/// Fixed-point units of the compute splat for a typical photon's peak (its power over its
/// kernel's normalisation; the median over the set): 2^12 keeps a single addition's
/// rounding small and leaves room for 2^20 such peaks in one texel.
const UNITS_PER_PEAK: f32 = 4096.0;

const ACCUM: wgpu::TextureSampleType = wgpu::TextureSampleType::Float { filterable: false };

/// Most accumulation levels.
pub const MAX_LEVELS: u32 = 4;

// The compute splat's guide array has MAX_LEVELS layers, and wgpu's GL backend guesses a
// texture's target from its layers (one: a 2D texture, a multiple of six: a cube map; see
// raster/shadow.rs), neither of which it can read as a 2D array.
const _: () = assert!(MAX_LEVELS > 1 && !MAX_LEVELS.is_multiple_of(6));

/// Splatting settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SplatSettings {
    /// The finest accumulation buffer is this many times smaller per axis (1, 2 or 4).
    pub downsample: u32,
    /// Accumulation levels, each half the resolution of the one before (1 to
    /// [`MAX_LEVELS`]; 1: every photon in the finest buffer).
    pub levels: u32,
    /// A photon goes to the coarsest level where its disk's projected radius spans at least
    /// this many texels. Cornell box, 10k photons (`bench quality`, relMSE; `bench client`,
    /// indirect pass at 640×360 on lavapipe): one level 0.0426 at 128², 0.0530 at 640×360,
    /// 152 ms; 3 texels 0.0415, 0.0490, 42 ms; 2 texels 0.0536, 0.0463, 32 ms (coarse
    /// levels smooth noise, but in a small frame they are too coarse for the box's edges:
    /// at 2.5k photons and 128², 0.071 → 0.105).
    pub min_texels: f32,
    /// A surface point farther than `flatten × r` from a photon's plane along its own
    /// normal does not receive it (keeps light from leaking around corners and thin walls).
    pub flatten: f32,
    /// Plane-distance scale σ of the upsample's and the folds' depth weight, as a fraction
    /// of the scene's bounding diagonal. It keeps parallel surfaces a step apart from
    /// sharing light (a floor and the channel 0.33 m below its edge, or a walkway and the
    /// wall top beside it, seen from afar); the coarse levels' folds blend taps several
    /// pixels apart, where such steps meet. 0.005 → 0.001 (σ 0.75 → 0.15 m in the
    /// dungeon): `bench quality --technique photons --scene assets/dungeon/level-dungeon.gltf
    /// --spp 1024 --budgets 80000 --set passes=32 --width 640 --height 360 --seed S` (its
    /// outside view), relMSE after 32 passes 0.1469 / 0.1483 / 0.1428 → 0.1370 / 0.1380 /
    /// 0.1405 for S = default, 2, 3 (0.1242 → 0.1229 after 128); flat from 0.0005 to 0.002,
    /// 0.1462 at 0.003 and 0.1399 at 0.0002. The Cornell box (10k, 40k), the dungeon's
    /// courtyard and fountains and `city:250000` read the same within 0.0003. A σ of k
    /// texel footprints of each level instead gave the coarse levels' folds a σ of metres
    /// again (0.146–0.152 for k = 0.5–4); half a full-resolution pixel's footprint read
    /// 0.1368, as the constant does, for more arithmetic per tap.
    pub depth_sigma: f32,
    /// Exponent of the upsample's normal weight.
    pub normal_power: f32,
    /// A photon carrying its surface's normal ([`super::Receive::Normal`]) lights surfaces
    /// whose normal's cosine with it exceeds this (0.8: within 37°; 0 — any surface not
    /// facing away — let light round every edge). `bench quality` on the dungeon, 40k /
    /// 160k photons, seeds 5, 2, 3: relMSE 0.254 / 0.241, 0.277 / 0.267, 0.267 / 0.260 at 0.5
    /// (60°); 0.222 / 0.224, 0.247 / 0.245, 0.234 / 0.241 at 0.8 (HDR-FLIP ~5% higher); the
    /// Cornell box and the city, whose surfaces meet at right angles, read the same.
    pub facing: f32,
    /// Splat with a compute shader (a photon per invocation, its disk's texels added in
    /// fixed point) where the device runs compute shaders; else, or when false, each photon
    /// is a quad rasterised into its level. Same image (up to rounding); the compute splat
    /// has no per-triangle cost, and its integer sums do not lose small additions to
    /// half-precision accumulation.
    pub compute: bool,
    /// Photons per compute dispatch at most (each bound as its own range of the photon
    /// buffer); `None`: as many as one storage binding of the device holds (128 MiB, 2.8M
    /// photons, on lavapipe and llvmpipe — a long progressive set holds more).
    pub chunk_photons: Option<u32>,
    /// With the compute splat: pixels whose surface none of the finest level's upsample
    /// taps stands for (a ledge a pixel wide between faces that turn from it, the top row
    /// of a wall seen from afar) get that level's photons added at full resolution (and the
    /// coarser levels' light from level 1), instead of borrowing another surface's light
    /// through the bilateral weights. Where the finest level's taps weigh the pixel's
    /// surface at less than half (`EDGE_MATCH` in splat.wgsl), it is an edge. Downsample 4
    /// at most (ignored beyond).
    /// Off by default: it did not move the error enough for its cost (README, "Edges").
    pub edges: bool,
    /// Photons within a cell of this fraction of their radius (of one radius class and
    /// receiving alike) are merged into one before they are uploaded ([`super::merge`]);
    /// 0: none. A splat's cost is its photon count, and a still light's refinement passes
    /// multiply it. `bench quality --technique photons` and `bench client --technique
    /// photons --set passes=P`, merge 0 → 0.5: see the README ("Merging photons").
    pub merge: f32,
}

impl Default for SplatSettings {
    fn default() -> Self {
        SplatSettings {
            downsample: 2,
            levels: MAX_LEVELS,
            min_texels: 3.0,
            flatten: 0.3,
            depth_sigma: 0.001,
            normal_power: 8.0,
            facing: 0.8,
            compute: true,
            chunk_photons: None,
            edges: false,
            merge: 0.5,
        }
    }
}

/// One photon client frame.
pub type PhotonFrame = crate::raster::ReadFrame;

/// Must match `SplatParams` in splat.wgsl.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct SplatParams {
    clip_from_world: [f32; 16],
    view_from_world: [f32; 16],
    /// x, y: clip_from_view's scale of view x and y (P00, P11); z: near plane distance, m.
    projection: [f32; 4],
    sizes: [f32; 4],
    settings: [f32; 4],
    scale: [f32; 4],
    /// x: levels, y: min_texels, z: facing.
    levels: [f32; 4],
    /// x: photons.
    counts: [u32; 4],
}

/// Greatest common divisor.
fn gcd(a: u64, b: u64) -> u64 {
    if b == 0 { a } else { gcd(b, a % b) }
}

/// Targets and bind groups of the pass for one frame renderer.
struct SplatTargets {
    renderer_id: u64,
    /// One per level (1×1 stand-ins beyond `levels`).
    accum: Vec<Target>,
    /// Each level's surfaces (1×1 stand-ins beyond `levels`).
    guides: Vec<Target>,
    /// The compute splat's copy of the guides: level l in layer l of one array at level 0's
    /// size (its top-left corner), so that one dispatch reads every level's. A copy, because
    /// GL reads a single layer viewed as a 2D texture as zero.
    guide_levels: Option<(wgpu::Texture, wgpu::TextureView)>,
    /// Bind groups: writing the guides (the G-buffer only), splatting into level l (its
    /// guide), folding level l + 1 into l (its buffer and guide, and l's guide), upsampling
    /// level 0.
    guide: wgpu::BindGroup,
    splat: Vec<wgpu::BindGroup>,
    collapse: Vec<wgpu::BindGroup>,
    upsample: wgpu::BindGroup,
    low: (u32, u32),
    levels: u32,
    /// The compute splat's fixed-point sums (three per texel of every level; with edges,
    /// then three per pixel, a mark per pixel and a bit mask per texel of level 0), where the
    /// device runs compute shaders.
    fixed: Option<wgpu::Buffer>,
}

/// The photon client's indirect pass.
pub struct PhotonSplatPass {
    pipelines: std::sync::Arc<SplatPipelines>,
    settings: SplatSettings,
    photons: Option<wgpu::Buffer>,
    count: u32,
    /// Photons given to the last [`PhotonSplatPass::set_photons`] (before merging).
    received: u32,
    /// Σ over photons of their largest power channel, watts (sets the accumulation scale).
    power_w: f32,
    /// Fixed-point units per W/m² of the compute splat ([`UNITS_PER_PEAK`] over the median
    /// photon's peak irradiance).
    fixed_units: f32,
    params: wgpu::Buffer,
    targets: Option<SplatTargets>,
}

impl PhotonSplatPass {
    /// A pass without photons (its pipelines are built at the first pass on `raster`'s
    /// device).
    pub fn new(raster: &Raster, settings: SplatSettings) -> Result<Self, RasterError> {
        Ok(PhotonSplatPass {
            pipelines: raster.pipelines_of(SplatPipelines::new)?,
            settings,
            photons: None,
            count: 0,
            received: 0,
            power_w: 0.0,
            fixed_units: 1.0,
            params: raster.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("splat params"),
                size: std::mem::size_of::<SplatParams>() as u64,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }),
            targets: None,
        })
    }

    /// Photons splatted from now on (non-finite photons and those without a radius are
    /// left out).
    pub fn set_photons(&mut self, raster: &Raster, photons: &[Photon]) -> Result<(), RasterError> {
        self.received = photons.len() as u32;
        let merged;
        let photons = if self.settings.merge > 0.0 {
            merged = super::merge::merge(photons, self.settings.merge);
            &merged[..]
        } else {
            photons
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
                direction: p
                    .direction
                    .extend(match p.receive {
                        super::Receive::Normal => 1.0,
                        super::Receive::Direction => 0.0,
                    })
                    .to_array(),
            })
            .collect();
        // Each photon's largest power channel, W.
        let largest: Vec<f32> = instances
            .iter()
            .map(|p| p.power[..3].iter().fold(0.0f32, |a, b| a.max(b.abs())))
            .collect();
        self.power_w = largest.iter().sum();
        // Each photon's peak irradiance: power over the cone kernel's normalisation πr²/3.
        let mut peaks: Vec<f32> = instances
            .iter()
            .zip(&largest)
            .map(|(p, max)| {
                let r = p.position_radius[3];
                max * 3.0 / (std::f32::consts::PI * r * r)
            })
            .filter(|e| e.is_finite() && *e > 0.0)
            .collect();
        self.fixed_units = if peaks.is_empty() {
            1.0
        } else {
            let mid = peaks.len() / 2;
            let (_, median, _) = peaks.select_nth_unstable_by(mid, f32::total_cmp);
            let units = UNITS_PER_PEAK / *median;
            if units.is_finite() { units } else { 1.0 }
        };
        self.count = instances.len() as u32;
        let bytes: &[u8] = bytemuck::cast_slice(&instances);
        raster.checked("uploading photons", || {
            match &self.photons {
                Some(b) if b.size() >= bytes.len() as u64 && !bytes.is_empty() => {
                    raster.queue.write_buffer(b, 0, bytes);
                }
                _ if bytes.is_empty() => {}
                _ => {
                    // Room for growth: sets change size a little from one generation to the next.
                    let size =
                        (bytes.len() as u64 * 5 / 4).next_multiple_of(wgpu::COPY_BUFFER_ALIGNMENT);
                    let b = raster.device.create_buffer(&wgpu::BufferDescriptor {
                        label: Some("photons"),
                        size,
                        usage: wgpu::BufferUsages::VERTEX
                            | wgpu::BufferUsages::STORAGE
                            | wgpu::BufferUsages::COPY_DST,
                        mapped_at_creation: false,
                    });
                    raster.queue.write_buffer(&b, 0, bytes);
                    self.photons = Some(b);
                }
            }
            Ok(())
        })
    }

    /// Whether the compute splat adds the finest level's photons to edge pixels (the
    /// settings' `edges`, with a downsample of 4 at most: a texel's edge pixels are the bits
    /// of one word).
    fn edges(&self) -> bool {
        self.settings.edges && self.settings.downsample.clamp(1, 8) <= 4
    }

    /// Photons uploaded (after merging, [`SplatSettings::merge`]).
    pub fn photon_count(&self) -> u32 {
        self.count
    }

    /// Photons given to the last [`PhotonSplatPass::set_photons`], before merging.
    pub fn received_count(&self) -> u32 {
        self.received
    }

    fn targets(&mut self, raster: &Raster, ctx: &IndirectContext<'_>) -> &SplatTargets {
        let ds = self.settings.downsample.clamp(1, 8);
        let levels = self.settings.levels.clamp(1, MAX_LEVELS);
        let low = (
            ctx.width.div_ceil(ds).max(1),
            ctx.height.div_ceil(ds).max(1),
        );
        if self
            .targets
            .as_ref()
            .is_none_or(|t| t.renderer_id != ctx.renderer_id || t.low != low || t.levels != levels)
        {
            let level_targets = |label: &str, format| -> Vec<Target> {
                (0..MAX_LEVELS)
                    .map(|l| {
                        let (w, h) = if l < levels {
                            let f = ds << l;
                            (ctx.width.div_ceil(f).max(1), ctx.height.div_ceil(f).max(1))
                        } else {
                            (1, 1)
                        };
                        Target::new(raster, label, w, h, format)
                    })
                    .collect()
            };
            let formats = raster.formats();
            let accum = level_targets("photon accumulation", formats.accum);
            let guides = level_targets("photon guide", formats.exact4);
            let guide_levels = self.pipelines.compute.as_ref().map(|_| {
                let texture = raster.device.create_texture(&wgpu::TextureDescriptor {
                    label: Some("photon guides"),
                    size: wgpu::Extent3d {
                        width: low.0,
                        height: low.1,
                        depth_or_array_layers: MAX_LEVELS,
                    },
                    mip_level_count: 1,
                    sample_count: 1,
                    dimension: wgpu::TextureDimension::D2,
                    format: formats.exact4,
                    usage: wgpu::TextureUsages::COPY_DST | wgpu::TextureUsages::TEXTURE_BINDING,
                    view_formats: &[],
                });
                let view = texture.create_view(&wgpu::TextureViewDescriptor {
                    label: Some("photon guides"),
                    dimension: Some(wgpu::TextureViewDimension::D2Array),
                    ..Default::default()
                });
                (texture, view)
            });
            // A pass never reads what it writes: stand-ins there.
            let stand_in = Target::new(raster, "unused", 1, 1, formats.accum);
            let guide_stand_in = Target::new(raster, "unused", 1, 1, formats.exact4);
            let g = ctx.gbuffer;
            // The compute splat's sums: every level's texels, three words each (a stand-in
            // where the layout has the binding but the raster splat is used).
            let fixed = self.pipelines.compute.as_ref().map(|_| {
                let texels: u64 = (0..levels)
                    .map(|l| {
                        let f = ds << l;
                        u64::from(ctx.width.div_ceil(f).max(1))
                            * u64::from(ctx.height.div_ceil(f).max(1))
                    })
                    .sum();
                let pixels = u64::from(ctx.width) * u64::from(ctx.height);
                let level0 = u64::from(low.0) * u64::from(low.1);
                let size = match (self.settings.compute, self.settings.edges) {
                    (true, true) => (texels * 3 + pixels * 4 + level0) * 4,
                    (true, false) => texels * 12,
                    _ => 16,
                };
                raster.device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("photon fixed-point sums"),
                    size,
                    usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                })
            });
            // (the level read: buffer, guide; the guide of the level written; level 1's
            // buffer and guide for the edges' upsample)
            let bind =
                |src_accum: &wgpu::TextureView,
                 src_guide: &wgpu::TextureView,
                 dst_guide: &wgpu::TextureView,
                 coarse: Option<(&wgpu::TextureView, &wgpu::TextureView)>| {
                    let tex = |binding, view| wgpu::BindGroupEntry {
                        binding,
                        resource: wgpu::BindingResource::TextureView(view),
                    };
                    let mut entries = vec![
                        wgpu::BindGroupEntry {
                            binding: 0,
                            resource: self.params.as_entire_binding(),
                        },
                        tex(1, &g.position.view),
                        tex(2, &g.normal.view),
                        tex(3, &g.albedo.view),
                        tex(4, src_accum),
                        tex(5, src_guide),
                        tex(6, dst_guide),
                    ];
                    if let Some(sums) = &fixed {
                        let (coarse_accum, coarse_guide) =
                            coarse.unwrap_or((&stand_in.view, &guide_stand_in.view));
                        entries.extend([
                            wgpu::BindGroupEntry {
                                binding: 7,
                                resource: sums.as_entire_binding(),
                            },
                            tex(10, coarse_accum),
                            tex(11, coarse_guide),
                        ]);
                    }
                    raster.device.create_bind_group(&wgpu::BindGroupDescriptor {
                        label: Some("splat"),
                        layout: &self.pipelines.layout,
                        entries: &entries,
                    })
                };
            let (none, no_guide) = (&stand_in.view, &guide_stand_in.view);
            let splat = (0..MAX_LEVELS as usize)
                .map(|l| bind(none, no_guide, &guides[l].view, None))
                .collect();
            let collapse = (0..MAX_LEVELS as usize - 1)
                .map(|l| {
                    bind(
                        &accum[l + 1].view,
                        &guides[l + 1].view,
                        &guides[l].view,
                        None,
                    )
                })
                .collect();
            self.targets = Some(SplatTargets {
                renderer_id: ctx.renderer_id,
                guide: bind(none, no_guide, no_guide, None),
                splat,
                collapse,
                upsample: bind(
                    &accum[0].view,
                    &guides[0].view,
                    no_guide,
                    Some((&accum[1].view, &guides[1].view)),
                ),
                accum,
                guides,
                guide_levels,
                low,
                levels,
                fixed,
            });
        }
        self.targets.as_ref().expect("just made")
    }
}

impl PhotonSplatPass {
    /// The compute splat: the sums cleared, one dispatch (a photon per invocation, at its
    /// level), then each level resolved into its accumulation buffer with the next coarser
    /// one folded in, coarsest first.
    fn splat_compute(
        &self,
        raster: &Raster,
        ctx: &IndirectContext<'_>,
        compute: &ComputePipelines,
        sums: &wgpu::Buffer,
        enc: &mut wgpu::CommandEncoder,
    ) -> Result<(), RasterError> {
        let t = self.targets.as_ref().expect("made by encode");
        enc.clear_buffer(sums, 0, None);
        let (levels_texture, levels_view) = t
            .guide_levels
            .as_ref()
            .expect("made with the compute pipelines");
        for level in 0..t.levels {
            let guide = &t.guides[level as usize].texture;
            enc.copy_texture_to_texture(
                guide.as_image_copy(),
                wgpu::TexelCopyTextureInfo {
                    texture: levels_texture,
                    mip_level: 0,
                    origin: wgpu::Origin3d {
                        x: 0,
                        y: 0,
                        z: level,
                    },
                    aspect: wgpu::TextureAspect::All,
                },
                guide.size(),
            );
        }
        // A set larger than one storage binding may hold goes in chunks, each a range of
        // the buffer at an offset the device accepts.
        let limits = raster.device.limits();
        let size = std::mem::size_of::<SplatPhoton>() as u64;
        let align = limits.min_storage_buffer_offset_alignment.max(1) as u64;
        let step = align / gcd(align, size);
        let fits = limits.max_storage_buffer_binding_size / size;
        let wanted = self
            .settings
            .chunk_photons
            .map_or(fits, |c| (c as u64).min(fits));
        let chunk = (wanted / step * step).max(step).min(u32::MAX as u64) as u32;
        let chunks = match (&self.photons, self.count > 0) {
            (Some(photons), true) => (0..self.count.div_ceil(chunk))
                .map(|k| (photons, k * chunk, (self.count - k * chunk).min(chunk)))
                .collect(),
            _ => Vec::new(),
        };
        let max = limits.max_compute_workgroups_per_dimension.max(1);
        let grid = |invocations: u32| {
            let groups = invocations.div_ceil(WORKGROUP);
            (groups.min(max), groups.div_ceil(max))
        };
        for (k, (photons, first, count)) in chunks.into_iter().enumerate() {
            let tex = |binding, view| wgpu::BindGroupEntry {
                binding,
                resource: wgpu::BindingResource::TextureView(view),
            };
            let group = raster.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("compute splat"),
                layout: &compute.layout,
                entries: &[
                    wgpu::BindGroupEntry {
                        binding: 0,
                        resource: self.params.as_entire_binding(),
                    },
                    tex(1, &ctx.gbuffer.position.view),
                    tex(2, &ctx.gbuffer.normal.view),
                    tex(12, levels_view),
                    wgpu::BindGroupEntry {
                        binding: 8,
                        resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                            buffer: photons,
                            offset: first as u64 * size,
                            size: std::num::NonZeroU64::new(count as u64 * size),
                        }),
                    },
                    wgpu::BindGroupEntry {
                        binding: 9,
                        resource: sums.as_entire_binding(),
                    },
                ],
            });
            // The edges are marked before the first chunk splats (a pass of their own: the
            // splat reads the marks).
            if k == 0 && self.edges() {
                let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("splat edges"),
                    timestamp_writes: None,
                });
                pass.set_pipeline(&compute.edges);
                pass.set_bind_group(0, &group, &[]);
                let (x, y) = grid(ctx.width * ctx.height);
                pass.dispatch_workgroups(x, y, 1);
                drop(pass);
                ctx.step_done(raster, enc, "edges")?;
            }
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("compute splat"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&compute.splat);
            pass.set_bind_group(0, &group, &[]);
            let (x, y) = grid(count);
            pass.dispatch_workgroups(x, y, 1);
            if self.edges() {
                pass.set_pipeline(&compute.splat_edges);
                pass.dispatch_workgroups(x, y, 1);
            }
        }
        ctx.step_done(raster, enc, "splat")?;
        for level in (0..t.levels).rev() {
            let l = level as usize;
            let mut pass = overwrite_pass(enc, "splat resolve", &t.accum[l].view);
            pass.set_pipeline(&compute.resolve);
            // Level l + 1's buffer and guide and l's guide; the coarsest level folds nothing.
            let group = t.collapse.get(l).unwrap_or(&t.splat[l]);
            pass.set_bind_group(0, group, &[]);
            pass.draw(3 * level..3 * level + 3, 0..1);
        }
        Ok(())
    }

    /// The raster splat: each photon a quad drawn additively into its level, then the
    /// levels folded into the next finer one, coarsest first.
    fn splat_raster(
        &self,
        raster: &Raster,
        ctx: &IndirectContext<'_>,
        enc: &mut wgpu::CommandEncoder,
    ) -> Result<(), RasterError> {
        let t = self.targets.as_ref().expect("made by encode");
        for level in 0..t.levels {
            let mut pass = clear_pass(enc, "splat", &t.accum[level as usize].view);
            if let (Some(buf), true) = (&self.photons, self.count > 0) {
                pass.set_pipeline(&self.pipelines.splat);
                pass.set_bind_group(0, &t.splat[level as usize], &[]);
                pass.set_vertex_buffer(0, buf.slice(..));
                pass.draw(4 * level..4 * level + 4, 0..self.count);
            }
        }
        ctx.step_done(raster, enc, "splat")?;
        for into in (0..t.levels - 1).rev() {
            let mut pass = enc.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("splat collapse"),
                color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                    view: &t.accum[into as usize].view,
                    depth_slice: None,
                    resolve_target: None,
                    ops: wgpu::Operations {
                        load: wgpu::LoadOp::Load,
                        store: wgpu::StoreOp::Store,
                    },
                })],
                depth_stencil_attachment: None,
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
            pass.set_pipeline(&self.pipelines.collapse);
            pass.set_bind_group(0, &t.collapse[into as usize], &[]);
            pass.draw(3 * into..3 * into + 3, 0..1);
        }
        Ok(())
    }
}

/// The near-plane distance of a right-handed [0, 1]-depth perspective projection.
fn near_plane(clip_from_view: &glam::Mat4) -> f32 {
    // z_clip = a·z + b, w = −z: the near plane (z_clip = 0) is at z = −b/a.
    let (a, b) = (clip_from_view.z_axis.z, clip_from_view.w_axis.z);
    if a != 0.0 { (b / a).abs() } else { 0.0 }
}

impl IndirectPass for PhotonSplatPass {
    fn encode(
        &mut self,
        raster: &Raster,
        ctx: &IndirectContext<'_>,
        enc: &mut wgpu::CommandEncoder,
    ) -> Result<(), RasterError> {
        let ds = self.settings.downsample.clamp(1, 8);
        // Accumulate irradiance × scale, the scale putting a typical irradiance (the photons'
        // power over the scene's extent squared) near 1: f16 accumulation then holds any
        // light unit, and f32 loses nothing.
        let extent2 = (ctx.scene_extent_m * ctx.scene_extent_m).max(1e-12);
        let scale = if self.power_w > 0.0 && (extent2 / self.power_w).is_finite() {
            extent2 / self.power_w
        } else {
            1.0
        };
        let (count, settings) = (self.count, self.settings);
        let low = self.targets(raster, ctx).low;
        let t = self.targets.as_ref().expect("made above");
        let compute = match (&self.pipelines.compute, &t.fixed, settings.compute) {
            (Some(compute), Some(sums), true) => Some((compute, sums)),
            _ => None,
        };
        let edges = compute.is_some() && self.edges();
        let params = SplatParams {
            clip_from_world: ctx.clip_from_world.to_cols_array(),
            view_from_world: ctx.view_from_world.to_cols_array(),
            projection: [
                ctx.clip_from_view.x_axis.x,
                ctx.clip_from_view.y_axis.y,
                near_plane(&ctx.clip_from_view),
                0.0,
            ],
            sizes: [
                ctx.width as f32,
                ctx.height as f32,
                low.0 as f32,
                low.1 as f32,
            ],
            settings: [
                ds as f32,
                settings.flatten,
                (settings.depth_sigma * ctx.scene_extent_m).max(1e-6),
                settings.normal_power,
            ],
            scale: [scale, self.fixed_units, 0.0, 0.0],
            levels: [
                settings.levels.clamp(1, MAX_LEVELS) as f32,
                settings.min_texels.max(0.5),
                settings.facing.clamp(-1.0, 1.0),
                0.0,
            ],
            counts: [count, u32::from(edges), 0, 0],
        };
        raster
            .queue
            .write_buffer(&self.params, 0, bytemuck::bytes_of(&params));
        // Vertices 3·l .. 3·l + 3 of a full-screen pass (4·l .. 4·l + 4 of a splat) tell the
        // shader which level it works on.
        for level in 0..t.levels {
            let mut pass = overwrite_pass(enc, "splat guide", &t.guides[level as usize].view);
            pass.set_pipeline(&self.pipelines.guide);
            pass.set_bind_group(0, &t.guide, &[]);
            pass.draw(3 * level..3 * level + 3, 0..1);
        }
        ctx.step_done(raster, enc, "guides")?;
        match compute {
            Some((compute, sums)) => self.splat_compute(raster, ctx, compute, sums, enc)?,
            None => self.splat_raster(raster, ctx, enc)?,
        }
        ctx.step_done(raster, enc, "resolve")?;
        let mut pass = overwrite_pass(enc, "upsample", ctx.indirect);
        pass.set_pipeline(match compute {
            Some((compute, _)) if edges => &compute.upsample,
            _ => &self.pipelines.upsample,
        });
        pass.set_bind_group(0, &t.upsample, &[]);
        pass.draw(0..3, 0..1);
        drop(pass);
        ctx.step_done(raster, enc, "upsample")?;
        Ok(())
    }
}

/// A one-frame photon client on `raster`: direct light of `lights` plus the indirect light
/// of `photons` (a [`PhotonSplatPass`] rendered once, everything read back).
#[allow(clippy::too_many_arguments)]
pub fn photon_frame(
    raster: &Raster,
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
    let mut pass = PhotonSplatPass::new(raster, splat)?;
    pass.set_photons(raster, photons)?;
    let view = OneFrame::new(scene, triangles, lights, camera, (width, height), shadows);
    raster.read_frame(&view, &mut pass)
}

#[cfg(test)]
mod tests;
