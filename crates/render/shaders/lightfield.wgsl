// Depth of field by dynamic light-field generation (Yu, Wang, Yu 2010; CPU twin:
// src/lightfield.rs). Per focus: prefilter every source pixel from the Gaussian pyramid;
// then for each chunk of views (z = view): splat the nearest depth with atomicMax, splat the
// largest source index among the sources at that depth with a second atomicMax (together the
// CPU's max over (depth bits, index + 1) keys, exactly, with no quantisation); accumulate the
// views in order with cos^4 weights, widening into empty pixels from their 3 x 3 neighbours.

struct Params {
    w: u32,
    h: u32,
    nv: u32,
    v0: u32,
    focus: f32,
    pupil_m: f32,
    pitch: f32,
    spacing: f32,
    lens_f: f32,
    top: u32,
    nlev: u32,
    // Depth maps per view: 0 when every view warps the one reference depth map (defocus),
    // w * h when each input view has its own (view synthesis, shaders/views.wgsl).
    dstride: u32,
}

@group(0) @binding(0) var<uniform> p: Params;

// PREFILTER and LEVEL_SIGMA come from src/lightfield.rs, prepended by the host.

// prefilter: levels (nlev x 3 planes), depth -> pre (r, g, b, 0)
@group(0) @binding(1) var<storage, read> levels: array<f32>;
@group(0) @binding(2) var<storage, read> pf_depth: array<f32>;
@group(0) @binding(3) var<storage, read_write> pre: array<vec4<f32>>;

fn level_rgb(l: u32, i: u32) -> vec3<f32> {
    let n = p.w * p.h;
    let b = min(l, p.nlev - 1u) * 3u * n + i;
    return vec3<f32>(levels[b], levels[b + n], levels[b + 2u * n]);
}

@compute @workgroup_size(16, 16)
fn prefilter(@builtin(global_invocation_id) g: vec3<u32>) {
    if g.x >= p.w || g.y >= p.h { return; }
    let i = g.y * p.w + g.x;
    let coc = p.pupil_m * abs(pf_depth[i] - p.focus) / p.pitch;
    let sigma = PREFILTER * coc * p.spacing;
    var l = 0u;
    while l < p.top && LEVEL_SIGMA[l + 1u] < sigma { l++; }
    if l == p.top {
        pre[i] = vec4<f32>(level_rgb(l, i), 0.0);
        return;
    }
    let s0 = LEVEL_SIGMA[l];
    let s1 = LEVEL_SIGMA[l + 1u];
    let t = clamp((sigma - s0) / (s1 - s0), 0.0, 1.0);
    pre[i] = vec4<f32>(level_rgb(l, i) * (1.0 - t) + level_rgb(l + 1u, i) * t, 0.0);
}

// views: per view (shift x, shift y, lens x, lens y) in pixels and metres.
@group(0) @binding(1) var<storage, read> sd_depth: array<f32>;
@group(0) @binding(2) var<storage, read> sd_views: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read_write> sd_key: array<atomic<u32>>;

// The target pixel of source pixel `g` in view `v`, or n when it falls outside.
fn target_of(g: vec3<u32>, d: f32, v: vec4<f32>) -> u32 {
    let tx = f32(g.x) + 0.5 + v.x * (d - p.focus);
    let ty = f32(g.y) + 0.5 + v.y * (d - p.focus);
    if tx < 0.0 || ty < 0.0 || tx >= f32(p.w) || ty >= f32(p.h) { return p.w * p.h; }
    return u32(ty) * p.w + u32(tx);
}

@compute @workgroup_size(16, 16)
fn splat_depth(@builtin(global_invocation_id) g: vec3<u32>) {
    if g.x >= p.w || g.y >= p.h || g.z >= p.nv { return; }
    let n = p.w * p.h;
    let d = sd_depth[(p.v0 + g.z) * p.dstride + g.y * p.w + g.x];
    let j = target_of(g, d, sd_views[p.v0 + g.z]);
    if j == n { return; }
    // Depths are >= 0, so their bits order like the floats; +1 keeps 0 for "empty".
    atomicMax(&sd_key[g.z * n + j], bitcast<u32>(d) + 1u);
}

