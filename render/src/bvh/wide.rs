//! An 8-wide BVH, built here top-down with the binned SAH ([`build`]): nodes of eight children
//! whose boxes sit in structure-of-arrays form (one step tests eight boxes), with the
//! triangles of each leaf in blocks of four, laid out for the test (a vertex and two edges).
//! This is Embree's layout for one-ray traversal (BVH8 over "triangle4v" blocks, Wald et al.,
//! "Embree: a kernel framework for efficient CPU ray tracing", 2014).
//!
//! The loops over the eight lanes are written in scalar Rust for LLVM to vectorize; they are
//! compiled a second time for AVX2 and FMA and that copy is chosen at run time where the CPU
//! has them (pulp's dispatch), so the binary still runs on any x86-64.
//!
//! Three ways through it: one ray at a time ([`WideBvh::intersect`]); streams of up to
//! [`STREAM`] rays that share their paths, traversed together behind a frustum
//! ([`WideBvh::intersect_stream`]); and rays that share nothing, [`TURNS`] at a time taking
//! turns node by node so that one ray's wait on memory overlaps the others' work
//! ([`WideBvh::intersect_many`]; software pipelining of independent pointer chases, as in
//! Kocberber et al., "Asynchronous memory access chaining", VLDB 2015).

// Lane loops index several arrays by the same lane, the form LLVM vectorizes.
#![allow(clippy::needless_range_loop)]

mod build;

use obvhs::triangle::Triangle;

/// Children per node.
const W: usize = 8;
/// Set on a child that is a leaf: bits 28-30 hold its block count, 0-27 its first block.
const LEAF: u32 = 1 << 31;
const BLOCK_SHIFT: u32 = 28;
const FIRST_MASK: u32 = (1 << BLOCK_SHIFT) - 1;
/// An empty child slot.
const EMPTY: u32 = u32::MAX;
/// Box far distances are scaled up by this (1 + 2γ₃, Ize's "Robust BVH ray traversal") so
/// rounding never drops a box the ray touches.
const FAR_SCALE: f32 = 1.0 + 2.0 * 3.0 * f32::EPSILON * 0.5 / (1.0 - 3.0 * f32::EPSILON * 0.5);

#[repr(C, align(64))]
#[derive(Clone, Copy)]
struct Node {
    /// Child boxes: min x, max x, min y, max y, min z, max z (empty slots: +inf, -inf).
    b: [[f32; W]; 6],
    /// Inner child: node index; leaf child: `LEAF | blocks << 28 | first block`; `EMPTY`.
    child: [u32; W],
}

impl Node {
    fn empty() -> Self {
        let (lo, hi) = ([f32::INFINITY; W], [f32::NEG_INFINITY; W]);
        Node {
            b: [lo, hi, lo, hi, lo, hi],
            child: [EMPTY; W],
        }
    }
}

/// Four triangles: a vertex and the two edges of each, as used by obvhs' intersection test
/// (madmann91's form of Möller–Trumbore); unused lanes are NaN. The test computes the normal
/// (e1 × e2) itself: 160 bytes a block instead of 208 with it stored, and incoherent rays,
/// bound by cache misses, are faster for it (city:250000's random rays +2-4%, 5 alternations).
#[repr(C, align(16))]
#[derive(Clone, Copy)]
struct Tri4 {
    v0: [[f32; 4]; 3],
    e1: [[f32; 4]; 3],
    e2: [[f32; 4]; 3],
    id: [u32; 4],
}

/// Work one traversal did: boxes tested (node visits) and triangles tested.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Visits {
    /// Inner nodes visited (each tests eight boxes).
    pub nodes: u64,
    /// Leaf blocks visited (each tests four triangles).
    pub blocks: u64,
}

/// The wide BVH.
pub struct WideBvh {
    nodes: Vec<Node>,
    tris: Vec<Tri4>,
    /// Stack entries the deepest path can need.
    stack_need: usize,
    arch: pulp::Arch,
    /// Diagonal of the root box.
    extent: f32,
    /// Σ area(inner node) / area(root) and Σ area(leaf) · blocks / area(root): the expected
    /// node and block visits of a random line through the root box without early exit (the
    /// SAH's cost terms).
    sah: (f64, f64),
}

/// The block of up to four triangles `ids` (unused lanes NaN).
fn block(tris: &[Triangle], ids: impl Iterator<Item = u32>) -> Tri4 {
    let nan = [f32::NAN; 4];
    let mut b = Tri4 {
        v0: [nan; 3],
        e1: [nan; 3],
        e2: [nan; 3],
        id: [u32::MAX; 4],
    };
    for (l, id) in ids.enumerate() {
        let t = &tris[id as usize];
        let e1 = t.v0 - t.v1;
        let e2 = t.v2 - t.v0;
        for a in 0..3 {
            b.v0[a][l] = t.v0[a];
            b.e1[a][l] = e1[a];
            b.e2[a][l] = e2[a];
        }
        b.id[l] = id;
    }
    b
}

/// One traversal as pulp's operation: `with_simd` is compiled once per instruction set and
/// everything it calls is inlined into it (a closure is not: measured, it stayed SSE-only).
struct Trace<'a, const ANY: bool> {
    bvh: &'a WideBvh,
    ray: &'a WideRay,
}

impl<const ANY: bool> pulp::WithSimd for Trace<'_, ANY> {
    type Output = Option<WideHit>;

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) -> Self::Output {
        self.bvh
            .traverse::<ANY, false, S>(simd, self.ray, &mut Visits::default())
    }
}

