//! Photons merged where their disks nearly coincide ([`merge`]), so a client splats fewer of
//! them for about the same light.
//!
//! A splat's cost is its photon count (each photon costs about the same texels at its
//! level, whatever its radius), and a still light's refinement passes multiply that count:
//! P passes of N photons are drawn together, each disk holding ~P^α times the photons of
//! one pass. Photons that landed within a small fraction of their radius of each other add
//! nearly the same kernel to every point; one photon with their summed power at their
//! power-weighted centroid adds nearly their sum (Suykens & Willems 2000, "Density control
//! for photon maps", thin a photon map the same way). So photons are binned by a grid whose
//! cell is [`merge`]'s `cell` times their radius, and merged within a bin when they also
//! share a radius class (half an octave) and what they tell about receiving surfaces: the
//! same `receive`, and a normal within one of 16 × 16 octahedral buckets (`Normal`) or a
//! direction in the same octant (`Direction`: then every surface facing along an axis
//! receives the merged photon exactly when it received each of them).
//!
//! The merged estimate moves by the spread of photons within a cell, second order in the
//! kernel's width where light is smooth; what it is worth against what it costs is measured
//! (`SplatSettings::merge`).

use glam::{Vec2, Vec3};
use rayon::prelude::*;

use super::{Photon, Receive};

/// Radius classes per octave: photons merge only with those whose radius is within the
/// same half octave (a factor of 1.41). A still light's 32 passes of 20k photons on the
/// Cornell box (`receive = "direction"`, merge 0.5–0.6): 4 classes per octave left 175k
/// photons at relMSE 0.0102, 2 left 123k at 0.0105, 1 left 103k at 0.0106.
const CLASSES_PER_OCTAVE: f32 = 2.0;

/// Octahedral buckets per axis of a `Normal` photon's normal.
const NORMAL_BUCKETS: f32 = 16.0;

/// The photons with those that share a cell of side `cell × r` (and a radius class and a
/// receiving bucket, see the module's documentation) merged into one: summed power, the
/// power-weighted centroid, mean radius and mean direction. `cell` ≤ 0 (or not finite)
/// merges nothing. Photons without a finite position, power or positive radius are kept
/// as they are (the splat leaves them out). Total power is kept exactly (up to rounding).
pub fn merge(photons: &[Photon], cell: f32) -> Vec<Photon> {
    if !(cell > 0.0 && cell.is_finite()) || photons.len() < 2 {
        return photons.to_vec();
    }
    let keys: Vec<Option<u128>> = photons.par_iter().map(|p| key(p, cell)).collect();
    let mut keyed: Vec<(u128, u32)> = Vec::with_capacity(photons.len());
    // Photons that cannot be merged (the splat leaves most of them out) pass through.
    let mut out: Vec<Photon> = Vec::new();
    for (i, k) in keys.into_iter().enumerate() {
        match k {
            Some(k) => keyed.push((k, i as u32)),
            None => out.push(photons[i]),
        }
    }
    keyed.par_sort_unstable();
    out.par_extend(
        keyed
            .par_chunk_by(|a, b| a.0 == b.0)
            .map(|group| match group {
                [(_, only)] => photons[*only as usize],
                _ => merged(group, photons),
            }),
    );
    out
}

/// The photon that stands for `group` (two photons or more, all finite).
fn merged(group: &[(u128, u32)], photons: &[Photon]) -> Photon {
    let first = photons[group[0].1 as usize];
    let (mut power, mut weight) = (Vec3::ZERO, 0.0f64);
    let (mut position, mut radius, mut direction) = (glam::DVec3::ZERO, 0.0f64, Vec3::ZERO);
    for p in group.iter().map(|(_, i)| &photons[*i as usize]) {
        // Weighted by the sum of channels (what the splat adds in), floored so a group of
        // black photons still has a centroid.
        let w = (p.power.max(Vec3::ZERO).element_sum() as f64).max(1e-30);
        power += p.power;
        weight += w;
        position += p.position.as_dvec3() * w;
        radius += p.radius as f64 * w;
        direction += p.direction * w as f32;
    }
    Photon {
        position: (position / weight).as_vec3(),
        direction: direction.try_normalize().unwrap_or(first.direction),
        power,
        radius: (radius / weight) as f32,
        receive: first.receive,
    }
}

