//! One irradiance-map update (CloudLight §4.2, steps 3–4): a texture-space deferred pass.
//!
//! Phases of [`Gatherer::update`]:
//! 1. **Scene** at the update's time: the BVH and the texels' world frames (rebuilt only when
//!    geometry moves).
//! 2. **Direct light in texture space**: E_direct per valid texel from `direct_samples`
//!    light samples with ray-traced shadows ([`DirectLight`]), kept while lights and
//!    geometry are static.
//! 3. **Radiosity**: per texel, the radiance it sends on, B = ρ/π · (E_direct + E_previous),
//!    dilated into the padding. Reading the previous map adds one bounce per update.
//! 4. **Gather**: per basis (or per texel, the paper's naive server), N cosine-distributed
//!    rays from a Hammersley set, traced in Morton order over the sample square so that
//!    consecutive rays leave in neighbouring directions: coherent bundles
//!    ([`coherent_samples`]; on the Cornell box an update is ~10–16% faster than in index
//!    order). Each ray gives one sample π · B(hit) of the irradiance where it leaves (back
//!    faces and misses give 0). A basis's rays leave from all its texels (a third stratified
//!    coordinate picks the texel) and a least-squares polynomial in the surface's
//!    coordinates is fitted to their samples ([`BasisFit`]: the gradients of irradiance
//!    caching, fitted instead of derived); with [`BasisFit::Constant`] they all leave the
//!    centre and their mean is the basis's one value (the paper's bases).
//! 5. **Reconstruct**: per texel, E = Σ w_k E_k(x) over its bases, each basis's polynomial
//!    evaluated at the texel (clamped at 0), made an [`HdrMap`] (dilated once, there; the
//!    next bounce reads that map).
//!
//! While lights and geometry are static the update converges to a fixed point (a fixed
//! sample set); once an update changes the map by less than [`CONVERGED`] relative, later
//! updates re-gather nothing and hand out the same map.

use std::sync::Arc;
use std::time::Instant;

use glam::Vec3;
use rayon::prelude::*;

use crate::bvh::{BvhKind, Hit, RayQuery, SceneBvh};
use crate::direct_light::DirectLight;
use crate::hdr_map::{HdrMap, bilinear};
use crate::sampling::{Rng, basis, cosine_hemisphere, morton2, radical_inverse3};

use super::Lightmap;
use super::changes::{Aabb, Changes, TileChanges};
use super::texels::hammersley;

/// Relative change of the map's energy below which a static scene's update is final.
pub const CONVERGED: f32 = 1e-4;

/// Where gather rays start.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum GatherMode {
    /// Once per basis, reconstructed per texel (the paper's efficient server).
    #[default]
    Bases,
    /// At every valid texel (the paper's naive server).
    Texels,
}

/// What a basis carries of the irradiance over its texels (CloudLight's bases carry one
/// value; a slope and a curvature, fitted to rays that leave from all its texels, follow the
/// light across the basis as irradiance caching's gradients do).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum BasisFit {
    /// One value, gathered with every ray leaving the basis's centre (the paper's bases).
    Constant,
    /// Value and gradient along the surface (3 terms): rays leave from all its texels.
    Linear,
    /// Value, gradient and curvature (6 terms); needs a few hundred rays per basis, below
    /// which `linear` is less noisy.
    #[default]
    Quadratic,
}

impl BasisFit {
    /// Terms of the fitted polynomial.
    pub fn terms(self) -> usize {
        match self {
            BasisFit::Constant => 1,
            BasisFit::Linear => 3,
            BasisFit::Quadratic => 6,
        }
    }
}

/// Settings of the gather.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GatherSettings {
    /// Per basis or per texel.
    pub mode: GatherMode,
    /// Rays per basis (the paper: 26k rays for 50 bases).
    pub rays_per_basis: u32,
    /// What a basis carries: with `linear` or `quadratic`, a basis's rays leave from all its
    /// texels (stratified over them) and it carries a least-squares fit of what they gather.
    pub fit: BasisFit,
    /// Rays per texel in [`GatherMode::Texels`].
    pub rays_per_texel: u32,
    /// Light samples per texel for texture-space direct light.
    pub direct_samples: u32,
    /// Whether an update re-computes only what changed ([`super::changes`]): the direct
    /// light of texels whose lights moved or whose shadows a moving object may cross, and
    /// the bases whose rays may reach a moving object or read changed radiosity. Off: every
    /// update re-computes everything. (Per texel, [`GatherMode::Texels`], always does.)
    pub partial: bool,
    /// Seed of the direct-light samples and the gather's sample rotation.
    pub seed: u64,
}

