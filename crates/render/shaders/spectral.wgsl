// The spectral multifocal decomposition on the GPU (CPU twin: src/spectral.rs with the FFTs of
// src/fft2.rs). The CPU's padded grid, half spectra and per-frequency matrices exactly; its
// real FFTs become complex Stockham FFTs (mixed radix 2, 3, 4, 5, one dispatch per pass) with
// two real images packed into one complex one.
//
// pad:           images (any layout) -> padded real images, edges replicated
// slices:        RGB-D -> the depth slices of the colour on the padded grid
// pack:          real images -> complex rows, two images a complex image
// fft_pass:      one Stockham pass along contiguous lines (radix `radix`, `ns` done before)
// rows_to_half:  complex row spectra -> each real image's half spectrum (column-major)
// half_to_rows:  half spectra (columns inverted) -> complex rows of two images, scaled
// rows_to_real:  complex rows -> real images, clamped to [0, 1]; the FISTA update with them
// apply:         per frequency, out[c][a] (+)= scale sum_d mat[a][d] in[c][d]
// grad_step:     per frequency, S <- S - step A (S - Y0); partial sums of the objective
// admm_step:     per frequency, S <- Y0 + B (S - Y0) (B = rho (A + rho I)^-1); the objective too
// admm_update:   per pixel, z = clamp(x + u), u = x + u - z, v = z - u (the next step's input)

struct Params {
    // Line length (fft_pass) or frequencies per spectrum (apply, grad_step).
    n: u32,
    // Lines in the batch (fft_pass); work items (pad).
    lines: u32,
    // Stockham: product of the radices of the passes before this one.
    ns: u32,
    radix: u32,
    // This length's roots in the twiddle table.
    tw_off: u32,
    // 1: the inverse transform (conjugate roots).
    inverse: u32,
    pw: u32,
    ph: u32,
    hw: u32,
    // Real images in the batch.
    count: u32,
    w: u32,
    h: u32,
    margin: u32,
    // apply: output rows (layers); pad: images in the source; grad_step: layers.
    rows: u32,
    // apply: input columns; pad and slices: images per colour channel in the destination.
    cols: u32,
    // apply: first input image; pad: first source value.
    off: u32,
    row_pitch: u32,
    plane_pitch: u32,
    // pad: first destination image; pad: from one source image to the next (img_pitch).
    dst: u32,
    img_pitch: u32,
    scale: f32,
    step: f32,
    mom: f32,
    // apply: 1 adds to out; rows_to_real: 1 clamps.
    flag: u32,
}

@group(0) @binding(0) var<uniform> p: Params;

// A flat index over a 2-D grid of WG1-wide workgroups (more than 65535 groups).
fn flat_index(wg: vec3<u32>, nw: vec3<u32>, l: u32) -> u32 {
    return (wg.y * nw.x + wg.x) * WG1 + l;
}

fn cmul(a: vec2<f32>, b: vec2<f32>) -> vec2<f32> {
    return vec2<f32>(a.x * b.x - a.y * b.y, a.x * b.y + a.y * b.x);
}

fn conj(a: vec2<f32>) -> vec2<f32> {
    return vec2<f32>(a.x, -a.y);
}

// The source pixel of a padded-grid pixel: the image `margin` in, edges replicated.
fn source(q: u32) -> u32 {
    let x = clamp(i32(q % p.pw) - i32(p.margin), 0, i32(p.w) - 1);
    let y = clamp(i32(q / p.pw) - i32(p.margin), 0, i32(p.h) - 1);
    return u32(y) * p.row_pitch + u32(x);
}

@group(0) @binding(1) var<storage, read> pad_src: array<f32>;
@group(0) @binding(2) var<storage, read_write> pad_dst: array<f32>;

// `rows` images of 3 planes from `off` (image k at off + k img_pitch, planes plane_pitch
// apart, rows row_pitch apart) to destination image dst + k + c cols.
@compute @workgroup_size(WG1)
fn pad(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nw: vec3<u32>,
       @builtin(local_invocation_index) l: u32) {
    let i = flat_index(wg, nw, l);
    let pn = p.pw * p.ph;
    if i >= p.rows * 3u * pn { return; }
    let q = i % pn;
    let c = (i / pn) % 3u;
    let k = i / (3u * pn);
    let s = p.off + k * p.img_pitch + c * p.plane_pitch + source(q);
    pad_dst[(p.dst + k + c * p.cols) * pn + q] = pad_src[s];
}

