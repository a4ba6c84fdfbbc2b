//! Voxelization: every triangle's exact share of every leaf cell it crosses (CloudLight
//! §4.1 step 1). A triangle is scanned over the cells of its dominant projection; per cell
//! column the plane's depth range gives the one to three cells to clip it against
//! ([`super::clip`]), so the work follows the triangle's area, not its bounding box. The
//! shares are sorted by Morton code and merged, so a leaf's surface area, mean albedo and
//! mean normal are exact sums over the triangles in it.

use cloudlight_scenes::{Material, WorldTriangle};
use glam::{UVec3, Vec2, Vec3};
use rayon::prelude::*;

use super::clip::clip_triangle;
use super::morton;

/// The cube an octree subdivides: the scene's bounds, padded so that no surface lies on
/// its upper faces.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Grid {
    /// Lower corner, meters.
    pub origin: Vec3,
    /// Side of the cube, meters.
    pub size_m: f32,
    /// Levels below the root: the leaves are 2^depth per axis.
    pub depth: u32,
}

/// The deepest octree a Morton code holds.
pub const MAX_DEPTH: u32 = morton::BITS;

impl Grid {
    /// The cube around the box `lo..hi` with `depth` levels below the root.
    pub fn around(lo: Vec3, hi: Vec3, depth: u32) -> Grid {
        let (lo, hi) = if lo.cmple(hi).all() && lo.is_finite() && hi.is_finite() {
            (lo, hi)
        } else {
            (Vec3::ZERO, Vec3::ZERO)
        };
        let extent = (hi - lo).max_element();
        // Pad by a thousandth on every side (at least a micrometre of a metre-sized scene).
        let pad = (extent * 1e-3).max(1e-6 * extent.max(1.0));
        let size_m = extent + 2.0 * pad;
        let center = (lo + hi) * 0.5;
        Grid {
            origin: center - Vec3::splat(size_m * 0.5),
            size_m,
            depth: depth.min(MAX_DEPTH),
        }
    }

    /// Cells per axis at `level` (0: the root).
    pub fn cells(&self, level: u32) -> u32 {
        1 << level.min(self.depth)
    }

    /// Side of a voxel at `level`, meters.
    pub fn voxel_m(&self, level: u32) -> f32 {
        self.size_m / self.cells(level) as f32
    }

    /// The same cube with another depth.
    pub fn with_depth(&self, depth: u32) -> Grid {
        Grid {
            depth: depth.min(MAX_DEPTH),
            ..*self
        }
    }

    /// The lower corner of leaf cell `c`, meters.
    pub fn leaf_corner(&self, c: UVec3) -> Vec3 {
        self.origin + c.as_vec3() * self.voxel_m(self.depth)
    }
}

/// One leaf's share of the surfaces in it, summed over triangles.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Fragment {
    /// Morton code of the leaf.
    pub code: u64,
    /// Surface area inside the leaf, m².
    pub area_m2: f32,
    /// Albedo × area, m².
    pub albedo_area: Vec3,
    /// Centroid × area of the surface inside the leaf, m³.
    pub centroid_area: Vec3,
    /// Unit normal × area, each triangle's normal turned so that its largest component is
    /// positive (surfaces are two-sided; opposite faces of a thin wall must not cancel).
    pub normal_area: Vec3,
}

impl Fragment {
    pub(crate) fn add(&mut self, o: &Fragment) {
        self.area_m2 += o.area_m2;
        self.albedo_area += o.albedo_area;
        self.centroid_area += o.centroid_area;
        self.normal_area += o.normal_area;
    }
}

/// A normal turned so that its largest-magnitude component is positive.
fn canonical(n: Vec3) -> Vec3 {
    let a = n.abs();
    let k = if a.x >= a.y && a.x >= a.z {
        n.x
    } else if a.y >= a.z {
        n.y
    } else {
        n.z
    };
    if k < 0.0 { -n } else { n }
}

