//! The wide BVH built top-down with the binned surface area heuristic, eight children at a
//! time (Wald, "On fast construction of SAH-based bounding volume hierarchies", 2007, and
//! Embree's BVH8 builder: Wald et al., "Embree: a kernel framework for efficient CPU ray
//! tracing", 2014, section 4.1). Each node's range of triangles is split in two at the best of
//! 32 bins per axis; the child of largest area is split again until the node has eight
//! children; each child becomes a leaf when the SAH says so. Leaves are costed in blocks of
//! four triangles (a block of one costs as much as a block of four), so the tree fills the
//! blocks the traversal tests. Large ranges bin in parallel and their children are built in
//! parallel, each into its own arrays that the parent appends.
//!
//! It replaced obvhs' PLOC, reinsertion and leaf collapse followed by a collapse to eight
//! children (obvhs 0.4 runs PLOC on one thread; that tree's SAH cost 7.6 expected node visits
//! per line against 5.4 here). Measured on city:250000 in alternating runs: random rays
//! 4.5-5.0 -> 6.1 Mrays/s on one thread, builds 0.12 -> 0.09-0.11 s on one thread and
//! 0.08-0.09 -> 0.055-0.06 s on two.

use glam::{Vec3A, Vec4};
use obvhs::triangle::Triangle;
use rayon::prelude::*;

use super::{BLOCK_SHIFT, EMPTY, FIRST_MASK, LEAF, Node, Tri4, W, block};

/// Bins per axis.
const BINS: usize = 32;
/// Ranges of at most this many triangles always become a leaf (one block).
const MIN_LEAF: usize = 4;
/// Ranges of more triangles are never a leaf (two blocks).
pub(super) const MAX_LEAF: usize = 8;
/// Cost of a node visit against a block's triangle test, per unit of area.
const NODE_COST: f32 = 1.0;
/// Ranges with at least this many triangles build their children in parallel.
const PARALLEL_BUILD: usize = 4096;
/// Ranges with at least this many triangles bin in parallel chunks of this size.
const PARALLEL_BINS: usize = 16 * 1024;

/// A triangle's box; the triangle's index sits in the bits of `lo.w`.
#[derive(Clone, Copy)]
struct Prim {
    lo: Vec4,
    hi: Vec4,
}

impl Prim {
    #[inline(always)]
    fn id(&self) -> u32 {
        self.lo.w.to_bits()
    }
}

/// A box (empty: lo = +inf, hi = -inf).
#[derive(Clone, Copy, Debug)]
struct Bounds {
    lo: Vec3A,
    hi: Vec3A,
}

impl Bounds {
    const EMPTY: Bounds = Bounds {
        lo: Vec3A::INFINITY,
        hi: Vec3A::NEG_INFINITY,
    };

    #[inline(always)]
    fn grow(&mut self, lo: Vec3A, hi: Vec3A) {
        self.lo = self.lo.min(lo);
        self.hi = self.hi.max(hi);
    }

    #[inline(always)]
    fn union(self, o: Bounds) -> Bounds {
        Bounds {
            lo: self.lo.min(o.lo),
            hi: self.hi.max(o.hi),
        }
    }

    #[inline(always)]
    fn half_area(&self) -> f32 {
        let d = (self.hi - self.lo).max(Vec3A::ZERO);
        d.x * d.y + d.y * d.z + d.z * d.x
    }
}

/// A range of primitives with the bounds of their boxes and of their (doubled) centres.
#[derive(Clone, Copy, Debug)]
struct Range {
    start: usize,
    end: usize,
    bounds: Bounds,
    centres: Bounds,
}

impl Range {
    fn len(&self) -> usize {
        self.end - self.start
    }
}

/// Blocks of four needed for `n` triangles.
#[inline(always)]
fn blocks(n: u32) -> f32 {
    n.div_ceil(4) as f32
}

/// Bins of one range: per axis, the box and count of each of `N` bins.
#[derive(Clone, Copy)]
struct Bins<const N: usize> {
    bounds: [[Bounds; N]; 3],
    count: [[u32; N]; 3],
}

