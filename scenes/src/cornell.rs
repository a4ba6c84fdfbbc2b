//! The Cornell box, from the measured Cornell data (the geometry of `cornell_box.obj` as
//! shipped by tinyobjloader and Embree, converted from millimeters to meters), with the
//! reflectances and light radiance commonly used for it in physically based renderers
//! (white 0.725/0.71/0.68, red 0.63/0.065/0.05, green 0.14/0.45/0.091, light 17/12/4 W·m⁻²·sr⁻¹).
//!
//! The data's two floor patches under the blocks (coplanar with the floor and hidden inside
//! the blocks) are left out: 32 triangles. The front is open; the camera is the data's
//! (278, 273, −800) mm looking down +z with a 39.3° vertical field of view.

use glam::{Affine3A, Vec3};

use crate::model::{Camera, CameraPath, Material, Mesh, Motion, Object, Scene};

const MM: f32 = 0.001;

fn v(x: f32, y: f32, z: f32) -> Vec3 {
    Vec3::new(x, y, z) * MM
}

fn quads(quads: &[[Vec3; 4]]) -> Mesh {
    let mut m = Mesh::default();
    for q in quads {
        m.push_quad(q[0], q[1], q[2], q[3]);
    }
    m
}

/// Material indices of the Cornell box.
pub mod materials {
    /// White walls, floor, ceiling and blocks.
    pub const WHITE: u32 = 0;
    /// The red (left, x ≈ 0.55 m) wall.
    pub const RED: u32 = 1;
    /// The green (right, x = 0) wall.
    pub const GREEN: u32 = 2;
    /// The ceiling light.
    pub const LIGHT: u32 = 3;
}

/// Center of the ceiling light, meters.
pub const LIGHT_CENTER: Vec3 = Vec3::new(0.278, 0.548, 0.2795);

