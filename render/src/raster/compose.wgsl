// Compose pass: the frame's radiance, direct + the technique's indirect (f32 bits in and out).

@group(0) @binding(0) var direct: texture_2d<u32>;
@group(0) @binding(1) var indirect: texture_2d<u32>;

@vertex
fn vs_main(@builtin(vertex_index) i: u32) -> @builtin(position) vec4<f32> {
    // One triangle covering the screen.
    let uv = vec2<f32>(f32((i << 1u) & 2u), f32(i & 2u));
    return vec4<f32>(uv * 2.0 - 1.0, 0.0, 1.0);
}

@fragment
fn fs_main(@builtin(position) frag: vec4<f32>) -> @location(0) vec4<u32> {
    let px = vec2<i32>(frag.xy);
    let d = bitcast<vec4<f32>>(textureLoad(direct, px, 0));
    let i = bitcast<vec4<f32>>(textureLoad(indirect, px, 0));
    // w: 1 where a surface was drawn (the direct pass's w), else 0.
    return bitcast<vec4<u32>>(vec4<f32>(d.rgb + i.rgb, d.w));
}
