//! Cone tracing per voxel (CloudLight §4.1 step 3): from each leaf's two sides, a few wide
//! cones march through the filtered octree ([`super::filter`](fn@super::filter)) and gather the irradiance
//! that the lit voxels send toward the leaf. The result is view-independent (one
//! irradiance per side of each leaf), so one gather serves every client; fed back into
//! [`super::inject`](fn@super::inject) it adds a bounce per update.
//!
//! A cone of half-angle θ at distance t covers a disc of diameter 2t·tan θ and samples the
//! level whose voxels are that size (between two levels, the two are blended), so far light
//! comes from coarse levels: the paper's multi-resolution remedy. Two departures from the
//! textbook, both measured in a closed box (a uniformly bright one must give E = π·B, and
//! one bounce must carry the reflected power; without them: 0.27 and 0.19 of that):
//! - no voxel read is larger than half the sample's height over the surface the cone
//!   leaves, so a coarse voxel never holds that surface's dark back;
//! - a voxel seen from a direction weighs only the faces behind which it holds surface
//!   (squared components of the direction), so a wall seen obliquely is as opaque and as
//!   bright as seen head-on.
//!
//! Cones leave from voxels [`ConeSettings::levels_above_leaves`] above the leaves where the
//! surface is flat, and from finer voxels (down to the leaves) where it is not; the result
//! is an irradiance for every voxel of every level ([`Gathered`]).
//!
//! Each sample's opacity is corrected for the step (α' = 1 − (1 − α)^(Δt / voxel)) and
//! composited front to back, until the cone is opaque or leaves the grid.

use glam::Vec3;
use rayon::prelude::*;

use super::inject::VoxelRadiance;
use super::octree::{Locator, Octree};
use crate::sampling::basis;

/// Cone-tracing settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ConeSettings {
    /// Step along a cone, as a fraction of its diameter where it is.
    pub step: f32,
    /// The cones start this many leaf voxels off the surface (against self-occlusion).
    pub offset_voxels: f32,
    /// A cone stops when this opaque.
    pub opaque: f32,
    /// The coarsest level a cone samples (0: the root). A voxel as large as a room holds
    /// the cone's own origin wall, whose dark back hides the room's light; far samples
    /// read finer voxels instead (sparser, not darker).
    pub coarsest_level: u32,
    /// No voxel a cone reads is larger than this fraction of the sample's height over the
    /// surface the cone leaves: a larger grid-aligned voxel may hold that surface, whose
    /// back (dark, and opaque when seen from it) would hide the light beyond. Steps are no
    /// longer than the voxels read, so the samples get denser near a surface.
    pub voxel_per_height: f32,
    /// Cones leave from voxels this many levels above the leaves (the paper's remedy for
    /// large scenes: "computing indirect illumination at intermediate octree nodes instead
    /// of leaves"); the leaves below take their ancestor's irradiance. Indirect light is
    /// smooth, and each level up gathers from a quarter of the voxels.
    pub levels_above_leaves: u32,
    /// Where a gathering voxel's surfaces are less flat than this ([`VoxelSurface::flatness`]:
    /// a corner, an edge, a curve), its children gather instead, down to the leaves: full
    /// resolution only where the geometry has detail (CloudLight §4.1).
    ///
    /// [`VoxelSurface::flatness`]: super::octree::VoxelSurface::flatness
    pub refine_below_flatness: f32,
    /// Cones per side of a gathering voxel: 6 (one along the normal and five at 60° from
    /// it, 30° wide, as in Crassin et al. 2011) or any other count from 1 to
    /// [`MAX_CONES`], laid out as a cosine-weighted Fibonacci spiral (equal weights, each
    /// as wide as its share of the hemisphere). More cones are narrower: finer and slower.
    pub cones: u32,
}

/// The most cones per side [`ConeSettings::cones`] takes.
pub const MAX_CONES: u32 = 64;

impl Default for ConeSettings {
    fn default() -> Self {
        ConeSettings {
            step: 0.75,
            offset_voxels: 1.0,
            opaque: 0.97,
            coarsest_level: 2,
            voxel_per_height: 0.5,
            levels_above_leaves: 2,
            refine_below_flatness: 0.95,
            cones: 6,
        }
    }
}

/// The six 60° cones of a hemisphere (one along the normal, five at 60° from it) and their
/// weights, which sum to π so that E = Σ w_k · L_k for a cosine-weighted hemisphere.
const HALF_ANGLE_TAN: f32 = 0.577_350_3; // tan 30°
const AXIS_WEIGHT: f32 = std::f32::consts::PI / 4.0;
const SIDE_WEIGHT: f32 = 3.0 * std::f32::consts::PI / 20.0;

