// Photon splatting (Mara et al. 2013, "2.5D bounds"; CloudLight §4.3) and the joint-bilateral
// upsample. Layouts match raster/splat.rs (`SplatPhoton`, `SplatParams`). The G-buffer holds
// f32 bits (position) and f16 pairs (normal, albedo); the accumulation buffer is float
// (Rgba32Float or Rgba16Float, irradiance × `scale.x` so that f16 stays in range); the
// upsample writes indirect radiance as f32 bits.
//
// Splat: one screen-space quad per photon covering the projection of its sphere, drawn into
// one of up to four accumulation levels (each half the resolution of the one before): the
// coarsest where the projected radius still spans `levels.y` texels (vertices 4l..4l+4 draw
// level l; a photon of another level is culled). Each covered pixel of the level reads the
// full-resolution G-buffer at its centre, keeps the photon only if the surface point lies within the photon's disk (flattened
// along the surface normal) and faces the photon's arrival, and adds
// Φ · κ(s) / N_κ(r) (cone kernel κ = 1 − s/r, N = π r² / 3): irradiance, W/m².

struct SplatParams {
    clip_from_world: mat4x4<f32>,
    view_from_world: mat4x4<f32>,
    // x, y: the projection's scale of view x and y; z: near plane distance (m).
    projection: vec4<f32>,
    // Full-resolution size (x, y), low-resolution size (z, w).
    sizes: vec4<f32>,
    // x: downsample factor, y: flatten (max |Δ·n| / r), z: depth sigma (m), w: normal power.
    settings: vec4<f32>,
    // x: accumulation scale (accumulated = irradiance × x); y: fixed-point units per W/m²
    // of the compute splat's sums.
    scale: vec4<f32>,
    // x: levels, y: least projected radius in texels of a photon's level, z: least cosine
    // between a receiver's normal and a photon's (photons that carry their normal).
    levels: vec4<f32>,
    // x: photons (the compute splat's); y: 1 when edge pixels are splatted at full
    // resolution (`cs_edges`), else 0.
    counts: vec4<u32>,
};

@group(0) @binding(0) var<uniform> params: SplatParams;
@group(0) @binding(1) var gpos: texture_2d<u32>;
@group(0) @binding(2) var gnrm: texture_2d<u32>;
@group(0) @binding(3) var galb: texture_2d<u32>;
// The level a pass reads (its accumulation and guide) and the guide of the level it writes;
// each pass binds its own. A guide holds each texel's surface point (f32 bits) and normal
// (`pack_normal`: 3 × 10-bit snorm, lowest bit set; 0 where the texel sees no geometry),
// read from the G-buffer once a frame.
@group(0) @binding(4) var src_accum: texture_2d<f32>;
@group(0) @binding(5) var src_guide: texture_2d<u32>;
@group(0) @binding(6) var dst_guide: texture_2d<u32>;
// After a compute splat with edges, the upsample's view of level 1 (its buffer, the coarser
// levels folded in, and its guide): what an edge pixel adds to its own level-0 sums.
@group(0) @binding(10) var coarse_accum: texture_2d<f32>;
@group(0) @binding(11) var coarse_guide: texture_2d<u32>;
// Every level's guide, layer l level l (in its top-left corner): the compute splat reads a
// photon's texels there, one load per texel.
@group(0) @binding(12) var guide_levels: texture_2d_array<u32>;

// The compute splat (see `cs_splat`): the photons, and the levels' fixed-point sums (three
// per texel, level after level) written atomically by the splat and read by the resolve.
struct PhotonStored {
    position_radius: vec4<f32>,
    power: vec4<f32>,
    direction: vec4<f32>,
};
@group(0) @binding(7) var<storage, read> fixed_sums: array<u32>;
@group(0) @binding(8) var<storage, read> photons: array<PhotonStored>;
@group(0) @binding(9) var<storage, read_write> fixed_accum: array<atomic<u32>>;

struct PhotonIn {
    @location(0) position_radius: vec4<f32>,
    @location(1) power: vec4<f32>,
    @location(2) direction: vec4<f32>,
};

