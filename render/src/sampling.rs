//! Deterministic sampling: a counter-based random stream per (pixel, sample, seed), and the
//! warps the integrators use. Same inputs, same numbers, on any thread.

use glam::{Vec2, Vec3};

/// A small PCG-style generator seeded from a hash of its stream identifiers.
#[derive(Clone, Debug)]
pub struct Rng {
    state: u64,
}

fn mix(mut x: u64) -> u64 {
    // SplitMix64 finalizer.
    x = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    x = (x ^ (x >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    x ^ (x >> 31)
}

impl Rng {
    /// A stream for `(seed, stream)`; e.g. stream = pixel index × samples + sample.
    pub fn new(seed: u64, stream: u64) -> Self {
        Rng {
            state: mix(mix(seed) ^ stream.wrapping_mul(0xD1B5_4A32_D192_ED03)),
        }
    }

    /// Next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        mix(self.state)
    }

    /// Uniform in [0, 1).
    pub fn next_f32(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }
}

/// Uniform direction on the unit sphere.
pub fn uniform_sphere(u1: f32, u2: f32) -> Vec3 {
    let z = 1.0 - 2.0 * u1;
    let r = (1.0 - z * z).max(0.0).sqrt();
    let phi = std::f32::consts::TAU * u2;
    Vec3::new(r * phi.cos(), r * phi.sin(), z)
}

/// Cosine-weighted direction around +z (pdf cosθ/π), by Malley's method on a concentric disk.
pub fn cosine_hemisphere(u1: f32, u2: f32) -> Vec3 {
    let d = concentric_disk(u1, u2);
    Vec3::new(d.x, d.y, (1.0 - d.length_squared()).max(0.0).sqrt())
}

/// Shirley–Chiu concentric map from the unit square to the unit disk.
pub fn concentric_disk(u1: f32, u2: f32) -> Vec2 {
    let o = Vec2::new(2.0 * u1 - 1.0, 2.0 * u2 - 1.0);
    if o == Vec2::ZERO {
        return Vec2::ZERO;
    }
    let (r, theta) = if o.x.abs() > o.y.abs() {
        (o.x, std::f32::consts::FRAC_PI_4 * (o.y / o.x))
    } else {
        (
            o.y,
            std::f32::consts::FRAC_PI_2 - std::f32::consts::FRAC_PI_4 * (o.x / o.y),
        )
    };
    Vec2::new(r * theta.cos(), r * theta.sin())
}

/// An orthonormal basis (tangent, bitangent) around unit `n` (Duff et al. 2017).
pub fn basis(n: Vec3) -> (Vec3, Vec3) {
    let sign = 1f32.copysign(n.z);
    let a = -1.0 / (sign + n.z);
    let b = n.x * n.y * a;
    (
        Vec3::new(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x),
        Vec3::new(b, sign + n.y * n.y * a, -n.y),
    )
}

/// The Morton (Z-curve) code of `(x, y)`: interleaved bits, x in the even ones.
pub fn morton2(x: u32, y: u32) -> u64 {
    fn spread(v: u32) -> u64 {
        let mut x = u64::from(v);
        x = (x | (x << 16)) & 0x0000_FFFF_0000_FFFF;
        x = (x | (x << 8)) & 0x00FF_00FF_00FF_00FF;
        x = (x | (x << 4)) & 0x0F0F_0F0F_0F0F_0F0F;
        x = (x | (x << 2)) & 0x3333_3333_3333_3333;
        (x | (x << 1)) & 0x5555_5555_5555_5555
    }
    spread(x) | (spread(y) << 1)
}

/// The base-3 radical inverse of `i` in [0, 1): the third Halton dimension, which with the
/// Hammersley pair (i / n, base-2 inverse) stratifies a third coordinate.
pub fn radical_inverse3(mut i: u32) -> f32 {
    let (mut inv, mut f) = (0.0f64, 1.0f64 / 3.0);
    while i > 0 {
        inv += f64::from(i % 3) * f;
        i /= 3;
        f /= 3.0;
    }
    inv as f32
}

/// Uniform point on a triangle, as barycentric weights of vertices 1 and 2.
pub fn uniform_triangle(u1: f32, u2: f32) -> Vec2 {
    let s = u1.sqrt();
    Vec2::new(s * (1.0 - u2), s * u2)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn streams_are_deterministic_and_distinct() {
        let a: Vec<u64> = (0..4)
            .map(|_| 0)
            .scan(Rng::new(1, 2), |r, _| Some(r.next_u64()))
            .collect();
        let b: Vec<u64> = (0..4)
            .map(|_| 0)
            .scan(Rng::new(1, 2), |r, _| Some(r.next_u64()))
            .collect();
        let c: Vec<u64> = (0..4)
            .map(|_| 0)
            .scan(Rng::new(1, 3), |r, _| Some(r.next_u64()))
            .collect();
        assert_eq!(a, b);
        assert_ne!(a, c);
    }

    #[test]
    fn cosine_hemisphere_has_the_right_moments() {
        // E[cos θ] under pdf cos θ/π is 2/3; every sample is in the upper hemisphere.
        let mut rng = Rng::new(3, 0);
        let n = 200_000;
        let mut sum = 0.0f64;
        for _ in 0..n {
            let d = cosine_hemisphere(rng.next_f32(), rng.next_f32());
            assert!(d.z >= 0.0 && (d.length() - 1.0).abs() < 1e-4);
            sum += d.z as f64;
        }
        assert!(
            (sum / n as f64 - 2.0 / 3.0).abs() < 3e-3,
            "{}",
            sum / n as f64
        );
    }

    #[test]
    fn basis_is_orthonormal() {
        let mut rng = Rng::new(5, 0);
        for _ in 0..1000 {
            let n = uniform_sphere(rng.next_f32(), rng.next_f32());
            let (t, b) = basis(n);
            assert!(t.dot(n).abs() < 1e-5 && b.dot(n).abs() < 1e-5 && t.dot(b).abs() < 1e-5);
            assert!((t.length() - 1.0).abs() < 1e-5 && (b.length() - 1.0).abs() < 1e-5);
        }
    }
}
