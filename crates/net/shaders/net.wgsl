// The network's operations on the GPU (CPU twin: src/cpu.rs). Tensors between layers are
// CHW at interleaved resolution, so neighbouring invocations read neighbouring addresses;
// only the network's input (before space_to_depth) and output (after depth_to_space) are
// HWC, the layout the host hands over and reads back.

struct Params {
    w: u32,       // interleaved width (full-resolution width / r for s2d, d2s)
    h: u32,
    cin: u32,
    cout: u32,
    act: u32,     // conv: 1 = ELU after the bias
    r: u32,       // interleave rate
    len: u32,     // elementwise: number of values
    stride: u32,  // elementwise: invocations per row of the dispatch grid
}

@group(0) @binding(0) var<uniform> p: Params;

// ---- conv: 3x3 "same" convolution + bias (+ ELU) -------------------------------------------
// A 16 x 16 workgroup computes a 16 x 16 pixel tile for COT output channels (workgroup z picks
// them): each invocation keeps COT accumulators, so every input value loaded into workgroup
// memory feeds 9 * COT multiply-adds. Input channels stream through in chunks of CIC: an
// 18 x 18 halo tile per channel and the chunk's COT x CIC x 9 weights, 12.4 KiB in all.

const TS: u32 = 16u;
const HALO: u32 = 18u;
const COT: u32 = 8u;
const CIC: u32 = 8u;
const TILE: u32 = 324u;  // HALO * HALO

@group(0) @binding(1) var<storage, read> cx: array<f32>;
@group(0) @binding(2) var<storage, read> cw: array<f32>;   // [cout][cin][3][3]
@group(0) @binding(3) var<storage, read> cb: array<f32>;   // [cout]
@group(0) @binding(4) var<storage, read_write> cy: array<f32>;

var<workgroup> tile: array<f32, 2592>;  // CIC * TILE
var<workgroup> wts: array<f32, 576>;    // COT * CIC * 9

@compute @workgroup_size(16, 16)
fn conv(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(local_invocation_id) l: vec3<u32>,
    @builtin(local_invocation_index) li: u32,
) {
    let x0 = i32(wg.x * TS) - 1;
    let y0 = i32(wg.y * TS) - 1;
    let co0 = wg.z * COT;
    var acc: array<f32, 8>;
    for (var k = 0u; k < COT; k++) {
        acc[k] = select(0.0, cb[min(co0 + k, p.cout - 1u)], co0 + k < p.cout);
    }
    for (var c0 = 0u; c0 < p.cin; c0 += CIC) {
        for (var e = li; e < CIC * TILE; e += 256u) {
            let ci = c0 + e / TILE;
            let rem = e % TILE;
            let sx = x0 + i32(rem % HALO);
            let sy = y0 + i32(rem / HALO);
            var v = 0.0;
            if ci < p.cin && sx >= 0 && sy >= 0 && sx < i32(p.w) && sy < i32(p.h) {
                v = cx[(ci * p.h + u32(sy)) * p.w + u32(sx)];
            }
            tile[e] = v;
        }
        for (var e = li; e < COT * CIC * 9u; e += 256u) {
            let co = co0 + e / (CIC * 9u);
            let rem = e % (CIC * 9u);
            let ci = c0 + rem / 9u;
            var v = 0.0;
            if co < p.cout && ci < p.cin {
                v = cw[(co * p.cin + ci) * 9u + rem % 9u];
            }
            wts[e] = v;
        }
        workgroupBarrier();
        let nc = min(CIC, p.cin - c0);
        for (var ci = 0u; ci < nc; ci++) {
            for (var ky = 0u; ky < 3u; ky++) {
                for (var kx = 0u; kx < 3u; kx++) {
                    let v = tile[ci * TILE + (l.y + ky) * HALO + l.x + kx];
                    let t = ci * 9u + ky * 3u + kx;
                    for (var k = 0u; k < COT; k++) {
                        acc[k] += v * wts[k * CIC * 9u + t];
                    }
                }
            }
        }
        workgroupBarrier();
    }
    let x = wg.x * TS + l.x;
    let y = wg.y * TS + l.y;
    if x >= p.w || y >= p.h { return; }
    for (var k = 0u; k < COT; k++) {
        let co = co0 + k;
        if co < p.cout {
            var v = acc[k];
            if p.act == 1u && v < 0.0 {
                v = exp(v) - 1.0;
            }
            cy[(co * p.h + y) * p.w + x] = v;
        }
    }
}

// ---- elementwise: residual add, (tanh x + 1) / 2 -------------------------------------------

@group(0) @binding(1) var<storage, read> ea: array<f32>;
@group(0) @binding(2) var<storage, read> eb: array<f32>;
@group(0) @binding(3) var<storage, read_write> eo: array<f32>;

@compute @workgroup_size(256)
fn add(@builtin(global_invocation_id) g: vec3<u32>) {
    let i = g.y * p.stride + g.x;
    if i >= p.len { return; }
    eo[i] = ea[i] + eb[i];
}

@group(0) @binding(2) var<storage, read_write> to: array<f32>;

@compute @workgroup_size(256)
fn tanh01(@builtin(global_invocation_id) g: vec3<u32>) {
    let i = g.y * p.stride + g.x;
    if i >= p.len { return; }
    // (tanh x + 1) / 2 = 1 / (1 + exp(-2x)): no inf / inf at large |x|.
    to[i] = 1.0 / (1.0 + exp(-2.0 * ea[i]));
}

// ---- interleave --------------------------------------------------------------------------
// Channel c * r^2 + dy * r + dx of the interleaved tensor is channel c at full-resolution
// pixel (r X + dx, r Y + dy) (PyTorch's pixel_unshuffle order, as on the CPU).

@group(0) @binding(2) var<storage, read_write> so: array<f32>;

// s2d: HWC full resolution (cin channels) -> CHW interleaved (cin r^2 channels, h x w);
// z = interleaved channel.
@compute @workgroup_size(16, 16)
fn space_to_depth(@builtin(global_invocation_id) g: vec3<u32>) {
    if g.x >= p.w || g.y >= p.h { return; }
    let rr = p.r * p.r;
    let oc = g.z;
    let ci = oc / rr;
    let dy = (oc % rr) / p.r;
    let dx = oc % p.r;
    let fx = g.x * p.r + dx;
    let fy = g.y * p.r + dy;
    so[(oc * p.h + g.y) * p.w + g.x] = ea[(fy * p.w * p.r + fx) * p.cin + ci];
}

// d2s: CHW interleaved (cout r^2 channels, h x w) -> HWC full resolution (cout channels);
// one invocation per full-resolution pixel.
@compute @workgroup_size(16, 16)
fn depth_to_space(@builtin(global_invocation_id) g: vec3<u32>) {
    let fw = p.w * p.r;
    if g.x >= fw || g.y >= p.h * p.r { return; }
    let rr = p.r * p.r;
    let sx = g.x / p.r;
    let sy = g.y / p.r;
    let ph = (g.y % p.r) * p.r + g.x % p.r;
    for (var c = 0u; c < p.cout; c++) {
        so[(g.y * fw + g.x) * p.cout + c] = ea[((c * rr + ph) * p.h + sy) * p.w + sx];
    }
}