/// Barycentric coordinates of `p` in triangle `q` (normal `n`, unnormalised).
fn barycentric(q: &[Vec3; 3], n: Vec3, p: Vec3) -> Vec3 {
    let nn = n.length_squared().max(f32::MIN_POSITIVE);
    let b0 = (q[2] - q[1]).cross(p - q[1]).dot(n) / nn;
    let b1 = (q[0] - q[2]).cross(p - q[2]).dot(n) / nn;
    Vec3::new(b0, b1, 1.0 - b0 - b1)
}

/// Calls `emit(cell, area in cell units², centroid in cell units)` for every leaf cell of
/// `grid` that triangle `q` (in cell units) crosses.
fn scan_triangle(q: &[Vec3; 3], cells: u32, mut emit: impl FnMut(UVec3, f32, Vec3)) {
    let n = (q[1] - q[0]).cross(q[2] - q[0]);
    let finite = n.is_finite() && q.iter().all(|v| v.is_finite());
    if !finite || n.length_squared() <= 0.0 {
        return;
    }
    let a = n.abs();
    // k: the dominant axis; (i, j): the projection plane.
    let k = if a.x >= a.y && a.x >= a.z {
        0
    } else if a.y >= a.z {
        1
    } else {
        2
    };
    let (i, j) = ((k + 1) % 3, (k + 2) % 3);
    let lo = q[0].min(q[1]).min(q[2]);
    let hi = q[0].max(q[1]).max(q[2]);
    let last = (cells - 1) as f32;
    let range = |axis: usize| {
        (
            lo[axis].floor().clamp(0.0, last) as u32,
            hi[axis].floor().clamp(0.0, last) as u32,
        )
    };
    let ((i0, i1), (j0, j1)) = (range(i), range(j));
    // 2D edge functions of the projection, oriented inward.
    let p2 = q.map(|v| Vec2::new(v[i], v[j]));
    let area2 = (p2[1] - p2[0]).perp_dot(p2[2] - p2[0]);
    let sign = if area2 < 0.0 { -1.0 } else { 1.0 };
    let edges: [(Vec2, f32); 3] = std::array::from_fn(|e| {
        let (s, t) = (p2[e], p2[(e + 1) % 3]);
        let normal = Vec2::new(-(t - s).y, (t - s).x) * sign;
        (normal, -normal.dot(s))
    });
    let d = n.dot(q[0]);
    for ci in i0..=i1 {
        for cj in j0..=j1 {
            let center = Vec2::new(ci as f32 + 0.5, cj as f32 + 0.5);
            // Conservative reject: the square's most inward corner outside an edge.
            if edges
                .iter()
                .any(|(m, c)| m.dot(center) + c + 0.5 * (m.x.abs() + m.y.abs()) < 0.0)
            {
                continue;
            }
            // The plane's depth over the square, within the triangle's.
            let depth_at = |x: f32, y: f32| (d - n[i] * x - n[j] * y) / n[k];
            let (x0, y0) = (ci as f32, cj as f32);
            let corners = [
                depth_at(x0, y0),
                depth_at(x0 + 1.0, y0),
                depth_at(x0, y0 + 1.0),
                depth_at(x0 + 1.0, y0 + 1.0),
            ];
            let kmin = corners
                .iter()
                .copied()
                .fold(f32::INFINITY, f32::min)
                .max(lo[k]);
            let kmax = corners
                .iter()
                .copied()
                .fold(f32::NEG_INFINITY, f32::max)
                .min(hi[k]);
            // Rounding can cross the two for a triangle parallel to the cells' faces; the
            // clip below decides exactly, so a candidate too many costs only time.
            let (a, b) = (kmin.min(kmax) - 1e-3, kmin.max(kmax) + 1e-3);
            if a.is_nan() || b.is_nan() {
                continue;
            }
            let (k0, k1) = (
                a.floor().clamp(0.0, last) as u32,
                b.floor().clamp(0.0, last) as u32,
            );
            for ck in k0..=k1 {
                let mut c = UVec3::ZERO;
                c[i] = ci;
                c[j] = cj;
                c[k] = ck;
                let box_lo = c.as_vec3();
                if let Some((area, centroid)) = clip_triangle(*q, box_lo, box_lo + 1.0) {
                    emit(c, area, centroid);
                }
            }
        }
    }
}

