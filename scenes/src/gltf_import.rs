//! glTF 2.0 import: node transforms, triangle meshes, base-colour factors and textures,
//! emissive materials, `KHR_lights_punctual` lights and perspective cameras.
//!
//! Units. glTF positions are meters. `KHR_lights_punctual` gives point and spot intensity
//! in candela (lm/sr) and directional illuminance in lux (lm/m²); they become watts with
//! the photometric constant 683 lm/W (the luminous efficacy at 555 nm, the conversion the
//! spec's units imply for a monochromatic reference): radiant intensity = cd / 683 × colour,
//! point power = 4π × that, spot power = that × the cone's solid angle 2π(1 − cos outer),
//! sun irradiance = lux / 683 × colour. Emissive factors (× `KHR_materials_emissive_strength`)
//! are taken as radiance in W·m⁻²·sr⁻¹.
//!
//! Every problem is an error naming the file and what is wrong; malformed files never panic
//! (the reader is also guarded, since `gltf` unwraps some optional fields itself).

use std::path::Path;

use glam::{Affine3A, Mat4, Vec2, Vec3};

use crate::SceneError;
use crate::model::{
    Camera, CameraPath, Light, LightKind, Material, Mesh, Motion, Object, Scene, SunPath, Texture,
};

/// Deepest node hierarchy accepted (a cycle exceeds any bound).
const MAX_NODE_DEPTH: usize = 256;
/// Most node visits (instancing can multiply nodes).
const MAX_NODE_VISITS: usize = 10_000_000;

/// Photometric constant: lumens per watt.
pub const LUMENS_PER_WATT: f32 = 683.0;

fn err(path: &Path, message: impl Into<String>) -> SceneError {
    SceneError::Gltf {
        file: path.display().to_string(),
        message: message.into(),
    }
}

/// Loads a glTF 2.0 file (`.gltf` with its buffers and images, or `.glb`).
pub fn load(path: &Path) -> Result<Scene, SceneError> {
    match std::panic::catch_unwind(|| load_unguarded(path)) {
        Ok(r) => r,
        Err(p) => {
            let what = p
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| p.downcast_ref::<String>().cloned());
            Err(err(
                path,
                format!(
                    "malformed file (the glTF reader failed: {})",
                    what.unwrap_or_else(|| "no message".into())
                ),
            ))
        }
    }
}

fn srgb_to_linear(c: u8) -> f32 {
    let x = c as f32 / 255.0;
    if x <= 0.04045 {
        x / 12.92
    } else {
        ((x + 0.055) / 1.055).powf(2.4)
    }
}

/// An image as a linear-RGB texture (none for formats without 8-bit channels); `total` counts
/// the texels of every texture so far, each and all bounded.
fn texture(
    path: &Path,
    data: &gltf::image::Data,
    total: &mut u64,
) -> Result<Option<Texture>, SceneError> {
    use gltf::image::Format;
    let channels = match data.format {
        Format::R8 => 1,
        Format::R8G8 => 2,
        Format::R8G8B8 => 3,
        Format::R8G8B8A8 => 4,
        _ => return Ok(None),
    };
    let texels = data.width as u64 * data.height as u64;
    *total += texels;
    if texels > MAX_TEXTURE_TEXELS || *total > MAX_TOTAL_TEXELS {
        return Err(err(
            path,
            format!(
                "a {}×{} texture brings the textures to {} texels, more than {MAX_TEXTURE_TEXELS} for one or {MAX_TOTAL_TEXELS} for all",
                data.width, data.height, total
            ),
        ));
    }
    if data.pixels.len() as u64 != texels * channels as u64 || texels == 0 {
        return Ok(None);
    }
    let texels = data
        .pixels
        .chunks_exact(channels)
        .map(|p| {
            let g = |i: usize| srgb_to_linear(p[i.min(channels - 1)]);
            Vec3::new(g(0), g(1), g(2))
        })
        .collect::<Vec<_>>();
    Ok(Some(Texture {
        width: data.width,
        height: data.height,
        texels,
    }))
}

/// Largest glTF file, buffer or image file read (a 24 GiB machine holds a scene of this many
/// bytes several times over, as vertices, BVH and textures).
const MAX_FILE_BYTES: u64 = 2 << 30;

