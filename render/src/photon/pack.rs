//! Bit-packed photon batches: what crosses the network in the photon technique.
//!
//! The paper packs direction, power, position, radius and normalisation into 20 bytes per
//! photon without publishing the layout. Three layouts here, all little-endian:
//!
//! | format | position | power | direction | radius | bytes |
//! |---|---|---|---|---|---|
//! | [`PackFormat::Wide20`] | 3 × f32 | RGB, 9-bit mantissas + 5-bit shared exponent | octahedral 2 × 12 bit | 8-bit log | 20 |
//! | [`PackFormat::Compact12`] | 3 × 16 bit in the batch's bounds | RGB, 7-bit mantissas + 5-bit shared exponent | octahedral 2 × 8 bit | 6-bit log | 12 |
//! | [`PackFormat::Compact8`] | Morton order, Exp-Golomb gaps on a grid of 1/12 of each photon's radius (rounded down to a power of two of the smallest's) | RGB, 6-bit dithered mantissas + 4-bit shared exponent | octahedral 2 × 5 bit | 5-bit log | ~7–8 (varies) |
//!
//! Compact8 is a bit stream whose photons come out in Morton order, not the order packed
//! ([`super::compact8`] has its layout and bounds).
//!
//! Power is relative to the batch's largest channel (`power_scale`), radius is log-quantised
//! between the batch's smallest and largest radius (one value when they agree: exact). The
//! kernel normalisation N_κ(r) is a function of the radius and the kernel, so the client
//! recomputes it instead of receiving it. Worst-case errors (the bounds the tests hold):
//!
//! | | Wide20 | Compact12 |
//! |---|---|---|
//! | position, per axis | f32 rounding | extent / 65535 / 2 (15 µm in a 2 m batch) |
//! | each power channel | max channel / 511 | max channel / 127 |
//! | direction | 0.06° | 1.0° |
//! | radius (relative) | ln(hi/lo)/255/2 | ln(hi/lo)/63/2 |
//!
//! A batch carries a CRC-32 of its header and data; [`PackedBatch::unpack`] rejects a batch
//! whose checksum, lengths or header values are wrong, and never panics on any bytes.

use glam::{Vec2, Vec3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::{Photon, compact8};

/// A photon layout.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum PackFormat {
    /// 12 bytes per photon.
    Compact12,
    /// 20 bytes per photon (the paper's size).
    Wide20,
    /// About 8 bytes per photon or fewer: Morton-sorted, positions coded as gaps
    /// ([`super::compact8`]); the size varies with the batch.
    Compact8,
}

impl PackFormat {
    /// Bytes per photon: exact for the fixed layouts, the nominal size of Compact8 (a
    /// batch's own figure is [`PackedBatch::bytes_per_photon`]).
    pub fn bytes_per_photon(self) -> usize {
        match self {
            PackFormat::Compact12 => 12,
            PackFormat::Wide20 => 20,
            PackFormat::Compact8 => 8,
        }
    }

    /// Every name [`Self::parse`] accepts, for error messages.
    pub const NAMES: &'static str = "`compact8`, `compact12` or `wide20`";

    /// Parses `compact8` / `compact12` / `wide20` (or `8` / `12` / `20`).
    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "compact8" | "8" => Some(PackFormat::Compact8),
            "compact12" | "12" => Some(PackFormat::Compact12),
            "wide20" | "20" => Some(PackFormat::Wide20),
            _ => None,
        }
    }

    /// The name [`Self::parse`] reads.
    pub fn name(self) -> &'static str {
        match self {
            PackFormat::Compact8 => "compact8",
            PackFormat::Compact12 => "compact12",
            PackFormat::Wide20 => "wide20",
        }
    }
}

/// Identity of a batch: which light, which of its slots, which generation of that light,
/// and the scene time it was traced for.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct BatchHeader {
    /// Light id ([`super::PhotonLight::id`]).
    pub light: u32,
    /// Slot of this batch among the light's batches.
    pub slot: u32,
    /// Batches of this light per iteration.
    pub slots: u32,
    /// Generation of the light's batch set (increases when the light is re-traced).
    pub generation: u64,
    /// Refinement pass within the generation: 0 first, then one more set of fresh photons
    /// per iteration while the light stands still ([`super::progressive_radius_scale`]).
    pub pass: u32,
    /// Scene time the batch was traced for, seconds.
    pub scene_time_s: f64,
    /// Photons emitted for the batch (the stored ones are fewer or more).
    pub emitted: u32,
    /// What the photons' vectors are ([`super::Receive`]).
    pub receive: super::Receive,
}

