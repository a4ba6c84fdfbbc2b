//! [`HdrMap`]: the one type of an HDR light map, from the kernel that computes it (the
//! irradiance gatherer) through every edge (in process or on the wire, unchanged) to the
//! video packer and the client that shows it.
//!
//! A map holds linear RGB per texel (W·m⁻² or radiance, as its producer says), row-major from
//! the top, as `f16` of value / `scale` (6 bytes a texel): the brightest channel lands at
//! 2¹⁴, so any light unit fits f16's range, with a relative precision of 2⁻¹¹ over the 28
//! stops below the brightest (darker texels flush towards 0). Chart coverage is one bit a
//! texel. Texels outside every chart are **dilated once, when the map is made**
//! ([`dilate`]): filled from their valid neighbours, so that a bilinear lookup at a chart's
//! edge, the packer's 2×2 chroma average and the codec's prediction never pull garbage in.
//! Because the stored form is the wire form, a map is the same bits in process and across a
//! cut edge.
//!
//! A map from a peer may be anything: [`HdrMap::check`] it before use (sizes agree, the scale
//! is a positive finite number); non-finite and negative values always read as 0.

use glam::{Vec2, Vec3};
use serde::{Deserialize, Serialize};

/// Rings of invalid texels filled from their neighbours when a map is made: more than the
/// light-map atlas's widest gutter (two paddings of 4, rounded up to 4×4 blocks). Texels
/// further from every chart take the mean of the valid texels.
pub const DILATE_RINGS: usize = 16;

/// Largest side of a map, texels.
pub const MAX_SIDE: u32 = 16384;

/// Where the brightest channel lands in f16.
const TOP: f32 = 16384.0;

/// Why values do not make a map.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum HdrMapError {
    /// A side is 0 or over [`MAX_SIDE`].
    #[error("a {width}×{height} map (sides must be 1 to {MAX_SIDE})")]
    Size {
        /// Width, texels.
        width: u32,
        /// Height, texels.
        height: u32,
    },
    /// The texel or coverage data does not match the sides.
    #[error("{what}: {got} for a {width}×{height} map, {want} expected")]
    Length {
        /// Which data.
        what: &'static str,
        /// Width, texels.
        width: u32,
        /// Height, texels.
        height: u32,
        /// What came.
        got: usize,
        /// What the sides ask for.
        want: usize,
    },
    /// The scale is not a positive finite number.
    #[error("scale {0} is not a positive finite number")]
    Scale(f32),
}

/// An HDR light map (see the module documentation).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HdrMap {
    width: u32,
    height: u32,
    scale: f32,
    /// `f16` R, G, B per texel, little-endian.
    #[serde(with = "serde_bytes")]
    texels: Vec<u8>,
    /// Bit `i % 8` of byte `i / 8`: texel `i` lies in a chart (empty: every texel does).
    #[serde(with = "serde_bytes")]
    valid: Vec<u8>,
}

/// Each channel as itself when finite and positive, else 0.
fn clean(c: Vec3) -> Vec3 {
    let one = |v: f32| if v.is_finite() && v > 0.0 { v } else { 0.0 };
    Vec3::new(one(c.x), one(c.y), one(c.z))
}

impl HdrMap {
    /// A map of `texels` (one per texel; negative and non-finite values become 0) with chart
    /// coverage `valid` (one per texel; empty: every texel is valid), dilated into the
    /// invalid texels.
    pub fn new(
        width: u32,
        height: u32,
        texels: &[Vec3],
        valid: &[bool],
    ) -> Result<Self, HdrMapError> {
        check_size(width, height)?;
        let n = width as usize * height as usize;
        let length = |what, got| HdrMapError::Length {
            what,
            width,
            height,
            got,
            want: n,
        };
        if texels.len() != n {
            return Err(length("texels", texels.len()));
        }
        if !valid.is_empty() && valid.len() != n {
            return Err(length("coverage flags", valid.len()));
        }
        let plan = DilationPlan::new(width, height, valid, DILATE_RINGS);
        Ok(Self::filled(&plan, &plan.apply(texels), valid))
    }

