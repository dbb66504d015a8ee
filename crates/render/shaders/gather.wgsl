// Gather blur driven by the circle of confusion (CPU twin: src/gather.rs).
// prep: radius per pixel and a packed (r, g, b, radius) texel; max_h / max_v: the separable
// max filter bounding every tap; gather: the per-pixel sum over offsets sorted by distance.

struct Params {
    w: u32,
    h: u32,
    n_off: u32,
    reach: u32,
    focus: f32,
    pupil_m: f32,
    pitch: f32,
    _pad: u32,
}

@group(0) @binding(0) var<uniform> p: Params;

// prep: color (3 planes), depth -> packed (vec4), radius
@group(0) @binding(1) var<storage, read> ro0: array<f32>;
@group(0) @binding(2) var<storage, read> ro1: array<f32>;
@group(0) @binding(3) var<storage, read_write> rw0: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read_write> rw1: array<f32>;

@compute @workgroup_size(16, 16)
fn prep(@builtin(global_invocation_id) g: vec3<u32>) {
    if g.x >= p.w || g.y >= p.h { return; }
    let n = p.w * p.h;
    let i = g.y * p.w + g.x;
    let r = 0.5 * (p.pupil_m * abs(ro1[i] - p.focus) / p.pitch);
    rw0[i] = vec4<f32>(ro0[i], ro0[n + i], ro0[2u * n + i], r);
    rw1[i] = r;
}

// max_h / max_v: maximum over the (2 reach + 1) window along a row / a column.
@group(0) @binding(1) var<storage, read> m_src: array<f32>;
@group(0) @binding(2) var<storage, read_write> m_dst: array<f32>;

@compute @workgroup_size(16, 16)
fn max_h(@builtin(global_invocation_id) g: vec3<u32>) {
    if g.x >= p.w || g.y >= p.h { return; }
    let lo = select(0u, g.x - p.reach, g.x >= p.reach);
    let hi = min(g.x + p.reach + 1u, p.w);
    var m = 0.0;
    for (var x = lo; x < hi; x++) { m = max(m, m_src[g.y * p.w + x]); }
    m_dst[g.y * p.w + g.x] = m;
}

@compute @workgroup_size(16, 16)
fn max_v(@builtin(global_invocation_id) g: vec3<u32>) {
    if g.x >= p.w || g.y >= p.h { return; }
    let lo = select(0u, g.y - p.reach, g.y >= p.reach);
    let hi = min(g.y + p.reach + 1u, p.h);
    var m = 0.0;
    for (var y = lo; y < hi; y++) { m = max(m, m_src[y * p.w + g.x]); }
    m_dst[g.y * p.w + g.x] = m;
}

// gather: packed texels, depth, local max radius, offsets (dx, dy, distance) nearest first.
@group(0) @binding(1) var<storage, read> g_tex: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> g_depth: array<f32>;
@group(0) @binding(3) var<storage, read> g_max: array<f32>;
@group(0) @binding(4) var<storage, read> g_off: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read_write> g_out: array<f32>;

@compute @workgroup_size(16, 16)
fn gather(@builtin(global_invocation_id) g: vec3<u32>) {
    if g.x >= p.w || g.y >= p.h { return; }
    let n = p.w * p.h;
    let i = g.y * p.w + g.x;
    let dc = g_depth[i];
    let rc = g_tex[i].w;
    let limit = g_max[i] + 0.5;
    var acc = vec3<f32>(0.0);
    var wsum = 0.0;
    for (var k = 0u; k < p.n_off; k++) {
        let o = g_off[k];
        // Offsets are sorted by distance: none further on can reach this pixel.
        if o.z > limit { break; }
        let sx = i32(g.x) + i32(o.x);
        let sy = i32(g.y) + i32(o.y);
        if sx < 0 || sy < 0 || sx >= i32(p.w) || sy >= i32(p.h) { continue; }
        let j = u32(sy) * p.w + u32(sx);
        let t = g_tex[j];
        var r = t.w;
        if g_depth[j] < dc { r = min(r, rc); }
        let cover = clamp(r + 0.5 - o.z, 0.0, 1.0);
        if cover > 0.0 {
            let rr = max(r, 0.5);
            let wgt = cover / (rr * rr);
            acc += wgt * t.xyz;
            wsum += wgt;
        }
    }
    let c = acc / wsum;
    g_out[i] = c.x;
    g_out[n + i] = c.y;
    g_out[2u * n + i] = c.z;
}
