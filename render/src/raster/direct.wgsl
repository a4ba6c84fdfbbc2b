// Direct lighting from a G-buffer with shadow maps: point (six cube faces), spot and
// directional lights. Layouts match raster/shadow.rs (`LightGpu`, `Params`); the G-buffer
// and the output hold f32 bits (position, radiance) and f16 pairs (normal, albedo).

struct LightGpu {
    // xyz: position (m); w: kind (0 point, 1 spot, 2 directional, 3 surface sample).
    position: vec4<f32>,
    // xyz: unit direction (spot axis / travel of sunlight / emitter normal); w: cosine of the
    // spot cone.
    direction: vec4<f32>,
    // rgb: intensity (W/sr) or irradiance (W/m²); w: index of the light's first shadow view.
    intensity: vec4<f32>,
};

struct ShadowView {
    clip_from_world: mat4x4<f32>,
};

struct Params {
    light_count: u32,
    depth_bias: f32,
    normal_offset_m: f32,
    pad: f32,
};

@group(0) @binding(0) var gpos: texture_2d<u32>;
@group(0) @binding(1) var gnrm: texture_2d<u32>;
@group(0) @binding(2) var galb: texture_2d<u32>;
@group(0) @binding(3) var shadow_maps: texture_depth_2d_array;
@group(0) @binding(4) var shadow_sampler: sampler_comparison;
@group(0) @binding(5) var<storage, read> lights: array<LightGpu>;
@group(0) @binding(6) var<storage, read> views: array<ShadowView>;
@group(0) @binding(7) var<uniform> params: Params;

@vertex
fn vs_main(@builtin(vertex_index) i: u32) -> @builtin(position) vec4<f32> {
    // One triangle covering the screen.
    let uv = vec2<f32>(f32((i << 1u) & 2u), f32(i & 2u));
    return vec4<f32>(uv * 2.0 - 1.0, 0.0, 1.0);
}

fn cube_face(d: vec3<f32>) -> u32 {
    let a = abs(d);
    if (a.x >= a.y && a.x >= a.z) {
        return select(1u, 0u, d.x > 0.0);
    }
    if (a.y >= a.z) {
        return select(3u, 2u, d.y > 0.0);
    }
    return select(5u, 4u, d.z > 0.0);
}

fn visibility(view_index: u32, p: vec3<f32>) -> f32 {
    let clip = views[view_index].clip_from_world * vec4<f32>(p, 1.0);
    if (clip.w <= 0.0) {
        return 1.0;
    }
    let ndc = clip.xyz / clip.w;
    if (any(abs(ndc.xy) > vec2<f32>(1.0)) || ndc.z > 1.0) {
        return 1.0;
    }
    let uv = vec2<f32>(ndc.x * 0.5 + 0.5, 0.5 - ndc.y * 0.5);
    return textureSampleCompareLevel(shadow_maps, shadow_sampler, uv, i32(view_index), ndc.z - params.depth_bias);
}

@fragment
fn fs_main(@builtin(position) frag: vec4<f32>) -> @location(0) vec4<u32> {
    let px = vec2<i32>(frag.xy);
    let g = bitcast<vec4<f32>>(textureLoad(gpos, px, 0));
    if (g.w < 0.5) {
        return vec4<u32>(0u);
    }
    let gn = textureLoad(gnrm, px, 0).xy;
    let n = normalize(vec3<f32>(unpack2x16float(gn.x), unpack2x16float(gn.y).x));
    let ga = textureLoad(galb, px, 0).xy;
    let albedo = vec3<f32>(unpack2x16float(ga.x), unpack2x16float(ga.y).x);
    let p = g.xyz + n * params.normal_offset_m;
    var e = vec3<f32>(0.0);
    for (var k = 0u; k < params.light_count; k = k + 1u) {
        let l = lights[k];
        let kind = u32(l.position.w);
        let first = u32(l.intensity.w);
        if (kind == 2u) {
            let w = -l.direction.xyz;
            let c = dot(n, w);
            if (c > 0.0) {
                e += l.intensity.rgb * c * visibility(first, p);
            }
            continue;
        }
        let to = l.position.xyz - g.xyz;
        let dist2 = dot(to, to);
        let w = to / sqrt(dist2);
        let c = dot(n, w);
        if (c <= 0.0) {
            continue;
        }
        var view = first;
        var falloff = 1.0;
        if (kind == 0u || kind == 3u) {
            view = first + cube_face(-w);
            if (kind == 3u) {
                // Lambertian emitter: intensity × cosine at the light, nothing behind it.
                falloff = max(dot(-w, l.direction.xyz), 0.0);
            }
        } else if (dot(-w, l.direction.xyz) < l.direction.w) {
            continue;
        }
        e += l.intensity.rgb * falloff * c / dist2 * visibility(view, p);
    }
    return bitcast<vec4<u32>>(vec4<f32>(albedo / 3.14159265 * e, 1.0));
}
