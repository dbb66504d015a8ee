// The panel's transfer function as a look-up table: linear light v (0 to 1, above the panel's
// black) to code value, sampled at `n` points evenly spaced in sqrt(v) (dense near black,
// where a power law's inverse is steep) and read linearly between them. Joined to the shader
// that binds `lut`. CPU twin: dioptra_render::transfer::EncodeLut::encode.

fn lut_encode(v: f32, n: u32) -> f32 {
    // NaN and below 0: black; above 1: white.
    if !(v > 0.0) {
        return lut[0];
    }
    let t = sqrt(min(v, 1.0)) * f32(n - 1u);
    let i = min(u32(t), n - 2u);
    let f = t - f32(i);
    return lut[i] + (lut[i + 1u] - lut[i]) * f;
}
