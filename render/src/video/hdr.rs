//! HDR light maps in 8-bit 4:2:0 video: log₂ luminance in Y, chromaticity in U and V, the
//! frame's luminance range carried beside the stream ([`HdrRange`]).
//!
//! Packing of a texel of linear RGB (R, G, B), luminance L = 0.2126 R + 0.7152 G + 0.0722 B
//! (BT.709), S = R + G + B:
//! - Y = 0 for L = 0 (unlit texels stay exactly black); otherwise
//!   Y = 1 + round(254 · (log₂ L − lo) / (hi − lo)), clamped to [1, 255]. `lo` and `hi` are
//!   whole stops around the frame's valid texels, at most [`MAX_STOPS`] apart (darker texels
//!   are clamped up to 2^lo and counted; so are the darkest [`DARK_SHARE`] of lit texels,
//!   which would otherwise widen every step for a few noisy ones). One code step is (hi − lo)/254 stops, so packing
//!   alone changes luminance by at most 2^(step/2) − 1 (0.55 % at 8 stops, 2.2 % at 16).
//! - U = round(255 · B/S), V = round(255 · R/S) (G/S follows from the two), each averaged
//!   over the valid texels of its 2×2 block; chromaticity of a flat 2×2 block is kept within
//!   1/510.
//! - Texels outside every chart (`valid` false) were filled from their valid neighbours when
//!   the [`HdrMap`] was made, so neither the 2×2 chroma average nor the codec's prediction
//!   pulls garbage into a chart's edge; packing does not dilate again.
//!
//! Unpacking inverts this: L from Y and the range, then S = L / (0.2126 r + 0.7152 g +
//! 0.0722 b) with (r, g, b) the chromaticities, and RGB = S · (r, g, b).

use glam::Vec3;

use super::yuv::{FrameError, Yuv420};
use crate::hdr_map::HdrMap;

/// Widest range of a packed frame, stops (a factor of 65,536 between the darkest and the
/// brightest texel kept apart).
pub const MAX_STOPS: f32 = 16.0;

/// Share of a frame's lit texels that may lie below its range (clamped up to its bottom and
/// counted in [`Packed::clamped`]).
pub const DARK_SHARE: f32 = 0.005;

const LUMA: Vec3 = Vec3::new(0.2126, 0.7152, 0.0722);

/// The luminance range of a packed frame: Y code 1 is 2^`log2_min`, 255 is 2^`log2_max`.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct HdrRange {
    /// log₂ of the smallest non-zero luminance coded.
    pub log2_min: f32,
    /// log₂ of the largest luminance coded.
    pub log2_max: f32,
}

impl HdrRange {
    /// The range covering luminances `min` to `max` (> 0), widened to whole stops and
    /// narrowed to [`MAX_STOPS`] below the top.
    pub fn covering(min: f32, max: f32) -> Self {
        let hi = max.max(f32::MIN_POSITIVE).log2().ceil();
        let lo = min
            .max(f32::MIN_POSITIVE)
            .log2()
            .floor()
            .max(hi - MAX_STOPS);
        HdrRange {
            log2_min: lo,
            log2_max: if hi > lo { hi } else { lo + 1.0 },
        }
    }

    /// Stops per Y code.
    pub fn step_stops(&self) -> f32 {
        (self.log2_max - self.log2_min) / 254.0
    }

    /// The largest relative luminance change packing alone may cause.
    pub fn packing_bound(&self) -> f32 {
        (self.step_stops() * 0.5).exp2() - 1.0
    }

    fn code(&self, l: f32) -> u8 {
        if l <= 0.0 {
            return 0;
        }
        let t = (l.log2() - self.log2_min) / (self.log2_max - self.log2_min);
        (1.0 + (254.0 * t).round()).clamp(1.0, 255.0) as u8
    }

    fn luminance(&self, y: u8) -> f32 {
        if y == 0 {
            return 0.0;
        }
        let t = (y as f32 - 1.0) / 254.0;
        (self.log2_min + t * (self.log2_max - self.log2_min)).exp2()
    }
}

