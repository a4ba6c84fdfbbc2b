//! Embree 3 as a yardstick for `cloudlight bench rays --against-embree`: the same triangles and
//! the same rays through Intel's kernels, one ray at a time, in 8-wide packets and in streams.
//!
//! The library is opened at run time (`libembree3.so.3`, Debian's `libembree-dev`, or the file
//! named by `CLOUDLIGHT_EMBREE`), so the default build neither links nor needs it: where it is
//! not installed [`Embree::load`] says so and the benchmark runs without it. No crate binds
//! Embree 3 by run-time loading (the `embree` crate links at build time), so the dozen entry
//! points the benchmark calls are declared here from Embree 3.13's headers (`rtcore_*.h`).
//!
//! This module is allowed `unsafe` (the workspace denies it): every call crosses into C, each
//! with its `SAFETY` reason. Nothing of it is on a serving path.
#![allow(unsafe_code)]

use std::ffi::{CString, c_char, c_int, c_uint, c_void};
use std::mem::ManuallyDrop;
use std::time::{Duration, Instant};

use cloudlight_scenes::WorldTriangle;
use libloading::Library;

use crate::bvh::RayQuery;

type Device = *mut c_void;
type Scene = *mut c_void;
type Geometry = *mut c_void;

/// `struct RTCIntersectContext` with `RTC_MAX_INSTANCE_LEVEL_COUNT` 1 and no minimum width
/// (Debian's 3.13 build: `rtcore_config.h`).
#[repr(C)]
struct Context {
    flags: c_uint,
    filter: *const c_void,
    inst_id: [c_uint; 1],
}

impl Context {
    /// `rtcInitIntersectContext` (an inline function of the header).
    fn new(coherent: bool) -> Self {
        Context {
            flags: u32::from(coherent),
            filter: std::ptr::null(),
            inst_id: [u32::MAX],
        }
    }
}

/// `struct RTCRay` then `struct RTCHit` (`RTCRayHit`), 16-byte aligned.
#[repr(C, align(16))]
#[derive(Clone, Copy)]
struct RayHit1 {
    org: [f32; 3],
    tnear: f32,
    dir: [f32; 3],
    time: f32,
    tfar: f32,
    mask: c_uint,
    id: c_uint,
    flags: c_uint,
    ng: [f32; 3],
    u: f32,
    v: f32,
    prim_id: c_uint,
    geom_id: c_uint,
    inst_id: [c_uint; 1],
}

impl RayHit1 {
    fn new(&(o, d, t_max): &RayQuery) -> Self {
        RayHit1 {
            org: o.to_array(),
            tnear: 0.0,
            dir: d.to_array(),
            time: 0.0,
            tfar: t_max,
            mask: u32::MAX,
            id: 0,
            flags: 0,
            ng: [0.0; 3],
            u: 0.0,
            v: 0.0,
            prim_id: u32::MAX,
            geom_id: u32::MAX,
            inst_id: [u32::MAX],
        }
    }

    fn hit(&self) -> Option<(f32, u32)> {
        (self.geom_id != u32::MAX).then_some((self.tfar, self.prim_id))
    }
}

/// `struct RTCRayHit8`: `RTCRay8` then `RTCHit8`, structure of arrays, 32-byte aligned.
#[repr(C, align(32))]
struct RayHit8 {
    org: [[f32; 8]; 3],
    tnear: [f32; 8],
    dir: [[f32; 8]; 3],
    time: [f32; 8],
    tfar: [f32; 8],
    mask: [c_uint; 8],
    id: [c_uint; 8],
    flags: [c_uint; 8],
    ng: [[f32; 8]; 3],
    u: [f32; 8],
    v: [f32; 8],
    prim_id: [c_uint; 8],
    geom_id: [c_uint; 8],
    inst_id: [[c_uint; 8]; 1],
}

/// `int valid[8]` of a packet call: aligned as the packet (Embree loads it as one vector).
#[repr(C, align(32))]
struct Valid8([c_int; 8]);