/// The albedo of `t` at barycentric `b` (material colour × texture).
fn albedo_at(t: &WorldTriangle, materials: &[Material], b: Vec3) -> Vec3 {
    let Some(m) = materials.get(t.material as usize) else {
        return Vec3::ZERO;
    };
    let uv = t.uv[0] * b.x + t.uv[1] * b.y + t.uv[2] * b.z;
    m.albedo * m.texture.as_ref().map_or(Vec3::ONE, |tex| tex.sample(uv))
}

/// The leaf fragments of `triangles` in `grid`, sorted by code, one per leaf. Emissive
/// triangles count like any other surface (they occlude and reflect).
pub fn fragments(
    triangles: &[WorldTriangle],
    materials: &[Material],
    grid: &Grid,
) -> Vec<Fragment> {
    let cells = grid.cells(grid.depth);
    let leaf_m = grid.voxel_m(grid.depth);
    // Each fragment with its triangle: sorting by (code, triangle) fixes the order in which
    // a leaf's shares are summed, so the same scene gives the same bits on any thread count.
    let mut all: Vec<(u32, Fragment)> = triangles
        .par_iter()
        .enumerate()
        .fold(Vec::new, |mut out, (index, t)| {
            let q = t.v.map(|v| (v - grid.origin) / leaf_m);
            let n = (q[1] - q[0]).cross(q[2] - q[0]);
            let unit = canonical(n.normalize_or_zero());
            scan_triangle(&q, cells, |c, area, centroid| {
                let area_m2 = area * leaf_m * leaf_m;
                let b = barycentric(&q, n, centroid);
                out.push((
                    index as u32,
                    Fragment {
                        code: morton::encode(c),
                        area_m2,
                        albedo_area: albedo_at(t, materials, b) * area_m2,
                        centroid_area: (grid.origin + centroid * leaf_m) * area_m2,
                        normal_area: unit * area_m2,
                    },
                ));
            });
            out
        })
        .reduce(Vec::new, |mut a, mut b| {
            if a.len() < b.len() {
                std::mem::swap(&mut a, &mut b);
            }
            a.append(&mut b);
            a
        });
    all.par_sort_unstable_by_key(|(index, f)| (f.code, *index));
    let all: Vec<Fragment> = all.into_iter().map(|(_, f)| f).collect();
    merge_sorted(all)
}

/// Combines runs of equal codes in a sorted list.
fn merge_sorted(sorted: Vec<Fragment>) -> Vec<Fragment> {
    let mut out: Vec<Fragment> = Vec::with_capacity(sorted.len());
    for f in sorted {
        match out.last_mut() {
            Some(last) if last.code == f.code => last.add(&f),
            _ => out.push(f),
        }
    }
    out
}

/// Merges two sorted fragment lists (e.g. the static scene's and the moving objects').
pub fn merge(a: &[Fragment], b: &[Fragment]) -> Vec<Fragment> {
    let mut out: Vec<Fragment> = Vec::with_capacity(a.len() + b.len());
    let (mut i, mut j) = (0, 0);
    while i < a.len() || j < b.len() {
        let take_a = j == b.len() || (i < a.len() && a[i].code <= b[j].code);
        let f = if take_a {
            i += 1;
            a[i - 1]
        } else {
            j += 1;
            b[j - 1]
        };
        match out.last_mut() {
            Some(last) if last.code == f.code => last.add(&f),
            _ => out.push(f),
        }
    }
    out
}