/// The rays of a stream that all point into one octant, in structure-of-arrays form, with
/// the bounds of their origins and reciprocal directions: a frustum that one 8-wide test
/// checks against a node's children for every ray at once (Embree's coherent streams;
/// Reshetov et al., "Multi-level ray tracing algorithm", 2005). Only children the frustum
/// touches are tested ray by ray, eight rays per step.
struct Frustum {
    inv: [[f32; STREAM]; 3],
    oi: [[f32; STREAM]; 3],
    t_min: [f32; STREAM],
    /// Origins and directions, for the triangle tests.
    org: [[f32; STREAM]; 3],
    dir: [[f32; STREAM]; 3],
    near: [usize; 3],
    o: ([f32; 3], [f32; 3]),
    i: ([f32; 3], [f32; 3]),
    t_min_all: f32,
}

impl Frustum {
    /// The rays (all pointing into one octant) in structure-of-arrays form; unused lanes
    /// repeat the first ray.
    #[inline(always)]
    fn new(rays: &[WideRay]) -> Self {
        let mut f = Frustum {
            inv: [[1.0; STREAM]; 3],
            oi: [[0.0; STREAM]; 3],
            t_min: [0.0; STREAM],
            org: [[0.0; STREAM]; 3],
            dir: [[0.0; STREAM]; 3],
            near: [0, 2, 4],
            o: ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]),
            i: ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]),
            t_min_all: f32::INFINITY,
        };
        for r in 0..STREAM {
            let ray = rays.get(r).unwrap_or(&rays[0]);
            for a in 0..3 {
                f.org[a][r] = ray.o[a];
                f.dir[a][r] = ray.d[a];
            }
            f.t_min[r] = ray.t.0;
        }
        // Lane loops (vectorized): reciprocals and their bounds, origin bounds.
        for a in 0..3 {
            for r in 0..STREAM {
                let inv = rcp_safe(f.dir[a][r]);
                f.inv[a][r] = inv;
                f.oi[a][r] = f.org[a][r] * inv;
            }
            f.near[a] = if f.inv[a][0] >= 0.0 { 2 * a } else { 2 * a + 1 };
            for r in 0..STREAM {
                f.i.0[a] = min(f.i.0[a], f.inv[a][r]);
                f.i.1[a] = max(f.i.1[a], f.inv[a][r]);
                f.o.0[a] = min(f.o.0[a], f.org[a][r]);
                f.o.1[a] = max(f.o.1[a], f.org[a][r]);
            }
        }
        for r in 0..STREAM {
            f.t_min_all = min(f.t_min_all, f.t_min[r]);
        }
        f
    }

    /// Fills `rays_of` (a bit per ray of `active` that enters the child) and `nearest` (the
    /// nearest entry of those rays) for `node`'s children.
    #[inline(always)]
    fn children<S: pulp::Simd>(
        &self,
        simd: S,
        node: &Node,
        active: u64,
        t_max: &[f32; STREAM],
        rays_of: &mut [u64; W],
        nearest: &mut [f32; W],
    ) {
        let near = self.near;
        let far = near.map(|n| n ^ 1);
        let mut t_max_all = f32::NEG_INFINITY;
        for t in t_max {
            t_max_all = max(t_max_all, *t);
        }
        // The frustum against the eight boxes: interval bounds of every ray's entry and exit;
        // the lower bound of the entries orders and culls the children.
        let mut far_all = [0f32; W];
        for i in 0..W {
            let mut n = self.t_min_all;
            let mut f = t_max_all;
            for a in 0..3 {
                let (il, ih) = (self.i.0[a], self.i.1[a]);
                let d0 = node.b[near[a]][i] - self.o.1[a];
                let d1 = node.b[near[a]][i] - self.o.0[a];
                n = max(n, min(min(d0 * il, d0 * ih), min(d1 * il, d1 * ih)));
                let e0 = node.b[far[a]][i] - self.o.1[a];
                let e1 = node.b[far[a]][i] - self.o.0[a];
                f = min(f, max(max(e0 * il, e0 * ih), max(e1 * il, e1 * ih)));
            }
            // An empty slot's entry is NaN: never touched.
            nearest[i] = if node.child[i] == EMPTY { f32::NAN } else { n };
            far_all[i] = f * FAR_SCALE;
        }
        let mut touched = le_bits(simd, nearest, &far_all);
        // The rays against the touched boxes, eight at a time (the same arithmetic as one
        // ray's test in `Prepared::boxes`, so the same decisions; written out per lane here
        // because a shared helper taking gathered lanes stopped LLVM vectorizing this loop:
        // measured, streams 15-20% slower).
        while touched != 0 {
            let c = touched.trailing_zeros() as usize;
            touched &= touched - 1;
            let bn = [0, 1, 2].map(|a| node.b[near[a]][c]);
            let bf = [0, 1, 2].map(|a| node.b[far[a]][c]);
            for k in 0..STREAM / 8 {
                let lanes = (active >> (8 * k)) as u8;
                if lanes == 0 {
                    continue;
                }
                let lane = |a: &[f32; STREAM]| -> [f32; 8] {
                    a[8 * k..8 * k + 8].try_into().expect("eight lanes")
                };
                let inv = [lane(&self.inv[0]), lane(&self.inv[1]), lane(&self.inv[2])];
                let oi = [lane(&self.oi[0]), lane(&self.oi[1]), lane(&self.oi[2])];
                let (t0, t1) = (lane(&self.t_min), lane(t_max));
                let mut n = [0f32; 8];
                let mut f = [0f32; 8];
                for l in 0..8 {
                    let x0 = bn[0] * inv[0][l] - oi[0][l];
                    let y0 = bn[1] * inv[1][l] - oi[1][l];
                    let z0 = bn[2] * inv[2][l] - oi[2][l];
                    let x1 = bf[0] * inv[0][l] - oi[0][l];
                    let y1 = bf[1] * inv[1][l] - oi[1][l];
                    let z1 = bf[2] * inv[2][l] - oi[2][l];
                    n[l] = max(max(x0, y0), max(z0, t0[l]));
                    f[l] = min(min(x1, y1), min(z1, t1[l])) * FAR_SCALE;
                }
                let hits = le_bits(simd, &n, &f) & u32::from(lanes);
                rays_of[c] |= u64::from(hits) << (8 * k);
            }
        }
    }

    /// The active rays against a leaf's triangles, one triangle against eight rays per step
    /// (the test of [`intersect4`], written out per lane for the same reason as the box
    /// test's); hits shorten `t_max` and are kept in `hit`.
    #[inline(always)]
    fn leaf(&self, blocks: &[Tri4], active: u64, t_max: &mut [f32; STREAM], hit: &mut Hits) {
        for b in blocks {
            for j in 0..4 {
                if b.id[j] == u32::MAX {
                    continue;
                }
                let v0 = [b.v0[0][j], b.v0[1][j], b.v0[2][j]];
                let e1 = [b.e1[0][j], b.e1[1][j], b.e1[2][j]];
                let e2 = [b.e2[0][j], b.e2[1][j], b.e2[2][j]];
                let n = cross(e1, e2);
                for k in 0..STREAM / 8 {
                    let lanes = (active >> (8 * k)) as u8;
                    if lanes == 0 {
                        continue;
                    }
                    let span = 8 * k..8 * k + 8;
                    let lane = |a: &[f32; STREAM]| -> [f32; 8] {
                        a[span.clone()].try_into().expect("eight lanes")
                    };
                    let o = [lane(&self.org[0]), lane(&self.org[1]), lane(&self.org[2])];
                    let d = [lane(&self.dir[0]), lane(&self.dir[1]), lane(&self.dir[2])];
                    let t0 = lane(&self.t_min);
                    let mut tm = lane(t_max);
                    let mut u8s = lane(&hit.u);
                    let mut v8s = lane(&hit.v);
                    let mut ids: [u32; 8] = hit.id[span.clone()].try_into().expect("eight");
                    for l in 0..8 {
                        let c = [v0[0] - o[0][l], v0[1] - o[1][l], v0[2] - o[2][l]];
                        let r = [
                            d[1][l] * c[2] - d[2][l] * c[1],
                            d[2][l] * c[0] - d[0][l] * c[2],
                            d[0][l] * c[1] - d[1][l] * c[0],
                        ];
                        let det = n[0] * d[0][l] + n[1] * d[1][l] + n[2] * d[2][l];
                        let inv = 1.0 / det;
                        let u = (r[0] * e2[0] + r[1] * e2[1] + r[2] * e2[2]) * inv;
                        let v = (r[0] * e1[0] + r[1] * e1[1] + r[2] * e1[2]) * inv;
                        let w = 1.0 - u - v;
                        let t = (n[0] * c[0] + n[1] * c[1] + n[2] * c[2]) * inv;
                        let ok = (u >= 0.0)
                            & (v >= 0.0)
                            & (w >= 0.0)
                            & (t >= t0[l])
                            & (t < tm[l])
                            & ((lanes >> l) & 1 == 1);
                        tm[l] = if ok { t } else { tm[l] };
                        u8s[l] = if ok { u } else { u8s[l] };
                        v8s[l] = if ok { v } else { v8s[l] };
                        ids[l] = if ok { b.id[j] } else { ids[l] };
                    }
                    t_max[span.clone()].copy_from_slice(&tm);
                    hit.u[span.clone()].copy_from_slice(&u8s);
                    hit.v[span.clone()].copy_from_slice(&v8s);
                    hit.id[span].copy_from_slice(&ids);
                }
            }
        }
    }
}

