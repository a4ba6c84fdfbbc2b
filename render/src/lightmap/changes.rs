//! What changed between two updates of a light map, so that an update re-computes only
//! what it must ([`super::Gatherer::update`]):
//! - **lights**: a punctual light whose state differs, or an emissive object that moved,
//!   makes every texel's direct light stale;
//! - **movers**: objects whose transform differs, as world boxes at both times. A texel's
//!   direct light is stale if a shadow ray of it may cross a mover; a basis must gather
//!   again if one of its rays' segments may cross a mover, if its own texels moved, or if its
//!   rays read a part of the map whose radiosity changed ([`TileChanges`]).
//!
//! The tests are conservative (boxes around segments), so what they keep is exactly what a
//! full update would compute, up to [`RADIOSITY_TOLERANCE`].

use cloudlight_scenes::{LightState, Scene};
use glam::Vec3;

/// Radiosity change, relative to the map's mean radiosity, below which a texel counts as
/// unchanged (the gather is not repeated for it; the error this leaves is at most this
/// fraction of the mean irradiance per bounce).
pub const RADIOSITY_TOLERANCE: f32 = 1e-3;

/// An axis-aligned box, meters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb {
    /// Lower corner.
    pub lo: Vec3,
    /// Upper corner.
    pub hi: Vec3,
}

impl Default for Aabb {
    fn default() -> Self {
        Aabb::EMPTY
    }
}

impl Aabb {
    /// Contains nothing.
    pub const EMPTY: Aabb = Aabb {
        lo: Vec3::INFINITY,
        hi: Vec3::NEG_INFINITY,
    };

    /// The box around `points`.
    pub fn around(points: impl IntoIterator<Item = Vec3>) -> Aabb {
        let mut b = Aabb::EMPTY;
        for p in points {
            b.grow(p);
        }
        b
    }

    /// Grows to contain `p`.
    pub fn grow(&mut self, p: Vec3) {
        self.lo = self.lo.min(p);
        self.hi = self.hi.max(p);
    }

    /// Whether the two boxes share a point.
    pub fn intersects(&self, o: &Aabb) -> bool {
        self.lo.cmple(o.hi).all() && o.lo.cmple(self.hi).all()
    }

    /// Whether the ray `o + t·d`, t ≥ 0, enters the box (slab test).
    pub fn hit_by_ray(&self, o: Vec3, d: Vec3) -> bool {
        let inv = d.recip();
        let (a, b) = ((self.lo - o) * inv, (self.hi - o) * inv);
        let near = a.min(b);
        let far = a.max(b);
        // NaN (a zero direction component on a slab's plane) counts as inside that slab.
        let t0 = near
            .to_array()
            .into_iter()
            .filter(|t| !t.is_nan())
            .fold(0.0f32, f32::max);
        let t1 = far
            .to_array()
            .into_iter()
            .filter(|t| !t.is_nan())
            .fold(f32::INFINITY, f32::min);
        t0 <= t1
    }

    /// Where the ray `o + t·d` from inside leaves the box (its far slab), or `o` if it does
    /// not.
    pub fn exit(&self, o: Vec3, d: Vec3) -> Vec3 {
        let inv = d.recip();
        let far = ((self.lo - o) * inv).max((self.hi - o) * inv);
        let t = far
            .to_array()
            .into_iter()
            .filter(|t| t.is_finite() && *t >= 0.0)
            .fold(f32::INFINITY, f32::min);
        if t.is_finite() { o + d * t } else { o }
    }
}

/// What moved between two scene times.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Changes {
    /// Every texel's direct light is stale: a light changed or an emissive object moved.
    pub lights: bool,
    /// World boxes of the objects that moved, at both times.
    pub movers: Vec<Aabb>,
    /// Per object, whether it moved.
    pub moved: Vec<bool>,
}

impl Changes {
    /// What differs in `scene` between `t0_s` and `t1_s`.
    pub fn between(scene: &Scene, t0_s: f64, t1_s: f64) -> Changes {
        let mut c = Changes {
            moved: vec![false; scene.objects.len()],
            ..Default::default()
        };
        for (i, o) in scene.objects.iter().enumerate() {
            if !o.motion.is_animated() {
                continue;
            }
            let (a, b) = (
                o.motion.world_from_local(t0_s),
                o.motion.world_from_local(t1_s),
            );
            if a == b {
                continue;
            }
            c.moved[i] = true;
            c.lights |= scene.materials[o.material as usize].emission.max_element() > 0.0;
            for m in [a, b] {
                c.movers.push(Aabb::around(
                    o.mesh.positions.iter().map(|&p| m.transform_point3(p)),
                ));
            }
        }
        c.lights |= scene.lights.iter().any(|l| l.at(t0_s) != l.at(t1_s));
        c
    }

    /// Whether nothing moved.
    pub fn none(&self) -> bool {
        !self.lights && self.movers.is_empty()
    }

    /// Whether the segment from `a` to `b` may cross a mover.
    pub fn segment_may_cross(&self, a: Vec3, b: Vec3) -> bool {
        let s = Aabb::around([a, b]);
        self.movers.iter().any(|m| m.intersects(&s))
    }

    /// Whether a shadow ray from `x` to any of `lights` (or to the emitters within
    /// `emitters`) may cross a mover.
    pub fn shadow_may_cross(&self, x: Vec3, lights: &[LightState], emitters: &Aabb) -> bool {
        if self.movers.is_empty() {
            return false;
        }
        if emitters.lo.cmple(emitters.hi).all() {
            let mut s = *emitters;
            s.grow(x);
            if self.movers.iter().any(|m| m.intersects(&s)) {
                return true;
            }
        }
        lights.iter().any(|l| match *l {
            LightState::Point { position, .. }
            | LightState::Spot { position, .. }
            | LightState::Surface { position, .. } => self.segment_may_cross(x, position),
            LightState::Directional { direction, .. } => {
                self.movers.iter().any(|m| m.hit_by_ray(x, -direction))
            }
        })
    }
}