/// (cos φ, sin φ) of the five side cones around the normal, φ = 2πk/5.
const SIDE_PHI: [(f32, f32); 5] = [
    (1.0, 0.0),
    (0.309_017, 0.951_056_5),
    (-0.809_017, 0.587_785_3),
    (-0.809_017, -0.587_785_3),
    (0.309_017, -0.951_056_5),
];

/// A hemisphere's cones in the frame of its normal (+Z): directions, weights summing to π
/// (E = Σ w_k · L_k for a cosine-weighted hemisphere) and the tangent of their half-angle.
#[derive(Clone, Debug, PartialEq)]
struct ConeSet {
    local: Vec<(Vec3, f32)>,
    half_angle_tan: f32,
}

impl ConeSet {
    fn new(count: u32) -> ConeSet {
        let count = count.clamp(1, MAX_CONES);
        if count == 6 {
            let (s, c) = (0.866_025_4, 0.5); // sin 60°, cos 60°
            let local = std::iter::once((Vec3::Z, AXIS_WEIGHT))
                .chain(
                    SIDE_PHI
                        .iter()
                        .map(|&(cos, sin)| (Vec3::new(cos * s, sin * s, c), SIDE_WEIGHT)),
                )
                .collect();
            return ConeSet {
                local,
                half_angle_tan: HALF_ANGLE_TAN,
            };
        }
        // Fibonacci points, area-uniform on the unit disc and lifted onto the hemisphere
        // (Malley's method), are cosine-distributed: each carries π / count. A cone covers
        // its share of the solid angle, 2π / count = 2π (1 − cos θ).
        let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
        let local = (0..count)
            .map(|k| {
                let r2 = (k as f32 + 0.5) / count as f32;
                let (sin_phi, cos_phi) = (golden * k as f32).sin_cos();
                let r = r2.sqrt();
                let d = Vec3::new(r * cos_phi, r * sin_phi, (1.0 - r2).sqrt());
                (d, std::f32::consts::PI / count as f32)
            })
            .collect();
        let cos = (1.0 - 1.0 / count as f32).max(0.5); // one cone: 60°, as wide as a side cone
        ConeSet {
            local,
            half_angle_tan: (1.0 - cos * cos).sqrt() / cos,
        }
    }

    /// The cones around unit `n`, world space.
    fn around(&self, n: Vec3) -> impl Iterator<Item = (Vec3, f32)> + '_ {
        let (t, b) = basis(n);
        self.local
            .iter()
            .map(move |&(d, w)| (t * d.x + b * d.y + n * d.z, w))
    }
}

/// log₂ of a positive, normal `x`, within 10⁻⁵ (log₂ m = 2/ln 2 · atanh((m − 1)/(m + 1))
/// over the mantissa, to y⁵): libm's `log2f` and `powf` were a third of the gather's time.
fn fast_log2(x: f32) -> f32 {
    let bits = x.to_bits();
    let mut exponent = ((bits >> 23) & 0xff) as i32 - 127;
    let mut m = f32::from_bits((bits & 0x007f_ffff) | 0x3f80_0000);
    // The mantissa in [1/√2, √2), so |y| < 0.18 and the series' remainder is below 10⁻⁵.
    if m > std::f32::consts::SQRT_2 {
        m *= 0.5;
        exponent += 1;
    }
    let y = (m - 1.0) / (m + 1.0);
    let y2 = y * y;
    exponent as f32 + 2.885_39 * y * (1.0 + y2 * (1.0 / 3.0 + y2 * 0.2))
}

/// 2^x for x ≤ 0, within 10⁻⁵ relative; 0 below 2⁻¹²⁶.
fn fast_exp2(x: f32) -> f32 {
    if x < -126.0 {
        return 0.0;
    }
    let mut i = x as i32;
    if (i as f32) > x {
        i -= 1;
    }
    let f = x - i as f32;
    // 2^f = √2 · e^g, g = (f − ½)·ln 2 ∈ [−0.35, 0.35]: Taylor to g⁵.
    let g = (f - 0.5) * std::f32::consts::LN_2;
    let p = std::f32::consts::SQRT_2
        * (1.0 + g * (1.0 + g * (0.5 + g * (1.0 / 6.0 + g * (1.0 / 24.0 + g / 120.0)))));
    p * f32::from_bits(((i + 127) as u32) << 23)
}

