//! Image error metrics: RMSE, relMSE, PSNR and FLIP (LDR through NVIDIA's reference code
//! via the `nv-flip` crate, HDR by the exposure bracketing of HDR-FLIP on top of it).
//!
//! Images are linear RGB radiance, row-major, `width × height`. [`relmse`] takes an
//! absolute ε in the image's units, which hides error wherever radiance is small; every
//! figure this project reports comes from [`compare`] instead: relMSE on images divided by
//! the reference's mean luminance over the pixels that see geometry (so ε = 0.01 means 1%
//! of that mean), HDR-FLIP, and the energy ratio — none of which changes when every light is
//! scaled (ALGORITHMS.md §4).

use glam::Vec3;

/// The ε of relMSE used throughout the project.
pub const REL_MSE_EPSILON: f64 = 0.01;

/// Default viewing condition of FLIP: 67 pixels per degree (a 0.7 m wide 4K screen at 0.7 m).
pub const PIXELS_PER_DEGREE: f32 = 67.0;

fn pairs<'a>(test: &'a [Vec3], reference: &'a [Vec3]) -> impl Iterator<Item = (f64, f64)> + 'a {
    assert_eq!(test.len(), reference.len(), "images differ in size");
    test.iter()
        .zip(reference)
        .flat_map(|(a, b)| (0..3).map(move |c| (a[c] as f64, b[c] as f64)))
}

/// Mean squared error over pixels and channels.
pub fn mse(test: &[Vec3], reference: &[Vec3]) -> f64 {
    let n = (test.len() * 3).max(1) as f64;
    pairs(test, reference)
        .map(|(x, y)| (x - y).powi(2))
        .sum::<f64>()
        / n
}

/// Root mean squared error.
pub fn rmse(test: &[Vec3], reference: &[Vec3]) -> f64 {
    mse(test, reference).sqrt()
}

/// Relative MSE: mean over pixels and channels of (x − y)² / (y² + ε), y the reference.
pub fn relmse(test: &[Vec3], reference: &[Vec3], epsilon: f64) -> f64 {
    let n = (test.len() * 3).max(1) as f64;
    pairs(test, reference)
        .map(|(x, y)| (x - y).powi(2) / (y * y + epsilon))
        .sum::<f64>()
        / n
}

/// Peak signal-to-noise ratio in dB, the peak being the reference's largest channel value
/// (infinite for identical images).
pub fn psnr(test: &[Vec3], reference: &[Vec3]) -> f64 {
    let peak = reference
        .iter()
        .map(|v| v.max_element())
        .fold(0.0f32, f32::max) as f64;
    10.0 * (peak * peak / mse(test, reference)).log10()
}

/// A FLIP comparison.
#[derive(Clone, Debug, PartialEq)]
pub struct Flip {
    /// Mean per-pixel error in [0, 1].
    pub mean: f32,
    /// Per-pixel error in [0, 1].
    pub error_map: Vec<f32>,
    /// Pixel counts in ten equal bins over [0, 1].
    pub histogram: [u32; 10],
}

impl Flip {
    fn from_map(error_map: Vec<f32>) -> Self {
        let mut histogram = [0u32; 10];
        for e in &error_map {
            histogram[((e * 10.0) as usize).min(9)] += 1;
        }
        let mean = error_map.iter().map(|e| *e as f64).sum::<f64>() / error_map.len().max(1) as f64;
        Flip {
            mean: mean as f32,
            error_map,
            histogram,
        }
    }
}

/// LDR-FLIP of sRGB8 images (RGB, 3 bytes per pixel).
pub fn flip_ldr(
    test: &[u8],
    reference: &[u8],
    width: u32,
    height: u32,
    pixels_per_degree: f32,
) -> Flip {
    let r = nv_flip::FlipImageRgb8::with_data(width, height, reference);
    let t = nv_flip::FlipImageRgb8::with_data(width, height, test);
    Flip::from_map(nv_flip::flip(r, t, pixels_per_degree).to_vec())
}

