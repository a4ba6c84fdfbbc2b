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

use std::f32::consts::PI;
use std::num::NonZero;

use glam::Vec3;
use kiddo::{ImmutableKdTree, SquaredEuclidean};
use rayon::prelude::*;

use super::{Photon, View};
use crate::bvh::SceneBvh;

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
            // Neighbours farther than `reach` would give the largest radius anyway. Unsorted:
            // only the farthest of them counts (kiddo keeps a heap instead of a sorted vector;
            // a 10k-photon Cornell batch traced 5% faster).
            let near = tree.nearest_n_within::<SquaredEuclidean>(x, reach2, n, false);
            let d2 = if near.len() == n.get() {
                near.iter().map(|m| m.distance).fold(0.0, f32::max)
            } else {
                f32::INFINITY
            };
            let r = d2.max(0.0).sqrt() * scale;
            p.radius = if r.is_finite() { r.clamp(lo, hi) } else { hi };
        });
}

/// A photon is closed in when every wall around it stands within this fraction of its
/// radius.
pub const ENCLOSED: f32 = 0.5;

/// Directions along its surface in which [`enclose`] looks from a photon.
pub const ENCLOSURE_RAYS: u32 = 8;

/// Height above its surface, a fraction of its radius, at which [`enclose`] looks along it
/// for walls: a step lower than this is part of the surface (a tile's bevel, a seam), one
/// higher a wall (the dungeon measured the same at 0.02 and 0.05).
pub const WALL_LIFT: f32 = 0.05;

/// Keeps each photon's disk on its side of the walls around it: the client's splat tests
/// plane and facing, not visibility, so a disk reaching through a wall lights whatever
/// stands in its plane on the far side.
/// - **Closed in**: a photon with a wall on every side along its surface within
///   [`ENCLOSED`] of its radius (a light inside a fountain's bowl, a lamp in its housing, a
///   pocket under a stair) gets the radius of the farthest of them. The dungeon's two
///   point lights sit inside its fountains, and their light, which the path tracer finds
///   nowhere, showed as yellow pools around them.
/// - **Reaching past a wall into a darker place a client sees**: a disk that meets a wall
///   within its radius stops at that wall when beyond it the disk would land on a surface
///   one of `views` sees ([`lights_seen_beyond`]) where the batch's photons lie less than
///   [`DARKER_BEYOND`] as densely as on its own side. The dungeon's floor runs on past its
///   thin front wall, and the floor's photons lit the strip outside it at 5–7 times the
///   level's mean luminance where the path tracer finds 0.15–0.35 (outside view at
///   640×360, 80k photons a pass, relMSE after 1 / 32 passes 0.494 / 0.218 → 0.353 /
///   0.143). No views: no disk stops at a wall.
///
/// [`ENCLOSURE_RAYS`] rays along the photon's surface (its unit geometric normal
/// `normals[i]`), lifted by [`WALL_LIFT`] of its radius: without views, cast until one runs
/// free for [`ENCLOSED`] of the radius (an open photon costs one ray); with views, all of
/// them over the whole radius. No radius falls below `least` (meters; a batch's smallest
/// radius sets its packing's position step). Powers are untouched.
pub fn enclose(
    photons: &mut [Photon],
    normals: &[Vec3],
    bvh: &SceneBvh,
    eps: f32,
    least: f32,
    views: &[View],
) {
    assert_eq!(photons.len(), normals.len(), "a normal per photon");
    let receiving = Receiving::default();
    // Where the batch's photons landed, to weigh what lies past a wall (only where a view
    // could see past one).
    let lit = (!views.is_empty() && !photons.is_empty()).then(|| Lit::new(photons));
    photons
        .par_iter_mut()
        .zip(normals.par_iter())
        .enumerate()
        .for_each(|(i, (p, &n))| {
            let r = p.radius;
            if !(r > least && r > 8.0 * eps && r.is_finite()) || n == Vec3::ZERO {
                return;
            }
            let (a, b) = crate::sampling::basis(n);
            let origin = p.position + n * (WALL_LIFT * r).max(4.0 * eps);
            // Turned by the photon's index, so that no direction is always left out.
            let turn = i as f32 * 0.618_034;
            let (mut farthest, mut closed, mut reach) = (0.0f32, true, r);
            // Without a view of its disk, only walls within ENCLOSED of the radius matter,
            // and the first ray that runs free settles it: an open photon costs one short ray.
            let lit = lit
                .as_ref()
                .filter(|_| views.iter().any(|v| in_view(v, p.position, r)));
            let len = if lit.is_some() { r } else { ENCLOSED * r };
            for k in 0..ENCLOSURE_RAYS {
                let angle = (k as f32 + turn) * std::f32::consts::TAU / ENCLOSURE_RAYS as f32;
                let dir = a * angle.cos() + b * angle.sin();
                let Some(hit) = bvh.closest_hit(origin, dir, len) else {
                    closed = false;
                    match lit {
                        Some(_) => continue,
                        None => break,
                    }
                };
                if hit.t < ENCLOSED * r {
                    farthest = farthest.max(hit.t);
                } else {
                    closed = false;
                }
                if hit.t < reach
                    && lit.is_some_and(|l| {
                        lights_seen_beyond(p, n, dir, hit.t, bvh, receiving, eps, views)
                            && l.darker_beyond(p, dir, hit.t)
                    })
                {
                    reach = hit.t;
                }
            }
            // Walls all round but some of them far (a tunnel's, a room's with pillars): only
            // a wall with a seen, darker place behind it stops the disk.
            let radius = if closed { farthest } else { r }.min(reach);
            p.radius = radius.max(least).max(4.0 * eps).min(r);
        });
}

