// Linear light to the panel's code values, an image pass: planar linear RGB in a buffer (the
// renderer's layout) to a packed planar image of code values (0 to 1). CPU twin:
// dioptra_render::transfer::EncodeLut::encode_image. lut_encode is in transfer_lut.wgsl,
// joined after this file.

struct Params {
    width: u32,
    height: u32,
    // The source's layout in f32 values (dioptra_render::gpu::ImageLayout).
    offset: u32,
    row_pitch: u32,
    plane_pitch: u32,
    lut_len: u32,
    _pad0: u32,
    _pad1: u32,
};

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> pixels: array<f32>;
@group(0) @binding(2) var<storage, read> lut: array<f32>;
@group(0) @binding(3) var<storage, read_write> out: array<f32>;

@compute @workgroup_size(16, 16)
fn encode(@builtin(global_invocation_id) id: vec3<u32>) {
    if (id.x >= params.width || id.y >= params.height) {
        return;
    }
    let plane = params.width * params.height;
    for (var c = 0u; c < 3u; c = c + 1u) {
        let v = pixels[params.offset + c * params.plane_pitch + id.y * params.row_pitch + id.x];
        out[c * plane + id.y * params.width + id.x] = lut_encode(v, params.lut_len);
    }
}
