//! Basis functions: clusters of mutually visible texels with similar normals, each with a
//! radius of influence; every texel blends up to [`MAX_BASES_PER_TEXEL`] of them.
//!
//! Phases (offline, once per scene):
//! 1. **Seeds** at a spacing s = √(A / N) set by the basis budget N (valid area A): texels in
//!    a seeded random order become seeds unless a seed with a similar normal lies within s
//!    (Poisson-disk dart throwing over a hash grid: a linear-time stand-in for
//!    farthest-point sampling with the same guarantees — no two compatible seeds closer
//!    than s, every texel within s of one).
//! 2. **Lloyd iterations**: each texel joins the nearest centre with a similar normal
//!    (n·n_k ≥ cos `max_normal_deg`) that it sees (a visibility ray); a texel that finds none
//!    seeds a new basis (so walls split clusters). Each centre moves to the member nearest
//!    its members' mean (centres stay on the surface).
//! 3. **Weights**: w_k = (1 − (d/r_k)²)₊² · max(0, n·n_k)^p · vis, over the bases within
//!    reach, the largest [`MAX_BASES_PER_TEXEL`] kept and normalised to sum to 1.
//! 4. **Members**: each basis's texels in Morton order over the atlas, which the gather
//!    spreads a basis's rays over.

use std::collections::HashMap;

use glam::{IVec3, Vec3};
use rayon::prelude::*;

use crate::bvh::SceneBvh;
use crate::sampling::{Rng, morton2};

use super::texels::TexelSurface;

/// Most bases one texel blends (the paper's eight).
pub const MAX_BASES_PER_TEXEL: usize = 8;

/// How bases are made.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BasisSettings {
    /// Valid texels per basis: sets the basis budget (the Cornell box's ~16k texels / 330 ≈
    /// the paper's 50).
    pub texels_per_basis: f32,
    /// Lloyd iterations.
    pub lloyd_iterations: u32,
    /// Largest angle between a texel's normal and its basis's, degrees.
    pub max_normal_deg: f32,
    /// Exponent p of the normal term of the blend weights.
    pub normal_power: f32,
    /// Radius of influence as a multiple of the farthest member's distance.
    pub radius_scale: f32,
    /// Seed of the seeding order.
    pub seed: u64,
}

impl Default for BasisSettings {
    fn default() -> Self {
        BasisSettings {
            texels_per_basis: 180.0,
            lloyd_iterations: 3,
            max_normal_deg: 30.0,
            normal_power: 8.0,
            radius_scale: 1.5,
            seed: 1,
        }
    }
}

/// One basis function.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Basis {
    /// The texel at its centre (where it gathers).
    pub texel: u32,
    /// Texels assigned to it.
    pub members: u32,
    /// Where its members start in [`Bases::members`].
    pub first: u32,
    /// Radius of influence, meters.
    pub radius_m: f32,
}

/// The bases of a map and each texel's blend.
#[derive(Clone, Debug, PartialEq)]
pub struct Bases {
    /// The bases.
    pub bases: Vec<Basis>,
    /// Per texel: `(basis, weight)` pairs, weights summing to 1 (empty for invalid texels).
    pub weights: Vec<Vec<(u32, f32)>>,
    /// Every valid texel once, grouped by basis (basis k's are
    /// `members[first..first + members]`), each group in Morton order over the atlas so that
    /// an even stride through it is an even spread over the basis's area.
    pub members: Vec<u32>,
}

impl Bases {
    /// The texels of basis `k`, in Morton order over the atlas.
    pub fn members_of(&self, k: usize) -> &[u32] {
        let b = &self.bases[k];
        &self.members[b.first as usize..(b.first + b.members) as usize]
    }
}

struct Grid {
    cell: f32,
    cells: HashMap<IVec3, Vec<u32>>,
}

impl Grid {
    fn new(cell: f32) -> Self {
        Grid {
            cell: cell.max(1e-9),
            cells: HashMap::new(),
        }
    }

    fn key(&self, p: Vec3) -> IVec3 {
        (p / self.cell).floor().as_ivec3()
    }

    fn insert(&mut self, p: Vec3, id: u32) {
        self.cells.entry(self.key(p)).or_default().push(id);
    }

    /// Ids in the 27 cells around `p`.
    fn near(&self, p: Vec3) -> impl Iterator<Item = u32> + '_ {
        let k = self.key(p);
        (-1..=1)
            .flat_map(move |z| {
                (-1..=1).flat_map(move |y| {
                    (-1..=1).filter_map(move |x| self.cells.get(&(k + IVec3::new(x, y, z))))
                })
            })
            .flatten()
            .copied()
    }
}

