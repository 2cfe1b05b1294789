//! `evalstats`: the interval arithmetic of success rates, in one place.
//!
//! It owns the Wilson score interval of one rate, Newcombe's hybrid score interval (Newcombe 1998,
//! method 10) of the difference of two independent rates, the number of rollouts per arm an
//! evaluation needs for that difference's interval to exclude 0 at given rates, and how many
//! unlabeled episodes could change whether it does. The sim's summaries, the demo's report and the
//! store's scoreboard all call it, so their numbers agree to the last bit. It also owns the
//! agreement between labelers (Cohen's κ, Krippendorff's α; [`agreement`]), and the
//! anytime-valid sequential comparison of two arms that stays correct when people look after every
//! rollout ([`sequential`]: betting confidence sequences, pairing, Fisher's exact test as the
//! fixed-n reference), and Spearman's rank correlation ([`rank`]). No dependencies.

pub mod agreement;
pub mod rank;
pub mod sequential;
pub mod splitmix;
pub use agreement::{cohen_kappa, krippendorff_alpha_nominal};
pub use rank::spearman;
pub use sequential::{
    compare_pairs, pair_by_key, Decision, Pair, PairedCounts, SequentialConfig, SequentialResult,
    SequentialTest,
};

/// z for a two-sided 95% interval (the 0.975 quantile of the standard normal).
pub const Z95: f64 = 1.959963984540054;

/// Wilson score interval for k successes out of n (95%). n = 0 gives (0, 1).
pub fn wilson(k: u64, n: u64) -> (f64, f64) {
    wilson_z(k, n, Z95)
}

/// [`wilson`] at any z.
pub fn wilson_z(k: u64, n: u64, z: f64) -> (f64, f64) {
    if n == 0 {
        return (0.0, 1.0);
    }
    wilson_p(k as f64 / n as f64, n as f64, z)
}

/// The Wilson interval of an observed proportion `p` over `n` trials (n may be fractional: the
/// sample-size search uses it at the observed rates).
pub fn wilson_p(p: f64, n: f64, z: f64) -> (f64, f64) {
    if n <= 0.0 || !p.is_finite() {
        return (0.0, 1.0);
    }
    let p = p.clamp(0.0, 1.0);
    let z2 = z * z;
    let denom = 1.0 + z2 / n;
    let centre = (p + z2 / (2.0 * n)) / denom;
    let half = z / denom * (p * (1.0 - p) / n + z2 / (4.0 * n * n)).sqrt();
    // At p = 0 (p = 1) the lower (upper) end is exactly 0 (1); centre − half only rounds to it.
    let lo = if p == 0.0 { 0.0 } else { (centre - half).max(0.0) };
    let hi = if p == 1.0 { 1.0 } else { (centre + half).min(1.0) };
    (lo, hi)
}

/// Newcombe's hybrid score interval (Newcombe 1998, method 10) for p1 − p2 of two independent
/// proportions k1/n1 and k2/n2 (95%).
pub fn newcombe_diff(k1: u64, n1: u64, k2: u64, n2: u64) -> (f64, f64) {
    let p = |k: u64, n: u64| if n > 0 { k as f64 / n as f64 } else { 0.0 };
    newcombe_p(p(k1, n1), n1 as f64, p(k2, n2), n2 as f64, Z95)
}

/// Method 10 from observed proportions and (possibly fractional) sizes, at any z.
pub fn newcombe_p(p1: f64, n1: f64, p2: f64, n2: f64, z: f64) -> (f64, f64) {
    let (l1, u1) = wilson_p(p1, n1, z);
    let (l2, u2) = wilson_p(p2, n2, z);
    // An empty arm has the interval (0, 1) whatever its "proportion": centre it at 0, as the
    // counts version always did.
    let p1 = if n1 > 0.0 { p1 } else { 0.0 };
    let p2 = if n2 > 0.0 { p2 } else { 0.0 };
    let d = p1 - p2;
    let lo = d - ((p1 - l1).powi(2) + (u2 - p2).powi(2)).sqrt();
    let hi = d + ((u1 - p1).powi(2) + (p2 - l2).powi(2)).sqrt();
    (lo.max(-1.0), hi.min(1.0))
}