/// The bin of `p`, or `None` when it cannot be merged (not finite, no radius, or so far
/// out that its cell's coordinates do not fit).
fn key(p: &Photon, cell: f32) -> Option<u128> {
    if !(p.position.is_finite()
        && p.power.is_finite()
        && p.direction.is_finite()
        && p.radius > 0.0
        && p.radius.is_finite())
    {
        return None;
    }
    let class = (p.radius.log2() * CLASSES_PER_OCTAVE).floor();
    if !(-127.0..=127.0).contains(&class) {
        return None;
    }
    let side = cell * (class / CLASSES_PER_OCTAVE).exp2();
    let grid = (p.position / side).floor();
    if grid.abs().max_element() >= i32::MAX as f32 / 2.0 {
        return None;
    }
    let bucket = match p.receive {
        Receive::Normal => {
            let o = octahedral(p.direction);
            let b = ((o * 0.5 + 0.5) * NORMAL_BUCKETS)
                .floor()
                .clamp(Vec2::ZERO, Vec2::splat(NORMAL_BUCKETS - 1.0));
            (b.x as u32) * NORMAL_BUCKETS as u32 + b.y as u32
        }
        Receive::Direction => {
            512 + (p.direction.x < 0.0) as u32
                + 2 * (p.direction.y < 0.0) as u32
                + 4 * (p.direction.z < 0.0) as u32
        }
    };
    let axis = |v: f32| (v as i32 as u32) as u128;
    Some(
        ((class as i32 + 128) as u128) << 106
            | (bucket as u128) << 96
            | axis(grid.x) << 64
            | axis(grid.y) << 32
            | axis(grid.z),
    )
}

/// A unit vector on the octahedron folded to the square [−1, 1]².
fn octahedral(n: Vec3) -> Vec2 {
    let n = n / n.abs().element_sum().max(f32::MIN_POSITIVE);
    if n.z >= 0.0 {
        Vec2::new(n.x, n.y)
    } else {
        let sign = |v: f32| if v >= 0.0 { 1.0 } else { -1.0 };
        Vec2::new((1.0 - n.y.abs()) * sign(n.x), (1.0 - n.x.abs()) * sign(n.y))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn photon(position: Vec3, power: f32, radius: f32) -> Photon {
        Photon {
            position,
            direction: Vec3::NEG_Y,
            power: Vec3::splat(power),
            radius,
            receive: Receive::Normal,
        }
    }

    #[test]
    fn photons_in_one_cell_merge_keeping_power_and_centroid() {
        let a = photon(Vec3::new(0.01, 0.0, 0.01), 1.0, 1.0);
        let b = photon(Vec3::new(0.03, 0.0, 0.01), 3.0, 1.0);
        let out = merge(&[a, b], 0.5);
        assert_eq!(out.len(), 1);
        assert_eq!(out[0].power, Vec3::splat(4.0));
        assert!(
            (out[0].position.x - 0.025).abs() < 1e-6,
            "{:?}",
            out[0].position
        );
        assert_eq!(out[0].direction, Vec3::NEG_Y);
    }

    #[test]
    fn photons_apart_or_unalike_stay_apart() {
        let a = photon(Vec3::new(0.1, 0.0, 0.1), 1.0, 1.0);
        // A cell away.
        let far = photon(Vec3::new(0.6, 0.0, 0.1), 1.0, 1.0);
        // Another radius class.
        let small = photon(Vec3::new(0.1, 0.0, 0.1), 1.0, 0.5);
        // Another surface's normal.
        let wall = Photon {
            direction: Vec3::X,
            ..a
        };
        // Another way of receiving.
        let travelled = Photon {
            receive: Receive::Direction,
            ..a
        };
        assert_eq!(merge(&[a, far, small, wall, travelled], 0.5).len(), 5);
        // Merging off.
        assert_eq!(merge(&[a, a], 0.0).len(), 2);
    }

    #[test]
    fn directions_merge_within_an_octant_only() {
        let p = |d: Vec3| Photon {
            direction: d.normalize(),
            receive: Receive::Direction,
            ..photon(Vec3::ZERO, 1.0, 1.0)
        };
        let out = merge(
            &[p(Vec3::new(0.1, -1.0, 0.2)), p(Vec3::new(0.5, -1.0, 0.1))],
            0.5,
        );
        assert_eq!(out.len(), 1);
        let out = merge(
            &[p(Vec3::new(0.1, -1.0, 0.2)), p(Vec3::new(-0.5, -1.0, 0.1))],
            0.5,
        );
        assert_eq!(out.len(), 2);
    }

    #[test]
    fn power_is_kept_and_invalid_photons_pass_through() {
        let mut photons: Vec<Photon> = (0..1000)
            .map(|i| {
                let t = i as f32 * 0.618;
                photon(
                    Vec3::new(t.fract(), 0.0, (t * 0.37).fract()),
                    0.001 * (1 + i % 7) as f32,
                    0.2,
                )
            })
            .collect();
        photons.push(photon(Vec3::splat(f32::NAN), 1.0, 0.2));
        photons.push(photon(Vec3::ZERO, 1.0, 0.0));
        let out = merge(&photons, 0.5);
        assert!(
            out.len() < photons.len() / 4,
            "{} of {}",
            out.len(),
            photons.len()
        );
        let sum = |ps: &[Photon]| -> f64 {
            ps.iter()
                .filter(|p| p.position.is_finite())
                .map(|p| p.power.x as f64)
                .sum()
        };
        assert!((sum(&out) - sum(&photons)).abs() < 1e-4 * sum(&photons));
        assert_eq!(out.iter().filter(|p| !p.position.is_finite()).count(), 1);
        assert_eq!(out.iter().filter(|p| p.radius == 0.0).count(), 1);
    }
}
