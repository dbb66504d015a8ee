// Linear blending (CPU twin: linear_blend in src/multifocal.rs): each pixel's colour split
// between the two planes bracketing its depth. Output: plane-major, then channel, planar.

struct Params {
    w: u32,
    h: u32,
    np: u32,
    _pad: u32,
}

@group(0) @binding(0) var<uniform> p: Params;
@group(0) @binding(1) var<storage, read> color: array<f32>;
@group(0) @binding(2) var<storage, read> depth: array<f32>;
@group(0) @binding(3) var<storage, read> planes: array<f32>;
@group(0) @binding(4) var<storage, read_write> out: array<f32>;

@compute @workgroup_size(16, 16)
fn linear_blend(@builtin(global_invocation_id) g: vec3<u32>) {
    if g.x >= p.w || g.y >= p.h { return; }
    let n = p.w * p.h;
    let i = g.y * p.w + g.x;
    let d = depth[i];
    // partition_point(p <= d): planes are strictly increasing.
    var k = 0u;
    while k < p.np && planes[k] <= d { k++; }
    var a = 0u;
    var b = 0u;
    var t = 0.0;
    if k == 0u {
        a = 0u; b = 0u;
    } else if k == p.np {
        a = k - 1u; b = k - 1u;
    } else {
        let p0 = planes[k - 1u];
        let p1 = planes[k];
        a = k - 1u; b = k; t = (d - p0) / (p1 - p0);
    }
    for (var c = 0u; c < 3u; c++) {
        let v = color[c * n + i];
        for (var l = 0u; l < p.np; l++) {
            var o = 0.0;
            if l == a { o += v * (1.0 - t); }
            if l == b { o += v * t; }
            out[(l * 3u + c) * n + i] = o;
        }
    }
}