impl<const N: usize> Bins<N> {
    fn new() -> Self {
        Bins {
            bounds: [[Bounds::EMPTY; N]; 3],
            count: [[0; N]; 3],
        }
    }

    fn merge(&mut self, o: &Self) {
        for a in 0..3 {
            for b in 0..N {
                self.bounds[a][b] = self.bounds[a][b].union(o.bounds[a][b]);
                self.count[a][b] += o.count[a][b];
            }
        }
    }

    /// Adds `prims`, binned by `binning`.
    fn add(&mut self, binning: &Binning, prims: &[Prim]) {
        for p in prims {
            let (lo, hi) = (Vec3A::from_vec4(p.lo), Vec3A::from_vec4(p.hi));
            let c = lo + hi;
            // Written out: `[0, 1, 2].map(..)` stayed a call per primitive (perf: a fifth of
            // the build in `try_map`).
            let b = [
                binning.bin(c.x, 0),
                binning.bin(c.y, 1),
                binning.bin(c.z, 2),
            ];
            for a in 0..3 {
                self.bounds[a][b[a]].grow(lo, hi);
                self.count[a][b[a]] += 1;
            }
        }
    }

    /// The best split of the binned primitives. With `per_triangle` each side costs its
    /// triangles / 4 rather than its whole blocks (see [`SMALL_RANGE`]).
    fn best(&self, binning: &Binning, per_triangle: bool) -> Option<Split> {
        let blocks = |n: u32| {
            if per_triangle {
                n as f32 / 4.0
            } else {
                blocks(n)
            }
        };
        let mut best: Option<Split> = None;
        for axis in 0..3 {
            if binning.scale[axis] == 0.0 {
                continue;
            }
            // Sweep from the right: the SAH term of bins i.. for every i.
            let mut right = [0f32; N];
            let (mut b, mut n) = (Bounds::EMPTY, 0u32);
            for i in (1..N).rev() {
                b = b.union(self.bounds[axis][i]);
                n += self.count[axis][i];
                right[i] = if n > 0 {
                    b.half_area() * blocks(n)
                } else {
                    -1.0
                };
            }
            let (mut b, mut n) = (Bounds::EMPTY, 0u32);
            for i in 1..N {
                b = b.union(self.bounds[axis][i - 1]);
                n += self.count[axis][i - 1];
                if n == 0 || right[i] < 0.0 {
                    continue;
                }
                let sah = b.half_area() * blocks(n) + right[i];
                if best.is_none_or(|s| sah < s.sah) {
                    best = Some(Split { axis, bin: i, sah });
                }
            }
        }
        best
    }
}

/// Maps doubled centres to bins.
#[derive(Clone, Copy)]
struct Binning {
    lo: Vec3A,
    scale: Vec3A,
    /// The last bin's index.
    last: f32,
}

impl Binning {
    fn new(centres: &Bounds, bins: usize) -> Self {
        let extent = centres.hi - centres.lo;
        // Slightly fewer than `bins` so the largest centre lands in the last bin. An axis
        // without extent (or with a subnormal or infinite one) is not split.
        let s = bins as f32 * (1.0 - 1e-5);
        let scale = Vec3A::from_array([0, 1, 2].map(|a| {
            let k = s / extent[a];
            if extent[a] > 0.0 && k.is_finite() {
                k
            } else {
                0.0
            }
        }));
        Binning {
            lo: centres.lo,
            scale,
            last: (bins - 1) as f32,
        }
    }

    /// The bin of doubled centre coordinate `c` on `axis`: binning and partitioning both
    /// use this, so no primitive changes side between them.
    #[inline(always)]
    fn bin(&self, c: f32, axis: usize) -> usize {
        ((c - self.lo[axis]) * self.scale[axis])
            .max(0.0)
            .min(self.last) as usize
    }
}

/// The best split of a range: axis, first bin on the right, and the SAH of the two sides
/// (area times blocks).
#[derive(Clone, Copy, Debug)]
struct Split {
    axis: usize,
    bin: usize,
    sah: f32,
}