/// The ACES filmic curve (Narkowicz's fit), linear in → [0, 1] out.
pub fn aces(x: f32) -> f32 {
    let x = x.max(0.0);
    ((x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14)).clamp(0.0, 1.0)
}

/// Linear [0, 1] → sRGB-encoded byte.
pub fn srgb8(x: f32) -> u8 {
    let x = x.clamp(0.0, 1.0);
    let s = if x <= 0.003_130_8 {
        12.92 * x
    } else {
        1.055 * x.powf(1.0 / 2.4) - 0.055
    };
    (s * 255.0 + 0.5) as u8
}

/// The inverse of [`aces`] on [0, 1) (the larger root of the curve's quadratic); 1 and
/// above map to infinity.
pub fn aces_inverse(y: f32) -> f32 {
    let y = y.max(0.0) as f64;
    let a = 2.51 - 2.43 * y;
    if a <= 0.0 || y >= 1.0 {
        return f32::INFINITY;
    }
    let b = 0.03 - 0.59 * y;
    let c = -0.14 * y;
    ((-b + (b * b - 4.0 * a * c).sqrt()) / (2.0 * a)) as f32
}

/// An sRGB-encoded byte → linear [0, 1].
pub fn srgb8_to_linear(v: u8) -> f32 {
    let s = v as f32 / 255.0;
    if s <= 0.040_45 {
        s / 12.92
    } else {
        ((s + 0.055) / 1.055).powf(2.4)
    }
}

/// The radiance a picture of [`tonemap`] at exposure `2^stops` shows: each pixel mapped
/// back through sRGB, ACES and the exposure, and whether it is saturated (a channel at
/// 255, whose radiance is only known to be at least what it maps to).
pub fn untonemap(rgb: &[u8], stops: f32) -> (Vec<Vec3>, Vec<bool>) {
    let k = 2f32.powf(-stops);
    let lut: Vec<f32> = (0..=255u8)
        .map(|v| aces_inverse(srgb8_to_linear(v).min(0.999_9)) * k)
        .collect();
    rgb.chunks_exact(3)
        .map(|p| {
            (
                Vec3::new(lut[p[0] as usize], lut[p[1] as usize], lut[p[2] as usize]),
                p.contains(&255),
            )
        })
        .unzip()
}

/// Tone-maps a linear image at exposure `2^stops` with ACES to sRGB8 RGB bytes.
pub fn tonemap(image: &[Vec3], stops: f32) -> Vec<u8> {
    let k = 2f32.powf(stops);
    image
        .iter()
        .flat_map(|v| {
            [
                srgb8(aces(v.x * k)),
                srgb8(aces(v.y * k)),
                srgb8(aces(v.z * k)),
            ]
        })
        .collect()
}

/// A test image's errors against a reference, none of which depends on the unit (or scale)
/// of radiance.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ImageErrors {
    /// relMSE of both images divided by the reference's mean luminance, ε = 0.01, over the
    /// pixels that see geometry.
    pub relmse: f64,
    /// Mean HDR-FLIP over the whole image.
    pub flip: f32,
    /// Mean luminance of the test over the reference's, over the pixels that see geometry.
    pub energy_ratio: f64,
    /// Pixels that see geometry.
    pub pixels: usize,
    /// Share of the relMSE held by the worst [`WORST_PIXELS`] (1%) of those pixels
    /// ([`worst_share`]): near 0.01 where the error is spread (noise, bias), large where a few
    /// pixels hold it.
    #[serde(default)]
    pub worst_share: f64,
}

/// Mean luminance of `image` over the pixels `mask` keeps.
fn masked_mean_luminance(image: &[Vec3], mask: &[bool]) -> (f64, usize) {
    let (sum, n) = image
        .iter()
        .zip(mask)
        .filter(|(_, m)| **m)
        .fold((0.0f64, 0usize), |(s, n), (v, _)| {
            (s + luminance(*v) as f64, n + 1)
        });
    (if n > 0 { sum / n as f64 } else { 0.0 }, n)
}