/// A packed batch of photons, as sent.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PackedBatch {
    /// Which light, slot and generation, and the scene time traced for.
    pub header: BatchHeader,
    /// Layout of `data`.
    pub format: PackFormat,
    /// Low corner of the photons' bounds, meters.
    pub origin: [f32; 3],
    /// Size of the photons' bounds, meters.
    pub extent: [f32; 3],
    /// Largest power channel of any photon, watts.
    pub power_scale: f32,
    /// Smallest and largest radius, meters.
    pub radius_range: [f32; 2],
    /// Photons in `data`.
    pub count: u32,
    /// CRC-32 of the header fields above and `data`.
    pub checksum: u32,
    /// The photons.
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// Why a batch was rejected.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PackError {
    /// `data` does not hold `count` photons of the format.
    #[error("batch holds {got} bytes, {count} photons of {per} bytes need {}", *count as usize * per)]
    Length {
        /// Bytes present.
        got: usize,
        /// Photons claimed.
        count: u32,
        /// Bytes per photon.
        per: usize,
    },
    /// The checksum does not match.
    #[error("batch checksum mismatch (corrupt or forged)")]
    Checksum,
    /// A header value is out of range.
    #[error("batch header invalid: {0}")]
    Header(&'static str),
    /// A decoded photon is not finite.
    #[error("batch decodes to non-finite photon {0}")]
    NonFinite(u32),
    /// A coded stream is malformed.
    #[error("batch data malformed: {0}")]
    Stream(&'static str),
}

impl PackedBatch {
    /// Packs `photons` with `header` in `format`.
    pub fn pack(header: BatchHeader, photons: &[Photon], format: PackFormat) -> PackedBatch {
        let finite: Vec<&Photon> = photons
            .iter()
            .filter(|p| {
                p.position.is_finite()
                    && p.direction.is_finite()
                    && p.power.is_finite()
                    && p.radius.is_finite()
                    && p.radius > 0.0
            })
            .collect();
        let mut lo = Vec3::splat(f32::INFINITY);
        let mut hi = Vec3::splat(f32::NEG_INFINITY);
        let mut power_scale = 0.0f32;
        let mut r_lo = f32::INFINITY;
        let mut r_hi = 0.0f32;
        for p in &finite {
            lo = lo.min(p.position);
            hi = hi.max(p.position);
            power_scale = power_scale.max(p.power.max_element());
            r_lo = r_lo.min(p.radius);
            r_hi = r_hi.max(p.radius);
        }
        if finite.is_empty() {
            (lo, hi, r_lo, r_hi) = (Vec3::ZERO, Vec3::ZERO, 1.0, 1.0);
        }
        let power_scale = if power_scale > 0.0 { power_scale } else { 1.0 };
        let mut b = PackedBatch {
            header,
            format,
            origin: lo.to_array(),
            extent: (hi - lo).to_array(),
            power_scale,
            radius_range: [r_lo, r_hi],
            count: finite.len() as u32,
            checksum: 0,
            data: Vec::new(),
        };
        if format == PackFormat::Compact8 {
            b.data = compact8::encode(&Quantizer::of(&b).frame(), &finite);
            b.checksum = b.compute_checksum();
            return b;
        }
        b.data = vec![0; finite.len() * format.bytes_per_photon()];
        let q = Quantizer::of(&b);
        // Photons pack independently: in parallel, 1024 at a time.
        let per = format.bytes_per_photon();
        b.data
            .par_chunks_mut(per * 1024)
            .zip(finite.par_chunks(1024))
            .for_each(|(out, photons)| {
                for (o, p) in out.chunks_exact_mut(per).zip(photons) {
                    q.encode(p, o);
                }
            });
        b.checksum = b.compute_checksum();
        b
    }

    /// Bytes of photon data.
    pub fn data_bytes(&self) -> usize {
        self.data.len()
    }

    /// Bytes of data per photon (the format's size when the batch is empty).
    pub fn bytes_per_photon(&self) -> f64 {
        if self.count == 0 {
            self.format.bytes_per_photon() as f64
        } else {
            self.data.len() as f64 / self.count as f64
        }
    }

    /// Recomputes the checksum after the fields were changed (what a sender of forged
    /// batches would do; tests use it to reach the decoder with garbage).
    #[cfg(test)]
    pub(crate) fn seal(&mut self) {
        self.checksum = self.compute_checksum();
    }

    fn compute_checksum(&self) -> u32 {
        let mut h = crc32fast::Hasher::new();
        let id = &self.header;
        h.update(&id.light.to_le_bytes());
        h.update(&id.slot.to_le_bytes());
        h.update(&id.slots.to_le_bytes());
        h.update(&id.generation.to_le_bytes());
        h.update(&id.pass.to_le_bytes());
        h.update(&id.scene_time_s.to_le_bytes());
        h.update(&id.emitted.to_le_bytes());
        h.update(&[self.format as u8]);
        for v in self.origin.iter().chain(&self.extent) {
            h.update(&v.to_le_bytes());
        }
        h.update(&self.power_scale.to_le_bytes());
        h.update(&self.radius_range[0].to_le_bytes());
        h.update(&self.radius_range[1].to_le_bytes());
        h.update(&self.count.to_le_bytes());
        h.update(&self.data);
        h.finalize()
    }

    /// Checks the header, lengths and checksum without decoding.
    pub fn validate(&self) -> Result<(), PackError> {
        let per = self.format.bytes_per_photon();
        let fits = match self.format {
            // Header bits, then at most ~23 bytes a photon (the widest gap and every field).
            PackFormat::Compact8 => self.data.len() <= 2 + 24 * self.count as usize,
            _ => self.data.len() == self.count as usize * per,
        };
        if !fits {
            return Err(PackError::Length {
                got: self.data.len(),
                count: self.count,
                per,
            });
        }
        if self.compute_checksum() != self.checksum {
            return Err(PackError::Checksum);
        }
        if self.header.slots == 0 || self.header.slot >= self.header.slots {
            return Err(PackError::Header("slot outside the light's slots"));
        }
        if !self.header.scene_time_s.is_finite() {
            return Err(PackError::Header("scene time is not finite"));
        }
        let finite = |v: &[f32]| v.iter().all(|x| x.is_finite());
        if !finite(&self.origin) || !finite(&self.extent) || self.extent.iter().any(|e| *e < 0.0) {
            return Err(PackError::Header("bounds are not finite"));
        }
        if !(self.power_scale.is_finite() && self.power_scale > 0.0) {
            return Err(PackError::Header("power scale is not a positive number"));
        }
        let [r0, r1] = self.radius_range;
        if !(r0.is_finite() && r1.is_finite() && r0 > 0.0 && r0 <= r1) {
            return Err(PackError::Header("radius range is invalid"));
        }
        Ok(())
    }

    /// Validates and decodes the photons.
    pub fn unpack(&self) -> Result<Vec<Photon>, PackError> {
        self.validate()?;
        let q = Quantizer::of(self);
        let per = self.format.bytes_per_photon();
        let decoded: Vec<Photon> = match self.format {
            PackFormat::Compact8 => compact8::decode(&q.frame(), &self.data, self.count)?,
            _ => self.data.chunks_exact(per).map(|c| q.decode(c)).collect(),
        };
        let mut out = Vec::with_capacity(self.count as usize);
        for (i, p) in decoded.into_iter().enumerate() {
            if !(p.position.is_finite()
                && p.power.is_finite()
                && p.direction.is_finite()
                && p.radius.is_finite())
            {
                return Err(PackError::NonFinite(i as u32));
            }
            out.push(Photon {
                receive: self.header.receive,
                ..p
            });
        }
        Ok(out)
    }
}

/// The batch-wide ranges photons are quantised against.
struct Quantizer {
    format: PackFormat,
    origin: Vec3,
    extent: Vec3,
    power_scale: f32,
    r_lo: f32,
    log_ratio: f32,
}

impl Quantizer {
    fn of(b: &PackedBatch) -> Self {
        let [r_lo, r_hi] = b.radius_range;
        Quantizer {
            format: b.format,
            origin: Vec3::from_array(b.origin),
            extent: Vec3::from_array(b.extent),
            power_scale: b.power_scale,
            r_lo,
            log_ratio: if r_hi > r_lo && r_lo > 0.0 {
                (r_hi / r_lo).ln()
            } else {
                0.0
            },
        }
    }

    fn frame(&self) -> compact8::Frame {
        compact8::Frame {
            origin: self.origin,
            extent: self.extent,
            power_scale: self.power_scale,
            r_lo: self.r_lo,
            log_ratio: self.log_ratio,
        }
    }

    fn radius_code(&self, r: f32, bits: u32) -> u64 {
        if self.log_ratio <= 0.0 {
            return 0;
        }
        let max = ((1u64 << bits) - 1) as f32;
        quantize((r / self.r_lo).ln() / self.log_ratio * max, max)
    }

    fn radius(&self, code: u64, bits: u32) -> f32 {
        let max = ((1u64 << bits) - 1) as f32;
        self.r_lo * (self.log_ratio * code as f32 / max).exp()
    }

    fn encode(&self, p: &Photon, out: &mut [u8]) {
        let power = p.power.max(Vec3::ZERO) / self.power_scale;
        match self.format {
            PackFormat::Compact12 => {
                let rel = ((p.position - self.origin) / self.extent.max(Vec3::splat(1e-30)))
                    .clamp(Vec3::ZERO, Vec3::ONE);
                // Truncating after +½ rounds (rel is in [0, 1]).
                let q = rel * 65535.0 + Vec3::splat(0.5);
                let (ou, ov) = oct_quantize(p.direction, 8);
                let (e, m) = shared_exponent(power, 7);
                let bits: u128 = q.x as u128
                    | (q.y as u128) << 16
                    | (q.z as u128) << 32
                    | (ou as u128) << 48
                    | (ov as u128) << 56
                    | (e as u128) << 64
                    | (m[0] as u128) << 69
                    | (m[1] as u128) << 76
                    | (m[2] as u128) << 83
                    | (self.radius_code(p.radius, 6) as u128) << 90;
                out.copy_from_slice(&bits.to_le_bytes()[..12]);
            }
            PackFormat::Compact8 => unreachable!("Compact8 is a stream, coded whole"),
            PackFormat::Wide20 => {
                for (k, c) in p.position.to_array().iter().enumerate() {
                    out[4 * k..4 * k + 4].copy_from_slice(&c.to_le_bytes());
                }
                let (ou, ov) = oct_quantize(p.direction, 12);
                let (e, m) = shared_exponent(power, 9);
                let bits: u64 = e
                    | m[0] << 5
                    | m[1] << 14
                    | m[2] << 23
                    | ou << 32
                    | ov << 44
                    | self.radius_code(p.radius, 8) << 56;
                out[12..20].copy_from_slice(&bits.to_le_bytes());
            }
        }
    }

    fn decode(&self, c: &[u8]) -> Photon {
        match self.format {
            PackFormat::Compact12 => {
                let mut bytes = [0u8; 16];
                bytes[..12].copy_from_slice(c);
                let bits = u128::from_le_bytes(bytes);
                let f = |shift: u32, width: u32| ((bits >> shift) & ((1u128 << width) - 1)) as u64;
                let rel = Vec3::new(f(0, 16) as f32, f(16, 16) as f32, f(32, 16) as f32) / 65535.0;
                Photon {
                    position: self.origin + rel * self.extent,
                    direction: oct_dequantize(f(48, 8), f(56, 8), 8),
                    power: from_shared_exponent(exp5(f(64, 5)), [f(69, 7), f(76, 7), f(83, 7)], 7)
                        * self.power_scale,
                    radius: self.radius(f(90, 6), 6),
                    // The header's, set by `unpack`.
                    receive: super::Receive::Normal,
                }
            }
            PackFormat::Compact8 => unreachable!("Compact8 is a stream, decoded whole"),
            PackFormat::Wide20 => {
                let float = |i: usize| f32::from_le_bytes([c[i], c[i + 1], c[i + 2], c[i + 3]]);
                let mut word = [0u8; 8];
                word.copy_from_slice(&c[12..20]);
                let bits = u64::from_le_bytes(word);
                let f = |shift: u32, width: u32| (bits >> shift) & ((1u64 << width) - 1);
                Photon {
                    position: Vec3::new(float(0), float(4), float(8)),
                    direction: oct_dequantize(f(32, 12), f(44, 12), 12),
                    power: from_shared_exponent(exp5(f(0, 5)), [f(5, 9), f(14, 9), f(23, 9)], 9)
                        * self.power_scale,
                    radius: self.radius(f(56, 8), 8),
                    receive: super::Receive::Normal,
                }
            }
        }
    }
}

/// Octahedral map of a unit vector to [−1, 1]², quantised to `bits` per axis.
pub(super) fn oct_quantize(d: Vec3, bits: u32) -> (u64, u64) {
    let d = d.normalize_or(Vec3::Z);
    let n = d / (d.x.abs() + d.y.abs() + d.z.abs());
    let sign = |v: f32| if v >= 0.0 { 1.0 } else { -1.0 };
    let e = if n.z < 0.0 {
        Vec2::new((1.0 - n.y.abs()) * sign(n.x), (1.0 - n.x.abs()) * sign(n.y))
    } else {
        Vec2::new(n.x, n.y)
    };
    let max = ((1u64 << bits) - 1) as f32;
    let q = |v: f32| quantize((v * 0.5 + 0.5) * max, max);
    (q(e.x), q(e.y))
}

pub(super) fn oct_dequantize(u: u64, v: u64, bits: u32) -> Vec3 {
    let max = ((1u64 << bits) - 1) as f32;
    let e = Vec2::new(u as f32 / max * 2.0 - 1.0, v as f32 / max * 2.0 - 1.0);
    let mut n = Vec3::new(e.x, e.y, 1.0 - e.x.abs() - e.y.abs());
    if n.z < 0.0 {
        let sign = |v: f32| if v >= 0.0 { 1.0 } else { -1.0 };
        let (x, y) = (n.x, n.y);
        n.x = (1.0 - y.abs()) * sign(x);
        n.y = (1.0 - x.abs()) * sign(y);
    }
    n.normalize_or(Vec3::Z)
}

/// RGB in [0, 1] as a 5-bit shared exponent (2^(e−31)) and `bits`-bit mantissas.
fn shared_exponent(c: Vec3, bits: u32) -> (u64, [u64; 3]) {
    let c = c.clamp(Vec3::ZERO, Vec3::ONE);
    let m = c.max_element();
    if m <= 2f32.powi(-32) {
        return (0, [0; 3]);
    }
    // ⌈log2 m⌉ from the float's bits (m is normal here).
    let b = m.to_bits();
    let e = (((b >> 23) & 0xff) as i32 - 127 + i32::from(b & 0x7f_ffff != 0)).clamp(-31, 0);
    let inv_scale = pow2(-e);
    let max = ((1u64 << bits) - 1) as f32;
    let q = |v: f32| quantize(v * inv_scale * max, max);
    ((e + 31) as u64, [q(c.x), q(c.y), q(c.z)])
}

/// A 5-bit exponent code as the exponent.
fn exp5(code: u64) -> i32 {
    code as i32 - 31
}

/// Mantissas `m` of `bits` bits times 2^e.
pub(super) fn from_shared_exponent(e: i32, m: [u64; 3], bits: u32) -> Vec3 {
    let scale = pow2(e);
    let max = ((1u64 << bits) - 1) as f32;
    Vec3::new(m[0] as f32, m[1] as f32, m[2] as f32) * (scale / max)
}

/// `v` rounded to the nearest integer in [0, max] (NaN → 0). Adds ½ and truncates: `round()`
/// is a libm call on baseline x86-64, and packing calls this eight times per photon.
fn quantize(v: f32, max: f32) -> u64 {
    (v.clamp(0.0, max) + 0.5) as u64
}

/// 2^e for e in [−126, 127], exactly.
fn pow2(e: i32) -> f32 {
    f32::from_bits(((e + 127) as u32) << 23)
}
