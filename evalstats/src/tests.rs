//! Published values (Newcombe 1998) and independent computations of the same quantities.

use super::*;

fn r4(x: f64) -> f64 {
    (x * 1e4).round() / 1e4
}

/// Newcombe (1998), "Two-sided confidence intervals for the single proportion: comparison of seven
/// methods", Stat. Med. 17:857-872, Table I, method 3 (the Wilson score interval).
#[test]
fn wilson_matches_newcombe_1998_table_i() {
    for (k, n, lo, hi) in [
        (81, 263, 0.2553, 0.3662),
        (15, 148, 0.0624, 0.1605),
        (0, 20, 0.0, 0.1611),
        (1, 29, 0.0061, 0.1718),
        (0, 10, 0.0, 0.2775),
    ] {
        let (l, u) = wilson(k, n);
        assert_eq!((r4(l), r4(u)), (lo, hi), "{k}/{n}");
    }
}

/// Newcombe (1998), "Interval estimation for the difference between independent proportions:
/// comparison of eleven methods", Stat. Med. 17:873-890, Table II, method 10, examples (a)-(h).
#[test]
fn newcombe_matches_newcombe_1998_table_ii() {
    for (k1, n1, k2, n2, lo, hi) in [
        (56, 70, 48, 80, 0.0524, 0.3339),
        (9, 10, 3, 10, 0.1705, 0.8090),
        (6, 7, 2, 7, 0.0582, 0.8062),
        (5, 56, 0, 29, -0.0381, 0.1926),
        (0, 10, 0, 20, -0.1611, 0.2775),
        (0, 10, 0, 10, -0.2775, 0.2775),
        (10, 10, 0, 20, 0.6791, 1.0),
        (10, 10, 0, 10, 0.6075, 1.0),
    ] {
        let (l, u) = newcombe_diff(k1, n1, k2, n2);
        assert_eq!((r4(l), r4(u)), (lo, hi), "{k1}/{n1} - {k2}/{n2}");
    }
}

/// The Wilson interval's ends are the roots π of (p − π)² = z² π(1 − π) / n: solved here as a
/// quadratic, a different route from the centre ± half-width form of the crate.
fn wilson_by_roots(k: u64, n: u64) -> (f64, f64) {
    let (p, n, z2) = (k as f64 / n as f64, n as f64, Z95 * Z95);
    // (1 + z²/n) π² − (2p + z²/n) π + p² = 0
    let a = 1.0 + z2 / n;
    let b = -(2.0 * p + z2 / n);
    let c = p * p;
    let disc = (b * b - 4.0 * a * c).max(0.0).sqrt();
    ((-b - disc) / (2.0 * a), (-b + disc) / (2.0 * a))
}

/// A small deterministic generator (no dependencies): xorshift64*.
struct Xs(u64);
impl Xs {
    fn next(&mut self, m: u64) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545F4914F6CDD1D) % m
    }
}

#[test]
fn wilson_and_newcombe_agree_with_an_independent_computation() {
    let mut g = Xs(0x9E3779B97F4A7C15);
    for _ in 0..2000 {
        let n1 = 1 + g.next(3000);
        let k1 = g.next(n1 + 1);
        let n2 = 1 + g.next(3000);
        let k2 = g.next(n2 + 1);
        let (l1, u1) = wilson_by_roots(k1, n1);
        let (a, b) = wilson(k1, n1);
        assert!((a - l1).abs() < 1e-12 && (b - u1).abs() < 1e-12, "{k1}/{n1}: {a},{b} vs {l1},{u1}");
        assert!(a <= k1 as f64 / n1 as f64 && k1 as f64 / n1 as f64 <= b);
        // Method 10 from the root form of both Wilson intervals.
        let (l2, u2) = wilson_by_roots(k2, n2);
        let (p1, p2) = (k1 as f64 / n1 as f64, k2 as f64 / n2 as f64);
        let lo = p1 - p2 - ((p1 - l1).powi(2) + (u2 - p2).powi(2)).sqrt();
        let hi = p1 - p2 + ((u1 - p1).powi(2) + (p2 - l2).powi(2)).sqrt();
        let (x, y) = newcombe_diff(k1, n1, k2, n2);
        assert!((x - lo).abs() < 1e-12 && (y - hi).abs() < 1e-12, "{k1}/{n1} - {k2}/{n2}");
        assert!(x <= p1 - p2 && p1 - p2 <= y);
    }
}

