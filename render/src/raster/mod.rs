//! Raster on wgpu, headless: a client's frame as named passes in order — G-buffer
//! (world position, normal, albedo, light-map UV), shadow maps, direct light, the technique's indirect
//! pass, compose, read-back ([`frame`]). The raster owns the shared passes and the pass
//! trait ([`IndirectPass`]); each technique's indirect pass lives beside its kernels and
//! owns its pipelines (built once per device through [`Raster::pipelines_of`]). Imports run
//! one way: [`targets`] ← the passes ← [`frame`].
//!
//! [`Raster`] is one device with every pipeline built once; a [`FrameRenderer`] holds one
//! client's targets, geometry buffers and shadow maps and keeps them between frames.
//! Formats follow what the adapter reports ([`device`]), so Vulkan (lavapipe on a GPU-less
//! box), GL (llvmpipe) and hardware adapters all work; every wgpu error is a
//! [`RasterError`] value, never a panic. This module never touches scenes' files, actors or
//! sockets.

use cloudlight_scenes::Camera;
use glam::{Mat4, Vec2, Vec3, Vec4};

mod accumulate;
mod albedo;
mod compose;
pub mod device;
pub mod direct;
pub mod frame;
mod gbuffer;
pub mod pass;
pub(crate) mod pipelines;
mod readback;
pub mod shadow;
pub mod targets;

pub use device::Formats;
pub use frame::{
    FrameImages, FrameInputs, FrameRenderer, OneFrame, PassTimes, ReadFrame, Readback, pixel_jitter,
};
pub use pass::{IndirectContext, IndirectPass, NoIndirect, StepTimer};
pub use shadow::{MAX_LIGHTS, ShadowSettings};
pub use targets::{GBufferTargets, Target};

/// Why the raster cannot run.
#[derive(Debug, thiserror::Error)]
pub enum RasterError {
    /// No adapter at all.
    #[error(
        "no graphics adapter found ({0}); on a machine without a GPU install Mesa's software drivers: {mesa}",
        mesa = device::MESA_PACKAGES
    )]
    NoAdapter(String),
    /// Adapters exist but none can do what a pass needs.
    #[error("adapter {adapter} cannot run the raster: it lacks {capability}")]
    Unsupported {
        /// Adapter name and backend.
        adapter: String,
        /// What is missing.
        capability: String,
    },
    /// The adapter refused a device.
    #[error("the graphics adapter {adapter} refused a device: {message}")]
    Device {
        /// Adapter name and backend.
        adapter: String,
        /// wgpu's reason.
        message: String,
    },
    /// A wgpu validation or out-of-memory error.
    #[error("wgpu error in {operation}: {message}")]
    Wgpu {
        /// What the raster was doing.
        operation: String,
        /// wgpu's message.
        message: String,
    },
    /// The device was lost (driver reset, destroyed).
    #[error("the graphics device was lost: {0}")]
    DeviceLost(String),
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
    /// More lights than the direct pass holds ([`MAX_LIGHTS`]).
    #[error("{lights} lights exceed the direct pass's {max}: use fewer lights or light samples")]
    TooManyLights {
        /// Lights given.
        lights: usize,
        /// What the pass holds.
        max: usize,
    },
    /// A frame size the device cannot hold.
    #[error("a {width}x{height} frame exceeds the device's {max}-pixel texture size (or is empty)")]
    BadSize {
        /// Width asked for.
        width: u32,
        /// Height asked for.
        height: u32,
        /// Device limit per side.
        max: u32,
    },
    /// A light map the lookup pass cannot show (inconsistent, or larger than the device's
    /// textures).
    #[error("the light map cannot be shown: {0}")]
    BadMap(String),
    /// Reading results back failed.
    #[error("reading back from the GPU failed: {0}")]
    Readback(String),
}

/// One headless wgpu device with the raster's pipelines.
pub struct Raster {
    pub(crate) device: wgpu::Device,
    pub(crate) queue: wgpu::Queue,
    adapter_info: wgpu::AdapterInfo,
    /// Whether compute shaders with storage buffers (read in fragment shaders too) run here.
    compute: bool,
    formats: Formats,
    errors: device::ErrorSink,
    pub(crate) pipelines: pipelines::Pipelines,
    /// Technique passes' pipelines, one value per type, built at first use.
    technique_pipelines: std::sync::Mutex<TechniquePipelines>,
}

