//! The scene's albedo textures on the GPU, for the G-buffer pass: one layer of a 2D array
//! per textured material (resampled to one size, with a mip chain), layer 0 white for the
//! untextured ones.
//!
//! The path tracer reads a texture's nearest texel at full resolution and averages its
//! samples over a pixel; the G-buffer reads the nearest texel where a texel covers more than
//! a pixel, and a trilinear mip (each level a 2×2 mean of the one below, in linear RGB)
//! where a pixel covers many texels: the same mean over the pixel's footprint. Texels are
//! stored sRGB-encoded in 8 bits (filtering in linear RGB): ~0.4% steps at an albedo of 0.5.

use cloudlight_scenes::{Material, Scene, Texture};
use glam::{Vec2, Vec3};
use rayon::prelude::*;
use wgpu::util::DeviceExt;

use super::Raster;

/// Largest side of a layer: textures larger than this are box-filtered down to it.
pub const MAX_SIDE: u32 = 512;

/// The albedo texture array and its bind group (group 1 of the G-buffer pass).
pub(crate) struct AlbedoTextures {
    /// Layer of each material (0: untextured, white).
    layers: Vec<u32>,
    /// What the array was built from (each material's texture's size and first texel), so
    /// that a frame whose geometry is uploaded again does not upload the textures again.
    key: Vec<Option<(u32, u32, [u32; 3])>>,
    pub(crate) bind: wgpu::BindGroup,
}

impl AlbedoTextures {
    /// The fingerprint of `scene`'s textures that [`AlbedoTextures::key`] holds.
    fn key_of(scene: &Scene) -> Vec<Option<(u32, u32, [u32; 3])>> {
        scene
            .materials
            .iter()
            .map(|m| {
                texture_of(m).map(|t| (t.width, t.height, t.texels[0].to_array().map(f32::to_bits)))
            })
            .collect()
    }

    /// Whether this array holds `scene`'s textures.
    pub(crate) fn holds(&self, scene: &Scene) -> bool {
        self.key == Self::key_of(scene)
    }

    /// The layer material `m` reads (0, white, for an untextured or unknown one).
    pub(crate) fn layer(&self, material: u32) -> u32 {
        self.layers.get(material as usize).copied().unwrap_or(0)
    }

    /// Uploads `scene`'s textures.
    pub(crate) fn new(raster: &Raster, scene: &Scene) -> Self {
        let textured: Vec<&Texture> = scene.materials.iter().filter_map(texture_of).collect();
        // Textured materials take layers 1, 2, … in order.
        let layers = scene
            .materials
            .iter()
            .scan(0, |next, m| {
                Some(match texture_of(m) {
                    Some(_) => {
                        *next += 1;
                        *next
                    }
                    None => 0,
                })
            })
            .collect();
        let side = textured
            .iter()
            .map(|t| t.width.max(t.height))
            .max()
            .unwrap_or(1)
            .next_power_of_two()
            .min(MAX_SIDE);
        // wgpu's GL backend takes an array of 1 layer, or of a multiple of 6, for a 2D
        // texture or a cube (as `shadow.rs` notes): pad past both.
        let mut count = (textured.len() as u32 + 1).max(2);
        if count.is_multiple_of(6) {
            count += 1;
        }
        let white = Texture {
            width: 1,
            height: 1,
            texels: vec![Vec3::ONE],
        };
        let mips = side.ilog2() + 1;
        let data: Vec<u8> = (0..count as usize)
            .into_par_iter()
            .flat_map_iter(|i| {
                let t = match i {
                    0 => &white,
                    i => textured.get(i - 1).copied().unwrap_or(&white),
                };
                mip_chain(t, side)
                    .into_iter()
                    .flat_map(|level| level.into_iter().flat_map(srgb8))
            })
            .collect();
        let texture = raster.device.create_texture_with_data(
            &raster.queue,
            &wgpu::TextureDescriptor {
                label: Some("albedo textures"),
                size: wgpu::Extent3d {
                    width: side,
                    height: side,
                    depth_or_array_layers: count,
                },
                mip_level_count: mips,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format: wgpu::TextureFormat::Rgba8UnormSrgb,
                usage: wgpu::TextureUsages::TEXTURE_BINDING,
                view_formats: &[],
            },
            wgpu::util::TextureDataOrder::LayerMajor,
            &data,
        );
        let view = texture.create_view(&wgpu::TextureViewDescriptor {
            dimension: Some(wgpu::TextureViewDimension::D2Array),
            ..Default::default()
        });
        let sampler = raster.device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("albedo"),
            address_mode_u: wgpu::AddressMode::Repeat,
            address_mode_v: wgpu::AddressMode::Repeat,
            // The nearest texel, as the path tracer reads it, where texels are larger than
            // pixels; the footprint's mean where they are smaller.
            mag_filter: wgpu::FilterMode::Nearest,
            min_filter: wgpu::FilterMode::Linear,
            mipmap_filter: wgpu::MipmapFilterMode::Linear,
            ..Default::default()
        });
        let bind = raster.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("albedo textures"),
            layout: &raster.pipelines.albedo_layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: wgpu::BindingResource::TextureView(&view),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wgpu::BindingResource::Sampler(&sampler),
                },
            ],
        });
        AlbedoTextures {
            layers,
            key: Self::key_of(scene),
            bind,
        }
    }
}