/// Small ranges bin into fewer bins: the sweep over 32 bins costs more than binning a few
/// primitives, and a few primitives need few candidate planes. Their split sweep also costs
/// each side by its triangles, not its whole blocks (the leaf decision still counts blocks):
/// rounding to blocks there drove splits towards full blocks of large overlapping triangles
/// (the Cornell box: 8 full blocks, SAH 3.1 block visits a line, bounce and random rays 15-25%
/// slower than the tree obvhs built). Measured in alternating runs, one thread: Cornell
/// bounce 11.0 -> 11.5 and random 11.1 -> 11.6-12.3 Mrays/s; city:250000 random 6.3-6.9 ->
/// 6.7-7.3 (one ray) and 6.2-6.9 -> 6.8-7.6 (streams); the cost in triangles at every size
/// instead cost the city 5-10%.
const SMALL_RANGE: usize = 128;
const SMALL_BINS: usize = 16;
const TINY_RANGE: usize = 32;
const TINY_BINS: usize = 8;

/// The best split of `prims` into `N` bins.
fn find_split_in<const N: usize>(prims: &[Prim], range: &Range) -> Option<(Split, Binning)> {
    let binning = Binning::new(&range.centres, N);
    let mut bins = Bins::<N>::new();
    bins.add(&binning, prims);
    bins.best(&binning, true).map(|s| (s, binning))
}

/// The best binned split of `prims`, or `None` if every centre is the same.
fn find_split(prims: &[Prim], range: &Range) -> Option<(Split, Binning)> {
    if prims.len() < TINY_RANGE {
        return find_split_in::<TINY_BINS>(prims, range);
    }
    if prims.len() < SMALL_RANGE {
        return find_split_in::<SMALL_BINS>(prims, range);
    }
    let binning = Binning::new(&range.centres, BINS);
    let bins = if prims.len() >= 2 * PARALLEL_BINS {
        prims
            .par_chunks(PARALLEL_BINS)
            .map(|c| {
                let mut bins = Box::new(Bins::<BINS>::new());
                bins.add(&binning, c);
                bins
            })
            .reduce_with(|mut a, b| {
                a.merge(&b);
                a
            })
            .expect("a large range has chunks")
    } else {
        let mut bins = Box::new(Bins::<BINS>::new());
        bins.add(&binning, prims);
        bins
    };
    bins.best(&binning, false).map(|s| (s, binning))
}

/// Bounds of a slice of primitives and of their centres.
fn bounds_of(prims: &[Prim]) -> (Bounds, Bounds) {
    let (mut b, mut c) = (Bounds::EMPTY, Bounds::EMPTY);
    for p in prims {
        grow_by(&mut b, &mut c, p);
    }
    (b, c)
}

/// Grows `bounds` by `p`'s box and `centres` by its (doubled) centre.
#[inline(always)]
fn grow_by(bounds: &mut Bounds, centres: &mut Bounds, p: &Prim) {
    let (lo, hi) = (Vec3A::from_vec4(p.lo), Vec3A::from_vec4(p.hi));
    bounds.grow(lo, hi);
    let m = lo + hi;
    centres.grow(m, m);
}

/// Splits `range` (whose primitives are `prims`) in two: at the best binned split, or in the
/// middle of the range where every centre is the same (or, as a safety net, where the split
/// left a side empty).
fn split(prims: &mut [Prim], range: &Range, found: Option<(Split, Binning)>) -> (Range, Range) {
    let n = prims.len();
    let partitioned = found.and_then(|(s, binning)| {
        {
            let left_of = |p: &Prim| binning.bin(p.lo[s.axis] + p.hi[s.axis], s.axis) < s.bin;
            // Hoare partition, growing each side's bounds as its primitives are seen.
            let (mut lb, mut lc, mut rb, mut rc) =
                (Bounds::EMPTY, Bounds::EMPTY, Bounds::EMPTY, Bounds::EMPTY);
            let (mut i, mut j) = (0, prims.len());
            loop {
                while i < j && left_of(&prims[i]) {
                    grow_by(&mut lb, &mut lc, &prims[i]);
                    i += 1;
                }
                while i < j && !left_of(&prims[j - 1]) {
                    grow_by(&mut rb, &mut rc, &prims[j - 1]);
                    j -= 1;
                }
                if i >= j {
                    break;
                }
                prims.swap(i, j - 1);
                grow_by(&mut lb, &mut lc, &prims[i]);
                grow_by(&mut rb, &mut rc, &prims[j - 1]);
                i += 1;
                j -= 1;
            }
            (i > 0 && i < n).then_some((i, (lb, lc), (rb, rc)))
        }
    });
    let (mid, (lb, lc), (rb, rc)) = partitioned.unwrap_or_else(|| {
        let mid = n / 2;
        let (l, r) = prims.split_at(mid);
        (mid, bounds_of(l), bounds_of(r))
    });
    let at = range.start + mid;
    (
        Range {
            start: range.start,
            end: at,
            bounds: lb,
            centres: lc,
        },
        Range {
            start: at,
            end: range.end,
            bounds: rb,
            centres: rc,
        },
    )
}