type TechniquePipelines =
    std::collections::HashMap<std::any::TypeId, std::sync::Arc<dyn std::any::Any + Send + Sync>>;

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
    /// Light-map UV in [0, 1]² (NaN where the surface has none; see [`GBuffer::lightmap_uv_at`]).
    pub lightmap_uv: Vec<Vec2>,
}

impl GBuffer {
    /// Whether pixel `i` sees a surface.
    pub fn covered(&self, i: usize) -> bool {
        self.position[i].w > 0.5
    }

    /// Light-map UV of pixel `i`: `None` where no surface was drawn or it has no light-map
    /// UVs.
    pub fn lightmap_uv_at(&self, i: usize) -> Option<Vec2> {
        let uv = *self.lightmap_uv.get(i)?;
        (self.covered(i) && uv.is_finite()).then_some(uv)
    }

    /// Indices of the pixels that see a surface.
    pub fn covered_pixels(&self) -> Vec<usize> {
        (0..self.position.len())
            .filter(|&i| self.covered(i))
            .collect()
    }
}

/// clip_from_world of a camera (wgpu clip space: y up, z in [0, 1]).
pub fn clip_from_world(camera: &Camera, aspect: f32, near: f32, far: f32) -> Mat4 {
    let (clip_from_view, view_from_world) = camera_matrices(camera, aspect, near, far);
    clip_from_view * view_from_world
}

/// clip_from_view and view_from_world of a camera (view space: right-handed, looking down
/// −z).
pub fn camera_matrices(camera: &Camera, aspect: f32, near: f32, far: f32) -> (Mat4, Mat4) {
    (
        glam::camera::rh::proj::directx::perspective(camera.fov_y_rad, aspect, near, far),
        glam::camera::rh::view::look_at_mat4(camera.position, camera.target, camera.up),
    )
}

impl Raster {
    /// Opens the best adapter wgpu finds (hardware before software, Vulkan before GL;
    /// `WGPU_BACKEND` restricts the backends, e.g. `WGPU_BACKEND=gl`).
    pub fn new() -> Result<Raster, RasterError> {
        Self::with_backends(device::backends(wgpu::Backends::all()))
    }

    /// Opens the best adapter of exactly `backends` (whatever `WGPU_BACKEND` says).
    pub fn with_backends(backends: wgpu::Backends) -> Result<Raster, RasterError> {
        pollster::block_on(Self::open(backends))
    }

    async fn open(backends: wgpu::Backends) -> Result<Raster, RasterError> {
        let (usable, refused) = device::usable_adapters(backends).await;
        let Some((adapter, formats, features)) = usable.into_iter().next() else {
            return Err(match refused.into_iter().next() {
                Some(why) => RasterError::NoAdapter(why),
                None => RasterError::NoAdapter(format!("backends {backends:?}")),
            });
        };
        let adapter_info = adapter.get_info();
        let limits = adapter.limits();
        let compute = adapter
            .get_downlevel_capabilities()
            .flags
            .contains(wgpu::DownlevelFlags::COMPUTE_SHADERS)
            && limits.max_storage_buffers_per_shader_stage >= 2
            && limits.max_compute_invocations_per_workgroup >= 64;
        let (device, queue) = adapter
            .request_device(&wgpu::DeviceDescriptor {
                label: Some("cloudlight raster"),
                required_features: features,
                required_limits: adapter.limits(),
                ..Default::default()
            })
            .await
            .map_err(|e| RasterError::Device {
                adapter: format!("{} ({:?})", adapter_info.name, adapter_info.backend),
                message: e.to_string(),
            })?;
        let errors = device::ErrorSink::default();
        errors.attach(&device);
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let pipelines = pipelines::Pipelines::new(&device, &formats);
        if let Some(e) = scope.pop().await {
            return Err(RasterError::Wgpu {
                operation: "building the raster's pipelines".into(),
                message: e.to_string(),
            });
        }
        errors.take()?;
        Ok(Raster {
            device,
            queue,
            adapter_info,
            compute,
            formats,
            errors,
            pipelines,
            technique_pipelines: Default::default(),
        })
    }