/// relMSE of `test` against `reference`, both divided by the reference's mean luminance over
/// the pixels `mask` keeps, ε = [`REL_MSE_EPSILON`] (relative), over those pixels. Zero when
/// the reference is black there (nothing to be relative to) and the test is too; infinite
/// when only the test has light.
pub fn relmse_normalized(test: &[Vec3], reference: &[Vec3], mask: &[bool]) -> f64 {
    relmse_of_map(&relmse_map(test, reference, mask), mask)
}

/// The relMSE a [`relmse_map`] stands for: its mean over the pixels `mask` keeps (0 when it
/// keeps none).
pub fn relmse_of_map(map: &[f64], mask: &[bool]) -> f64 {
    let n = mask.iter().filter(|m| **m).count();
    if n == 0 {
        return 0.0;
    }
    map.iter().sum::<f64>() / n as f64
}

/// Each pixel's term of [`relmse_normalized`]: the mean over its channels of
/// (x − y)² / (y² + ε), both divided by the reference's mean luminance over the pixels `mask`
/// keeps; 0 for the pixels it leaves out. Their mean over the kept pixels is the relMSE.
/// Where the reference is black over the whole mask, a kept pixel with light in the test
/// reads infinite, any other 0.
pub fn relmse_map(test: &[Vec3], reference: &[Vec3], mask: &[bool]) -> Vec<f64> {
    assert!(
        test.len() == reference.len() && mask.len() == reference.len(),
        "images and mask differ in size"
    );
    let (mean, _) = masked_mean_luminance(reference, mask);
    let black = mean <= 0.0 || !mean.is_finite();
    let k = if black { 0.0 } else { 1.0 / mean };
    test.iter()
        .zip(reference)
        .zip(mask)
        .map(|((a, b), &kept)| {
            if !kept {
                0.0
            } else if black {
                if luminance(*a) > 0.0 {
                    f64::INFINITY
                } else {
                    0.0
                }
            } else {
                (0..3)
                    .map(|c| {
                        let (x, y) = (a[c] as f64 * k, b[c] as f64 * k);
                        (x - y).powi(2) / (y * y + REL_MSE_EPSILON)
                    })
                    .sum::<f64>()
                    / 3.0
            }
        })
        .collect()
}

/// Share (0–1) of a [`relmse_map`]'s sum that its largest `fraction` of the kept pixels hold
/// (at least one pixel): about `fraction` where the error is spread evenly (noise, a
/// uniform bias), near 1 where a few pixels hold it (light leaking onto a hidden face,
/// fireflies, edges). 0 when there is no error.
pub fn worst_share(map: &[f64], mask: &[bool], fraction: f64) -> f64 {
    let mut kept: Vec<f64> = map
        .iter()
        .zip(mask)
        .filter(|(_, m)| **m)
        .map(|(e, _)| *e)
        .collect();
    let total: f64 = kept.iter().sum();
    if kept.is_empty() || total <= 0.0 {
        return 0.0;
    }
    if !total.is_finite() {
        return 1.0;
    }
    let count = ((kept.len() as f64 * fraction).ceil() as usize).clamp(1, kept.len());
    kept.sort_unstable_by(|a, b| b.total_cmp(a));
    kept[..count].iter().sum::<f64>() / total
}

/// The share of the pixels [`ImageErrors::worst_share`] is about.
pub const WORST_PIXELS: f64 = 0.01;

/// Mean luminance of `test` over that of `reference`, over the pixels `mask` keeps (1 when
/// both are black).
pub fn energy_ratio(test: &[Vec3], reference: &[Vec3], mask: &[bool]) -> f64 {
    let (t, _) = masked_mean_luminance(test, mask);
    let (r, _) = masked_mean_luminance(reference, mask);
    if r > 0.0 {
        t / r
    } else if t > 0.0 {
        f64::INFINITY
    } else {
        1.0
    }
}