/// Which tiles of the map hold radiosity that changed since the gathers that read them:
/// each texel's radiosity is compared with the value the map's readers last gathered; a
/// tile whose change exceeds the tolerance is marked (with its neighbours, since bilinear
/// lookups reach one texel over) and its reference values move to the new ones, because
/// every basis reading it gathers again now.
#[derive(Clone, Debug)]
pub struct TileChanges {
    width: u32,
    height: u32,
    side: u32,
    reference: Vec<Vec3>,
}

impl TileChanges {
    /// Tiles of `side` texels over a `width` × `height` map whose readers saw `radiosity`.
    pub fn new(width: u32, height: u32, radiosity: Vec<Vec3>) -> TileChanges {
        let side = (width.max(height) / 64).max(8);
        TileChanges {
            width,
            height,
            side,
            reference: radiosity,
        }
    }

    /// Tiles per row.
    fn columns(&self) -> u32 {
        self.width.div_ceil(self.side)
    }

    /// Tiles in the map.
    pub fn tiles(&self) -> usize {
        (self.columns() * self.height.div_ceil(self.side)) as usize
    }

    /// The tile holding the texel nearest light-map coordinate `uv`.
    pub fn tile_of(&self, uv: glam::Vec2) -> u32 {
        let x = ((uv.x * self.width as f32) as i64).clamp(0, self.width as i64 - 1) as u32;
        let y = ((uv.y * self.height as f32) as i64).clamp(0, self.height as i64 - 1) as u32;
        (y / self.side) * self.columns() + x / self.side
    }

    /// The tiles whose texels changed by more than [`RADIOSITY_TOLERANCE`] of `mean` from
    /// the reference (grown by one tile), with their references set to `radiosity`.
    pub fn update(&mut self, radiosity: &[Vec3], mean: f32) -> Vec<bool> {
        let (cols, rows) = (self.columns(), self.height.div_ceil(self.side));
        let limit = RADIOSITY_TOLERANCE * mean.max(f32::MIN_POSITIVE);
        let mut changed = vec![false; self.tiles()];
        for (i, (new, old)) in radiosity.iter().zip(&self.reference).enumerate() {
            if (*new - *old).abs().max_element() > limit {
                let (x, y) = (i as u32 % self.width, i as u32 / self.width);
                changed[((y / self.side) * cols + x / self.side) as usize] = true;
            }
        }
        let mut grown = changed.clone();
        for ty in 0..rows {
            for tx in 0..cols {
                if !changed[(ty * cols + tx) as usize] {
                    continue;
                }
                for ny in ty.saturating_sub(1)..(ty + 2).min(rows) {
                    for nx in tx.saturating_sub(1)..(tx + 2).min(cols) {
                        grown[(ny * cols + nx) as usize] = true;
                    }
                }
            }
        }
        for (i, r) in self.reference.iter_mut().enumerate() {
            let (x, y) = (i as u32 % self.width, i as u32 / self.width);
            if grown[((y / self.side) * cols + x / self.side) as usize] {
                *r = radiosity[i];
            }
        }
        grown
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn boxes_rays_and_segments_meet_where_they_should() {
        let b = Aabb {
            lo: Vec3::splat(1.0),
            hi: Vec3::splat(2.0),
        };
        assert!(b.hit_by_ray(Vec3::ZERO, Vec3::ONE));
        assert!(!b.hit_by_ray(Vec3::ZERO, -Vec3::ONE));
        assert!(
            b.hit_by_ray(Vec3::new(1.5, 1.5, 0.0), Vec3::Z),
            "axis-parallel, inside two slabs"
        );
        assert!(!b.hit_by_ray(Vec3::new(0.5, 1.5, 0.0), Vec3::Z));
        assert_eq!(b.exit(Vec3::splat(1.5), Vec3::X), Vec3::new(2.0, 1.5, 1.5));
        let c = Changes {
            movers: vec![b],
            ..Default::default()
        };
        assert!(c.segment_may_cross(Vec3::ZERO, Vec3::splat(3.0)));
        assert!(!c.segment_may_cross(Vec3::ZERO, Vec3::splat(0.9)));
        let sun = LightState::Directional {
            direction: Vec3::NEG_Y,
            irradiance: Vec3::ONE,
        };
        assert!(c.shadow_may_cross(Vec3::new(1.5, 0.0, 1.5), &[sun], &Aabb::EMPTY));
        assert!(!c.shadow_may_cross(Vec3::new(3.5, 0.0, 1.5), &[sun], &Aabb::EMPTY));
    }

    #[test]
    fn a_tile_is_marked_once_per_change_with_its_neighbours() {
        let mut t = TileChanges::new(32, 32, vec![Vec3::ONE; 32 * 32]);
        assert_eq!(t.tiles(), 16);
        let mut r = vec![Vec3::ONE; 32 * 32];
        r[0] = Vec3::splat(1.1);
        let marked = t.update(&r, 1.0);
        let ids: Vec<usize> = (0..16).filter(|&i| marked[i]).collect();
        assert_eq!(ids, [0, 1, 4, 5], "tile 0 and its neighbours");
        assert!(
            t.update(&r, 1.0).iter().all(|m| !m),
            "the readers saw it now"
        );
        r[0] = Vec3::splat(1.1005);
        assert!(t.update(&r, 1.0).iter().all(|m| !m), "below the tolerance");
    }
}
