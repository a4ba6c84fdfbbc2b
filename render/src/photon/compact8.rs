//! [`PackFormat::Compact8`](super::PackFormat::Compact8): photons coded against their
//! neighbours, at most ~8 bytes each.
//!
//! The batch's photons are sorted along a Morton curve over a cubic grid whose step is
//! at most the [`STEPS_PER_RADIUS`]-th of the batch's smallest radius, and each photon's
//! Morton code is sent as the gap from the previous one in an Exp-Golomb code whose order
//! the batch chooses (photons lie on surfaces, close to each other, so a 10k-photon
//! batch's gaps take ~20–25 bits where its three coordinates would take 36–48). A photon
//! wider than the smallest stands in a cell 2^k steps wide, 2^k the largest power of two
//! within its radius over the smallest: its position is as fine relative to its own radius
//! as the smallest photon's, as fine as its splat needs and no finer, and its gap is
//! counted in its own cells (3k bits fewer: `city:250000`'s 640k-photon batches went from
//! 8.3 to 8.1 B a photon, and to 7.7 with 12 steps a radius instead of 16). The rest of a
//! photon is fixed-width and comes before its gap, so that the reader knows its cell:
//!
//! | field | bits | error |
//! |---|---|---|
//! | position | Exp-Golomb gap of a Morton code, `3 × (b − k)` bits per code | its cell / 2 per axis: ≤ its radius / (2 × [`STEPS_PER_RADIUS`]) |
//! | power | 4-bit shared exponent + 3 × 6-bit mantissas, dithered | < one step: channel max / 31, unbiased |
//! | direction | octahedral 2 × 5 bit | 5° (the splat only tests its side of a surface) |
//! | radius | 5-bit log in the batch's range (none when all radii agree) | ln(hi/lo)/31/2 |
//!
//! Power mantissas are rounded with a golden-ratio dither per photon, so a batch of photons
//! of equal power (a light's first bounce off one wall) keeps its total instead of all
//! rounding the same way. The stream starts with `b − 1` (4 bits) and the Exp-Golomb order
//! (6 bits); it is read with bounds on every field and must end within its last byte, so
//! malformed data is an error, never a panic.

use std::io;

use bitstream_io::{BitRead, BitReader, BitWrite, BitWriter, LittleEndian};
use glam::{UVec3, Vec3};
use rayon::prelude::*;

use super::Photon;
use super::pack::{PackError, from_shared_exponent, oct_dequantize, oct_quantize};
use crate::voxel::morton;

/// Grid steps per radius: a photon's cell is at most 1/12 of its radius wide. At 1/16 the
/// error was the same within noise (Cornell box 2.5k–40k photons and `city:250000`
/// 160k–640k, seeds 1–4, against `wide20`'s exact positions) for ~0.4 B more a photon.
pub const STEPS_PER_RADIUS: f32 = 12.0;
/// Largest bits per axis (finer than this is Compact12's precision).
const MAX_AXIS_BITS: u32 = 16;
const POWER_EXP_BITS: u32 = 4;
const POWER_BITS: u32 = 6;
const DIRECTION_BITS: u32 = 5;
const RADIUS_BITS: u32 = 5;
const FIXED_DIRECTION_SHIFT: u32 = POWER_EXP_BITS + 3 * POWER_BITS;
/// Bits of a photon's fixed-width word without its radius.
const FIXED_BITS: u32 = FIXED_DIRECTION_SHIFT + 2 * DIRECTION_BITS;

/// The batch-wide values a Compact8 stream is coded against (from the batch's header).
#[derive(Clone, Copy, Debug)]
pub struct Frame {
    /// Low corner of the photons' bounds.
    pub origin: Vec3,
    /// Size of the bounds.
    pub extent: Vec3,
    /// Largest power channel.
    pub power_scale: f32,
    /// Smallest radius.
    pub r_lo: f32,
    /// ln(largest / smallest radius); 0 when all radii agree.
    pub log_ratio: f32,
}

impl Frame {
    /// Bits per axis of the position grid.
    fn axis_bits(&self) -> u32 {
        let size = self.extent.max_element();
        if size.is_nan() || size <= 0.0 {
            return 1;
        }
        let cells = (size / (self.r_lo / STEPS_PER_RADIUS)).max(1.0) + 1.0;
        (cells.log2().ceil() as u32).clamp(1, MAX_AXIS_BITS)
    }

