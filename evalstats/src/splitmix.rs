//! The deterministic generator the simulations of this crate's bench and tests (and the store's)
//! draw outcomes from, here so that each has one definition and the crate keeps no dependencies.

/// SplitMix64 (Steele, Lea & Flood 2014): a 64-bit state, one multiply-xorshift mix per draw.
#[derive(Debug, Clone)]
pub struct SplitMix64(pub u64);

impl SplitMix64 {
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform on [0, 1) with 53 random bits.
    pub fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// 1.0 with probability `p`, else 0.0.
    pub fn bernoulli(&mut self, p: f64) -> f64 {
        f64::from(self.next_f64() < p)
    }
}
