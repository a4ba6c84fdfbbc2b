//! The scene model: meshes placed by objects, diffuse materials, lights with power in watts,
//! and camera paths — all evaluated as pure functions of scene time.
//!
//! World units are meters; colours are linear RGB; radiance is W·m⁻²·sr⁻¹ per channel,
//! power W per channel, irradiance W·m⁻² per channel.

use glam::{Affine3A, Mat3, Quat, Vec2, Vec3};

/// A diffuse material.
#[derive(Clone, Debug, PartialEq)]
pub struct Material {
    /// Name, for diagnostics.
    pub name: String,
    /// Diffuse reflectance (albedo), linear RGB in [0, 1].
    pub albedo: Vec3,
    /// Albedo texture, multiplied with `albedo`.
    pub texture: Option<Texture>,
    /// Emitted radiance, W·m⁻²·sr⁻¹ per channel (zero for non-emitters).
    pub emission: Vec3,
}

impl Material {
    /// A plain diffuse material.
    pub fn diffuse(name: &str, albedo: Vec3) -> Self {
        Material {
            name: name.into(),
            albedo,
            texture: None,
            emission: Vec3::ZERO,
        }
    }

    /// Whether the material emits light.
    pub fn is_emissive(&self) -> bool {
        self.emission.max_element() > 0.0
    }
}

/// An RGBA8 texture (sRGB-encoded colour), sampled with wrapping.
#[derive(Clone, Debug, PartialEq)]
pub struct Texture {
    /// Width in texels.
    pub width: u32,
    /// Height in texels.
    pub height: u32,
    /// Linear RGB texels, row-major from the top.
    pub texels: Vec<Vec3>,
}

impl Texture {
    /// Nearest texel at `uv` (wrapping).
    pub fn sample(&self, uv: Vec2) -> Vec3 {
        let u = uv.x - uv.x.floor();
        let v = uv.y - uv.y.floor();
        let x = ((u * self.width as f32) as u32).min(self.width - 1);
        let y = ((v * self.height as f32) as u32).min(self.height - 1);
        self.texels[(y * self.width + x) as usize]
    }
}

/// Triangles in an object's local frame.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    /// Vertex positions, meters.
    pub positions: Vec<Vec3>,
    /// Unit vertex normals (one per position).
    pub normals: Vec<Vec3>,
    /// Texture coordinates (empty, or one per position).
    pub uvs: Vec<Vec2>,
    /// Light-map coordinates (empty, or one per position).
    pub lightmap_uvs: Vec<Vec2>,
    /// Triangles as vertex indices, counter-clockwise seen from the front.
    pub indices: Vec<[u32; 3]>,
}

impl Mesh {
    /// Adds a planar quad `a b c d` (counter-clockwise seen from the front) with flat normals.
    pub fn push_quad(&mut self, a: Vec3, b: Vec3, c: Vec3, d: Vec3) {
        let n = (b - a).cross(d - a).normalize_or_zero();
        let base = self.positions.len() as u32;
        self.positions.extend([a, b, c, d]);
        self.normals.extend([n; 4]);
        self.uvs.extend([
            Vec2::new(0.0, 0.0),
            Vec2::new(1.0, 0.0),
            Vec2::new(1.0, 1.0),
            Vec2::new(0.0, 1.0),
        ]);
        self.indices
            .extend([[base, base + 1, base + 2], [base, base + 2, base + 3]]);
    }

    /// Adds an axis-aligned box from `min` to `max` with outward faces.
    pub fn push_box(&mut self, min: Vec3, max: Vec3) {
        let (a, b) = (min, max);
        let p = |x: f32, y: f32, z: f32| Vec3::new(x, y, z);
        self.push_quad(
            p(a.x, a.y, b.z),
            p(b.x, a.y, b.z),
            p(b.x, b.y, b.z),
            p(a.x, b.y, b.z),
        ); // +z
        self.push_quad(
            p(b.x, a.y, a.z),
            p(a.x, a.y, a.z),
            p(a.x, b.y, a.z),
            p(b.x, b.y, a.z),
        ); // -z
        self.push_quad(
            p(b.x, a.y, b.z),
            p(b.x, a.y, a.z),
            p(b.x, b.y, a.z),
            p(b.x, b.y, b.z),
        ); // +x
        self.push_quad(
            p(a.x, a.y, a.z),
            p(a.x, a.y, b.z),
            p(a.x, b.y, b.z),
            p(a.x, b.y, a.z),
        ); // -x
        self.push_quad(
            p(a.x, b.y, b.z),
            p(b.x, b.y, b.z),
            p(b.x, b.y, a.z),
            p(a.x, b.y, a.z),
        ); // +y
        self.push_quad(
            p(a.x, a.y, a.z),
            p(b.x, a.y, a.z),
            p(b.x, a.y, b.z),
            p(a.x, a.y, b.z),
        ); // -y
    }