struct Api {
    new_device: unsafe extern "C" fn(*const c_char) -> Device,
    release_device: unsafe extern "C" fn(Device),
    device_error: unsafe extern "C" fn(Device) -> c_int,
    new_scene: unsafe extern "C" fn(Device) -> Scene,
    release_scene: unsafe extern "C" fn(Scene),
    scene_build_quality: unsafe extern "C" fn(Scene, c_int),
    commit_scene: unsafe extern "C" fn(Scene),
    new_geometry: unsafe extern "C" fn(Device, c_int) -> Geometry,
    new_buffer: unsafe extern "C" fn(Geometry, c_int, c_uint, c_int, usize, usize) -> *mut c_void,
    commit_geometry: unsafe extern "C" fn(Geometry),
    attach_geometry: unsafe extern "C" fn(Scene, Geometry) -> c_uint,
    release_geometry: unsafe extern "C" fn(Geometry),
    intersect1: unsafe extern "C" fn(Scene, *mut Context, *mut RayHit1),
    intersect8: unsafe extern "C" fn(*const c_int, Scene, *mut Context, *mut RayHit8),
    intersect1m: unsafe extern "C" fn(Scene, *mut Context, *mut RayHit1, c_uint, usize),
    occluded1: unsafe extern "C" fn(Scene, *mut Context, *mut RayHit1),
}

/// The Embree 3 library, opened at run time.
pub struct Embree {
    api: Api,
    /// Never unloaded: Embree leaves thread-local destructors in the threads that cast rays,
    /// which run when those threads end (measured: a crash at the thread pool's exit after
    /// an unload).
    _lib: ManuallyDrop<Library>,
    /// Where it was loaded from.
    pub path: String,
}

const RTC_GEOMETRY_TYPE_TRIANGLE: c_int = 0;
const RTC_BUFFER_TYPE_INDEX: c_int = 0;
const RTC_BUFFER_TYPE_VERTEX: c_int = 1;
const RTC_FORMAT_UINT3: c_int = 0x5003;
const RTC_FORMAT_FLOAT3: c_int = 0x9003;
const RTC_BUILD_QUALITY_MEDIUM: c_int = 1;

impl Embree {
    /// Opens `CLOUDLIGHT_EMBREE` or `libembree3.so.3`; the error says what to install.
    pub fn load() -> Result<Self, String> {
        let path =
            std::env::var("CLOUDLIGHT_EMBREE").unwrap_or_else(|_| "libembree3.so.3".to_owned());
        // SAFETY: loading runs the library's initialisers; Embree 3's are plain C++ static
        // constructors with no requirements on the caller.
        let lib = unsafe { Library::new(&path) }.map_err(|e| {
            format!(
                "Embree 3 is not installed ({e}); install Debian's libembree-dev or point \
                 CLOUDLIGHT_EMBREE at libembree3.so"
            )
        })?;
        macro_rules! sym {
            ($name:literal) => {
                // SAFETY: the symbol's C signature is the one declared for the field it fills
                // (Embree 3.13's rtcore_*.h); the pointer stays valid while `_lib` lives,
                // and it lives as long as `Api`.
                *unsafe { lib.get(concat!($name, "\0").as_bytes()) }
                    .map_err(|e| format!("{path} lacks {}: {e}", $name))?
            };
        }
        let api = Api {
            new_device: sym!("rtcNewDevice"),
            release_device: sym!("rtcReleaseDevice"),
            device_error: sym!("rtcGetDeviceError"),
            new_scene: sym!("rtcNewScene"),
            release_scene: sym!("rtcReleaseScene"),
            scene_build_quality: sym!("rtcSetSceneBuildQuality"),
            commit_scene: sym!("rtcCommitScene"),
            new_geometry: sym!("rtcNewGeometry"),
            new_buffer: sym!("rtcSetNewGeometryBuffer"),
            commit_geometry: sym!("rtcCommitGeometry"),
            attach_geometry: sym!("rtcAttachGeometry"),
            release_geometry: sym!("rtcReleaseGeometry"),
            intersect1: sym!("rtcIntersect1"),
            intersect8: sym!("rtcIntersect8"),
            intersect1m: sym!("rtcIntersect1M"),
            occluded1: sym!("rtcOccluded1"),
        };
        Ok(Embree {
            api,
            _lib: ManuallyDrop::new(lib),
            path,
        })
    }