/// Whether photon `p`'s disk (its surface's unit normal `n`), reaching along `dir` past a
/// wall `t` away, lands beyond it where a client sees: a point halfway between the wall and
/// the disk's edge receives the photon as the client's splat would, and one of `views` sees
/// that point ([`seen`]). Where no one looks past the wall (below a floor, behind a
/// courtyard's wall seen from inside it) the disk keeps its radius. Stopping disks at every
/// wall with open ground behind it made radii near walls small and noisy, and their
/// estimate high along the walls' feet: relMSE after one pass, the dungeon's courtyard
/// 0.108 → 0.285, its fountains 0.167 → 0.238, `city:250000` 0.064 → 0.077; with the
/// views, the fountains still read 0.229, and the darker-beyond test brought them to
/// 0.185 (after 32 passes 0.108 → 0.105).
#[allow(clippy::too_many_arguments)]
fn lights_seen_beyond(
    p: &Photon,
    n: Vec3,
    dir: Vec3,
    t: f32,
    bvh: &SceneBvh,
    receiving: Receiving,
    eps: f32,
    views: &[View],
) -> bool {
    let h = (receiving.flatten * p.radius).max(4.0 * eps);
    let at = p.position + dir * (0.5 * (t + p.radius));
    received_at(p, at + n * h, -n, 2.0 * h, bvh, receiving)
        .is_some_and(|q| views.iter().any(|v| seen(v, bvh, q + n * (4.0 * eps))))
}

/// A batch's photons as they landed, to tell how densely they lie in a region.
struct Lit {
    photons: Vec<Photon>,
    tree: ImmutableKdTree<f32, 3>,
}

/// Below this share of the photons' density on a photon's side of a wall, the far side is
/// dark enough that a disk reaching it shows (the dungeon's strip outside its front wall);
/// above it, the disk only blurs alike light (a step between two lit floors) and keeps its
/// radius.
pub const DARKER_BEYOND: f32 = 0.5;

impl Lit {
    fn new(photons: &[Photon]) -> Self {
        let points: Vec<[f32; 3]> = photons.iter().map(|p| p.position.to_array()).collect();
        Lit {
            photons: photons.to_vec(),
            tree: ImmutableKdTree::new_from_slice(&points),
        }
    }