/// The hits of a stream's rays so far (`id` `u32::MAX`: none).
struct Hits {
    id: [u32; STREAM],
    u: [f32; STREAM],
    v: [f32; STREAM],
}

/// Rays traversed together by [`WideBvh::intersect_stream`] (one bit each in a `u64`).
pub const STREAM: usize = 64;

/// Largest spread of a stream's origins, as a fraction of the scene's diagonal, for which it
/// is traversed as a stream.
pub const STREAM_SPREAD: f32 = 0.05;

struct Stream<'a> {
    bvh: &'a WideBvh,
    rays: &'a [WideRay],
    out: &'a mut [Option<WideHit>],
}

impl pulp::WithSimd for Stream<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) -> Self::Output {
        self.bvh.streams(simd, self.rays, self.out)
    }
}

/// [`WideBvh::interleaved`] as pulp's operation.
struct Interleave<'a, const ANY: bool> {
    bvh: &'a WideBvh,
    rays: &'a [WideRay],
    out: &'a mut [Option<WideHit>],
}

impl<const ANY: bool> pulp::WithSimd for Interleave<'_, ANY> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) -> Self::Output {
        self.bvh.interleaved::<ANY, S>(simd, self.rays, self.out)
    }
}

/// A bit per lane, set where `a <= b` (false where either is NaN). With AVX this is one
/// compare and one `vmovmskps`: LLVM makes the portable loop a reduction of shuffles and
/// ors, eight instructions on the path of every node visit (perf annotate, one ray at a
/// time on city:250000's random rays: a tenth of the kernel's samples).
#[inline(always)]
fn le_bits<S: pulp::Simd>(simd: S, a: &[f32; 8], b: &[f32; 8]) -> u32 {
    #[cfg(target_arch = "x86_64")]
    if let Some(v3) = (&simd as &dyn std::any::Any).downcast_ref::<pulp::x86::V3>() {
        use std::arch::x86_64::{__m256, _CMP_LE_OQ};
        let (a, b): (__m256, __m256) = (pulp::cast(*a), pulp::cast(*b));
        let le = v3.avx._mm256_cmp_ps::<_CMP_LE_OQ>(a, b);
        return v3.avx._mm256_movemask_ps(le) as u32;
    }
    let _ = simd;
    let mut m = 0u32;
    for i in 0..8 {
        m |= u32::from(a[i] <= b[i]) << i;
    }
    m
}

/// `1 / x`, with components too small to invert replaced by ±1e-18 (Embree's `rcp_safe`):
/// box distances then stay finite and never NaN.
#[inline(always)]
fn rcp_safe(x: f32) -> f32 {
    let x = if x.abs() < 1e-18 {
        1e-18f32.copysign(x)
    } else {
        x
    };
    1.0 / x
}

