// What the eye sees (CPU twins: src/retina.rs, MultifocalRetina in src/multifocal.rs).
// convolve: sum over layers of the layer convolved with its disk PSF, edge-clamped (the CPU
// pads by edge replication before its FFT, which is the same operator); z = focus index.
// shift_add: a light-field display, shift-and-add of the views over the pupil.

struct Params {
    w: u32,
    h: u32,
    nl: u32,
    _pad: u32,
}

@group(0) @binding(0) var<uniform> p: Params;

// layers (nl x 3 planes), kernels (per focus and layer: weight offset, radius), weights
@group(0) @binding(1) var<storage, read> layers: array<f32>;
@group(0) @binding(2) var<storage, read> kinfo: array<vec4<u32>>;
@group(0) @binding(3) var<storage, read> weights: array<f32>;
@group(0) @binding(4) var<storage, read_write> c_out: array<f32>;

@compute @workgroup_size(16, 16)
fn convolve(@builtin(global_invocation_id) g: vec3<u32>) {
    if g.x >= p.w || g.y >= p.h { return; }
    let n = p.w * p.h;
    let f = g.z;
    var acc = vec3<f32>(0.0);
    for (var l = 0u; l < p.nl; l++) {
        let ki = kinfo[f * p.nl + l];
        let r = i32(ki.y);
        let side = 2 * r + 1;
        let base = l * 3u * n;
        for (var dy = -r; dy <= r; dy++) {
            let yi = u32(clamp(i32(g.y) - dy, 0, i32(p.h) - 1));
            for (var dx = -r; dx <= r; dx++) {
                let wgt = weights[ki.x + u32((dy + r) * side + dx + r)];
                let xi = u32(clamp(i32(g.x) - dx, 0, i32(p.w) - 1));
                let j = base + yi * p.w + xi;
                acc += wgt * vec3<f32>(layers[j], layers[n + j], layers[2u * n + j]);
            }
        }
    }
    let o = f * 3u * n + g.y * p.w + g.x;
    c_out[o] = acc.x;
    c_out[n + o] = acc.y;
    c_out[2u * n + o] = acc.z;
}

// views (nl x 3 planes), per view (shift x, shift y, weight / total, 0); accumulates into
// s_out so batches of views add up in the CPU's order.
@group(0) @binding(1) var<storage, read> views: array<f32>;
@group(0) @binding(2) var<storage, read> vparam: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read_write> s_out: array<f32>;

fn bilinear(base: u32, x: f32, y: f32) -> f32 {
    let t = bilinear_taps(base, x, y, p.w, p.h);
    return bilinear_mix(t, views[t.i00], views[t.i10], views[t.i01], views[t.i11]);
}

@compute @workgroup_size(16, 16)
fn shift_add(@builtin(global_invocation_id) g: vec3<u32>) {
    if g.x >= p.w || g.y >= p.h { return; }
    let n = p.w * p.h;
    let i = g.y * p.w + g.x;
    var acc = vec3<f32>(s_out[i], s_out[n + i], s_out[2u * n + i]);
    let x = f32(g.x) + 0.5;
    let y = f32(g.y) + 0.5;
    for (var v = 0u; v < p.nl; v++) {
        let q = vparam[v];
        let base = v * 3u * n;
        acc.x += q.z * bilinear(base, x - q.x, y - q.y);
        acc.y += q.z * bilinear(base + n, x - q.x, y - q.y);
        acc.z += q.z * bilinear(base + 2u * n, x - q.x, y - q.y);
    }
    s_out[i] = acc.x;
    s_out[n + i] = acc.y;
    s_out[2u * n + i] = acc.z;
}
