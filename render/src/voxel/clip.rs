//! The part of a triangle inside an axis-aligned box (Sutherland–Hodgman against the six
//! planes): its area and centroid, which give a voxel its exact share of a surface.

use glam::Vec3;

/// Vertices a triangle clipped by a box can have (3 + one per plane).
const MAX_VERTICES: usize = 9;

/// A convex polygon of at most [`MAX_VERTICES`] vertices.
#[derive(Clone, Copy)]
struct Polygon {
    v: [Vec3; MAX_VERTICES],
    n: usize,
}

impl Polygon {
    /// Keeps the part at or above `bound` along `axis`, or strictly below it: a polygon lying
    /// on a boundary between two boxes belongs to the upper one only.
    fn clip(&self, axis: usize, bound: f32, keep_below: bool) -> Polygon {
        let mut out = Polygon {
            v: [Vec3::ZERO; MAX_VERTICES],
            n: 0,
        };
        let inside = |p: Vec3| {
            if keep_below {
                p[axis] < bound
            } else {
                p[axis] >= bound
            }
        };
        for i in 0..self.n {
            let (a, b) = (self.v[i], self.v[(i + 1) % self.n]);
            let (ia, ib) = (inside(a), inside(b));
            if ia && out.n < MAX_VERTICES {
                out.v[out.n] = a;
                out.n += 1;
            }
            if ia != ib && out.n < MAX_VERTICES {
                let t = ((bound - a[axis]) / (b[axis] - a[axis])).clamp(0.0, 1.0);
                let mut p = a + (b - a) * t;
                p[axis] = bound;
                out.v[out.n] = p;
                out.n += 1;
            }
        }
        out
    }
}

/// The area and area centroid of triangle `t` inside the box `lo..hi` (lower faces
/// included, upper ones not); `None` when less than a 1e-12 share of the box's face area
/// lies inside.
pub fn clip_triangle(t: [Vec3; 3], lo: Vec3, hi: Vec3) -> Option<(f32, Vec3)> {
    let mut poly = Polygon {
        v: [Vec3::ZERO; MAX_VERTICES],
        n: 3,
    };
    poly.v[..3].copy_from_slice(&t);
    for axis in 0..3 {
        poly = poly.clip(axis, lo[axis], false);
        if poly.n < 3 {
            return None;
        }
        poly = poly.clip(axis, hi[axis], true);
        if poly.n < 3 {
            return None;
        }
    }
    // Fan from the first vertex: area and area-weighted centroid.
    let mut twice_area = 0.0f32;
    let mut centroid = Vec3::ZERO;
    let o = poly.v[0];
    for i in 1..poly.n - 1 {
        let (a, b) = (poly.v[i], poly.v[i + 1]);
        let w = (a - o).cross(b - o).length();
        twice_area += w;
        centroid += (o + a + b) * (w / 3.0);
    }
    let face = (hi - lo).max_element().powi(2);
    (twice_area > 2e-12 * face).then(|| (0.5 * twice_area, centroid / twice_area))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_triangle_split_by_boxes_keeps_its_area() {
        let t = [
            Vec3::new(0.1, 0.2, 0.3),
            Vec3::new(3.7, 0.9, 1.4),
            Vec3::new(1.2, 2.8, 2.9),
        ];
        let area = 0.5 * (t[1] - t[0]).cross(t[2] - t[0]).length();
        let mut sum = 0.0;
        let mut moment = Vec3::ZERO;
        for x in 0..4 {
            for y in 0..3 {
                for z in 0..3 {
                    let lo = Vec3::new(x as f32, y as f32, z as f32);
                    if let Some((a, c)) = clip_triangle(t, lo, lo + 1.0) {
                        assert!(c.cmpge(lo - 1e-5).all() && c.cmple(lo + 1.0 + 1e-5).all());
                        sum += a;
                        moment += c * a;
                    }
                }
            }
        }
        assert!((sum - area).abs() < 1e-4 * area, "{sum} against {area}");
        let centroid = (t[0] + t[1] + t[2]) / 3.0;
        assert!((moment / sum - centroid).length() < 1e-4);
        // Outside, and touching a face only.
        assert!(clip_triangle(t, Vec3::splat(10.0), Vec3::splat(11.0)).is_none());
        let flat = [Vec3::ZERO, Vec3::X, Vec3::Y];
        // A triangle on the face two boxes share belongs to the upper box alone.
        assert!(clip_triangle(flat, Vec3::new(0.0, 0.0, -1.0), Vec3::new(1.0, 1.0, 0.0)).is_none());
        let (a, _) = clip_triangle(flat, Vec3::ZERO, Vec3::ONE).unwrap();
        assert!((a - 0.5).abs() < 1e-6);
        assert!(clip_triangle(flat, Vec3::new(0.0, 0.0, 0.5), Vec3::new(1.0, 1.0, 1.0)).is_none());
    }
}
