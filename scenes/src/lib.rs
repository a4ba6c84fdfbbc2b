//! The scene model (meshes, diffuse materials, lights in watts, cameras, animation as a
//! function of scene time), the built-in Cornell box and the procedural `city:N`.
//!
//! Kernels get a [`Scene`] and a scene time and ask it for world-space triangles and light
//! states; nothing here knows about actors, queues or sockets. [`load`] also reads glTF 2.0.

pub use glam;

pub mod check;
pub mod city;
pub mod cornell;
pub mod gltf_import;
pub mod model;

pub use model::{
    Camera, CameraPath, Light, LightKind, LightState, Material, Mesh, Motion, Object, Scene,
    SunPath, Texture, View, WorldTriangle,
};

/// Smallest and largest `N` accepted by `city:N`.
pub const CITY_RANGE: (usize, usize) = (1_000, 20_000_000);

/// Why a scene could not be made.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SceneError {
    /// The name is none of the built-in scenes.
    #[error(
        "unknown scene `{0}` (built-in: cornell, cornell-animated, city:N; or a .gltf/.glb file)"
    )]
    Unknown(String),
    /// A glTF file could not be loaded.
    #[error("{file}: {message}")]
    Gltf {
        /// The file.
        file: String,
        /// What is wrong.
        message: String,
    },
    /// The scene loaded but holds values no kernel can use (non-finite or far geometry,
    /// degenerate cameras, negative light).
    #[error("{scene}: {message}")]
    Invalid {
        /// The scene's name or file.
        scene: String,
        /// Every problem found.
        message: String,
    },
    /// `city:N` with a bad N.
    #[error("`{0}`: N must be a whole number from {min} to {max}", min = CITY_RANGE.0, max = CITY_RANGE.1)]
    CitySize(String),
}

/// A scene by name (`cornell`, `cornell-animated`, `city:N`) or path to a glTF 2.0 file
/// (`.gltf` or `.glb`), checked ([`check::check`]): finite, within
/// [`check::MAX_EXTENT_M`], with cameras that see.
pub fn load(spec: &str) -> Result<Scene, SceneError> {
    let lower = spec.to_ascii_lowercase();
    let scene = if lower.ends_with(".gltf") || lower.ends_with(".glb") {
        gltf_import::load(std::path::Path::new(spec))?
    } else {
        builtin(spec)?
    };
    check::check(&scene).map_err(|message| SceneError::Invalid {
        scene: spec.to_string(),
        message,
    })?;
    Ok(scene)
}

/// A view of `scene` at `time_s` from a spec: the index of one of its camera paths, or
/// `px,py,pz:tx,ty,tz[:fov_deg]` (eye and target in meters, up +y, vertical field of view
/// in degrees, default 45), checked ([`check::check_camera`]).
pub fn camera(scene: &Scene, spec: &str, time_s: f64) -> Result<Camera, String> {
    if let Ok(i) = spec.trim().parse::<usize>() {
        return scene.cameras.get(i).map(|c| c.at(time_s)).ok_or_else(|| {
            format!(
                "scene `{}` has {} camera paths; camera {i} is none of them",
                scene.name,
                scene.cameras.len()
            )
        });
    }
    let err = || format!("camera `{spec}`: expected an index or `px,py,pz:tx,ty,tz[:fov_deg]`");
    let parts: Vec<&str> = spec.split(':').collect();
    if !(2..=3).contains(&parts.len()) {
        return Err(err());
    }
    let point = |s: &str| -> Result<glam::Vec3, String> {
        let v: Vec<f32> = s
            .split(',')
            .map(|x| x.trim().parse::<f32>())
            .collect::<Result<_, _>>()
            .map_err(|_| err())?;
        <[f32; 3]>::try_from(v)
            .map(glam::Vec3::from_array)
            .map_err(|_| err())
    };
    let fov: f32 = parts
        .get(2)
        .map_or(Ok(45.0), |f| f.trim().parse().map_err(|_| err()))?;
    let camera = Camera {
        position: point(parts[0])?,
        target: point(parts[1])?,
        up: glam::Vec3::Y,
        fov_y_rad: fov.to_radians(),
    };
    check::check_camera(&camera).map_err(|e| format!("camera `{spec}`: {e}"))?;
    Ok(camera)
}

/// A built-in scene by name: `cornell`, `cornell-animated` or `city:N`.
pub fn builtin(name: &str) -> Result<Scene, SceneError> {
    match name {
        "cornell" => Ok(cornell::cornell(false)),
        "cornell-animated" => Ok(cornell::cornell(true)),
        _ => match name.strip_prefix("city:") {
            Some(n) => match n.replace('_', "").parse::<usize>() {
                Ok(n) if (CITY_RANGE.0..=CITY_RANGE.1).contains(&n) => Ok(city::city(n)),
                _ => Err(SceneError::CitySize(name.to_string())),
            },
            None => Err(SceneError::Unknown(name.to_string())),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builtin_names() {
        assert_eq!(builtin("cornell").unwrap().name, "cornell");
        assert_eq!(builtin("city:1_000").unwrap().name, "city:1000");
        assert!(matches!(builtin("city:10"), Err(SceneError::CitySize(_))));
        assert!(matches!(builtin("city:x"), Err(SceneError::CitySize(_))));
        assert!(matches!(builtin("sponza"), Err(SceneError::Unknown(_))));
    }

    #[test]
    fn cameras_by_index_or_eye_and_target() {
        let scene = builtin("cornell").unwrap();
        assert_eq!(camera(&scene, "0", 0.0).unwrap(), scene.cameras[0].at(0.0));
        let c = camera(&scene, " 1, 2,3 : 0,2,0 : 60 ", 0.0).unwrap();
        assert_eq!(c.position, glam::Vec3::new(1.0, 2.0, 3.0));
        assert_eq!(c.target, glam::Vec3::new(0.0, 2.0, 0.0));
        assert!((c.fov_y_rad - 60f32.to_radians()).abs() < 1e-6);
        assert_eq!(
            camera(&scene, "0,1,3:0,1,0", 0.0).unwrap().fov_y_rad,
            45f32.to_radians()
        );
        for bad in [
            "7",
            "",
            "0,1,3",
            "0,1,3:0,1",
            "0,1,3:0,1,0:45:1",
            "0,1,3:0,1,3",
            "0,1,3:0,1,0:0",
            "0,1,3:0,1,0:180",
            "nan,1,3:0,1,0",
            "0,0,0:0,5,0",
            "a,b,c:0,0,0",
        ] {
            assert!(camera(&scene, bad, 0.0).is_err(), "{bad:?}");
        }
        assert!(
            camera(&scene, "7", 0.0)
                .unwrap_err()
                .contains("has 1 camera paths")
        );
    }
}