impl Default for GatherSettings {
    fn default() -> Self {
        GatherSettings {
            mode: GatherMode::Bases,
            rays_per_basis: 512,
            fit: BasisFit::Quadratic,
            rays_per_texel: 64,
            direct_samples: 4,
            partial: true,
            seed: 1,
        }
    }
}

/// What one update did.
#[derive(Clone, Debug, PartialEq)]
pub struct Update {
    /// The new map: E_indirect per texel, W·m⁻² per channel, dilated into invalid texels.
    pub map: Arc<HdrMap>,
    /// Scene time the map is valid for, seconds.
    pub time_s: f64,
    /// Gather rays traced (0 when converged).
    pub rays: u64,
    /// Shadow rays of texture-space direct light (0 when kept).
    pub direct_rays: u64,
    /// Points of the map (bases or texels).
    pub gather_points: usize,
    /// Of which gathered again in this update (the rest kept what they had).
    pub regathered: usize,
    /// Texels whose direct light was computed again (0 when kept).
    pub direct_texels: usize,
    /// Whether the scene was static and converged, so nothing was re-gathered.
    pub converged: bool,
    /// Wall time of the whole update, seconds.
    pub seconds: f64,
}

/// The light-map server's state across updates: the previous map (for the next bounce)
/// and the direct light while it is valid.
pub struct Gatherer {
    lightmap: Arc<Lightmap>,
    settings: GatherSettings,
    bvh: Option<SceneBvh>,
    frame: (Vec<Vec3>, Vec<Vec3>),
    direct: Option<Vec<Vec3>>,
    /// The last map's texels, which the next bounce reads.
    previous: Vec<Vec3>,
    /// The last map as handed out, and the scene time it is valid for.
    map: (Arc<HdrMap>, f64),
    converged: bool,
    updates: u64,
    /// The gather's sample set in coherent order ([`coherent_samples`]).
    samples: Vec<[f32; 3]>,
    /// Scene time of the last update that computed anything.
    time: Option<f64>,
    /// Per basis: what it gathered last, and what its rays touched then.
    bases: Vec<GatheredBasis>,
    /// Which parts of the map changed since the bases that read them gathered.
    tiles: Option<TileChanges>,
    /// Per texel: its object (`u32::MAX` where invalid).
    texel_object: Vec<u32>,
    /// Per basis: the objects its texels lie on.
    basis_objects: Vec<Vec<u32>>,
}

/// One basis's last gather: its fitted light, the box around its rays' segments and the
/// map tiles whose radiosity they read.
#[derive(Clone, Debug, Default)]
struct GatheredBasis {
    light: BasisLight,
    reach: Aabb,
    tiles: Vec<u32>,
}

/// The `n` Hammersley points of the unit square in Morton (Z-curve) order: consecutive
/// samples map to neighbouring directions on the hemisphere, so a point's rays run as
/// coherent bundles (each ray's traversal finds the nodes of the one before it in cache).
/// Each carries a third coordinate, the base-3 radical inverse of its Hammersley index, which
/// picks the texel a basis's ray leaves from (stratified over the basis's texels and
/// independent of the direction).
pub fn coherent_samples(n: u32) -> Vec<[f32; 3]> {
    let quantize = |u: f32| (u.clamp(0.0, 1.0) * 65535.0) as u32;
    let mut s: Vec<(u64, [f32; 3])> = (0..n)
        .map(|i| {
            let (u1, u2) = hammersley(i, n);
            (
                morton2(quantize(u1), quantize(u2)),
                [u1, u2, radical_inverse3(i)],
            )
        })
        .collect();
    s.sort_unstable_by_key(|e| e.0);
    s.into_iter().map(|e| e.1).collect()
}