/// (1 − a)^r: what a sample of opacity `a` transmits over `r` of its voxel's length.
fn transmitted(a: f32, r: f32) -> f32 {
    if a >= 1.0 {
        0.0
    } else {
        fast_exp2(r * fast_log2(1.0 - a))
    }
}

/// The filtered octree, ready to be sampled.
pub struct ConeTracer<'a> {
    octree: &'a Octree,
    locator: Locator,
    /// Per level, cells per meter.
    cells_per_m: Vec<f32>,
    levels: &'a [Vec<VoxelRadiance>],
    settings: ConeSettings,
    cones: ConeSet,
}

impl<'a> ConeTracer<'a> {
    /// Traces cones through `octree` with the filtered voxels `levels` (root first).
    pub fn new(
        octree: &'a Octree,
        levels: &'a [Vec<VoxelRadiance>],
        settings: ConeSettings,
    ) -> Self {
        ConeTracer {
            octree,
            locator: Locator::new(octree),
            cells_per_m: (0..=octree.depth())
                .map(|l| 1.0 / octree.grid.voxel_m(l))
                .collect(),
            levels,
            settings,
            cones: ConeSet::new(settings.cones),
        }
    }

    /// Radiance (premultiplied) and opacity that the voxel of `level` around `p` sends
    /// toward `toward` (a unit direction); empty outside the grid and where nothing is.
    fn voxel(&self, level: u32, p: Vec3, toward: Vec3) -> (Vec3, f32) {
        let g = &self.octree.grid;
        let c = (p - g.origin) * self.cells_per_m[level as usize];
        if c.cmplt(Vec3::ZERO).any() || c.cmpge(Vec3::splat(g.cells(level) as f32)).any() {
            return (Vec3::ZERO, 0.0);
        }
        // Non-negative, so truncation is the floor (a call into libm without SSE4.1).
        let Some(i) = self.locator.find(self.octree, level, c.as_uvec3()) else {
            return (Vec3::ZERO, 0.0);
        };
        let v = &self.levels[level as usize][i];
        // The faces facing `toward`, weighted by its squared components, counting only
        // faces behind which there is surface: a wall seen obliquely covers the view as
        // fully as seen head-on (the faces along which it is edge-on see nothing, and do
        // not dilute it).
        let w2 = toward * toward;
        let (mut radiance, mut opacity, mut weight) = (Vec3::ZERO, 0.0, 0.0);
        for axis in 0..3 {
            let slot = 2 * axis + usize::from(toward[axis] < 0.0);
            if v.opacity[slot] > 0.0 {
                radiance += v.radiance[slot] * w2[axis];
                opacity += v.opacity[slot] * w2[axis];
                weight += w2[axis];
            }
        }
        if weight <= 0.0 {
            return (Vec3::ZERO, 0.0);
        }
        (radiance / weight, opacity / weight)
    }

    /// The mean radiance arriving at `origin` from the cone around unit `dir` (as wide as
    /// [`ConeSettings::cones`] makes it), W·m⁻²·sr⁻¹, and the number of samples taken. The cone leaves a surface of
    /// normal `n` from a voxel `start_m` wide.
    pub fn cone(&self, origin: Vec3, dir: Vec3, n: Vec3, start_m: f32) -> (Vec3, u32) {
        let g = &self.octree.grid;
        let depth = g.depth;
        let leaf_m = g.voxel_m(depth);
        let max_t = g.size_m * 3f32.sqrt();
        let coarsest = self.settings.coarsest_level.min(depth) as f32;
        let cos = dir.dot(n).max(0.0);
        let mut t = start_m;
        let (mut color, mut alpha) = (Vec3::ZERO, 0.0f32);
        let mut samples = 0;
        while t < max_t && alpha < self.settings.opaque {
            let diameter = 2.0 * t * self.cones.half_angle_tan;
            // Voxels no larger than the footprint (fine ones near, coarse far), nor than a
            // fraction of the height over the surface left (see `voxel_per_height`).
            let height = t * cos + start_m * self.settings.offset_voxels;
            let size = diameter
                .min(self.settings.voxel_per_height * height)
                .max(leaf_m);
            let level = (depth as f32 - fast_log2(size / leaf_m)).clamp(coarsest, depth as f32);
            // Between two levels, both are read and blended.
            let coarse = level as u32;
            let blend = level - coarse as f32;
            let fine = if blend > 0.0 { coarse + 1 } else { coarse };
            let p = origin + dir * t;
            if (p - g.origin).cmplt(Vec3::ZERO).any()
                || (p - g.origin).cmpge(Vec3::splat(g.size_m)).any()
            {
                break; // out of the grid: nothing more to meet
            }
            let toward = -dir;
            let (c0, a0) = self.voxel(coarse, p, toward);
            let (c1, a1) = if fine == coarse {
                (c0, a0)
            } else {
                self.voxel(fine, p, toward)
            };
            let (c, a) = (c0 + (c1 - c0) * blend, a0 + (a1 - a0) * blend);
            // Steps no longer than the voxels read, so no wall is stepped over.
            let step = size * self.settings.step;
            if a > 1e-6 {
                let voxel_m = g.voxel_m(coarse) * (1.0 - blend) + g.voxel_m(fine) * blend;
                let corrected = 1.0 - transmitted(a, step / voxel_m);
                color += (1.0 - alpha) * c * (corrected / a);
                alpha += (1.0 - alpha) * corrected;
            }
            samples += 1;
            t += step;
        }
        (color, samples)
    }

