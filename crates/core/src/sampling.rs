//! Low-discrepancy sampling shared by the renderer (lens samples) and the scene simulator
//! (ground-truth rays), so both draw from one definition of the Halton sequence.

/// The `i`-th element of the van der Corput sequence in `base`: digits of `i` mirrored about
/// the radix point. Halton points are these in coprime bases.
pub fn radical_inverse(mut i: u32, base: u32) -> f32 {
    let base = base.max(2);
    let inv = 1.0 / base as f32;
    let (mut f, mut r) = (inv, 0.0f32);
    while i > 0 {
        r += f * (i % base) as f32;
        i /= base;
        f *= inv;
    }
    r
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn radical_inverse_known_values() {
        // base 2: 1 -> 0.1b, 2 -> 0.01b, 3 -> 0.11b; base 3: 5 = 12 (base 3) -> 0.21 = 7/9
        assert_eq!(radical_inverse(1, 2), 0.5);
        assert_eq!(radical_inverse(2, 2), 0.25);
        assert_eq!(radical_inverse(3, 2), 0.75);
        assert!((radical_inverse(5, 3) - 7.0 / 9.0).abs() < 1e-6);
        assert_eq!(radical_inverse(0, 7), 0.0);
        assert_eq!(radical_inverse(3, 0), 0.75); // a base below 2 is taken as 2
    }
}
