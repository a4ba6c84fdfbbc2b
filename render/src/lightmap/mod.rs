//! Irradiance maps (CloudLight §4.2): the offline light-map atlas, texel G-buffer and basis
//! functions ([`Lightmap::bake`]), and the server's per-update gather ([`Gatherer`]).
//!
//! Offline phases, once per scene (and cached per scene and settings in the process, so a
//! gatherer and every client of an in-process cluster share one bake):
//! 1. **Atlas** ([`atlas`]): the scene's own second UV set, or an unwrap by `uvunwrap`;
//! 2. **Texel G-buffer** ([`texels`]): a surface point per texel, repaired against leaks;
//! 3. **Bases** ([`basis`]): clusters of mutually visible texels with similar normals.
//!
//! A scene that cannot be parametrised within the budget is [`NotParametrizable`]: the
//! paper's "n/a", with its reason. This module knows nothing about stages or sockets.

use std::collections::HashMap;
use std::hash::{Hash, Hasher};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::Instant;

use cloudlight_scenes::Scene;
use glam::Vec3;

use crate::bvh::{BvhKind, SceneBvh};
use crate::hdr_map::{DILATE_RINGS, DilationPlan};

pub mod atlas;
pub mod basis;
pub mod changes;
pub mod gather;
pub mod pass;
pub mod texels;

pub use atlas::{Atlas, AtlasSettings, UvSource};
pub use basis::{Bases, Basis, BasisSettings, MAX_BASES_PER_TEXEL};
pub use gather::{BasisFit, GatherMode, GatherSettings, Gatherer, Update};
pub use pass::{LightmapPass, lightmap_frame};
pub use texels::TexelSurface;

/// Why a scene has no irradiance map (the paper's "n/a").
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum NotParametrizable {
    /// Nothing to map.
    #[error("the scene has no surfaces to map")]
    NoSurfaces,
    /// No UVs, and unwrapping is off.
    #[error(
        "the scene has no light-map UVs (TEXCOORD_1) and unwrapping is disabled (unwrap_limit_s = 0)"
    )]
    NoUvsAndNoUnwrap,
    /// More charts than one page of the budget holds.
    #[error(
        "{charts} charts do not fit one {resolution}² map (they need {pages} pages): too many charts for the texel budget"
    )]
    TooManyCharts {
        /// Charts.
        charts: u32,
        /// Pages they needed.
        pages: u32,
        /// Map side, texels.
        resolution: u32,
    },
    /// Texels coarser than allowed.
    #[error(
        "texels would be {texel_m:.3} m across, coarser than the {max_texel_m} m the budget allows"
    )]
    TexelsTooLarge {
        /// Texel edge reached, meters.
        texel_m: f32,
        /// Largest allowed, meters.
        max_texel_m: f32,
    },
    /// The unwrap ran over its limit.
    #[error("unwrapping took longer than its {limit_s} s limit")]
    TimeLimit {
        /// Limit, seconds.
        limit_s: f64,
    },
    /// The unwrapper refused the meshes.
    #[error("the unwrapper failed: {0}")]
    Unwrap(String),
    /// Every texel is buried or uncovered.
    #[error("no texel of the map sees the scene (all {texels} are uncovered or buried)")]
    NoValidTexels {
        /// Texels of the map.
        texels: usize,
    },
}

/// Everything the offline phases take.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LightmapSettings {
    /// The atlas.
    pub atlas: AtlasSettings,
    /// The bases.
    pub bases: BasisSettings,
}

/// A baked light map: the scene with its light-map UVs, the atlas, the texel G-buffer, the
/// bases and each texel's albedo.
#[derive(Debug)]
pub struct Lightmap {
    /// The scene, its meshes carrying light-map UVs (re-indexed where charts split them).
    pub scene: Scene,
    /// The atlas.
    pub atlas: Atlas,
    /// The texel G-buffer at time 0.
    pub texels: TexelSurface,
    /// The bases.
    pub bases: Bases,
    /// Albedo per texel (material × texture; zero where invalid).
    pub albedo: Vec<Vec3>,
    /// How the texels outside the charts are filled (the coverage never changes).
    pub dilation: DilationPlan,
    /// Time of the texel G-buffer and basis phases, seconds (the atlas's is its own).
    pub bake_s: f64,
}

