// PSNR and SSIM reductions on sRGB-encoded values (CPU twin: src/metrics.rs). Each workgroup
// writes one partial sum; the host adds the partials in f64.

struct Params {
    w: u32,
    h: u32,
    _a: u32,
    _b: u32,
}

@group(0) @binding(0) var<uniform> p: Params;

fn encode(v: f32) -> f32 {
    var x = clamp(v, 0.0, 1.0);
    if v != v { x = 0.0; }
    if x <= 0.0031308 { return x * 12.92; }
    return 1.055 * pow(x, 1.0 / 2.4) - 0.055;
}

var<workgroup> part: array<f32, WG1>;

fn reduce(l: u32, v: f32) -> f32 {
    part[l] = v;
    workgroupBarrier();
    for (var s = WG1 / 2u; s > 0u; s >>= 1u) {
        if l < s { part[l] += part[l + s]; }
        workgroupBarrier();
    }
    return part[0];
}

// psnr_sum: a, b (3 planes each), mask (1 plane) -> partial squared errors
@group(0) @binding(1) var<storage, read> pa: array<f32>;
@group(0) @binding(2) var<storage, read> pb: array<f32>;
@group(0) @binding(3) var<storage, read> pmask: array<f32>;
@group(0) @binding(4) var<storage, read_write> p_out: array<f32>;

@compute @workgroup_size(WG1)
fn psnr_sum(@builtin(global_invocation_id) g: vec3<u32>, @builtin(local_invocation_index) l: u32,
            @builtin(workgroup_id) wg: vec3<u32>) {
    let n = p.w * p.h;
    let i = g.x;
    var s = 0.0;
    if i < n && pmask[i] > 0.5 {
        for (var c = 0u; c < 3u; c++) {
            let d = encode(pa[c * n + i]) - encode(pb[c * n + i]);
            s += d * d;
        }
    }
    let t = reduce(l, s);
    if l == 0u { p_out[wg.x] = t; }
}

// ssim_prep: a, b -> per channel c, planes 5c..5c+4: x, y, x^2, y^2, xy
@group(0) @binding(1) var<storage, read> sa: array<f32>;
@group(0) @binding(2) var<storage, read> sb: array<f32>;
@group(0) @binding(3) var<storage, read_write> s_q: array<f32>;

@compute @workgroup_size(16, 16)
fn ssim_prep(@builtin(global_invocation_id) g: vec3<u32>) {
    if g.x >= p.w || g.y >= p.h { return; }
    let n = p.w * p.h;
    let i = g.y * p.w + g.x;
    for (var c = 0u; c < 3u; c++) {
        let x = encode(sa[c * n + i]);
        let y = encode(sb[c * n + i]);
        let o = 5u * c * n + i;
        s_q[o] = x;
        s_q[o + n] = y;
        s_q[o + 2u * n] = x * x;
        s_q[o + 3u * n] = y * y;
        s_q[o + 4u * n] = x * y;
    }
}

// ssim_sum: blurred quantities (15 planes), mask -> partial SSIM sums
@group(0) @binding(1) var<storage, read> m_q: array<f32>;
@group(0) @binding(2) var<storage, read> m_mask: array<f32>;
@group(0) @binding(3) var<storage, read_write> m_out: array<f32>;

@compute @workgroup_size(WG1)
fn ssim_sum(@builtin(global_invocation_id) g: vec3<u32>, @builtin(local_invocation_index) l: u32,
            @builtin(workgroup_id) wg: vec3<u32>) {
    let n = p.w * p.h;
    let i = g.x;
    let c1 = 0.01 * 0.01;
    let c2 = 0.03 * 0.03;
    var s = 0.0;
    if i < n && m_mask[i] > 0.5 {
        for (var c = 0u; c < 3u; c++) {
            let o = 5u * c * n + i;
            let ux = m_q[o];
            let uy = m_q[o + n];
            let vx = m_q[o + 2u * n] - ux * ux;
            let vy = m_q[o + 3u * n] - uy * uy;
            let cov = m_q[o + 4u * n] - ux * uy;
            s += ((2.0 * ux * uy + c1) * (2.0 * cov + c2)) / ((ux * ux + uy * uy + c1) * (vx + vy + c2));
        }
    }
    let t = reduce(l, s);
    if l == 0u { m_out[wg.x] = t; }
}
