// A light field from sparse RGB-D views (CPU twin: src/views.rs). After the light-field
// splat kernels (shaders/lightfield.wgsl, one depth map per input) have resolved, per input,
// the nearest source at each target pixel: resolve blends the inputs that see the nearest
// surface, reading each at its sub-pixel position (a crack fill that lands on no pixel of its
// surface dropped);
// fill_rows fills the holes from the farther of the nearest valid pixels along the row (the
// pixel up to FILL_SKIP beyond it on its surface), fill_cols the rest along the column and
// writes the view planar: red, green, blue, then its depth (diopters; 0 where nothing was
// seen on the pixel's row or column, as views.rs's synthesize_rgbd_view).

struct Params {
    w: u32,
    h: u32,
    ni: u32,
    _pad: u32,
}

@group(0) @binding(0) var<uniform> p: Params;

const SAME_SURFACE_D: f32 = 0.03;
const SURFACE_STEP_PX: f32 = 1.0;
const FILL_SKIP: i32 = 3;

@group(0) @binding(1) var<storage, read> dkey: array<u32>;
@group(0) @binding(2) var<storage, read> ikey: array<u32>;
@group(0) @binding(3) var<storage, read> depths: array<f32>;
@group(0) @binding(4) var<storage, read> colors: array<f32>;
@group(0) @binding(5) var<storage, read> inputs: array<vec4<f32>>;
@group(0) @binding(6) var<storage, read_write> px: array<vec4<f32>>;

// The source (index + 1) input v sees at target (x, y), and whether it is an exact write.
fn source(v: u32, x: i32, y: i32) -> vec2<u32> {
    let b = v * p.w * p.h;
    let j = b + u32(y) * p.w + u32(x);
    if dkey[j] != 0u { return vec2<u32>(ikey[j], 1u); }
    var bd = 0xffffffffu;
    var bi = 0xffffffffu;
    for (var ny = max(y - 1, 0); ny < min(y + 2, i32(p.h)); ny++) {
        for (var nx = max(x - 1, 0); nx < min(x + 2, i32(p.w)); nx++) {
            let k = b + u32(ny) * p.w + u32(nx);
            if dkey[k] != 0u && (dkey[k] < bd || (dkey[k] == bd && ikey[k] < bi)) {
                bd = dkey[k];
                bi = ikey[k];
            }
        }
    }
    if bd == 0xffffffffu { return vec2<u32>(0u, 0u); }
    return vec2<u32>(bi, 0u);
}

// Whether a bilinear read of input v at (x, y) takes any pixel (with a weight above zero) on
// the surface at depth d: its parallax at `shift` (px per diopter) within SURFACE_STEP_PX of
// d's (views.rs's lands_on_surface).
fn lands_on_surface(v: u32, x: f32, y: f32, d: f32, shift: vec2<f32>) -> bool {
    let n = p.w * p.h;
    let fx = x - 0.5;
    let fy = y - 0.5;
    let x0 = floor(fx);
    let y0 = floor(fy);
    let t = vec2<f32>(fx - x0, fy - y0);
    let per_d = length(shift);
    for (var k = 0; k < 4; k++) {
        let dx = k & 1;
        let dy = k >> 1u;
        let weight = select(1.0 - t.x, t.x, dx == 1) * select(1.0 - t.y, t.y, dy == 1);
        let tx = u32(clamp(i32(x0) + dx, 0, i32(p.w) - 1));
        let ty = u32(clamp(i32(y0) + dy, 0, i32(p.h) - 1));
        if weight > 0.0 && abs(depths[v * n + ty * p.w + tx] - d) * per_d <= SURFACE_STEP_PX {
            return true;
        }
    }
    return false;
}

// Input v's read at target pixel centre (fx, fy) for source s (index + 1, exact flag): its
// colour, and w = -1 for a crack fill whose ray lands on no pixel of its source's surface (a
// disocclusion, not a crack: dropped, as views.rs's warp_to drops it).
fn read_input(v: u32, s: vec2<u32>, fx: f32, fy: f32) -> vec4<f32> {
    let n = p.w * p.h;
    let d = depths[v * n + s.x - 1u];
    let q = inputs[v];
    let sx = fx - q.x * d;
    let sy = fy - q.y * d;
    if s.y == 0u && !lands_on_surface(v, sx, sy, d, q.xy) {
        return vec4<f32>(0.0, 0.0, 0.0, -1.0);
    }
    let b = v * 3u * n;
    return vec4<f32>(bilinear(b, sx, sy), bilinear(b + n, sx, sy), bilinear(b + 2u * n, sx, sy), 1.0);
}

fn bilinear(base: u32, x: f32, y: f32) -> f32 {
    let t = bilinear_taps(base, x, y, p.w, p.h);
    return bilinear_mix(t, colors[t.i00], colors[t.i10], colors[t.i01], colors[t.i11]);
}