/// What one basis gathered: irradiance over its texels as a polynomial in the centre's
/// tangent-plane coordinates (u, v) in units of `scale_m` (its radius of influence):
/// coefficients of 1, u, v, u², uv, v² ([`BasisFit::terms`] of them non-zero). `span` is
/// the (u, v) box of the texels the fit was sampled over, [u_lo, u_hi, v_lo, v_hi]: a point
/// outside it is read at the nearest point inside, so a neighbouring texel never
/// extrapolates a slope the samples could not see (a thin strip of texels fits its cross
/// direction from nothing).
#[derive(Clone, Copy, Debug, Default)]
struct BasisLight {
    centre: Vec3,
    tangent: Vec3,
    bitangent: Vec3,
    scale_m: f32,
    c: [Vec3; 6],
    span: [f32; 4],
}

fn features(u: f32, v: f32) -> [f32; 6] {
    [1.0, u, v, u * u, u * v, v * v]
}

impl BasisLight {
    /// Irradiance the basis predicts at `x`, never negative.
    fn at(&self, x: Vec3) -> Vec3 {
        let d = (x - self.centre) / self.scale_m;
        let [u_lo, u_hi, v_lo, v_hi] = self.span;
        let u = d.dot(self.tangent).clamp(u_lo, u_hi);
        let v = d.dot(self.bitangent).clamp(v_lo, v_hi);
        let f = features(u, v);
        f.iter()
            .zip(&self.c)
            .map(|(f, c)| *c * *f)
            .sum::<Vec3>()
            .max(Vec3::ZERO)
    }
}

/// Least-squares fit of the first `K` terms of [`features`] to samples (u, v, value).
struct SurfaceFit<const K: usize> {
    a: [[f64; K]; K],
    b: [[f64; 3]; K],
}

impl<const K: usize> SurfaceFit<K> {
    /// The coefficients fitted to `samples` ((u, v, value) each).
    fn fit(samples: impl Iterator<Item = (f32, f32, Vec3)>) -> [Vec3; 6] {
        let mut fit = SurfaceFit {
            a: [[0.0; K]; K],
            b: [[0.0; 3]; K],
        };
        for (u, v, y) in samples {
            fit.add(u, v, y);
        }
        fit.solve()
    }

    fn add(&mut self, u: f32, v: f32, y: Vec3) {
        let f = features(u, v);
        // The upper triangle only (the matrix is symmetric; `solve` mirrors it).
        for i in 0..K {
            for j in i..K {
                self.a[i][j] += f64::from(f[i] * f[j]);
            }
            for (c, y) in y.to_array().into_iter().enumerate() {
                self.b[i][c] += f64::from(f[i] * y);
            }
        }
    }

    /// The coefficients, with a ridge of 10⁻⁴ of the sample count on every term but the
    /// constant: a term the samples barely spread over (u on a strip one texel wide, where
    /// every u is nearly the same) comes out near 0 instead of a slope fitted to noise, and
    /// a degenerate spread (on a line, at a point) never divides by zero.
    fn solve(&self) -> [Vec3; 6] {
        let mut a = self.a;
        let mut b = self.b;
        for (i, j) in (0..K).flat_map(|i| (0..i).map(move |j| (i, j))) {
            a[i][j] = a[j][i];
        }
        let ridge = 1e-4 * a[0][0] + 1e-12;
        for (i, row) in a.iter_mut().enumerate().skip(1) {
            row[i] += ridge;
        }
        // Gaussian elimination with partial pivoting.
        for col in 0..K {
            let p = (col..K)
                .max_by(|&x, &y| a[x][col].abs().total_cmp(&a[y][col].abs()))
                .unwrap_or(col);
            a.swap(col, p);
            b.swap(col, p);
            if a[col][col].abs() < 1e-30 {
                continue;
            }
            let (pivot_a, pivot_b) = (a[col], b[col]);
            for r in col + 1..K {
                let f = a[r][col] / pivot_a[col];
                for (x, p) in a[r].iter_mut().zip(&pivot_a).skip(col) {
                    *x -= f * p;
                }
                for (x, p) in b[r].iter_mut().zip(&pivot_b) {
                    *x -= f * p;
                }
            }
        }
        let mut x = [[0.0f64; 3]; K];
        for r in (0..K).rev() {
            if a[r][r].abs() < 1e-30 {
                continue;
            }
            for c in 0..3 {
                let s: f64 = (r + 1..K).map(|k| a[r][k] * x[k][c]).sum();
                x[r][c] = (b[r][c] - s) / a[r][r];
            }
        }
        let mut out = [Vec3::ZERO; 6];
        for (o, x) in out.iter_mut().zip(x) {
            *o = Vec3::new(x[0] as f32, x[1] as f32, x[2] as f32);
        }
        if out.iter().all(|c| c.is_finite()) {
            out
        } else {
            [Vec3::ZERO; 6]
        }
    }
}