@group(0) @binding(1) var<storage, read> sl_color: array<f32>;
@group(0) @binding(2) var<storage, read> sl_depth: array<f32>;
@group(0) @binding(3) var<storage, read> sl_nodes: array<f32>;
@group(0) @binding(4) var<storage, read_write> sl_dst: array<f32>;

// Slice c nd + d: the colour's channel c times the tent weight of node d at the pixel's depth
// (`cols` nodes, increasing; outside them, all on the nearest end).
@compute @workgroup_size(WG1)
fn slices(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nw: vec3<u32>,
          @builtin(local_invocation_index) l: u32) {
    let q = flat_index(wg, nw, l);
    let pn = p.pw * p.ph;
    if q >= pn { return; }
    let s = source(q);
    let x = sl_depth[s];
    let nd = p.cols;
    var k = 0u;
    while k < nd && sl_nodes[k] <= x { k++; }
    var a = 0u;
    var b = 0u;
    var t = 0.0;
    if k == nd {
        a = nd - 1u;
        b = nd - 1u;
    } else if k > 0u {
        let n0 = sl_nodes[k - 1u];
        let n1 = sl_nodes[k];
        a = k - 1u;
        b = k;
        t = (x - n0) / (n1 - n0);
    }
    let plane = p.w * p.h;
    for (var c = 0u; c < 3u; c++) {
        let v = sl_color[c * plane + s];
        for (var d = 0u; d < nd; d++) {
            var wt = 0.0;
            if a == d { wt = 1.0 - t; }
            if b == d { wt += t; }
            sl_dst[(c * nd + d) * pn + q] = wt * v;
        }
    }
}

@group(0) @binding(1) var<storage, read> pk_src: array<f32>;
@group(0) @binding(2) var<storage, read_write> pk_dst: array<vec2<f32>>;

// Complex image k: real image 2k + i real image 2k + 1 (zero past the batch).
@compute @workgroup_size(WG1)
fn pack(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nw: vec3<u32>,
        @builtin(local_invocation_index) l: u32) {
    let i = flat_index(wg, nw, l);
    let pn = p.pw * p.ph;
    let pairs = (p.count + 1u) / 2u;
    if i >= pairs * pn { return; }
    let k = i / pn;
    let q = i % pn;
    var b = 0.0;
    if 2u * k + 1u < p.count { b = pk_src[(2u * k + 1u) * pn + q]; }
    pk_dst[i] = vec2<f32>(pk_src[2u * k * pn + q], b);
}

@group(0) @binding(1) var<storage, read> ff_src: array<vec2<f32>>;
@group(0) @binding(2) var<storage, read> ff_tw: array<vec2<f32>>;
@group(0) @binding(3) var<storage, read_write> ff_dst: array<vec2<f32>>;

// w^k = exp(-2 pi i k / n) from the table (computed on the host in f64); conjugated inverse.
fn root(k: u32) -> vec2<f32> {
    let w = ff_tw[p.tw_off + k];
    if p.inverse == 1u { return conj(w); }
    return w;
}

// Multiplies by the forward transform's i^-1 (-i), or by i for the inverse.
fn rot(a: vec2<f32>) -> vec2<f32> {
    if p.inverse == 1u { return vec2<f32>(-a.y, a.x); }
    return vec2<f32>(a.y, -a.x);
}

// The radix-3 and radix-5 butterflies' constants: sin(2 pi / 3), cos and sin of 2 pi / 5 and
// 4 pi / 5.
const SIN3: f32 = 0.8660254037844386;
const COS5A: f32 = 0.30901699437494745;
const COS5B: f32 = -0.8090169943749475;
const SIN5A: f32 = 0.9510565162951535;
const SIN5B: f32 = 0.5877852522924731;