struct SplatOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) @interpolate(flat) position_radius: vec4<f32>,
    @location(1) @interpolate(flat) power: vec4<f32>,
    @location(2) @interpolate(flat) direction: vec4<f32>,
    // x: the level's downsample factor, y: the level.
    @location(3) @interpolate(flat) level: vec4<f32>,
};

// The slopes x/depth of the two planes through the eye tangent to a sphere at (x, depth)
// of radius r (depth > r), smaller first.
fn tangent_bounds(x: f32, depth: f32, r: f32) -> vec2<f32> {
    let d2 = depth * depth - r * r;
    let root = r * sqrt(max(x * x + d2, 0.0));
    return vec2<f32>(x * depth - root, x * depth + root) / d2;
}

// Where a photon splats: its level and its padded screen bounds (NDC, lo and hi).
struct Footprint {
    lo: vec2<f32>,
    hi: vec2<f32>,
    level: u32,
    // x: the level's downsample factor (full-resolution pixels per texel).
    level_ds: f32,
    visible: bool,
};

fn footprint(position_radius: vec4<f32>) -> Footprint {
    let c = position_radius.xyz;
    let r = position_radius.w;
    // Tight screen bounds of the sphere (tangent planes through the eye, per axis); a
    // sphere that reaches the near plane covers the whole screen.
    let v = (params.view_from_world * vec4<f32>(c, 1.0)).xyz;
    let depth = -v.z;
    var lo = vec2<f32>(-1.0);
    var hi = vec2<f32>(1.0);
    if (depth - r > params.projection.z) {
        let bx = tangent_bounds(v.x, depth, r) * params.projection.x;
        let by = tangent_bounds(v.y, depth, r) * params.projection.y;
        lo = vec2<f32>(bx.x, by.x);
        hi = vec2<f32>(bx.y, by.y);
    }
    // The level: the coarsest whose texels the projected radius spans `levels.y` times
    // (the smaller half-extent, in full-resolution pixels, over the level's factor).
    let extent_px = (hi - lo) * 0.25 * params.sizes.xy;
    let radius_px = min(extent_px.x, extent_px.y);
    let ds = params.settings.x;
    let fits = max(radius_px / (ds * params.levels.y), 1.0);
    var f: Footprint;
    f.level = u32(clamp(floor(log2(fits)), 0.0, params.levels.x - 1.0));
    f.level_ds = ds * f32(1u << f.level);
    // Grow by half a pixel of the level: a pixel is shaded at its centre's surface, and a
    // centre just outside the sphere's bounds can still lie on its (flattened) disk.
    let level_size = ceil(params.sizes.xy / f.level_ds);
    let pad = 1.0 / level_size;
    f.lo = clamp(lo - pad, vec2<f32>(-1.0), vec2<f32>(1.0));
    f.hi = clamp(hi + pad, vec2<f32>(-1.0), vec2<f32>(1.0));
    f.visible = f.hi.x > f.lo.x && f.hi.y > f.lo.y && r > 0.0;
    return f;
}

@vertex
fn vs_splat(@builtin(vertex_index) vi: u32, p: PhotonIn) -> SplatOut {
    var out: SplatOut;
    out.position_radius = p.position_radius;
    out.power = p.power;
    out.direction = p.direction;
    let f = footprint(p.position_radius);
    out.level = vec4<f32>(f.level_ds, f32(f.level), 0.0, 0.0);
    // A strip of two triangles: (0,0) (1,0) (0,1) (1,1).
    let t = vec2<f32>(f32(vi & 1u), f32((vi >> 1u) & 1u));
    out.clip = vec4<f32>(mix(f.lo, f.hi, t), 0.5, 1.0);
    if (!f.visible || f.level != vi / 4u) {
        out.clip = vec4<f32>(2.0, 2.0, 2.0, 1.0);
    }
    return out;
}

fn position_at(px: vec2<i32>) -> vec4<f32> {
    return bitcast<vec4<f32>>(textureLoad(gpos, px, 0));
}

