// Separable convolution with edge clamping (CPU twin: separable_blur in src/kernel.rs),
// taps applied in the same order; z = plane index.

struct Params {
    w: u32,
    h: u32,
    ntaps: u32,
    _pad: u32,
}

@group(0) @binding(0) var<uniform> p: Params;
@group(0) @binding(1) var<storage, read> src: array<f32>;
@group(0) @binding(2) var<storage, read> taps: array<f32>;
@group(0) @binding(3) var<storage, read_write> dst: array<f32>;

@compute @workgroup_size(16, 16)
fn blur_h(@builtin(global_invocation_id) g: vec3<u32>) {
    if g.x >= p.w || g.y >= p.h { return; }
    let row = g.z * p.w * p.h + g.y * p.w;
    let r = i32(p.ntaps / 2u);
    var acc = 0.0;
    for (var k = 0; k < i32(p.ntaps); k++) {
        let x = u32(clamp(i32(g.x) + k - r, 0, i32(p.w) - 1));
        acc += taps[k] * src[row + x];
    }
    dst[row + g.x] = acc;
}

@compute @workgroup_size(16, 16)
fn blur_v(@builtin(global_invocation_id) g: vec3<u32>) {
    if g.x >= p.w || g.y >= p.h { return; }
    let base = g.z * p.w * p.h;
    let r = i32(p.ntaps / 2u);
    var acc = 0.0;
    for (var k = 0; k < i32(p.ntaps); k++) {
        let y = u32(clamp(i32(g.y) + k - r, 0, i32(p.h) - 1));
        acc += taps[k] * src[base + y * p.w + g.x];
    }
    dst[base + g.y * p.w + g.x] = acc;
}