    /// The same surfaces facing the other way (winding and normals reversed).
    pub fn flipped(mut self) -> Self {
        for t in &mut self.indices {
            t.swap(1, 2);
        }
        for n in &mut self.normals {
            *n = -*n;
        }
        self
    }

    /// Number of triangles.
    pub fn triangle_count(&self) -> usize {
        self.indices.len()
    }
}

/// How something moves: its world-from-local transform as a function of scene time.
#[derive(Clone, Debug, PartialEq)]
pub enum Motion {
    /// Fixed.
    Static(Affine3A),
    /// Circles `center` in the plane normal to `axis`, at `radius` meters, once per `period_s`,
    /// starting at `phase` (fraction of a turn).
    Orbit {
        /// Center, meters.
        center: Vec3,
        /// Axis of the orbit (unit).
        axis: Vec3,
        /// Radius, meters.
        radius: f32,
        /// Seconds per turn.
        period_s: f64,
        /// Fraction of a turn at time 0.
        phase: f64,
    },
    /// Piecewise-linear path through (time, position) keys, looping after the last key.
    Path {
        /// Keys sorted by time, seconds and meters.
        keys: Vec<(f64, Vec3)>,
    },
}

impl Motion {
    /// Identity.
    pub fn identity() -> Self {
        Motion::Static(Affine3A::IDENTITY)
    }

    /// world_from_local at scene time `t_s`.
    pub fn world_from_local(&self, t_s: f64) -> Affine3A {
        match self {
            Motion::Static(a) => *a,
            Motion::Orbit {
                center,
                axis,
                radius,
                period_s,
                phase,
            } => {
                let turns = t_s / period_s + phase;
                let angle = (turns.fract() * std::f64::consts::TAU) as f32;
                let axis = axis.normalize_or(Vec3::Y);
                let start = axis.any_orthonormal_vector() * *radius;
                Affine3A::from_translation(*center + Quat::from_axis_angle(axis, angle) * start)
            }
            Motion::Path { keys } => Affine3A::from_translation(path_position(keys, t_s)),
        }
    }

    /// Whether the transform changes with time.
    pub fn is_animated(&self) -> bool {
        !matches!(self, Motion::Static(_))
    }
    /// The box (lower, upper corner) that the translation of an animated motion stays in
    /// over all time, meters: a moving object's world points are its local points plus a
    /// translation inside it. `None` for a static transform (which may rotate and scale).
    pub fn translation_bounds(&self) -> Option<(Vec3, Vec3)> {
        match self {
            Motion::Static(_) => None,
            Motion::Orbit {
                center,
                axis,
                radius,
                ..
            } => {
                // A circle of `radius` in the plane normal to `axis` spans r·√(1 − a_i²).
                let a = axis.normalize_or(Vec3::Y);
                let half = (Vec3::ONE - a * a).max(Vec3::ZERO).powf(0.5) * radius.abs();
                Some((*center - half, *center + half))
            }
            Motion::Path { keys } => {
                let mut lo = Vec3::splat(f32::INFINITY);
                let mut hi = Vec3::splat(f32::NEG_INFINITY);
                for (_, p) in keys {
                    lo = lo.min(*p);
                    hi = hi.max(*p);
                }
                (lo.cmple(hi).all()).then_some((lo, hi))
            }
        }
    }
}

fn path_position(keys: &[(f64, Vec3)], t_s: f64) -> Vec3 {
    match keys {
        [] => Vec3::ZERO,
        [(_, p)] => *p,
        _ => {
            let (t0, t1) = (keys[0].0, keys[keys.len() - 1].0);
            let span = (t1 - t0).max(1e-9);
            let t = t0 + (t_s - t0).rem_euclid(span);
            let i = keys
                .partition_point(|(k, _)| *k <= t)
                .clamp(1, keys.len() - 1);
            let ((ta, a), (tb, b)) = (keys[i - 1], keys[i]);
            let f = ((t - ta) / (tb - ta).max(1e-12)).clamp(0.0, 1.0) as f32;
            a.lerp(b, f)
        }
    }
}