/// Nodes of a subtree, with its depth and SAH terms. Leaf children are coded
/// `LEAF | (triangles - 1) << BLOCK_SHIFT | first primitive` until [`build`] lays out the
/// blocks.
#[derive(Default)]
struct Arena {
    nodes: Vec<Node>,
    depth: usize,
    sah: (f64, f64),
}

impl Arena {
    /// Appends `o` (whose root is its node 0), returning the root's new index.
    fn append(&mut self, o: Arena) -> u32 {
        let off = self.nodes.len() as u32;
        self.nodes.extend(o.nodes.into_iter().map(|mut n| {
            for c in &mut n.child {
                if *c & LEAF == 0 {
                    *c += off;
                }
            }
            n
        }));
        self.depth = self.depth.max(o.depth);
        self.sah.0 += o.sah.0;
        self.sah.1 += o.sah.1;
        off
    }
}

struct Builder {
    root_area: f64,
}

impl Builder {
    fn leaf(&self, range: &Range, arena: &mut Arena) -> u32 {
        let n = range.len() as u32;
        debug_assert!((1..=MAX_LEAF as u32).contains(&n));
        arena.sah.1 +=
            f64::from(range.bounds.half_area()) / self.root_area * f64::from(n.div_ceil(4));
        LEAF | (n - 1) << BLOCK_SHIFT | range.start as u32
    }

    /// Whether `range` should be a leaf, and the split to make if not.
    fn decide(&self, prims: &[Prim], range: &Range) -> Result<Option<(Split, Binning)>, ()> {
        let n = range.len();
        if n <= MIN_LEAF {
            return Err(());
        }
        let found = find_split(prims, range);
        let area = range.bounds.half_area();
        let leaf_sah = area * blocks(n as u32);
        let split_sah = NODE_COST * area + found.map_or(f32::INFINITY, |(s, _)| s.sah);
        if n <= MAX_LEAF && leaf_sah <= split_sah {
            return Err(());
        }
        Ok(found)
    }

