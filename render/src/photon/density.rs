//! Splat radii from where photons land: each photon's radius is the distance within which
//! about `k` photons of its light lie (its k nearest stored neighbours, looked up in a k-d
//! tree of its batch), so dense regions (corners, near a lamp) get small disks and sparse
//! ones (open walls far from light) large ones — the "sample-point" density estimator of
//! adaptive kernel density estimation (Silverman 1986, §5.3; Jensen's photon maps use its
//! k-nearest counterpart at gather time). Each photon still integrates to its own power, so
//! the energy a splat deposits does not change.
//!
//! A batch holds `1/slots` of its light's photons: the `k`-th neighbour among all of them
//! lies about as far as the `k/slots`-th within the batch. At most [`MAX_NEIGHBOURS`] are
//! looked up and the distance extrapolated as on a surface (r grows with √count).

use std::num::NonZero;

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use rayon::prelude::*;

use super::Photon;

/// Neighbours looked up per photon at most; more are extrapolated from the farthest of
/// them (a k-nearest radius from 8 neighbours varies by ~18% from photon to photon). On
/// the Cornell box 16 cost twice the time (4 -> 8 ms for a batch of 10k photons, 2 threads)
/// for 3% less error.
pub const MAX_NEIGHBOURS: usize = 8;

/// Sets each photon's radius to its density radius: the distance to its `k`-th nearest
/// photon among its light's photons (this batch being one of `slots` alike), clamped to
/// `range` (meters).
pub fn assign(photons: &mut [Photon], k: f32, slots: u32, range: (f32, f32)) {
    let (lo, hi) = (range.0.min(range.1), range.0.max(range.1));
    if photons.len() < 2 {
        for p in photons.iter_mut() {
            p.radius = hi;
        }
        return;
    }
    let in_batch = (k.max(1.0) / slots.max(1) as f32).max(1.0);
    let q = (in_batch.round() as usize).clamp(1, MAX_NEIGHBOURS.min(photons.len() - 1));
    // r_k = r_q · √(k / (q · slots)): the count within r grows with r² on a surface.
    let scale = (k.max(1.0) / (q as f32 * slots.max(1) as f32)).sqrt();
    let points: Vec<[f32; 3]> = photons.iter().map(|p| p.position.to_array()).collect();
    let tree: ImmutableKdTree<f32, 3> = ImmutableKdTree::new_from_slice(&points);
    let reach2 = (hi / scale).powi(2);
    // The photon itself is its own nearest neighbour (distance 0): ask for one more.
    let n = NonZero::new(q + 1).expect("q + 1 > 0");
    photons
        .par_iter_mut()
        .zip(points.par_iter())
        .for_each(|(p, x)| {
            // Neighbours farther than `reach` would give the largest radius anyway.
            let near = tree.nearest_n_within::<SquaredEuclidean>(x, reach2, n, true);
            let d2 = if near.len() == n.get() {
                near.last().map_or(f32::INFINITY, |m| m.distance)
            } else {
                f32::INFINITY
            };
            let r = d2.max(0.0).sqrt() * scale;
            p.radius = if r.is_finite() { r.clamp(lo, hi) } else { hi };
        });
}

#[cfg(test)]
mod tests {
    use glam::Vec3;

    use super::*;

    fn photon(position: Vec3) -> Photon {
        Photon {
            position,
            direction: Vec3::NEG_Y,
            power: Vec3::ONE,
            radius: 0.0,
            receive: Default::default(),
        }
    }

    /// Photons on a square grid of spacing `h` in the plane y = 0 over `[x0, x0 + n·h)`.
    fn grid(x0: f32, n: usize, h: f32) -> Vec<Photon> {
        (0..n * n)
            .map(|i| photon(Vec3::new(x0 + (i % n) as f32 * h, 0.0, (i / n) as f32 * h)))
            .collect()
    }

    fn mean_radius(p: &[Photon]) -> f32 {
        p.iter().map(|p| p.radius).sum::<f32>() / p.len() as f32
    }

    #[test]
    fn an_even_spread_gets_the_disk_that_holds_k_photons() {
        // Density 1/h²: k photons fill a disk of radius √(k/π)·h.
        let h = 0.01;
        for k in [4.0f32, 16.0, 40.0] {
            let mut p = grid(0.0, 60, h);
            assign(&mut p, k, 1, (0.0, 1.0));
            // Away from the grid's border (a border photon has half its neighbours).
            let inner: Vec<Photon> = p
                .iter()
                .filter(|p| p.position.x > 0.15 && p.position.x < 0.45)
                .filter(|p| p.position.z > 0.15 && p.position.z < 0.45)
                .copied()
                .collect();
            let want = (k / std::f32::consts::PI).sqrt() * h;
            let got = mean_radius(&inner);
            assert!((got / want - 1.0).abs() < 0.2, "k {k}: {got} vs {want}");
        }
    }

    #[test]
    fn dense_regions_get_smaller_radii_and_a_batch_stands_for_its_light() {
        // Sixteen times the density on the left: a quarter of the radius.
        let mut p = grid(0.0, 40, 0.0025);
        p.extend(grid(1.0, 40, 0.01));
        let mut all = p.clone();
        assign(&mut all, 40.0, 1, (0.0, 1.0));
        let inner = |p: &[Photon], x0: f32, w: f32| -> f32 {
            let q: Vec<Photon> = p
                .iter()
                .filter(|p| p.position.x > x0 + 0.3 * w && p.position.x < x0 + 0.7 * w)
                .filter(|p| p.position.z > 0.3 * w && p.position.z < 0.7 * w)
                .copied()
                .collect();
            mean_radius(&q)
        };
        let (dense, sparse) = (inner(&all, 0.0, 0.1), inner(&all, 1.0, 0.4));
        assert!(
            (sparse / dense / 4.0 - 1.0).abs() < 0.25,
            "{dense} {sparse}"
        );
        // One batch of four holding every other photon along both axes: the same radii as
        // all four.
        let mut quarter: Vec<Photon> = p
            .iter()
            .enumerate()
            .filter(|(i, _)| (i % 1600) % 2 == 0 && (i % 1600 / 40) % 2 == 0)
            .map(|(_, p)| *p)
            .collect();
        assign(&mut quarter, 40.0, 4, (0.0, 1.0));
        let (d4, s4) = (inner(&quarter, 0.0, 0.1), inner(&quarter, 1.0, 0.4));
        assert!((d4 / dense - 1.0).abs() < 0.2, "{d4} vs {dense}");
        assert!((s4 / sparse - 1.0).abs() < 0.2, "{s4} vs {sparse}");
    }

    #[test]
    fn radii_keep_to_their_range_and_few_photons_are_harmless() {
        let mut p = grid(0.0, 10, 0.01);
        p.push(photon(Vec3::splat(100.0)));
        assign(&mut p, 40.0, 1, (0.02, 0.5));
        assert!(p.iter().all(|p| (0.02..=0.5).contains(&p.radius)));
        assert_eq!(
            p.last().unwrap().radius,
            0.5,
            "a lone photon gets the largest"
        );
        for n in [0, 1, 2] {
            let mut p: Vec<Photon> = (0..n).map(|i| photon(Vec3::X * i as f32)).collect();
            assign(&mut p, 40.0, 3, (0.1, 0.3));
            assert!(p.iter().all(|p| (0.1..=0.3).contains(&p.radius)));
        }
        // Photons on one spot: the smallest radius, not zero or NaN.
        let mut p = vec![photon(Vec3::ONE); 50];
        assign(&mut p, 40.0, 1, (0.01, 0.3));
        assert!(p.iter().all(|p| p.radius == 0.01));
    }
}