/// A packed frame and the texels that had to be clamped up to the range's bottom.
#[derive(Clone, Debug, PartialEq)]
pub struct Packed {
    /// The 8-bit planes.
    pub yuv: Yuv420,
    /// The range to unpack them with.
    pub range: HdrRange,
    /// Valid lit texels darker than 2^`log2_min` (raised to it).
    pub clamped: usize,
}

/// Packs an HDR map into 8-bit I420 and its range.
pub fn pack(img: &HdrMap) -> Result<Packed, FrameError> {
    let (w, h) = (img.width() as usize, img.height() as usize);
    let mut out = Yuv420::filled(img.width(), img.height(), [0, 85, 85])?;
    let texels = img.texels();
    let mut lit: Vec<f32> = (0..w * h)
        .filter(|&i| img.is_valid(i))
        .map(|i| LUMA.dot(texels[i]))
        .filter(|&l| l > 0.0)
        .collect();
    lit.sort_by(f32::total_cmp);
    let range = match (lit.first(), lit.last()) {
        (Some(_), Some(&max)) => {
            // The darkest DARK_SHARE of lit texels may be clamped: a few noisy or occluded
            // texels would otherwise widen every code step of the frame.
            let low = lit[((lit.len() as f32 * DARK_SHARE) as usize).min(lit.len() - 1)];
            HdrRange::covering(low, max)
        }
        _ => HdrRange::covering(1.0, 1.0),
    };
    let floor = range.log2_min.exp2();
    let mut clamped = 0;
    for (i, c) in texels.iter().enumerate() {
        let l = LUMA.dot(*c);
        if img.is_valid(i) && l > 0.0 && l < floor {
            clamped += 1;
        }
        out.y[i] = range.code(l);
    }
    let cw = w / 2;
    for cy in 0..h / 2 {
        for cx in 0..cw {
            let block =
                [(0, 0), (1, 0), (0, 1), (1, 1)].map(|(dx, dy)| (2 * cy + dy) * w + 2 * cx + dx);
            let any_valid = block.iter().any(|&i| img.is_valid(i));
            let mut sum = (0.0f32, 0.0f32, 0u32);
            for &i in &block {
                let s = texels[i].element_sum();
                if (!any_valid || img.is_valid(i)) && s > 0.0 {
                    sum = (sum.0 + texels[i].z / s, sum.1 + texels[i].x / s, sum.2 + 1);
                }
            }
            if sum.2 > 0 {
                let n = sum.2 as f32;
                out.u[cy * cw + cx] = (255.0 * sum.0 / n).round().clamp(0.0, 255.0) as u8;
                out.v[cy * cw + cx] = (255.0 * sum.1 / n).round().clamp(0.0, 255.0) as u8;
            }
        }
    }
    Ok(Packed {
        yuv: out,
        range,
        clamped,
    })
}

/// Unpacks 8-bit I420 planes into linear RGB texels (chroma upsampled by nearest neighbour).
pub fn unpack(yuv: &Yuv420, range: HdrRange) -> Vec<Vec3> {
    let (w, h) = (yuv.width as usize, yuv.height as usize);
    let cw = w / 2;
    let mut out = Vec::with_capacity(w * h);
    for y in 0..h {
        for x in 0..w {
            let l = range.luminance(yuv.y[y * w + x]);
            let c = (y / 2) * cw + x / 2;
            let (b, r) = (yuv.u[c] as f32 / 255.0, yuv.v[c] as f32 / 255.0);
            let g = (1.0 - r - b).max(0.0);
            let chroma = Vec3::new(r, g, b) / (r + g + b).max(1e-6);
            out.push(chroma * (l / LUMA.dot(chroma).max(1e-6)));
        }
    }
    out
}

/// How far unpacked texels are from the original, over valid texels whose luminance lies in
/// the packed range.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct HdrError {
    /// Mean relative luminance error |L′ − L| / L.
    pub luminance_mean: f64,
    /// 99th percentile of the relative luminance error.
    pub luminance_p99: f64,
    /// Largest relative luminance error.
    pub luminance_max: f64,
    /// Mean chromaticity error: the larger of |r′ − r| and |b′ − b| (r = R/S, b = B/S).
    pub chroma_mean: f64,
    /// Largest chromaticity error.
    pub chroma_max: f64,
    /// Texels compared.
    pub texels: usize,
}