#[inline(always)]
fn max(a: f32, b: f32) -> f32 {
    if a > b { a } else { b }
}

#[inline(always)]
fn min(a: f32, b: f32) -> f32 {
    if a < b { a } else { b }
}

/// A hit in the BVH's frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WideHit {
    /// Distance, in units of the ray's direction.
    pub t: f32,
    /// Triangle index.
    pub triangle: u32,
    /// Weights of the triangle's vertices 1 and 2 at the hit.
    pub uv: [f32; 2],
}

/// A ray in the BVH's frame.
#[derive(Clone, Copy, Debug)]
pub struct WideRay {
    /// Origin.
    pub o: [f32; 3],
    /// Direction (need not be unit; distances are in its units).
    pub d: [f32; 3],
    /// Nearest and farthest distance accepted.
    pub t: (f32, f32),
}

impl WideBvh {
    /// Builds over `tris` top-down with the binned SAH, eight children per node
    /// (`build`).
    pub fn build(tris: &[Triangle]) -> Self {
        let build::Built {
            nodes,
            blocks,
            depth,
            sah,
            extent,
        } = build::build(tris).unwrap_or(build::Built {
            nodes: Vec::new(),
            blocks: Vec::new(),
            depth: 0,
            sah: (0.0, 0.0),
            extent: 0.0,
        });
        WideBvh {
            stack_need: (W - 1) * (depth + 1) + 1,
            nodes,
            tris: blocks,
            arch: pulp::Arch::new(),
            extent,
            sah,
        }
    }

    /// Expected inner-node and leaf-block visits of a line through the root box (SAH terms).
    pub fn sah_visits(&self) -> (f64, f64) {
        self.sah
    }

    /// The triangle indices of every leaf, in leaf order (a test's view of the packing).
    #[cfg(test)]
    pub(crate) fn triangle_ids(&self) -> Vec<u32> {
        self.tris
            .iter()
            .flat_map(|b| b.id)
            .filter(|&id| id != u32::MAX)
            .collect()
    }

    /// Whether [`Self::intersect_many`] takes rays in turns: not where the tree stays in a
    /// core's cache ([`CACHED_TREE_BYTES`]).
    pub(crate) fn takes_turns(&self) -> bool {
        self.nodes.len() * size_of::<Node>() + self.tris.len() * size_of::<Tri4>()
            > CACHED_TREE_BYTES
    }

    /// Inner nodes and leaf blocks.
    pub fn size(&self) -> (usize, usize) {
        (self.nodes.len(), self.tris.len())
    }

    /// The closest hit: (t, triangle index), or with `any` the first hit found.
    pub fn intersect(&self, ray: &WideRay, any: bool) -> Option<WideHit> {
        if any {
            self.arch.dispatch(Trace::<true> { bvh: self, ray })
        } else {
            self.arch.dispatch(Trace::<false> { bvh: self, ray })
        }
    }

    /// The closest hits of `rays` (`out[i]` for `rays[i]`), `STREAM` at a time. A group
    /// whose origins lie within `STREAM_SPREAD` of the scene is traversed together: each
    /// node is tested for every ray still active in it, and a node's boxes are loaded once
    /// for all of them (camera rays, a photon batch's first segments, gather bundles).
    /// Groups spread wider share no path and go `TURNS` rays at a time taking turns
    /// ([`Self::intersect_many`]). Measured on city:250000, one thread: bounce rays from
    /// neighbouring pixels 1.4x as fast in streams as one at a time; random rays 0.8-0.9x in
    /// streams, 1.2x taking turns.
    pub fn intersect_stream(&self, rays: &[WideRay], out: &mut [Option<WideHit>]) {
        assert_eq!(rays.len(), out.len(), "one output per ray");
        self.arch.dispatch(Stream {
            bvh: self,
            rays,
            out,
        });
    }

    #[inline(always)]
    fn streams<S: pulp::Simd>(&self, simd: S, rays: &[WideRay], out: &mut [Option<WideHit>]) {
        // Consecutive spread groups go through `interleaved` as one run: turns need rays
        // to take them.
        let (mut run, mut at) = (0, 0);
        while at < rays.len() {
            let end = (at + STREAM).min(rays.len());
            let (spread, uniform) = self.group(&rays[at..end]);
            if spread {
                at = end;
                continue;
            }
            self.interleaved::<false, S>(simd, &rays[run..at], &mut out[run..at]);
            self.stream(simd, &rays[at..end], &mut out[at..end], uniform);
            (run, at) = (end, end);
        }
        self.interleaved::<false, S>(simd, &rays[run..], &mut out[run..]);
    }

    /// The hits of `rays` (`out[i]` for `rays[i]`: the closest, or with `any` the first
    /// found), `TURNS` rays at a time taking turns node by node: for rays that share no
    /// path (random rays, photon paths, shadow rays from scattered points).
    pub fn intersect_many(&self, rays: &[WideRay], any: bool, out: &mut [Option<WideHit>]) {
        assert_eq!(rays.len(), out.len(), "one output per ray");
        if any {
            self.arch.dispatch(Interleave::<true> {
                bvh: self,
                rays,
                out,
            });
        } else {
            self.arch.dispatch(Interleave::<false> {
                bvh: self,
                rays,
                out,
            });
        }
    }

    /// Whether the origins of `rays` spread over more than `STREAM_SPREAD` of the scene,
    /// and whether every direction lies in the first one's octant.
    #[inline(always)]
    fn group(&self, rays: &[WideRay]) -> (bool, bool) {
        let signs = |r: &WideRay| r.d.map(|c| rcp_safe(c) < 0.0);
        let first = signs(&rays[0]);
        let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
        let mut uniform = true;
        for r in rays {
            for a in 0..3 {
                lo[a] = min(lo[a], r.o[a]);
                hi[a] = max(hi[a], r.o[a]);
            }
            uniform &= signs(r) == first;
        }
        let spread = [0, 1, 2].map(|a| (hi[a] - lo[a]) * (hi[a] - lo[a]));
        let spread = spread[0] + spread[1] + spread[2] > (STREAM_SPREAD * self.extent).powi(2);
        (spread, uniform)
    }

