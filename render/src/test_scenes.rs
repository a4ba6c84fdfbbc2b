//! Small scenes built in code for the kernels' tests.

use cloudlight_scenes::{Material, Mesh, Motion, Object, Scene};

/// A static object.
pub(crate) fn object(name: &str, mesh: Mesh, material: u32) -> Object {
    Object {
        name: name.into(),
        mesh,
        material,
        motion: Motion::identity(),
    }
}

/// A scene of `objects` without lights or cameras.
pub(crate) fn bare(name: &str, materials: Vec<Material>, objects: Vec<Object>) -> Scene {
    Scene {
        name: name.into(),
        materials,
        objects,
        lights: Vec::new(),
        cameras: Vec::new(),
    }
}