/// A file the importer may read: a regular file (never a device such as `/dev/zero`) of at
/// most [`MAX_FILE_BYTES`], and at least `declared` bytes when its size is declared.
fn check_file(gltf: &Path, file: &Path, declared: Option<u64>) -> Result<(), SceneError> {
    let meta = match std::fs::metadata(file) {
        Ok(m) => m,
        // Not found under its literal name (e.g. a percent-encoded URI): the importer resolves
        // it and says what is missing.
        Err(e) if e.kind() == std::io::ErrorKind::NotFound && file != gltf => return Ok(()),
        Err(e) => return Err(err(gltf, format!("cannot read {}: {e}", file.display()))),
    };
    if !meta.is_file() {
        return Err(err(
            gltf,
            format!("{} is not a regular file", file.display()),
        ));
    }
    if meta.len() > MAX_FILE_BYTES {
        return Err(err(
            gltf,
            format!(
                "{} has {} bytes, more than a scene file may have ({MAX_FILE_BYTES})",
                file.display(),
                meta.len()
            ),
        ));
    }
    if let Some(n) = declared
        && meta.len() < n
    {
        return Err(err(
            gltf,
            format!(
                "{} has {} bytes but the file declares {n}",
                file.display(),
                meta.len()
            ),
        ));
    }
    Ok(())
}

/// Checks the file and every external buffer and image it names before the importer reads
/// them.
fn check_sources(path: &Path) -> Result<(), SceneError> {
    check_file(path, path, None)?;
    let doc = gltf::Gltf::open(path).map_err(|e| err(path, e.to_string()))?;
    let dir = path.parent().unwrap_or(Path::new("."));
    let external = |uri: &str| (!uri.starts_with("data:")).then(|| dir.join(uri));
    for b in doc.buffers() {
        if let gltf::buffer::Source::Uri(uri) = b.source()
            && let Some(file) = external(uri)
        {
            check_file(path, &file, Some(b.length() as u64))?;
        }
    }
    for i in doc.images() {
        if let gltf::image::Source::Uri { uri, .. } = i.source()
            && let Some(file) = external(uri)
        {
            check_file(path, &file, None)?;
        }
    }
    Ok(())
}

fn load_unguarded(path: &Path) -> Result<Scene, SceneError> {
    check_sources(path)?;
    let (doc, buffers, images) = gltf::import(path).map_err(|e| match e {
        gltf::Error::Io(io) => err(
            path,
            format!("cannot read the file or a buffer/image it references: {io}"),
        ),
        other => err(path, other.to_string()),
    })?;
    let mut scene = Scene {
        name: path.file_name().map_or_else(
            || path.display().to_string(),
            |n| n.to_string_lossy().into_owned(),
        ),
        materials: Vec::new(),
        objects: Vec::new(),
        lights: Vec::new(),
        cameras: Vec::new(),
    };
    let mut texels = 0u64;
    for m in doc.materials() {
        let pbr = m.pbr_metallic_roughness();
        let [r, g, b, _] = pbr.base_color_factor();
        let tex = match pbr
            .base_color_texture()
            .and_then(|t| images.get(t.texture().source().index()))
        {
            Some(image) => texture(path, image, &mut texels)?,
            None => None,
        };
        let strength = m.emissive_strength().unwrap_or(1.0);
        scene.materials.push(Material {
            name: m.name().unwrap_or("unnamed").to_string(),
            albedo: Vec3::new(r, g, b).clamp(Vec3::ZERO, Vec3::ONE),
            texture: tex,
            emission: Vec3::from(m.emissive_factor()) * strength,
        });
    }
    let default_material = scene.materials.len() as u32;
    scene
        .materials
        .push(Material::diffuse("default", Vec3::splat(0.8)));

    let gltf_scene = doc
        .default_scene()
        .or_else(|| doc.scenes().next())
        .ok_or_else(|| err(path, "the file has no scene"))?;
    let mut stack: Vec<(gltf::Node, Mat4, usize)> =
        gltf_scene.nodes().map(|n| (n, Mat4::IDENTITY, 0)).collect();
    let mut visited = 0usize;
    let mut budget = Budget::default();
    while let Some((node, parent, depth)) = stack.pop() {
        visited += 1;
        if depth > MAX_NODE_DEPTH || visited > MAX_NODE_VISITS {
            return Err(err(
                path,
                format!(
                    "node {} lies deeper than {MAX_NODE_DEPTH} levels: the node hierarchy is cyclic",
                    node.index()
                ),
            ));
        }
        let world = parent * Mat4::from_cols_array_2d(&node.transform().matrix());
        if !world.is_finite() {
            return Err(err(
                path,
                format!("node {} has a non-finite transform", node.index()),
            ));
        }
        if let Some(mesh) = node.mesh() {
            for (pi, prim) in mesh.primitives().enumerate() {
                if prim.mode() != gltf::mesh::Mode::Triangles {
                    continue; // points and lines carry no surface
                }
                let where_ = || {
                    format!(
                        "mesh {} primitive {pi}",
                        mesh.name().map_or(mesh.index().to_string(), String::from)
                    )
                };
                let mut m = read_primitive(path, &prim, &buffers, &where_)?;
                budget.take(path, &m, &where_)?;
                if m.normals.is_empty() {
                    m.normals = flat_normals(&m);
                }
                let material = prim
                    .material()
                    .index()
                    .map_or(default_material, |i| i as u32);
                scene.objects.push(Object {
                    name: where_(),
                    mesh: m,
                    material,
                    motion: Motion::Static(Affine3A::from_mat4(world)),
                });
            }
        }
        if let Some(light) = node.light() {
            scene.lights.push(punctual(path, &light, world)?);
        }
        if let Some(cam) = node.camera()
            && let gltf::camera::Projection::Perspective(p) = cam.projection()
        {
            let eye = world.transform_point3(Vec3::ZERO);
            let forward = world
                .transform_vector3(Vec3::NEG_Z)
                .normalize_or(Vec3::NEG_Z);
            let up = world.transform_vector3(Vec3::Y).normalize_or(Vec3::Y);
            scene.cameras.push(CameraPath {
                name: cam.name().unwrap_or("camera").to_string(),
                camera: Camera {
                    position: eye,
                    target: eye + forward,
                    up,
                    fov_y_rad: p.yfov(),
                },
                motion: Motion::identity(),
            });
        }
        for child in node.children() {
            stack.push((child, world, depth + 1));
        }
    }
    if scene.cameras.is_empty() {
        scene.cameras.push(default_camera(&scene));
    }
    Ok(scene)
}