    /// A map of `texels` (one per texel of `plan`'s mask) dilated by `plan` (a plan of
    /// [`DILATE_RINGS`] rings: [`HdrMap::new`]'s dilation, made once for a mask that does not
    /// change), with the plan's mask as its coverage.
    pub fn from_plan(plan: &DilationPlan, texels: &[Vec3]) -> Result<Self, HdrMapError> {
        let (width, height) = (plan.width, plan.height);
        check_size(width, height)?;
        let n = width as usize * height as usize;
        if texels.len() != n {
            return Err(HdrMapError::Length {
                what: "texels",
                width,
                height,
                got: texels.len(),
                want: n,
            });
        }
        let mut valid = vec![false; if plan.valid.is_some() { n } else { 0 }];
        for &i in plan.valid.iter().flatten() {
            valid[i as usize] = true;
        }
        Ok(Self::filled(plan, &plan.apply(texels), &valid))
    }

    /// The map of already dilated texels `filled` with coverage `valid`.
    fn filled(plan: &DilationPlan, filled: &[Vec3], valid: &[bool]) -> Self {
        let (width, height) = (plan.width, plan.height);
        let n = width as usize * height as usize;
        let max = filled
            .iter()
            .map(|t| t.max_element())
            .fold(0.0f32, f32::max);
        let scale = if max > 0.0 && (max / TOP).is_normal() {
            max / TOP
        } else {
            1.0
        };
        let bytes = filled
            .iter()
            .flat_map(|t| t.to_array())
            .flat_map(|c| half::f16::from_f32(c / scale).to_le_bytes())
            .collect();
        let mut bits = vec![0u8; if valid.is_empty() { 0 } else { n.div_ceil(8) }];
        for (i, _) in valid.iter().enumerate().filter(|(_, v)| **v) {
            bits[i / 8] |= 1 << (i % 8);
        }
        HdrMap {
            width,
            height,
            scale,
            texels: bytes,
            valid: bits,
        }
    }

    /// A black map with every texel valid.
    pub fn black(width: u32, height: u32) -> Result<Self, HdrMapError> {
        let n = width as usize * height as usize;
        check_size(width, height)?;
        Self::new(width, height, &vec![Vec3::ZERO; n], &[])
    }

    /// Checks a map from a peer: sides in range, data as long as the sides ask, a positive
    /// finite scale.
    pub fn check(&self) -> Result<(), HdrMapError> {
        check_size(self.width, self.height)?;
        let n = self.len();
        let length = |what, got, want| HdrMapError::Length {
            what,
            width: self.width,
            height: self.height,
            got,
            want,
        };
        if self.texels.len() != n * 6 {
            return Err(length("texel bytes", self.texels.len(), n * 6));
        }
        if !self.valid.is_empty() && self.valid.len() != n.div_ceil(8) {
            return Err(length("coverage bytes", self.valid.len(), n.div_ceil(8)));
        }
        if !(self.scale.is_finite() && self.scale > 0.0) {
            return Err(HdrMapError::Scale(self.scale));
        }
        Ok(())
    }

