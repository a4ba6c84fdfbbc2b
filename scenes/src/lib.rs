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
}