fn normal_at(px: vec2<i32>) -> vec3<f32> {
    let v = textureLoad(gnrm, px, 0).xy;
    // Unit when written (gbuffer.wgsl); f16 keeps it within 1e-3 of unit length.
    return vec3<f32>(unpack2x16float(v.x), unpack2x16float(v.y).x);
}

fn albedo_at(px: vec2<i32>) -> vec3<f32> {
    let v = textureLoad(galb, px, 0).xy;
    return vec3<f32>(unpack2x16float(v.x), unpack2x16float(v.y).x);
}

// The full-resolution texel that stands for pixel `lp` of a level `ds` times smaller.
fn full_texel(lp: vec2<i32>, ds: i32) -> vec2<i32> {
    let full = vec2<i32>(params.sizes.xy) - vec2<i32>(1);
    return min(lp * ds + vec2<i32>(ds / 2), full);
}

// What a photon (`position_radius`; `direction`: into its surface, w = 1 its surface's
// normal reversed, w = 0 the direction it travelled) adds to a surface point,
// Φ · κ(s) / N_κ(r) per unit power; negative where the point does not receive it. A photon
// with its normal lights surfaces facing within `levels.z` (a cosine) of it; one with its
// direction any surface facing against that direction.
fn kernel_at(surface: Surface, position_radius: vec4<f32>, direction: vec4<f32>) -> f32 {
    if (!surface.covered) {
        return -1.0;
    }
    let n = surface.normal;
    let r = position_radius.w;
    let delta = surface.position - position_radius.xyz;
    let dn = dot(delta, n);
    if (abs(dn) > params.settings.y * r) {
        return -1.0;
    }
    let s2 = max(dot(delta, delta) - dn * dn, 0.0);
    let against = -dot(n, direction.xyz);
    let least = select(0.0, params.levels.z, direction.w > 0.5);
    if (s2 >= r * r || against <= least) {
        return -1.0;
    }
    let kappa = 1.0 - sqrt(s2) / r;
    let norm = 3.14159265 * r * r / 3.0;
    return kappa / norm;
}

@fragment
fn fs_splat(in: SplatOut) -> @location(0) vec4<f32> {
    let surface = surface_of(textureLoad(dst_guide, vec2<i32>(in.clip.xy), 0));
    let k = kernel_at(surface, in.position_radius, in.direction);
    if (k < 0.0) {
        discard;
    }
    return vec4<f32>(in.power.rgb * (k * params.scale.x), 1.0);
}

struct Surface {
    position: vec3<f32>,
    normal: vec3<f32>,
    covered: bool,
};

// A unit normal in one word: 3 × 10-bit snorm (x from bit 2, y from 12, z from 22; within
// 0.002 of the normal, not renormalised) with bit 0 set, so that a covered texel is never 0.
// The splat, the resolve and the upsample decode one per tap: with an octahedral code (a
// branch and a normalisation per decode) llvmpipe ran them ~15% slower (Cornell, 640×360).
fn pack_normal(n: vec3<f32>) -> u32 {
    let q = vec3<i32>(round(clamp(n, vec3<f32>(-1.0), vec3<f32>(1.0)) * 511.0));
    let b = bitcast<vec3<u32>>(q) & vec3<u32>(1023u);
    return (b.x << 2u) | (b.y << 12u) | (b.z << 22u) | 1u;
}

fn unpack_normal(w: u32) -> vec3<f32> {
    // Each field shifted to the top of the word, then back with its sign.
    let i = bitcast<i32>(w);
    let q = vec3<i32>((i << 20u) >> 22u, (i << 10u) >> 22u, i >> 22u);
    return vec3<f32>(q) * (1.0 / 511.0);
}

fn surface_of(v: vec4<u32>) -> Surface {
    var s: Surface;
    s.covered = v.w != 0u;
    s.position = bitcast<vec3<f32>>(v.xyz);
    s.normal = unpack_normal(v.w);
    return s;
}

struct FullOut {
    @builtin(position) clip: vec4<f32>,
    // x: the level the pass works on (vertices 3l .. 3l + 3 draw level l).
    @location(0) @interpolate(flat) level: vec4<u32>,
};

