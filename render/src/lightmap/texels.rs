//! The texel G-buffer: which surface point each light-map texel stands for.
//!
//! Triangles are rasterised in light-map UV space (a texel belongs to the triangle covering
//! its centre). A texel is stored as (triangle, barycentrics), so its world position and
//! normal follow the object through motion ([`TexelSurface::frame_at`]). Two repairs keep
//! light from leaking through walls and seams:
//! - **moved out**: a texel whose surrounding texel-sized neighbourhood crosses the back of
//!   another surface (a wall standing on a floor) is pushed past that surface, as Godot's
//!   and Bakery's bakers do;
//! - **buried**: a texel whose hemisphere mostly sees back faces lies inside or under other
//!   geometry (a floor under a block) and is invalid: nothing can see it.
//!
//! Invalid texels (padding, buried) are filled from valid neighbours when a map is output
//! (dilation), so bilinear filtering and the codec never pull in black.

use cloudlight_scenes::WorldTriangle;
use glam::{Vec2, Vec3};
use rayon::prelude::*;

use crate::bvh::SceneBvh;
use crate::sampling::{basis, cosine_hemisphere};

/// A texel's surface point: triangle index (into the scene's `triangles_at` order) and the
/// barycentric weights of its vertices 1 and 2.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TexelPoint {
    /// Triangle index.
    pub triangle: u32,
    /// Weights of vertices 1 and 2.
    pub bary: Vec2,
    /// Offset along the surface applied by the move-out repair, meters (world frame at
    /// time 0; small, so kept through rigid motion as a translation).
    pub shift: Vec3,
}

/// The texel G-buffer of an atlas.
#[derive(Clone, Debug, PartialEq)]
pub struct TexelSurface {
    /// Map width, texels.
    pub width: u32,
    /// Map height, texels.
    pub height: u32,
    /// Per texel (row-major from the top): its surface point, `None` outside every chart.
    pub points: Vec<Option<TexelPoint>>,
    /// Per texel: a valid surface point (covered and not buried).
    pub valid: Vec<bool>,
    /// World position at time 0, meters (zero where invalid).
    pub positions: Vec<Vec3>,
    /// Unit normal at time 0 (zero where invalid).
    pub normals: Vec<Vec3>,
    /// Texel edge, meters (from the atlas density).
    pub texel_m: f32,
    /// Texels moved out from under other geometry.
    pub moved: u32,
    /// Texels invalidated as buried.
    pub buried: u32,
}

/// Hemisphere rays per texel of the buried test.
const BURIED_RAYS: u32 = 16;

impl TexelSurface {
    /// Rasterises `triangles` (with light-map UVs) into a `width` × `height` map and repairs
    /// it against `bvh` (the same triangles).
    pub fn build(
        triangles: &[WorldTriangle],
        bvh: &SceneBvh,
        width: u32,
        height: u32,
        texel_m: f32,
    ) -> Self {
        let (w, h) = (width as usize, height as usize);
        let mut points: Vec<Option<TexelPoint>> = vec![None; w * h];
        for (ti, t) in triangles.iter().enumerate() {
            rasterize(t, ti as u32, width, height, &mut points);
        }
        let eps = {
            let (lo, hi) = bvh.bounds();
            let e = (hi - lo).length() * 1e-5;
            if e.is_finite() && e > 0.0 { e } else { 1e-5 }
        };
        let repaired: Vec<(Option<TexelPoint>, bool, bool)> = points
            .par_iter()
            .map(|p| match p {
                None => (None, false, false),
                Some(p) => repair(*p, triangles, bvh, texel_m, eps),
            })
            .collect();
        let mut s = TexelSurface {
            width,
            height,
            points: Vec::with_capacity(w * h),
            valid: Vec::with_capacity(w * h),
            positions: vec![Vec3::ZERO; w * h],
            normals: vec![Vec3::ZERO; w * h],
            texel_m,
            moved: 0,
            buried: 0,
        };
        for (p, moved, buried) in repaired {
            s.moved += moved as u32;
            s.buried += buried as u32;
            s.valid.push(p.is_some() && !buried);
            s.points.push(p);
        }
        let (pos, nrm) = s.frame_at(triangles);
        s.positions = pos;
        s.normals = nrm;
        s
    }

    /// Number of valid texels.
    pub fn valid_count(&self) -> usize {
        self.valid.iter().filter(|v| **v).count()
    }

