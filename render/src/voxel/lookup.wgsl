// The voxel frame renderer's indirect pass (CloudLight §4.1, "per-pixel irradiance looked up
// in the voxels"): each pixel samples the ambient-cube volume of volume.rs at its world
// position, for each axis the face its normal points along, with trilinear filtering, and
// shows ρ/π · E. Layouts match voxel/pass.rs (`VolumeParams`) and volume.rs (six slabs of
// N + 1 slices, weighted irradiance in rgb and the weight in a). The G-buffer holds f32 bits
// (position, w = 1 where drawn) and f16 pairs (normal, albedo); the pass writes indirect
// radiance as f32 bits. Branch-free after the first test: llvmpipe samples far more slowly
// under divergent control flow.

struct VolumeParams {
    // xyz: the grid's low corner, meters; w: its side, meters.
    origin_size: vec4<f32>,
    // x: cells per axis N; y: slices per slab (N + 1); z: slices in all (6 (N + 1));
    // w: what a texel's value is multiplied by to give irradiance, W/m².
    cells: vec4<f32>,
};

@group(0) @binding(0) var<uniform> params: VolumeParams;
@group(0) @binding(1) var gpos: texture_2d<u32>;
@group(0) @binding(2) var gnrm: texture_2d<u32>;
@group(0) @binding(3) var galb: texture_2d<u32>;
@group(0) @binding(4) var volume: texture_3d<f32>;
@group(0) @binding(5) var volume_sampler: sampler;

@vertex
fn vs_full(@builtin(vertex_index) i: u32) -> @builtin(position) vec4<f32> {
    let uv = vec2<f32>(f32((i << 1u) & 2u), f32(i & 2u));
    return vec4<f32>(uv * 2.0 - 1.0, 0.0, 1.0);
}

// Face `d`'s filtered (weighted irradiance, weight) at grid coordinates `u` in [0, 1]³.
fn face(d: f32, u: vec3<f32>) -> vec4<f32> {
    let z = (d * params.cells.y + u.z * params.cells.x) / params.cells.z;
    return textureSampleLevel(volume, volume_sampler, vec3<f32>(u.xy, z), 0.0);
}

@fragment
fn fs_lookup(@builtin(position) frag: vec4<f32>) -> @location(0) vec4<u32> {
    let px = vec2<i32>(frag.xy);
    let g = bitcast<vec4<f32>>(textureLoad(gpos, px, 0));
    if (g.w < 0.5) {
        return vec4<u32>(0u);
    }
    let nb = textureLoad(gnrm, px, 0).xy;
    let n = vec3<f32>(unpack2x16float(nb.x), unpack2x16float(nb.y).x);
    let u = (g.xyz - params.origin_size.xyz) / params.origin_size.w;
    // One face per axis: +X/-X are slabs 0/1, +Y/-Y 2/3, +Z/-Z 4/5.
    let neg = select(vec3<f32>(0.0), vec3<f32>(1.0), n < vec3<f32>(0.0));
    let fx = face(neg.x, u);
    let fy = face(2.0 + neg.y, u);
    let fz = face(4.0 + neg.z, u);
    let n2 = n * n;
    let has = vec3<f32>(select(0.0, 1.0, fx.a > 1e-4), select(0.0, 1.0, fy.a > 1e-4), select(0.0, 1.0, fz.a > 1e-4));
    let w = n2 * has;
    let e_sum = fx.rgb / max(fx.a, 1e-4) * w.x + fy.rgb / max(fy.a, 1e-4) * w.y + fz.rgb / max(fz.a, 1e-4) * w.z;
    let weight = w.x + w.y + w.z;
    let e = select(vec3<f32>(0.0), e_sum / max(weight, 1e-12), weight > 0.0) * params.cells.w;
    let v = textureLoad(galb, px, 0).xy;
    let albedo = vec3<f32>(unpack2x16float(v.x), unpack2x16float(v.y).x);
    return bitcast<vec4<u32>>(vec4<f32>(albedo / 3.14159265 * max(e, vec3<f32>(0.0)), 1.0));
}
