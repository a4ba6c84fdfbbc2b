//! 3D Morton codes: the three coordinates' bits interleaved (x lowest), 21 bits per axis.
//! Sorting cells by code keeps each octree node's children contiguous, and a cell's
//! ancestor `k` levels up is its code shifted right by 3k.

use glam::UVec3;

/// Bits per axis a code holds.
pub const BITS: u32 = 21;

/// Spreads the low 21 bits of `v` two zero bits apart.
fn spread(v: u32) -> u64 {
    let mut x = u64::from(v) & 0x1f_ffff;
    x = (x | x << 32) & 0x001f_0000_0000_ffff;
    x = (x | x << 16) & 0x001f_0000_ff00_00ff;
    x = (x | x << 8) & 0x100f_00f0_0f00_f00f;
    x = (x | x << 4) & 0x10c3_0c30_c30c_30c3;
    x = (x | x << 2) & 0x1249_2492_4924_9249;
    x
}

/// Gathers every third bit of `x` back into the low 21 bits.
fn compact(x: u64) -> u32 {
    let mut x = x & 0x1249_2492_4924_9249;
    x = (x | x >> 2) & 0x10c3_0c30_c30c_30c3;
    x = (x | x >> 4) & 0x100f_00f0_0f00_f00f;
    x = (x | x >> 8) & 0x001f_0000_ff00_00ff;
    x = (x | x >> 16) & 0x001f_0000_0000_ffff;
    x = (x | x >> 32) & 0x1f_ffff;
    x as u32
}

/// The code of cell `c` (each coordinate below 2²¹).
pub fn encode(c: UVec3) -> u64 {
    spread(c.x) | spread(c.y) << 1 | spread(c.z) << 2
}

/// The cell of `code`.
pub fn decode(code: u64) -> UVec3 {
    UVec3::new(compact(code), compact(code >> 1), compact(code >> 2))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codes_round_trip_and_interleave_x_lowest() {
        assert_eq!(encode(UVec3::new(1, 0, 0)), 1);
        assert_eq!(encode(UVec3::new(0, 1, 0)), 2);
        assert_eq!(encode(UVec3::new(0, 0, 1)), 4);
        assert_eq!(encode(UVec3::new(2, 0, 0)), 8);
        let max = (1 << BITS) - 1;
        for c in [
            UVec3::ZERO,
            UVec3::new(max, 0, 7),
            UVec3::new(12345, 999_999, max),
            UVec3::splat(max),
        ] {
            assert_eq!(decode(encode(c)), c);
        }
        // The parent of a cell is its code shifted by three bits.
        let c = UVec3::new(37, 1000, 5);
        assert_eq!(encode(c) >> 3, encode(c / 2));
    }
}