@vertex
fn vs_full(@builtin(vertex_index) vi: u32) -> FullOut {
    let i = vi % 3u;
    let uv = vec2<f32>(f32((i << 1u) & 2u), f32(i & 2u));
    var out: FullOut;
    out.clip = vec4<f32>(uv * 2.0 - 1.0, 0.0, 1.0);
    out.level = vec4<u32>(vi / 3u, 0u, 0u, 0u);
    return out;
}

// The guide of one level: each texel's surface from the full-resolution G-buffer.
@fragment
fn fs_guide(in: FullOut) -> @location(0) vec4<u32> {
    let ds = i32(params.settings.x) << in.level.x;
    let px = full_texel(vec2<i32>(in.clip.xy), ds);
    let g = position_at(px);
    if (g.w < 0.5) {
        return vec4<u32>(0u);
    }
    return vec4<u32>(bitcast<vec3<u32>>(g.xyz), pack_normal(normal_at(px)));
}

// cos^p of the upsample's normal weight: by squaring when p is 8 (the default; llvmpipe's
// pow is an exp2 and a log2 per tap), else pow.
fn cosine_power(c: f32) -> f32 {
    if (params.settings.w == 8.0) {
        let c2 = c * c;
        let c4 = c2 * c2;
        return c4 * c4;
    }
    return pow(c, params.settings.w);
}

// Joint-bilateral upsample of the irradiance of level `level` (`src_accum`, `src_guide`) at
// a point (`frag`, in full-resolution pixels; surface `g`, `n`). Taps: the four nearest pixels of the level,
// weighted bilinearly × exp(−|plane distance| / σ) × max(0, n·n')^p; the nearest tap in
// plane distance is the fallback when every weight vanishes.
fn upsample_level(level: u32, frag: vec2<f32>, g: vec3<f32>, n: vec3<f32>) -> vec3<f32> {
    return upsample_from(src_accum, src_guide, level, frag, g, n);
}

// `upsample_level` from the given level's buffer and guide.
fn upsample_from(
    accum: texture_2d<f32>,
    guide: texture_2d<u32>,
    level: u32,
    frag: vec2<f32>,
    g: vec3<f32>,
    n: vec3<f32>,
) -> vec3<f32> {
    let ds = params.settings.x * f32(1u << level);
    let low = vec2<i32>(ceil(params.sizes.xy / ds)) - vec2<i32>(1);
    let lp = frag / ds - vec2<f32>(0.5);
    let base = vec2<i32>(floor(lp));
    let f = lp - floor(lp);
    var sum = vec3<f32>(0.0);
    var wsum = 0.0;
    var best = vec3<f32>(0.0);
    var best_d = 1e30;
    for (var k = 0u; k < 4u; k = k + 1u) {
        let o = vec2<i32>(i32(k & 1u), i32(k >> 1u));
        let t = clamp(base + o, vec2<i32>(0), low);
        let tap = surface_of(textureLoad(guide, t, 0));
        let e = textureLoad(accum, t, 0).rgb;
        let plane = abs(dot(tap.position - g, n));
        let cosine = max(dot(n, tap.normal), 0.0);
        let bw = select(1.0 - f.x, f.x, o.x == 1) * select(1.0 - f.y, f.y, o.y == 1);
        let w = select(0.0, bw * exp(-plane / params.settings.z) * cosine_power(cosine), tap.covered);
        sum += w * e;
        wsum += w;
        let d = select(1e30, plane + (1.0 - cosine), tap.covered);
        let closer = d < best_d;
        best_d = select(best_d, d, closer);
        best = select(best, e, closer);
    }
    if (wsum > 1e-4) {
        return sum / wsum;
    }
    return best;
}

// Folds level l + 1 into level l (l = the pass's level), at level l's resolution: the
// coarse levels reach full resolution through one upsample.
@fragment
fn fs_collapse(in: FullOut) -> @location(0) vec4<f32> {
    return vec4<f32>(coarser_at(in.level.x, vec2<i32>(in.clip.xy)), 0.0);
}