@compute @workgroup_size(16, 16)
fn resolve(@builtin(global_invocation_id) g: vec3<u32>) {
    if g.x >= p.w || g.y >= p.h { return; }
    let n = p.w * p.h;
    let x = i32(g.x);
    let y = i32(g.y);
    let fx = f32(g.x) + 0.5;
    let fy = f32(g.y) + 0.5;
    var nearest = -1.0;
    for (var v = 0u; v < p.ni; v++) {
        let s = source(v, x, y);
        if s.x == 0u { continue; }
        if read_input(v, s, fx, fy).w < 0.0 { continue; }
        nearest = max(nearest, depths[v * n + s.x - 1u]);
    }
    var acc = vec3<f32>(0.0);
    var wsum = 0.0;
    for (var v = 0u; v < p.ni; v++) {
        let s = source(v, x, y);
        if s.x == 0u { continue; }
        let d = depths[v * n + s.x - 1u];
        if d < nearest - SAME_SURFACE_D { continue; } // hidden behind a nearer surface
        let r = read_input(v, s, fx, fy);
        if r.w < 0.0 { continue; }
        // Crack fills are guesses: they count a quarter.
        let wt = inputs[v].z * select(0.25, 1.0, s.y == 1u);
        acc += wt * r.xyz;
        wsum += wt;
    }
    let i = g.y * p.w + g.x;
    if wsum > 0.0 {
        px[i] = vec4<f32>(acc / wsum, nearest);
    } else {
        px[i] = vec4<f32>(0.0, 0.0, 0.0, -1.0); // a hole (depths are >= 0)
    }
}

@group(0) @binding(1) var<storage, read> fr_in: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read_write> fr_out: array<vec4<f32>>;

@compute @workgroup_size(16, 16)
fn fill_rows(@builtin(global_invocation_id) g: vec3<u32>) {
    if g.x >= p.w || g.y >= p.h { return; }
    let row = g.y * p.w;
    let c = fr_in[row + g.x];
    if c.w >= 0.0 { fr_out[row + g.x] = c; return; }
    var li = -1;
    for (var x = i32(g.x) - 1; x >= 0; x--) {
        if fr_in[row + u32(x)].w >= 0.0 { li = x; break; }
    }
    var ri = -1;
    for (var x = i32(g.x) + 1; x < i32(p.w); x++) {
        if fr_in[row + u32(x)].w >= 0.0 { ri = x; break; }
    }
    // The farther side (left on a tie), then up to FILL_SKIP beyond on its surface.
    var k = li;
    var step = -1;
    if li < 0 || (ri >= 0 && fr_in[row + u32(ri)].w < fr_in[row + u32(li)].w) {
        k = ri;
        step = 1;
    }
    if k < 0 {
        fr_out[row + g.x] = vec4<f32>(0.0, 0.0, 0.0, -1.0);
        return;
    }
    let d = fr_in[row + u32(k)].w;
    for (var m = 0; m < FILL_SKIP; m++) {
        let next = k + step;
        if next < 0 || next >= i32(p.w) { break; }
        let v = fr_in[row + u32(next)];
        if v.w < 0.0 || abs(v.w - d) > SAME_SURFACE_D { break; }
        k = next;
    }
    fr_out[row + g.x] = fr_in[row + u32(k)];
}

@group(0) @binding(1) var<storage, read> fc_in: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read_write> fc_out: array<f32>;

@compute @workgroup_size(16, 16)
fn fill_cols(@builtin(global_invocation_id) g: vec3<u32>) {
    if g.x >= p.w || g.y >= p.h { return; }
    let n = p.w * p.h;
    let i = g.y * p.w + g.x;
    var o = fc_in[i];
    if o.w < 0.0 {
        var up = vec4<f32>(0.0, 0.0, 0.0, -1.0);
        for (var y = i32(g.y) - 1; y >= 0; y--) {
            let v = fc_in[u32(y) * p.w + g.x];
            if v.w >= 0.0 { up = v; break; }
        }
        var down = vec4<f32>(0.0, 0.0, 0.0, -1.0);
        for (var y = g.y + 1u; y < p.h; y++) {
            let v = fc_in[y * p.w + g.x];
            if v.w >= 0.0 { down = v; break; }
        }
        o = up;
        if up.w >= 0.0 && down.w >= 0.0 {
            if down.w < up.w { o = down; }
        } else if down.w >= 0.0 {
            o = down;
        }
        if o.w < 0.0 { o = vec4<f32>(0.0); }
    }
    fc_out[i] = o.x;
    fc_out[n + i] = o.y;
    fc_out[2u * n + i] = o.z;
    fc_out[3u * n + i] = o.w;
}
