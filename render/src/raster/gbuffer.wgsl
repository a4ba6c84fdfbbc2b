// G-buffer pass: world position, shading normal and albedo of the nearest surface per pixel.
// Layout shared with raster/mod.rs: `Globals` and `Vertex` (marked there too).

struct Globals {
    clip_from_world: mat4x4<f32>,
};

@group(0) @binding(0) var<uniform> globals: Globals;

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
    out.clip = globals.clip_from_world * vec4<f32>(v.position, 1.0);
    out.world = v.position;
    out.normal = v.normal;
    out.albedo = v.albedo;
    return out;
}

struct GBuffer {
    // xyz: world position (m); w: 1 where a surface was drawn.
    @location(0) position: vec4<f32>,
    // xyz: unit shading normal facing the camera side of the surface.
    @location(1) normal: vec4<f32>,
    // rgb: albedo.
    @location(2) albedo: vec4<f32>,
};

@fragment
fn fs_main(in: VertexOut, @builtin(front_facing) front: bool) -> GBuffer {
    var g: GBuffer;
    var n = normalize(in.normal);
    if (!front) {
        n = -n;
    }
    g.position = vec4<f32>(in.world, 1.0);
    g.normal = vec4<f32>(n, 0.0);
    g.albedo = vec4<f32>(in.albedo, 1.0);
    return g;
}
