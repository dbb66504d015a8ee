// Log-polar sampling and inverse-distance interpolation (CPU twin: src/foveate.rs).
// mask: one invocation per (ring r, angle t) marks the pixel its sample lands on; the
// transcendental values (rho per ring, cos/sin per angle) come from the host in f32 exactly as
// the CPU computes them, so the GPU's reduced-precision exp/sin/cos cannot move a sample.
// cells: one 8 x 8 workgroup per 8 x 8-pixel cell compacts its samples, in raster order (the
// CPU's bucket order), into a fixed FOV_CELL^2-entry slot: no prefix sum over the image, no atomics.
// interp: one invocation per pixel visits cells ring by ring in the CPU's order and keeps the
// four nearest samples with the CPU's tie rule (strictly nearer replaces; equal keeps the
// first visited). Distances are compared as exact integer squares.

struct Params {
    w: u32,
    h: u32,
    rings: u32,   // R
    angles: u32,  // Theta
    cx: f32,
    cy: f32,
    gw: u32,      // cells per row
    gh: u32,      // cells per column
}

// FOV_CELL (pixels per cell side) comes from src/foveate.rs, prepended by the host.

@group(0) @binding(0) var<uniform> p: Params;

// mask: rho (R), cos/sin (Theta, vec2) -> mask (u32 per pixel, cleared before)
@group(0) @binding(1) var<storage, read> rho: array<f32>;
@group(0) @binding(2) var<storage, read> dir: array<vec2<f32>>;
@group(0) @binding(3) var<storage, read_write> mask_out: array<atomic<u32>>;

@compute @workgroup_size(16, 16)
fn mask(@builtin(global_invocation_id) g: vec3<u32>) {
    if g.x >= p.angles || g.y >= p.rings { return; }
    let r = rho[g.y];
    let d = dir[g.x];
    let x = floor(p.cx + r * d.x);
    let y = floor(p.cy + r * d.y);
    if x >= 0.0 && y >= 0.0 && x < f32(p.w) && y < f32(p.h) {
        atomicStore(&mask_out[u32(y) * p.w + u32(x)], 1u);
    }
}

// cells: mask -> counts (one per cell), entries (FOV_CELL^2 per cell: pixel index y * w + x)
@group(0) @binding(1) var<storage, read> mask_in: array<u32>;
@group(0) @binding(2) var<storage, read_write> counts: array<u32>;
@group(0) @binding(3) var<storage, read_write> entries: array<u32>;

var<workgroup> flags: array<u32, FOV_CELL * FOV_CELL>;

@compute @workgroup_size(FOV_CELL, FOV_CELL)
fn cells(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_id) l: vec3<u32>) {
    let x = wg.x * FOV_CELL + l.x;
    let y = wg.y * FOV_CELL + l.y;
    let k = l.y * FOV_CELL + l.x;
    var f = 0u;
    if x < p.w && y < p.h && mask_in[y * p.w + x] != 0u {
        f = 1u;
    }
    flags[k] = f;
    workgroupBarrier();
    let cell = wg.y * p.gw + wg.x;
    if f == 1u {
        var slot = 0u;
        for (var j = 0u; j < k; j++) {
            slot += flags[j];
        }
        entries[cell * FOV_CELL * FOV_CELL + slot] = y * p.w + x;
    }
    if k == 63u {
        var n = 0u;
        for (var j = 0u; j < FOV_CELL * FOV_CELL; j++) {
            n += flags[j];
        }
        counts[cell] = n;
    }
}

// interp: image (3 planes), mask, counts, entries -> out (3 planes)
@group(0) @binding(1) var<storage, read> img: array<f32>;
@group(0) @binding(2) var<storage, read> m: array<u32>;
@group(0) @binding(3) var<storage, read> cnt: array<u32>;
@group(0) @binding(4) var<storage, read> ent: array<u32>;
@group(0) @binding(5) var<storage, read_write> dst: array<f32>;

@compute @workgroup_size(16, 16)
fn interp(@builtin(global_invocation_id) g: vec3<u32>) {
    if g.x >= p.w || g.y >= p.h { return; }
    let n = p.w * p.h;
    let i = g.y * p.w + g.x;
    if m[i] != 0u {
        dst[i] = img[i];
        dst[n + i] = img[n + i];
        dst[2u * n + i] = img[2u * n + i];
        return;
    }
    let x = i32(g.x);
    let y = i32(g.y);
    let cx = x / i32(FOV_CELL);
    let cy = y / i32(FOV_CELL);
    // The four nearest, sorted by squared distance; found = how many are set.
    var bd = array<i32, 4>(0, 0, 0, 0);
    var bs = array<u32, 4>(0u, 0u, 0u, 0u);
    var found = 0u;
    let gw = i32(p.gw);
    let gh = i32(p.gh);
    let last = max(gw, gh);
    for (var ring = 0; ring <= last; ring++) {
        // Every sample in this ring or beyond is at least (ring - 1) * FOV_CELL away.
        let lb = max(ring - 1, 0) * i32(FOV_CELL);
        if found == 4u && lb * lb > bd[3] { break; }
        for (var gy = cy - ring; gy <= cy + ring; gy++) {
            if gy < 0 || gy >= gh { continue; }
            let edge_row = abs(gy - cy) == ring;
            // Inside a ring only its two end columns are on it (unless on its top/bottom row).
            var gx = cx - ring;
            loop {
                if gx > cx + ring { break; }
                if gx >= 0 && gx < gw {
                    let cell = u32(gy * gw + gx);
                    let c = cnt[cell];
                    for (var e = 0u; e < c; e++) {
                        let s = ent[cell * FOV_CELL * FOV_CELL + e];
                        let dx = i32(s % p.w) - x;
                        let dy = i32(s / p.w) - y;
                        let d = dx * dx + dy * dy;
                        if found < 4u || d < bd[3] {
                            // Insert keeping order; equal distances stay after earlier ones.
                            var k = min(found, 3u);
                            loop {
                                if k == 0u || bd[k - 1u] <= d { break; }
                                bd[k] = bd[k - 1u];
                                bs[k] = bs[k - 1u];
                                k -= 1u;
                            }
                            bd[k] = d;
                            bs[k] = s;
                            found = min(found + 1u, 4u);
                        }
                    }
                }
                if edge_row || ring == 0 || gx == cx + ring {
                    gx += 1;
                } else {
                    gx = cx + ring;
                }
            }
        }
    }
    var acc = vec3<f32>(0.0);
    var wsum = 0.0;
    for (var k = 0u; k < found; k++) {
        let wt = 1.0 / sqrt(f32(bd[k]));
        let s = bs[k];
        acc += wt * vec3<f32>(img[s], img[n + s], img[2u * n + s]);
        wsum += wt;
    }
    let v = acc / wsum;
    dst[i] = v.x;
    dst[n + i] = v.y;
    dst[2u * n + i] = v.z;
}