impl Gatherer {
    /// A gatherer over a baked light map, starting from a black map.
    pub fn new(lightmap: Arc<Lightmap>, settings: GatherSettings) -> Self {
        let t = &lightmap.texels;
        let previous = vec![Vec3::ZERO; t.valid.len()];
        let map = HdrMap::new(t.width, t.height, &previous, &t.valid)
            .expect("a baked light map's sides and coverage agree");
        // Triangles are the scene's objects' in order.
        let mut object_of = Vec::new();
        for (i, o) in lightmap.scene.objects.iter().enumerate() {
            object_of.extend(std::iter::repeat_n(i as u32, o.mesh.indices.len()));
        }
        let texel_object: Vec<u32> = t
            .points
            .iter()
            .zip(&t.valid)
            .map(|(p, &valid)| match p {
                Some(p) if valid => object_of.get(p.triangle as usize).copied().unwrap_or(0),
                _ => u32::MAX,
            })
            .collect();
        let basis_objects = (0..lightmap.bases.bases.len())
            .map(|k| {
                let mut objects: Vec<u32> = lightmap
                    .bases
                    .members_of(k)
                    .iter()
                    .map(|&m| texel_object[m as usize])
                    .collect();
                objects.sort_unstable();
                objects.dedup();
                objects
            })
            .collect();
        Gatherer {
            map: (Arc::new(map), 0.0),
            frame: (t.positions.clone(), t.normals.clone()),
            time: None,
            bases: Vec::new(),
            tiles: None,
            texel_object,
            basis_objects,
            lightmap,
            settings,
            bvh: None,
            direct: None,
            previous,
            converged: false,
            updates: 0,
            samples: coherent_samples(match settings.mode {
                GatherMode::Bases => settings.rays_per_basis,
                GatherMode::Texels => settings.rays_per_texel,
            }),
        }
    }

    /// The light map gathered over.
    pub fn lightmap(&self) -> &Arc<Lightmap> {
        &self.lightmap
    }

    /// The latest map.
    pub fn map(&self) -> &Arc<HdrMap> {
        &self.map.0
    }

    /// Computes the map for scene time `t_s` (one more bounce than the last).
    pub fn update(&mut self, t_s: f64) -> Update {
        let start = Instant::now();
        let lightmap = self.lightmap.clone();
        let scene = &lightmap.scene;
        let is_static = !scene.is_animated();
        if is_static && self.converged {
            self.map.1 = t_s;
            return self.finish(start, [0; 4], true);
        }
        // What moved since the last update (everything, the first time).
        let changes = self.time.map(|t0| Changes::between(scene, t0, t_s));
        let partial = self.settings.partial && changes.is_some();
        let moving_geometry = changes.as_ref().is_none_or(|c| !c.movers.is_empty());
        // 1. Scene.
        if self.bvh.is_none() || moving_geometry {
            let bvh = SceneBvh::at(scene, t_s, BvhKind::default());
            if scene.has_moving_geometry() {
                self.frame = lightmap.texels.frame_at(bvh.triangles());
            }
            self.bvh = Some(bvh);
        }
        let bvh = self.bvh.take().expect("built above");
        // 2. Direct light: every texel when a light changed (or the first time); else the
        // texels on movers and those whose shadow rays a mover may cross.
        let (mut direct_rays, mut direct_texels) = (0, 0);
        let stale: Option<Vec<bool>> = match &changes {
            _ if self.direct.is_none() => None,
            Some(c) if c.none() => Some(Vec::new()),
            Some(c) if partial && !c.lights => {
                let light = DirectLight::new(scene, &bvh, t_s);
                let lights: Vec<_> = scene.lights.iter().map(|l| l.at(t_s)).collect();
                let emitters = light.emitter_box();
                let emitters = Aabb {
                    lo: emitters.0,
                    hi: emitters.1,
                };
                Some(
                    (0..self.texel_object.len())
                        .into_par_iter()
                        .map(|i| {
                            let o = self.texel_object[i];
                            o != u32::MAX
                                && (c.moved[o as usize]
                                    || c.shadow_may_cross(self.frame.0[i], &lights, &emitters))
                        })
                        .collect(),
                )
            }
            _ => None,
        };
        if stale.as_ref().is_none_or(|s| s.iter().any(|&s| s)) {
            let (e, rays, texels) = direct_map(
                &lightmap,
                &bvh,
                &self.frame,
                t_s,
                &self.settings,
                self.updates,
                stale.as_deref().zip(self.direct.as_deref()),
            );
            self.direct = Some(e);
            (direct_rays, direct_texels) = (rays, texels);
        }
        // 3. Radiosity.
        let radiosity = self.radiosity();
        // 4–5. Gather and reconstruct.
        let (texels, rays, regathered) = self.gather(&bvh, &radiosity, changes.as_ref(), partial);
        self.bvh = Some(bvh);
        let t = &lightmap.texels;
        let map = HdrMap::from_plan(&lightmap.dilation, &texels)
            .expect("a baked light map's sides and coverage agree");
        // The next bounce reads the map as clients get it (dilated once, in the map).
        let texels = map.texels();
        let (old, new) = (energy(&self.previous, &t.valid), energy(&texels, &t.valid));
        self.converged = is_static && (new - old).abs() <= CONVERGED * new.max(f32::MIN_POSITIVE);
        self.previous = texels;
        self.map = (Arc::new(map), t_s);
        self.time = Some(t_s);
        self.finish(
            start,
            [rays, direct_rays, regathered as u64, direct_texels as u64],
            false,
        )
    }