/// Most elements (vertices, indices) one accessor may hold: a sparse accessor without a
/// buffer declares its count freely, and 2³² − 1 of them would fill 48 GB.
const MAX_ACCESSOR_ELEMENTS: usize = 64 << 20;
/// Most triangles and vertices a file may give the scene in all (instancing multiplies
/// them): about 10 GB with the BVH and the client's copies.
const MAX_SCENE_TRIANGLES: usize = 64 << 20;
/// Most texels of one texture, and of all textures together (12 bytes each as linear RGB).
const MAX_TEXTURE_TEXELS: u64 = 8192 * 8192;
const MAX_TOTAL_TEXELS: u64 = 4 * MAX_TEXTURE_TEXELS;

/// What the file has given the scene so far, bounded.
#[derive(Default)]
struct Budget {
    triangles: usize,
    vertices: usize,
}

impl Budget {
    fn take(
        &mut self,
        path: &Path,
        m: &Mesh,
        where_: &dyn Fn() -> String,
    ) -> Result<(), SceneError> {
        self.triangles += m.indices.len();
        self.vertices += m.positions.len();
        if self.triangles > MAX_SCENE_TRIANGLES || self.vertices > MAX_SCENE_TRIANGLES {
            return Err(err(
                path,
                format!(
                    "at {}, the scene has {} triangles and {} vertices, more than {MAX_SCENE_TRIANGLES} (are meshes instanced too often?)",
                    where_(),
                    self.triangles,
                    self.vertices
                ),
            ));
        }
        Ok(())
    }
}

/// An accessor's elements collected into a vector whose size is checked first.
fn collect_bounded<T>(
    path: &Path,
    what: &str,
    where_: &dyn Fn() -> String,
    iter: impl ExactSizeIterator<Item = T>,
) -> Result<Vec<T>, SceneError> {
    let n = iter.len();
    let too_many = || {
        err(
            path,
            format!(
                "{}: {what} has {n} elements, more than an accessor may have ({MAX_ACCESSOR_ELEMENTS})",
                where_()
            ),
        )
    };
    if n > MAX_ACCESSOR_ELEMENTS {
        return Err(too_many());
    }
    let mut v = Vec::new();
    v.try_reserve_exact(n).map_err(|_| too_many())?;
    v.extend(iter);
    Ok(v)
}

