//! Small deterministic random numbers for the simulator: a SplitMix64 stream and a stateless hash
//! to Gaussian noise, so noise is reproducible per (seed, frame, pixel) and independent of how rows
//! are split across threads.

/// SplitMix64: a fast 64-bit generator with good statistical quality for simulation.
#[derive(Debug, Clone)]
pub struct SplitMix64 {
    state: u64,
}

impl SplitMix64 {
    /// A stream starting from `seed`.
    pub fn new(seed: u64) -> Self {
        SplitMix64 { state: seed }
    }

    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        mix(self.state)
    }

    /// Uniform in `[0, 1)`.
    pub fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }
}

/// The SplitMix64 finaliser: a bijective 64-bit mix.
#[inline]
pub fn mix(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A standard normal deviate that depends only on `(seed, stream, index)` (Box-Muller on two 32-bit
/// uniforms from one hash).
#[inline]
pub fn gaussian(seed: u64, stream: u64, index: u64) -> f32 {
    let h = mix(seed ^ mix(stream.wrapping_add(0x632B_E59B_D9B4_E019)) ^ index.wrapping_mul(0x9E37_79B9_7F4A_7C15));
    let u1 = ((h >> 32) as f32 + 0.5) * (1.0 / 4_294_967_296.0);
    let u2 = ((h & 0xFFFF_FFFF) as f32) * (1.0 / 4_294_967_296.0);
    (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gaussian_has_zero_mean_unit_variance_and_is_deterministic() {
        let n = 200_000u64;
        let (mut s, mut s2) = (0.0f64, 0.0f64);
        for i in 0..n {
            let g = gaussian(42, 7, i) as f64;
            s += g;
            s2 += g * g;
        }
        let mean = s / n as f64;
        let var = s2 / n as f64 - mean * mean;
        assert!(mean.abs() < 0.01, "mean {mean}");
        assert!((var - 1.0).abs() < 0.02, "variance {var}");
        assert_eq!(gaussian(1, 2, 3), gaussian(1, 2, 3));
        assert_ne!(gaussian(1, 2, 3), gaussian(1, 3, 3));
    }
}