    /// Whether the batch's photons that light as `p` does lie less densely beyond a wall `t`
    /// along `dir` from `p` than [`DARKER_BEYOND`] times their density on `p`'s side: counted
    /// within `p`'s radius around `p` (its side only) and around a point halfway between the
    /// wall and the disk's edge (the far side only).
    fn darker_beyond(&self, p: &Photon, dir: Vec3, t: f32) -> bool {
        let r = p.radius;
        let wall = p.position.dot(dir) + t;
        let count = |at: Vec3, beyond: bool| {
            self.tree
                .within_unsorted::<SquaredEuclidean>(&at.to_array(), r * r)
                .iter()
                .filter(|m| {
                    let q = &self.photons[m.item as usize];
                    (q.position.dot(dir) > wall) == beyond
                        && q.receive == p.receive
                        && q.direction.dot(p.direction) > 0.8
                })
                .count() as f32
        };
        let here = count(p.position, false) / (PI * r * r - cap_area(r, t));
        let half = 0.5 * (r - t);
        let at = p.position + dir * (t + half);
        let beyond = count(at, true) / (PI * r * r - cap_area(r, half));
        beyond < DARKER_BEYOND * here
    }
}

/// Area of the part of a disk of radius `r` beyond a chord `s` from its centre (0 ≤ s ≤ r).
fn cap_area(r: f32, s: f32) -> f32 {
    let s = s.clamp(0.0, r);
    r * r * (s / r).acos() - s * (r * r - s * s).max(0.0).sqrt()
}

/// Whether `view`'s camera sees point `q`: in its view ([`in_view`]) with nothing between.
pub fn seen(view: &View, bvh: &SceneBvh, q: Vec3) -> bool {
    let to = q - view.camera.position;
    let d = to.length();
    in_view(view, q, 0.0) && !bvh.occluded(view.camera.position, to / d, d * (1.0 - 1e-4))
}

/// Whether some of the ball of `radius` around `center` lies inside the cone around
/// `view`'s axis that holds its image's corners (or holds its eye).
pub fn in_view(view: &View, center: Vec3, radius: f32) -> bool {
    let c = &view.camera;
    let to = center - c.position;
    let (d, forward) = (to.length(), (c.target - c.position).normalize_or_zero());
    if !d.is_finite() || forward == Vec3::ZERO {
        return false;
    }
    if d <= radius {
        return d > 0.0 || radius > 0.0;
    }
    let corner = (c.fov_y_rad * 0.5).tan() * (1.0 + view.aspect * view.aspect).sqrt();
    let off_axis = (to.dot(forward) / d).clamp(-1.0, 1.0).acos();
    off_axis - (radius / d).asin() <= corner.atan()
}

/// What the client's splat accepts (mirrors `kernel_at` in `splat.wgsl`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Receiving {
    /// A point farther than `flatten × r` off its own plane does not receive a photon.
    pub flatten: f32,
    /// Least cosine between a surface's normal and a photon carrying its surface's normal.
    pub facing: f32,
}

impl Default for Receiving {
    fn default() -> Self {
        let s = super::splat::SplatSettings::default();
        Receiving {
            flatten: s.flatten,
            facing: s.facing,
        }
    }
}

/// A disk keeps its radius when at least this share of its kernel lands on surfaces that
/// receive it.
pub const FIT_KEEP: f32 = 0.7;

/// Points of a disk [`fit`] looks at per round (8 measured the same as 4 in the dungeon).
pub const FIT_SAMPLES: u32 = 4;

