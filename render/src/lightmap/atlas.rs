//! The light-map atlas: one unique parametrisation of every surface in a square map.
//!
//! A scene whose meshes all carry a second UV set (glTF `TEXCOORD_1`) keeps it. Otherwise
//! charts are segmented, flattened and packed by the `uvunwrap` crate (pure Rust, in the
//! spirit of xatlas): charts sit at least `2 × padding` texels apart on 4×4-aligned blocks,
//! so bilinear filtering and the codec's 2×2 chroma never mix two charts. The atlas side
//! follows a texel budget (from the surface area at a texels-per-m² density, capped at
//! `max_resolution`); when the scene cannot be parametrised within it (too many charts for
//! one page, texels larger than allowed, the unwrap over its time limit), the result is the
//! paper's "n/a" with its reason, never a broken map.

use std::time::Instant;

use cloudlight_scenes::{Mesh, Scene};
use glam::Vec2;

use super::NotParametrizable;

/// How the atlas is made.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AtlasSettings {
    /// Texels per m² of surface the atlas aims for (the Cornell box's 128² on 2 m²).
    pub texels_per_m2: f64,
    /// Side of the map in texels; 0: from the surface area at `texels_per_m2`, rounded up to
    /// a multiple of 16 and capped at `max_resolution`.
    pub resolution: u32,
    /// Largest side in texels the budget allows (the paper's maps are at most 1024²).
    pub max_resolution: u32,
    /// Empty texels around each chart (≥ 4 for H.264's 4:2:0 and bilinear filtering).
    pub padding: u32,
    /// Largest texel edge allowed, meters: a scene that only fits with coarser texels
    /// cannot be parametrised within the budget.
    pub max_texel_m: f32,
    /// Time the unwrap may take, seconds; 0 disables unwrapping (only a scene's own
    /// light-map UVs are used).
    pub unwrap_limit_s: f64,
}

impl Default for AtlasSettings {
    fn default() -> Self {
        AtlasSettings {
            texels_per_m2: 8_200.0,
            resolution: 0,
            max_resolution: 1024,
            padding: 4,
            max_texel_m: 0.25,
            unwrap_limit_s: 120.0,
        }
    }
}

/// Where the light-map UVs came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub enum UvSource {
    /// The scene's own second UV set.
    Scene,
    /// Unwrapped and packed by `uvunwrap`.
    Unwrapped,
}

/// What the atlas is.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Atlas {
    /// Map width, texels.
    pub width: u32,
    /// Map height, texels.
    pub height: u32,
    /// Charts (0 when the scene's own UVs were used: not counted).
    pub charts: u32,
    /// Fraction of the map covered by charts (as the unwrapper measured it; for a scene's
    /// own UVs, the texel G-buffer's valid fraction is the figure).
    pub utilization: f32,
    /// Texels per meter along a chart (1 / texel edge).
    pub texels_per_m: f32,
    /// Unwrap and pack time, seconds (0 for the scene's own UVs).
    pub unwrap_s: f64,
    /// Where the UVs came from.
    pub source: UvSource,
}

/// The map side for `area_m2` of surface under `s`.
pub fn resolution_for(area_m2: f64, s: &AtlasSettings) -> u32 {
    if s.resolution > 0 {
        return s.resolution.min(s.max_resolution.max(16)).max(16);
    }
    let side = (area_m2.max(0.0) * s.texels_per_m2).sqrt().ceil() as u32;
    side.div_ceil(16)
        .max(2)
        .saturating_mul(16)
        .min(s.max_resolution.max(16))
}

/// The scene with light-map UVs on every mesh, and its atlas.
pub fn build(scene: &Scene, s: &AtlasSettings) -> Result<(Scene, Atlas), NotParametrizable> {
    let meshes: Vec<&Mesh> = scene
        .objects
        .iter()
        .map(|o| &o.mesh)
        .filter(|m| !m.indices.is_empty())
        .collect();
    if meshes.is_empty() {
        return Err(NotParametrizable::NoSurfaces);
    }
    let area: f64 = scene
        .triangles_at(0.0)
        .iter()
        .map(|t| 0.5 * (t.v[1] - t.v[0]).cross(t.v[2] - t.v[0]).length() as f64)
        .filter(|a| a.is_finite())
        .sum();
    if area <= 0.0 {
        return Err(NotParametrizable::NoSurfaces);
    }
    let side = resolution_for(area, s);
    if meshes
        .iter()
        .all(|m| m.lightmap_uvs.len() == m.positions.len())
    {
        let atlas = Atlas {
            width: side,
            height: side,
            charts: 0,
            utilization: 0.0,
            texels_per_m: ((side as f64).powi(2) / area).sqrt() as f32,
            unwrap_s: 0.0,
            source: UvSource::Scene,
        };
        return Ok((scene.clone(), atlas));
    }
    if s.unwrap_limit_s <= 0.0 {
        return Err(NotParametrizable::NoUvsAndNoUnwrap);
    }
    unwrap(scene, side, s)
}

