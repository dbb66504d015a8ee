// Draws the frame over the viewport (set to the letterboxed rectangle on the CPU side), from
// the frame texture (fs_main) or from a frame left in GPU memory by the renderer (fs_buffer).
// The texture is Rgba8UnormSrgb, so sampling gives linear light; the buffer holds linear light;
// the surface view is sRGB, so the hardware encodes it on write.

struct VsOut {
    @builtin(position) position: vec4<f32>,
    @location(0) uv: vec2<f32>,
};

// One triangle that covers the viewport: (-1,-1), (3,-1), (-1,3).
@vertex
fn vs_main(@builtin(vertex_index) i: u32) -> VsOut {
    let x = f32((i << 1u) & 2u);
    let y = f32(i & 2u);
    var out: VsOut;
    out.position = vec4<f32>(x * 2.0 - 1.0, y * 2.0 - 1.0, 0.0, 1.0);
    // Row 0 of the frame is the top of the screen.
    out.uv = vec2<f32>(x, 1.0 - y);
    return out;
}

@group(0) @binding(0) var frame: texture_2d<f32>;
@group(0) @binding(1) var frame_sampler: sampler;

@fragment
fn fs_main(in: VsOut) -> @location(0) vec4<f32> {
    return vec4<f32>(textureSample(frame, frame_sampler, in.uv).rgb, 1.0);
}

// A frame in the renderer's buffer: planar linear f32 (red, green, blue planes), `offset`
// values in, rows `row_pitch` apart, planes `plane_pitch` apart.
struct Layout {
    width: u32,
    height: u32,
    offset: u32,
    row_pitch: u32,
    plane_pitch: u32,
};

@group(0) @binding(2) var<uniform> frame_layout: Layout;
@group(0) @binding(3) var<storage, read> pixels: array<f32>;

@fragment
fn fs_buffer(in: VsOut) -> @location(0) vec4<f32> {
    // The nearest pixel, as the texture path's sampler takes it.
    let x = min(u32(in.uv.x * f32(frame_layout.width)), frame_layout.width - 1u);
    let y = min(u32(in.uv.y * f32(frame_layout.height)), frame_layout.height - 1u);
    let i = frame_layout.offset + y * frame_layout.row_pitch + x;
    let c = vec3<f32>(pixels[i], pixels[i + frame_layout.plane_pitch], pixels[i + 2u * frame_layout.plane_pitch]);
    // As the texture path packs it: clamped to [0, 1], NaN black.
    return vec4<f32>(select(vec3<f32>(0.0), clamp(c, vec3<f32>(0.0), vec3<f32>(1.0)), c == c), 1.0);
}

// The marker patch, drawn over the frame within a scissor rectangle in its corner
// (MarkerDraw::rect): full white or black for the photodiode taped over it. The CPU twin is
// MarkerDraw::paint, which the headless sink uses.
@fragment
fn fs_white(in: VsOut) -> @location(0) vec4<f32> {
    return vec4<f32>(1.0, 1.0, 1.0, 1.0);
}

@fragment
fn fs_black(in: VsOut) -> @location(0) vec4<f32> {
    return vec4<f32>(0.0, 0.0, 0.0, 1.0);
}