    /// Irradiance at `origin` over the hemisphere around unit `n`, W·m⁻², and the samples,
    /// for cones leaving a voxel `start_m` wide.
    pub fn irradiance(&self, origin: Vec3, n: Vec3, start_m: f32) -> (Vec3, u32) {
        let mut e = Vec3::ZERO;
        let mut samples = 0;
        for (dir, weight) in self.cones.around(n) {
            let (l, s) = self.cone(origin, dir, n, start_m);
            e += l * weight;
            samples += s;
        }
        (e, samples)
    }
}

/// What one gather computed.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Gathered {
    /// Per level (root first, aligned with the octree's levels), per voxel, the indirect
    /// irradiance on its two sides (along its [`side_normal`](super::octree::VoxelSurface::side_normal), then against
    /// it), W·m⁻². Voxels that gathered hold what their cones found; voxels above them the
    /// area-weighted mean of their children; voxels below them their ancestor's, so the
    /// leaves are the next injection's `indirect` input.
    pub levels: Vec<Vec<[Vec3; 2]>>,
    /// Voxels whose cones were traced.
    pub gathered: u64,
    /// Voxel samples taken by all cones.
    pub samples: u64,
}

impl Gathered {
    /// The leaves' irradiance (the octree's leaf order).
    pub fn leaves(&self) -> &[[Vec3; 2]] {
        self.levels.last().map_or(&[], |l| l.as_slice())
    }
}

/// The voxels (level, index) whose cones are traced: those `settings.levels_above_leaves`
/// above the leaves, or their descendants where they are not flat.
fn gathering_voxels(octree: &Octree, settings: &ConeSettings) -> Vec<(u32, u32)> {
    let depth = octree.depth();
    let top = depth.saturating_sub(settings.levels_above_leaves);
    let mut stack: Vec<(u32, u32)> = (0..octree.levels[top as usize].len() as u32)
        .rev()
        .map(|i| (top, i))
        .collect();
    let mut out = Vec::new();
    while let Some((level, i)) = stack.pop() {
        let l = &octree.levels[level as usize];
        if level == depth || l.surfaces[i as usize].flatness >= settings.refine_below_flatness {
            out.push((level, i));
        } else {
            let children = l.first_child[i as usize]..l.first_child[i as usize + 1];
            stack.extend(children.rev().map(|c| (level + 1, c)));
        }
    }
    out
}