    /// The update's report; `counts` are the gather rays, the direct-light rays, the points
    /// gathered again and the texels whose direct light was computed.
    fn finish(&mut self, start: Instant, counts: [u64; 4], converged: bool) -> Update {
        self.updates += 1;
        let [rays, direct_rays, regathered, direct_texels] = counts;
        Update {
            map: self.map.0.clone(),
            time_s: self.map.1,
            rays,
            direct_rays,
            gather_points: match self.settings.mode {
                GatherMode::Bases => self.lightmap.bases.bases.len(),
                GatherMode::Texels => self.lightmap.texels.valid_count(),
            },
            regathered: regathered as usize,
            direct_texels: direct_texels as usize,
            converged,
            seconds: start.elapsed().as_secs_f64(),
        }
    }

    /// B = ρ/π · (E_direct + E_previous) per texel, dilated.
    fn radiosity(&self) -> Vec<Vec3> {
        let lm = &self.lightmap;
        let direct = self.direct.as_deref().unwrap_or_default();
        let b: Vec<Vec3> = (0..lm.albedo.len())
            .into_par_iter()
            .map(|i| {
                if !lm.texels.valid[i] {
                    return Vec3::ZERO;
                }
                let e = direct.get(i).copied().unwrap_or_default() + self.previous[i];
                lm.albedo[i] * e / std::f32::consts::PI
            })
            .collect();
        lm.dilated(b)
    }

