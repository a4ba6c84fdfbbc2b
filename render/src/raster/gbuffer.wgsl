// G-buffer pass: world position, shading normal, albedo and light-map UV of the nearest
// surface per pixel. Targets (see raster/targets.rs, `GBufferTargets`): position as f32 bits
// (Rgba32Uint), normal and albedo as four f16 each (Rg32Uint), light-map UV as two f32 bits
// (Rg32Uint; NaN where the geometry has none). `VertexIn` matches `GBufferVertex` in
// raster/pipelines.rs. Albedo is the material's times its texture (raster/albedo.rs: the
// nearest texel when magnified, a trilinear mip when minified; layer 0 is white).

struct View {
    clip_from_world: mat4x4<f32>,
};

@group(0) @binding(0) var<uniform> view: View;
@group(1) @binding(0) var albedo_maps: texture_2d_array<f32>;
@group(1) @binding(1) var albedo_sampler: sampler;

struct VertexIn {
    @location(0) position: vec3<f32>,
    // xyz (snorm16; w unused).
    @location(1) normal: vec4<f32>,
    // rgb (unorm16; a unused).
    @location(2) albedo: vec4<f32>,
    // Light-map UV in [0, 1]²; negative where the triangle has none.
    @location(3) lightmap: vec2<f32>,
    @location(4) uv: vec2<f32>,
    // The albedo array's layer (0: white).
    @location(5) layer: u32,
};

struct VertexOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) world: vec3<f32>,
    @location(1) normal: vec3<f32>,
    @location(2) albedo: vec3<f32>,
    @location(3) lightmap: vec2<f32>,
    @location(4) uv: vec2<f32>,
    @location(5) @interpolate(flat) layer: u32,
};

@vertex
fn vs_main(v: VertexIn) -> VertexOut {
    var out: VertexOut;
    out.clip = view.clip_from_world * vec4<f32>(v.position, 1.0);
    out.world = v.position;
    out.normal = v.normal.xyz;
    out.albedo = v.albedo.rgb;
    out.lightmap = v.lightmap;
    out.uv = v.uv;
    out.layer = v.layer;
    return out;
}

struct GBufferOut {
    // xyz: world position (m); w: 1 where a surface was drawn (f32 bits).
    @location(0) position: vec4<u32>,
    // xyz: unit shading normal facing the camera side of the surface (f16 pairs).
    @location(1) normal: vec2<u32>,
    // rgb: albedo (f16 pairs).
    @location(2) albedo: vec2<u32>,
    // Light-map UV in [0, 1]² as f32 bits; quiet NaN where the surface has none.
    @location(3) lightmap: vec2<u32>,
};

@fragment
fn fs_main(in: VertexOut, @builtin(front_facing) front: bool) -> GBufferOut {
    var g: GBufferOut;
    var n = normalize(in.normal);
    if (!front) {
        n = -n;
    }
    g.position = bitcast<vec4<u32>>(vec4<f32>(in.world, 1.0));
    g.normal = vec2<u32>(pack2x16float(n.xy), pack2x16float(vec2<f32>(n.z, 0.0)));
    // Derivatives in uniform control flow; an untextured surface (layer 0, white) skips the
    // lookup.
    let du = dpdx(in.uv);
    let dv = dpdy(in.uv);
    var albedo = in.albedo;
    if (in.layer > 0u) {
        albedo *= textureSampleGrad(albedo_maps, albedo_sampler, in.uv, in.layer, du, dv).rgb;
    }
    g.albedo = vec2<u32>(pack2x16float(albedo.rg), pack2x16float(vec2<f32>(albedo.b, 1.0)));
    if (in.lightmap.x > -0.5) {
        g.lightmap = bitcast<vec2<u32>>(in.lightmap.xy);
    } else {
        g.lightmap = vec2<u32>(0x7fc00000u, 0x7fc00000u);
    }
    return g;
}
