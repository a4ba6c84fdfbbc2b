// The irradiance-map client's indirect pass (CloudLight §4.2): each pixel looks the map up
// through its light-map UV with bilinear filtering and shows ρ/π · E. Layouts match
// lightmap/pass.rs (`LookupParams`). The G-buffer holds f32 bits (position, light-map UV;
// the UV is a quiet NaN where the geometry has none) and f16 pairs (albedo); the map is
// Rgba16Float of E / `params.scale.x`, so that any light unit stays in f16's range; the pass
// writes indirect radiance as f32 bits.

struct LookupParams {
    // x: what a map texel is multiplied by to give irradiance, W/m²; y: 1 when a map is bound.
    scale: vec4<f32>,
};

@group(0) @binding(0) var<uniform> params: LookupParams;
@group(0) @binding(1) var gpos: texture_2d<u32>;
@group(0) @binding(2) var galb: texture_2d<u32>;
@group(0) @binding(3) var guv: texture_2d<u32>;
@group(0) @binding(4) var map: texture_2d<f32>;
@group(0) @binding(5) var map_sampler: sampler;

@vertex
fn vs_full(@builtin(vertex_index) i: u32) -> @builtin(position) vec4<f32> {
    let uv = vec2<f32>(f32((i << 1u) & 2u), f32(i & 2u));
    return vec4<f32>(uv * 2.0 - 1.0, 0.0, 1.0);
}

// Branch-free after the first test: llvmpipe samples far more slowly under divergent
// control flow.
@fragment
fn fs_lookup(@builtin(position) frag: vec4<f32>) -> @location(0) vec4<u32> {
    let px = vec2<i32>(frag.xy);
    let g = bitcast<vec4<f32>>(textureLoad(gpos, px, 0));
    if (g.w < 0.5) {
        return vec4<u32>(0u);
    }
    let uv_bits = textureLoad(guv, px, 0).xy;
    // A NaN (no light-map UV) tested on its bits: WGSL may assume floats are never NaN.
    let exponent = 0x7f800000u;
    let mapped = (uv_bits.x & exponent) != exponent && (uv_bits.y & exponent) != exponent && params.scale.y >= 0.5;
    let uv = select(vec2<f32>(0.0), bitcast<vec2<f32>>(uv_bits), mapped);
    let v = textureLoad(galb, px, 0).xy;
    let albedo = vec3<f32>(unpack2x16float(v.x), unpack2x16float(v.y).x);
    let e = max(textureSampleLevel(map, map_sampler, uv, 0.0).rgb, vec3<f32>(0.0)) * params.scale.x;
    let radiance = select(vec3<f32>(0.0), albedo / 3.14159265 * e, mapped);
    return bitcast<vec4<u32>>(vec4<f32>(radiance, 1.0));
}