/// Whether `a` (normal `na`) and `b` (normal `nb`) see each other.
fn visible(bvh: &SceneBvh, a: Vec3, na: Vec3, b: Vec3, nb: Vec3, eps: f32) -> bool {
    let (o, e) = (a + na * eps, b + nb * eps);
    let d = e - o;
    let len = d.length();
    len <= eps || !bvh.occluded(o, d / len, len * (1.0 - 1e-4))
}

/// Clusters the valid texels of `surface` into bases (see the module's phases).
pub fn build(surface: &TexelSurface, bvh: &SceneBvh, s: &BasisSettings) -> Bases {
    let valid: Vec<u32> = (0..surface.valid.len() as u32)
        .filter(|&i| surface.valid[i as usize])
        .collect();
    let n = surface.valid.len();
    if valid.is_empty() {
        return Bases {
            bases: Vec::new(),
            weights: vec![Vec::new(); n],
            members: Vec::new(),
        };
    }
    let (pos, nrm) = (&surface.positions, &surface.normals);
    let area = valid.len() as f32 * surface.texel_m * surface.texel_m;
    let budget = (valid.len() as f32 / s.texels_per_basis.max(1.0)).max(1.0);
    let spacing = (area / budget).sqrt().max(surface.texel_m);
    let cos_max = s.max_normal_deg.to_radians().cos();
    let eps = surface.texel_m * 1e-3;

    // 1. Seeds.
    let mut order = valid.clone();
    let mut rng = Rng::new(s.seed, 0x6261_7369);
    for i in (1..order.len()).rev() {
        order.swap(i, (rng.next_u64() % (i as u64 + 1)) as usize);
    }
    let mut grid = Grid::new(spacing);
    let mut centres: Vec<u32> = Vec::new();
    for &t in &order {
        let (p, nt) = (pos[t as usize], nrm[t as usize]);
        let covered = grid.near(p).any(|c| {
            let c = centres[c as usize] as usize;
            pos[c].distance(p) < spacing && nrm[c].dot(nt) >= cos_max
        });
        if !covered {
            grid.insert(p, centres.len() as u32);
            centres.push(t);
        }
    }

    // 2. Lloyd iterations.
    let mut assignment = vec![u32::MAX; n];
    for _ in 0..s.lloyd_iterations.max(1) {
        let extra;
        (assignment, extra) = assign(&valid, &centres, surface, bvh, spacing, cos_max, eps);
        centres.extend(extra);
        centres = recentre(&valid, &assignment, &centres, surface);
    }
    let extra;
    (assignment, extra) = assign(&valid, &centres, surface, bvh, spacing, cos_max, eps);
    centres.extend(extra);
    let mut radius = vec![surface.texel_m * 2.0; centres.len()];
    for &t in &valid {
        let k = assignment[t as usize] as usize;
        let d = pos[t as usize].distance(pos[centres[k] as usize]) * s.radius_scale;
        radius[k] = radius[k].max(d);
    }
    // Members grouped by basis, each group in Morton order over the atlas.
    let width = surface.width;
    let mut grouped: Vec<(u32, u64, u32)> = valid
        .iter()
        .map(|&t| (assignment[t as usize], morton2(t % width, t / width), t))
        .collect();
    grouped.sort_unstable();
    let mut first = vec![0u32; centres.len()];
    let mut members = vec![0u32; centres.len()];
    for (i, &(k, _, _)) in grouped.iter().enumerate().rev() {
        first[k as usize] = i as u32;
        members[k as usize] += 1;
    }
    let bases: Vec<Basis> = (0..centres.len())
        .map(|k| Basis {
            texel: centres[k],
            members: members[k],
            first: first[k],
            radius_m: radius[k],
        })
        .collect();
    let members: Vec<u32> = grouped.into_iter().map(|(_, _, t)| t).collect();

    // 3. Weights.
    let reach = radius.iter().copied().fold(0.0, f32::max);
    let mut grid = Grid::new(reach);
    for (k, b) in bases.iter().enumerate() {
        grid.insert(pos[b.texel as usize], k as u32);
    }
    let weights = (0..n as u32)
        .into_par_iter()
        .map(|t| {
            if !surface.valid[t as usize] {
                return Vec::new();
            }
            blend(
                t,
                assignment[t as usize],
                &bases,
                &grid,
                surface,
                bvh,
                s,
                eps,
            )
        })
        .collect();
    Bases {
        bases,
        weights,
        members,
    }
}

