// Optimized blending (Narain et al. 2015; CPU twin: optimized_blend in src/multifocal.rs):
// FISTA on the padded grid, where the CPU's FFT products are circular convolutions. Direct
// convolution here: the disks are at most a few tens of taps across for the default planes and
// focal range, where a direct sum beats two FFTs per layer and channel on a GPU.
// residual: r_j = sum_i k_ij (*) y_i - t_j (z = focal sample j)
// step:     x_i' = clamp(y_i - step sum_j k_ij (*) r_j, 0, 1); y_i = x_i' + mom (x_i' - x_i)
// sq_sum:   partial sums of r^2 for the reported RMS retinal error.

struct Params {
    pw: u32,
    ph: u32,
    np: u32,
    nf: u32,
    step: f32,
    mom: f32,
    len: u32,
    _pad: u32,
}

@group(0) @binding(0) var<uniform> p: Params;

@group(0) @binding(1) var<storage, read> r_y: array<f32>;
@group(0) @binding(2) var<storage, read> r_t: array<f32>;
@group(0) @binding(3) var<storage, read> r_kinfo: array<vec4<u32>>;
@group(0) @binding(4) var<storage, read> r_w: array<f32>;
@group(0) @binding(5) var<storage, read_write> r_out: array<f32>;

@compute @workgroup_size(16, 16)
fn residual(@builtin(global_invocation_id) g: vec3<u32>) {
    if g.x >= p.pw || g.y >= p.ph { return; }
    let n = p.pw * p.ph;
    let j = g.z;
    var acc = vec3<f32>(0.0);
    for (var i = 0u; i < p.np; i++) {
        let ki = r_kinfo[j * p.np + i];
        let r = i32(ki.y);
        let side = 2 * r + 1;
        let base = i * 3u * n;
        for (var dy = -r; dy <= r; dy++) {
            let yi = u32((i32(g.y) - dy + i32(p.ph)) % i32(p.ph));
            for (var dx = -r; dx <= r; dx++) {
                let wgt = r_w[ki.x + u32((dy + r) * side + dx + r)];
                let xi = u32((i32(g.x) - dx + i32(p.pw)) % i32(p.pw));
                let s = base + yi * p.pw + xi;
                acc += wgt * vec3<f32>(r_y[s], r_y[s + n], r_y[s + 2u * n]);
            }
        }
    }
    let o = j * 3u * n + g.y * p.pw + g.x;
    r_out[o] = acc.x - r_t[o];
    r_out[o + n] = acc.y - r_t[o + n];
    r_out[o + 2u * n] = acc.z - r_t[o + 2u * n];
}

@group(0) @binding(1) var<storage, read> s_r: array<f32>;
@group(0) @binding(2) var<storage, read> s_kinfo: array<vec4<u32>>;
@group(0) @binding(3) var<storage, read> s_w: array<f32>;
@group(0) @binding(4) var<storage, read_write> s_x: array<f32>;
@group(0) @binding(5) var<storage, read_write> s_y: array<f32>;

@compute @workgroup_size(16, 16)
fn step(@builtin(global_invocation_id) g: vec3<u32>) {
    if g.x >= p.pw || g.y >= p.ph { return; }
    let n = p.pw * p.ph;
    let i = g.z;
    var grad = vec3<f32>(0.0);
    for (var j = 0u; j < p.nf; j++) {
        let ki = s_kinfo[j * p.np + i];
        let r = i32(ki.y);
        let side = 2 * r + 1;
        let base = j * 3u * n;
        // The disks are symmetric: the adjoint is the same convolution.
        for (var dy = -r; dy <= r; dy++) {
            let yi = u32((i32(g.y) - dy + i32(p.ph)) % i32(p.ph));
            for (var dx = -r; dx <= r; dx++) {
                let wgt = s_w[ki.x + u32((dy + r) * side + dx + r)];
                let xi = u32((i32(g.x) - dx + i32(p.pw)) % i32(p.pw));
                let s = base + yi * p.pw + xi;
                grad += wgt * vec3<f32>(s_r[s], s_r[s + n], s_r[s + 2u * n]);
            }
        }
    }
    let o = i * 3u * n + g.y * p.pw + g.x;
    for (var c = 0u; c < 3u; c++) {
        let k = o + c * n;
        let nw = clamp(s_y[k] - p.step * grad[c], 0.0, 1.0);
        s_y[k] = nw + p.mom * (nw - s_x[k]);
        s_x[k] = nw;
    }
}

var<workgroup> part: array<f32, WG1>;

@group(0) @binding(1) var<storage, read> q_r: array<f32>;
@group(0) @binding(2) var<storage, read_write> q_out: array<f32>;

@compute @workgroup_size(WG1)
fn sq_sum(@builtin(global_invocation_id) g: vec3<u32>, @builtin(local_invocation_index) l: u32,
          @builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nw: vec3<u32>) {
    let i = (wg.y * nw.x + wg.x) * WG1 + l;
    var s = 0.0;
    if i < p.len { s = q_r[i] * q_r[i]; }
    part[l] = s;
    workgroupBarrier();
    for (var k = WG1 / 2u; k > 0u; k >>= 1u) {
        if l < k { part[l] += part[l + k]; }
        workgroupBarrier();
    }
    if l == 0u { q_out[wg.y * nw.x + wg.x] = part[0]; }
}
