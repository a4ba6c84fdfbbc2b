//! `city:N`: a procedural town of about N triangles, the stand-in for the paper's game
//! levels. Deterministic: the same N gives the same town.
//!
//! The town is a grid of 24 m lots separated by 8 m streets. Each lot holds one of: a hollow
//! house with 0.3 m walls, a door opening, a window and a roof (an interior lit through its
//! openings: light leaks and thin walls), an arch, a tower with setbacks, or a row of thin
//! street-lamp poles. A sun follows a day cycle; street lamps are point lights. Lots are
//! added until the triangle count reaches N, so the total is N plus at most one lot.

use glam::{Affine3A, Vec3};

use crate::model::{
    Camera, CameraPath, Light, LightKind, Material, Mesh, Motion, Object, Scene, SunPath,
};

const LOT: f32 = 24.0;
const STREET: f32 = 8.0;
const PITCH: f32 = LOT + STREET;
/// Most street lamps that become point lights.
pub const MAX_LAMPS: usize = 16;

/// Material indices of the town.
pub mod materials {
    /// Ground and streets.
    pub const GROUND: u32 = 0;
    /// Walls.
    pub const WALL: u32 = 1;
    /// Roofs.
    pub const ROOF: u32 = 2;
    /// Poles and arches.
    pub const STONE: u32 = 3;
    /// Red-painted walls.
    pub const RED: u32 = 4;
}

