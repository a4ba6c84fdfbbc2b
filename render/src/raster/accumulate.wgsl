// A still view's accumulation: the mean of its jittered frames, image by image (f32 bits in
// and out). Frame n (0 starts it) blends its pixel, clamped per channel to the range of the
// mean so far over the pixel and its four neighbours, into that mean with weight 1 / (n + 1);
// w (each frame's own w: the compose pass's is 1 where a surface was drawn, else 0) becomes
// the share of the frames whose sample saw a surface.

struct Params {
    // x: frames already in the mean (0: this frame starts it).
    frames: vec4<u32>,
};

@group(0) @binding(0) var fresh: texture_2d<u32>;
@group(0) @binding(1) var history: texture_2d<u32>;
@group(0) @binding(2) var<uniform> params: Params;

@vertex
fn vs_main(@builtin(vertex_index) i: u32) -> @builtin(position) vec4<f32> {
    // One triangle covering the screen.
    let uv = vec2<f32>(f32((i << 1u) & 2u), f32(i & 2u));
    return vec4<f32>(uv * 2.0 - 1.0, 0.0, 1.0);
}

fn at(t: texture_2d<u32>, px: vec2<i32>) -> vec4<f32> {
    return bitcast<vec4<f32>>(textureLoad(t, px, 0));
}

@fragment
fn fs_main(@builtin(position) frag: vec4<f32>) -> @location(0) vec4<u32> {
    let px = vec2<i32>(frag.xy);
    let sample = at(fresh, px);
    let n = params.frames.x;
    if (n == 0u) {
        return bitcast<vec4<u32>>(sample);
    }
    // The pixel and its four neighbours: at 640×360 on lavapipe the pass takes 2.9–4.8 ms
    // (a 3 × 3 window: 4.8–6.6 ms; the compose pass 1.5–3.1 ms).
    let last = vec2<i32>(textureDimensions(history)) - vec2<i32>(1);
    let mean = at(history, px);
    var lo = mean.rgb;
    var hi = mean.rgb;
    for (var k = 0; k < 4; k = k + 1) {
        let d = select(vec2<i32>(0, 2 * (k & 1) - 1), vec2<i32>(2 * (k & 1) - 1, 0), k < 2);
        let h = at(history, clamp(px + d, vec2<i32>(0), last)).rgb;
        lo = min(lo, h);
        hi = max(hi, h);
    }
    let w = 1.0 / f32(n + 1u);
    let blended = mix(mean, vec4<f32>(clamp(sample.rgb, lo, hi), sample.w), w);
    return bitcast<vec4<u32>>(blended);
}