    /// Up to `STREAM` rays traversed together (see [`Self::intersect_stream`]); `uniform`:
    /// whether their directions all lie in one octant.
    #[inline(always)]
    fn stream<S: pulp::Simd>(
        &self,
        simd: S,
        rays: &[WideRay],
        out: &mut [Option<WideHit>],
        uniform: bool,
    ) {
        debug_assert!(rays.len() <= STREAM && out.len() == rays.len());
        out.fill(None);
        if self.nodes.is_empty() || rays.is_empty() {
            return;
        }
        // One-ray box tests where the rays point into different octants.
        let mut p = [Prepared {
            inv: [1.0; 3],
            oi: [0.0; 3],
            near: [0, 2, 4],
            t_min: 0.0,
        }; STREAM];
        if !uniform {
            for (q, r) in p.iter_mut().zip(rays) {
                *q = Prepared::new(r);
            }
        }
        let frustum = uniform.then(|| Frustum::new(rays));
        // Unused lanes never hit anything.
        let mut t_max = [f32::NEG_INFINITY; STREAM];
        for (t, r) in t_max.iter_mut().zip(rays) {
            *t = r.t.1;
        }
        let all = u64::MAX >> (STREAM - rays.len());
        let mut hits = Hits {
            id: [u32::MAX; STREAM],
            u: [0.0; STREAM],
            v: [0.0; STREAM],
        };
        // (nearest entry of any ray, child, rays) entries.
        let mut small = [(0f32, 0u32, 0u64); 128];
        let mut big;
        let stack: &mut [(f32, u32, u64)] = if self.stack_need <= small.len() {
            &mut small
        } else {
            big = vec![(0f32, 0u32, 0u64); self.stack_need];
            &mut big
        };
        let mut sp = 0usize;
        let (mut cur, mut active) = (0u32, all);
        loop {
            if cur & LEAF == 0 {
                let node = &self.nodes[cur as usize];
                let mut rays_of = [0u64; W];
                let mut nearest = [f32::INFINITY; W];
                if let Some(f) = &frustum {
                    f.children(simd, node, active, &t_max, &mut rays_of, &mut nearest);
                }
                let mut m = if frustum.is_some() { 0 } else { active };
                while m != 0 {
                    let r = m.trailing_zeros() as usize;
                    m &= m - 1;
                    let (mut hits, tn) = p[r].boxes(simd, node, t_max[r]);
                    for i in 0..W {
                        nearest[i] = min(nearest[i], tn[i]);
                    }
                    while hits != 0 {
                        let c = hits.trailing_zeros() as usize;
                        hits &= hits - 1;
                        rays_of[c] |= 1 << r;
                    }
                }
                let mut kids = 0u32;
                for (c, r) in rays_of.iter().enumerate() {
                    kids |= u32::from(*r != 0) << c;
                }
                if kids.count_ones() == 1 {
                    let c = kids.trailing_zeros() as usize;
                    (cur, active) = (node.child[c], rays_of[c]);
                    continue;
                }
                // Push every child some ray entered, farthest first, and take the nearest.
                let base = sp;
                while kids != 0 {
                    let c = kids.trailing_zeros() as usize;
                    kids &= kids - 1;
                    let e = (nearest[c], node.child[c], rays_of[c]);
                    let mut k = sp;
                    while k > base && stack[k - 1].0 < e.0 {
                        stack[k] = stack[k - 1];
                        k -= 1;
                    }
                    stack[k] = e;
                    sp += 1;
                }
            } else {
                let first = (cur & FIRST_MASK) as usize;
                let count = ((cur & !LEAF) >> BLOCK_SHIFT) as usize;
                if let Some(f) = &frustum {
                    f.leaf(
                        &self.tris[first..first + count],
                        active,
                        &mut t_max,
                        &mut hits,
                    );
                }
                let mut m = if frustum.is_some() { 0 } else { active };
                while m != 0 {
                    let r = m.trailing_zeros() as usize;
                    m &= m - 1;
                    for b in &self.tris[first..first + count] {
                        if let Some(h) = intersect4(b, &rays[r], rays[r].t.0, t_max[r]) {
                            t_max[r] = h.t;
                            out[r] = Some(h);
                        }
                    }
                }
            }
            // Pop the next entry, without the rays that already hit something nearer.
            loop {
                if sp == 0 {
                    if frustum.is_some() {
                        for (r, o) in out.iter_mut().enumerate() {
                            *o = (hits.id[r] != u32::MAX).then_some(WideHit {
                                t: t_max[r],
                                triangle: hits.id[r],
                                uv: [hits.u[r], hits.v[r]],
                            });
                        }
                    }
                    return;
                }
                sp -= 1;
                let (d, c, mut m) = stack[sp];
                let mut keep = 0u64;
                for (k, lanes) in t_max.chunks_exact(8).enumerate() {
                    let far = std::array::from_fn(|l| lanes[l] * FAR_SCALE);
                    keep |= u64::from(le_bits(simd, &[d; 8], &far)) << (8 * k);
                }
                m &= keep;
                if m != 0 {
                    (cur, active) = (c, m);
                    break;
                }
            }
        }
    }

    /// As [`Self::intersect`], counting the work done.
    pub fn intersect_counted(&self, ray: &WideRay, visits: &mut Visits) -> Option<WideHit> {
        self.traverse::<false, true, _>(pulp::Scalar::new(), ray, visits)
    }