// Level l + 1 upsampled at texel `t` of level l (its guide `dst_guide`): zero where the
// texel sees no geometry.
fn coarser_at(level: u32, t: vec2<i32>) -> vec3<f32> {
    let surface = surface_of(textureLoad(dst_guide, t, 0));
    if (!surface.covered) {
        return vec3<f32>(0.0);
    }
    let ds = params.settings.x * f32(1u << level);
    // The full-resolution point this texel stands for (its centre texel, as the guide).
    let frag = vec2<f32>(full_texel(t, i32(ds))) + vec2<f32>(0.5);
    return upsample_level(level + 1u, frag, surface.position, surface.normal);
}

// Level 0 (holding the coarser levels, folded in) at full resolution, times ρ/π: indirect
// radiance.
@fragment
fn fs_upsample(@builtin(position) frag: vec4<f32>) -> @location(0) vec4<u32> {
    let px = vec2<i32>(frag.xy);
    let g = position_at(px);
    if (g.w < 0.5) {
        return vec4<u32>(0u);
    }
    let irradiance = upsample_level(0u, frag.xy, g.xyz, normal_at(px));
    return radiance_bits(px, irradiance);
}

// Accumulated irradiance (× `scale.x`) at pixel `px` as the upsample writes it: ρ/π × E.
fn radiance_bits(px: vec2<i32>, irradiance: vec3<f32>) -> vec4<u32> {
    return bitcast<vec4<u32>>(vec4<f32>(albedo_at(px) / 3.14159265 * irradiance / params.scale.x, 1.0));
}

// `fs_upsample` after a compute splat with edges: an edge pixel (`cs_edges`) reads its own
// full-resolution sums of the level-0 photons instead of level 0, plus level 1 (the coarser
// photons) upsampled.
@fragment
fn fs_upsample_edges(@builtin(position) frag: vec4<f32>) -> @location(0) vec4<u32> {
    let px = vec2<i32>(frag.xy);
    let g = position_at(px);
    if (g.w < 0.5) {
        return vec4<u32>(0u);
    }
    let i = pixel_index(px);
    if (params.counts.y != 0u && fixed_sums[edge_mask_offset() + i] != 0u) {
        let e = edge_sums_offset() + 3u * i;
        let sums = vec3<f32>(f32(fixed_sums[e]), f32(fixed_sums[e + 1u]), f32(fixed_sums[e + 2u]));
        var irradiance = sums * (params.scale.x / params.scale.y);
        if (params.levels.x > 1.0) {
            irradiance += upsample_from(coarse_accum, coarse_guide, 1u, frag.xy, g.xyz, normal_at(px));
        }
        return radiance_bits(px, irradiance);
    }
    return radiance_bits(px, upsample_level(0u, frag.xy, g.xyz, normal_at(px)));
}

// Texels of level `l` (per axis).
fn level_size(l: u32) -> vec2<u32> {
    return vec2<u32>(ceil(params.sizes.xy / (params.settings.x * f32(1u << l))));
}

// The first texel of level `l` in the fixed-point sums.
fn level_offset(l: u32) -> u32 {
    var o = 0u;
    for (var k = 0u; k < l; k = k + 1u) {
        let s = level_size(k);
        o = o + s.x * s.y;
    }
    return o;
}

// Edges: a pixel whose surface none of level 0's upsample taps stands for (a ledge one
// pixel wide between faces that turn away from it, a pole seen edge-on, the top row of a
// wall) would borrow another surface's light through the bilateral weights, whatever its
// own. `cs_edges` marks those pixels; the compute splat then adds the photons of level 0
// to them at full resolution too, and the upsample reads those sums there (the coarser
// levels' photons, spanning a few texels of level 1 or more and so smooth there, still
// come through level 1's upsample: testing every level marked a band as wide as a coarse
// texel along every crease, and put each coarse photon on thousands of pixels — Cornell at
// 640×360: frame 43 → 530 ms). Their sums follow the
// levels' in the same buffer: three words per pixel, then a mark per pixel, then a mark
// per texel of level 0 (a bit per pixel of it that is an edge, row after row: downsample
// 4 at most).
fn pixel_index(px: vec2<i32>) -> u32 {
    return u32(px.y) * u32(params.sizes.x) + u32(px.x);
}