    /// Gathers the bases (all, or with `partial` those that `changes` and the radiosity's
    /// changes reach) or every texel; the texels' irradiance, the rays traced and the points
    /// gathered.
    fn gather(
        &mut self,
        bvh: &SceneBvh,
        radiosity: &[Vec3],
        changes: Option<&Changes>,
        partial: bool,
    ) -> (Vec<Vec3>, u64, usize) {
        let lm = self.lightmap.clone();
        let (pos, nrm) = &self.frame;
        let eps = lm.texels.texel_m * 1e-2;
        let (w, h) = (lm.texels.width, lm.texels.height);
        let (lo, hi) = bvh.bounds();
        let scene_box = Aabb { lo, hi };
        // Which bases gather: all, or those a change reaches.
        let count = lm.bases.bases.len();
        let tiles = self
            .tiles
            .get_or_insert_with(|| TileChanges::new(w, h, radiosity.to_vec()));
        let dirty: Vec<bool> = match changes {
            Some(c) if partial && self.bases.len() == count => {
                let mean = energy(radiosity, &lm.texels.valid) / 3.0;
                let changed = tiles.update(radiosity, mean);
                (0..count)
                    .map(|k| {
                        let g = &self.bases[k];
                        self.basis_objects[k].iter().any(|&o| c.moved[o as usize])
                            || c.movers.iter().any(|m| m.intersects(&g.reach))
                            || g.tiles.iter().any(|&t| changed[t as usize])
                    })
                    .collect()
            }
            _ => {
                *tiles = TileChanges::new(w, h, radiosity.to_vec());
                vec![true; count]
            }
        };
        let tiles: &TileChanges = tiles;
        // The ray leaving texel `from` along sample `s` (rotated by `r`).
        let ray_of = |from: usize, s: &[f32; 3], r: (f32, f32)| -> RayQuery {
            let (x, n) = (pos[from], nrm[from]);
            let (t, b) = basis(n);
            let l = cosine_hemisphere((s[0] + r.0).fract(), (s[1] + r.1).fract());
            let d = (t * l.x + b * l.y + n * l.z).normalize();
            (x + n * eps, d, f32::INFINITY)
        };
        // What a ray found: π · B(hit), one sample of the irradiance there (0 for a miss or
        // a back face); where its segment ends (the hit, or where it leaves the scene); the
        // map tile it read.
        let shade = |(o, d, _): RayQuery, hit: Option<Hit>| -> (Vec3, Vec3, Option<u32>) {
            match hit {
                Some(hit) => {
                    let end = o + d * hit.t;
                    if bvh.geometric_normal(hit.triangle).dot(d) >= 0.0 {
                        return (Vec3::ZERO, end, None);
                    }
                    let tri = &bvh.triangles()[hit.triangle as usize];
                    let (bu, bv) = (hit.uv.x, hit.uv.y);
                    let uv = tri.lightmap_uv[0] * (1.0 - bu - bv)
                        + tri.lightmap_uv[1] * bu
                        + tri.lightmap_uv[2] * bv;
                    let e = bilinear(radiosity, w, h, uv) * std::f32::consts::PI;
                    (e, end, Some(tiles.tile_of(uv)))
                }
                None => (Vec3::ZERO, scene_box.exit(o, d), None),
            }
        };
        // A point's rays leave together: same or neighbouring origins, directions in Morton
        // order over the sample square, traced in streams ([`SceneBvh::closest_hits_into`]).
        let trace = |queries: &[RayQuery], hits: &mut Vec<Option<Hit>>| {
            hits.clear();
            hits.resize(queries.len(), None);
            bvh.closest_hits_into(queries, hits);
        };
        // A fixed rotation per point decorrelates neighbours' sample sets.
        let rotation = |texel: usize| {
            let mut rng = Rng::new(self.settings.seed, texel as u64);
            (rng.next_f32(), rng.next_f32())
        };
        match self.settings.mode {
            GatherMode::Bases => {
                let n = self.settings.rays_per_basis;
                let gathered: Vec<(usize, GatheredBasis)> = (0..count)
                    .into_par_iter()
                    .filter(|&k| dirty[k])
                    .map_init(Scratch::default, |scratch, k| {
                        let b = &lm.bases.bases[k];
                        let centre = b.texel as usize;
                        let (tangent, bitangent) = basis(nrm[centre]);
                        let mut light = BasisLight {
                            centre: pos[centre],
                            tangent,
                            bitangent,
                            scale_m: b.radius_m.max(f32::MIN_POSITIVE),
                            ..Default::default()
                        };
                        let r = rotation(centre);
                        let mut reach = Aabb::EMPTY;
                        let mut read = Vec::new();
                        let mut note = |from: usize, (e, end, tile): (Vec3, Vec3, Option<u32>)| {
                            reach.grow(pos[from]);
                            reach.grow(end);
                            read.extend(tile);
                            e
                        };
                        // The texel each sample leaves from, its ray, and what they hit.
                        let members = lm.bases.members_of(k);
                        let from = |s: &[f32; 3]| match self.settings.fit {
                            BasisFit::Constant => centre,
                            _ => {
                                let m =
                                    ((s[2] * members.len() as f32) as usize).min(members.len() - 1);
                                members[m] as usize
                            }
                        };
                        let Scratch { queries, hits } = scratch;
                        queries.clear();
                        queries.extend(self.samples.iter().map(|s| ray_of(from(s), s, r)));
                        trace(queries, hits);
                        let found = self
                            .samples
                            .iter()
                            .zip(queries.iter().zip(hits.iter()))
                            .map(|(s, (q, h))| (from(s), shade(*q, *h)));
                        if self.settings.fit == BasisFit::Constant {
                            let sum: Vec3 = found.map(|(f, x)| note(f, x)).sum();
                            light.c[0] = sum / n.max(1) as f32;
                        } else {
                            let uv = |t: usize| {
                                let d = (pos[t] - light.centre) / light.scale_m;
                                (d.dot(tangent), d.dot(bitangent))
                            };
                            let mut span = [f32::MAX, f32::MIN, f32::MAX, f32::MIN];
                            for &m in members {
                                let (u, v) = uv(m as usize);
                                span = [
                                    span[0].min(u),
                                    span[1].max(u),
                                    span[2].min(v),
                                    span[3].max(v),
                                ];
                            }
                            if span[0] <= span[1] && span[2] <= span[3] {
                                light.span = span;
                            }
                            let samples = found.map(|(f, x)| {
                                let (u, v) = uv(f);
                                (u, v, note(f, x))
                            });
                            light.c = match self.settings.fit {
                                BasisFit::Linear => SurfaceFit::<3>::fit(samples),
                                _ => SurfaceFit::<6>::fit(samples),
                            };
                        }
                        read.sort_unstable();
                        read.dedup();
                        let tiles = read;
                        (
                            k,
                            GatheredBasis {
                                light,
                                reach,
                                tiles,
                            },
                        )
                    })
                    .collect();
                let regathered = gathered.len();
                self.bases.resize_with(count, Default::default);
                for (k, g) in gathered {
                    self.bases[k] = g;
                }
                let per_basis = &self.bases;
                let texels = lm
                    .bases
                    .weights
                    .par_iter()
                    .enumerate()
                    .map(|(t, blend)| {
                        blend
                            .iter()
                            .map(|&(k, wk)| per_basis[k as usize].light.at(pos[t]) * wk)
                            .sum()
                    })
                    .collect();
                (texels, regathered as u64 * n as u64, regathered)
            }
            GatherMode::Texels => {
                let n = self.settings.rays_per_texel;
                let texels: Vec<Vec3> = (0..lm.texels.valid.len())
                    .into_par_iter()
                    .map_init(Scratch::default, |Scratch { queries, hits }, i| {
                        if lm.texels.valid[i] {
                            let r = rotation(i);
                            queries.clear();
                            queries.extend(self.samples.iter().map(|s| ray_of(i, s, r)));
                            trace(queries, hits);
                            let sum: Vec3 = queries
                                .iter()
                                .zip(hits.iter())
                                .map(|(q, h)| shade(*q, *h).0)
                                .sum();
                            sum / n.max(1) as f32
                        } else {
                            Vec3::ZERO
                        }
                    })
                    .collect();
                let points = lm.texels.valid_count();
                (texels, points as u64 * n as u64, points)
            }
        }
    }
}

