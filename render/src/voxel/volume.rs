//! What the frame renderer looks voxel irradiance up in: one level of the gathered octree
//! as a dense 3D texture ([`VoxelVolume`]), sampled per pixel with trilinear filtering
//! (`lookup.wgsl`, [`super::pass::VoxelPass`]).
//!
//! Each voxel's two sides become an ambient cube (Mitchell et al. 2006): the face toward
//! axis direction d holds the irradiance of the side whose normal points along d, weighted
//! by that normal's squared component along d, and the weight itself. A pixel of normal n
//! takes, for each axis, the face n points along, as the filtered weighted sum over the
//! filtered weight (so empty cells and faces a surface does not have fall out instead of
//! darkening), and blends the axes by n's squared components. A voxel of a wall thus lights
//! only the pixels on its own side.
//!
//! The texture is `Rgba16Float`, one slab of N³ per face direction (with an empty slice
//! between slabs, so filtering never mixes two faces), values divided by a scale that puts
//! the brightest at 2¹⁴ (any light unit fits f16). Voxels that hold only their parent's
//! value (below the voxels that gathered, or below the deepest level of an update that has
//! arrived) take the filtered lookup of the level above instead, so coarse light shows
//! smooth rather than as blocks.

use glam::{UVec3, Vec3};
use half::f16;

use super::inject::DIRECTIONS;
use super::morton;
use super::octree::Octree;

/// Where the brightest value lands in f16.
const TOP: f32 = 16384.0;

/// The deepest level a volume is made of by default: 64³ cells, 12.8 MB of texture.
pub const DEFAULT_VOLUME_LEVEL: u32 = 6;

/// The values of level `to` when only the levels down to `from` are trusted (a receiver
/// partway through an update): voxels below `from` take their ancestor's, sides matched.
pub fn values_at(octree: &Octree, levels: &[Vec<[Vec3; 2]>], from: u32, to: u32) -> Vec<[Vec3; 2]> {
    let depth = octree.levels.len() - 1;
    let to = (to as usize).min(depth);
    let from = (from as usize).min(to);
    let mut current: Vec<[Vec3; 2]> = levels[from].clone();
    for l in from + 1..=to {
        current = octree
            .parent_links(l)
            .iter()
            .map(|link| link.onto(current[link.parent as usize]))
            .collect();
    }
    current
}

/// One level's irradiance as a dense ambient-cube texture.
#[derive(Clone, Debug, PartialEq)]
pub struct VoxelVolume {
    /// Low corner of the grid, meters.
    pub origin: Vec3,
    /// Side of the grid, meters.
    pub size_m: f32,
    /// Cells per axis (N).
    pub cells: u32,
    /// What a texel's value is multiplied by to give irradiance, W·m⁻².
    pub scale: f32,
    /// `f16` RGBA texels, x fastest, then y, then z over six slabs of N + 1 slices (one
    /// per entry of [`DIRECTIONS`], the last slice of each empty): weighted irradiance
    /// (rgb) and weight (a).
    pub texels: Vec<[f16; 4]>,
}

impl VoxelVolume {
    /// Slices along z: six slabs of N + 1.
    pub fn depth_slices(&self) -> u32 {
        6 * (self.cells + 1)
    }

    /// The volume of `level` of `octree` (its values per level in `values`, trusted down to
    /// `complete`).
    ///
    /// A voxel whose value is its parent's (the gather inherits below the voxels that
    /// traced cones, and levels below `complete` have not arrived) would show as a block of
    /// one colour; it takes instead the filtered lookup of the level above at its surface,
    /// level by level from the root, so light is as smooth as the cells that gathered it.
    pub fn new(
        octree: &Octree,
        values: &[Vec<[Vec3; 2]>],
        complete: u32,
        level: u32,
    ) -> VoxelVolume {
        let level = level.min(octree.depth());
        let mut shown = values[0].clone();
        let mut volume = VoxelVolume::of_level(octree, 0, &shown);
        for l in 1..=level as usize {
            let surfaces = &octree.levels[l].surfaces;
            let trusted = l <= complete as usize;
            shown = octree
                .parent_links(l)
                .iter()
                .enumerate()
                .map(|(i, link)| {
                    let own = values[l][i];
                    let inherited =
                        !trusted || own == link.onto(values[l - 1][link.parent as usize]);
                    if inherited {
                        let (p, n) = (surfaces[i].position, surfaces[i].side_normal());
                        [volume.irradiance(p, n), volume.irradiance(p, -n)]
                    } else {
                        own
                    }
                })
                .collect();
            volume = VoxelVolume::of_level(octree, l as u32, &shown);
        }
        volume
    }