    /// Width, texels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height, texels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Texels in the map.
    pub fn len(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// Whether the map has no texel (never, for a checked map).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Bytes of texel and coverage data (what the map costs on the wire, framing aside).
    pub fn data_bytes(&self) -> usize {
        self.texels.len() + self.valid.len()
    }

    /// Texel `i` (row-major from the top); 0 outside the map.
    pub fn texel(&self, i: usize) -> Vec3 {
        let Some(b) = self.texels.get(i * 6..i * 6 + 6) else {
            return Vec3::ZERO;
        };
        let c = |k: usize| half::f16::from_le_bytes([b[k], b[k + 1]]).to_f32() * self.scale;
        clean(Vec3::new(c(0), c(2), c(4)))
    }

    /// Texel at column `x`, row `y` from the top (clamped to the map).
    pub fn at(&self, x: u32, y: u32) -> Vec3 {
        let (x, y) = (x.min(self.width - 1), y.min(self.height - 1));
        self.texel((y * self.width + x) as usize)
    }

    /// Every texel, as linear RGB.
    pub fn texels(&self) -> Vec<Vec3> {
        (0..self.len()).map(|i| self.texel(i)).collect()
    }

    /// Whether texel `i` lies in a chart.
    pub fn is_valid(&self, i: usize) -> bool {
        self.valid.is_empty() || self.valid.get(i / 8).is_some_and(|b| b >> (i % 8) & 1 == 1)
    }

    /// Chart coverage per texel (empty: every texel is valid).
    pub fn valid(&self) -> Vec<bool> {
        if self.valid.is_empty() {
            return Vec::new();
        }
        (0..self.len()).map(|i| self.is_valid(i)).collect()
    }

    /// Texels that lie in a chart.
    pub fn valid_count(&self) -> usize {
        (0..self.len()).filter(|&i| self.is_valid(i)).count()
    }

    /// Mean of the valid texels.
    pub fn mean_valid(&self) -> Vec3 {
        let (sum, n) = (0..self.len())
            .filter(|&i| self.is_valid(i))
            .fold((Vec3::ZERO, 0usize), |(s, n), i| (s + self.texel(i), n + 1));
        sum / n.max(1) as f32
    }

    /// What a stored `f16` is multiplied by to give the texel's value.
    pub fn scale(&self) -> f32 {
        self.scale
    }

    /// The texels as `f16` RGBA of value / [`HdrMap::scale`] (alpha 1), little-endian, 8
    /// bytes a texel: an `Rgba16Float` texture's bytes.
    pub fn rgba16_bytes(&self) -> Vec<u8> {
        const ONE: [u8; 2] = half::f16::ONE.to_bits().to_le_bytes();
        self.texels
            .chunks_exact(6)
            .flat_map(|rgb| {
                let mut t = [0u8; 8];
                t[..6].copy_from_slice(rgb);
                t[6..].copy_from_slice(&ONE);
                t
            })
            .collect()
    }

    /// Bilinear lookup at light-map UV `uv` in [0, 1]² (clamped at the edges).
    pub fn sample(&self, uv: Vec2) -> Vec3 {
        bilinear_with(self.width, self.height, uv, |x, y| self.at(x, y))
    }
}

fn check_size(width: u32, height: u32) -> Result<(), HdrMapError> {
    if (1..=MAX_SIDE).contains(&width) && (1..=MAX_SIDE).contains(&height) {
        Ok(())
    } else {
        Err(HdrMapError::Size { width, height })
    }
}

/// Bilinear lookup at `uv` in a `w` × `h` map of `texels`.
pub fn bilinear(texels: &[Vec3], w: u32, h: u32, uv: Vec2) -> Vec3 {
    if texels.len() != w as usize * h as usize {
        return Vec3::ZERO;
    }
    bilinear_with(w, h, uv, |x, y| texels[(y * w + x) as usize])
}

/// Bilinear lookup at `uv` in a `w` × `h` map whose texel (x, y) is `at(x, y)`.
fn bilinear_with(w: u32, h: u32, uv: Vec2, at: impl Fn(u32, u32) -> Vec3) -> Vec3 {
    if w == 0 || h == 0 {
        return Vec3::ZERO;
    }
    let p = uv * Vec2::new(w as f32, h as f32) - 0.5;
    let p = if p.is_finite() { p } else { Vec2::ZERO };
    let x0 = p.x.floor().clamp(0.0, (w - 1) as f32);
    let y0 = p.y.floor().clamp(0.0, (h - 1) as f32);
    let f = (p - Vec2::new(x0, y0)).clamp(Vec2::ZERO, Vec2::ONE);
    let (x0, y0) = (x0 as u32, y0 as u32);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let top = at(x0, y0).lerp(at(x1, y0), f.x);
    let bottom = at(x0, y1).lerp(at(x1, y1), f.x);
    top.lerp(bottom, f.y)
}

/// `texels` of a `width` × `height` map (negative and non-finite values as 0) with the
/// texels outside `valid` (empty: all valid) filled from their valid 4-neighbours, ring by
/// ring (at most `rings`); what is left takes the mean of the valid texels.
pub fn dilate(width: u32, height: u32, texels: &[Vec3], valid: &[bool], rings: usize) -> Vec<Vec3> {
    DilationPlan::new(width, height, valid, rings).apply(texels)
}

/// How [`dilate`] fills one coverage mask: which invalid texel takes the mean of which known
/// 4-neighbours, ring by ring. A light map's mask never changes, so its plan is made once and
/// applied to every update in one pass over the invalid texels, instead of scanning the whole
/// map once per ring.
#[derive(Clone, Debug, PartialEq)]
pub struct DilationPlan {
    width: u32,
    height: u32,
    /// (texel, its known neighbours, how many), in fill order. A texel filled in one ring is
    /// read only by later rings, so applying the steps in order, in place, is the ring-by-ring
    /// fill.
    steps: Vec<(u32, [u32; 4], u8)>,
    /// Texels no ring reached: they take the mean of the valid texels.
    rest: Vec<u32>,
    /// The valid texels (`None`: no mask, nothing to fill).
    valid: Option<Vec<u32>>,
}

impl DilationPlan {
    /// The plan of `rings` rings for a `width` × `height` mask `valid` (empty, or of another
    /// length: nothing is filled).
    pub fn new(width: u32, height: u32, valid: &[bool], rings: usize) -> Self {
        let (w, h) = (width as usize, height as usize);
        let mut plan = DilationPlan {
            width,
            height,
            steps: Vec::new(),
            rest: Vec::new(),
            valid: None,
        };
        if valid.is_empty() || valid.len() != w * h {
            return plan;
        }
        plan.valid = Some((0..w * h).filter(|&i| valid[i]).map(|i| i as u32).collect());
        let mut known = valid.to_vec();
        let mut frontier: Vec<usize> = (0..w * h).filter(|&i| !valid[i]).collect();
        for _ in 0..rings {
            let mut ring = Vec::new();
            for &i in &frontier {
                let (x, y) = (i % w, i / w);
                let neighbours = [
                    (x > 0).then(|| i - 1),
                    (x + 1 < w).then(|| i + 1),
                    (y > 0).then(|| i - w),
                    (y + 1 < h).then(|| i + w),
                ];
                let mut sources = [0u32; 4];
                let mut n = 0u8;
                for j in neighbours.into_iter().flatten().filter(|&j| known[j]) {
                    sources[n as usize] = j as u32;
                    n += 1;
                }
                if n > 0 {
                    ring.push((i as u32, sources, n));
                }
            }
            if ring.is_empty() {
                break;
            }
            for &(i, ..) in &ring {
                known[i as usize] = true;
            }
            frontier.retain(|&i| !known[i]);
            plan.steps.extend(ring);
        }
        plan.rest = frontier.into_iter().map(|i| i as u32).collect();
        plan
    }

