//! Which adapter the raster opens, which texture formats its passes use on it, and how wgpu's
//! errors become values.
//!
//! - **Adapter**: every adapter of the allowed backends (wgpu's `WGPU_BACKEND` variable
//!   restricts them, e.g. `WGPU_BACKEND=gl`; `WGPU_ADAPTER_NAME` picks one by name) is
//!   ranked: hardware before software, then Vulkan (or Metal/DX12) before GL.
//! - **Formats**: the G-buffer and every radiance target hold exact `f32` values as their
//!   bits in `Rgba32Uint`/`Rg32Uint` targets (integer targets are colour-renderable on every
//!   backend, GL ES 3.0 included, where `Rgba32Float` often is not). Only the photon
//!   accumulation blends: it uses `Rgba32Float` where the adapter can blend it
//!   (`FLOAT32_BLENDABLE`), else `Rgba16Float` (scaled so that any light unit stays in its
//!   range). An adapter that can do neither is an error naming the capability.
//! - **Errors**: validation and out-of-memory errors are caught by error scopes around every
//!   operation ([`super::Raster::checked`]); anything outside a scope goes to an uncaptured
//!   error handler, and a lost device is recorded: both surface as [`RasterError`] values of
//!   the next operation, never as a panic.

use std::sync::{Arc, Mutex};

use super::RasterError;

/// The Debian packages of Mesa's software drivers, named in errors.
pub(crate) const MESA_PACKAGES: &str = "`apt-get install mesa-vulkan-drivers libvulkan1` (Vulkan lavapipe) \
     or `apt-get install libegl-mesa0 libgl1-mesa-dri` (GL llvmpipe); `scripts/setup.sh` installs both";

/// Texture formats of the raster's targets on one adapter.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Formats {
    /// Exact four-component targets (world position, radiance): `f32` bits.
    pub exact4: wgpu::TextureFormat,
    /// Four `f16` values packed in two `u32` (normal, albedo).
    pub half4: wgpu::TextureFormat,
    /// Exact two-component targets (light-map UV): `f32` bits.
    pub exact2: wgpu::TextureFormat,
    /// The additive photon accumulation buffer (must blend).
    pub accum: wgpu::TextureFormat,
    /// Depth of the G-buffer and of shadow maps.
    pub depth: wgpu::TextureFormat,
}

impl Formats {
    /// Whether the accumulation buffer is half precision (and needs scaling into range).
    pub fn accum_is_half(&self) -> bool {
        self.accum == wgpu::TextureFormat::Rgba16Float
    }
}

/// Colour targets of the G-buffer pass.
const GBUFFER_TARGETS: u32 = 4;
/// Bytes per sample of the G-buffer's colour targets.
const GBUFFER_BYTES_PER_SAMPLE: u32 = 16 + 8 + 8 + 8;

/// What the passes need of a format.
fn supports(adapter: &wgpu::Adapter, format: wgpu::TextureFormat, blend: bool) -> bool {
    let f = adapter.get_texture_format_features(format);
    let usages = wgpu::TextureUsages::RENDER_ATTACHMENT
        | wgpu::TextureUsages::TEXTURE_BINDING
        | wgpu::TextureUsages::COPY_SRC;
    f.allowed_usages.contains(usages)
        && (!blend || f.flags.contains(wgpu::TextureFormatFeatureFlags::BLENDABLE))
}

