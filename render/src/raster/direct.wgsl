// Direct lighting from a G-buffer with shadow maps: point (six cube faces), spot and
// directional lights. Layouts match raster/shadow.rs (`LightGpu`, `DirectParams`); the
// G-buffer and the output hold f32 bits (position, radiance) and f16 pairs (normal, albedo).
//
// Each light's contribution is computed without branching on the pixel (cube lights and
// one-view lights in two loops, each body of one kind), lights are a uniform array, and shadow
// coordinates come from a few numbers per light instead of a matrix per view: llvmpipe (the
// software driver used without a GPU) runs a texture lookup under divergent control flow,
// or after a per-pixel matrix gather, several times slower. Measured on the Cornell box
// (8 emitters, 640×360): direct pass 40 → 20–25 ms.

struct LightGpu {
    // xyz: position (m; for the sun, the eye of its orthographic shadow view); w: kind
    // (0 point, 1 spot, 2 directional, 3 surface sample).
    position: vec4<f32>,
    // xyz: unit direction (spot axis / travel of sunlight / emitter normal), which is also
    // the forward axis of a spot's or the sun's shadow view; w: cosine of the spot cone.
    direction: vec4<f32>,
    // rgb: intensity (W/sr) or irradiance (W/m²); w: index of the light's first shadow view.
    intensity: vec4<f32>,
    // A spot's or the sun's shadow view: xyz its right axis, w the scale from view units to
    // NDC (cot of half the field of view; 1 / half-extent for the sun).
    shadow_right: vec4<f32>,
    // xyz: that view's up axis; w: depth per metre of an orthographic view (the sun), 0 for
    // a perspective one.
    shadow_up: vec4<f32>,
};

struct Params {
    light_count: u32,
    depth_bias: f32,
    normal_offset_m: f32,
    // Every perspective shadow view's depth range, and the cube faces' cot of half their
    // field of view.
    cube_cot: f32,
    near_m: f32,
    far_m: f32,
    // Lights [0, cube_lights) have cube maps; the rest one view each.
    cube_lights: u32,
    pad: f32,
};

@group(0) @binding(0) var gpos: texture_2d<u32>;
@group(0) @binding(1) var gnrm: texture_2d<u32>;
@group(0) @binding(2) var galb: texture_2d<u32>;
@group(0) @binding(3) var shadow_maps: texture_depth_2d_array;
@group(0) @binding(4) var shadow_sampler: sampler_comparison;
@group(0) @binding(5) var<uniform> lights: array<LightGpu, 256>;
@group(0) @binding(6) var<uniform> params: Params;

@vertex
fn vs_main(@builtin(vertex_index) i: u32) -> @builtin(position) vec4<f32> {
    // One triangle covering the screen.
    let uv = vec2<f32>(f32((i << 1u) & 2u), f32(i & 2u));
    return vec4<f32>(uv * 2.0 - 1.0, 0.0, 1.0);
}

// The cube face that sees `d` (from the light to the point), in the order of shadow.rs's
// CUBE_FACES (+x, −x, +y, −y, +z, −z), and d in that face's view: right, up and forward
// coordinates (each face a look_to view: right = forward × up, up = right × forward).
fn cube_view(d: vec3<f32>) -> vec4<f32> {
    let a = abs(d);
    var v = vec4<f32>(select(-d.x, d.x, d.z > 0.0), -d.y, a.z, select(5.0, 4.0, d.z > 0.0));
    if (a.y >= a.z) {
        v = vec4<f32>(d.x, select(-d.z, d.z, d.y > 0.0), a.y, select(3.0, 2.0, d.y > 0.0));
    }
    if (a.x >= a.y && a.x >= a.z) {
        v = vec4<f32>(select(d.z, -d.z, d.x > 0.0), -d.y, a.x, select(1.0, 0.0, d.x > 0.0));
    }
    return v;
}

fn perspective_depth(forward: f32) -> f32 {
    return params.far_m / (params.far_m - params.near_m) * (1.0 - params.near_m / forward);
}

