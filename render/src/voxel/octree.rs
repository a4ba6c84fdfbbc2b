//! The sparse voxel octree: per level, the occupied cells' Morton codes in order, each inner
//! node's first child in the next level, and each voxel's surface (area, albedo, normal,
//! opacity). Memory exists only where geometry is; a node's children (its brick, up to 2×2×2
//! voxels) are contiguous. Inner levels aggregate their children exactly, so the root holds
//! the whole scene's area.

use glam::Vec3;

use super::voxelize::{Fragment, Grid};

/// What a voxel holds about the surfaces in it.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct VoxelSurface {
    /// Surface area inside the voxel, m².
    pub area_m2: f32,
    /// Area-weighted mean albedo.
    pub albedo: Vec3,
    /// Centroid of the surface inside the voxel, meters.
    pub position: Vec3,
    /// Area-weighted mean normal (unit, or zero where opposite-facing surfaces cancel;
    /// surfaces are two-sided).
    pub normal: Vec3,
    /// Isotropic opacity in [0, 1]: the surface area over the voxel's face area, clamped (a
    /// plane across the voxel blocks it; a sliver barely does).
    pub opacity: f32,
}

/// Bytes a voxel's geometry takes: its code (8), first child (4) and surface (44).
pub const BYTES_PER_VOXEL: u64 = 8 + 4 + 44;

/// One level of the octree.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Level {
    /// Morton codes of the occupied cells, ascending.
    pub codes: Vec<u64>,
    /// Per voxel, what its surfaces are.
    pub surfaces: Vec<VoxelSurface>,
    /// Inner levels: index of each voxel's first child in the next level, and one more
    /// entry (the next level's length), so voxel `i`'s children are
    /// `first_child[i]..first_child[i + 1]`. Empty at the leaves.
    pub first_child: Vec<u32>,
}

impl Level {
    /// Voxels at this level.
    pub fn len(&self) -> usize {
        self.codes.len()
    }

    /// Whether the level holds no voxel.
    pub fn is_empty(&self) -> bool {
        self.codes.is_empty()
    }

    /// The index of the voxel with `code`, if occupied.
    pub fn find(&self, code: u64) -> Option<usize> {
        self.codes.binary_search(&code).ok()
    }
}

/// A sparse voxel octree over a [`Grid`]: `levels[0]` is the root, `levels[grid.depth]`
/// the leaves.
#[derive(Clone, Debug, PartialEq)]
pub struct Octree {
    /// The cube it subdivides.
    pub grid: Grid,
    /// Root first.
    pub levels: Vec<Level>,
}

fn surface_of(f: &Fragment, voxel_m: f32) -> VoxelSurface {
    let area = f.area_m2.max(0.0);
    let inv = if area > 0.0 { 1.0 / area } else { 0.0 };
    VoxelSurface {
        area_m2: area,
        albedo: f.albedo_area * inv,
        position: f.centroid_area * inv,
        normal: f.normal_area.normalize_or_zero(),
        opacity: (area / (voxel_m * voxel_m)).clamp(0.0, 1.0),
    }
}

impl VoxelSurface {
    /// The normal of the voxel's first side (the second faces the opposite way): its mean
    /// normal, or +Y where its surfaces' normals cancel.
    pub fn side_normal(&self) -> Vec3 {
        if self.normal.length_squared() > 0.5 {
            self.normal
        } else {
            Vec3::Y
        }
    }
}

impl Octree {
    /// The octree of leaf fragments (sorted by code, one per leaf, from
    /// [`super::voxelize::fragments`] at `grid.depth`).
    pub fn from_leaves(grid: Grid, leaves: &[Fragment]) -> Octree {
        let depth = grid.depth as usize;
        let mut levels = vec![Level::default(); depth + 1];
        let mut current: Vec<Fragment> = leaves.to_vec();
        // The children offsets of the level being built, found while building the one below.
        let mut first_child: Vec<u32> = Vec::new();
        for level in (0..=depth).rev() {
            let voxel_m = grid.voxel_m(level as u32);
            levels[level] = Level {
                codes: current.iter().map(|f| f.code).collect(),
                surfaces: current.iter().map(|f| surface_of(f, voxel_m)).collect(),
                first_child: std::mem::take(&mut first_child),
            };
            if level == 0 {
                break;
            }
            // Parents: runs of equal code >> 3 (children of one node are contiguous).
            let mut parents: Vec<Fragment> = Vec::new();
            for (i, f) in current.iter().enumerate() {
                let code = f.code >> 3;
                match parents.last_mut() {
                    Some(p) if p.code == code => p.add(f),
                    _ => {
                        parents.push(Fragment { code, ..*f });
                        first_child.push(i as u32);
                    }
                }
            }
            first_child.push(current.len() as u32);
            current = parents;
        }
        Octree { grid, levels }
    }

    /// Levels below the root.
    pub fn depth(&self) -> u32 {
        self.grid.depth
    }

    /// The leaf level.
    pub fn leaves(&self) -> &Level {
        &self.levels[self.levels.len() - 1]
    }

    /// Bytes each level takes, root first.
    pub fn bytes_per_level(&self) -> Vec<u64> {
        self.levels
            .iter()
            .map(|l| l.len() as u64 * BYTES_PER_VOXEL)
            .collect()
    }

    /// Bytes the whole octree takes.
    pub fn bytes(&self) -> u64 {
        self.bytes_per_level().iter().sum()
    }

    /// The same octree without its deepest `levels` levels (the level above becomes the
    /// leaves).
    pub fn coarsened(mut self, levels: u32) -> Octree {
        let depth = self.grid.depth.saturating_sub(levels);
        self.levels.truncate(depth as usize + 1);
        if let Some(leaves) = self.levels.last_mut() {
            leaves.first_child.clear();
        }
        self.grid = self.grid.with_depth(depth);
        self
    }
}