    /// The radius of (fractional) radius code `c`.
    fn radius_of(&self, c: f32) -> f32 {
        let max = ((1u32 << RADIUS_BITS) - 1) as f32;
        self.r_lo * (self.log_ratio * c / max).exp()
    }

    /// Bits per axis that a photon of radius code `c` drops from the grid of `bits` per axis:
    /// its cell is 2^k steps wide, the largest power of two within its radius over the
    /// smallest, so its position is as fine relative to its own radius as the smallest
    /// photon's is to its.
    fn coarse_bits(&self, c: u32, bits: u32) -> u32 {
        // NaN (a forged header) drops nothing.
        if self.log_ratio.is_nan() || self.log_ratio <= 0.0 {
            return 0;
        }
        let max = ((1u32 << RADIUS_BITS) - 1) as f32;
        let octaves = self.log_ratio * c as f32 / max / std::f32::consts::LN_2;
        (octaves.max(0.0) as u32).min(bits)
    }

    /// The grid step for `bits` per axis.
    fn step(&self, bits: u32) -> f32 {
        self.extent.max_element().max(0.0) / ((1u32 << bits) - 1) as f32
    }
}

/// Encodes `photons` (finite, radius > 0, inside `frame`) into a bit stream.
pub fn encode(frame: &Frame, photons: &[&Photon]) -> Vec<u8> {
    if photons.is_empty() {
        return Vec::new();
    }
    let bits = frame.axis_bits();
    let step = frame.step(bits);
    let max = ((1u32 << bits) - 1) as f32;
    // Position in fine steps from the origin, within the grid.
    let steps = |p: Vec3| -> Vec3 {
        if step > 0.0 {
            ((p - frame.origin) / step).clamp(Vec3::ZERO, Vec3::splat(max))
        } else {
            Vec3::ZERO
        }
    };
    // Radius code c stands for r_lo·(hi/lo)^(c/31); bound c sits halfway (in log) to c + 1.
    let radius_bounds: Vec<f32> = (0..(1u32 << RADIUS_BITS) - 1)
        .map(|c| frame.radius_of(c as f32 + 0.5))
        .collect();
    let radius_code = |p: &Photon| -> u32 {
        if frame.log_ratio > 0.0 {
            radius_bounds.partition_point(|b| *b < p.radius) as u32
        } else {
            0
        }
    };
    // (Morton code, radius code, bits per axis dropped, photon): a photon's cell is as
    // coarse as its own radius allows, its code the centre of that cell.
    let mut coded: Vec<(u64, u32, u32, &Photon)> = photons
        .par_iter()
        .with_min_len(8192)
        .map(|p| {
            let c = radius_code(p);
            let k = frame.coarse_bits(c, bits);
            (morton::encode(cell_of(steps(p.position), k)), c, k, *p)
        })
        .collect();
    coded.par_sort_unstable_by_key(|(code, ..)| *code);
    // Gap from the previous code, counted in the photon's own cells (codes are sorted, so
    // its coarse code is never below the previous one's at its scale).
    let gaps: Vec<(u64, u32)> = coded
        .iter()
        .scan(0u64, |prev, (code, _, k, _)| {
            let gap = (code >> (3 * k)) - (*prev >> (3 * k));
            *prev = *code;
            Some((gap, 3 * k))
        })
        .collect();
    let order = best_order(&gaps, 3 * bits);

    let mut w = BitWriter::endian(Vec::with_capacity(photons.len() * 8 + 2), LittleEndian);
    let written: io::Result<()> = (|| {
        w.write_var(4, bits - 1)?;
        w.write_var(6, order)?;
        for (i, ((_, c, _, p), (gap, shift))) in coded.iter().zip(&gaps).enumerate() {
            // The fixed-width fields as one word: exponent, mantissas, direction, radius
            // (before the gap, so that the reader knows the photon's cell size).
            let power = p.power.max(Vec3::ZERO) / frame.power_scale;
            let (e, [r, g, b]) = dithered_shared_exponent(power, i as u64);
            let (u, v) = oct_quantize(p.direction, DIRECTION_BITS);
            let mut word = u64::from(e)
                | r << POWER_EXP_BITS
                | g << (POWER_EXP_BITS + POWER_BITS)
                | b << (POWER_EXP_BITS + 2 * POWER_BITS)
                | u << FIXED_DIRECTION_SHIFT
                | v << (FIXED_DIRECTION_SHIFT + DIRECTION_BITS);
            let mut width = FIXED_BITS;
            if frame.log_ratio > 0.0 {
                word |= u64::from(*c) << FIXED_BITS;
                width += RADIUS_BITS;
            }
            w.write_var(width, word)?;
            write_exp_golomb(&mut w, *gap, order.saturating_sub(*shift))?;
        }
        w.byte_align()
    })();
    written.expect("writing to a Vec cannot fail");
    w.into_writer()
}

