//! Light injection (CloudLight §4.1 step 2): the direct irradiance on each leaf's surface,
//! from every light with ray-traced shadows ([`crate::direct_light`], the kernel the
//! reference tracer and the light-map gather share), turned into the radiance the leaf
//! sends toward each of the six axis directions.
//!
//! Voxels are **anisotropic** (six directions, [`VoxelRadiance`]): a wall lit on one side
//! sends its light only toward that side and hides what lies behind it only along its
//! normal, which is what keeps light from leaking through walls one or two voxels thick
//! (an isotropic voxel sends a lit wall's light out of both faces). It costs 6× the memory
//! of one value.
//!
//! Surfaces are two-sided: each leaf's two sides (its mean normal and the opposite) are lit
//! separately, and a side's radiosity B = ρ/π · E leaves toward the directions it faces.

use cloudlight_scenes::Scene;
use glam::Vec3;
use rayon::prelude::*;

use super::octree::Octree;
use crate::bvh::SceneBvh;
use crate::direct_light::DirectLight;
use crate::sampling::Rng;

/// The six axis directions of anisotropic voxels, in this order: +X, −X, +Y, −Y, +Z, −Z.
pub const DIRECTIONS: [Vec3; 6] = [
    Vec3::X,
    Vec3::NEG_X,
    Vec3::Y,
    Vec3::NEG_Y,
    Vec3::Z,
    Vec3::NEG_Z,
];

/// What a voxel sends toward each of [`DIRECTIONS`] and how much it hides along it.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct VoxelRadiance {
    /// Radiance leaving through the voxel's face toward each direction, averaged over the
    /// face (so premultiplied by the coverage), W·m⁻²·sr⁻¹ per channel.
    pub radiance: [Vec3; 6],
    /// Opacity along each direction, [0, 1]: the share of the face the surfaces cover.
    pub opacity: [f32; 6],
}

/// Injection settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InjectSettings {
    /// Light samples per side of a leaf (emissive surfaces are sampled; punctual lights
    /// are exact).
    pub samples: u32,
    /// Seed of the emitter samples.
    pub seed: u64,
}

impl Default for InjectSettings {
    fn default() -> Self {
        InjectSettings {
            samples: 4,
            seed: 1,
        }
    }
}

/// The leaves' direct light.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Injection {
    /// Per leaf (in the octree's leaf order).
    pub leaves: Vec<VoxelRadiance>,
    /// Per leaf, the direct irradiance on its two sides (along its normal, then against
    /// it), W·m⁻².
    pub direct: Vec<[Vec3; 2]>,
    /// Shadow-ray samples taken (light samples × sides × leaves).
    pub samples: u64,
}

/// Injects the direct light of `scene` at `t_s` (its BVH at that time: `bvh`) into the
/// leaves of `octree`; `indirect`, per leaf and side, is irradiance gathered by the previous
/// bounce, added before reflection (multi-bounce).
pub fn inject(
    octree: &Octree,
    scene: &Scene,
    bvh: &SceneBvh,
    t_s: f64,
    indirect: Option<&[[Vec3; 2]]>,
    settings: &InjectSettings,
) -> Injection {
    let leaves = octree.leaves();
    let light = DirectLight::new(scene, bvh, t_s);
    let samples = settings.samples.max(1);
    let voxel_m = octree.grid.voxel_m(octree.grid.depth);
    let face_m2 = voxel_m * voxel_m;
    let (direct, out): (Vec<[Vec3; 2]>, Vec<VoxelRadiance>) = leaves
        .surfaces
        .par_iter()
        .enumerate()
        .map(|(i, s)| {
            let n = s.side_normal();
            let mut rng = Rng::new(settings.seed, leaves.codes[i]);
            let sides = [n, -n];
            let e: [Vec3; 2] = sides.map(|side| {
                if !light.any() {
                    return Vec3::ZERO;
                }
                let x = s.position + side * light.eps();
                (0..samples)
                    .map(|_| light.irradiance(x, side, &mut rng))
                    .sum::<Vec3>()
                    / samples as f32
            });
            let gathered = indirect.and_then(|g| g.get(i)).copied().unwrap_or_default();
            let radiosity = [0, 1].map(|k| s.albedo / std::f32::consts::PI * (e[k] + gathered[k]));
            let coverage = s.area_m2 / face_m2;
            let mut v = VoxelRadiance::default();
            for (d, dir) in DIRECTIONS.iter().enumerate() {
                let c = dir.dot(n);
                // The side facing `dir` sends its radiosity through the face, weighted by
                // the surface's projected area.
                let facing = if c >= 0.0 { radiosity[0] } else { radiosity[1] };
                v.radiance[d] = facing * (coverage * c.abs());
                v.opacity[d] = (coverage * c.abs()).min(1.0);
            }
            (e, v)
        })
        .unzip();
    Injection {
        samples: u64::from(samples) * 2 * leaves.len() as u64,
        leaves: out,
        direct,
    }
}