// One Stockham autosort pass (Govindaraju et al. 2008): butterfly j of n / radix reads
// src[j + r n / radix], twiddles by w^(r (j mod ns) n / (ns radix)), takes the radix-point DFT
// and writes dst[(j / ns) ns radix + j mod ns + r ns]. After every pass, natural order. The
// butterflies are written out per radix (the host's radices: 4 and the grid's primes), so
// nothing is indexed dynamically.
@compute @workgroup_size(WG1)
fn fft_pass(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nw: vec3<u32>,
            @builtin(local_invocation_index) l: u32) {
    let i = flat_index(wg, nw, l);
    let m = p.n / p.radix;
    if i >= p.lines * m { return; }
    let base = (i / m) * p.n;
    let j = i % m;
    let k = j % p.ns;
    // Input r is twiddled by root r t (below n).
    let t = k * (p.n / (p.ns * p.radix));
    let src = base + j;
    let d = base + (j / p.ns) * p.ns * p.radix + k;
    let s = p.ns;
    let a0 = ff_src[src];
    let a1 = cmul(ff_src[src + m], root(t));
    switch p.radix {
        case 2u: {
            ff_dst[d] = a0 + a1;
            ff_dst[d + s] = a0 - a1;
        }
        case 3u: {
            let a2 = cmul(ff_src[src + 2u * m], root(2u * t));
            let t1 = a1 + a2;
            let b = a0 - 0.5 * t1;
            let r = SIN3 * rot(a1 - a2);
            ff_dst[d] = a0 + t1;
            ff_dst[d + s] = b + r;
            ff_dst[d + 2u * s] = b - r;
        }
        case 4u: {
            let a2 = cmul(ff_src[src + 2u * m], root(2u * t));
            let a3 = cmul(ff_src[src + 3u * m], root(3u * t));
            let e = a0 + a2;
            let f = a0 - a2;
            let g = a1 + a3;
            let h = rot(a1 - a3);
            ff_dst[d] = e + g;
            ff_dst[d + s] = f + h;
            ff_dst[d + 2u * s] = e - g;
            ff_dst[d + 3u * s] = f - h;
        }
        case 5u: {
            let a2 = cmul(ff_src[src + 2u * m], root(2u * t));
            let a3 = cmul(ff_src[src + 3u * m], root(3u * t));
            let a4 = cmul(ff_src[src + 4u * m], root(4u * t));
            let t1 = a1 + a4;
            let t2 = a2 + a3;
            let d1 = a1 - a4;
            let d2 = a2 - a3;
            let b1 = a0 + COS5A * t1 + COS5B * t2;
            let b2 = a0 + COS5B * t1 + COS5A * t2;
            let r1 = rot(SIN5A * d1 + SIN5B * d2);
            let r2 = rot(SIN5B * d1 - SIN5A * d2);
            ff_dst[d] = a0 + t1 + t2;
            ff_dst[d + s] = b1 + r1;
            ff_dst[d + 2u * s] = b2 + r2;
            ff_dst[d + 3u * s] = b2 - r2;
            ff_dst[d + 4u * s] = b1 - r1;
        }
        default: {}
    }
}

@group(0) @binding(1) var<storage, read> rh_src: array<vec2<f32>>;
@group(0) @binding(2) var<storage, read_write> rh_dst: array<vec2<f32>>;

// The row spectra Z of x + i y give X = (Z[k] + conj Z[-k]) / 2 and Y = (Z[k] - conj Z[-k]) / 2i,
// written column-major (kx ph + y) as the CPU's half spectra are.
@compute @workgroup_size(WG1)
fn rows_to_half(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nw: vec3<u32>,
                @builtin(local_invocation_index) l: u32) {
    let i = flat_index(wg, nw, l);
    let pairs = (p.count + 1u) / 2u;
    let hn = p.hw * p.ph;
    if i >= pairs * hn { return; }
    let k = i / hn;
    let kx = (i % hn) / p.ph;
    let y = i % p.ph;
    let row = k * p.pw * p.ph + y * p.pw;
    let z = rh_src[row + kx];
    let zc = conj(rh_src[row + (p.pw - kx) % p.pw]);
    let s = z + zc;
    let d = z - zc;
    rh_dst[2u * k * hn + kx * p.ph + y] = 0.5 * s;
    if 2u * k + 1u < p.count {
        rh_dst[(2u * k + 1u) * hn + kx * p.ph + y] = vec2<f32>(0.5 * d.y, -0.5 * d.x);
    }
}

@group(0) @binding(1) var<storage, read> hr_src: array<vec2<f32>>;
@group(0) @binding(2) var<storage, read_write> hr_dst: array<vec2<f32>>;

