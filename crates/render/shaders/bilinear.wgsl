// A bilinear read of one plane of a storage array, shared by the shaders that resample views
// (put before each shader by `shared_wgsl`): WGSL cannot pass a storage array to a function,
// so the taps' indices and weights are computed here and each shader reads its own array.

struct BilinearTaps {
    i00: u32,
    i10: u32,
    i01: u32,
    i11: u32,
    tx: f32,
    ty: f32,
}

// The four taps around (x, y) in the w x h plane starting at `base`: pixel centres at +0.5,
// edges clamped.
fn bilinear_taps(base: u32, x: f32, y: f32, w: u32, h: u32) -> BilinearTaps {
    let fx = x - 0.5;
    let fy = y - 0.5;
    let x0 = floor(fx);
    let y0 = floor(fy);
    let xa = u32(clamp(i32(x0), 0, i32(w) - 1));
    let xb = u32(clamp(i32(x0) + 1, 0, i32(w) - 1));
    let ya = u32(clamp(i32(y0), 0, i32(h) - 1));
    let yb = u32(clamp(i32(y0) + 1, 0, i32(h) - 1));
    return BilinearTaps(
        base + ya * w + xa,
        base + ya * w + xb,
        base + yb * w + xa,
        base + yb * w + xb,
        fx - x0,
        fy - y0,
    );
}

// The taps' values `v00 v10 v01 v11` mixed by their weights.
fn bilinear_mix(t: BilinearTaps, v00: f32, v10: f32, v01: f32, v11: f32) -> f32 {
    let a = v00 * (1.0 - t.tx) + v10 * t.tx;
    let b = v01 * (1.0 - t.tx) + v11 * t.tx;
    return a * (1.0 - t.ty) + b * t.ty;
}