/// An object's mesh as the unwrapper takes it: (object index, positions, flat indices,
/// world scale).
type UnwrapInput = (usize, Vec<[f32; 3]>, Vec<u32>, f32);

fn unwrap(
    scene: &Scene,
    side: u32,
    s: &AtlasSettings,
) -> Result<(Scene, Atlas), NotParametrizable> {
    let start = Instant::now();
    let inputs: Vec<UnwrapInput> = scene
        .objects
        .iter()
        .enumerate()
        .filter(|(_, o)| !o.mesh.indices.is_empty())
        .map(|(i, o)| {
            let m = o.motion.world_from_local(0.0).matrix3;
            let scale = m.determinant().abs().cbrt();
            let scale = if scale.is_finite() && scale > 0.0 {
                scale
            } else {
                1.0
            };
            let positions = o.mesh.positions.iter().map(|p| p.to_array()).collect();
            let indices = o.mesh.indices.iter().flatten().copied().collect();
            (i, positions, indices, scale)
        })
        .collect();
    let meshes: Vec<uvunwrap::MeshInput<'_>> = inputs
        .iter()
        .map(|(_, p, i, scale)| uvunwrap::MeshInput {
            scale: *scale,
            ..uvunwrap::MeshInput::new(p, i)
        })
        .collect();
    let options = uvunwrap::Options {
        density: uvunwrap::Density::Auto { page_size: side },
        padding: s.padding.max(1),
        block_align: true,
        ..Default::default()
    };
    let limit = s.unwrap_limit_s;
    let result = uvunwrap::generate_with_progress(&meshes, &options, |_| {
        start.elapsed().as_secs_f64() < limit
    });
    let atlas = match result {
        Ok(a) => a,
        Err(uvunwrap::Error::Cancelled) => {
            return Err(NotParametrizable::TimeLimit { limit_s: limit });
        }
        Err(e) => return Err(NotParametrizable::Unwrap(e.to_string())),
    };
    if atlas.page_count > 1 {
        return Err(NotParametrizable::TooManyCharts {
            charts: atlas.chart_count,
            pages: atlas.page_count,
            resolution: side,
        });
    }
    let texel_m = 1.0 / atlas.texels_per_unit.max(1e-12);
    if texel_m.is_nan() || texel_m > s.max_texel_m {
        return Err(NotParametrizable::TexelsTooLarge {
            texel_m,
            max_texel_m: s.max_texel_m,
        });
    }
    let mut out = scene.clone();
    let (w, h) = (atlas.width as f32, atlas.height as f32);
    // uvunwrap crops the page to its rows; keep the map square at `side` so texel size is
    // what was budgeted (UVs are rescaled into the square).
    let (sx, sy) = (w / side as f32, h / side as f32);
    for ((object, ..), unwrapped) in inputs.iter().zip(&atlas.meshes) {
        let mesh = &mut out.objects[*object].mesh;
        *mesh = remap(mesh, unwrapped, Vec2::new(sx, sy));
    }
    let built = Atlas {
        width: side,
        height: side,
        charts: atlas.chart_count,
        utilization: atlas.utilization * sx * sy,
        texels_per_m: atlas.texels_per_unit,
        unwrap_s: start.elapsed().as_secs_f64(),
        source: UvSource::Unwrapped,
    };
    Ok((out, built))
}

/// `mesh` re-indexed onto the unwrapper's vertices (seam vertices duplicated), with its
/// light-map UVs scaled by `scale` into the square map.
fn remap(mesh: &Mesh, out: &uvunwrap::OutputMesh, scale: Vec2) -> Mesh {
    let pick = |v: &[Vec2], k: usize| v.get(k).copied();
    let mut m = Mesh::default();
    for v in &out.vertices {
        let k = v.xref as usize;
        m.positions.push(mesh.positions[k]);
        m.normals
            .push(mesh.normals.get(k).copied().unwrap_or_default());
        if let Some(uv) = pick(&mesh.uvs, k) {
            m.uvs.push(uv);
        }
        m.lightmap_uvs.push(Vec2::from(v.uv) * scale);
    }
    if m.uvs.len() != m.positions.len() {
        m.uvs.clear();
    }
    m.indices = out
        .indices
        .chunks_exact(3)
        .map(|c| [c[0], c[1], c[2]])
        .collect();
    m
}