impl Lightmap {
    /// Runs the offline phases on `scene`.
    pub fn bake(scene: &Scene, s: &LightmapSettings) -> Result<Lightmap, NotParametrizable> {
        let (scene, atlas) = unwrapped(scene, &s.atlas)?;
        let scene = Scene::clone(&scene);
        let start = Instant::now();
        let bvh = SceneBvh::at(&scene, 0.0, BvhKind::default());
        let texel_m = 1.0 / atlas.texels_per_m.max(1e-12);
        let texels = TexelSurface::build(bvh.triangles(), &bvh, atlas.width, atlas.height, texel_m);
        if texels.valid_count() == 0 {
            return Err(NotParametrizable::NoValidTexels {
                texels: texels.valid.len(),
            });
        }
        let bases = basis::build(&texels, &bvh, &s.bases);
        let albedo = texels
            .points
            .iter()
            .zip(&texels.valid)
            .map(|(p, &valid)| match p {
                Some(p) if valid => {
                    let t = &bvh.triangles()[p.triangle as usize];
                    let m = &scene.materials[t.material as usize];
                    let w0 = 1.0 - p.bary.x - p.bary.y;
                    let uv = t.uv[0] * w0 + t.uv[1] * p.bary.x + t.uv[2] * p.bary.y;
                    m.albedo * m.texture.as_ref().map_or(Vec3::ONE, |tex| tex.sample(uv))
                }
                _ => Vec3::ZERO,
            })
            .collect();
        let dilation = DilationPlan::new(texels.width, texels.height, &texels.valid, DILATE_RINGS);
        Ok(Lightmap {
            scene,
            atlas,
            texels,
            bases,
            albedo,
            dilation,
            bake_s: start.elapsed().as_secs_f64(),
        })
    }

    /// [`Lightmap::bake`], once per (scene content, settings) in this process.
    pub fn cached(scene: &Scene, s: &LightmapSettings) -> Result<Arc<Lightmap>, NotParametrizable> {
        type Cache = Mutex<HashMap<u64, Result<Arc<Lightmap>, NotParametrizable>>>;
        static CACHE: OnceLock<Cache> = OnceLock::new();
        let key = fingerprint(scene, s);
        let cache = CACHE.get_or_init(Default::default);
        if let Some(hit) = crate::lock(cache).get(&key) {
            return hit.clone();
        }
        let baked = Lightmap::bake(scene, s).map(Arc::new);
        crate::lock(cache).insert(key, baked.clone());
        baked
    }

    /// `values` (one per texel) with invalid texels filled from valid neighbours.
    pub fn dilated(&self, values: Vec<Vec3>) -> Vec<Vec3> {
        self.dilation.apply(&values)
    }

    /// Bytes a client holds for one map at f16 RGBA, 8 B a texel (the paper's "local device
    /// indirect light size" is 768 kB for the Cornell box's 128², 48 B a texel).
    pub fn client_bytes(&self) -> u64 {
        self.texels.valid.len() as u64 * 8
    }
}

/// `scene` with light-map UVs on every mesh and its atlas ([`atlas::build`]), once per
/// (scene content, atlas settings) in this process: what a client needs to draw a light map
/// made with the same atlas settings (a gatherer's bake in the process shares it).
pub fn unwrapped(
    scene: &Scene,
    s: &AtlasSettings,
) -> Result<(Arc<Scene>, Atlas), NotParametrizable> {
    type Cache = Mutex<HashMap<u64, Result<(Arc<Scene>, Atlas), NotParametrizable>>>;
    static CACHE: OnceLock<Cache> = OnceLock::new();
    let key = fingerprint(scene, s);
    let cache = CACHE.get_or_init(Default::default);
    if let Some(hit) = crate::lock(cache).get(&key) {
        return hit.clone();
    }
    let built = atlas::build(scene, s).map(|(scene, atlas)| (Arc::new(scene), atlas));
    crate::lock(cache).insert(key, built.clone());
    built
}

/// A hash of what a bake depends on and holds: the scene's name (the baked light map keeps
/// its scene), geometry, materials with their textures' texels, lights and settings.
fn fingerprint(scene: &Scene, s: &impl std::fmt::Debug) -> u64 {
    let mut h = std::collections::hash_map::DefaultHasher::new();
    format!("{s:?}").hash(&mut h);
    scene.name.hash(&mut h);
    for o in &scene.objects {
        o.material.hash(&mut h);
        for p in o.mesh.positions.iter().chain(&o.mesh.normals) {
            p.to_array().map(f32::to_bits).hash(&mut h);
        }
        for uv in o.mesh.uvs.iter().chain(&o.mesh.lightmap_uvs) {
            uv.to_array().map(f32::to_bits).hash(&mut h);
        }
        o.mesh.indices.hash(&mut h);
        format!("{:?}", o.motion).hash(&mut h);
    }
    for m in &scene.materials {
        m.albedo.to_array().map(f32::to_bits).hash(&mut h);
        m.emission.to_array().map(f32::to_bits).hash(&mut h);
        if let Some(t) = &m.texture {
            (t.width, t.height).hash(&mut h);
            for c in &t.texels {
                c.to_array().map(f32::to_bits).hash(&mut h);
            }
        }
    }
    format!("{:?}", scene.lights).hash(&mut h);
    h.finish()
}

#[cfg(test)]
mod tests;