/// The formats of `adapter`, and the features the device must be asked for; an error names
/// what is missing.
pub(crate) fn choose_formats(
    adapter: &wgpu::Adapter,
) -> Result<(Formats, wgpu::Features), RasterError> {
    let info = adapter.get_info();
    let missing = |capability: String| RasterError::Unsupported {
        adapter: format!("{} ({:?})", info.name, info.backend),
        capability,
    };
    for (format, what) in [
        (wgpu::TextureFormat::Rgba32Uint, "Rgba32Uint render targets"),
        (wgpu::TextureFormat::Rg32Uint, "Rg32Uint render targets"),
    ] {
        if !supports(adapter, format, false) {
            return Err(missing(what.to_string()));
        }
    }
    // The G-buffer writes four targets: position (16 bytes), normal, albedo and light-map
    // UV (8 each).
    let limits = adapter.limits();
    if limits.max_color_attachments < GBUFFER_TARGETS
        || limits.max_color_attachment_bytes_per_sample < GBUFFER_BYTES_PER_SAMPLE
    {
        return Err(missing(format!(
            "{GBUFFER_TARGETS} colour targets of {GBUFFER_BYTES_PER_SAMPLE} bytes per sample in all (it allows {} and {})",
            limits.max_color_attachments, limits.max_color_attachment_bytes_per_sample
        )));
    }
    let lights_bytes = (super::MAX_LIGHTS * std::mem::size_of::<super::shadow::LightGpu>()) as u64;
    if limits.max_uniform_buffer_binding_size < lights_bytes {
        return Err(missing(format!(
            "uniform buffers of {lights_bytes} bytes for {} lights (it allows {})",
            super::MAX_LIGHTS,
            limits.max_uniform_buffer_binding_size
        )));
    }
    let depth = wgpu::TextureFormat::Depth32Float;
    let d = adapter.get_texture_format_features(depth);
    if !d
        .allowed_usages
        .contains(wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::TEXTURE_BINDING)
    {
        return Err(missing("sampled Depth32Float targets".into()));
    }
    let blend32 = adapter
        .features()
        .contains(wgpu::Features::FLOAT32_BLENDABLE)
        && supports(adapter, wgpu::TextureFormat::Rgba32Float, true);
    let (accum, features) = if blend32 {
        (
            wgpu::TextureFormat::Rgba32Float,
            wgpu::Features::FLOAT32_BLENDABLE,
        )
    } else if supports(adapter, wgpu::TextureFormat::Rgba16Float, true) {
        (wgpu::TextureFormat::Rgba16Float, wgpu::Features::empty())
    } else {
        return Err(missing(
            "a blendable floating-point render target (Rgba32Float with FLOAT32_BLENDABLE, or Rgba16Float)"
                .into(),
        ));
    };
    Ok((
        Formats {
            exact4: wgpu::TextureFormat::Rgba32Uint,
            half4: wgpu::TextureFormat::Rg32Uint,
            exact2: wgpu::TextureFormat::Rg32Uint,
            accum,
            depth,
        },
        features,
    ))
}

/// Rank of an adapter: lower is preferred.
fn rank(info: &wgpu::AdapterInfo) -> (u8, u8) {
    let device = match info.device_type {
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Cpu | wgpu::DeviceType::Other => 3,
    };
    let backend = match info.backend {
        wgpu::Backend::Vulkan | wgpu::Backend::Metal | wgpu::Backend::Dx12 => 0,
        wgpu::Backend::Gl => 1,
        _ => 2,
    };
    (device, backend)
}

/// The backends allowed: `WGPU_BACKEND` if set, else `requested`.
pub(crate) fn backends(requested: wgpu::Backends) -> wgpu::Backends {
    wgpu::Backends::from_env().unwrap_or(requested)
}