/// Whether a difference interval excludes 0.
pub fn separates((lo, hi): (f64, f64)) -> bool {
    lo > 0.0 || hi < 0.0
}

/// The most rollouts per arm [`rollouts_to_separate`] looks at.
pub const MAX_ROLLOUTS: u64 = 1 << 40;

/// The smallest number of rollouts per arm (the same in both) for which the Newcombe 95%
/// interval of p1 − p2 excludes 0, if the two arms kept the observed rates p1 and p2. `None`
/// when the rates are equal (no number suffices) or either is not a proportion. The interval
/// narrows as n grows at fixed rates, so a bisection finds the boundary.
pub fn rollouts_to_separate(p1: f64, p2: f64) -> Option<u64> {
    if !(0.0..=1.0).contains(&p1) || !(0.0..=1.0).contains(&p2) || p1 == p2 {
        return None;
    }
    let ok = |n: u64| separates(newcombe_p(p1, n as f64, p2, n as f64, Z95));
    if !ok(MAX_ROLLOUTS) {
        return None;
    }
    let (mut lo, mut hi) = (0u64, MAX_ROLLOUTS); // !ok(lo) (n = 0 never separates), ok(hi)
    if ok(1) {
        return Some(1);
    }
    lo = lo.max(1);
    while hi - lo > 1 {
        let mid = lo + (hi - lo) / 2;
        if ok(mid) {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    Some(hi)
}

/// One arm of a comparison: labeled successes and failures, and episodes without a label yet.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Arm {
    pub successes: u64,
    pub failures: u64,
    pub unlabeled: u64,
}

impl Arm {
    pub fn labeled(&self) -> u64 {
        self.successes + self.failures
    }
    /// The Newcombe interval of this arm's rate minus `base`'s, over labeled episodes.
    pub fn diff(&self, base: &Arm) -> (f64, f64) {
        newcombe_diff(self.successes, self.labeled(), base.successes, base.labeled())
    }
}

/// The fewest unlabeled episodes (of `row` and `base` together) whose labels, once given, could
/// change the answer of the Newcombe interval of row − base: when it excludes 0, labels against
/// the observed difference (failures in the better arm, successes in the worse) until it no
/// longer does; when it does not, labels that open the gap, in whichever direction needs fewer,
/// until it does. `None` when even labeling every unlabeled episode so cannot change the answer.
/// O(unlabeled) interval evaluations.
pub fn unlabeled_to_flip(row: &Arm, base: &Arm) -> Option<u64> {
    let (lo, hi) = row.diff(base);
    // `up`: the row gains successes and the baseline failures (the difference grows); `done`
    // says whether the interval after that has the other answer.
    let search = |up: bool, done: &dyn Fn((f64, f64)) -> bool| -> Option<u64> {
        let with = |a: u64, b: u64| {
            let r = if up {
                Arm { successes: row.successes + a, ..*row }
            } else {
                Arm { failures: row.failures + a, ..*row }
            };
            let s = if up {
                Arm { failures: base.failures + b, ..*base }
            } else {
                Arm { successes: base.successes + b, ..*base }
            };
            done(r.diff(&s))
        };
        if !with(row.unlabeled, base.unlabeled) {
            return None;
        }
        // For each a the smallest b that flips does not grow with a (labels in one direction
        // only push further): a two-pointer walk.
        let mut best: Option<u64> = None;
        let mut b = base.unlabeled;
        for a in 0..=row.unlabeled {
            if !with(a, b) {
                continue;
            }
            while b > 0 && with(a, b - 1) {
                b -= 1;
            }
            best = Some(best.map_or(a + b, |x| x.min(a + b)));
            if b == 0 {
                break;
            }
        }
        best
    };
    if lo > 0.0 {
        search(false, &|(l, _)| l <= 0.0)
    } else if hi < 0.0 {
        search(true, &|(_, h)| h >= 0.0)
    } else {
        match (search(true, &|(l, _)| l > 0.0), search(false, &|(_, h)| h < 0.0)) {
            (Some(x), Some(y)) => Some(x.min(y)),
            (x, y) => x.or(y),
        }
    }
}

#[cfg(test)]
mod tests;