    #[inline(always)]
    fn traverse<const ANY: bool, const COUNT: bool, S: pulp::Simd>(
        &self,
        simd: S,
        ray: &WideRay,
        visits: &mut Visits,
    ) -> Option<WideHit> {
        if self.nodes.is_empty() {
            return None;
        }
        // The stack is zeroed for each ray (no `unsafe` here), so it is sized to the tree:
        // measured, zeroing 256 entries cost a quarter of a camera ray.
        match self.stack_need {
            0..=32 => self.traverse_with::<ANY, COUNT, S>(simd, ray, &mut [0u64; 32], visits),
            33..=64 => self.traverse_with::<ANY, COUNT, S>(simd, ray, &mut [0u64; 64], visits),
            65..=128 => self.traverse_with::<ANY, COUNT, S>(simd, ray, &mut [0u64; 128], visits),
            n => self.traverse_with::<ANY, COUNT, S>(simd, ray, &mut vec![0u64; n], visits),
        }
    }

    /// Asks the cache for a child's node (its four lines) or its first leaf block while the
    /// ray goes on: the children pushed on the stack arrive while the nearest is traversed
    /// (measured on city:250000's 1M random rays, one thread: 4.5-5.0 -> 5.1-5.7 Mrays/s).
    #[inline(always)]
    #[allow(unsafe_code)]
    fn prefetch(&self, child: u32) {
        #[cfg(target_arch = "x86_64")]
        {
            use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
            let p = if child & LEAF == 0 {
                self.nodes.as_ptr().wrapping_add(child as usize) as *const i8
            } else {
                let first = (child & FIRST_MASK) as usize;
                self.tris.as_ptr().wrapping_add(first) as *const i8
            };
            for line in 0..4 {
                // SAFETY: a prefetch is a hint: it never faults and reads nothing Rust sees.
                unsafe { _mm_prefetch::<_MM_HINT_T0>(p.wrapping_add(64 * line)) };
            }
        }
    }

    /// Pushes the children of `node` in `mask` (entry distances `tn`) on `stack` above
    /// `sp`, with `PREFETCH` asking the cache for each, orders the pushed run so the nearest
    /// is on top, and pops it: the child to visit next and the new stack height. Rays taking
    /// turns do not prefetch what they push: each asks for its next node after every step,
    /// and asking for every pushed child as well kept the core's line-fill buffers full
    /// (perf: a tenth of the samples on the prefetches; city:250000's random rays, one
    /// thread, alternating binaries: 10.30-10.33 -> 10.60-10.63 Mrays/s).
    #[inline(always)]
    fn push_children<const PREFETCH: bool>(
        &self,
        node: &Node,
        mask: u32,
        tn: &[f32; W],
        stack: &mut [u64],
        mut sp: usize,
    ) -> (u32, usize) {
        let base = sp;
        let mut m = mask;
        while m != 0 {
            let i = m.trailing_zeros() as usize;
            m &= m - 1;
            if PREFETCH {
                self.prefetch(node.child[i]);
            }
            stack[sp] = u64::from(tn[i].to_bits()) << 32 | u64::from(node.child[i]);
            sp += 1;
        }
        // Insertion sort, farthest first (distances are >= 0: their bits order as the
        // values).
        for j in base + 1..sp {
            let e = stack[j];
            let mut k = j;
            while k > base && stack[k - 1] < e {
                stack[k] = stack[k - 1];
                k -= 1;
            }
            stack[k] = e;
        }
        sp -= 1;
        (stack[sp] as u32, sp)
    }

    /// One ray from the root to its hit: [`Self::step`]'s loop written out (measured on
    /// city:250000, one thread: a loop over `step` cost camera and bounce rays 3-7%).
    #[inline(always)]
    fn traverse_with<const ANY: bool, const COUNT: bool, S: pulp::Simd>(
        &self,
        simd: S,
        ray: &WideRay,
        stack: &mut [u64],
        visits: &mut Visits,
    ) -> Option<WideHit> {
        let p = Prepared::new(ray);
        let t_min = ray.t.0;
        let mut t_max = ray.t.1;
        let mut best: Option<WideHit> = None;
        let mut sp = 0usize;
        let mut cur = 0u32;
        loop {
            if cur & LEAF == 0 {
                let node = &self.nodes[cur as usize];
                if COUNT {
                    visits.nodes += 1;
                }
                let (mask, tn) = p.boxes(simd, node, t_max);
                match mask.count_ones() {
                    0 => {}
                    1 => {
                        cur = node.child[mask.trailing_zeros() as usize];
                        continue;
                    }
                    _ => {
                        (cur, sp) = self.push_children::<true>(node, mask, &tn, stack, sp);
                        continue;
                    }
                }
            } else {
                let first = (cur & FIRST_MASK) as usize;
                let count = ((cur & !LEAF) >> BLOCK_SHIFT) as usize;
                for b in &self.tris[first..first + count] {
                    if COUNT {
                        visits.blocks += 1;
                    }
                    if let Some(h) = intersect4(b, ray, t_min, t_max) {
                        if ANY {
                            return Some(h);
                        }
                        t_max = h.t;
                        best = Some(h);
                    }
                }
            }
            // Pop the nearest entry still closer than the closest hit.
            loop {
                if sp == 0 {
                    return best;
                }
                sp -= 1;
                let e = stack[sp];
                if f32::from_bits((e >> 32) as u32) <= t_max * FAR_SCALE {
                    cur = e as u32;
                    break;
                }
            }
        }
    }