/// A worker's buffers for one point's rays and their hits.
#[derive(Default)]
struct Scratch {
    queries: Vec<RayQuery>,
    hits: Vec<Option<Hit>>,
}

/// Mean of the valid texels' channel sums.
fn energy(texels: &[Vec3], valid: &[bool]) -> f32 {
    let (sum, n) = texels
        .iter()
        .zip(valid)
        .filter(|(_, v)| **v)
        .fold((0.0f64, 0u64), |(s, n), (e, _)| {
            (s + e.element_sum() as f64, n + 1)
        });
    (sum / n.max(1) as f64) as f32
}

/// Texture-space direct irradiance (W·m⁻²) of every valid texel — or, given `(stale,
/// kept)`, of the stale texels, the others keeping their `kept` values — the shadow rays
/// spent and the texels computed.
pub(super) fn direct_map(
    lm: &Lightmap,
    bvh: &SceneBvh,
    frame: &(Vec<Vec3>, Vec<Vec3>),
    t_s: f64,
    s: &GatherSettings,
    update: u64,
    only: Option<(&[bool], &[Vec3])>,
) -> (Vec<Vec3>, u64, usize) {
    let light = DirectLight::new(&lm.scene, bvh, t_s);
    let samples = s.direct_samples.max(1);
    let eps = light.eps().max(lm.texels.texel_m * 1e-3);
    let seed = s.seed ^ update.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    // Texels in chunks whose shadow rays are cast together ([`DirectLight::blocked`]).
    const CHUNK: usize = 256;
    let texels = lm.texels.valid.len();
    let e: Vec<Vec3> = (0..texels.div_ceil(CHUNK))
        .into_par_iter()
        .flat_map_iter(|c| {
            let ids = c * CHUNK..((c + 1) * CHUNK).min(texels);
            // Each computed texel's samples' terms: (texel, ranges of `lit`).
            let mut lit = Vec::new();
            let mut spans = Vec::with_capacity(ids.len() * samples as usize);
            for i in ids.clone() {
                if only.is_some_and(|(stale, _)| !stale[i]) || !lm.texels.valid[i] || !light.any() {
                    continue;
                }
                let (x, n) = (frame.0[i], frame.1[i]);
                let mut rng = Rng::new(seed, i as u64);
                for _ in 0..samples {
                    let first = lit.len();
                    light.samples(x + n * eps, n, &mut rng, &mut lit);
                    spans.push((i, first..lit.len()));
                }
            }
            let blocked = light.blocked(&lit);
            let mut sums = vec![Vec3::ZERO; ids.len()];
            for (i, terms) in spans {
                sums[i - ids.start] += DirectLight::sum_clear(&lit[terms.clone()], &blocked[terms]);
            }
            ids.map(move |i| {
                if let Some((stale, kept)) = only
                    && !stale[i]
                {
                    return kept[i];
                }
                let e = sums[i - c * CHUNK] / samples as f32;
                if e.is_finite() {
                    e.max(Vec3::ZERO)
                } else {
                    Vec3::ZERO
                }
            })
        })
        .collect();
    let computed = match only {
        Some((stale, _)) => (0..stale.len())
            .filter(|&i| stale[i] && lm.texels.valid[i])
            .count(),
        None => lm.texels.valid_count(),
    };
    let lights = lm.scene.lights.len() as u64 + 1;
    (e, computed as u64 * samples as u64 * lights, computed)
}