    /// Builds the inner node for `range` (which `decide` split with `found`) into `arena`
    /// and returns its index there.
    fn node(
        &self,
        prims: &mut [Prim],
        range: Range,
        found: Option<(Split, Binning)>,
        arena: &mut Arena,
        depth: usize,
    ) -> u32 {
        arena.depth = arena.depth.max(depth);
        arena.sah.0 += f64::from(range.bounds.half_area()) / self.root_area;
        let base = range.start;
        let local = |r: &Range| r.start - base..r.end - base;
        // Open the node's range into up to eight children: split in two, then split the
        // child of largest area until there are eight or none can be split.
        let (l, r) = split(prims, &range, found);
        let mut kids = vec![l, r];
        while kids.len() < W {
            let Some(j) = (0..kids.len())
                .filter(|&j| kids[j].len() > MIN_LEAF)
                .max_by(|&a, &b| {
                    kids[a]
                        .bounds
                        .half_area()
                        .total_cmp(&kids[b].bounds.half_area())
                })
            else {
                break;
            };
            let k = kids[j];
            let sub = &mut prims[local(&k)];
            let found = find_split(sub, &k);
            let (l, r) = split(sub, &k, found);
            kids[j] = l;
            kids.push(r);
        }
        kids.sort_by_key(|k| k.start);
        // Each child: a leaf, or an inner node with its split.
        let decide = |k: &Range| self.decide(&prims[local(k)], k);
        let decided: Vec<_> = if range.len() >= PARALLEL_BUILD {
            kids.par_iter().map(decide).collect()
        } else {
            kids.iter().map(decide).collect()
        };
        let index = arena.nodes.len();
        arena.nodes.push(Node::empty());
        let mut codes = [EMPTY; W];
        if range.len() >= PARALLEL_BUILD {
            // Cut the primitives into the children's slices and build the inner children
            // in parallel, each into its own arena.
            let mut slices = Vec::with_capacity(kids.len());
            let mut rest = &mut *prims;
            for k in &kids {
                let (s, r) = rest.split_at_mut(k.len());
                slices.push(s);
                rest = r;
            }
            let subtrees: Vec<Option<Arena>> = slices
                .into_par_iter()
                .zip(&kids)
                .zip(&decided)
                .map(|((s, k), d)| {
                    d.as_ref().ok().map(|found| {
                        let mut a = Arena::default();
                        self.node(s, *k, *found, &mut a, depth + 1);
                        a
                    })
                })
                .collect();
            for (slot, (k, sub)) in kids.iter().zip(subtrees).enumerate() {
                codes[slot] = match sub {
                    Some(a) => arena.append(a),
                    None => self.leaf(k, arena),
                };
            }
        } else {
            for (slot, (k, d)) in kids.iter().zip(&decided).enumerate() {
                let sub = &mut prims[local(k)];
                codes[slot] = match d {
                    Ok(found) => self.node(sub, *k, *found, arena, depth + 1),
                    Err(()) => self.leaf(k, arena),
                };
            }
        }
        let node = &mut arena.nodes[index];
        for (slot, k) in kids.iter().enumerate() {
            node.child[slot] = codes[slot];
            for a in 0..3 {
                node.b[2 * a][slot] = k.bounds.lo[a];
                node.b[2 * a + 1][slot] = k.bounds.hi[a];
            }
        }
        index as u32
    }
}

/// A built tree.
pub(super) struct Built {
    pub nodes: Vec<Node>,
    pub blocks: Vec<Tri4>,
    /// Inner nodes on the longest path from the root.
    pub depth: usize,
    /// The SAH terms of [`WideBvh::sah_visits`](super::WideBvh::sah_visits).
    pub sah: (f64, f64),
    /// Diagonal of the root box.
    pub extent: f32,
}