/// Every error figure of `test` against `reference` (`width × height`), `mask` marking the
/// pixels that see geometry.
pub fn compare(
    test: &[Vec3],
    reference: &[Vec3],
    mask: &[bool],
    width: u32,
    height: u32,
) -> ImageErrors {
    let map = relmse_map(test, reference, mask);
    ImageErrors {
        relmse: relmse_of_map(&map, mask),
        flip: flip_hdr(test, reference, width, height, PIXELS_PER_DEGREE).mean,
        energy_ratio: energy_ratio(test, reference, mask),
        pixels: mask.iter().filter(|m| **m).count(),
        worst_share: worst_share(&map, mask, WORST_PIXELS),
    }
}

fn luminance(v: Vec3) -> f32 {
    0.2126 * v.x + 0.7152 * v.y + 0.0722 * v.z
}

/// The exposures (stops) HDR-FLIP brackets for `reference`: from the one at which its
/// brightest pixel reaches 0.85 after tone mapping to the one at which its median does.
pub fn hdr_exposures(reference: &[Vec3]) -> Vec<f32> {
    let mut y: Vec<f32> = reference
        .iter()
        .map(|v| luminance(*v))
        .filter(|l| l.is_finite() && *l > 0.0)
        .collect();
    if y.is_empty() {
        return vec![0.0];
    }
    y.sort_by(f32::total_cmp);
    let (median, max) = (y[y.len() / 2], y[y.len() - 1]);
    // Input that ACES maps to 0.85, by bisection (the curve is monotonic).
    let (mut lo, mut hi) = (0.0f32, 100.0f32);
    for _ in 0..60 {
        let mid = 0.5 * (lo + hi);
        if aces(mid) < 0.85 { lo = mid } else { hi = mid }
    }
    let target = 0.5 * (lo + hi);
    let stop = (target / max).log2();
    let start = (target / median).log2();
    let n = ((start - stop).ceil() as usize).max(2);
    (0..n)
        .map(|i| stop + (start - stop) * i as f32 / (n - 1) as f32)
        .collect()
}