    /// A technique pass's pipelines `P`, built by `build` the first time any pass asks on this
    /// device and shared from then on (every client of a process shares one device, so a
    /// pipeline is compiled once, not once per client). A build that fails is not kept.
    pub fn pipelines_of<P: Send + Sync + 'static>(
        &self,
        build: impl FnOnce(&Raster) -> P,
    ) -> Result<std::sync::Arc<P>, RasterError> {
        let key = std::any::TypeId::of::<P>();
        if let Some(p) = crate::lock(&self.technique_pipelines).get(&key) {
            return Ok(p.clone().downcast::<P>().expect("keyed by its type"));
        }
        let built =
            std::sync::Arc::new(self.checked("building a pass's pipelines", || Ok(build(self)))?);
        crate::lock(&self.technique_pipelines)
            .entry(key)
            .or_insert_with(|| built.clone());
        Ok(built)
    }

    /// The adapter in use (name, backend, device type).
    pub fn adapter(&self) -> &wgpu::AdapterInfo {
        &self.adapter_info
    }

    /// Whether compute shaders (with storage buffers, which fragment shaders may read) run on
    /// this device.
    pub fn supports_compute(&self) -> bool {
        self.compute
    }

    /// One line naming the adapter and its backend.
    pub fn describe(&self) -> String {
        format!(
            "{} ({:?}, {:?}; accumulation {:?})",
            self.adapter_info.name,
            self.adapter_info.backend,
            self.adapter_info.device_type,
            self.formats.accum
        )
    }

    /// The formats of the targets on this adapter.
    pub fn formats(&self) -> &Formats {
        &self.formats
    }

    /// Runs `f` inside wgpu error scopes: a validation or out-of-memory error it causes, or
    /// one reported since the last call, becomes an error of `operation`.
    pub fn checked<R>(
        &self,
        operation: &str,
        f: impl FnOnce() -> Result<R, RasterError>,
    ) -> Result<R, RasterError> {
        self.errors.take()?;
        let validation = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let memory = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let result = f();
        let out_of_memory = pollster::block_on(memory.pop());
        let invalid = pollster::block_on(validation.pop());
        if let Some(e) = invalid.or(out_of_memory) {
            return Err(RasterError::Wgpu {
                operation: operation.to_string(),
                message: e.to_string(),
            });
        }
        self.errors.take()?;
        result
    }

    /// Submits what `enc` holds and waits for it, leaving `enc` a new, empty encoder.
    pub(crate) fn submit_so_far(&self, enc: &mut wgpu::CommandEncoder) -> Result<(), RasterError> {
        let done = std::mem::replace(enc, self.device.create_command_encoder(&Default::default()));
        self.submit_and_wait(done)
    }

    /// Submits `enc` and waits until the device has done it.
    pub(crate) fn submit_and_wait(&self, enc: wgpu::CommandEncoder) -> Result<(), RasterError> {
        self.queue.submit([enc.finish()]);
        self.device
            .poll(wgpu::PollType::Wait {
                submission_index: None,
                timeout: None,
            })
            .map(|_| ())
            .map_err(|e| RasterError::Readback(e.to_string()))
    }

    /// The G-buffer of `triangles` seen by `camera`.
    pub fn gbuffer(
        &self,
        scene: &cloudlight_scenes::Scene,
        triangles: &[cloudlight_scenes::WorldTriangle],
        camera: &Camera,
        width: u32,
        height: u32,
    ) -> Result<GBuffer, RasterError> {
        let view = OneFrame {
            scene,
            triangles,
            lights: &[],
            camera: *camera,
            width,
            height,
            shadows: ShadowSettings {
                size: 1,
                ..Default::default()
            },
            samples: 1,
        };
        let images = self.render_once(&view, &mut NoIndirect, Readback::GBuffer)?;
        images
            .gbuffer
            .ok_or_else(|| RasterError::Readback("no G-buffer read back".into()))
    }
}

#[cfg(test)]
pub(crate) mod tests;