@group(0) @binding(1) var<storage, read> si_depth: array<f32>;
@group(0) @binding(2) var<storage, read> si_views: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read> si_dkey: array<u32>;
@group(0) @binding(4) var<storage, read_write> si_key: array<atomic<u32>>;

@compute @workgroup_size(16, 16)
fn splat_index(@builtin(global_invocation_id) g: vec3<u32>) {
    if g.x >= p.w || g.y >= p.h || g.z >= p.nv { return; }
    let n = p.w * p.h;
    let i = g.y * p.w + g.x;
    let d = si_depth[(p.v0 + g.z) * p.dstride + i];
    let j = target_of(g, d, si_views[p.v0 + g.z]);
    if j == n { return; }
    if si_dkey[g.z * n + j] == bitcast<u32>(d) + 1u {
        atomicMax(&si_key[g.z * n + j], i + 1u);
    }
}

@group(0) @binding(1) var<storage, read> a_dkey: array<u32>;
@group(0) @binding(2) var<storage, read> a_ikey: array<u32>;
@group(0) @binding(3) var<storage, read> a_pre: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read> a_views: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read_write> acc: array<vec4<f32>>;

@compute @workgroup_size(16, 16)
fn accumulate(@builtin(global_invocation_id) g: vec3<u32>) {
    if g.x >= p.w || g.y >= p.h { return; }
    let n = p.w * p.h;
    let j = g.y * p.w + g.x;
    var a = acc[j];
    let px = (f32(g.x) + 0.5 - 0.5 * f32(p.w)) * p.pitch;
    let py = (f32(g.y) + 0.5 - 0.5 * f32(p.h)) * p.pitch;
    for (var v = 0u; v < p.nv; v++) {
        let b = v * n;
        var src = 0u;
        if a_dkey[b + j] != 0u {
            src = a_ikey[b + j];
        } else {
            // Widened write: the farthest (smallest key) exact neighbour fills the crack.
            var bd = 0xffffffffu;
            var bi = 0xffffffffu;
            for (var ny = max(i32(g.y) - 1, 0); ny < min(i32(g.y) + 2, i32(p.h)); ny++) {
                for (var nx = max(i32(g.x) - 1, 0); nx < min(i32(g.x) + 2, i32(p.w)); nx++) {
                    let k = b + u32(ny) * p.w + u32(nx);
                    let kd = a_dkey[k];
                    let ki = a_ikey[k];
                    if kd != 0u && (kd < bd || (kd == bd && ki < bi)) { bd = kd; bi = ki; }
                }
            }
            if bd != 0xffffffffu { src = bi; }
        }
        if src == 0u { continue; } // invalid ray: disoccluded in this view
        let c = a_pre[src - 1u];
        let l = a_views[p.v0 + v];
        let rx = px + l.z / p.lens_f;
        let ry = py + l.w / p.lens_f;
        let c2 = 1.0 / (1.0 + rx * rx + ry * ry);
        let wgt = c2 * c2;
        a += vec4<f32>(wgt * c.xyz, wgt);
    }
    acc[j] = a;
}

@group(0) @binding(1) var<storage, read> f_acc: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> f_color: array<f32>;
@group(0) @binding(3) var<storage, read_write> f_out: array<f32>;

@compute @workgroup_size(16, 16)
fn finish(@builtin(global_invocation_id) g: vec3<u32>) {
    if g.x >= p.w || g.y >= p.h { return; }
    let n = p.w * p.h;
    let j = g.y * p.w + g.x;
    let a = f_acc[j];
    for (var c = 0u; c < 3u; c++) {
        var v = f_color[c * n + j];
        if a.w > 0.0 { v = a[c] / a.w; }
        f_out[c * n + j] = v;
    }
}