/// HDR-FLIP of linear images: LDR-FLIP at each exposure of [`hdr_exposures`] (ACES tone
/// mapping), keeping each pixel's largest error.
pub fn flip_hdr(
    test: &[Vec3],
    reference: &[Vec3],
    width: u32,
    height: u32,
    pixels_per_degree: f32,
) -> Flip {
    let mut worst = vec![0.0f32; test.len()];
    for stops in hdr_exposures(reference) {
        let f = flip_ldr(
            &tonemap(test, stops),
            &tonemap(reference, stops),
            width,
            height,
            pixels_per_degree,
        );
        for (w, e) in worst.iter_mut().zip(f.error_map) {
            *w = w.max(e);
        }
    }
    Flip::from_map(worst)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn untonemap_inverts_tonemap_up_to_quantization() {
        for x in [0.0f32, 0.01, 0.1, 0.5, 1.0, 3.0] {
            let y = aces(x);
            assert!((aces_inverse(y) - x).abs() <= 1e-4 * (1.0 + x), "{x}");
        }
        for v in 0..=255u8 {
            assert_eq!(srgb8(srgb8_to_linear(v)), v);
        }
        let image = vec![
            Vec3::new(0.05, 0.2, 0.7),
            Vec3::new(0.4, 0.4, 0.4),
            Vec3::splat(500.0),
        ];
        let (back, saturated) = untonemap(&tonemap(&image, 1.0), 1.0);
        assert_eq!(saturated, vec![false, false, true]);
        for (a, b) in image.iter().zip(&back).take(2) {
            for c in 0..3 {
                assert!((a[c] - b[c]).abs() <= 0.03 * a[c], "{a} {b}");
            }
        }
    }

    fn flat(v: f32, n: usize) -> Vec<Vec3> {
        vec![Vec3::splat(v); n]
    }

    #[test]
    fn closed_forms_on_constant_images() {
        let (a, b) = (flat(1.1, 16), flat(1.0, 16));
        assert!((rmse(&a, &b) - 0.1).abs() < 1e-6);
        assert!((relmse(&a, &b, 0.01) - 0.01 / 1.01).abs() < 1e-6);
        assert!((psnr(&a, &b) - 20.0).abs() < 1e-4);
        assert_eq!(rmse(&b, &b), 0.0);
        assert_eq!(relmse(&b, &b, REL_MSE_EPSILON), 0.0);
        assert!(psnr(&b, &b).is_infinite());
        // relMSE is asymmetric: relative to the reference.
        assert!(relmse(&b, &a, 0.01) < relmse(&a, &b, 0.01));
    }

    #[test]
    fn normalized_errors_do_not_change_when_every_light_is_scaled() {
        let (w, h) = (16u32, 16u32);
        let reference: Vec<Vec3> = (0..w * h)
            .map(|i| Vec3::new(0.2 + (i % 7) as f32 * 0.1, 0.3, 0.1 + (i % 3) as f32 * 0.2))
            .collect();
        let test: Vec<Vec3> = reference
            .iter()
            .enumerate()
            .map(|(i, v)| *v * if i % 4 == 0 { 1.4 } else { 0.9 })
            .collect();
        let mask: Vec<bool> = (0..w * h).map(|i| i % 5 != 0).collect();
        let base = compare(&test, &reference, &mask, w, h);
        assert!(base.relmse > 0.01 && base.flip > 0.0, "{base:?}");
        assert!((base.energy_ratio - 1.0).abs() > 0.01);
        assert_eq!(base.pixels, mask.iter().filter(|m| **m).count());
        for k in [1e-6f32, 1e6] {
            let s = |img: &[Vec3]| img.iter().map(|v| *v * k).collect::<Vec<_>>();
            let e = compare(&s(&test), &s(&reference), &mask, w, h);
            assert!(
                (e.relmse / base.relmse - 1.0).abs() < 1e-4,
                "{k}: {e:?} vs {base:?}"
            );
            assert!((e.energy_ratio / base.energy_ratio - 1.0).abs() < 1e-5);
            assert!((e.flip - base.flip).abs() < 1e-3, "{k}: {e:?} vs {base:?}");
            // The absolute-ε relMSE is what it is not: it reads ~0 at small radiance.
            let absolute = relmse(&s(&test), &s(&reference), REL_MSE_EPSILON);
            if k < 1.0 {
                assert!(absolute < base.relmse * 1e-6);
            }
        }
        // Masked-out pixels do not count; a black reference with a black test is no error.
        let mut outside = test.clone();
        for (i, v) in outside.iter_mut().enumerate() {
            if !mask[i] {
                *v = Vec3::splat(1e9);
            }
        }
        assert_eq!(relmse_normalized(&outside, &reference, &mask), base.relmse);
        let black = vec![Vec3::ZERO; (w * h) as usize];
        assert_eq!(relmse_normalized(&black, &black, &mask), 0.0);
        assert_eq!(energy_ratio(&black, &black, &mask), 1.0);
        assert!(relmse_normalized(&test, &black, &mask).is_infinite());
    }

    #[test]
    fn the_error_map_sums_to_the_relmse_and_tells_spread_error_from_a_few_bad_pixels() {
        let (w, h) = (20u32, 10u32);
        let n = (w * h) as usize;
        let reference: Vec<Vec3> = (0..n)
            .map(|i| Vec3::new(0.5 + (i % 5) as f32 * 0.1, 0.4, 0.3))
            .collect();
        let mask: Vec<bool> = (0..n).map(|i| i % 7 != 0).collect();
        let kept = mask.iter().filter(|m| **m).count();
        // Every pixel 10% too bright: the error is spread, the worst 1% hold about 1%.
        let spread: Vec<Vec3> = reference.iter().map(|v| *v * 1.1).collect();
        let map = relmse_map(&spread, &reference, &mask);
        let mean = map.iter().sum::<f64>() / kept as f64;
        assert!((mean / relmse_normalized(&spread, &reference, &mask) - 1.0).abs() < 1e-12);
        assert!(map.iter().zip(&mask).all(|(e, m)| *m || *e == 0.0));
        let share = worst_share(&map, &mask, WORST_PIXELS);
        assert!(share > 0.005 && share < 0.03, "{share}");
        // One pixel lit where the reference is dark holds nearly all of it.
        let mut leak = reference.clone();
        leak[1] = Vec3::splat(40.0);
        let errors = compare(&leak, &reference, &mask, w, h);
        assert!(errors.worst_share > 0.99, "{errors:?}");
        let map = relmse_map(&leak, &reference, &mask);
        assert_eq!(
            map.iter()
                .enumerate()
                .max_by(|a, b| a.1.total_cmp(b.1))
                .unwrap()
                .0,
            1
        );
        assert!((map.iter().sum::<f64>() / kept as f64 / errors.relmse - 1.0).abs() < 1e-12);
        // The same under any scale of the lights; nothing wrong, nothing to share.
        let s = |img: &[Vec3]| img.iter().map(|v| *v * 1e-5).collect::<Vec<_>>();
        let scaled = relmse_map(&s(&leak), &s(&reference), &mask);
        assert!(
            scaled
                .iter()
                .zip(&map)
                .all(|(a, b)| (a - b).abs() <= 1e-3 * b.max(1e-9))
        );
        assert_eq!(
            worst_share(&relmse_map(&reference, &reference, &mask), &mask, 0.01),
            0.0
        );
        assert_eq!(worst_share(&map, &[false; 200], 0.01), 0.0);
    }

    #[test]
    fn flip_sees_nothing_between_equal_images_and_much_between_black_and_white() {
        let (w, h) = (32, 32);
        let grey = vec![128u8; (w * h * 3) as usize];
        let same = flip_ldr(&grey, &grey, w, h, PIXELS_PER_DEGREE);
        assert!(same.mean < 1e-6, "{}", same.mean);
        assert_eq!(same.histogram[0], w * h);
        let black = vec![0u8; (w * h * 3) as usize];
        let white = vec![255u8; (w * h * 3) as usize];
        let far = flip_ldr(&black, &white, w, h, PIXELS_PER_DEGREE);
        assert!(far.mean > 0.8, "{}", far.mean);
        let noisy: Vec<u8> = grey
            .iter()
            .enumerate()
            .map(|(i, g)| g.wrapping_add((i % 7) as u8))
            .collect();
        let small = flip_ldr(&noisy, &grey, w, h, PIXELS_PER_DEGREE);
        assert!(small.mean > 0.0 && small.mean < 0.2, "{}", small.mean);
    }

    #[test]
    fn hdr_flip_does_not_depend_on_the_unit_of_radiance() {
        let (w, h) = (24, 24);
        let reference: Vec<Vec3> = (0..w * h)
            .map(|i| Vec3::splat(0.05 + (i % 24) as f32 * 0.2))
            .collect();
        let test: Vec<Vec3> = reference
            .iter()
            .enumerate()
            .map(|(i, v)| *v * if i % 5 == 0 { 1.3 } else { 1.0 })
            .collect();
        let f1 = flip_hdr(&test, &reference, w, h, PIXELS_PER_DEGREE);
        let scaled = |img: &[Vec3]| img.iter().map(|v| *v * 1000.0).collect::<Vec<_>>();
        let f2 = flip_hdr(&scaled(&test), &scaled(&reference), w, h, PIXELS_PER_DEGREE);
        assert!(f1.mean > 0.0);
        assert!(
            (f1.mean - f2.mean).abs() < 0.01,
            "{} vs {}",
            f1.mean,
            f2.mean
        );
        assert!(hdr_exposures(&reference).len() >= 2);
    }
}
