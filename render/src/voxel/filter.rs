//! The octree filter (CloudLight §4.1 step 2): each inner voxel's anisotropic radiance and
//! opacity from its 2×2×2 children. Along a direction the children form four columns of
//! two; each column is composited front to back as seen from that direction (the child
//! nearer the viewer hides part of the one behind: c = c_front + (1 − α_front)·c_back,
//! α = α_front + (1 − α_front)·α_back), and the parent is the mean of the four columns. A
//! missing child is empty (no radiance, no opacity).

use super::inject::VoxelRadiance;
use super::octree::Octree;

/// Composites one parent from its children (each with its position bits x | y << 1 | z << 2
/// inside the parent).
fn parent_of(children: &[(u8, VoxelRadiance)]) -> VoxelRadiance {
    let mut slots = [VoxelRadiance::default(); 8];
    for (bits, v) in children {
        slots[*bits as usize & 7] = *v;
    }
    let mut out = VoxelRadiance::default();
    for d in 0..6 {
        let axis = d / 2;
        // Seen from +axis, the child with the bit set is in front.
        let front_bit = if d % 2 == 0 { 1 } else { 0 };
        let (a, b) = ((axis + 1) % 3, (axis + 2) % 3);
        for column in 0..4u8 {
            let base = ((column & 1) << a) | ((column >> 1) << b);
            let front = &slots[(base | (front_bit << axis)) as usize];
            let back = &slots[(base | ((1 - front_bit) << axis)) as usize];
            let t = 1.0 - front.opacity[d];
            out.radiance[d] += (front.radiance[d] + back.radiance[d] * t) * 0.25;
            out.opacity[d] += (front.opacity[d] + back.opacity[d] * t) * 0.25;
        }
    }
    out
}

/// Every level's voxels from the leaves' (`leaves`, in the octree's leaf order): root
/// first, aligned with `octree.levels`.
pub fn filter(octree: &Octree, leaves: Vec<VoxelRadiance>) -> Vec<Vec<VoxelRadiance>> {
    let depth = octree.levels.len().saturating_sub(1);
    let mut out: Vec<Vec<VoxelRadiance>> = vec![Vec::new(); depth + 1];
    out[depth] = leaves;
    for level in (0..depth).rev() {
        let parents = &octree.levels[level];
        let below = &octree.levels[level + 1];
        let values = &out[level + 1];
        let filtered: Vec<VoxelRadiance> = (0..parents.len())
            .map(|i| {
                let range = parents.first_child[i] as usize..parents.first_child[i + 1] as usize;
                let children: Vec<(u8, VoxelRadiance)> = range
                    .map(|c| ((below.codes[c] & 7) as u8, values[c]))
                    .collect();
                parent_of(&children)
            })
            .collect();
        out[level] = filtered;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    fn voxel(radiance: f32, opacity: f32) -> VoxelRadiance {
        VoxelRadiance {
            radiance: [Vec3::splat(radiance); 6],
            opacity: [opacity; 6],
        }
    }

    #[test]
    fn the_front_child_hides_the_back_one_along_each_direction() {
        // Children at x = 1 (bits 1) and x = 0 (bits 0) in the same column.
        let children = [(1u8, voxel(2.0, 0.5)), (0u8, voxel(4.0, 1.0))];
        let p = parent_of(&children);
        // Seen from +X the x = 1 child is in front: 2 + 0.5·4 = 4 over one column of four.
        assert!((p.radiance[0].x - 4.0 / 4.0).abs() < 1e-6);
        assert!((p.opacity[0] - 1.0 / 4.0).abs() < 1e-6);
        // From −X the opaque x = 0 child is in front and hides the other.
        assert!((p.radiance[1].x - 4.0 / 4.0).abs() < 1e-6);
        assert!((p.opacity[1] - 1.0 / 4.0).abs() < 1e-6);
        // From ±Y and ±Z the two lie in different columns: a mean.
        for d in 2..6 {
            assert!((p.radiance[d].x - 6.0 / 4.0).abs() < 1e-6, "{d}");
            assert!((p.opacity[d] - 1.5 / 4.0).abs() < 1e-6, "{d}");
        }
        // Eight opaque children: an opaque parent with their radiance.
        let full: Vec<(u8, VoxelRadiance)> = (0..8).map(|b| (b, voxel(3.0, 1.0))).collect();
        let p = parent_of(&full);
        for d in 0..6 {
            assert!((p.radiance[d].x - 3.0).abs() < 1e-6 && (p.opacity[d] - 1.0).abs() < 1e-6);
        }
    }
}
