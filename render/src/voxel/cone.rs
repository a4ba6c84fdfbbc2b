//! Cone tracing per voxel (CloudLight §4.1 step 3): from each leaf's two sides, a few wide
//! cones march through the filtered octree ([`super::filter`]) and gather the irradiance
//! that the lit voxels send toward the leaf. The result is view-independent (one
//! irradiance per side of each leaf), so one gather serves every client; fed back into
//! [`super::inject`] it adds a bounce per update.
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
//! Each sample's opacity is corrected for the step (α' = 1 − (1 − α)^(Δt / voxel)) and
//! composited front to back, until the cone is opaque or leaves the grid.

use glam::Vec3;
use rayon::prelude::*;

use super::inject::VoxelRadiance;
use super::morton;
use super::octree::Octree;
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
}

impl Default for ConeSettings {
    fn default() -> Self {
        ConeSettings {
            step: 0.75,
            offset_voxels: 1.0,
            opaque: 0.97,
            coarsest_level: 2,
            voxel_per_height: 0.5,
        }
    }
}

/// The six 60° cones of a hemisphere (one along the normal, five at 60° from it) and their
/// weights, which sum to π so that E = Σ w_k · L_k for a cosine-weighted hemisphere.
const HALF_ANGLE_TAN: f32 = 0.577_350_3; // tan 30°
const AXIS_WEIGHT: f32 = std::f32::consts::PI / 4.0;
const SIDE_WEIGHT: f32 = 3.0 * std::f32::consts::PI / 20.0;

fn cones(n: Vec3) -> [(Vec3, f32); 6] {
    let (t, b) = basis(n);
    let (s, c) = (60f32.to_radians().sin(), 60f32.to_radians().cos());
    let mut out = [(n, AXIS_WEIGHT); 6];
    for (k, cone) in out.iter_mut().enumerate().skip(1) {
        let phi = std::f32::consts::TAU * (k - 1) as f32 / 5.0;
        *cone = (n * c + (t * phi.cos() + b * phi.sin()) * s, SIDE_WEIGHT);
    }
    out
}

/// The filtered octree, ready to be sampled.
pub struct ConeTracer<'a> {
    octree: &'a Octree,
    levels: &'a [Vec<VoxelRadiance>],
    settings: ConeSettings,
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
            levels,
            settings,
        }
    }

    /// Radiance (premultiplied) and opacity that the voxel of `level` around `p` sends
    /// toward `toward` (a unit direction); empty outside the grid and where nothing is.
    fn voxel(&self, level: u32, p: Vec3, toward: Vec3) -> (Vec3, f32) {
        let g = &self.octree.grid;
        let cells = g.cells(level);
        let c = ((p - g.origin) / g.voxel_m(level)).floor();
        if c.cmplt(Vec3::ZERO).any() || c.cmpge(Vec3::splat(cells as f32)).any() {
            return (Vec3::ZERO, 0.0);
        }
        let lvl = &self.octree.levels[level as usize];
        let Some(i) = lvl.find(morton::encode(c.as_uvec3())) else {
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

    /// The mean radiance arriving at `origin` from the cone around unit `dir` (half-angle
    /// 30°), W·m⁻²·sr⁻¹, and the number of samples taken.
    pub fn cone(&self, origin: Vec3, dir: Vec3, n: Vec3) -> (Vec3, u32) {
        let g = &self.octree.grid;
        let depth = g.depth;
        let leaf_m = g.voxel_m(depth);
        let max_t = g.size_m * 3f32.sqrt();
        let mut t = leaf_m;
        let (mut color, mut alpha) = (Vec3::ZERO, 0.0f32);
        let mut samples = 0;
        while t < max_t && alpha < self.settings.opaque {
            let diameter = (2.0 * t * HALF_ANGLE_TAN).max(leaf_m);
            // Level whose voxel is the footprint's size: fine ones near, coarse far.
            let coarsest = self.settings.coarsest_level.min(depth) as f32;
            // Voxels no larger than the footprint, nor than a fraction of the height over
            // the surface left (see `voxel_per_height`).
            let height = t * dir.dot(n).max(0.0) + leaf_m * self.settings.offset_voxels;
            let size = diameter
                .min(self.settings.voxel_per_height * height)
                .max(leaf_m);
            let level = (depth as f32 - (size / leaf_m).log2()).clamp(coarsest, depth as f32);
            let (fine, coarse) = (level.ceil() as u32, level.floor() as u32);
            let blend = level - coarse as f32;
            let p = origin + dir * t;
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
                let corrected = 1.0 - (1.0 - a.min(1.0)).powf(step / voxel_m);
                color += (1.0 - alpha) * c * (corrected / a);
                alpha += (1.0 - alpha) * corrected;
            }
            samples += 1;
            t += step;
        }
        (color, samples)
    }

    /// Irradiance at `origin` over the hemisphere around unit `n`, W·m⁻², and the samples.
    pub fn irradiance(&self, origin: Vec3, n: Vec3) -> (Vec3, u32) {
        let mut e = Vec3::ZERO;
        let mut samples = 0;
        for (dir, weight) in cones(n) {
            let (l, s) = self.cone(origin, dir, n);
            e += l * weight;
            samples += s;
        }
        (e, samples)
    }
}

/// What one gather computed.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Gathered {
    /// Per leaf (the octree's leaf order), the indirect irradiance on its two sides (along
    /// its normal, then against it), W·m⁻²: the `indirect` input of the next injection.
    pub irradiance: Vec<[Vec3; 2]>,
    /// Voxel samples taken by all cones.
    pub samples: u64,
}

/// Gathers indirect irradiance on both sides of every leaf of `octree` from the filtered
/// voxels `levels`.
pub fn gather(octree: &Octree, levels: &[Vec<VoxelRadiance>], settings: &ConeSettings) -> Gathered {
    let tracer = ConeTracer::new(octree, levels, *settings);
    let leaf_m = octree.grid.voxel_m(octree.grid.depth);
    let (irradiance, samples): (Vec<[Vec3; 2]>, Vec<u64>) = octree
        .leaves()
        .surfaces
        .par_iter()
        .map(|s| {
            let n = s.side_normal();
            let mut count = 0u64;
            let e = [n, -n].map(|side| {
                let origin = s.position + side * (leaf_m * settings.offset_voxels);
                let (e, k) = tracer.irradiance(origin, side);
                count += u64::from(k);
                e
            });
            (e, count)
        })
        .unzip();
    Gathered {
        irradiance,
        samples: samples.iter().sum(),
    }
}