/// Halves the disks that overhang their surface, up to `rounds` times: a photon's splat
/// spreads its power over its whole disk, but the client deposits only on the points that
/// receive it (within the flattened disk, facing within 37° of the photon's normal), so
/// the share of a disk that hangs past a surface's edge or across a curved one (a pot, a
/// fountain's stem, a pillar: a 2 m disk spans normals the facing test refuses) is light
/// lost — the dungeon's small round things showed at half their light. While less than
/// [`FIT_KEEP`] of its kernel lands (looked at in [`FIT_SAMPLES`] points, rays straight
/// down the surface's normal `normals[i]` as the client's test would see them), a disk is
/// halved, never below `least` (meters; a batch's smallest radius sets its packing's
/// position step). Renormalising the power by the share that lands instead overshot in
/// dark pixels (relMSE 0.22 → 0.43 in the dungeon; looked at in 16 points and by at most
/// 1 / 0.7 after the halvings, the outside view at 640×360 after 32 passes of 80k photons
/// read 0.143 → 0.188 for an energy ratio of 0.86 → 1.00); a smaller disk keeps the estimate
/// unbiased and trades the bias for noise, which progressive passes average away. Only
/// photons that carry their surface's normal ([`super::Receive::Normal`]): one that
/// carries its direction lights the surface past a corner on purpose. Powers are
/// untouched. Returns how many disks were halved.
pub fn fit(
    photons: &mut [Photon],
    normals: &[Vec3],
    bvh: &SceneBvh,
    eps: f32,
    least: f32,
    rounds: u32,
    receiving: Receiving,
) -> usize {
    assert_eq!(photons.len(), normals.len(), "a normal per photon");
    if rounds == 0 {
        return 0;
    }
    photons
        .par_iter_mut()
        .zip(normals.par_iter())
        .enumerate()
        .map(|(i, (p, &n))| {
            if p.receive != super::Receive::Normal {
                return 0;
            }
            let mut halved = 0;
            for _ in 0..rounds {
                if p.radius * 0.5 < least
                    || landed_share(p, n, i as u32, bvh, FIT_SAMPLES, receiving, eps) >= FIT_KEEP
                {
                    break;
                }
                p.radius *= 0.5;
                halved = 1;
            }
            halved
        })
        .sum()
}

/// The share of photon `p`'s cone kernel (1 − s/r) that falls on receiving surfaces, from
/// `samples` points of its disk on a Vogel spiral turned by the photon's index.
fn landed_share(
    p: &Photon,
    normal: Vec3,
    index: u32,
    bvh: &SceneBvh,
    samples: u32,
    receiving: Receiving,
    eps: f32,
) -> f32 {
    let r = p.radius;
    if !(r > eps && r.is_finite()) || normal == Vec3::ZERO {
        return 1.0;
    }
    let (a, b) = crate::sampling::basis(normal);
    let h = (receiving.flatten * r).max(4.0 * eps);
    let turn = index as f32 * 0.618_034 * std::f32::consts::TAU;
    let (mut landed, mut total) = (0.0f32, 0.0f32);
    for j in 0..samples {
        let u = (j as f32 + 0.5) / samples as f32;
        let s = r * u.sqrt();
        let theta = turn + j as f32 * GOLDEN_ANGLE;
        let kappa = 1.0 - s / r;
        total += kappa;
        let at = p.position + (a * theta.cos() + b * theta.sin()) * s;
        if received_at(p, at + normal * h, -normal, 2.0 * h, bvh, receiving).is_some() {
            landed += kappa;
        }
    }
    if total > 0.0 { landed / total } else { 1.0 }
}

/// 2π (1 − 1/φ): consecutive points of a Vogel spiral.
const GOLDEN_ANGLE: f32 = 2.399_963;

