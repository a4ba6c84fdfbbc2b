//! The sparse voxel octree: per level, the occupied cells' Morton codes in order, each inner
//! node's first child in the next level, and each voxel's surface (area, albedo, normal,
//! opacity). Memory exists only where geometry is; a node's children (its brick, up to 2×2×2
//! voxels) are contiguous. Inner levels aggregate their children exactly, so the root holds
//! the whole scene's area.

use glam::{UVec3, Vec3};

use super::voxelize::{Fragment, Grid};

/// What a voxel holds about the surfaces in it.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
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
    /// How much the surfaces in the voxel agree in orientation: the length of the
    /// area-weighted mean of their (sign-canonical) normals, 1 for a plane, less at a
    /// corner or on a curve. The gather refines below voxels that are not flat.
    pub flatness: f32,
}

/// Bytes a voxel's geometry takes: its code (8), first child (4) and surface (48).
pub const BYTES_PER_VOXEL: u64 = 8 + 4 + 48;

/// One level of the octree.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
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
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
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
        flatness: (f.normal_area.length() * inv).clamp(0.0, 1.0),
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

/// A voxel's parent, and whether the voxel's two sides are its parent's swapped (their
/// side normals disagree): how per-side values pass between levels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ParentLink {
    /// Index of the parent in the level above.
    pub parent: u32,
    /// Whether the sides swap.
    pub flipped: bool,
}

impl ParentLink {
    /// Per-side values of one voxel as seen from the other (the relation is symmetric).
    pub fn onto<T: Copy>(&self, v: [T; 2]) -> [T; 2] {
        if self.flipped { [v[1], v[0]] } else { v }
    }
}

impl Octree {
    /// For each voxel of `level` (above 0), its [`ParentLink`].
    pub fn parent_links(&self, level: usize) -> Vec<ParentLink> {
        let (parents, below) = (&self.levels[level - 1], &self.levels[level]);
        let mut out = Vec::with_capacity(below.len());
        for (p, parent) in parents.surfaces.iter().enumerate() {
            let n = parent.side_normal();
            for child in &below.surfaces
                [parents.first_child[p] as usize..parents.first_child[p + 1] as usize]
            {
                out.push(ParentLink {
                    parent: p as u32,
                    flipped: n.dot(child.side_normal()) < 0.0,
                });
            }
        }
        out
    }
}

/// Levels up to this one are located through a dense table (4 bytes per cell: 8 MiB at
/// level 7); deeper voxels are found by descending from their ancestor at this level.
pub const DENSE_LEVELS: u32 = 7;

/// Finds the voxel of any cell in constant time: a dense table of voxel indices per level
/// down to [`DENSE_LEVELS`], then at most `depth − DENSE_LEVELS` steps down through each
/// node's (at most eight, contiguous) children. Binary search over the sorted codes cost
/// two cache-missing searches per cone sample.
#[derive(Clone, Debug, Default)]
pub struct Locator {
    /// Per level (root first, down to the dense limit), per cell in x-fastest order, the
    /// voxel's index in its level, or `u32::MAX` where the cell is empty.
    dense: Vec<Vec<u32>>,
}

const EMPTY: u32 = u32::MAX;

impl Locator {
    /// The tables of `octree`.
    pub fn new(octree: &Octree) -> Locator {
        let dense_depth = octree.depth().min(DENSE_LEVELS);
        let dense = (0..=dense_depth)
            .map(|level| {
                let cells = octree.grid.cells(level) as usize;
                let mut table = vec![EMPTY; cells * cells * cells];
                for (i, &code) in octree.levels[level as usize].codes.iter().enumerate() {
                    let c = super::morton::decode(code);
                    table[c.x as usize + cells * (c.y as usize + cells * c.z as usize)] = i as u32;
                }
                table
            })
            .collect();
        Locator { dense }
    }

    /// Bytes the tables take.
    pub fn bytes(&self) -> u64 {
        self.dense.iter().map(|t| 4 * t.len() as u64).sum()
    }

    /// The index (in `octree.levels[level]`) of the voxel at `cell` of `level`, if occupied;
    /// `cell` must lie inside the grid.
    pub fn find(&self, octree: &Octree, level: u32, cell: UVec3) -> Option<usize> {
        let dense_level = (self.dense.len() as u32 - 1).min(level);
        let up = level - dense_level;
        let top = cell >> up;
        let cells = octree.grid.cells(dense_level) as usize;
        let table = &self.dense[dense_level as usize];
        let mut i = table[top.x as usize + cells * (top.y as usize + cells * top.z as usize)];
        if i == EMPTY {
            return None;
        }
        for l in dense_level..level {
            let shift = level - l - 1;
            let b = (cell >> shift) & UVec3::ONE;
            let bits = u64::from(b.x | b.y << 1 | b.z << 2);
            let parent = &octree.levels[l as usize];
            let below = &octree.levels[l as usize + 1];
            let range = parent.first_child[i as usize] as usize
                ..parent.first_child[i as usize + 1] as usize;
            i = range
                .into_iter()
                .find(|&c| below.codes[c] & 7 == bits)
                .map(|c| c as u32)?;
        }
        Some(i as usize)
    }
}