fn edge_sums_offset() -> u32 {
    return 3u * level_offset(u32(params.levels.x));
}

fn edge_mask_offset() -> u32 {
    return edge_sums_offset() + 3u * u32(params.sizes.x) * u32(params.sizes.y);
}

fn edge_block_offset() -> u32 {
    return edge_mask_offset() + u32(params.sizes.x) * u32(params.sizes.y);
}

// Least weighted similarity (the upsample's exp(−plane/σ)·cos^p, averaged with its own
// weights) of a pixel's surface to the level's taps for the upsample to stand for it.
const EDGE_MATCH: f32 = 0.5;

// Whether level `level`'s upsample stands for the surface (`g`, `n`) at `frag` (as
// `upsample_level` weighs its taps, each tap's surface read from the G-buffer as its guide
// holds it).
fn represented(level: u32, frag: vec2<f32>, g: vec3<f32>, n: vec3<f32>) -> bool {
    let ds = params.settings.x * f32(1u << level);
    let low = vec2<i32>(ceil(params.sizes.xy / ds)) - vec2<i32>(1);
    let lp = frag / ds - vec2<f32>(0.5);
    let base = vec2<i32>(floor(lp));
    let f = lp - floor(lp);
    var wsum = 0.0;
    var msum = 0.0;
    for (var k = 0u; k < 4u; k = k + 1u) {
        let o = vec2<i32>(i32(k & 1u), i32(k >> 1u));
        let t = clamp(base + o, vec2<i32>(0), low);
        let px = full_texel(t, i32(ds));
        let tap = position_at(px);
        if (tap.w < 0.5) {
            continue;
        }
        let plane = abs(dot(tap.xyz - g, n));
        let m = exp(-plane / params.settings.z) * cosine_power(max(dot(n, normal_at(px)), 0.0));
        let bw = select(1.0 - f.x, f.x, o.x == 1) * select(1.0 - f.y, f.y, o.y == 1);
        wsum += bw * m;
        msum += bw * m * m;
    }
    return wsum > 1e-4 && msum >= EDGE_MATCH * wsum;
}

// Marks the edge pixels of level 0 (and its texels holding one) for the compute splat: one
// invocation per pixel.
@compute @workgroup_size(64)
fn cs_edges(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = id.x + id.y * groups.x * 64u;
    let w = u32(params.sizes.x);
    if (i >= w * u32(params.sizes.y)) {
        return;
    }
    let px = vec2<i32>(i32(i % w), i32(i / w));
    let g = position_at(px);
    if (g.w < 0.5) {
        return;
    }
    let n = normal_at(px);
    // Most pixels lie on the surface of their own texel of level 0, whose bilinear weight
    // (at least 0.75² with a factor of 2) then carries the upsample: no need to weigh all
    // four taps.
    let ds = i32(params.settings.x);
    let own = full_texel(px / ds, ds);
    let own_g = position_at(own);
    if (ds <= 2 && own_g.w >= 0.5 && dot(n, normal_at(own)) > 0.99
        && abs(dot(own_g.xyz - g.xyz, n)) < 0.05 * params.settings.z) {
        return;
    }
    let frag = vec2<f32>(px) + vec2<f32>(0.5);
    if (!represented(0u, frag, g.xyz, n)) {
        atomicStore(&fixed_accum[edge_mask_offset() + i], 1u);
        let ds = i32(params.settings.x);
        let t = px / ds;
        let block = u32(t.y) * level_size(0u).x + u32(t.x);
        let bit = u32((px.y - t.y * ds) * ds + px.x - t.x * ds);
        atomicOr(&fixed_accum[edge_block_offset() + block], 1u << bit);
    }
}

