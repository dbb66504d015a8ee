// Pyramid-spread defocus (CPU twin: src/pyramid.rs). Per level and kind of cell: aggregate
// sums each cell's sources (one invocation per cell), spread gathers the cells' ramped disks
// into the level image (one invocation per texel: the CPU scatters the same terms); compose
// runs gather's exact pass for radii below EXACT_RADIUS, reads every level bilinearly and
// normalises. EXACT_RADIUS, BANDS_PER_OCTAVE, KINDS, MAX_RADIUS and SPREAD_REACH come from
// src/pyramid.rs, prepended by the host.

struct Params {
    w: u32,
    h: u32,
    // Levels present (compose) / the level being built (aggregate, spread).
    top: u32,
    level: u32,
    k: f32,
    q: f32,
    kind: u32,
    n_off: u32,
    // The pixels computed: [x0, y0, x1, y1) and the annulus (centre x, y, inner, outer).
    region: vec4<u32>,
    annulus: vec4<f32>,
    // The level's record rectangle and output rectangle, in cells.
    rec: vec4<u32>,
    out: vec4<u32>,
    // Band edges rho_0 .. rho_BANDS.
    edges: array<vec4<f32>, 4>,
    // Per level m: grid width, height (texels), texel side (px), offset of kind 0's image.
    levels: array<vec4<u32>, 8>,
}

@group(0) @binding(0) var<uniform> p: Params;

fn edge(b: u32) -> f32 {
    return p.edges[b / 4u][b % 4u];
}

fn signed_radius(d: f32) -> f32 {
    return clamp(p.k * (d - p.q), -MAX_RADIUS, MAX_RADIUS);
}

fn band_of(r: f32) -> u32 {
    var b = 0u;
    while b + 1u < BANDS && edge(b + 1u) <= r { b++; }
    return b;
}

fn ramp_disk_m2(r: f32) -> f32 {
    let r2 = r * r;
    return 0.15 * (5.0 * r2 * r2 + 2.5 * r2 + 0.0625) / (3.0 * r2 + 0.25);
}

fn spread_radius(r: f32, cell: f32, grid: f32) -> f32 {
    var tent = 0.0;
    if grid > 1.0 { tent = grid * grid / 6.0; }
    let m = (ramp_disk_m2(r) + (cell * cell - 1.0) / 12.0 - tent) / (grid * grid);
    let b = 3.0 * m - 0.375;
    let u = (b + sqrt(max(b * b - 3.0 * (0.009375 - 0.25 * m), 0.0))) / 1.5;
    return sqrt(max(u, 0.25));
}

// aggregate: colour (3 planes), depth -> records (2 vec4 per cell of the rec rectangle).
@group(0) @binding(1) var<storage, read> a_color: array<f32>;
@group(0) @binding(2) var<storage, read> a_depth: array<f32>;
@group(0) @binding(3) var<storage, read_write> a_rec: array<vec4<f32>>;

// The weight source `sr` adds to kind `kind` of level `m` (first band `first`); 0: none.
fn kind_weight(sr: f32, m: u32, first: u32, kind: u32) -> f32 {
    let r = abs(sr);
    if r < EXACT_RADIUS { return 0.0; }
    let b = band_of(r);
    let own = b / BANDS_PER_OCTAVE == m;
    if sr > 0.0 {
        return select(0.0, 1.0 / (r * r), own && kind == 0u);
    }
    if kind == 0u { return 0.0; }
    if kind <= BANDS_PER_OCTAVE {
        return select(0.0, 1.0 / (r * r), own && 1u + b - first == kind);
    }
    return select(0.0, 1.0, first + kind - 1u - BANDS_PER_OCTAVE <= b);
}