    /// Advances `w` by one node or one leaf, then to the next node or leaf to visit (the
    /// nearest child entered, else the nearest entry on `stack` still closer than the
    /// closest hit): false when there is none, the traversal done and its hit in `w.best`.
    #[inline(always)]
    fn step<const ANY: bool, S: pulp::Simd>(
        &self,
        simd: S,
        w: &mut Walk,
        ray: &WideRay,
        stack: &mut [u64],
    ) -> bool {
        if w.cur & LEAF == 0 {
            let node = &self.nodes[w.cur as usize];
            let (mask, tn) = w.p.boxes(simd, node, w.t_max);
            match mask.count_ones() {
                0 => {}
                1 => {
                    w.cur = node.child[mask.trailing_zeros() as usize];
                    return true;
                }
                _ => {
                    (w.cur, w.sp) = self.push_children::<false>(node, mask, &tn, stack, w.sp);
                    return true;
                }
            }
        } else {
            let first = (w.cur & FIRST_MASK) as usize;
            let count = ((w.cur & !LEAF) >> BLOCK_SHIFT) as usize;
            for b in &self.tris[first..first + count] {
                if let Some(h) = intersect4(b, ray, w.p.t_min, w.t_max) {
                    w.best = Some(h);
                    if ANY {
                        return false;
                    }
                    w.t_max = h.t;
                }
            }
        }
        // Pop the nearest entry still closer than the closest hit.
        while w.sp > 0 {
            w.sp -= 1;
            let e = stack[w.sp];
            if f32::from_bits((e >> 32) as u32) <= w.t_max * FAR_SCALE {
                w.cur = e as u32;
                return true;
            }
        }
        false
    }

    /// The hits of `rays` (`out[i]` for `rays[i]`; with `ANY`, the first hit found), traversed
    /// `TURNS` at a time taking turns: each ray visits one node or leaf, asks the cache for
    /// the next, and waits for it while the others take their turns. Rays that share no
    /// path (random rays, photon paths after a few bounces) spend most of their time waiting
    /// on a node or block from memory (perf: the first load of each is the kernel's top
    /// line); one ray's loads form a chain, the turns overlap several chains.
    #[inline(always)]
    fn interleaved<const ANY: bool, S: pulp::Simd>(
        &self,
        simd: S,
        rays: &[WideRay],
        out: &mut [Option<WideHit>],
    ) {
        debug_assert_eq!(rays.len(), out.len());
        if self.nodes.is_empty() || rays.is_empty() {
            out.fill(None);
            return;
        }
        if !self.takes_turns() {
            // No wait on memory to overlap: one ray at a time does less.
            for (o, r) in out.iter_mut().zip(rays) {
                *o = self.traverse::<ANY, false, S>(simd, r, &mut Visits::default());
            }
            return;
        }
        let need = self.stack_need;
        let mut small = [0u64; TURNS * 96];
        let mut big;
        let stacks: &mut [u64] = if TURNS * need <= small.len() {
            &mut small
        } else {
            big = vec![0u64; TURNS * need];
            &mut big
        };
        let mut walks = [Walk::new(&rays[0]); TURNS];
        let mut of = [0usize; TURNS];
        let mut live = 0u32;
        let mut next = 0;
        for k in 0..TURNS.min(rays.len()) {
            walks[k] = Walk::new(&rays[k]);
            of[k] = k;
            live |= 1 << k;
            next += 1;
        }
        while live != 0 {
            let mut m = live;
            while m != 0 {
                let k = m.trailing_zeros() as usize;
                m &= m - 1;
                let stack = &mut stacks[k * need..(k + 1) * need];
                if self.step::<ANY, S>(simd, &mut walks[k], &rays[of[k]], stack) {
                    self.prefetch(walks[k].cur);
                    continue;
                }
                out[of[k]] = walks[k].best;
                if next < rays.len() {
                    walks[k] = Walk::new(&rays[next]);
                    of[k] = next;
                    next += 1;
                } else {
                    live &= !(1 << k);
                }
            }
        }
    }
}

/// Rays one thread traverses at once by [`WideBvh::interleaved`] (measured on city:250000's
/// random rays, one thread: 4, 8 and 16 turns 8.7-8.9, 8.9-9.2 and 9.1-9.4 Mrays/s; against
/// Embree's packets in the same runs, 1 / 2 threads: 8 turns 0.82-0.92 / 0.72-0.77, 16 turns
/// 0.88-0.89 / 0.77-0.81).
const TURNS: usize = 16;

/// A tree at most this large (nodes and blocks) stays in a core's L2 cache: its rays go one
/// at a time even where they share no path (measured: turns made the Cornell box's reference
/// render 6% slower, city:250000's 5% faster).
const CACHED_TREE_BYTES: usize = 512 << 10;

/// One ray's traversal in progress.
#[derive(Clone, Copy)]
struct Walk {
    p: Prepared,
    t_max: f32,
    best: Option<WideHit>,
    /// The node or leaf to visit next.
    cur: u32,
    /// Entries on the walk's stack.
    sp: usize,
}

impl Walk {
    #[inline(always)]
    fn new(ray: &WideRay) -> Self {
        Walk {
            p: Prepared::new(ray),
            t_max: ray.t.1,
            best: None,
            cur: 0,
            sp: 0,
        }
    }
}

/// A ray made ready for box tests: reciprocal direction, origin times it, and which bound
/// is near on each axis.
#[derive(Clone, Copy)]
struct Prepared {
    inv: [f32; 3],
    oi: [f32; 3],
    near: [usize; 3],
    t_min: f32,
}

impl Prepared {
    #[inline(always)]
    fn new(ray: &WideRay) -> Self {
        let inv = ray.d.map(rcp_safe);
        Prepared {
            inv,
            oi: [ray.o[0] * inv[0], ray.o[1] * inv[1], ray.o[2] * inv[2]],
            near: [0, 1, 2].map(|a| if inv[a] >= 0.0 { 2 * a } else { 2 * a + 1 }),
            t_min: ray.t.0,
        }
    }

