//! Confidence intervals for success rates.

/// z for a two-sided 95% interval.
pub const Z95: f64 = 1.959963984540054;

/// Wilson score interval for k successes out of n (95%). n = 0 gives (0, 1).
pub fn wilson(k: u64, n: u64) -> (f64, f64) {
    wilson_z(k, n, Z95)
}

pub fn wilson_z(k: u64, n: u64, z: f64) -> (f64, f64) {
    if n == 0 {
        return (0.0, 1.0);
    }
    let n_f = n as f64;
    let p = k as f64 / n_f;
    let z2 = z * z;
    let denom = 1.0 + z2 / n_f;
    let centre = (p + z2 / (2.0 * n_f)) / denom;
    let half = z / denom * (p * (1.0 - p) / n_f + z2 / (4.0 * n_f * n_f)).sqrt();
    ((centre - half).max(0.0), (centre + half).min(1.0))
}

/// Newcombe's hybrid score interval (Newcombe 1998, method 10) for p1 - p2 of two independent
/// proportions k1/n1 and k2/n2 (95%).
pub fn newcombe_diff(k1: u64, n1: u64, k2: u64, n2: u64) -> (f64, f64) {
    let p1 = if n1 > 0 { k1 as f64 / n1 as f64 } else { 0.0 };
    let p2 = if n2 > 0 { k2 as f64 / n2 as f64 } else { 0.0 };
    let (l1, u1) = wilson(k1, n1);
    let (l2, u2) = wilson(k2, n2);
    let d = p1 - p2;
    let lo = d - ((p1 - l1).powi(2) + (u2 - p2).powi(2)).sqrt();
    let hi = d + ((u1 - p1).powi(2) + (p2 - l2).powi(2)).sqrt();
    (lo.max(-1.0), hi.min(1.0))
}

#[cfg(test)]
mod tests {
    use super::*;
    fn r4(x: f64) -> f64 {
        (x * 1e4).round() / 1e4
    }
    #[test]
    fn newcombe_examples() {
        let (l, u) = newcombe_diff(56, 70, 48, 80);
        assert_eq!((r4(l), r4(u)), (0.0524, 0.3339));
        let (l, u) = newcombe_diff(10, 10, 0, 10);
        assert_eq!((r4(l), r4(u)), (0.6075, 1.0));
    }
    #[test]
    fn wilson_examples() {
        // Newcombe 1998 Table I: 81/263 -> 0.2553, 0.3662 ; 0/10 -> 0, 0.2775
        let (l, u) = wilson(81, 263);
        assert_eq!((r4(l), r4(u)), (0.2553, 0.3662));
        let (l, u) = wilson(0, 10);
        assert_eq!((r4(l), r4(u)), (0.0, 0.2775));
    }
}