    /// Builds a scene of `triangles` (meters) at build quality MEDIUM with `threads` build
    /// threads; the build time is measured around `rtcCommitScene`.
    pub fn scene(
        &self,
        triangles: &[WorldTriangle],
        threads: usize,
    ) -> Result<EmbreeScene<'_>, String> {
        let a = &self.api;
        let config = CString::new(format!("threads={}", threads.max(1))).expect("no NUL");
        // SAFETY: a NUL-terminated configuration string.
        let device = unsafe { (a.new_device)(config.as_ptr()) };
        if device.is_null() {
            // SAFETY: a null device asks for the thread's last error.
            let e = unsafe { (a.device_error)(std::ptr::null_mut()) };
            return Err(format!("rtcNewDevice failed (error {e})"));
        }
        // SAFETY: `device` is live; the geometry's buffers are sized for `triangles` and
        // written in bounds below; everything is released in `Drop`.
        unsafe {
            let scene = (a.new_scene)(device);
            (a.scene_build_quality)(scene, RTC_BUILD_QUALITY_MEDIUM);
            let geometry = (a.new_geometry)(device, RTC_GEOMETRY_TYPE_TRIANGLE);
            let n = triangles.len();
            let vertices = (a.new_buffer)(
                geometry,
                RTC_BUFFER_TYPE_VERTEX,
                0,
                RTC_FORMAT_FLOAT3,
                12,
                3 * n,
            ) as *mut f32;
            let indices =
                (a.new_buffer)(geometry, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, 12, n)
                    as *mut u32;
            if n > 0 && (vertices.is_null() || indices.is_null()) {
                let e = (a.device_error)(device);
                (a.release_geometry)(geometry);
                (a.release_scene)(scene);
                (a.release_device)(device);
                return Err(format!("Embree could not allocate buffers (error {e})"));
            }
            if n > 0 {
                let v = std::slice::from_raw_parts_mut(vertices, 9 * n);
                let ix = std::slice::from_raw_parts_mut(indices, 3 * n);
                for (i, t) in triangles.iter().enumerate() {
                    for k in 0..3 {
                        v[9 * i + 3 * k..9 * i + 3 * k + 3].copy_from_slice(&t.v[k].to_array());
                        ix[3 * i + k] = (3 * i + k) as u32;
                    }
                }
            }
            (a.commit_geometry)(geometry);
            (a.attach_geometry)(scene, geometry);
            (a.release_geometry)(geometry);
            let t = Instant::now();
            (a.commit_scene)(scene);
            let build_time = t.elapsed();
            let e = (a.device_error)(device);
            if e != 0 {
                (a.release_scene)(scene);
                (a.release_device)(device);
                return Err(format!("Embree build failed (error {e})"));
            }
            Ok(EmbreeScene {
                api: a,
                device,
                scene,
                build_time,
            })
        }
    }
}

/// A committed Embree scene.
pub struct EmbreeScene<'a> {
    api: &'a Api,
    device: Device,
    scene: Scene,
    /// Time of `rtcCommitScene`.
    pub build_time: Duration,
}

// SAFETY: a committed Embree scene may be queried from any number of threads at once (Embree's
// documentation of rtcIntersect*); the handles are only released in `Drop`.
unsafe impl Send for EmbreeScene<'_> {}
// SAFETY: as above: queries take `&self` and Embree's traversal does not mutate the scene.
unsafe impl Sync for EmbreeScene<'_> {}