// Adds `power` × kernel `k` (W/m² per W, fixed point) to word `first` on: one texel's sums.
fn add_units(first: u32, power: vec3<f32>, k: f32, i: u32) {
    let u = hash01(i, first);
    let e = min(power * k + vec3<f32>(u), vec3<f32>(MAX_UNITS));
    let units = vec3<u32>(e);
    if (units.r != 0u) {
        atomicAdd(&fixed_accum[first], units.r);
    }
    if (units.g != 0u) {
        atomicAdd(&fixed_accum[first + 1u], units.g);
    }
    if (units.b != 0u) {
        atomicAdd(&fixed_accum[first + 2u], units.b);
    }
}

// A uniform number in [0, 1) from two words (PCG hash; Jarzynski & Olano 2020).
fn hash01(a: u32, b: u32) -> f32 {
    var v = a * 747796405u + b * 2891336453u + 2654435769u;
    let w = ((v >> ((v >> 28u) + 4u)) ^ v) * 277803737u;
    return f32((w >> 22u) ^ w) * 2.3283064e-10;
}

// Fixed-point units one photon may add to one texel (keeps a pathological photon from
// overflowing a sum: ~2^12 units is a typical photon's peak).
const MAX_UNITS: f32 = 16777216.0;

// Adds photon `p` (number `i`) at full resolution to the edge pixels of level-0 texel `t`
// (`cs_edges`' marks), if it holds any.
fn splat_edges(t: vec2<i32>, p: PhotonStored, power: vec3<f32>, i: u32) {
    // One iteration per edge pixel of the texel (its mark's bits), none for a texel without.
    var bits = atomicLoad(&fixed_accum[edge_block_offset() + u32(t.y) * level_size(0u).x + u32(t.x)]);
    let ds = i32(params.settings.x);
    let sums = edge_sums_offset();
    while (bits != 0u) {
        let k = i32(firstTrailingBit(bits));
        bits = bits & (bits - 1u);
        let px = t * ds + vec2<i32>(k % ds, k / ds);
        let kernel = kernel_at(pixel_surface(px), p.position_radius, p.direction);
        if (kernel >= 0.0) {
            add_units(sums + 3u * pixel_index(px), power, kernel, i);
        }
    }
}

// The texels of a photon's level whose centre lies in its padded bounds (NDC y up, texel
// rows down), clamped to the level; empty (`lo > hi`) where the photon splats nowhere.
struct Span {
    lo: vec2<i32>,
    hi: vec2<i32>,
    level: u32,
};

fn texel_span(position_radius: vec4<f32>) -> Span {
    let f = footprint(position_radius);
    var s: Span;
    s.level = f.level;
    s.lo = vec2<i32>(0);
    s.hi = vec2<i32>(-1);
    if (!f.visible) {
        return s;
    }
    let size = level_size(f.level);
    let sizef = vec2<f32>(size);
    let x0 = i32(ceil((f.lo.x * 0.5 + 0.5) * sizef.x - 0.5));
    let x1 = i32(floor((f.hi.x * 0.5 + 0.5) * sizef.x - 0.5));
    let y0 = i32(ceil((0.5 - f.hi.y * 0.5) * sizef.y - 0.5));
    let y1 = i32(floor((0.5 - f.lo.y * 0.5) * sizef.y - 0.5));
    s.lo = max(vec2<i32>(x0, y0), vec2<i32>(0));
    s.hi = min(vec2<i32>(x1, y1), vec2<i32>(size) - vec2<i32>(1));
    return s;
}

// Texels of a span.
fn span_texels(s: Span) -> i32 {
    let extent = max(s.hi - s.lo + vec2<i32>(1), vec2<i32>(0));
    return extent.x * extent.y;
}

// The texel after `t` in a span, row after row.
fn next_texel(s: Span, t: vec2<i32>) -> vec2<i32> {
    let wrap = t.x >= s.hi.x;
    return vec2<i32>(select(t.x + 1, s.lo.x, wrap), select(t.y, t.y + 1, wrap));
}