// Half spectrum value (kx, y) of image `img`, extended by symmetry past the half; the DC and
// Nyquist columns real (as the CPU's inverse makes them).
fn half_at(img: u32, x: u32, y: u32) -> vec2<f32> {
    if img >= p.count { return vec2<f32>(0.0); }
    let hn = p.hw * p.ph;
    var v: vec2<f32>;
    if x < p.hw {
        v = hr_src[img * hn + x * p.ph + y];
        if x == 0u || (p.pw % 2u == 0u && x == p.hw - 1u) { v.y = 0.0; }
    } else {
        v = conj(hr_src[img * hn + (p.pw - x) * p.ph + y]);
    }
    return v;
}

@compute @workgroup_size(WG1)
fn half_to_rows(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nw: vec3<u32>,
                @builtin(local_invocation_index) l: u32) {
    let i = flat_index(wg, nw, l);
    let pn = p.pw * p.ph;
    let pairs = (p.count + 1u) / 2u;
    if i >= pairs * pn { return; }
    let k = i / pn;
    let y = (i % pn) / p.pw;
    let x = i % p.pw;
    let a = half_at(2u * k, x, y);
    let b = half_at(2u * k + 1u, x, y);
    // a + i b
    hr_dst[i] = p.scale * vec2<f32>(a.x - b.y, a.y + b.x);
}

@group(0) @binding(1) var<storage, read> rr_src: array<vec2<f32>>;
@group(0) @binding(2) var<storage, read_write> rr_x: array<f32>;
@group(0) @binding(3) var<storage, read_write> rr_y: array<f32>;

// Real image 2k is the real part of complex image k, 2k + 1 its imaginary part; each value v
// (clamped to [0, 1] when flag is 1) becomes x, and y = v + mom (v - x_before).
@compute @workgroup_size(WG1)
fn rows_to_real(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nw: vec3<u32>,
                @builtin(local_invocation_index) l: u32) {
    let i = flat_index(wg, nw, l);
    let pn = p.pw * p.ph;
    if i >= p.count * pn { return; }
    let img = i / pn;
    let z = rr_src[(img / 2u) * pn + i % pn];
    var v = select(z.x, z.y, img % 2u == 1u);
    if p.flag == 1u { v = clamp(v, 0.0, 1.0); }
    // Without momentum x is not read: its buffer may hold anything (NaN times 0 is NaN).
    var next = v;
    if p.mom != 0.0 { next = v + p.mom * (v - rr_x[i]); }
    rr_y[i] = next;
    rr_x[i] = v;
}

@group(0) @binding(1) var<storage, read> ap_in: array<vec2<f32>>;
@group(0) @binding(2) var<storage, read> ap_mat: array<f32>;
@group(0) @binding(3) var<storage, read_write> ap_out: array<vec2<f32>>;

@compute @workgroup_size(WG1)
fn apply(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nw: vec3<u32>,
         @builtin(local_invocation_index) l: u32) {
    let i = flat_index(wg, nw, l);
    if i >= 3u * p.rows * p.n { return; }
    let f = i % p.n;
    let a = (i / p.n) % p.rows;
    let c = i / (p.rows * p.n);
    var acc = vec2<f32>(0.0);
    for (var d = 0u; d < p.cols; d++) {
        acc += ap_mat[(a * p.cols + d) * p.n + f] * ap_in[(p.off + c * p.cols + d) * p.n + f];
    }
    let o = (c * p.rows + a) * p.n + f;
    if p.flag == 1u {
        ap_out[o] += p.scale * acc;
    } else {
        ap_out[o] = p.scale * acc;
    }
}

@group(0) @binding(1) var<storage, read> gs_y0: array<vec2<f32>>;
@group(0) @binding(2) var<storage, read> gs_a: array<f32>;
@group(0) @binding(3) var<storage, read_write> gs_s: array<vec2<f32>>;
@group(0) @binding(4) var<storage, read_write> gs_part: array<f32>;

var<workgroup> part: array<f32, WG1>;