/// Compares `decoded` with the original map.
pub fn error(original: &HdrMap, decoded: &[Vec3], range: HdrRange) -> HdrError {
    let floor = range.log2_min.exp2();
    let mut lum = Vec::new();
    let mut chroma = Vec::new();
    for (i, (a, &b)) in original.texels().into_iter().zip(decoded).enumerate() {
        let l = LUMA.dot(a);
        if !original.is_valid(i) || l < floor {
            continue;
        }
        lum.push(((LUMA.dot(b) - l).abs() / l) as f64);
        let (sa, sb) = (a.element_sum(), b.element_sum().max(1e-12));
        let d = ((a.x / sa - b.x / sb).abs()).max((a.z / sa - b.z / sb).abs());
        chroma.push(d as f64);
    }
    if lum.is_empty() {
        return HdrError::default();
    }
    lum.sort_by(f64::total_cmp);
    let n = lum.len();
    HdrError {
        luminance_mean: lum.iter().sum::<f64>() / n as f64,
        luminance_p99: lum[((n as f64 * 0.99) as usize).min(n - 1)],
        luminance_max: lum[n - 1],
        chroma_mean: chroma.iter().sum::<f64>() / n as f64,
        chroma_max: chroma.iter().copied().fold(0.0, f64::max),
        texels: n,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp_texels(w: u32, h: u32) -> Vec<Vec3> {
        // Luminance over 12 stops across the map, a colour per 2×2 block.
        (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                let l = (x as f32 / w as f32 * 12.0 - 6.0).exp2();
                let tint = match (x / 2 + y / 2) % 3 {
                    0 => Vec3::new(1.0, 0.6, 0.3),
                    1 => Vec3::new(0.3, 0.8, 1.0),
                    _ => Vec3::ONE,
                };
                tint * l
            })
            .collect()
    }

    fn ramp(w: u32, h: u32) -> HdrMap {
        HdrMap::new(w, h, &ramp_texels(w, h), &[]).unwrap()
    }

    #[test]
    fn packing_alone_stays_within_its_stated_bounds() {
        let img = ramp(64, 32);
        let p = pack(&img).unwrap();
        assert_eq!(p.clamped, 0);
        assert!(p.range.log2_max - p.range.log2_min <= MAX_STOPS);
        let e = error(&img, &unpack(&p.yuv, p.range), p.range);
        let bound = p.range.packing_bound() as f64;
        assert!(e.luminance_max <= bound * 1.01 + 1e-5, "{e:?} vs {bound}");
        // Flat 2×2 blocks: chromaticity quantised to 1/255 per channel, G following.
        assert!(e.chroma_max <= 1.0 / 510.0 + 1e-4, "{e:?}");
    }

    #[test]
    fn black_stays_black_and_a_wide_range_is_clamped_and_counted() {
        let mut texels = ramp_texels(8, 8);
        texels[0] = Vec3::ZERO;
        texels[1] = Vec3::splat(1e-7); // 23 stops below the rest
        let p = pack(&HdrMap::new(8, 8, &texels, &[]).unwrap()).unwrap();
        assert_eq!(p.yuv.y[0], 0);
        assert_eq!(p.clamped, 1);
        assert_eq!(p.range.log2_max - p.range.log2_min, MAX_STOPS);
        assert_eq!(unpack(&p.yuv, p.range)[0], Vec3::ZERO);
    }

    #[test]
    fn invalid_texels_take_their_neighbours_so_charts_keep_their_edges() {
        let mut texels = ramp_texels(8, 8);
        let valid: Vec<bool> = (0..64).map(|i| i % 8 < 4).collect();
        for (t, _) in texels.iter_mut().zip(&valid).filter(|(_, v)| !**v) {
            *t = Vec3::new(1e6, 0.0, 0.0); // garbage outside the chart
        }
        let img = HdrMap::new(8, 8, &texels, &valid).unwrap();
        assert!(
            img.texels().iter().all(|c| c.x < 1e3),
            "garbage survived dilation"
        );
        let p = pack(&img).unwrap();
        let e = error(&img, &unpack(&p.yuv, p.range), p.range);
        assert!(
            e.luminance_max <= p.range.packing_bound() as f64 * 1.01 + 1e-5,
            "{e:?}"
        );
    }
}
