// Shadow pass: depth of the scene from one shadow view (one layer of the shadow array).
// `View` is one 256-byte slot of the views buffer (raster/shadow.rs), bound with a dynamic
// offset.

struct View {
    clip_from_world: mat4x4<f32>,
};

@group(0) @binding(0) var<uniform> view: View;

@vertex
fn vs_main(@location(0) position: vec3<f32>) -> @builtin(position) vec4<f32> {
    return view.clip_from_world * vec4<f32>(position, 1.0);
}