// S <- S - step A (S - Y0) per channel and frequency (`rows` layers); the objective
// (S - Y0)^H A (S - Y0) at S, the half spectrum's inner columns counted twice, summed per
// workgroup.
@compute @workgroup_size(WG1)
fn grad_step(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nw: vec3<u32>,
             @builtin(local_invocation_index) l: u32) {
    let i = flat_index(wg, nw, l);
    var sum = 0.0;
    if i < 3u * p.n {
        let f = i % p.n;
        let c = i / p.n;
        let np = p.rows;
        var d: array<vec2<f32>, MAX_PLANES>;
        for (var a = 0u; a < np; a++) {
            let o = (c * np + a) * p.n + f;
            d[a] = gs_s[o] - gs_y0[o];
        }
        let kx = f / p.ph;
        var twice = 2.0;
        if kx == 0u || (p.pw % 2u == 0u && kx == p.hw - 1u) { twice = 1.0; }
        var acc = 0.0;
        for (var a = 0u; a < np; a++) {
            var g = vec2<f32>(0.0);
            for (var b = 0u; b < np; b++) {
                g += gs_a[(a * np + b) * p.n + f] * d[b];
            }
            acc += dot(d[a], g);
            let o = (c * np + a) * p.n + f;
            gs_s[o] = gs_s[o] - p.step * g;
        }
        sum = twice * acc;
    }
    part[l] = sum;
    workgroupBarrier();
    for (var k = WG1 / 2u; k > 0u; k >>= 1u) {
        if l < k { part[l] += part[l + k]; }
        workgroupBarrier();
    }
    if l == 0u { gs_part[wg.y * nw.x + wg.x] = part[0]; }
}

@group(0) @binding(1) var<storage, read> as_y0: array<vec2<f32>>;
@group(0) @binding(2) var<storage, read> as_a: array<f32>;
@group(0) @binding(3) var<storage, read> as_b: array<f32>;
@group(0) @binding(4) var<storage, read_write> as_s: array<vec2<f32>>;
@group(0) @binding(5) var<storage, read_write> as_part: array<f32>;

// ADMM's x-update S <- Y0 + B (S - Y0) per channel and frequency (`rows` layers), B the plan's
// rho (A + rho I)^-1; the objective (S - Y0)^H A (S - Y0) at S summed per workgroup, as
// grad_step sums it.
@compute @workgroup_size(WG1)
fn admm_step(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nw: vec3<u32>,
             @builtin(local_invocation_index) l: u32) {
    let i = flat_index(wg, nw, l);
    var sum = 0.0;
    if i < 3u * p.n {
        let f = i % p.n;
        let c = i / p.n;
        let np = p.rows;
        var d: array<vec2<f32>, MAX_PLANES>;
        for (var a = 0u; a < np; a++) {
            let o = (c * np + a) * p.n + f;
            d[a] = as_s[o] - as_y0[o];
        }
        let kx = f / p.ph;
        var twice = 2.0;
        if kx == 0u || (p.pw % 2u == 0u && kx == p.hw - 1u) { twice = 1.0; }
        var acc = 0.0;
        for (var a = 0u; a < np; a++) {
            var g = vec2<f32>(0.0);
            var h = vec2<f32>(0.0);
            for (var b = 0u; b < np; b++) {
                g += as_a[(a * np + b) * p.n + f] * d[b];
                h += as_b[(a * np + b) * p.n + f] * d[b];
            }
            acc += dot(d[a], g);
            let o = (c * np + a) * p.n + f;
            as_s[o] = as_y0[o] + h;
        }
        sum = twice * acc;
    }
    part[l] = sum;
    workgroupBarrier();
    for (var k = WG1 / 2u; k > 0u; k >>= 1u) {
        if l < k { part[l] += part[l + k]; }
        workgroupBarrier();
    }
    if l == 0u { as_part[wg.y * nw.x + wg.x] = part[0]; }
}

@group(0) @binding(1) var<storage, read> au_x: array<f32>;
@group(0) @binding(2) var<storage, read_write> au_z: array<f32>;
@group(0) @binding(3) var<storage, read_write> au_u: array<f32>;
@group(0) @binding(4) var<storage, read_write> au_v: array<f32>;

// ADMM's z- and u-updates per pixel of `count` padded images: z = clamp(x + u, 0, 1),
// u = x + u - z, and v = z - u for the next x-update. flag 1: u starts at zero (not read).
@compute @workgroup_size(WG1)
fn admm_update(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nw: vec3<u32>,
               @builtin(local_invocation_index) l: u32) {
    let i = flat_index(wg, nw, l);
    if i >= p.count * p.pw * p.ph { return; }
    var u = 0.0;
    if p.flag != 1u { u = au_u[i]; }
    let v = au_x[i] + u;
    let z = clamp(v, 0.0, 1.0);
    let un = v - z;
    au_z[i] = z;
    au_u[i] = un;
    au_v[i] = z - un;
}