/// A mesh placed in the world with a material.
#[derive(Clone, Debug, PartialEq)]
pub struct Object {
    /// Name, for diagnostics.
    pub name: String,
    /// Geometry in the object's frame.
    pub mesh: Mesh,
    /// Index into [`Scene::materials`].
    pub material: u32,
    /// world_from_local over time.
    pub motion: Motion,
}

/// Kinds of punctual and distant lights.
#[derive(Clone, Debug, PartialEq)]
pub enum LightKind {
    /// Emits `power_w` uniformly in all directions.
    Point,
    /// Emits `power_w` into a cone around `direction` (uniform inside `cone_angle_rad`, the
    /// half-angle).
    Spot {
        /// Unit direction in the light's frame (rotated by nothing: world space).
        direction: Vec3,
        /// Half-angle of the cone, radians.
        cone_angle_rad: f32,
    },
    /// A sun: parallel light of `irradiance_w_m2` on a surface facing it.
    Directional {
        /// Per-channel irradiance on a surface facing the light, W·m⁻².
        irradiance_w_m2: Vec3,
    },
}

/// A light.
#[derive(Clone, Debug, PartialEq)]
pub struct Light {
    /// Name, for diagnostics.
    pub name: String,
    /// What it is.
    pub kind: LightKind,
    /// Emitted power per channel, watts (point and spot lights).
    pub power_w: Vec3,
    /// Position over time (point, spot), from the motion's translation.
    pub motion: Motion,
    /// For directional lights: unit direction the light travels, over time (a day cycle).
    pub sun_path: Option<SunPath>,
}

/// A sun direction as a function of time: a day of `day_length_s` scene seconds, or a
/// fixed direction.
#[derive(Clone, Debug, PartialEq)]
pub struct SunPath {
    /// A fixed direction of travel, overriding the day cycle.
    pub fixed: Option<Vec3>,
    /// Scene seconds per day.
    pub day_length_s: f64,
    /// Highest elevation above the horizon, radians.
    pub max_elevation_rad: f32,
    /// Fraction of the day at scene time 0.
    pub phase: f64,
}

impl SunPath {
    /// A sun that does not move, its light travelling along `direction`.
    pub fn fixed(direction: Vec3) -> Self {
        SunPath {
            fixed: Some(direction.normalize_or(Vec3::NEG_Y)),
            day_length_s: 1.0,
            max_elevation_rad: 1.0,
            phase: 0.0,
        }
    }

    /// Unit direction of travel of sunlight at `t_s` (pointing down when the sun is up).
    pub fn direction(&self, t_s: f64) -> Vec3 {
        if let Some(d) = self.fixed {
            return d;
        }
        let day = (t_s / self.day_length_s + self.phase).fract() as f32;
        let azimuth = day * std::f32::consts::TAU;
        // Elevation follows a sine over the day, kept above the horizon.
        let elevation = (self.max_elevation_rad * (0.25 + 0.75 * (azimuth * 0.5).sin())).max(0.05);
        let to_sun = Vec3::new(
            azimuth.cos() * elevation.cos(),
            elevation.sin(),
            azimuth.sin() * elevation.cos(),
        );
        -to_sun
    }
}

/// The state of a light at one scene time.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum LightState {
    /// Point light: position (m) and intensity (W·sr⁻¹ per channel).
    Point {
        /// Position, meters.
        position: Vec3,
        /// Radiant intensity, W/sr per channel.
        intensity: Vec3,
    },
    /// Spot light.
    Spot {
        /// Position, meters.
        position: Vec3,
        /// Unit cone axis.
        direction: Vec3,
        /// Cosine of the cone half-angle.
        cos_cone: f32,
        /// Radiant intensity inside the cone, W/sr per channel.
        intensity: Vec3,
    },
    /// A small piece of an emissive surface: a Lambertian point emitter whose radiant
    /// intensity toward a direction at angle θ from `normal` is `intensity`·cos θ (zero
    /// behind it). Techniques and the raster approximate area lights with these.
    Surface {
        /// Position, meters.
        position: Vec3,
        /// Unit normal of the emitting side.
        normal: Vec3,
        /// Radiant intensity along the normal (radiance × area), W/sr per channel.
        intensity: Vec3,
    },
    /// Directional light.
    Directional {
        /// Unit direction light travels.
        direction: Vec3,
        /// Irradiance on a surface facing the light, W/m² per channel.
        irradiance: Vec3,
    },
}