    /// The eight child boxes of `node` against the ray up to `t_max`: a bit per box hit,
    /// and the entry distances (+inf where missed).
    #[inline(always)]
    fn boxes<S: pulp::Simd>(&self, simd: S, node: &Node, t_max: f32) -> (u32, [f32; W]) {
        let (inv, oi, near) = (self.inv, self.oi, self.near);
        let far = near.map(|n| n ^ 1);
        let mut tn = [0f32; W];
        let mut n8 = [0f32; W];
        let mut f8 = [0f32; W];
        for i in 0..W {
            let x0 = node.b[near[0]][i] * inv[0] - oi[0];
            let y0 = node.b[near[1]][i] * inv[1] - oi[1];
            let z0 = node.b[near[2]][i] * inv[2] - oi[2];
            let x1 = node.b[far[0]][i] * inv[0] - oi[0];
            let y1 = node.b[far[1]][i] * inv[1] - oi[1];
            let z1 = node.b[far[2]][i] * inv[2] - oi[2];
            let n = max(max(x0, y0), max(z0, self.t_min));
            let f = min(min(x1, y1), min(z1, t_max)) * FAR_SCALE;
            tn[i] = if n <= f { n } else { f32::INFINITY };
            (n8[i], f8[i]) = (n, f);
        }
        (le_bits(simd, &n8, &f8), tn)
    }
}

/// a × b.
#[inline(always)]
fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// The nearest of four triangles hit within `[t_min, t_max)`, if any, with the weights of
/// its vertices 1 and 2 (obvhs' test: `e1 = v0 - v1`, `e2 = v2 - v0`, `n = e1 × e2`; then
/// `u = ((d × (v0 - o)) · e2) / (n · d)` weighs v1 and `v` likewise with `e1` weighs v2).
#[inline(always)]
fn intersect4(b: &Tri4, ray: &WideRay, t_min: f32, t_max: f32) -> Option<WideHit> {
    let (o, d) = (ray.o, ray.d);
    let mut t = [f32::INFINITY; 4];
    let mut uv = [[0f32; 2]; 4];
    for l in 0..4 {
        let n = cross(
            [b.e1[0][l], b.e1[1][l], b.e1[2][l]],
            [b.e2[0][l], b.e2[1][l], b.e2[2][l]],
        );
        let c = [b.v0[0][l] - o[0], b.v0[1][l] - o[1], b.v0[2][l] - o[2]];
        let r = [
            d[1] * c[2] - d[2] * c[1],
            d[2] * c[0] - d[0] * c[2],
            d[0] * c[1] - d[1] * c[0],
        ];
        let det = n[0] * d[0] + n[1] * d[1] + n[2] * d[2];
        let inv = 1.0 / det;
        let u = (r[0] * b.e2[0][l] + r[1] * b.e2[1][l] + r[2] * b.e2[2][l]) * inv;
        let v = (r[0] * b.e1[0][l] + r[1] * b.e1[1][l] + r[2] * b.e1[2][l]) * inv;
        let w = 1.0 - u - v;
        let tt = (n[0] * c[0] + n[1] * c[1] + n[2] * c[2]) * inv;
        let hit = u >= 0.0 && v >= 0.0 && w >= 0.0 && tt >= t_min && tt < t_max;
        t[l] = if hit { tt } else { f32::INFINITY };
        uv[l] = [u, v];
    }
    let mut best = 0;
    for l in 1..4 {
        if t[l] < t[best] {
            best = l;
        }
    }
    (t[best] < f32::INFINITY).then_some(WideHit {
        t: t[best],
        triangle: b.id[best],
        uv: uv[best],
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Lanes that hold every order of two floats: equal, less, greater, zeros of both
    /// signs, infinities and NaN.
    fn lanes() -> Vec<f32> {
        vec![
            0.0,
            -0.0,
            1.0,
            -1.0,
            1.0 + f32::EPSILON,
            f32::MIN_POSITIVE,
            f32::MAX,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
        ]
    }

    #[test]
    fn lane_bits_are_the_portable_comparison_on_every_instruction_set() {
        let v = lanes();
        let arch = pulp::Arch::new();
        for k in 0..v.len() * v.len() {
            let a: [f32; 8] = std::array::from_fn(|l| v[(k + 3 * l) % v.len()]);
            let b: [f32; 8] = std::array::from_fn(|l| v[(k / v.len() + 7 * l) % v.len()]);
            let mut want = 0u32;
            for l in 0..8 {
                want |= u32::from(a[l] <= b[l]) << l;
            }
            assert_eq!(le_bits(pulp::Scalar::new(), &a, &b), want, "{a:?} {b:?}");
            struct Op<'a>(&'a [f32; 8], &'a [f32; 8]);
            impl pulp::WithSimd for Op<'_> {
                type Output = u32;
                #[inline(always)]
                fn with_simd<S: pulp::Simd>(self, simd: S) -> u32 {
                    le_bits(simd, self.0, self.1)
                }
            }
            assert_eq!(arch.dispatch(Op(&a, &b)), want, "{a:?} {b:?}");
        }
    }

    #[test]
    fn the_portable_traversal_finds_what_the_vectorized_one_finds() {
        // `intersect_counted` runs the portable code (pulp's scalar fallback): a CPU without
        // AVX takes it for every ray.
        let tris: Vec<Triangle> = (0..300)
            .map(|i| {
                let f = i as f32;
                let o = glam::Vec3A::new((f * 0.37).sin() * 5.0, (f * 0.11).cos() * 5.0, f * 0.03);
                Triangle {
                    v0: o,
                    v1: o + glam::Vec3A::new(0.6, 0.1, 0.0),
                    v2: o + glam::Vec3A::new(0.0, 0.5, 0.3),
                }
            })
            .collect();
        let bvh = WideBvh::build(&tris);
        let mut found = 0;
        for i in 0..2000 {
            let f = i as f32;
            let ray = WideRay {
                o: [(f * 0.7).sin() * 6.0, (f * 1.3).cos() * 6.0, -2.0],
                d: [(f * 0.3).sin() * 0.3, (f * 0.5).cos() * 0.3, 1.0],
                t: (0.0, f32::INFINITY),
            };
            let simd = bvh.intersect(&ray, false);
            let portable = bvh.intersect_counted(&ray, &mut Visits::default());
            assert_eq!(simd, portable, "ray {i}");
            found += usize::from(simd.is_some());
        }
        assert!(found > 200, "the rays hit something: {found}");
    }
}