/// Where the first surface the ray from `origin` along `dir` meets within `len` is, when
/// it receives photon `p` as the client's splat would.
fn received_at(
    p: &Photon,
    origin: Vec3,
    dir: Vec3,
    len: f32,
    bvh: &SceneBvh,
    receiving: Receiving,
) -> Option<Vec3> {
    let hit = bvh.closest_hit(origin, dir, len)?;
    let mut n = bvh.shading_normal(&hit);
    if n.dot(dir) > 0.0 {
        n = -n;
    }
    let q = origin + dir * hit.t;
    let off_plane = (q - p.position).dot(n).abs();
    let against = -n.dot(p.direction);
    let least = match p.receive {
        super::Receive::Normal => receiving.facing,
        super::Receive::Direction => 0.0,
    };
    (off_plane <= receiving.flatten * p.radius && against > least).then_some(q)
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

    /// A floor (y = 0, 20 m square).
    fn floor() -> cloudlight_scenes::Mesh {
        let v = Vec3::new;
        let mut mesh = cloudlight_scenes::Mesh::default();
        mesh.push_quad(
            v(-10.0, 0.0, -10.0),
            v(-10.0, 0.0, 10.0),
            v(10.0, 0.0, 10.0),
            v(10.0, 0.0, -10.0),
        );
        mesh
    }

    /// The BVH of a scene of `mesh` alone.
    fn bvh_of(mesh: cloudlight_scenes::Mesh) -> crate::bvh::SceneBvh {
        let scene = cloudlight_scenes::Scene {
            name: "test".into(),
            materials: vec![cloudlight_scenes::Material::diffuse(
                "grey",
                Vec3::splat(0.5),
            )],
            objects: vec![cloudlight_scenes::Object {
                name: "test".into(),
                mesh,
                material: 0,
                motion: cloudlight_scenes::Motion::identity(),
            }],
            lights: Vec::new(),
            cameras: Vec::new(),
        };
        crate::bvh::SceneBvh::at(&scene, 0.0, crate::bvh::BvhKind::default())
    }

    /// A floor with a closed box of half-size `h` standing on it at the origin (four walls
    /// and a lid; the floor is its bottom).
    fn floor_and_box(h: f32) -> crate::bvh::SceneBvh {
        let v = Vec3::new;
        let mut mesh = floor();
        let c = [v(-h, 0.0, -h), v(h, 0.0, -h), v(h, 0.0, h), v(-h, 0.0, h)];
        for k in 0..4 {
            let (a, b) = (c[k], c[(k + 1) % 4]);
            mesh.push_quad(a, b, b + Vec3::Y * 2.0 * h, a + Vec3::Y * 2.0 * h);
        }
        let top = c.map(|p| p + Vec3::Y * 2.0 * h);
        mesh.push_quad(top[0], top[1], top[2], top[3]);
        bvh_of(mesh)
    }

    /// A floor split by a thin wall (one quad) along x = 0, `height` tall: the floor runs
    /// on under it.
    fn floor_and_wall(height: f32) -> crate::bvh::SceneBvh {
        let v = Vec3::new;
        let mut mesh = floor();
        mesh.push_quad(
            v(0.0, 0.0, -10.0),
            v(0.0, height, -10.0),
            v(0.0, height, 10.0),
            v(0.0, 0.0, 10.0),
        );
        bvh_of(mesh)
    }

    /// A view from `eye` toward `target`, 60° high, square.
    fn view(eye: Vec3, target: Vec3) -> View {
        View {
            camera: cloudlight_scenes::Camera {
                position: eye,
                target,
                up: Vec3::Y,
                fov_y_rad: 60f32.to_radians(),
            },
            aspect: 1.0,
        }
    }

    /// Photons of 1 m disks every 10 cm on the floor over x in [`x0`, `x1`), |z| < 4.
    fn lit_floor(x0: f32, x1: f32) -> Vec<Photon> {
        let steps = ((x1 - x0) / 0.1).round() as usize;
        (0..steps * 80)
            .map(|i| Photon {
                radius: 1.0,
                ..photon(Vec3::new(
                    x0 + 0.05 + (i % steps) as f32 * 0.1,
                    0.0,
                    -3.95 + (i / steps) as f32 * 0.1,
                ))
            })
            .collect()
    }

    #[test]
    fn a_disk_stops_at_a_wall_past_which_a_view_sees_a_darker_floor() {
        let bvh = floor_and_wall(0.5);
        let beyond = view(Vec3::new(5.0, 3.0, 0.0), Vec3::new(1.0, 0.0, 0.0));
        let enclosed = |photons: &[Photon], views: &[View]| {
            let mut p = photons.to_vec();
            let normals = vec![Vec3::Y; p.len()];
            enclose(&mut p, &normals, &bvh, 1e-4, 0.05, views);
            p
        };
        // Lit on one side of the wall only, seen from the dark side: the disks within a
        // radius of the wall end at it (the nearest of 8 rays is within 22.5° of the wall's
        // normal), the others keep theirs.
        let one_side = lit_floor(-3.0, 0.0);
        let stopped = enclosed(&one_side, std::slice::from_ref(&beyond));
        for (p, before) in stopped.iter().zip(&one_side) {
            let to_wall = -p.position.x;
            if to_wall < 0.9 && p.position.z.abs() < 1.0 {
                let bound = (to_wall / 22.5f32.to_radians().cos()).max(0.05);
                assert!(
                    p.radius <= bound + 1e-3,
                    "{:?}: {} > {bound}",
                    p.position,
                    p.radius
                );
            } else if to_wall > 1.05 {
                assert_eq!(p.radius, before.radius, "{:?}", p.position);
            }
        }
        // Photons away from the lit patch's edges (past which the floor is dark) keep their
        // radii: without views; seen from the lit side, over the wall that hides the floor
        // behind it; lit alike on both sides.
        let unchanged = |photons: &[Photon], views: &[View]| {
            enclosed(photons, views)
                .iter()
                .zip(photons)
                .filter(|(a, _)| a.position.z.abs() < 2.0)
                .all(|(a, b)| a.radius == b.radius)
        };
        assert!(unchanged(&one_side, &[]));
        let lit_side = view(Vec3::new(-5.0, 3.0, 0.0), Vec3::new(-1.0, 0.0, 0.0));
        assert!(unchanged(&one_side, &[lit_side]));
        let both_sides = lit_floor(-3.0, 3.0);
        assert!(unchanged(&both_sides, std::slice::from_ref(&beyond)));
    }

    #[test]
    fn a_view_sees_points_in_its_frustum_with_nothing_between() {
        let bvh = floor_and_wall(0.5);
        let v = view(Vec3::new(5.0, 3.0, 0.0), Vec3::new(1.0, 0.0, 0.0));
        let up = Vec3::Y * 1e-3;
        assert!(seen(&v, &bvh, Vec3::new(1.0, 0.0, 0.0) + up));
        assert!(seen(&v, &bvh, Vec3::new(0.3, 0.0, 1.0) + up));
        // Behind the wall, behind the eye, far off the axis.
        assert!(!seen(&v, &bvh, Vec3::new(-0.3, 0.0, 0.0) + up));
        assert!(!seen(&v, &bvh, Vec3::new(8.0, 3.0, 0.0)));
        assert!(!seen(&v, &bvh, Vec3::new(4.0, 0.0, 8.0) + up));
        // A degenerate view sees nothing.
        assert!(!seen(&view(Vec3::ONE, Vec3::ONE), &bvh, Vec3::ZERO + up));
        // A ball is in view when some of it is: one off to the side by its radius.
        let side = Vec3::new(4.0, 0.0, 8.0);
        assert!(!in_view(&v, side, 0.5));
        assert!(in_view(&v, side, 6.0));
        assert!(in_view(&v, v.camera.position, 0.1));
    }

    #[test]
    fn a_photon_closed_in_keeps_its_disk_inside_and_an_open_one_keeps_its_own() {
        // A 0.5 m box on a floor; photons on the floor with disks of 1.5 m: inside the box,
        // at its outer wall, and in the open.
        let bvh = floor_and_box(0.25);
        let at = [
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(0.2, 0.0, -0.1),
            Vec3::new(0.3, 0.0, 0.0),
            Vec3::new(3.0, 0.0, 2.0),
        ];
        let mut p: Vec<Photon> = at
            .iter()
            .map(|&x| Photon {
                radius: 1.5,
                ..photon(x)
            })
            .collect();
        let normals = vec![Vec3::Y; p.len()];
        enclose(&mut p, &normals, &bvh, 1e-4, 0.05, &[]);
        // Inside: its farthest wall (≤ the box's half diagonal plus its offset), no more.
        for q in &p[..2] {
            let farthest = (q.position.x.abs() + 0.25).hypot(q.position.z.abs() + 0.25);
            assert!(
                q.radius >= 0.05 && q.radius <= farthest + 1e-3,
                "{:?}: {} (walls within {farthest})",
                q.position,
                q.radius
            );
        }
        // Against the box's outside and in the open: the way is free on one side at least.
        assert_eq!(p[2].radius, 1.5);
        assert_eq!(p[3].radius, 1.5);
        // The smallest radius is kept to; radii already below it, or a lone degenerate
        // photon, are left alone.
        let mut q = vec![
            Photon {
                radius: 1.5,
                ..photon(Vec3::ZERO)
            },
            Photon {
                radius: 0.01,
                ..photon(Vec3::ZERO)
            },
        ];
        enclose(&mut q, &[Vec3::Y, Vec3::ZERO], &bvh, 1e-4, 0.6, &[]);
        assert_eq!((q[0].radius, q[1].radius), (0.6, 0.01));
        enclose(&mut [], &[], &bvh, 1e-4, 0.6, &[]);
    }

    #[test]
    fn a_disk_that_overhangs_its_surface_is_halved_and_one_that_lies_on_it_is_not() {
        // A 0.5 m box on a floor; disks of 1.5 m on its lid, on its side, in the open.
        let bvh = floor_and_box(0.25);
        let on = |x: Vec3, n: Vec3| Photon {
            radius: 1.5,
            direction: -n,
            power: Vec3::new(1.0, 2.0, 3.0),
            ..photon(x)
        };
        let lid = on(Vec3::new(0.0, 0.5, 0.0), Vec3::Y);
        let side = on(Vec3::new(0.25, 0.25, 0.0), Vec3::X);
        let open = on(Vec3::new(3.0, 0.0, 2.0), Vec3::Y);
        let along = Photon {
            receive: super::super::Receive::Direction,
            ..lid
        };
        let mut p = vec![lid, side, open, along];
        let normals = vec![Vec3::Y, Vec3::X, Vec3::Y, Vec3::Y];
        let halved = fit(&mut p, &normals, &bvh, 1e-4, 0.05, 3, Receiving::default());
        assert_eq!(halved, 2);
        // The lid's and the side's disks come down to the box's size (a 0.5 m face), no
        // lower than three halvings.
        for q in &p[..2] {
            assert!(
                (0.1875..=0.375).contains(&q.radius),
                "{:?}: {}",
                q.position,
                q.radius
            );
        }
        // The open floor's disk lies on its surface; a photon that carries its direction
        // lights past the edge on purpose; powers are untouched.
        assert_eq!((p[2].radius, p[3].radius), (1.5, 1.5));
        assert!(p.iter().all(|q| q.power == Vec3::new(1.0, 2.0, 3.0)));
        // Never below the least radius; no rounds, no change.
        let mut q = vec![lid];
        fit(&mut q, &[Vec3::Y], &bvh, 1e-4, 0.6, 3, Receiving::default());
        assert_eq!(q[0].radius, 0.75);
        let mut q = vec![lid];
        assert_eq!(
            fit(
                &mut q,
                &[Vec3::Y],
                &bvh,
                1e-4,
                0.05,
                0,
                Receiving::default()
            ),
            0
        );
        assert_eq!(q[0].radius, 1.5);
        assert_eq!(
            fit(&mut [], &[], &bvh, 1e-4, 0.05, 3, Receiving::default()),
            0
        );
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