/// The nearest compatible, visible centre of every valid texel, and the texels without one,
/// which seed new bases (numbered after `centres`, in texel order: deterministic).
fn assign(
    valid: &[u32],
    centres: &[u32],
    surface: &TexelSurface,
    bvh: &SceneBvh,
    spacing: f32,
    cos_max: f32,
    eps: f32,
) -> (Vec<u32>, Vec<u32>) {
    let (pos, nrm) = (&surface.positions, &surface.normals);
    let cell = spacing * 2.0;
    let mut grid = Grid::new(cell);
    for (k, &c) in centres.iter().enumerate() {
        grid.insert(pos[c as usize], k as u32);
    }
    let found: Vec<Option<u32>> = valid
        .par_iter()
        .map(|&t| {
            let (p, nt) = (pos[t as usize], nrm[t as usize]);
            let mut near: Vec<(f32, u32)> = grid
                .near(p)
                .filter(|&k| nrm[centres[k as usize] as usize].dot(nt) >= cos_max)
                .map(|k| (pos[centres[k as usize] as usize].distance_squared(p), k))
                .filter(|(d2, _)| *d2 <= cell * cell)
                .collect();
            near.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            near.into_iter().take(4).map(|(_, k)| k).find(|&k| {
                let c = centres[k as usize] as usize;
                c == t as usize || visible(bvh, p, nt, pos[c], nrm[c], eps)
            })
        })
        .collect();
    let mut assignment = vec![u32::MAX; surface.valid.len()];
    let mut extra: Vec<u32> = Vec::new();
    let mut extra_grid = Grid::new(spacing);
    for (&t, k) in valid.iter().zip(found) {
        let k = k.unwrap_or_else(|| {
            // Join a basis seeded in this pass if one is near, similar and visible.
            let (p, nt) = (pos[t as usize], nrm[t as usize]);
            let hit = extra_grid.near(p).find(|&e| {
                let c = extra[e as usize] as usize;
                pos[c].distance(p) < spacing
                    && nrm[c].dot(nt) >= cos_max
                    && visible(bvh, p, nt, pos[c], nrm[c], eps)
            });
            match hit {
                Some(e) => (centres.len() + e as usize) as u32,
                None => {
                    extra_grid.insert(p, extra.len() as u32);
                    extra.push(t);
                    (centres.len() + extra.len() - 1) as u32
                }
            }
        });
        assignment[t as usize] = k;
    }
    (assignment, extra)
}

/// New centres: per basis, the member nearest the members' mean position.
fn recentre(
    valid: &[u32],
    assignment: &[u32],
    centres: &[u32],
    surface: &TexelSurface,
) -> Vec<u32> {
    let all = centres;
    let pos = &surface.positions;
    let mut sum = vec![(Vec3::ZERO, 0u32); all.len()];
    for &t in valid {
        let k = assignment[t as usize] as usize;
        sum[k].0 += pos[t as usize];
        sum[k].1 += 1;
    }
    let mut best: Vec<(f32, u32)> = all.iter().map(|&c| (f32::INFINITY, c)).collect();
    for &t in valid {
        let k = assignment[t as usize] as usize;
        let mean = sum[k].0 / sum[k].1.max(1) as f32;
        let d = pos[t as usize].distance_squared(mean);
        if d < best[k].0 {
            best[k] = (d, t);
        }
    }
    best.into_iter()
        .zip(sum)
        .filter(|(_, (_, count))| *count > 0)
        .map(|((_, t), _)| t)
        .collect()
}

/// Blend weights of texel `t` (assigned to basis `own`).
#[allow(clippy::too_many_arguments)]
fn blend(
    t: u32,
    own: u32,
    bases: &[Basis],
    grid: &Grid,
    surface: &TexelSurface,
    bvh: &SceneBvh,
    s: &BasisSettings,
    eps: f32,
) -> Vec<(u32, f32)> {
    let (pos, nrm) = (&surface.positions, &surface.normals);
    let (p, nt) = (pos[t as usize], nrm[t as usize]);
    let weight = |k: u32| {
        let b = &bases[k as usize];
        let c = b.texel as usize;
        let q = pos[c].distance(p) / b.radius_m;
        let radial = (1.0 - q * q).max(0.0).powi(2);
        radial * nt.dot(nrm[c]).max(0.0).powf(s.normal_power)
    };
    let mut cands: Vec<(f32, u32)> = grid
        .near(p)
        .filter(|&k| k != own)
        .map(|k| (weight(k), k))
        .filter(|(w, _)| *w > 0.0)
        .collect();
    cands.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
    let mut out = vec![(own, weight(own).max(1e-6))];
    for (w, k) in cands {
        if out.len() == MAX_BASES_PER_TEXEL {
            break;
        }
        let c = bases[k as usize].texel as usize;
        if visible(bvh, p, nt, pos[c], nrm[c], eps) {
            out.push((k, w));
        }
    }
    let total: f32 = out.iter().map(|(_, w)| w).sum();
    out.iter_mut().for_each(|(_, w)| *w /= total);
    out
}