/// One triangle primitive's mesh: positions (finite), indices (in range), normals and both
/// UV sets when they match the positions (flat normals are made later when absent).
fn read_primitive(
    path: &Path,
    prim: &gltf::Primitive<'_>,
    buffers: &[gltf::buffer::Data],
    where_: &dyn Fn() -> String,
) -> Result<Mesh, SceneError> {
    let reader = prim.reader(|b| buffers.get(b.index()).map(|d| &d.0[..]));
    let positions = reader
        .read_positions()
        .ok_or_else(|| err(path, format!("{} has no positions", where_())))?;
    let positions: Vec<Vec3> =
        collect_bounded(path, "POSITION", where_, positions.map(Vec3::from))?;
    if positions.iter().any(|p| !p.is_finite()) {
        return Err(err(
            path,
            format!("{} has non-finite vertex positions", where_()),
        ));
    }
    let n = positions.len();
    let indices: Vec<u32> = match reader.read_indices() {
        Some(i) => collect_bounded(path, "indices", where_, i.into_u32())?,
        None => (0..n as u32).collect(),
    };
    if let Some(bad) = indices.iter().find(|&&i| i as usize >= n) {
        return Err(err(
            path,
            format!("{}: index {bad} is out of range ({n} vertices)", where_()),
        ));
    }
    let normals = match reader.read_normals() {
        Some(r) => collect_bounded(path, "NORMAL", where_, r.map(Vec3::from))?,
        None => Vec::new(),
    };
    let uvs = match reader.read_tex_coords(0) {
        Some(r) => collect_bounded(path, "TEXCOORD_0", where_, r.into_f32().map(Vec2::from))?,
        None => Vec::new(),
    };
    let lightmap_uvs = match reader.read_tex_coords(1) {
        Some(r) => collect_bounded(path, "TEXCOORD_1", where_, r.into_f32().map(Vec2::from))?,
        None => Vec::new(),
    };
    Ok(Mesh {
        positions,
        normals: matching(normals, n),
        uvs: matching(uvs, n),
        lightmap_uvs: matching(lightmap_uvs, n),
        indices: indices
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect(),
    })
}

/// A per-vertex attribute when it has one value per vertex, else none.
fn matching<T>(v: Vec<T>, n: usize) -> Vec<T> {
    if v.len() == n { v } else { Vec::new() }
}

fn flat_normals(m: &Mesh) -> Vec<Vec3> {
    let mut n = vec![Vec3::ZERO; m.positions.len()];
    for t in &m.indices {
        let [a, b, c] = t.map(|i| m.positions[i as usize]);
        let f = (b - a).cross(c - a);
        for i in t {
            n[*i as usize] += f;
        }
    }
    n.into_iter().map(|v| v.normalize_or(Vec3::Y)).collect()
}

fn punctual(
    path: &Path,
    light: &gltf::khr_lights_punctual::Light,
    world: Mat4,
) -> Result<Light, SceneError> {
    use gltf::khr_lights_punctual::Kind;
    let color = Vec3::from(light.color());
    let intensity = light.intensity();
    if !intensity.is_finite() || intensity < 0.0 || !color.is_finite() {
        return Err(err(
            path,
            format!("light {} has an invalid intensity or colour", light.index()),
        ));
    }
    let position = world.transform_point3(Vec3::ZERO);
    let axis = world
        .transform_vector3(Vec3::NEG_Z)
        .normalize_or(Vec3::NEG_Y);
    let radiometric = color * intensity / LUMENS_PER_WATT;
    let name = light.name().unwrap_or("light").to_string();
    let at = Motion::Static(Affine3A::from_translation(position));
    Ok(match light.kind() {
        Kind::Point => Light {
            name,
            kind: LightKind::Point,
            power_w: radiometric * 4.0 * std::f32::consts::PI,
            motion: at,
            sun_path: None,
        },
        Kind::Spot {
            outer_cone_angle, ..
        } => {
            let solid_angle = std::f32::consts::TAU * (1.0 - outer_cone_angle.cos());
            Light {
                name,
                kind: LightKind::Spot {
                    direction: axis,
                    cone_angle_rad: outer_cone_angle,
                },
                power_w: radiometric * solid_angle,
                motion: at,
                sun_path: None,
            }
        }
        Kind::Directional => Light {
            name,
            kind: LightKind::Directional {
                irradiance_w_m2: radiometric,
            },
            power_w: Vec3::ZERO,
            motion: Motion::identity(),
            // A fixed sun along the node's −z: a day so long it does not move.
            sun_path: Some(SunPath::fixed(axis)),
        },
    })
}

fn default_camera(scene: &Scene) -> CameraPath {
    let (lo, hi) = scene.bounds_at(0.0);
    let (lo, hi) = if lo.is_finite() && hi.is_finite() {
        (lo, hi)
    } else {
        (Vec3::ZERO, Vec3::ONE)
    };
    let center = (lo + hi) * 0.5;
    let radius = (hi - lo).length().max(1e-3);
    CameraPath {
        name: "default".into(),
        camera: Camera {
            position: center + Vec3::new(0.0, 0.3, 1.0).normalize() * radius,
            target: center,
            up: Vec3::Y,
            fov_y_rad: 50f32.to_radians(),
        },
        motion: Motion::identity(),
    }
}