/// Material `m`'s texture, unless it has none (or an empty one).
fn texture_of(m: &Material) -> Option<&Texture> {
    m.texture.as_ref().filter(|t| !t.texels.is_empty())
}

/// `t` resampled to `side` × `side` (nearest texel at each texel's centre when enlarged, the
/// mean of the texels it covers when reduced), then halved by 2×2 means down to 1 × 1.
fn mip_chain(t: &Texture, side: u32) -> Vec<Vec<Vec3>> {
    let s = side as usize;
    let mut base = vec![Vec3::ZERO; s * s];
    // Source texels per base texel along each axis (≥ 1 when reducing).
    let (fx, fy) = (
        (t.width as usize).div_ceil(s).max(1),
        (t.height as usize).div_ceil(s).max(1),
    );
    for (i, out) in base.iter_mut().enumerate() {
        let (x, y) = (i % s, i / s);
        let mut sum = Vec3::ZERO;
        for j in 0..fy {
            for k in 0..fx {
                let uv = Vec2::new(
                    (x as f32 + (k as f32 + 0.5) / fx as f32) / s as f32,
                    (y as f32 + (j as f32 + 0.5) / fy as f32) / s as f32,
                );
                sum += t.sample(uv);
            }
        }
        *out = sum / (fx * fy) as f32;
    }
    let mut chain = vec![base];
    let mut n = s;
    while n > 1 {
        let prev = chain.last().expect("the base level");
        let half = n / 2;
        let level = (0..half * half)
            .map(|i| {
                let (x, y) = (i % half * 2, i / half * 2);
                (prev[y * n + x]
                    + prev[y * n + x + 1]
                    + prev[(y + 1) * n + x]
                    + prev[(y + 1) * n + x + 1])
                    * 0.25
            })
            .collect();
        chain.push(level);
        n = half;
    }
    chain
}

/// Linear RGB in [0, 1] as sRGB-encoded RGBA8.
fn srgb8(c: Vec3) -> [u8; 4] {
    let [r, g, b] = c.to_array().map(crate::metrics::srgb8);
    [r, g, b, 255]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mips_keep_the_mean_and_the_base_keeps_the_texels() {
        // A 4×2 texture (not square, not a power of two's side) on an 8×8 base: each texel
        // stands twice across and four times down; every level's mean is the texture's.
        let t = Texture {
            width: 4,
            height: 2,
            texels: (0..8).map(|i| Vec3::splat(i as f32 / 7.0)).collect(),
        };
        let chain = mip_chain(&t, 8);
        assert_eq!(chain.len(), 4);
        assert_eq!(chain[0][0], t.texels[0]);
        assert_eq!(chain[0][8 * 7 + 7], t.texels[7]);
        let mean = t.texels.iter().sum::<Vec3>() / 8.0;
        for level in &chain {
            let m = level.iter().sum::<Vec3>() / level.len() as f32;
            assert!((m - mean).abs().max_element() < 1e-5, "{m} vs {mean}");
        }
        // Reduced: a 16×16 checkerboard on a 4×4 base is grey everywhere.
        let checker = Texture {
            width: 16,
            height: 16,
            texels: (0..256)
                .map(|i| Vec3::splat(((i % 16 + i / 16) % 2) as f32))
                .collect(),
        };
        for c in &mip_chain(&checker, 4)[0] {
            assert!((*c - Vec3::splat(0.5)).abs().max_element() < 1e-6, "{c}");
        }
        assert_eq!(srgb8(Vec3::ZERO), [0, 0, 0, 255]);
        assert_eq!(srgb8(Vec3::ONE), [255, 255, 255, 255]);
        assert_eq!(srgb8(Vec3::splat(0.5))[0], 188);
    }
}