@compute @workgroup_size(16, 16)
fn aggregate(@builtin(global_invocation_id) g: vec3<u32>) {
    let rw = p.rec.z - p.rec.x;
    let rh = p.rec.w - p.rec.y;
    if g.x >= rw || g.y >= rh { return; }
    let n = p.w * p.h;
    let cx = p.rec.x + g.x;
    let cy = p.rec.y + g.y;
    let grid = 2u << p.level;
    let s = grid;
    let first = BANDS_PER_OCTAVE * p.level;
    var c = vec3<f32>(0.0);
    var wsum = 0.0;
    var pos = vec2<f32>(0.0);
    var rsum = 0.0;
    for (var y = cy * s; y < min((cy + 1u) * s, p.h); y++) {
        let fy = f32(y) + 0.5;
        for (var x = cx * s; x < min((cx + 1u) * s, p.w); x++) {
            let j = y * p.w + x;
            let sr = signed_radius(a_depth[j]);
            let wt = kind_weight(sr, p.level, first, p.kind);
            if wt == 0.0 { continue; }
            c += wt * vec3<f32>(a_color[j], a_color[n + j], a_color[2u * n + j]);
            wsum += wt;
            pos += wt * vec2<f32>(f32(x) + 0.5, fy);
            rsum += wt * abs(sr);
        }
    }
    let o = 2u * (g.y * rw + g.x);
    if wsum <= 0.0 {
        a_rec[o] = vec4<f32>(0.0);
        a_rec[o + 1u] = vec4<f32>(0.0);
        return;
    }
    let inv = 1.0 / wsum;
    var radius = rsum * inv;
    var weight = 1.0;
    if p.kind > BANDS_PER_OCTAVE {
        let rho = edge(first + p.kind - 1u - BANDS_PER_OCTAVE);
        radius = rho;
        weight = 1.0 / (rho * rho);
    }
    let gf = f32(grid);
    let r = spread_radius(radius, f32(s), gf);
    a_rec[o] = vec4<f32>(pos.x * inv / gf, pos.y * inv / gf, r, 0.0);
    a_rec[o + 1u] = vec4<f32>(c * weight, wsum * weight);
}

// spread: records -> level images (vec4 per texel: r, g, b, weight).
@group(0) @binding(1) var<storage, read> s_rec: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read_write> s_img: array<vec4<f32>>;

@compute @workgroup_size(16, 16)
fn spread(@builtin(global_invocation_id) g: vec3<u32>) {
    let X = p.out.x + g.x;
    let Y = p.out.y + g.y;
    if X >= p.out.z || Y >= p.out.w { return; }
    let rw = p.rec.z - p.rec.x;
    let fx = f32(X) + 0.5;
    let fy = f32(Y) + 0.5;
    var acc = vec4<f32>(0.0);
    // The cells within SPREAD_REACH texels (a cell is `ratio` texels a side).
    let ratio = 1u;
    let y0 = max(select(0u, Y - SPREAD_REACH, Y >= SPREAD_REACH) / ratio, p.rec.y);
    let y1 = min((Y + SPREAD_REACH) / ratio + 1u, p.rec.w);
    let x0 = max(select(0u, X - SPREAD_REACH, X >= SPREAD_REACH) / ratio, p.rec.x);
    let x1 = min((X + SPREAD_REACH) / ratio + 1u, p.rec.z);
    for (var cy = y0; cy < y1; cy++) {
        for (var cx = x0; cx < x1; cx++) {
            let o = 2u * ((cy - p.rec.y) * rw + (cx - p.rec.x));
            let v = s_rec[o + 1u];
            if v.w <= 0.0 { continue; }
            let r = s_rec[o];
            let dx = fx - r.x;
            let dy = fy - r.y;
            let cover = clamp(r.z + 0.5 - sqrt(dx * dx + dy * dy), 0.0, 1.0);
            acc += cover * v;
        }
    }
    let l = p.levels[p.level];
    s_img[l.w + p.kind * l.x * l.y + Y * l.x + X] = acc;
}

// compose: colour, depth, exact offsets (dx, dy, distance), level images -> output (3 planes).
@group(0) @binding(1) var<storage, read> c_color: array<f32>;
@group(0) @binding(2) var<storage, read> c_depth: array<f32>;
@group(0) @binding(3) var<storage, read> c_off: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read> c_img: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read_write> c_out: array<f32>;