/// A stable hash of two integers to [0, 1).
fn hash01(a: u32, b: u32) -> f32 {
    let mut x = (a as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (b as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
    x ^= x >> 31;
    x = x.wrapping_mul(0xBF58_476D_1CE4_E5B9);
    x ^= x >> 29;
    (x >> 40) as f32 / (1u64 << 24) as f32
}

struct Builder {
    meshes: [Mesh; 5],
    lamps: Vec<Vec3>,
}

impl Builder {
    fn tris(&self) -> usize {
        self.meshes.iter().map(Mesh::triangle_count).sum()
    }

    fn cuboid(&mut self, material: u32, min: Vec3, max: Vec3) {
        self.meshes[material as usize].push_box(min, max);
    }

    /// A hollow house: four walls (a door opening at the front, a window at the back) and a roof.
    fn house(&mut self, o: Vec3, size: f32, height: f32, wall_material: u32) {
        let t = 0.3;
        let (x0, z0, x1, z1) = (o.x, o.z, o.x + size, o.z + size);
        let m = wall_material;
        // Back wall with a window opening (built from the pieces around it); plain side walls.
        let (wy0, wy1) = (height * 0.4, height * 0.7);
        let mid = (x0 + x1) * 0.5;
        let (za, zb) = (z1 - t, z1);
        self.cuboid(m, Vec3::new(x0, 0.0, za), Vec3::new(mid - 1.0, height, zb));
        self.cuboid(m, Vec3::new(mid + 1.0, 0.0, za), Vec3::new(x1, height, zb));
        self.cuboid(
            m,
            Vec3::new(mid - 1.0, 0.0, za),
            Vec3::new(mid + 1.0, wy0, zb),
        );
        self.cuboid(
            m,
            Vec3::new(mid - 1.0, wy1, za),
            Vec3::new(mid + 1.0, height, zb),
        );
        self.cuboid(
            m,
            Vec3::new(x0, 0.0, z0 + t),
            Vec3::new(x0 + t, height, z1 - t),
        );
        self.cuboid(
            m,
            Vec3::new(x1 - t, 0.0, z0 + t),
            Vec3::new(x1, height, z1 - t),
        );
        // Front wall with a door opening 1.2 m wide and 2.2 m high.
        let mid = (x0 + x1) * 0.5;
        self.cuboid(
            m,
            Vec3::new(x0, 0.0, z0),
            Vec3::new(mid - 0.6, height, z0 + t),
        );
        self.cuboid(
            m,
            Vec3::new(mid + 0.6, 0.0, z0),
            Vec3::new(x1, height, z0 + t),
        );
        self.cuboid(
            m,
            Vec3::new(mid - 0.6, 2.2, z0),
            Vec3::new(mid + 0.6, height, z0 + t),
        );
        // Roof slab with an overhang.
        self.cuboid(
            materials::ROOF,
            Vec3::new(x0 - 0.5, height, z0 - 0.5),
            Vec3::new(x1 + 0.5, height + 0.25, z1 + 0.5),
        );
    }

    fn arch(&mut self, o: Vec3, span: f32, height: f32) {
        let w = 1.0;
        self.cuboid(materials::STONE, o, o + Vec3::new(w, height, w));
        self.cuboid(
            materials::STONE,
            o + Vec3::new(span, 0.0, 0.0),
            o + Vec3::new(span + w, height, w),
        );
        self.cuboid(
            materials::STONE,
            o + Vec3::new(0.0, height, 0.0),
            o + Vec3::new(span + w, height + w, w),
        );
    }

    fn tower(&mut self, o: Vec3, size: f32, height: f32) {
        let mut lo = o;
        let mut s = size;
        let mut h = height * 0.5;
        for _ in 0..3 {
            self.cuboid(materials::WALL, lo, lo + Vec3::new(s, h, s));
            lo += Vec3::new(s * 0.15, h, s * 0.15);
            s *= 0.7;
            h *= 0.5;
        }
    }

    fn poles(&mut self, o: Vec3, count: u32) {
        for i in 0..count {
            let p = o + Vec3::new(i as f32 * 5.0, 0.0, 0.0);
            self.cuboid(materials::STONE, p, p + Vec3::new(0.1, 5.0, 0.1));
            self.lamps.push(p + Vec3::new(0.05, 5.2, 0.05));
        }
    }

    fn lot(&mut self, ix: u32, iz: u32) {
        let o = Vec3::new(ix as f32 * PITCH, 0.0, iz as f32 * PITCH);
        // Street strips along the lot's two low edges, a little above the ground.
        self.meshes[materials::GROUND as usize].push_quad(
            o + Vec3::new(-STREET, 0.01, -STREET),
            o + Vec3::new(LOT, 0.01, -STREET),
            o + Vec3::new(LOT, 0.01, 0.0),
            o + Vec3::new(-STREET, 0.01, 0.0),
        );
        let r = hash01(ix, iz);
        let size = 8.0 + 10.0 * hash01(iz, ix ^ 77);
        let height = 3.0 + 9.0 * hash01(ix ^ 13, iz ^ 29);
        let inset = o + Vec3::new((LOT - size) * 0.5, 0.0, (LOT - size) * 0.5);
        match (r * 10.0) as u32 {
            0..=4 => self.house(
                inset,
                size,
                height,
                if r < 0.15 {
                    materials::RED
                } else {
                    materials::WALL
                },
            ),
            5 | 6 => self.tower(inset, size, height * 3.0),
            7 => self.arch(inset, size * 0.8, height),
            _ => self.poles(o + Vec3::new(2.0, 0.0, 2.0), 4),
        }
    }
}

/// A town of about `n` triangles (see the module documentation).
pub fn city(n: usize) -> Scene {
    let mut b = Builder {
        meshes: Default::default(),
        lamps: Vec::new(),
    };
    let side = ((n as f32 / 70.0).sqrt().ceil() as u32).max(1);
    // The ground under the whole grid.
    let extent = side as f32 * PITCH;
    b.meshes[materials::GROUND as usize].push_quad(
        Vec3::new(-STREET, 0.0, -STREET),
        Vec3::new(-STREET, 0.0, extent),
        Vec3::new(extent, 0.0, extent),
        Vec3::new(extent, 0.0, -STREET),
    );
    'grid: for iz in 0..u32::MAX {
        for ix in 0..side {
            if b.tris() >= n {
                break 'grid;
            }
            b.lot(ix, iz);
        }
    }
    let materials = vec![
        Material::diffuse("ground", Vec3::new(0.3, 0.3, 0.28)),
        Material::diffuse("wall", Vec3::new(0.7, 0.68, 0.62)),
        Material::diffuse("roof", Vec3::new(0.45, 0.2, 0.15)),
        Material::diffuse("stone", Vec3::new(0.5, 0.5, 0.5)),
        Material::diffuse("red", Vec3::new(0.6, 0.1, 0.08)),
    ];
    let names = ["ground", "walls", "roofs", "stone", "red walls"];
    let objects = b
        .meshes
        .into_iter()
        .enumerate()
        .filter(|(_, m)| m.triangle_count() > 0)
        .map(|(i, mesh)| Object {
            name: names[i].into(),
            mesh,
            material: i as u32,
            motion: Motion::identity(),
        })
        .collect();
    let mut lights = vec![Light {
        name: "sun".into(),
        kind: LightKind::Directional {
            irradiance_w_m2: Vec3::new(1000.0, 950.0, 880.0),
        },
        power_w: Vec3::ZERO,
        motion: Motion::identity(),
        sun_path: Some(SunPath {
            fixed: None,
            day_length_s: 600.0,
            max_elevation_rad: 1.1,
            phase: 0.2,
        }),
    }];
    let step = (b.lamps.len() / MAX_LAMPS).max(1);
    for (i, p) in b.lamps.iter().step_by(step).take(MAX_LAMPS).enumerate() {
        lights.push(Light {
            name: format!("lamp{i}"),
            kind: LightKind::Point,
            power_w: Vec3::new(100.0, 85.0, 60.0),
            motion: Motion::Static(Affine3A::from_translation(*p)),
            sun_path: None,
        });
    }
    let street = |z: f32, phase_x: f32| CameraPath {
        name: format!("street {z}"),
        camera: Camera {
            position: Vec3::new(-STREET * 0.5, 1.7, z),
            target: Vec3::new(-STREET * 0.5 + 10.0, 1.7, z + 1.0),
            up: Vec3::Y,
            fov_y_rad: 60f32.to_radians(),
        },
        motion: Motion::Path {
            keys: vec![
                (0.0, Vec3::new(phase_x, 0.0, 0.0)),
                (60.0, Vec3::new(phase_x + extent * 0.5, 0.0, 0.0)),
            ],
        },
    };
    Scene {
        name: format!("city:{n}"),
        materials,
        objects,
        lights,
        cameras: vec![
            street(-STREET * 0.5, 0.0),
            street(PITCH - STREET * 0.5, 20.0),
            street(2.0 * PITCH - STREET * 0.5, 40.0),
        ],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn triangle_count_is_about_n_over_the_whole_range() {
        for n in [1_000usize, 20_000, 250_000] {
            let s = city(n);
            let t = s.triangle_count();
            assert!(t >= n && t < n + 400, "city:{n} has {t} triangles");
        }
    }

    #[test]
    fn is_deterministic_and_has_sun_and_lamps() {
        assert_eq!(city(5000), city(5000));
        let s = city(20_000);
        assert!(matches!(s.lights[0].kind, LightKind::Directional { .. }));
        assert!(s.lights.len() > 1 && s.lights.len() <= 1 + MAX_LAMPS);
        assert!(s.is_animated(), "the sun moves");
        assert!(
            s.triangles_at(0.0)
                .iter()
                .all(|t| t.v.iter().all(|v| v.is_finite()))
        );
    }
}
