// Foveated defocus (CPU twin: src/foveated.rs): downsample halves an RGB-D layer (each 2 x 2
// block averaged); blend sums, per pixel, the layers with weight at its acuity level (the
// node grid read bilinearly), each layer read bilinearly. GRID and BLEND come from
// src/foveated.rs, prepended by the host.

struct Params {
    // downsample: source width, height; destination width, height.
    // blend: image width, height; grid width, height.
    w: u32,
    h: u32,
    a: u32,
    b: u32,
    // blend: the coarsest layer, and which layers were rendered (bit k).
    top: u32,
    present: u32,
    _pad0: u32,
    _pad1: u32,
    // blend: offset of layer k's planar image in the layers buffer.
    offsets: array<vec4<u32>, 2>,
}

@group(0) @binding(0) var<uniform> p: Params;

// downsample: colour (3 planes), depth -> colour (3 planes), depth.
@group(0) @binding(1) var<storage, read> d_color: array<f32>;
@group(0) @binding(2) var<storage, read> d_depth: array<f32>;
@group(0) @binding(3) var<storage, read_write> d_color_out: array<f32>;
@group(0) @binding(4) var<storage, read_write> d_depth_out: array<f32>;

@compute @workgroup_size(16, 16)
fn downsample(@builtin(global_invocation_id) g: vec3<u32>) {
    if g.x >= p.a || g.y >= p.b { return; }
    let n = p.w * p.h;
    var acc = vec4<f32>(0.0);
    var cnt = 0.0;
    for (var sy = 2u * g.y; sy < min(2u * g.y + 2u, p.h); sy++) {
        for (var sx = 2u * g.x; sx < min(2u * g.x + 2u, p.w); sx++) {
            let j = sy * p.w + sx;
            acc += vec4<f32>(d_color[j], d_color[n + j], d_color[2u * n + j], d_depth[j]);
            cnt += 1.0;
        }
    }
    let v = acc / cnt;
    let m = p.a * p.b;
    let i = g.y * p.a + g.x;
    d_color_out[i] = v.x;
    d_color_out[m + i] = v.y;
    d_color_out[2u * m + i] = v.z;
    d_depth_out[i] = v.w;
}

// blend: acuity levels at the grid nodes, the layers' images -> output (3 planes).
@group(0) @binding(1) var<storage, read> b_levels: array<f32>;
@group(0) @binding(2) var<storage, read> b_layers: array<f32>;
@group(0) @binding(3) var<storage, read_write> b_out: array<f32>;

fn smooth01(t: f32) -> f32 {
    let c = clamp(t, 0.0, 1.0);
    return c * c * (3.0 - 2.0 * c);
}

fn layer_weight(l: f32, k: u32) -> f32 {
    let kf = f32(k);
    var rising = 1.0;
    if k > 0u { rising = smooth01((l - kf) / BLEND); }
    var falling = 1.0;
    if k < p.top { falling = 1.0 - smooth01((l - kf - 1.0) / BLEND); }
    return rising * falling;
}

fn level_at(x: u32, y: u32) -> f32 {
    let inv = 1.0 / f32(GRID);
    let gw = p.a;
    let gh = p.b;
    let u = min((f32(x) + 0.5) * inv, f32(gw - 1u));
    let v = min((f32(y) + 0.5) * inv, f32(gh - 1u));
    let x0 = u32(u);
    let y0 = u32(v);
    let x1 = min(x0 + 1u, gw - 1u);
    let y1 = min(y0 + 1u, gh - 1u);
    let fx = u - f32(x0);
    let fy = v - f32(y0);
    let a = b_levels[y0 * gw + x0];
    let b = b_levels[y0 * gw + x1];
    let c = b_levels[y1 * gw + x0];
    let d = b_levels[y1 * gw + x1];
    let top = a + fx * (b - a);
    let bot = c + fx * (d - c);
    return top + fy * (bot - top);
}

fn layer_rgb(k: u32, x: u32, y: u32) -> vec3<f32> {
    let base = p.offsets[k / 4u][k % 4u];
    let s = 1u << k;
    let lw = (p.w + s - 1u) / s;
    let lh = (p.h + s - 1u) / s;
    let m = lw * lh;
    if k == 0u {
        let i = base + y * lw + x;
        return vec3<f32>(b_layers[i], b_layers[i + m], b_layers[i + 2u * m]);
    }
    let inv = 1.0 / f32(s);
    let u = clamp((f32(x) + 0.5) * inv - 0.5, 0.0, f32(lw - 1u));
    let v = clamp((f32(y) + 0.5) * inv - 0.5, 0.0, f32(lh - 1u));
    let x0 = u32(u);
    let y0 = u32(v);
    let x1 = min(x0 + 1u, lw - 1u);
    let y1 = min(y0 + 1u, lh - 1u);
    let fx = u - f32(x0);
    let fy = v - f32(y0);
    var out = vec3<f32>(0.0);
    for (var c = 0u; c < 3u; c++) {
        let o = base + c * m;
        let a = b_layers[o + y0 * lw + x0];
        let b = b_layers[o + y0 * lw + x1];
        let cc = b_layers[o + y1 * lw + x0];
        let d = b_layers[o + y1 * lw + x1];
        let top = a + fx * (b - a);
        let bot = cc + fx * (d - cc);
        out[c] = top + fy * (bot - top);
    }
    return out;
}

@compute @workgroup_size(16, 16)
fn blend(@builtin(global_invocation_id) g: vec3<u32>) {
    if g.x >= p.w || g.y >= p.h { return; }
    let l = level_at(g.x, g.y);
    var acc = vec3<f32>(0.0);
    for (var k = 0u; k <= p.top; k++) {
        let wt = layer_weight(l, k);
        if wt <= 0.0 || (p.present & (1u << k)) == 0u { continue; }
        acc += wt * layer_rgb(k, g.x, g.y);
    }
    let n = p.w * p.h;
    let i = g.y * p.w + g.x;
    b_out[i] = acc.x;
    b_out[n + i] = acc.y;
    b_out[2u * n + i] = acc.z;
}