// The surface pixel `px` sees, from the G-buffer (the edges' splat works at full
// resolution, where no guide is).
fn pixel_surface(px: vec2<i32>) -> Surface {
    let g = position_at(px);
    var surface: Surface;
    surface.covered = g.w >= 0.5;
    surface.position = g.xyz;
    surface.normal = normal_at(px);
    return surface;
}

// The compute splat: one invocation per photon, at the photon's level. Each covered texel
// of its padded bounds gets Φ · κ(s) / N_κ(r) — the same test and kernel as `fs_splat` —
// added in fixed point (`scale.y` units per W/m², rounded stochastically so that small
// additions stay unbiased). The cost is the texels a disk covers, with no per-triangle
// set-up (Cornell, 10k photons, 640×360 on lavapipe: one dispatch per level instead of one
// in all cost ~4 ms more, 8 invocations sharing a photon's texels no less). Binning the
// photons into tiles of 8 × 8 texels and gathering each tile's photons per texel (a
// surface read and one addition per texel) was slower on llvmpipe: 36 ms against the
// walk's 10, each photon's disk covering a small part of the 4–9 tiles it touches.
@compute @workgroup_size(64)
fn cs_splat(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = id.x + id.y * groups.x * 64u;
    // A large set is dispatched in chunks, each bound as its own range of the buffer.
    if (i >= min(params.counts.x, arrayLength(&photons))) {
        return;
    }
    let p = photons[i];
    let s = texel_span(p.position_radius);
    let size = level_size(s.level);
    let offset = level_offset(s.level);
    let power = p.power.rgb * params.scale.y;
    // One loop over the span's texels, row after row: lanes (photons) whose spans differ in
    // shape then wait only for the largest span, not for the widest row times the most rows
    // (splat 9.6 → 9.2 ms, two runs each).
    let count = span_texels(s);
    var t = s.lo;
    for (var n = 0; n < count; n = n + 1) {
        let k = kernel_at(surface_of(textureLoad(guide_levels, t, i32(s.level), 0)), p.position_radius, p.direction);
        if (k >= 0.0) {
            let texel = offset + u32(t.y) * size.x + u32(t.x);
            add_units(3u * texel, power, k, i);
        }
        t = next_texel(s, t);
    }
}

// The edges' splat (after `cs_edges`, beside `cs_splat`): each photon of level 0 added to
// the edge pixels of its span's texels at full resolution. A dispatch of its own: with this
// code inside `cs_splat`'s loop, llvmpipe ran that splat at 27 ms instead of 10 with edges
// off (behind a uniform `if`), and at 20 ms with edges on where no texel held an edge pixel
// (Cornell, 10k photons, 640×360); this dispatch takes ~0.3 ms.
@compute @workgroup_size(64)
fn cs_splat_edges(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = id.x + id.y * groups.x * 64u;
    if (i >= min(params.counts.x, arrayLength(&photons))) {
        return;
    }
    let p = photons[i];
    let s = texel_span(p.position_radius);
    let count = select(0, span_texels(s), s.level == 0u);
    let power = p.power.rgb * params.scale.y;
    var t = s.lo;
    for (var n = 0; n < count; n = n + 1) {
        splat_edges(t, p, power, i);
        t = next_texel(s, t);
    }
}

// After the compute splat, level l (the pass's level) as the accumulation buffer holds it:
// its own fixed-point sums plus level l + 1 folded in (as `fs_collapse`; the coarsest level
// has none). Levels are resolved coarsest first.
@fragment
fn fs_resolve(in: FullOut) -> @location(0) vec4<f32> {
    let level = in.level.x;
    let t = vec2<u32>(in.clip.xy);
    let texel = level_offset(level) + t.y * level_size(level).x + t.x;
    let sums = vec3<f32>(
        f32(fixed_sums[3u * texel]),
        f32(fixed_sums[3u * texel + 1u]),
        f32(fixed_sums[3u * texel + 2u]),
    );
    var e = sums * (params.scale.x / params.scale.y);
    if (level + 1u < u32(params.levels.x)) {
        e += coarser_at(level, vec2<i32>(t));
    }
    return vec4<f32>(e, 0.0);
}