#[test]
fn empty_arms_give_the_widest_intervals() {
    assert_eq!(wilson(0, 0), (0.0, 1.0));
    let (lo, hi) = newcombe_diff(0, 0, 0, 0);
    assert!(lo < 0.0 && hi > 0.0 && lo >= -1.0 && hi <= 1.0);
}

/// The bisection against a plain scan over n, and against the normal approximation
/// n ≈ z² (p1 q1 + p2 q2) / d², which it must approach as d shrinks.
#[test]
fn rollouts_to_separate_matches_a_scan_and_the_normal_approximation() {
    for (p1, p2) in [(0.662, 0.947), (0.9, 0.3), (0.5, 0.55), (0.0, 0.2), (1.0, 0.97), (0.662, 0.669)] {
        let n = rollouts_to_separate(p1, p2).unwrap();
        let scan = (1..=n + 5).find(|&m| separates(newcombe_p(p1, m as f64, p2, m as f64, Z95))).unwrap();
        assert_eq!(n, scan, "{p1} vs {p2}");
        assert!(!separates(newcombe_p(p1, (n - 1) as f64, p2, (n - 1) as f64, Z95)));
    }
    for (p1, p2) in [(0.5, 0.52), (0.3, 0.31), (0.66, 0.669)] {
        let n = rollouts_to_separate(p1, p2).unwrap() as f64;
        let approx = Z95 * Z95 * (p1 * (1.0 - p1) + p2 * (1.0 - p2)) / (p1 - p2).powi(2);
        assert!((n / approx - 1.0).abs() < 0.02, "{p1} vs {p2}: {n} vs {approx}");
    }
    assert_eq!(rollouts_to_separate(0.5, 0.5), None);
    assert_eq!(rollouts_to_separate(f64::NAN, 0.5), None);
    assert_eq!(rollouts_to_separate(1.5, 0.5), None);
}

#[test]
fn unlabeled_to_flip_is_the_smallest_count_that_changes_the_answer() {
    let arm = |s, f, u| Arm { successes: s, failures: f, unlabeled: u };
    // Significant now (947/1000 vs 662/1000): 40 unlabeled cannot undo a 28 pp gap.
    assert_eq!(unlabeled_to_flip(&arm(947, 53, 40), &arm(662, 338, 0)), None);
    // Barely significant: a few failures in the row undo it; check minimality by brute force.
    for (row, base) in [
        (arm(60, 40, 30), arm(45, 55, 20)),
        (arm(40, 60, 25), arm(55, 45, 0)),
        (arm(50, 50, 40), arm(50, 50, 40)),
        (arm(10, 10, 5), arm(8, 12, 7)),
    ] {
        let got = unlabeled_to_flip(&row, &base);
        let now = separates(row.diff(&base));
        // Brute force: every split of labels of a of the row's and b of the base's unlabeled.
        let mut best: Option<u64> = None;
        for a in 0..=row.unlabeled {
            for sa in 0..=a {
                for b in 0..=base.unlabeled {
                    for sb in 0..=b {
                        let r = arm(row.successes + sa, row.failures + a - sa, 0);
                        let s = arm(base.successes + sb, base.failures + b - sb, 0);
                        let (lo, hi) = r.diff(&s);
                        let (l0, h0) = row.diff(&base);
                        let changed = if l0 > 0.0 {
                            lo <= 0.0
                        } else if h0 < 0.0 {
                            hi >= 0.0
                        } else {
                            separates((lo, hi))
                        };
                        if changed {
                            best = Some(best.map_or(a + b, |x| x.min(a + b)));
                        }
                    }
                }
            }
        }
        assert_eq!(got, best, "{row:?} vs {base:?} (separates now: {now})");
    }
}
