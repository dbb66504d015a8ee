// A lenslet display's panel image from a light field of views in GPU memory (CPU twin:
// dioptra-sched's lenslet::elemental_images). Each panel column and row brings its sampling
// from the host (lenslet::Sampling: the first of its two views, each one's weight, its position
// in a view); a pixel sums the bilinear reads of the (row, column) view pairs by the products of
// their weights, pairs of weight 0 skipped, in the CPU's order.

struct Params {
    w: u32,
    h: u32,
    vw: u32,
    vh: u32,
    grid: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<uniform> p: Params;
// The views, each planar (red, green, blue), one after the other in grid order.
@group(0) @binding(1) var<storage, read> views: array<f32>;
@group(0) @binding(2) var<storage, read> cols: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read> rows: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read_write> panel: array<f32>;

// Bilinear read of plane `base` at (x, y), pixel centres at +0.5, edges clamped.
fn bilinear(base: u32, x: f32, y: f32) -> f32 {
    let t = bilinear_taps(base, x, y, p.vw, p.vh);
    return bilinear_mix(t, views[t.i00], views[t.i10], views[t.i01], views[t.i11]);
}

@compute @workgroup_size(16, 16)
fn elemental(@builtin(global_invocation_id) g: vec3<u32>) {
    if g.x >= p.w || g.y >= p.h { return; }
    let c = cols[g.x];
    let r = rows[g.y];
    let n = p.vw * p.vh;
    var acc = vec3<f32>(0.0);
    for (var j = 0u; j < 2u; j++) {
        let wj = select(r.y, r.z, j == 1u);
        for (var i = 0u; i < 2u; i++) {
            let wt = select(c.y, c.z, i == 1u) * wj;
            if wt == 0.0 { continue; }
            let v = (u32(r.x) + j) * p.grid + u32(c.x) + i;
            let base = v * 3u * n;
            acc += wt * vec3<f32>(
                bilinear(base, c.w, r.w),
                bilinear(base + n, c.w, r.w),
                bilinear(base + 2u * n, c.w, r.w),
            );
        }
    }
    let o = g.y * p.w + g.x;
    let m = p.w * p.h;
    panel[o] = acc.x;
    panel[m + o] = acc.y;
    panel[2u * m + o] = acc.z;
}