impl Drop for EmbreeScene<'_> {
    fn drop(&mut self) {
        // SAFETY: the handles were made in `Embree::scene` and are released once.
        unsafe {
            (self.api.release_scene)(self.scene);
            (self.api.release_device)(self.device);
        }
    }
}

/// A closest hit: distance (m) and triangle index.
pub type EmbreeHit = Option<(f32, u32)>;

impl EmbreeScene<'_> {
    /// One ray at a time (`rtcIntersect1`).
    pub fn closest_hit(&self, q: &RayQuery) -> EmbreeHit {
        let mut r = RayHit1::new(q);
        let mut c = Context::new(false);
        // SAFETY: a committed scene, an initialised context and ray.
        unsafe { (self.api.intersect1)(self.scene, &mut c, &mut r) };
        r.hit()
    }

    /// Whether anything lies closer than the ray's end (`rtcOccluded1`).
    pub fn occluded(&self, q: &RayQuery) -> bool {
        let mut r = RayHit1::new(q);
        let mut c = Context::new(false);
        // SAFETY: as `closest_hit`; `rtcOccluded1` reads the leading `RTCRay` of the struct.
        unsafe { (self.api.occluded1)(self.scene, &mut c, &mut r) };
        r.tfar < 0.0
    }

    /// Consecutive groups of eight rays as packets (`rtcIntersect8`); `out` as long as `rays`.
    pub fn closest_hits_packets(&self, rays: &[RayQuery], out: &mut [EmbreeHit]) {
        let mut c = Context::new(false);
        for (chunk, out) in rays.chunks(8).zip(out.chunks_mut(8)) {
            let mut p = RayHit8 {
                org: [[0.0; 8]; 3],
                tnear: [0.0; 8],
                dir: [[0.0; 8]; 3],
                time: [0.0; 8],
                tfar: [0.0; 8],
                mask: [u32::MAX; 8],
                id: [0; 8],
                flags: [0; 8],
                ng: [[0.0; 8]; 3],
                u: [0.0; 8],
                v: [0.0; 8],
                prim_id: [u32::MAX; 8],
                geom_id: [u32::MAX; 8],
                inst_id: [[u32::MAX; 8]],
            };
            let mut valid = Valid8([0; 8]);
            for (i, &(o, d, t)) in chunk.iter().enumerate() {
                for k in 0..3 {
                    p.org[k][i] = o[k];
                    p.dir[k][i] = d[k];
                }
                p.tfar[i] = t;
                valid.0[i] = -1;
            }
            // SAFETY: a committed scene, a 32-byte aligned packet and mask of eight lanes.
            unsafe { (self.api.intersect8)(valid.0.as_ptr(), self.scene, &mut c, &mut p) };
            for (i, o) in out.iter_mut().enumerate() {
                *o = (p.geom_id[i] != u32::MAX).then_some((p.tfar[i], p.prim_id[i]));
            }
        }
    }

    /// The rays as one stream (`rtcIntersect1M`), flagged coherent or not.
    pub fn closest_hits_stream(&self, rays: &[RayQuery], coherent: bool, out: &mut [EmbreeHit]) {
        let mut buf: Vec<RayHit1> = rays.iter().map(RayHit1::new).collect();
        let mut c = Context::new(coherent);
        // SAFETY: `buf` holds `len` contiguous rays of the declared stride.
        unsafe {
            (self.api.intersect1m)(
                self.scene,
                &mut c,
                buf.as_mut_ptr(),
                buf.len() as c_uint,
                std::mem::size_of::<RayHit1>(),
            )
        };
        for (o, r) in out.iter_mut().zip(&buf) {
            *o = r.hit();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layouts_match_embree_3_headers() {
        assert_eq!(std::mem::size_of::<RayHit1>(), 80);
        assert_eq!(std::mem::size_of::<RayHit8>(), 20 * 32);
        assert_eq!(std::mem::size_of::<Context>(), 24);
    }
}