/// The wide BVH's nodes and blocks over `tris` (triangles with a non-finite vertex are left
/// out: no ray can hit them); `None` when no triangle is finite.
pub(super) fn build(tris: &[Triangle]) -> Option<Built> {
    let mut prims: Vec<Prim> = tris
        .par_iter()
        .enumerate()
        .filter_map(|(i, t)| {
            // (min and max drop a NaN: the vertices are checked themselves.)
            let finite = t.v0.is_finite() && t.v1.is_finite() && t.v2.is_finite();
            let lo = t.v0.min(t.v1).min(t.v2);
            let hi = t.v0.max(t.v1).max(t.v2);
            finite.then(|| Prim {
                lo: lo.extend(f32::from_bits(i as u32)),
                hi: hi.extend(0.0),
            })
        })
        .collect();
    if prims.is_empty() {
        return None;
    }
    let (bounds, centres) = if prims.len() >= 2 * PARALLEL_BINS {
        prims.par_chunks(PARALLEL_BINS).map(bounds_of).reduce(
            || (Bounds::EMPTY, Bounds::EMPTY),
            |a, b| (a.0.union(b.0), a.1.union(b.1)),
        )
    } else {
        bounds_of(&prims)
    };
    let range = Range {
        start: 0,
        end: prims.len(),
        bounds,
        centres,
    };
    let b = Builder {
        root_area: f64::from(bounds.half_area()).max(f64::MIN_POSITIVE),
    };
    let mut arena = Arena {
        nodes: Vec::with_capacity(prims.len() / 10 + 1),
        ..Arena::default()
    };
    match b.decide(&prims, &range) {
        Ok(found) => {
            b.node(&mut prims, range, found, &mut arena, 1);
        }
        Err(()) => {
            // A single leaf: a root with one child.
            let leaf = b.leaf(&range, &mut arena);
            let mut node = Node::empty();
            node.child[0] = leaf;
            for a in 0..3 {
                node.b[2 * a][0] = bounds.lo[a];
                node.b[2 * a + 1][0] = bounds.hi[a];
            }
            arena.nodes.push(node);
            arena.sah.0 = 1.0;
        }
    }
    // Lay the leaves' blocks out in node order and point the leaf children at them.
    let mut leaves = Vec::new();
    let mut next = 0u32;
    for node in &mut arena.nodes {
        for c in &mut node.child {
            if *c != EMPTY && *c & LEAF != 0 {
                let (n, start) = (((*c & !LEAF) >> BLOCK_SHIFT) + 1, *c & FIRST_MASK);
                leaves.push(start as usize..(start + n) as usize);
                let count = n.div_ceil(4);
                assert!(
                    next + count <= FIRST_MASK,
                    "too many leaf blocks for their encoding"
                );
                *c = LEAF | count << BLOCK_SHIFT | next;
                next += count;
            }
        }
    }
    let blocks: Vec<Tri4> = leaves
        .par_iter()
        .flat_map_iter(|r| {
            prims[r.clone()]
                .chunks(4)
                .map(|c| block(tris, c.iter().map(Prim::id)))
        })
        .collect();
    debug_assert_eq!(blocks.len(), next as usize);
    Some(Built {
        nodes: arena.nodes,
        blocks,
        depth: arena.depth,
        sah: arena.sah,
        extent: (bounds.hi - bounds.lo).length(),
    })
}

#[cfg(test)]
mod tests {
    use super::super::WideBvh;
    use super::*;
    use glam::Vec3;

    fn city(n: usize) -> Vec<Triangle> {
        cloudlight_scenes::builtin(&format!("city:{n}"))
            .expect("builtin")
            .triangles_at(0.0)
            .iter()
            .map(|t| Triangle {
                v0: t.v[0].into(),
                v1: t.v[1].into(),
                v2: t.v[2].into(),
            })
            .collect()
    }

    /// Walks the tree: every child box holds what is below it, inner nodes fill their slots
    /// from the first and have two or more children, leaves hold one or two blocks. Returns
    /// the triangle ids in the leaves.
    fn check(w: &WideBvh, tris: &[Triangle]) -> Vec<u32> {
        let mut ids = Vec::new();
        let mut stack = vec![(0u32, None::<([f32; 3], [f32; 3])>)];
        let inside =
            |p: Vec3A, b: &([f32; 3], [f32; 3])| (0..3).all(|a| b.0[a] <= p[a] && p[a] <= b.1[a]);
        while let Some((n, parent)) = stack.pop() {
            let node = &w.nodes[n as usize];
            let used = node.child.iter().take_while(|&&c| c != EMPTY).count();
            assert!(
                node.child[used..].iter().all(|&c| c == EMPTY),
                "slots in order"
            );
            assert!(
                used >= 2 || (n == 0 && used == 1),
                "node {n}: {used} children"
            );
            for slot in 0..used {
                let b = (
                    [node.b[0][slot], node.b[2][slot], node.b[4][slot]],
                    [node.b[1][slot], node.b[3][slot], node.b[5][slot]],
                );
                if let Some(p) = &parent {
                    for a in 0..3 {
                        assert!(
                            p.0[a] <= b.0[a] && b.1[a] <= p.1[a],
                            "child box in parent's"
                        );
                    }
                }
                let c = node.child[slot];
                if c & LEAF == 0 {
                    stack.push((c, Some(b)));
                    continue;
                }
                let count = (c & !LEAF) >> BLOCK_SHIFT;
                assert!((1..=2).contains(&count), "leaf of {count} blocks");
                let first = (c & FIRST_MASK) as usize;
                for block in &w.tris[first..first + count as usize] {
                    for &id in block.id.iter().filter(|&&id| id != u32::MAX) {
                        let t = &tris[id as usize];
                        for v in [t.v0, t.v1, t.v2] {
                            assert!(inside(v, &b), "triangle {id} outside its leaf's box");
                        }
                        ids.push(id);
                    }
                }
            }
        }
        ids
    }

