// The eyepiece pre-warp: a mesh over the panel (dioptra_render::warp::WarpMesh) whose
// vertices carry, per colour channel, where in the source image that channel must be read so
// the eye sees the source undistorted through the eyepiece. Drawn into any colour target the
// size of the panel (a window's surface, or a float texture read back); the source is a frame
// in GPU memory (planar linear RGB, the renderer's layout). Each channel is read bilinearly,
// 0 outside the source; a triangle with a vertex the model cannot reach is black. With
// `lut_len` > 0 the output is encoded through the panel's transfer LUT (transfer_lut.wgsl,
// joined after this file); otherwise it is linear light. CPU twin:
// dioptra_render::warp::warp_cpu.

struct Params {
    // The source's layout in f32 values.
    width: u32,
    height: u32,
    offset: u32,
    row_pitch: u32,
    plane_pitch: u32,
    lut_len: u32,
    // Source coordinates are scaled by `scale` about (centre_x, centre_y): the magnification
    // compensation's inverse.
    scale: f32,
    centre_x: f32,
    centre_y: f32,
    // The panel (target) in pixels.
    target_width: f32,
    target_height: f32,
    _pad: u32,
};

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> pixels: array<f32>;
@group(0) @binding(2) var<storage, read> lut: array<f32>;

struct VertexIn {
    // Panel pixel (OpenCV's convention: pixel (i, j)'s centre at (i, j)).
    @location(0) position: vec2<f32>,
    @location(1) red: vec2<f32>,
    @location(2) green: vec2<f32>,
    @location(3) blue: vec2<f32>,
    @location(4) valid: f32,
};

struct VertexOut {
    @builtin(position) position: vec4<f32>,
    @location(0) red: vec2<f32>,
    @location(1) green: vec2<f32>,
    @location(2) blue: vec2<f32>,
    @location(3) valid: f32,
};

fn scaled(p: vec2<f32>) -> vec2<f32> {
    let c = vec2<f32>(params.centre_x, params.centre_y);
    return c + (p - c) * params.scale;
}

@vertex
fn vs_main(v: VertexIn) -> VertexOut {
    var out: VertexOut;
    let x = (v.position.x + 0.5) / params.target_width * 2.0 - 1.0;
    let y = 1.0 - (v.position.y + 0.5) / params.target_height * 2.0;
    out.position = vec4<f32>(x, y, 0.0, 1.0);
    out.red = scaled(v.red);
    out.green = scaled(v.green);
    out.blue = scaled(v.blue);
    out.valid = v.valid;
    return out;
}

fn texel(c: u32, x: i32, y: i32) -> f32 {
    if (x < 0 || y < 0 || x >= i32(params.width) || y >= i32(params.height)) {
        return 0.0;
    }
    return pixels[params.offset + c * params.plane_pitch + u32(y) * params.row_pitch + u32(x)];
}

fn bilinear(c: u32, p: vec2<f32>) -> f32 {
    // Far outside (or NaN): black, without integer overflow below.
    if (!(abs(p.x) < 1e7 && abs(p.y) < 1e7)) {
        return 0.0;
    }
    let x0 = floor(p.x);
    let y0 = floor(p.y);
    let fx = p.x - x0;
    let fy = p.y - y0;
    let ix = i32(x0);
    let iy = i32(y0);
    let top = texel(c, ix, iy) * (1.0 - fx) + texel(c, ix + 1, iy) * fx;
    let bottom = texel(c, ix, iy + 1) * (1.0 - fx) + texel(c, ix + 1, iy + 1) * fx;
    return top * (1.0 - fy) + bottom * fy;
}

@fragment
fn fs_main(in: VertexOut) -> @location(0) vec4<f32> {
    var rgb = vec3<f32>(0.0);
    if (in.valid > 0.999) {
        rgb = vec3<f32>(bilinear(0u, in.red), bilinear(1u, in.green), bilinear(2u, in.blue));
    }
    if (params.lut_len > 0u) {
        rgb = vec3<f32>(
            lut_encode(rgb.x, params.lut_len),
            lut_encode(rgb.y, params.lut_len),
            lut_encode(rgb.z, params.lut_len),
        );
    }
    return vec4<f32>(rgb, 1.0);
}