/// Decodes `count` photons; the stream must hold exactly them (up to its last byte).
pub fn decode(frame: &Frame, data: &[u8], count: u32) -> Result<Vec<Photon>, PackError> {
    if count == 0 {
        return if data.is_empty() {
            Ok(Vec::new())
        } else {
            Err(PackError::Stream("data after the last photon"))
        };
    }
    let malformed = |_: io::Error| PackError::Stream("data ends before the last photon");
    let mut r = BitReader::endian(data, LittleEndian);
    let bits = r.read_var::<u32>(4).map_err(malformed)? + 1;
    let order = r.read_var::<u32>(6).map_err(malformed)?;
    let code_bits = 3 * bits;
    if order > code_bits {
        return Err(PackError::Stream("gap code order exceeds the code width"));
    }
    let step = frame.step(bits);
    let max_code = (1u64 << code_bits) - 1;
    let radii: Vec<f32> = (0..1u32 << RADIUS_BITS)
        .map(|c| frame.radius_of(c as f32))
        .collect();
    let mut code = 0u64;
    let mut out = Vec::with_capacity(count as usize);
    let width = FIXED_BITS
        + if frame.log_ratio > 0.0 {
            RADIUS_BITS
        } else {
            0
        };
    for _ in 0..count {
        let word = r.read_var::<u64>(width).map_err(malformed)?;
        let field = |shift: u32, bits: u32| (word >> shift) & ((1u64 << bits) - 1);
        let c = field(FIXED_BITS, RADIUS_BITS) as u32;
        let k = frame.coarse_bits(c, bits);
        let shift = 3 * k;
        let gap = read_exp_golomb(&mut r, order.saturating_sub(shift), code_bits - shift)?;
        code = (code >> shift)
            .checked_add(gap)
            .filter(|c| *c <= max_code >> shift)
            .ok_or(PackError::Stream("position outside the batch's grid"))?
            << shift
            | centre_code(k);
        let e = field(0, POWER_EXP_BITS);
        let m = [0, 1, 2].map(|k| field(POWER_EXP_BITS + k * POWER_BITS, POWER_BITS));
        let u = field(FIXED_DIRECTION_SHIFT, DIRECTION_BITS);
        let v = field(FIXED_DIRECTION_SHIFT + DIRECTION_BITS, DIRECTION_BITS);
        let radius = radii[c as usize];
        let exp = e as i32 - ((1 << POWER_EXP_BITS) - 1);
        out.push(Photon {
            position: frame.origin + morton::decode(code).as_vec3() * step,
            direction: oct_dequantize(u, v, DIRECTION_BITS),
            power: from_shared_exponent(exp, m, POWER_BITS) * frame.power_scale,
            radius,
            // The header's, set by `PackedBatch::unpack`.
            receive: super::Receive::Normal,
        });
    }
    r.byte_align();
    if !r.into_reader().is_empty() {
        return Err(PackError::Stream("data after the last photon"));
    }
    Ok(out)
}

/// The fine grid point nearest the centre of the cell `2^k` fine steps wide that holds the
/// point `x` fine steps from the origin (`k` = 0: the grid point nearest `x`).
fn cell_of(x: Vec3, k: u32) -> UVec3 {
    if k == 0 {
        (x + Vec3::splat(0.5)).as_uvec3()
    } else {
        (x / (1u32 << k) as f32).as_uvec3() << k | UVec3::splat(1 << (k - 1))
    }
}