#[cfg(test)]
mod fit_tests {
    use super::*;

    /// Noisy samples of a constant 1 on a strip that is long in u and 2·10⁻⁴ of the basis's
    /// radius wide in v, as a basis over one row of texels sees it.
    fn strip(n: u64) -> Vec<(f32, f32, Vec3)> {
        let mut rng = Rng::new(7, 0);
        (0..n)
            .map(|i| {
                let u = 2.0 * (i as f32 + 0.5) / n as f32 - 1.0;
                let v = if rng.next_f32() < 0.5 { 1e-4 } else { -1e-4 };
                let y = 1.0 + 0.2 * (rng.next_f32() - 0.5);
                (u, v, Vec3::splat(y))
            })
            .collect()
    }

    #[test]
    fn a_fit_on_a_thin_strip_does_not_turn_noise_into_a_slope_across_it() {
        for c in [
            SurfaceFit::<3>::fit(strip(256).into_iter()),
            SurfaceFit::<6>::fit(strip(256).into_iter()),
        ] {
            // Noise of ±0.1 over a width of 2e-4 fits a slope of ~40 without the ridge.
            assert!(c[2].abs().max_element() < 1.0, "v slope {}", c[2]);
            assert!(
                (c[0] - Vec3::ONE).abs().max_element() < 0.05,
                "mean {}",
                c[0]
            );
        }
    }

    #[test]
    fn a_basis_predicts_within_its_samples_everywhere_it_is_read() {
        let light = BasisLight {
            centre: Vec3::ZERO,
            tangent: Vec3::X,
            bitangent: Vec3::Y,
            scale_m: 1.0,
            // A fit with a steep cross slope and curvature, as noise on a strip can give.
            c: [
                Vec3::ONE,
                Vec3::ZERO,
                Vec3::splat(100.0),
                Vec3::ZERO,
                Vec3::ZERO,
                Vec3::splat(-50.0),
            ],
            span: [-1.0, 1.0, -1e-3, 1e-3],
        };
        let (lo, hi) = (0.8, 1.2);
        for (u, v) in [
            (0.0, 0.0),
            (0.5, 1.0),
            (-0.5, -1.0),
            (2.0, 0.3),
            (0.0, -3.0),
        ] {
            let e = light.at(Vec3::new(u, v, 0.0)).x;
            assert!((lo..=hi).contains(&e), "at ({u}, {v}): {e}");
        }
        // Inside its span it reads the fit itself.
        assert!((light.at(Vec3::new(0.0, 1e-3, 0.0)).x - 1.1).abs() < 1e-3);
    }
}