/// The Cornell box. With `animated_light`, the light circles 0.12 m around its place on the
/// ceiling once every 8 scene seconds.
pub fn cornell(animated_light: bool) -> Scene {
    let materials = vec![
        Material::diffuse("white", Vec3::new(0.725, 0.71, 0.68)),
        Material::diffuse("red", Vec3::new(0.63, 0.065, 0.05)),
        Material::diffuse("green", Vec3::new(0.14, 0.45, 0.091)),
        Material {
            emission: Vec3::new(17.0, 12.0, 4.0),
            ..Material::diffuse("light", Vec3::splat(0.78))
        },
    ];
    let walls = quads(&[
        [
            v(552.8, 0.0, 0.0),
            v(0.0, 0.0, 0.0),
            v(0.0, 0.0, 559.2),
            v(549.6, 0.0, 559.2),
        ], // floor
        [
            v(556.0, 548.8, 0.0),
            v(556.0, 548.8, 559.2),
            v(0.0, 548.8, 559.2),
            v(0.0, 548.8, 0.0),
        ], // ceiling
        [
            v(549.6, 0.0, 559.2),
            v(0.0, 0.0, 559.2),
            v(0.0, 548.8, 559.2),
            v(556.0, 548.8, 559.2),
        ], // back
    ]);
    let green = quads(&[[
        v(0.0, 0.0, 559.2),
        v(0.0, 0.0, 0.0),
        v(0.0, 548.8, 0.0),
        v(0.0, 548.8, 559.2),
    ]]);
    let red = quads(&[[
        v(552.8, 0.0, 0.0),
        v(549.6, 0.0, 559.2),
        v(556.0, 548.8, 559.2),
        v(556.0, 548.8, 0.0),
    ]]);
    let short_block = quads(&[
        [
            v(130.0, 165.0, 65.0),
            v(82.0, 165.0, 225.0),
            v(240.0, 165.0, 272.0),
            v(290.0, 165.0, 114.0),
        ],
        [
            v(290.0, 0.0, 114.0),
            v(290.0, 165.0, 114.0),
            v(240.0, 165.0, 272.0),
            v(240.0, 0.0, 272.0),
        ],
        [
            v(130.0, 0.0, 65.0),
            v(130.0, 165.0, 65.0),
            v(290.0, 165.0, 114.0),
            v(290.0, 0.0, 114.0),
        ],
        [
            v(82.0, 0.0, 225.0),
            v(82.0, 165.0, 225.0),
            v(130.0, 165.0, 65.0),
            v(130.0, 0.0, 65.0),
        ],
        [
            v(240.0, 0.0, 272.0),
            v(240.0, 165.0, 272.0),
            v(82.0, 165.0, 225.0),
            v(82.0, 0.0, 225.0),
        ],
    ]);
    let tall_block = quads(&[
        [
            v(423.0, 330.0, 247.0),
            v(265.0, 330.0, 296.0),
            v(314.0, 330.0, 456.0),
            v(472.0, 330.0, 406.0),
        ],
        [
            v(423.0, 0.0, 247.0),
            v(423.0, 330.0, 247.0),
            v(472.0, 330.0, 406.0),
            v(472.0, 0.0, 406.0),
        ],
        [
            v(472.0, 0.0, 406.0),
            v(472.0, 330.0, 406.0),
            v(314.0, 330.0, 456.0),
            v(314.0, 0.0, 456.0),
        ],
        [
            v(314.0, 0.0, 456.0),
            v(314.0, 330.0, 456.0),
            v(265.0, 330.0, 296.0),
            v(265.0, 0.0, 296.0),
        ],
        [
            v(265.0, 0.0, 296.0),
            v(265.0, 330.0, 296.0),
            v(423.0, 330.0, 247.0),
            v(423.0, 0.0, 247.0),
        ],
    ]);
    // The light quad, centered on the origin of its own frame (130 × 105 mm, facing down).
    let (hx, hz) = (0.065, 0.0525);
    let light = quads(&[[
        Vec3::new(hx, 0.0, -hz),
        Vec3::new(hx, 0.0, hz),
        Vec3::new(-hx, 0.0, hz),
        Vec3::new(-hx, 0.0, -hz),
    ]]);
    let light_motion = if animated_light {
        Motion::Orbit {
            center: LIGHT_CENTER,
            axis: Vec3::Y,
            radius: 0.12,
            period_s: 8.0,
            phase: 0.0,
        }
    } else {
        Motion::Static(Affine3A::from_translation(LIGHT_CENTER))
    };
    let object = |name: &str, mesh: Mesh, material: u32| Object {
        name: name.into(),
        mesh,
        material,
        motion: Motion::identity(),
    };
    let camera = Camera {
        position: v(278.0, 273.0, -800.0),
        target: v(278.0, 273.0, 0.0),
        up: Vec3::Y,
        fov_y_rad: 39.3f32.to_radians(),
    };
    Scene {
        name: if animated_light {
            "cornell-animated".into()
        } else {
            "cornell".into()
        },
        materials,
        objects: vec![
            object("walls", walls, materials::WHITE),
            object("green_wall", green, materials::GREEN),
            object("red_wall", red, materials::RED),
            object("short_block", short_block, materials::WHITE),
            object("tall_block", tall_block, materials::WHITE),
            Object {
                name: "light".into(),
                mesh: light,
                material: materials::LIGHT,
                motion: light_motion,
            },
        ],
        lights: Vec::new(),
        cameras: vec![CameraPath {
            name: "front".into(),
            camera,
            motion: Motion::identity(),
        }],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn geometry_matches_the_measured_data() {
        let s = cornell(false);
        assert_eq!(s.triangle_count(), 32);
        let (lo, hi) = s.bounds_at(0.0);
        assert!((lo - Vec3::ZERO).abs().max_element() < 1e-6, "{lo}");
        assert!(
            (hi - Vec3::new(0.556, 0.5488, 0.5592)).abs().max_element() < 1e-6,
            "{hi}"
        );
        // Light: 130 mm × 105 mm at y = 548 mm, facing down, radiance (17, 12, 4).
        let light: Vec<_> = s
            .triangles_at(0.0)
            .into_iter()
            .filter(|t| t.material == materials::LIGHT)
            .collect();
        assert_eq!(light.len(), 2);
        let area: f32 = light
            .iter()
            .map(|t| 0.5 * (t.v[1] - t.v[0]).cross(t.v[2] - t.v[0]).length())
            .sum();
        assert!((area - 0.130 * 0.105).abs() < 1e-7);
        assert!(
            light
                .iter()
                .all(|t| t.n[0].y < -0.999 && (t.v[0].y - 0.548).abs() < 1e-6)
        );
        let power = s.emitted_power_w();
        let expect = Vec3::new(17.0, 12.0, 4.0) * std::f32::consts::PI * 0.130 * 0.105;
        assert!(
            (power - expect).abs().max_element() < 1e-5,
            "{power} vs {expect}"
        );
    }

    #[test]
    fn every_surface_faces_into_the_box() {
        let s = cornell(false);
        let center = Vec3::new(0.278, 0.274, 0.28);
        for t in s.triangles_at(0.0) {
            let c = (t.v[0] + t.v[1] + t.v[2]) / 3.0;
            let name = &s.materials[t.material as usize].name;
            let is_block =
                c.y > 0.001 && c.y < 0.5 && c.x > 0.05 && c.x < 0.5 && c.z > 0.05 && c.z < 0.5;
            if !is_block {
                assert!(
                    t.n[0].dot(center - c) > 0.0,
                    "{name} triangle at {c} faces out"
                );
            }
        }
    }

    #[test]
    fn the_animated_light_moves_and_keeps_its_size() {
        let s = cornell(true);
        let at = |t| -> Vec3 {
            let tris = s.triangles_at(t);
            let l: Vec<_> = tris
                .iter()
                .filter(|x| x.material == materials::LIGHT)
                .collect();
            (l[0].v[0] + l[0].v[1] + l[0].v[2] + l[1].v[0] + l[1].v[1] + l[1].v[2]) / 6.0
        };
        let (a, b) = (at(0.0), at(2.0));
        assert!((a - b).length() > 0.1, "{a} {b}");
        assert!((a.y - 0.548).abs() < 1e-6 && (b.y - 0.548).abs() < 1e-6);
        assert!((at(8.0) - a).length() < 1e-5, "one turn per 8 s");
        assert!(s.is_animated() && !cornell(false).is_animated());
    }
}