    /// Width of the mask, texels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height of the mask, texels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// `texels` (negative and non-finite values as 0) with the plan's texels filled.
    pub fn apply(&self, texels: &[Vec3]) -> Vec<Vec3> {
        let mut out: Vec<Vec3> = texels.iter().map(|&c| clean(c)).collect();
        let Some(valid) = &self.valid else {
            return out;
        };
        if out.len() != self.width as usize * self.height as usize {
            return out;
        }
        for &(i, sources, n) in &self.steps {
            let sum = sources[..n as usize]
                .iter()
                .fold(Vec3::ZERO, |s, &j| s + out[j as usize]);
            out[i as usize] = sum / f32::from(n);
        }
        if !self.rest.is_empty() {
            let sum = valid.iter().fold(Vec3::ZERO, |s, &i| s + out[i as usize]);
            let mean = sum / (valid.len() as f32).max(1.0);
            for &i in &self.rest {
                out[i as usize] = mean;
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn any_light_unit_keeps_f16_precision() {
        for unit in [1e-6f32, 1.0, 1e6] {
            let texels: Vec<Vec3> = (0..20)
                .map(|i| Vec3::new(1.0, 0.5, 0.25) * unit * 1.5f32.powi(i - 10))
                .collect();
            let m = HdrMap::new(4, 5, &texels, &[]).unwrap();
            m.check().unwrap();
            assert_eq!(m.data_bytes(), 20 * 6);
            for (a, b) in m.texels().iter().zip(&texels) {
                let rel = ((*a - *b).abs() / b.max_element()).max_element();
                assert!(rel <= 1.0 / 2048.0, "unit {unit}: {a} for {b}");
            }
        }
        let bad =
            HdrMap::new(2, 1, &[Vec3::NAN, Vec3::new(-1.0, f32::INFINITY, 2.0)], &[]).unwrap();
        assert_eq!(bad.texels(), vec![Vec3::ZERO, Vec3::new(0.0, 0.0, 2.0)]);
        let dark = HdrMap::black(1, 1).unwrap();
        assert_eq!((dark.scale, dark.texels()), (1.0, vec![Vec3::ZERO]));
    }

    #[test]
    fn invalid_texels_are_filled_from_their_charts_once_when_the_map_is_made() {
        // Left half a chart (a ramp), right half garbage outside every chart.
        let (w, h) = (8u32, 4u32);
        let valid: Vec<bool> = (0..w * h).map(|i| i % w < 4).collect();
        let texels: Vec<Vec3> = (0..w * h)
            .map(|i| {
                if valid[i as usize] {
                    Vec3::splat(1.0 + (i % w) as f32)
                } else {
                    Vec3::new(1e6, f32::NAN, -5.0)
                }
            })
            .collect();
        let m = HdrMap::new(w, h, &texels, &valid).unwrap();
        assert_eq!(m.valid(), valid);
        assert_eq!(m.valid_count(), 16);
        for y in 0..h {
            // The ring next to the chart takes its edge, and so on outwards.
            for x in 4..w {
                assert!(
                    (m.at(x, y) - Vec3::splat(4.0)).abs().max_element() < 1e-2,
                    "{x},{y}"
                );
            }
        }
        // Nothing of the chart moved.
        for y in 0..h {
            for x in 0..4 {
                assert!((m.at(x, y).x - (1.0 + x as f32)).abs() < 1e-2);
            }
        }
        // A texel too far from every chart takes the chart's mean.
        let far = dilate(w, h, &texels, &valid, 1);
        assert_eq!(far[4], Vec3::splat(4.0));
        assert_eq!((far[5], far[7]), (Vec3::splat(2.5), Vec3::splat(2.5)));
    }

    /// The ring-by-ring scan the plan replaces, kept as the reference it must match.
    fn scan_dilate(w: usize, h: usize, texels: &[Vec3], valid: &[bool], rings: usize) -> Vec<Vec3> {
        let mut out: Vec<Vec3> = texels.iter().map(|&c| clean(c)).collect();
        let mut known = valid.to_vec();
        for _ in 0..rings {
            let mut filled = Vec::new();
            for i in (0..w * h).filter(|&i| !known[i]) {
                let (x, y) = (i % w, i / w);
                let (sum, n) = [
                    (x > 0).then(|| i - 1),
                    (x + 1 < w).then(|| i + 1),
                    (y > 0).then(|| i - w),
                    (y + 1 < h).then(|| i + w),
                ]
                .into_iter()
                .flatten()
                .filter(|&j| known[j])
                .fold((Vec3::ZERO, 0), |(s, n), j| (s + out[j], n + 1));
                if n > 0 {
                    filled.push((i, sum / n as f32));
                }
            }
            for (i, c) in filled {
                out[i] = c;
                known[i] = true;
            }
        }
        let (sum, n) = (0..w * h)
            .filter(|&i| valid[i])
            .fold((Vec3::ZERO, 0), |(s, n), i| (s + out[i], n + 1));
        for i in (0..w * h).filter(|&i| !known[i]) {
            out[i] = sum / (n as f32).max(1.0);
        }
        out
    }

    #[test]
    fn a_dilation_plan_fills_exactly_as_the_ring_scan_and_a_map_from_it_is_the_same_map() {
        let (w, h) = (37usize, 23usize);
        let mut rng = crate::sampling::Rng::new(9, 0);
        for density in [0.0f32, 0.02, 0.3, 0.9, 1.0] {
            let valid: Vec<bool> = (0..w * h).map(|_| rng.next_f32() < density).collect();
            let texels: Vec<Vec3> = (0..w * h)
                .map(|_| Vec3::new(rng.next_f32(), rng.next_f32() * 4.0, -0.1))
                .collect();
            for rings in [0, 1, 3, DILATE_RINGS] {
                let plan = DilationPlan::new(w as u32, h as u32, &valid, rings);
                let want = scan_dilate(w, h, &texels, &valid, rings);
                assert_eq!(
                    plan.apply(&texels),
                    want,
                    "density {density}, {rings} rings"
                );
            }
            let plan = DilationPlan::new(w as u32, h as u32, &valid, DILATE_RINGS);
            let a = HdrMap::new(w as u32, h as u32, &texels, &valid).unwrap();
            assert_eq!(
                HdrMap::from_plan(&plan, &texels).unwrap(),
                a,
                "density {density}"
            );
        }
        // No mask: nothing filled, only cleaned.
        let plan = DilationPlan::new(2, 1, &[], DILATE_RINGS);
        assert_eq!(plan.apply(&[Vec3::NAN, Vec3::ONE]), [Vec3::ZERO, Vec3::ONE]);
        assert!(HdrMap::from_plan(&plan, &[Vec3::ONE]).is_err());
    }

    #[test]
    fn check_refuses_what_does_not_add_up() {
        let good = HdrMap::new(2, 2, &[Vec3::ONE; 4], &[true, false, true, true]).unwrap();
        good.check().unwrap();
        let mut short = good.clone();
        short.texels.pop();
        assert!(matches!(short.check(), Err(HdrMapError::Length { .. })));
        let mut wide = good.clone();
        wide.width = 3;
        assert!(wide.check().is_err());
        let mut coverage = good.clone();
        coverage.valid.push(0);
        assert!(
            coverage
                .check()
                .unwrap_err()
                .to_string()
                .contains("coverage")
        );
        for scale in [0.0, -1.0, f32::NAN, f32::INFINITY] {
            let mut s = good.clone();
            s.scale = scale;
            assert!(
                matches!(s.check(), Err(HdrMapError::Scale(_))),
                "scale {scale}"
            );
        }
        let mut empty = good;
        (empty.width, empty.texels) = (0, Vec::new());
        assert!(matches!(empty.check(), Err(HdrMapError::Size { .. })));
        assert!(HdrMap::new(2, 2, &[Vec3::ONE; 3], &[]).is_err());
        assert!(HdrMap::new(2, 2, &[Vec3::ONE; 4], &[true; 3]).is_err());
        assert!(HdrMap::new(0, 2, &[], &[]).is_err());
        // A map from a peer with garbage reads as 0, never NaN.
        let mut nan = HdrMap::new(1, 1, &[Vec3::ONE], &[]).unwrap();
        nan.texels = half::f16::NAN.to_le_bytes().repeat(3);
        assert_eq!(nan.texel(0), Vec3::ZERO);
        assert_eq!(nan.texel(5), Vec3::ZERO);
    }

    #[test]
    fn bilinear_lookups_interpolate_inside_and_clamp_outside() {
        let texels = [Vec3::ZERO, Vec3::ONE, Vec3::splat(2.0), Vec3::splat(3.0)];
        let m = HdrMap::new(2, 2, &texels, &[]).unwrap();
        // Texel centres.
        assert_eq!(m.sample(Vec2::new(0.25, 0.25)), Vec3::ZERO);
        assert_eq!(m.sample(Vec2::new(0.75, 0.75)), Vec3::splat(3.0));
        // The middle averages all four.
        assert!(
            (m.sample(Vec2::splat(0.5)) - Vec3::splat(1.5))
                .abs()
                .max_element()
                < 1e-3
        );
        // Outside clamps; non-finite UVs read the first texel.
        assert_eq!(m.sample(Vec2::new(-3.0, -3.0)), Vec3::ZERO);
        assert_eq!(m.sample(Vec2::new(9.0, 9.0)), Vec3::splat(3.0));
        assert_eq!(m.sample(Vec2::NAN), Vec3::ZERO);
        assert_eq!(bilinear(&texels, 2, 2, Vec2::splat(0.5)), Vec3::splat(1.5));
        assert_eq!(bilinear(&texels[..3], 2, 2, Vec2::splat(0.5)), Vec3::ZERO);
    }
}
