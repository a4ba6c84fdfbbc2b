//! Photon relaxation (Spencer & Jones, "Into the Blue: Better Caustics through Photon
//! Relaxation", Eurographics 2009): each stored photon is pushed away from its nearest
//! neighbours on its own surface, a few times over, so the batch's photons spread evenly
//! where they landed as a clump or left a gap. The photons' density — and so the light —
//! keeps every feature wider than a few photon spacings (a photon moves a fraction of the
//! distance to its neighbours per iteration), while the random clumping that a splat shows
//! as blotches thins out: the estimate's noise falls for the same photons on the wire.
//!
//! A photon moves only in its surface's tangent plane and only where the scene lets it:
//! the way along the surface must be clear, and the surface must still be under it (a ray
//! back along its normal hits a face of the same orientation, whose point it takes). A
//! photon at a surface's edge, pushed over it, stays where it is. Power is untouched: the
//! energy a batch carries does not change.

use std::num::NonZero;

use glam::Vec3;
use kiddo::{ImmutableKdTree, SquaredEuclidean};
use rayon::prelude::*;

use super::Photon;
use crate::bvh::SceneBvh;

/// Neighbours that push a photon (Spencer & Jones use a similar handful).
pub const NEIGHBOURS: usize = 8;

/// Largest step of one round, as a fraction of the neighbourhood's radius (the distance to
/// the farthest of the photon's [`NEIGHBOURS`]).
const MAX_STEP: f32 = 0.5;

/// Strength of the push: a round moves a photon by `GAIN` / [`NEIGHBOURS`] of the summed
/// repulsion. Tuned with [`REFRESH`] and [`MAX_STEP`] on the Cornell box (`bench quality`,
/// 10k photons, `receive = direction`, mean relMSE of seeds 1–4; 0.0377 unrelaxed): 6
/// rounds searching every third, gain 4 0.0298, gain 8 0.0302 (step 0.4: 0.0303); 4 rounds
/// searching every second, gain 4 0.0307, gain 8 0.0310, gain 16 (step 0.7) 0.0323.
const GAIN: f32 = 4.0;

/// Rounds between two neighbour searches (each round between them pushes against the
/// same neighbours from the same neighbourhood radius): the search is most of the cost
/// (two searches take ~12 of the ~16 ms 6 rounds cost for 10k photons on 2 cores; the
/// rounds ~2 ms, the final check against the scene ~1 ms). Cornell box as above,
/// gain 8: 6 rounds searching every second round 0.0307, every third 0.0302; 8 rounds
/// every fourth 0.0306, 9 every third 0.0315.
pub const REFRESH: u32 = 3;

/// Relaxes `photons`, whose surfaces' unit normals (facing where the photon came from)
/// are `normals`, for `iterations` rounds against the geometry of `bvh`; `eps` is the
/// scene's ray offset, meters.
///
/// Neighbours are sought every [`REFRESH`] rounds (the k-d tree and its queries are most
/// of the cost); the scene is asked once at the end whether each photon's whole way was
/// clear and still on its surface — else it stays where it landed.
pub fn relax(photons: &mut [Photon], normals: &[Vec3], bvh: &SceneBvh, iterations: u32, eps: f32) {
    assert_eq!(photons.len(), normals.len(), "a normal per photon");
    if photons.len() <= NEIGHBOURS || iterations == 0 {
        return;
    }
    let landed: Vec<Vec3> = photons.iter().map(|p| p.position).collect();
    let mut at = landed.clone();
    let mut near = (Vec::new(), Vec::new());
    for it in 0..iterations {
        if it % REFRESH == 0 {
            near = neighbours(&at, normals);
        }
        at = (0..at.len())
            .into_par_iter()
            .map(|i| at[i] + step(i, &at, normals[i], &near.0[i], near.1[i], eps))
            .collect();
    }
    let placed: Vec<Vec3> = (0..at.len())
        .into_par_iter()
        .map(|i| settle(bvh, landed[i], at[i], normals[i], eps))
        .collect();
    for (p, x) in photons.iter_mut().zip(placed) {
        p.position = x;
    }
}

/// Each photon's [`NEIGHBOURS`] nearest on its own surface (a normal within 26°, less than
/// a quarter of the neighbourhood's radius off its plane).
fn neighbours(at: &[Vec3], normals: &[Vec3]) -> (Vec<Vec<u32>>, Vec<f32>) {
    let points: Vec<[f32; 3]> = at.iter().map(|p| p.to_array()).collect();
    let tree: ImmutableKdTree<f32, 3> = ImmutableKdTree::new_from_slice(&points);
    let n = NonZero::new(NEIGHBOURS + 1).expect("NEIGHBOURS + 1 > 0");
    (0..at.len())
        .into_par_iter()
        .map(|i| {
            // The photon itself is its own nearest neighbour (distance 0). Unsorted: ~20%
            // faster than `nearest_n`.
            let near =
                tree.nearest_n_within::<SquaredEuclidean>(&points[i], f32::INFINITY, n, false);
            let r = near
                .iter()
                .fold(0.0f32, |a, m| a.max(m.distance))
                .max(0.0)
                .sqrt();
            let list: Vec<u32> = near
                .iter()
                .map(|m| m.item as u32)
                .filter(|&j| j as usize != i)
                .filter(|&j| {
                    let j = j as usize;
                    normals[j].dot(normals[i]) >= 0.9
                        && (at[i] - at[j]).dot(normals[i]).abs() <= 0.25 * r
                })
                .collect();
            (list, r)
        })
        .unzip()
}

/// One round's move of photon `i` (at `at[i]`, on a surface of `normal`): away from its
/// `near` neighbours in the surface's plane, Spencer & Jones' repulsion (stronger the
/// closer the neighbour), at most [`MAX_STEP`] of the neighbourhood's radius.
fn step(i: usize, at: &[Vec3], normal: Vec3, near: &[u32], r: f32, eps: f32) -> Vec3 {
    let x = at[i];
    if !(r > 0.0 && r.is_finite()) {
        return Vec3::ZERO;
    }
    let mut push = Vec3::ZERO;
    for &j in near {
        let v = x - at[j as usize];
        let t = v - normal * v.dot(normal);
        let d = t.length();
        if d > 0.0 {
            push += t / d * (r - d).max(0.0);
        } else {
            // Two photons in one place: part them along a direction of their own.
            let (a, _) = crate::sampling::basis(normal);
            push += a * if (i as u32) < j { r } else { -r };
        }
    }
    let step = push * GAIN / NEIGHBOURS as f32;
    let len = step.length();
    if len <= eps {
        return Vec3::ZERO;
    }
    step * (MAX_STEP * r / len).min(1.0)
}

/// Where a photon that landed at `from` and relaxed to `to` comes to rest: `to` (on the
/// surface found under it) if the way there along the surface is clear and the surface is
/// still there, about as far below as the photon is lifted to look (not a face inside
/// something above it); else `from`.
fn settle(bvh: &SceneBvh, from: Vec3, to: Vec3, normal: Vec3, eps: f32) -> Vec3 {
    let way = to - from;
    let len = way.length();
    if len <= eps {
        return from;
    }
    if bvh.occluded(from + normal * (eps * 4.0), way / len, len) {
        return from;
    }
    let h = (0.5 * len).max(eps * 8.0);
    let above = to + normal * h;
    match bvh.closest_hit(above, -normal, 2.0 * h) {
        Some(hit)
            if (hit.t - h).abs() < 0.5 * h
                && bvh.geometric_normal(hit.triangle).dot(normal).abs() > 0.99 =>
        {
            above - normal * hit.t
        }
        _ => from,
    }
}