impl Light {
    /// The light at scene time `t_s`.
    pub fn at(&self, t_s: f64) -> LightState {
        let position = self.motion.world_from_local(t_s).translation.into();
        match &self.kind {
            LightKind::Point => LightState::Point {
                position,
                intensity: self.power_w / (4.0 * std::f32::consts::PI),
            },
            LightKind::Spot {
                direction,
                cone_angle_rad,
            } => {
                let solid_angle = std::f32::consts::TAU * (1.0 - cone_angle_rad.cos());
                LightState::Spot {
                    position,
                    direction: direction.normalize_or(Vec3::NEG_Y),
                    cos_cone: cone_angle_rad.cos(),
                    intensity: self.power_w / solid_angle.max(1e-6),
                }
            }
            LightKind::Directional { irradiance_w_m2 } => LightState::Directional {
                direction: self
                    .sun_path
                    .as_ref()
                    .map_or(Vec3::NEG_Y, |s| s.direction(t_s)),
                irradiance: *irradiance_w_m2,
            },
        }
    }
}

/// A pinhole camera.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Camera {
    /// Eye position, meters.
    pub position: Vec3,
    /// Point looked at, meters.
    pub target: Vec3,
    /// Up direction.
    pub up: Vec3,
    /// Vertical field of view, radians.
    pub fov_y_rad: f32,
}

impl Camera {
    /// world_from_camera rotation (camera looks down its −z).
    pub fn world_from_camera(&self) -> Mat3 {
        let f = (self.target - self.position).normalize_or(Vec3::NEG_Z);
        let r = f.cross(self.up).normalize_or(Vec3::X);
        let u = r.cross(f);
        Mat3::from_cols(r, u, -f)
    }

    /// Unit world direction through normalized image coordinates (x right, y up, in [−1, 1]
    /// across the height; `aspect` = width / height).
    pub fn ray_direction(&self, ndc: Vec2, aspect: f32) -> Vec3 {
        let h = (self.fov_y_rad * 0.5).tan();
        let d = Vec3::new(ndc.x * h * aspect, ndc.y * h, -1.0);
        (self.world_from_camera() * d).normalize()
    }
}

/// Where a client looks: its camera and its image's aspect. Clients send theirs upstream
/// (the client shell's `view` port) so that servers can favour what they see.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct View {
    /// The camera.
    pub camera: Camera,
    /// Width / height of its image.
    pub aspect: f32,
}

impl View {
    /// Whether every number is finite, the field of view within (0, π), the aspect
    /// positive and the eye apart from the target.
    pub fn is_valid(&self) -> bool {
        let c = &self.camera;
        [c.position, c.target, c.up].iter().all(|v| v.is_finite())
            && c.position != c.target
            && c.fov_y_rad > 0.0
            && c.fov_y_rad < std::f32::consts::PI
            && self.aspect > 0.0
            && self.aspect < 1e3
    }
}

/// A camera moving over time (each client of a run follows one).
#[derive(Clone, Debug, PartialEq)]
pub struct CameraPath {
    /// Name.
    pub name: String,
    /// The camera at rest.
    pub camera: Camera,
    /// Eye motion (its translation is added to `camera.position`, as is the target's).
    pub motion: Motion,
}

impl CameraPath {
    /// The camera at scene time `t_s`.
    pub fn at(&self, t_s: f64) -> Camera {
        let offset: Vec3 = self.motion.world_from_local(t_s).translation.into();
        let mut c = self.camera;
        if self.motion.is_animated() {
            c.position += offset;
            c.target += offset;
        }
        c
    }
}

/// A scene: everything lighting needs, as a function of scene time.
#[derive(Clone, Debug, PartialEq)]
pub struct Scene {
    /// Name (`cornell`, `city:20000`, a file name).
    pub name: String,
    /// Materials.
    pub materials: Vec<Material>,
    /// Placed meshes.
    pub objects: Vec<Object>,
    /// Punctual and distant lights (emissive surfaces are lights through their material).
    pub lights: Vec<Light>,
    /// Client camera paths; the first is the default view.
    pub cameras: Vec<CameraPath>,
}

/// One world-space triangle with its shading data, as ray casting and raster consume them.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WorldTriangle {
    /// Vertices, meters.
    pub v: [Vec3; 3],
    /// Unit vertex normals.
    pub n: [Vec3; 3],
    /// Texture coordinates.
    pub uv: [Vec2; 3],
    /// Light-map coordinates in [0, 1]² of the atlas (zero when the mesh has none).
    pub lightmap_uv: [Vec2; 3],
    /// Material index.
    pub material: u32,
}