    /// The volume of `level` holding `here` (per voxel of the level).
    fn of_level(octree: &Octree, level: u32, here: &[[Vec3; 2]]) -> VoxelVolume {
        let n = octree.grid.cells(level);
        let max = here
            .iter()
            .flat_map(|v| [v[0].max_element(), v[1].max_element()])
            .filter(|x| x.is_finite())
            .fold(0.0f32, f32::max);
        let scale = if max > 0.0 { max / TOP } else { 1.0 };
        let slab = (n as usize).pow(2) * (n as usize + 1);
        let mut texels = vec![[f16::ZERO; 4]; 6 * slab];
        let voxels = &octree.levels[level as usize];
        for ((code, surface), value) in voxels.codes.iter().zip(&voxels.surfaces).zip(here) {
            let c = morton::decode(*code);
            let m = surface.side_normal();
            let at = c.x as usize + n as usize * (c.y as usize + n as usize * c.z as usize);
            for (d, dir) in DIRECTIONS.iter().enumerate() {
                let along = m.dot(*dir);
                if along <= 0.0 {
                    // The face toward `dir` belongs to the other side, if it is not edge-on.
                    let w = along * along;
                    if w > 0.0 {
                        texels[d * slab + at] = texel(value[1] / scale, w);
                    }
                } else {
                    texels[d * slab + at] = texel(value[0] / scale, along * along);
                }
            }
        }
        VoxelVolume {
            origin: octree.grid.origin,
            size_m: octree.grid.size_m,
            cells: n,
            scale,
            texels,
        }
    }

    /// The texels' bytes (an `Rgba16Float` 3D texture's, little-endian).
    pub fn bytes(&self) -> &[u8] {
        bytemuck::cast_slice(&self.texels)
    }

    fn fetch(&self, d: usize, c: UVec3) -> [f32; 4] {
        let n = self.cells as usize;
        let i = d * n * n * (n + 1) + c.x as usize + n * (c.y as usize + n * c.z as usize);
        self.texels[i].map(f16::to_f32)
    }

    /// Trilinear filtering of face `d` at `p`, as a GPU sampler with clamp-to-edge does:
    /// (weighted irradiance, weight).
    fn filtered(&self, d: usize, p: Vec3) -> [f32; 4] {
        let n = self.cells as f32;
        let u = ((p - self.origin) / self.size_m * n - 0.5)
            .clamp(Vec3::splat(-0.5), Vec3::splat(n - 0.5));
        let base = u.floor();
        let f = u - base;
        let mut out = [0.0f32; 4];
        for corner in 0..8u32 {
            let bit = UVec3::new(corner & 1, (corner >> 1) & 1, (corner >> 2) & 1);
            let c = (base + bit.as_vec3())
                .clamp(Vec3::ZERO, Vec3::splat(n - 1.0))
                .as_uvec3();
            let w = (0..3)
                .map(|k| if bit[k] == 1 { f[k] } else { 1.0 - f[k] })
                .product::<f32>();
            // The slab's empty slices beyond z = 0 and z = N − 1 (the first slab clamps to
            // its own first slice, as the sampler clamps at the texture's edge).
            let z = base.z + bit.z as f32;
            let empty = z > n - 1.0 || (z < 0.0 && d > 0);
            if !empty {
                let t = self.fetch(d, c);
                for k in 0..4 {
                    out[k] += w * t[k];
                }
            }
        }
        out
    }

    /// Irradiance at `p` on a surface of unit normal `n`, W·m⁻² (what the GPU lookup
    /// computes, up to its filtering precision).
    pub fn irradiance(&self, p: Vec3, n: Vec3) -> Vec3 {
        let (mut e, mut weight) = (Vec3::ZERO, 0.0);
        for axis in 0..3 {
            let d = 2 * axis + usize::from(n[axis] < 0.0);
            let t = self.filtered(d, p);
            if t[3] > 1e-4 {
                let w = n[axis] * n[axis];
                e += Vec3::new(t[0], t[1], t[2]) / t[3] * w;
                weight += w;
            }
        }
        if weight > 0.0 {
            e / weight * self.scale
        } else {
            Vec3::ZERO
        }
    }
}

fn texel(e: Vec3, w: f32) -> [f16; 4] {
    let e = e.max(Vec3::ZERO);
    [
        f16::from_f32(e.x * w),
        f16::from_f32(e.y * w),
        f16::from_f32(e.z * w),
        f16::from_f32(w),
    ]
}