fn lit(uv_ndc: vec2<f32>, layer: u32, depth: f32) -> f32 {
    let uv = vec2<f32>(uv_ndc.x * 0.5 + 0.5, 0.5 - uv_ndc.y * 0.5);
    return textureSampleCompareLevel(shadow_maps, shadow_sampler, uv, i32(layer), depth - params.depth_bias);
}

// Whether a point light's or a surface sample's cube map sees `p` lit.
fn cube_visibility(l: LightGpu, p: vec3<f32>) -> f32 {
    let v = cube_view(p - l.position.xyz);
    let forward = max(v.z, 1e-30);
    return lit(v.xy * (params.cube_cot / forward), u32(l.intensity.w) + u32(v.w), perspective_depth(forward));
}

// Whether a spot's or the sun's one shadow view sees `p` lit: 1 outside that view.
fn view_visibility(l: LightGpu, p: vec3<f32>) -> f32 {
    let d = p - l.position.xyz;
    let v = vec3<f32>(dot(d, l.shadow_right.xyz), dot(d, l.shadow_up.xyz), dot(d, l.direction.xyz));
    let forward = max(v.z, 1e-30);
    let ortho = l.shadow_up.w > 0.0;
    let ndc = v.xy * (l.shadow_right.w / select(forward, 1.0, ortho));
    let depth = select(perspective_depth(forward), v.z * l.shadow_up.w, ortho);
    let inside = v.z > 0.0 && all(abs(ndc) <= vec2<f32>(1.0)) && depth <= 1.0;
    return select(1.0, lit(select(vec2<f32>(0.0), ndc, inside), u32(l.intensity.w), depth), inside);
}

// Irradiance from light `l` at `x` (normal `n`) without its shadow, W/m².
fn unshadowed(l: LightGpu, x: vec3<f32>, n: vec3<f32>) -> vec3<f32> {
    let kind = u32(l.position.w);
    let sun = kind == 2u;
    let to = l.position.xyz - x;
    let dist2 = select(max(dot(to, to), 1e-12), 1.0, sun);
    let w = select(to * inverseSqrt(dist2), -l.direction.xyz, sun);
    let c = max(dot(n, w), 0.0);
    // A spot lights inside its cone; a surface sample is a Lambertian emitter.
    let axis = dot(-w, l.direction.xyz);
    let falloff = select(
        select(1.0, max(axis, 0.0), kind == 3u),
        select(0.0, 1.0, axis >= l.direction.w),
        kind == 1u,
    );
    return l.intensity.rgb * (falloff * c / dist2);
}

@fragment
fn fs_main(@builtin(position) frag: vec4<f32>) -> @location(0) vec4<u32> {
    let px = vec2<i32>(frag.xy);
    let g = bitcast<vec4<f32>>(textureLoad(gpos, px, 0));
    // Measured: returning early here beats a select at the end.
    if (g.w < 0.5) {
        return vec4<u32>(0u);
    }
    let gn = textureLoad(gnrm, px, 0).xy;
    // Unit when written (gbuffer.wgsl); f16 keeps it within 1e-3 of unit length.
    let n = vec3<f32>(unpack2x16float(gn.x), unpack2x16float(gn.y).x);
    let ga = textureLoad(galb, px, 0).xy;
    let albedo = vec3<f32>(unpack2x16float(ga.x), unpack2x16float(ga.y).x);
    let p = g.xyz + n * params.normal_offset_m;
    var e = vec3<f32>(0.0);
    // Cube lights come first (shadow.rs sorts them), so each loop's body is one kind.
    for (var k = 0u; k < params.cube_lights; k = k + 1u) {
        let l = lights[k];
        e += unshadowed(l, g.xyz, n) * cube_visibility(l, p);
    }
    for (var k = params.cube_lights; k < params.light_count; k = k + 1u) {
        let l = lights[k];
        e += unshadowed(l, g.xyz, n) * view_visibility(l, p);
    }
    return bitcast<vec4<u32>>(vec4<f32>(albedo / 3.14159265 * e, 1.0));
}