impl Scene {
    /// The lights a client shades itself with at `t_s`: every light's state, then the
    /// emissive surfaces' point samples `samples` (from [`Scene::surface_light_samples`], which
    /// a caller keeps while the geometry does not move).
    pub fn direct_lights(&self, t_s: f64, samples: &[LightState]) -> Vec<LightState> {
        let mut lights: Vec<LightState> = self.lights.iter().map(|l| l.at(t_s)).collect();
        lights.extend_from_slice(samples);
        lights
    }

    /// A view of the whole scene (at time 0) for scenes without camera paths.
    pub fn overview_camera(&self) -> Camera {
        let (lo, hi) = self.bounds_at(0.0);
        let (center, size) = if lo.is_finite() && hi.is_finite() {
            ((lo + hi) * 0.5, (hi - lo).length())
        } else {
            (Vec3::ZERO, 3.0)
        };
        Camera {
            position: center + Vec3::new(0.0, 0.0, size),
            target: center,
            up: Vec3::Y,
            fov_y_rad: 1.0,
        }
    }

    /// The same scene with every light's power, the sun's irradiance and every surface's
    /// emission multiplied by `k` (what a change of light unit does; error metrics must not
    /// notice).
    pub fn with_lights_scaled(&self, k: f32) -> Scene {
        let mut s = self.clone();
        for l in &mut s.lights {
            l.power_w *= k;
            if let LightKind::Directional { irradiance_w_m2 } = &mut l.kind {
                *irradiance_w_m2 *= k;
            }
        }
        for m in &mut s.materials {
            m.emission *= k;
        }
        s
    }

    /// The scene scaled by `s` about the origin: geometry, motions, lights and cameras
    /// (radiance and power are unchanged).
    pub fn scaled(mut self, s: f32) -> Self {
        let scale = |m: &mut Motion| match m {
            Motion::Static(a) => a.translation *= s,
            Motion::Orbit { center, radius, .. } => {
                *center *= s;
                *radius *= s;
            }
            Motion::Path { keys } => keys.iter_mut().for_each(|(_, p)| *p *= s),
        };
        for o in &mut self.objects {
            o.mesh.positions.iter_mut().for_each(|p| *p *= s);
            scale(&mut o.motion);
        }
        for l in &mut self.lights {
            scale(&mut l.motion);
        }
        for c in &mut self.cameras {
            c.camera.position *= s;
            c.camera.target *= s;
            scale(&mut c.motion);
        }
        self
    }

    /// Total triangle count.
    pub fn triangle_count(&self) -> usize {
        self.objects.iter().map(|o| o.mesh.triangle_count()).sum()
    }

    /// Whether anything moves (objects, lights or the sun).
    pub fn is_animated(&self) -> bool {
        self.objects.iter().any(|o| o.motion.is_animated())
            || self.lights.iter().any(|l| {
                l.motion.is_animated() || l.sun_path.as_ref().is_some_and(|s| s.fixed.is_none())
            })
    }

    /// Every triangle in world space at scene time `t_s`, objects in order.
    pub fn triangles_at(&self, t_s: f64) -> Vec<WorldTriangle> {
        let mut out = Vec::with_capacity(self.triangle_count());
        for o in &self.objects {
            push_object_triangles(o, t_s, &mut out);
        }
        out
    }

    /// The triangles of object `index` in world space at scene time `t_s`.
    pub fn object_triangles_at(&self, index: usize, t_s: f64) -> Vec<WorldTriangle> {
        let mut out = Vec::new();
        if let Some(o) = self.objects.get(index) {
            push_object_triangles(o, t_s, &mut out);
        }
        out
    }

    /// Whether any object moves (lights and the sun aside): whether geometry, and so a BVH,
    /// changes over time.
    pub fn has_moving_geometry(&self) -> bool {
        self.objects.iter().any(|o| o.motion.is_animated())
    }

