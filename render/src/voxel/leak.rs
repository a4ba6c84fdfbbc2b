//! Light leaks through walls thinner than a voxel (CloudLight §4.1: "a single voxel is
//! unable to represent the different illumination conditions on opposite sides of a very
//! thin wall that bisects it"), measured: a closed unit box split by a thin wall at x = ½,
//! a bulb in the left half ([`thin_wall_scene`]). No light reaches the right half; what the
//! voxels give it is leak ([`leak`]).

use cloudlight_scenes::{Light, LightKind, Material, Mesh, Motion, Object, Scene};
use glam::{Affine3A, Vec3};

use super::cone::Gathered;
use super::octree::{Octree, VoxelSurface};

/// The unit box split by a closed wall `wall_m` thick at x = ½, a 1 W bulb at
/// (0.25, 0.6, 0.45), everything grey (albedo ½).
pub fn thin_wall_scene(wall_m: f32) -> Scene {
    let mut shell = Mesh::default();
    shell.push_box(Vec3::ZERO, Vec3::ONE);
    let mut wall = Mesh::default();
    let h = wall_m / 2.0;
    wall.push_box(Vec3::new(0.5 - h, 0.0, 0.0), Vec3::new(0.5 + h, 1.0, 1.0));
    let object = |name: &str, mesh: Mesh| Object {
        name: name.into(),
        mesh,
        material: 0,
        motion: Motion::identity(),
    };
    Scene {
        name: "thin-wall".into(),
        materials: vec![Material::diffuse("grey", Vec3::splat(0.5))],
        objects: vec![object("box", shell.flipped()), object("wall", wall)],
        lights: vec![Light {
            name: "bulb".into(),
            kind: LightKind::Point,
            power_w: Vec3::ONE,
            motion: Motion::Static(Affine3A::from_translation(Vec3::new(0.25, 0.6, 0.45))),
            sun_path: None,
        }],
        cameras: Vec::new(),
    }
}

/// The side of a voxel (0: along its side normal, 1: against it) facing the point `toward`.
pub fn side_facing(s: &VoxelSurface, toward: Vec3) -> usize {
    usize::from((toward - s.position).dot(s.side_normal()) < 0.0)
}

/// Σ E·A (red) over the leaves' sides facing the dark half's centre, over the same for the
/// lit half, in a [`thin_wall_scene`] (the wall's own voxels count each face for its half).
pub fn leak(octree: &Octree, gathered: &Gathered) -> f64 {
    let (lit_c, dark_c) = (Vec3::new(0.25, 0.5, 0.5), Vec3::new(0.75, 0.5, 0.5));
    let (mut lit, mut dark) = (0.0f64, 0.0f64);
    for (s, e) in octree.leaves().surfaces.iter().zip(gathered.leaves()) {
        let x = s.position.x;
        let area = f64::from(s.area_m2);
        if x < 0.51 {
            lit += f64::from(e[side_facing(s, lit_c)].x) * area;
        }
        if x > 0.49 {
            dark += f64::from(e[side_facing(s, dark_c)].x) * area;
        }
    }
    if lit > 0.0 { dark / lit } else { 0.0 }
}