/// The low `3k` bits of the code of any [`cell_of`] at `k`: its centre within its cell.
fn centre_code(k: u32) -> u64 {
    if k == 0 {
        0
    } else {
        morton::encode(UVec3::splat(1 << (k - 1)))
    }
}

/// The Exp-Golomb order that codes `gaps` in the fewest bits: near log2 of their mean
/// (the best order of a geometric distribution), the exact cost of seven orders compared.
/// Each gap comes with the bits its photon's coarser cell drops from the code
/// ([`Frame::coarse_bits`], three per axis); its order is the batch's less those.
fn best_order(gaps: &[(u64, u32)], max_order: u32) -> u32 {
    // Bits of gap g at order k: 2·⌊log2((g >> k) + 1)⌋ + 1 + k.
    let cost = |k: u32| -> u64 {
        gaps.iter()
            .map(|&(g, shift)| exp_golomb_bits(g, k.saturating_sub(shift)))
            .sum()
    };
    let mean = gaps
        .iter()
        .map(|&(g, shift)| g as f64 * f64::from(shift).exp2())
        .sum::<f64>()
        / gaps.len().max(1) as f64;
    let guess = mean.max(1.0).log2() as u32;
    (guess.saturating_sub(3)..=(guess + 3).min(max_order))
        .min_by_key(|k| cost(*k))
        .unwrap_or(0)
}

/// Bits of `value` in an Exp-Golomb code of order `k`.
fn exp_golomb_bits(value: u64, k: u32) -> u64 {
    u64::from(2 * ((value >> k) + 1).ilog2() + 1 + k)
}

fn write_exp_golomb(w: &mut impl BitWrite, gap: u64, order: u32) -> io::Result<()> {
    let high = (gap >> order) + 1;
    let n = high.ilog2();
    w.write_unary::<1>(n)?;
    if n > 0 {
        w.write_var(n, high - (1 << n))?;
    }
    if order > 0 {
        w.write_var(order, gap & ((1u64 << order) - 1))?;
    }
    Ok(())
}

fn read_exp_golomb(r: &mut impl BitRead, order: u32, code_bits: u32) -> Result<u64, PackError> {
    let malformed = |_: io::Error| PackError::Stream("data ends before the last photon");
    let n = r.read_unary::<1>().map_err(malformed)?;
    if n + order > code_bits {
        return Err(PackError::Stream("position gap wider than the grid"));
    }
    let high = if n > 0 {
        (1u64 << n) + r.read_var::<u64>(n).map_err(malformed)?
    } else {
        1
    };
    let low = if order > 0 {
        r.read_var::<u64>(order).map_err(malformed)?
    } else {
        0
    };
    Ok(((high - 1) << order) | low)
}

/// RGB in [0, 1] as a 4-bit shared exponent and 6-bit mantissas, each rounded up with
/// probability equal to its fraction (a golden-ratio sequence over photons stands in for
/// the random numbers), so that rounding adds noise but no bias.
fn dithered_shared_exponent(c: Vec3, i: u64) -> (u32, [u64; 3]) {
    let c = c.clamp(Vec3::ZERO, Vec3::ONE);
    let m = c.max_element();
    let lowest = -((1i32 << POWER_EXP_BITS) - 1);
    if m <= 0.0 {
        return (0, [0; 3]);
    }
    // ⌈log2 m⌉ from the float's bits (libm's log2 and floor cost more than the rest).
    let bits = m.to_bits();
    let e =
        (((bits >> 23) & 0xff) as i32 - 127 + i32::from(bits & 0x7f_ffff != 0)).clamp(lowest, 0);
    let max = ((1u64 << POWER_BITS) - 1) as f32;
    let scale = f32::from_bits(((127 - e) as u32) << 23) * max;
    let mut out = [0u64; 3];
    for (k, v) in c.to_array().into_iter().enumerate() {
        // A Weyl sequence of the golden ratio in 24-bit fixed point.
        let n = i * 3 + k as u64;
        let u = (n.wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 40) as f32 / (1u32 << 24) as f32;
        out[k] = ((v * scale + u) as u64).min(max as u64);
    }
    ((e - lowest) as u32, out)
}