    /// Emissive surfaces at scene time `t_s` as Lambertian point emitters: each emissive
    /// triangle is split into `n`² equal sub-triangles, one emitter at each centroid.
    pub fn surface_light_samples(&self, t_s: f64, n: u32) -> Vec<LightState> {
        let n = n.max(1);
        let mut out = Vec::new();
        for t in self.triangles_at(t_s) {
            let le = self.materials[t.material as usize].emission;
            if le.max_element() <= 0.0 {
                continue;
            }
            let cross = (t.v[1] - t.v[0]).cross(t.v[2] - t.v[0]);
            let area = 0.5 * cross.length();
            if area <= 0.0 || !area.is_finite() {
                continue;
            }
            let normal = cross.normalize();
            let intensity = le * (area / (n * n) as f32);
            // A regular subdivision: upward and downward sub-triangles.
            let at = |i: f32, j: f32| {
                t.v[0] + (t.v[1] - t.v[0]) * (i / n as f32) + (t.v[2] - t.v[0]) * (j / n as f32)
            };
            for i in 0..n {
                for j in 0..(n - i) {
                    let (fi, fj) = (i as f32, j as f32);
                    let up = (at(fi, fj) + at(fi + 1.0, fj) + at(fi, fj + 1.0)) / 3.0;
                    out.push(LightState::Surface {
                        position: up,
                        normal,
                        intensity,
                    });
                    if i + j + 1 < n {
                        let down =
                            (at(fi + 1.0, fj) + at(fi, fj + 1.0) + at(fi + 1.0, fj + 1.0)) / 3.0;
                        out.push(LightState::Surface {
                            position: down,
                            normal,
                            intensity,
                        });
                    }
                }
            }
        }
        out
    }

    /// Bounds (lower, upper corner) of the geometry over all scene time, meters: static
    /// objects where they are, moving ones swept along their motion. Empty scenes give
    /// (+∞, −∞).
    pub fn swept_bounds(&self) -> (Vec3, Vec3) {
        let mut lo = Vec3::splat(f32::INFINITY);
        let mut hi = Vec3::splat(f32::NEG_INFINITY);
        for o in &self.objects {
            if o.mesh.positions.is_empty() {
                continue;
            }
            match o.motion.translation_bounds() {
                Some((t_lo, t_hi)) => {
                    for p in &o.mesh.positions {
                        lo = lo.min(*p + t_lo);
                        hi = hi.max(*p + t_hi);
                    }
                }
                None => {
                    let m = o.motion.world_from_local(0.0);
                    for p in &o.mesh.positions {
                        let w = m.transform_point3(*p);
                        lo = lo.min(w);
                        hi = hi.max(w);
                    }
                }
            }
        }
        (lo, hi)
    }

    /// Axis-aligned bounds at scene time `t_s`, meters (min, max).
    pub fn bounds_at(&self, t_s: f64) -> (Vec3, Vec3) {
        let mut lo = Vec3::splat(f32::INFINITY);
        let mut hi = Vec3::splat(f32::NEG_INFINITY);
        for t in self.triangles_at(t_s) {
            for v in t.v {
                lo = lo.min(v);
                hi = hi.max(v);
            }
        }
        (lo, hi)
    }

    /// Power emitted by every light and emissive surface, watts per channel (directional
    /// lights excluded: their power depends on the area they light).
    pub fn emitted_power_w(&self) -> Vec3 {
        let punctual: Vec3 = self
            .lights
            .iter()
            .filter(|l| !matches!(l.kind, LightKind::Directional { .. }))
            .map(|l| l.power_w)
            .sum();
        let surfaces: Vec3 = self
            .triangles_at(0.0)
            .iter()
            .filter_map(|t| {
                let m = &self.materials[t.material as usize];
                m.is_emissive().then(|| {
                    let area = 0.5 * (t.v[1] - t.v[0]).cross(t.v[2] - t.v[0]).length();
                    m.emission * std::f32::consts::PI * area
                })
            })
            .sum();
        punctual + surfaces
    }
}

fn push_object_triangles(o: &Object, t_s: f64, out: &mut Vec<WorldTriangle>) {
    let m = o.motion.world_from_local(t_s);
    let nm = Mat3::from(m.matrix3).inverse().transpose();
    let mesh = &o.mesh;
    for tri in &mesh.indices {
        let i = tri.map(|k| k as usize);
        let uv = |k: usize| mesh.uvs.get(k).copied().unwrap_or(Vec2::ZERO);
        let lightmap_uv = |k: usize| mesh.lightmap_uvs.get(k).copied().unwrap_or(Vec2::ZERO);
        out.push(WorldTriangle {
            v: i.map(|k| m.transform_point3(mesh.positions[k])),
            n: i.map(|k| (nm * mesh.normals[k]).normalize_or_zero()),
            uv: i.map(uv),
            lightmap_uv: i.map(lightmap_uv),
            material: o.material,
        });
    }
}