    #[test]
    fn the_tree_is_well_formed_and_the_same_on_any_number_of_threads() {
        let tris = city(20000);
        assert!(
            tris.len() > 4 * PARALLEL_BUILD,
            "large enough to build in parallel"
        );
        let build_on = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("pool")
                .install(|| WideBvh::build(&tris))
        };
        let (one, two) = (build_on(1), build_on(2));
        let mut ids = check(&one, &tris);
        ids.sort_unstable();
        assert_eq!(ids, (0..tris.len() as u32).collect::<Vec<_>>());
        // The layout depends on the ranges' sizes only, never on the threads' timing.
        assert_eq!(one.nodes.len(), two.nodes.len());
        assert_eq!(one.tris.len(), two.tris.len());
        for (a, b) in one.nodes.iter().zip(&two.nodes) {
            assert_eq!(a.child, b.child);
            assert_eq!(
                a.b.map(|r| r.map(f32::to_bits)),
                b.b.map(|r| r.map(f32::to_bits))
            );
        }
        for (a, b) in one.tris.iter().zip(&two.tris) {
            assert_eq!(a.id, b.id);
        }
        // Leaves are costed in blocks: most blocks are full.
        let filled = tris.len() as f64 / (4 * one.tris.len()) as f64;
        assert!(filled > 0.7, "blocks {filled:.2} full");
    }

    #[test]
    fn coincident_and_nearly_coincident_triangles_split_and_non_finite_ones_are_left_out() {
        // 100 copies of one triangle: no binned split separates them.
        let t = Triangle {
            v0: Vec3A::new(0.0, 0.0, 1.0),
            v1: Vec3A::new(1.0, 0.0, 1.0),
            v2: Vec3A::new(0.0, 1.0, 1.0),
        };
        let mut tris = vec![t; 100];
        tris.push(Triangle {
            v0: Vec3A::new(f32::NAN, 0.0, 0.0),
            ..t
        });
        let w = WideBvh::build(&tris);
        let mut ids = check(&w, &tris);
        ids.sort_unstable();
        assert_eq!(
            ids,
            (0..100).collect::<Vec<_>>(),
            "the NaN triangle is left out"
        );
        let ray = |o: Vec3, d: Vec3| super::super::WideRay {
            o: o.to_array(),
            d: d.to_array(),
            t: (0.0, f32::INFINITY),
        };
        let h = w
            .intersect(&ray(Vec3::new(0.2, 0.2, 0.0), Vec3::Z), false)
            .expect("hits a copy");
        assert!((h.t - 1.0).abs() < 1e-6 && h.triangle < 100);
        assert!(
            w.intersect(&ray(Vec3::new(0.8, 0.8, 0.0), Vec3::Z), false)
                .is_none()
        );
        // Centres a few subnormals apart: the binning's scale overflows, and binning and
        // partitioning must still agree on every triangle's side.
        let shifted: Vec<Triangle> = (0..40)
            .map(|i| {
                let x = |k: u32| f32::from_bits(i / 4 + k);
                Triangle {
                    v0: Vec3A::new(x(0), 0.0, 1.0),
                    v1: Vec3A::new(x(2), 0.0, 1.0),
                    v2: Vec3A::new(x(0), 1.0, 1.0),
                }
            })
            .collect();
        let mut ids = check(&WideBvh::build(&shifted), &shifted);
        ids.sort_unstable();
        assert_eq!(ids, (0..40).collect::<Vec<_>>());
        // Only non-finite triangles: an empty tree.
        let empty = WideBvh::build(&tris[100..]);
        assert_eq!(empty.size(), (0, 0));
        assert!(empty.intersect(&ray(Vec3::ZERO, Vec3::Z), false).is_none());
    }
}