    /// World positions and unit normals of every texel on `triangles` (the scene's
    /// triangles at some time, in the order the map was built from); zero where invalid.
    pub fn frame_at(&self, triangles: &[WorldTriangle]) -> (Vec<Vec3>, Vec<Vec3>) {
        self.points
            .par_iter()
            .zip(&self.valid)
            .map(|(p, &valid)| match p {
                Some(p) if valid => {
                    let (x, n) = surface_point(&triangles[p.triangle as usize], p.bary);
                    (x + p.shift, n)
                }
                _ => (Vec3::ZERO, Vec3::ZERO),
            })
            .unzip()
    }
}

/// Position and unit normal of triangle `t` at barycentrics `b`.
pub fn surface_point(t: &WorldTriangle, b: Vec2) -> (Vec3, Vec3) {
    let w0 = 1.0 - b.x - b.y;
    let x = t.v[0] * w0 + t.v[1] * b.x + t.v[2] * b.y;
    let ng = (t.v[1] - t.v[0]).cross(t.v[2] - t.v[0]).normalize_or_zero();
    let n = (t.n[0] * w0 + t.n[1] * b.x + t.n[2] * b.y).normalize_or(ng);
    // Shade with the geometric side the triangle faces (its front, counter-clockwise).
    (
        x,
        if n.dot(ng) < 0.0 && ng != Vec3::ZERO {
            -n
        } else {
            n
        },
    )
}

/// Marks the texels whose centres `t` covers in UV space.
fn rasterize(
    t: &WorldTriangle,
    index: u32,
    width: u32,
    height: u32,
    points: &mut [Option<TexelPoint>],
) {
    let size = Vec2::new(width as f32, height as f32);
    let p = t.lightmap_uv.map(|uv| uv * size);
    let area = (p[1] - p[0]).perp_dot(p[2] - p[0]);
    if !area.is_finite() || area.abs() < 1e-12 {
        return;
    }
    let lo = p[0].min(p[1]).min(p[2]).floor().max(Vec2::ZERO);
    let hi = p[0].max(p[1]).max(p[2]).ceil().min(size);
    for y in lo.y as u32..hi.y as u32 {
        for x in lo.x as u32..hi.x as u32 {
            let c = Vec2::new(x as f32 + 0.5, y as f32 + 0.5);
            let b1 = (c - p[0]).perp_dot(p[2] - p[0]) / area;
            let b2 = (p[1] - p[0]).perp_dot(c - p[0]) / area;
            let b0 = 1.0 - b1 - b2;
            let inside = -1e-4;
            if b0 >= inside && b1 >= inside && b2 >= inside {
                let slot = &mut points[(y * width + x) as usize];
                if slot.is_none() {
                    *slot = Some(TexelPoint {
                        triangle: index,
                        bary: Vec2::new(b1, b2).clamp(Vec2::ZERO, Vec2::ONE),
                        shift: Vec3::ZERO,
                    });
                }
            }
        }
    }
}

/// The move-out and buried repairs of one texel: (point, moved, buried).
fn repair(
    p: TexelPoint,
    triangles: &[WorldTriangle],
    bvh: &SceneBvh,
    texel_m: f32,
    eps: f32,
) -> (Option<TexelPoint>, bool, bool) {
    let (x, n) = surface_point(&triangles[p.triangle as usize], p.bary);
    if !x.is_finite() || n == Vec3::ZERO {
        return (None, false, false);
    }
    let (t, b) = basis(n);
    let origin = x + n * eps;
    let mut moved = p;
    let mut was_moved = false;
    // Along the surface, a texel's neighbourhood (one texel edge) that ends behind another
    // surface: push past it.
    for dir in [t, -t, b, -b] {
        if let Some(hit) = bvh.closest_hit(origin, dir, texel_m)
            && bvh.geometric_normal(hit.triangle).dot(dir) > 0.0
        {
            moved.shift = dir * (hit.t + 2.0 * eps + 0.05 * texel_m);
            was_moved = true;
            break;
        }
    }
    let o = origin + moved.shift;
    let mut back = 0;
    for i in 0..BURIED_RAYS {
        let (u1, u2) = hammersley(i, BURIED_RAYS);
        let l = cosine_hemisphere(u1, u2);
        let d = (t * l.x + b * l.y + n * l.z).normalize();
        if let Some(hit) = bvh.closest_hit(o, d, f32::INFINITY) {
            back += (bvh.geometric_normal(hit.triangle).dot(d) > 0.0) as u32;
        }
    }
    (Some(moved), was_moved, back * 2 > BURIED_RAYS)
}

/// The `i`-th of `n` Hammersley points in [0, 1)²: (i / n, radical inverse of i).
pub fn hammersley(i: u32, n: u32) -> (f32, f32) {
    (
        (i as f32 + 0.5) / n as f32,
        (i.reverse_bits() as f64 / 4_294_967_296.0) as f32,
    )
}