/// Routes libwayland-client's log into `tracing` (debug), once per process.
///
/// Opening a Vulkan instance with its window-system extensions makes Mesa's drivers try the
/// Wayland display; on a machine without a desktop session libwayland then prints "error:
/// XDG_RUNTIME_DIR is invalid or not set in the environment." on stderr, which reads as if
/// the run failed. The library's log goes through a handler any user of it may set
/// (`wl_log_set_handler_client`); ours keeps the line at debug level. Without the library
/// there is nothing to quiet.
#[cfg(target_os = "linux")]
#[allow(
    unsafe_code,
    reason = "a C library's log hook: loading it, setting it, reading a C string"
)]
fn quiet_wayland_log() {
    use std::ffi::{CStr, c_char, c_void};
    use std::sync::OnceLock;
    static LIBRARY: OnceLock<Option<libloading::Library>> = OnceLock::new();
    // `va_list` is passed as a pointer on the ABIs Linux runs on; the arguments are left
    // unread (the line is kept as its format string).
    extern "C" fn handler(format: *const c_char, _args: *mut c_void) {
        if format.is_null() {
            return;
        }
        // SAFETY: libwayland passes a NUL-terminated format string.
        let line = unsafe { CStr::from_ptr(format) }.to_string_lossy();
        tracing::debug!(target: "wayland", "{}", line.trim_end());
    }
    LIBRARY.get_or_init(|| {
        // SAFETY: loading libwayland-client runs no initialisers with requirements of ours,
        // and `wl_log_set_handler_client` has this signature in every release since 1.0.
        unsafe {
            let library = libloading::Library::new("libwayland-client.so.0").ok()?;
            let set: libloading::Symbol<
                unsafe extern "C" fn(extern "C" fn(*const c_char, *mut c_void)),
            > = library.get(b"wl_log_set_handler_client\0").ok()?;
            set(handler);
            // Kept loaded for the process's life, so the handler stays set.
            Some(library)
        }
    });
}

/// The adapters of `backends` that the raster can run on, best first, each with its formats
/// and required features; and, for each one it cannot run on, why.
pub(crate) async fn usable_adapters(
    backends: wgpu::Backends,
) -> (Vec<(wgpu::Adapter, Formats, wgpu::Features)>, Vec<String>) {
    #[cfg(target_os = "linux")]
    quiet_wayland_log();
    let instance =
        wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
    let mut adapters = instance.enumerate_adapters(backends).await;
    if let Ok(name) = std::env::var("WGPU_ADAPTER_NAME") {
        let name = name.to_lowercase();
        adapters.retain(|a| a.get_info().name.to_lowercase().contains(&name));
    }
    adapters.sort_by_key(|a| rank(&a.get_info()));
    let mut usable = Vec::new();
    let mut refused = Vec::new();
    for a in adapters {
        match choose_formats(&a) {
            Ok((formats, features)) => usable.push((a, formats, features)),
            Err(e) => refused.push(e.to_string()),
        }
    }
    (usable, refused)
}

/// Errors wgpu reported outside an error scope, and whether the device was lost.
#[derive(Clone, Default)]
pub(crate) struct ErrorSink {
    uncaptured: Arc<Mutex<Vec<String>>>,
    lost: Arc<Mutex<Option<String>>>,
}

impl ErrorSink {
    /// Routes `device`'s uncaptured errors and its loss here (instead of wgpu's default
    /// handler, which panics).
    pub(crate) fn attach(&self, device: &wgpu::Device) {
        let uncaptured = self.uncaptured.clone();
        device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
            if let Ok(mut v) = uncaptured.lock() {
                v.push(e.to_string());
            }
        }));
        let lost = self.lost.clone();
        device.set_device_lost_callback(move |reason, message| {
            if let Ok(mut l) = lost.lock() {
                *l = Some(format!("{reason:?}: {message}"));
            }
        });
    }

    /// The first error recorded since the last call, if any (a lost device stays an error).
    pub(crate) fn take(&self) -> Result<(), RasterError> {
        if let Some(reason) = self.lost.lock().ok().and_then(|l| l.clone()) {
            return Err(RasterError::DeviceLost(reason));
        }
        let first = self
            .uncaptured
            .lock()
            .ok()
            .and_then(|mut v| (!v.is_empty()).then(|| v.drain(..).next()).flatten());
        match first {
            Some(message) => Err(RasterError::Wgpu {
                operation: "an earlier operation".into(),
                message,
            }),
            None => Ok(()),
        }
    }
}