/// Gathers indirect irradiance on both sides of the voxels of `octree` from the filtered
/// voxels `levels` (see [`Gathered`]).
pub fn gather(octree: &Octree, levels: &[Vec<VoxelRadiance>], settings: &ConeSettings) -> Gathered {
    let tracer = ConeTracer::new(octree, levels, *settings);
    let gathering = gathering_voxels(octree, settings);
    let traced: Vec<([Vec3; 2], u64)> = gathering
        .par_iter()
        .map(|&(level, i)| {
            let s = &octree.levels[level as usize].surfaces[i as usize];
            let voxel_m = octree.grid.voxel_m(level);
            let n = s.side_normal();
            let mut count = 0u64;
            let e = [n, -n].map(|side| {
                let origin = s.position + side * (voxel_m * settings.offset_voxels);
                let (e, k) = tracer.irradiance(origin, side, voxel_m);
                count += u64::from(k);
                e
            });
            (e, count)
        })
        .collect();
    let mut out: Vec<Vec<[Vec3; 2]>> = octree
        .levels
        .iter()
        .map(|l| vec![[Vec3::ZERO; 2]; l.len()])
        .collect();
    let mut known: Vec<Vec<bool>> = octree.levels.iter().map(|l| vec![false; l.len()]).collect();
    for (&(level, i), (e, _)) in gathering.iter().zip(&traced) {
        out[level as usize][i as usize] = *e;
        known[level as usize][i as usize] = true;
    }
    // Up: a voxel all of whose children are known is their area-weighted mean (voxels
    // below a gathering one stay unknown).
    for level in (0..octree.levels.len().saturating_sub(1)).rev() {
        let (parents, below) = (&octree.levels[level], &octree.levels[level + 1]);
        let links = octree.parent_links(level + 1);
        for i in 0..parents.len() {
            let children = parents.first_child[i] as usize..parents.first_child[i + 1] as usize;
            if known[level][i]
                || children.is_empty()
                || !children.clone().all(|c| known[level + 1][c])
            {
                continue;
            }
            let (mut sum, mut area) = ([Vec3::ZERO; 2], 0.0);
            for c in children {
                let child = &below.surfaces[c];
                let e = links[c].onto(out[level + 1][c]);
                sum = [sum[0] + e[0] * child.area_m2, sum[1] + e[1] * child.area_m2];
                area += child.area_m2;
            }
            let inv = if area > 0.0 { 1.0 / area } else { 0.0 };
            out[level][i] = [sum[0] * inv, sum[1] * inv];
            known[level][i] = true;
        }
    }
    // Down: the rest take their parent's.
    for level in 1..octree.levels.len() {
        let (above, here) = out.split_at_mut(level);
        for (c, link) in octree.parent_links(level).iter().enumerate() {
            if !known[level][c] {
                here[0][c] = link.onto(above[level - 1][link.parent as usize]);
                known[level][c] = true;
            }
        }
    }
    Gathered {
        levels: out,
        gathered: gathering.len() as u64,
        samples: traced.iter().map(|(_, k)| k).sum(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fast_math_is_close_to_libm() {
        for k in 0..2000 {
            let x = 1e-6 * 1.02f32.powi(k);
            assert!((fast_log2(x) - x.log2()).abs() < 1e-5, "log2 {x}");
        }
        for k in 0..2000 {
            let x = -0.01 * k as f32;
            let (ours, libm) = (fast_exp2(x), x.exp2());
            assert!(
                (ours - libm).abs() <= 1e-5 * libm,
                "exp2 {x}: {ours} vs {libm}"
            );
        }
        for a in [0.0f32, 1e-6, 0.1, 0.5, 0.9, 0.999, 1.0] {
            for r in [0.25f32, 0.5, 0.75, 1.0, 1.5] {
                let want = (1.0 - a).powf(r);
                assert!((transmitted(a, r) - want).abs() < 1e-4, "{a} {r}");
            }
        }
        let six = ConeSet::new(6);
        assert_eq!(six.local.len(), 6);
        for (d, _) in &six.local[1..] {
            assert!((d.dot(Vec3::Z) - 0.5).abs() < 1e-5 && (d.length() - 1.0).abs() < 1e-5);
        }
    }

    #[test]
    fn every_cone_set_weighs_a_cosine_hemisphere() {
        // Σ w = π, every direction in the hemisphere, and Σ w·d = (0, 0, 2π/3) as
        // ∫ cos θ · ω dω over the hemisphere is: the set is not tilted.
        for count in [1, 2, 6, 8, 16, 32, MAX_CONES, MAX_CONES + 5] {
            let set = ConeSet::new(count);
            assert_eq!(set.local.len() as u32, count.clamp(1, MAX_CONES));
            let sum: f32 = set.local.iter().map(|c| c.1).sum();
            assert!((sum - std::f32::consts::PI).abs() < 1e-4, "{count}: {sum}");
            let mean: Vec3 = set.local.iter().map(|&(d, w)| d * w).sum();
            assert!(
                set.local
                    .iter()
                    .all(|(d, _)| d.z > 0.0 && (d.length() - 1.0).abs() < 1e-5)
            );
            if count >= 6 {
                let want = Vec3::new(0.0, 0.0, 2.0 * std::f32::consts::PI / 3.0);
                assert!((mean - want).length() < 0.12 * want.z, "{count}: {mean}");
            }
            assert!(set.half_angle_tan > 0.0 && set.half_angle_tan <= 3f32.sqrt());
        }
        // World space follows the normal.
        let n = Vec3::new(1.0, 2.0, -0.5).normalize();
        for (d, _) in ConeSet::new(16).around(n) {
            assert!(d.dot(n) > 0.0 && (d.length() - 1.0).abs() < 1e-5);
        }
    }
}