fn read_level(li: u32, kind: u32, x: u32, y: u32) -> vec4<f32> {
    let l = p.levels[li];
    let inv = 1.0 / f32(l.z);
    let u = clamp((f32(x) + 0.5) * inv - 0.5, 0.0, f32(l.x - 1u));
    let v = clamp((f32(y) + 0.5) * inv - 0.5, 0.0, f32(l.y - 1u));
    let x0 = u32(u);
    let y0 = u32(v);
    let x1 = min(x0 + 1u, l.x - 1u);
    let y1 = min(y0 + 1u, l.y - 1u);
    let fx = u - f32(x0);
    let fy = v - f32(y0);
    let base = l.w + kind * l.x * l.y;
    let a = c_img[base + y0 * l.x + x0];
    let b = c_img[base + y0 * l.x + x1];
    let c = c_img[base + y1 * l.x + x0];
    let d = c_img[base + y1 * l.x + x1];
    let top = a + fx * (b - a);
    let bot = c + fx * (d - c);
    return top + fy * (bot - top);
}

@compute @workgroup_size(16, 16)
fn compose(@builtin(global_invocation_id) g: vec3<u32>) {
    let x = p.region.x + g.x;
    let y = p.region.y + g.y;
    if x >= p.region.z || y >= p.region.w { return; }
    let ddx = f32(x) + 0.5 - p.annulus.x;
    let ddy = f32(y) + 0.5 - p.annulus.y;
    let d2 = ddx * ddx + ddy * ddy;
    if !(d2 >= p.annulus.z * abs(p.annulus.z) && d2 < p.annulus.w * p.annulus.w) { return; }
    let n = p.w * p.h;
    let i = y * p.w + x;
    let own = vec3<f32>(c_color[i], c_color[n + i], c_color[2u * n + i]);
    let dc = c_depth[i];
    let rc = abs(signed_radius(dc));
    var acc = vec3<f32>(0.0);
    var wsum = 0.0;
    var reached = false;
    for (var k = 0u; k < p.n_off; k++) {
        let o = c_off[k];
        let sx = i32(x) + i32(o.x);
        let sy = i32(y) + i32(o.y);
        if sx < 0 || sy < 0 || sx >= i32(p.w) || sy >= i32(p.h) { continue; }
        let j = u32(sy) * p.w + u32(sx);
        var r = abs(signed_radius(c_depth[j]));
        if c_depth[j] < dc { r = min(r, rc); }
        if r >= EXACT_RADIUS { continue; }
        let cover = clamp(r + 0.5 - o.z, 0.0, 1.0);
        if cover > 0.0 {
            let rr = max(r, 0.5);
            let wgt = cover / (rr * rr);
            acc += wgt * vec3<f32>(c_color[j], c_color[n + j], c_color[2u * n + j]);
            wsum += wgt;
            reached = reached || o.z > 0.0;
        }
    }
    var lacc = vec4<f32>(0.0);
    var b = 0u;
    var t = 0.0;
    let blurred = rc >= EXACT_RADIUS;
    if blurred {
        b = band_of(rc);
        t = clamp((rc - edge(b)) / (edge(b + 1u) - edge(b)), 0.0, 1.0);
    }
    for (var li = 0u; li < p.top; li++) {
        lacc += read_level(li, 0u, x, y);
        if !blurred { continue; }
        for (var kk = 0u; kk < BANDS_PER_OCTAVE; kk++) {
            let band = BANDS_PER_OCTAVE * li + kk;
            var f_own = 0.0;
            if band < b { f_own = 1.0; } else if band == b { f_own = t; }
            var f_clamp = 0.0;
            if band == b { f_clamp = 1.0 - t; } else if band == b + 1u { f_clamp = t; }
            if f_own > 0.0 { lacc += f_own * read_level(li, 1u + kk, x, y); }
            if f_clamp > 0.0 {
                lacc += f_clamp * read_level(li, 1u + BANDS_PER_OCTAVE + kk, x, y);
            }
        }
    }
    var res = own;
    if lacc.w > 0.0 || reached {
        let total = wsum + lacc.w;
        if total > 0.0 { res = (acc + lacc.xyz) / total; }
    }
    c_out[i] = res.x;
    c_out[n + i] = res.y;
    c_out[2u * n + i] = res.z;
}
