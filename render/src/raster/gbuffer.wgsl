// G-buffer pass: world position, shading normal and albedo of the nearest surface per pixel.
// Targets (see raster/frame.rs, `GBufferTargets`): position as f32 bits (Rgba32Uint), normal
// and albedo as four f16 each (Rg32Uint). `Vertex` matches raster/frame.rs.

struct View {
    clip_from_world: mat4x4<f32>,
};

@group(0) @binding(0) var<uniform> view: View;

struct VertexIn {
    @location(0) position: vec3<f32>,
    @location(1) normal: vec3<f32>,
    @location(2) albedo: vec3<f32>,
};

struct VertexOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) world: vec3<f32>,
    @location(1) normal: vec3<f32>,
    @location(2) albedo: vec3<f32>,
};

@vertex
fn vs_main(v: VertexIn) -> VertexOut {
    var out: VertexOut;
    out.clip = view.clip_from_world * vec4<f32>(v.position, 1.0);
    out.world = v.position;
    out.normal = v.normal;
    out.albedo = v.albedo;
    return out;
}

struct GBufferOut {
    // xyz: world position (m); w: 1 where a surface was drawn (f32 bits).
    @location(0) position: vec4<u32>,
    // xyz: unit shading normal facing the camera side of the surface (f16 pairs).
    @location(1) normal: vec2<u32>,
    // rgb: albedo (f16 pairs).
    @location(2) albedo: vec2<u32>,
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
    g.albedo = vec2<u32>(pack2x16float(in.albedo.rg), pack2x16float(vec2<f32>(in.albedo.b, 1.0)));
    return g;
}
