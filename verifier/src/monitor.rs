//! The failure monitor's contract, once: the monitor record (what a calibration produced and
//! the store keeps), the running statistic over a verifier's per-step scores, the alarm rule,
//! and the split-conformal threshold. The offline evaluation (`monitor` crate), the robot
//! (`steer::Monitor`) and the Python package all step the same [`MonitorState`], so they raise
//! the same alarm at the same step.
//!
//! The rule. At step `t` the verifier scores the executed chunk: `s_t` (a classifier's success
//! probability, or a Q value). The risk is `r_t = 1 − s_t`, smoothed by an exponential moving
//! average `m_t = β·m_{t−1} + (1 − β)·r_t` (`m_0 = r_0`). The alarm fires at the first step with
//! `m_t > τ`. Calibration takes each calibration success's peak `max_t m_t` and sets `τ` to the
//! `⌈(n + 1)(1 − α)⌉`-th smallest of the n peaks (split conformal prediction). A fresh successful
//! episode, exchangeable with the calibration episodes, then has peak `> τ` — the alarm fires —
//! with probability at most α (and at least α − 1/(n + 1) when peaks have no ties).
//!
//! That guarantee is marginal: on average over the draw of the calibration episodes. One
//! calibration's own false-alarm rate can be well above α. The training-conditional threshold
//! ([`training_conditional_threshold`]) instead takes the k-th smallest peak with the smallest k
//! such that `P(Binomial(n, 1 − α) ≥ k) ≤ δ`: the false-alarm rate on fresh successes of the
//! calibration at hand is then at most α with probability at least `1 − δ` over the draw (the
//! coverage of the k-th order statistic of n exchangeable peaks is Beta(k, n + 1 − k), whose CDF
//! at 1 − α is that binomial tail). It needs `n ≥ ln δ / ln(1 − α)`
//! ([`min_calibration_episodes_conditional`]). Its record names the method
//! [`SPLIT_CONFORMAL_PEAK_PAC`] and holds the confidence `1 − δ`.

use serde::{Deserialize, Serialize};

use crate::{Result, VerifierError};

/// The record's schema version.
pub const MONITOR_SCHEMA_VERSION: u32 = 1;
/// The calibration method the record names: the split-conformal threshold, whose false-alarm
/// guarantee holds on average over calibration draws (the record has no `confidence`).
pub const SPLIT_CONFORMAL_PEAK: &str = "split_conformal_peak";
/// The training-conditional method: the false-alarm rate of this calibration is at most α with
/// probability at least the record's `confidence` (1 − δ) over the calibration draw.
pub const SPLIT_CONFORMAL_PEAK_PAC: &str = "split_conformal_peak_training_conditional";

/// The running statistic the alarm thresholds.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Statistic {
    /// Exponential moving average of the risk `1 − score` with weight `smoothing` (β, in [0, 1))
    /// on the past; β = 0 is the raw per-step risk.
    RiskEma { smoothing: f64 },
}

impl Statistic {
    pub fn check(&self) -> Result<()> {
        match *self {
            Statistic::RiskEma { smoothing } if (0.0..1.0).contains(&smoothing) => Ok(()),
            Statistic::RiskEma { smoothing } => {
                Err(VerifierError::Input(format!("monitor smoothing must be in [0, 1), got {smoothing}")))
            }
        }
    }
}

/// A calibrated monitor: immutable; the store names it by the sha256 of its JSON.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MonitorRecord {
    pub schema_version: u32,
    /// The verifier artifact whose scores it thresholds; it refuses any other.
    pub artifact_id: String,
    pub policy: String,
    pub checkpoint: String,
    /// [`SPLIT_CONFORMAL_PEAK`] (marginal guarantee) or [`SPLIT_CONFORMAL_PEAK_PAC`]
    /// (training-conditional, with `confidence`).
    pub method: String,
    pub statistic: Statistic,
    /// The false-alarm rate on successful episodes it guarantees (at most): on average over
    /// calibration draws, or, with `confidence`, for this calibration with that probability.
    pub alpha: f64,
    /// 1 − δ of the training-conditional method: the probability over the calibration draw that
    /// this threshold's false-alarm rate is at most α. Absent for the marginal method (whose
    /// records, serialised without it, keep their bytes and ids).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub confidence: Option<f64>,
    /// τ: the alarm fires when the statistic exceeds it.
    pub threshold: f64,
    /// The store version whose labels the calibration read.
    pub version: i64,
    /// The seed that drew the calibration episodes from the pool.
    pub seed: u64,
    /// The successful episodes the threshold was calibrated on, by id.
    pub calibration_episodes: Vec<String>,
}

impl MonitorRecord {
    /// Parses and checks a record (schema, method and confidence, statistic, α, a finite threshold).
    pub fn from_json(bytes: &[u8]) -> Result<Self> {
        let r: MonitorRecord = serde_json::from_slice(bytes)
            .map_err(|e| VerifierError::Input(format!("monitor record is invalid: {e}")))?;
        r.check()?;
        Ok(r)
    }

    pub fn check(&self) -> Result<()> {
        if self.schema_version != MONITOR_SCHEMA_VERSION {
            return Err(VerifierError::Input(format!(
                "monitor record schema_version {} (this client knows {MONITOR_SCHEMA_VERSION})",
                self.schema_version
            )));
        }
        match (self.method.as_str(), self.confidence) {
            (SPLIT_CONFORMAL_PEAK, None) => {}
            (SPLIT_CONFORMAL_PEAK, Some(c)) => {
                return Err(VerifierError::Input(format!(
                    "monitor method {SPLIT_CONFORMAL_PEAK:?} has a marginal guarantee and no confidence, got \
                     confidence {c}"
                )))
            }
            (SPLIT_CONFORMAL_PEAK_PAC, Some(c)) => check_confidence(c)?,
            (SPLIT_CONFORMAL_PEAK_PAC, None) => {
                return Err(VerifierError::Input(format!(
                    "monitor method {SPLIT_CONFORMAL_PEAK_PAC:?} needs its confidence (1 - delta)"
                )))
            }
            (m, _) => return Err(VerifierError::Input(format!("unknown monitor method {m:?}"))),
        }
        self.statistic.check()?;
        if !(self.alpha > 0.0 && self.alpha < 1.0) {
            return Err(VerifierError::Input(format!("monitor alpha must be in (0, 1), got {}", self.alpha)));
        }
        if !self.threshold.is_finite() {
            return Err(VerifierError::Input("monitor threshold is not finite".into()));
        }
        Ok(())
    }

    /// Refuses a verifier the monitor was not calibrated for: its scores would be thresholded
    /// against another model's scale, and the false-alarm guarantee would be void.
    pub fn check_artifact(&self, artifact_id: Option<&str>) -> Result<()> {
        match artifact_id {
            Some(id) if id == self.artifact_id => Ok(()),
            Some(id) => Err(VerifierError::Input(format!(
                "monitor was calibrated for verifier artifact {} and cannot run on artifact {id}: calibrate one \
                 for it (`ufops monitor calibrate --artifact {id}`)",
                self.artifact_id
            ))),
            None => Err(VerifierError::Input(format!(
                "monitor was calibrated for verifier artifact {}, and this verifier has no artifact id to check it \
                 against (load it from its artifact directory, the store or the API)",
                self.artifact_id
            ))),
        }
    }

    pub fn state(&self) -> MonitorState {
        MonitorState::new(self.statistic, self.threshold)
    }

    /// The guarantee of the threshold, in words.
    pub fn guarantee(&self) -> String {
        match self.confidence {
            Some(c) => format!(
                "training-conditional: false-alarm rate at most {} with probability at least {c} over the \
                 calibration draw",
                self.alpha
            ),
            None => format!(
                "marginal (split conformal): false-alarm rate at most {} on average over calibration draws",
                self.alpha
            ),
        }
    }
}

fn check_confidence(confidence: f64) -> Result<()> {
    if confidence > 0.0 && confidence < 1.0 {
        Ok(())
    } else {
        Err(VerifierError::Input(format!(
            "monitor confidence (1 - delta) must be in (0, 1), got {confidence}"
        )))
    }
}

/// What one step of the monitor reports.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct MonitorStep {
    /// The verifier's score of this step.
    pub score: f32,
    /// The running statistic after this step.
    pub statistic: f64,
    /// The statistic exceeds the threshold at this step.
    pub alarm: bool,
    /// This is the episode's first alarm.
    pub first_alarm: bool,
}

/// The monitor's state over one episode; [`MonitorState::reset`] between episodes.
#[derive(Debug, Clone)]
pub struct MonitorState {
    statistic: Statistic,
    threshold: f64,
    current: Option<f64>,
    alarmed: bool,
}

impl MonitorState {
    pub fn new(statistic: Statistic, threshold: f64) -> Self {
        MonitorState { statistic, threshold, current: None, alarmed: false }
    }

    pub fn reset(&mut self) {
        self.current = None;
        self.alarmed = false;
    }

    /// The statistic after a step scored `score`.
    #[inline]
    pub fn update(&mut self, score: f32) -> MonitorStep {
        let risk = 1.0 - score as f64;
        let m = match (self.statistic, self.current) {
            (_, None) => risk,
            (Statistic::RiskEma { smoothing }, Some(prev)) => smoothing * prev + (1.0 - smoothing) * risk,
        };
        self.current = Some(m);
        let alarm = m > self.threshold;
        let first_alarm = alarm && !self.alarmed;
        self.alarmed |= alarm;
        MonitorStep { score, statistic: m, alarm, first_alarm }
    }

    /// Whether the alarm has fired in this episode.
    pub fn alarmed(&self) -> bool {
        self.alarmed
    }
}

/// An episode's peak statistic (its conformity score): `max_t m_t`; −∞ for no steps.
pub fn peak(statistic: Statistic, scores: &[f32]) -> f64 {
    let mut s = MonitorState::new(statistic, f64::INFINITY);
    scores.iter().map(|&x| s.update(x).statistic).fold(f64::NEG_INFINITY, f64::max)
}

/// The first step at which the alarm fires on an episode's scores, if any.
pub fn first_alarm(statistic: Statistic, threshold: f64, scores: &[f32]) -> Option<usize> {
    let mut s = MonitorState::new(statistic, threshold);
    scores.iter().position(|&x| s.update(x).alarm)
}

/// The fewest calibration episodes for which a finite threshold exists at `alpha`:
/// `⌈(n + 1)(1 − α)⌉ ≤ n` ⇔ `n ≥ (1 − α)/α`.
pub fn min_calibration_episodes(alpha: f64) -> usize {
    ((1.0 - alpha) / alpha - 1e-9).ceil().max(1.0) as usize
}

/// The rank k (1-based) of the split-conformal threshold among n calibration peaks,
/// `⌈(n + 1)(1 − α)⌉`; `None` when it exceeds n.
pub fn conformal_rank(n: usize, alpha: f64) -> Option<usize> {
    let k = ((n as f64 + 1.0) * (1.0 - alpha) - 1e-9).ceil() as usize;
    (n > 0 && k <= n).then_some(k.max(1))
}

/// The split-conformal threshold: the `⌈(n + 1)(1 − α)⌉`-th smallest of the calibration peaks.
pub fn conformal_threshold(peaks: &[f64], alpha: f64) -> Result<f64> {
    if !(alpha > 0.0 && alpha < 1.0) {
        return Err(VerifierError::Input(format!("alpha must be in (0, 1), got {alpha}")));
    }
    let mut p: Vec<f64> = peaks.iter().copied().filter(|x| x.is_finite()).collect();
    let n = p.len();
    let k = ((n as f64 + 1.0) * (1.0 - alpha) - 1e-9).ceil() as usize;
    if n == 0 || k > n {
        return Err(VerifierError::Input(format!(
            "calibrating at alpha = {alpha} needs at least {} successful episodes with steps, got {n}",
            min_calibration_episodes(alpha)
        )));
    }
    p.sort_by(f64::total_cmp);
    Ok(p[k.max(1) - 1])
}

/// `ln P(Binomial(n, p) ≥ k)`, summed in log space over `lgamma`'s log-binomial coefficients
/// (stable for any n: no term under- or overflows); `p` in (0, 1).
pub fn ln_binomial_upper_tail(n: usize, p: f64, k: usize) -> f64 {
    if k == 0 {
        return 0.0;
    }
    if k > n {
        return f64::NEG_INFINITY;
    }
    let (lp, lq) = (p.ln(), (-p).ln_1p());
    let ln_n1 = libm::lgamma(n as f64 + 1.0);
    let term = |i: usize| {
        ln_n1 - libm::lgamma(i as f64 + 1.0) - libm::lgamma((n - i) as f64 + 1.0)
            + i as f64 * lp
            + (n - i) as f64 * lq
    };
    let terms: Vec<f64> = (k..=n).map(term).collect();
    let max = terms.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    max + terms.iter().map(|t| (t - max).exp()).sum::<f64>().ln()
}

/// `P(Binomial(n, p) ≥ k)`: the CDF at `p` of Beta(k, n + 1 − k), the coverage of the k-th
/// smallest of n exchangeable scores.
pub fn binomial_upper_tail(n: usize, p: f64, k: usize) -> f64 {
    ln_binomial_upper_tail(n, p, k).exp()
}

fn check_alpha_delta(alpha: f64, delta: f64) -> Result<()> {
    if !(alpha > 0.0 && alpha < 1.0) {
        return Err(VerifierError::Input(format!("alpha must be in (0, 1), got {alpha}")));
    }
    if !(delta > 0.0 && delta < 1.0) {
        return Err(VerifierError::Input(format!("delta (1 - confidence) must be in (0, 1), got {delta}")));
    }
    Ok(())
}

/// The fewest calibration episodes for which a training-conditional threshold exists at
/// (`alpha`, `delta`): the largest peak (k = n) qualifies iff `(1 − α)^n ≤ δ`, so
/// `n = ⌈ln δ / ln(1 − α)⌉`. Panics unless both are in (0, 1).
pub fn min_calibration_episodes_conditional(alpha: f64, delta: f64) -> usize {
    check_alpha_delta(alpha, delta).expect("alpha and delta in (0, 1)");
    let (p, ln_delta) = (1.0 - alpha, delta.ln());
    // The closed form, then the very test `training_conditional_rank` makes (k = n), so that the
    // two agree at the boundary whatever the rounding.
    let qualifies = |n: usize| ln_binomial_upper_tail(n, p, n) <= ln_delta;
    let mut n = (ln_delta / (-alpha).ln_1p()).ceil().max(1.0) as usize;
    while n > 1 && qualifies(n - 1) {
        n -= 1;
    }
    while !qualifies(n) {
        n += 1;
    }
    n
}

/// The rank k (1-based) of the training-conditional threshold among n calibration peaks: the
/// smallest k with `P(Binomial(n, 1 − α) ≥ k) ≤ δ`; `None` when no k ≤ n qualifies.
pub fn training_conditional_rank(n: usize, alpha: f64, delta: f64) -> Option<usize> {
    if n == 0 {
        return None;
    }
    let p = 1.0 - alpha;
    let ln_delta = delta.ln();
    if ln_binomial_upper_tail(n, p, n) > ln_delta {
        return None;
    }
    // The tail falls as k grows: bisect for the first k at or under δ.
    let (mut lo, mut hi) = (1usize, n);
    while lo < hi {
        let mid = lo + (hi - lo) / 2;
        if ln_binomial_upper_tail(n, p, mid) <= ln_delta {
            hi = mid;
        } else {
            lo = mid + 1;
        }
    }
    Some(lo)
}

/// The training-conditional threshold: the k-th smallest calibration peak
/// ([`training_conditional_rank`]), so that with probability at least `1 − δ` over the
/// calibration draw a fresh successful episode raises the alarm with probability at most α.
/// Refuses, naming the count needed, when the peaks are too few for that (α, δ).
pub fn training_conditional_threshold(peaks: &[f64], alpha: f64, delta: f64) -> Result<f64> {
    check_alpha_delta(alpha, delta)?;
    let mut p: Vec<f64> = peaks.iter().copied().filter(|x| x.is_finite()).collect();
    let n = p.len();
    let Some(k) = training_conditional_rank(n, alpha, delta) else {
        return Err(VerifierError::Input(format!(
            "calibrating at alpha = {alpha} with confidence {} (1 - delta) needs at least {} successful \
             episodes with steps, got {n}",
            1.0 - delta,
            min_calibration_episodes_conditional(alpha, delta)
        )));
    };
    p.sort_by(f64::total_cmp);
    Ok(p[k - 1])
}

/// `ln C(a, b)`.
fn ln_choose(a: usize, b: usize) -> f64 {
    libm::lgamma(a as f64 + 1.0) - libm::lgamma(b as f64 + 1.0) - libm::lgamma((a - b) as f64 + 1.0)
}

/// Over a uniformly random partition of `n + m` distinct peaks into `n` calibration and `m`
/// held-out ones: the probability that the held-out false-alarm rate of the k-th smallest
/// calibration peak exceeds α (more than α·m held-out peaks above it). It depends only on the
/// sizes and the rank, not on the peaks: the held-out peaks above the threshold are those
/// ranked above the (n − k + 1)-th largest calibration peak in the pooled order. A measured
/// rate on m held-out episodes is noisy, so even a threshold whose rate on fresh successes is
/// at most α exceeds α on the held-out part this often.
pub fn held_out_exceedance(n: usize, m: usize, k: usize, alpha: f64) -> f64 {
    assert!(k >= 1 && k <= n, "rank {k} of {n}");
    let total = n + m;
    let j = n - k; // calibration peaks above the threshold
    let ln_all = ln_choose(total, n);
    // h held-out peaks above it: the top h + j + 1 of the pooled order hold j calibration peaks
    // and h held-out ones, then the threshold; the rest hold the other n − j − 1.
    (0..=m)
        .filter(|&h| h as f64 / m as f64 > alpha)
        .map(|h| (ln_choose(h + j, j) + ln_choose(total - h - j - 1, n - j - 1) - ln_all).exp())
        .sum::<f64>()
        .min(1.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    const EMA: Statistic = Statistic::RiskEma { smoothing: 0.7 };

    #[test]
    fn threshold_is_the_conformal_order_statistic() {
        let peaks: Vec<f64> = (1..=19).map(|i| i as f64).collect();
        // n = 19, α = 0.1: ⌈20 · 0.9⌉ = 18th smallest.
        assert_eq!(conformal_threshold(&peaks, 0.1).unwrap(), 18.0);
        assert_eq!(min_calibration_episodes(0.1), 9);
        assert!(conformal_threshold(&peaks[..8], 0.1).is_err());
        assert_eq!(conformal_threshold(&peaks[..9], 0.1).unwrap(), 9.0);
        assert_eq!(
            (conformal_rank(19, 0.1), conformal_rank(69, 0.1), conformal_rank(8, 0.1)),
            (Some(18), Some(63), None)
        );
    }

    /// `P(Binomial(n, p) ≥ k)` summed directly: each coefficient as a running product.
    fn direct_tail(n: usize, p: f64, k: usize) -> f64 {
        let mut total = 0.0;
        let mut coef = 1.0f64; // C(n, i)
        for i in 0..=n {
            if i >= k {
                total += coef * p.powi(i as i32) * (1.0 - p).powi((n - i) as i32);
            }
            coef = coef * (n - i) as f64 / (i + 1) as f64;
        }
        total
    }

    #[test]
    fn the_binomial_tail_matches_a_direct_sum() {
        for (n, p) in [(22, 0.9), (69, 0.9), (138, 0.8), (40, 0.5)] {
            for k in 0..=n + 1 {
                let (a, b) = (binomial_upper_tail(n, p, k), direct_tail(n, p, k));
                assert!((a - b).abs() <= 1e-12 + 1e-9 * b, "n {n} p {p} k {k}: {a} vs {b}");
            }
        }
        // Far in the tail (0.9^1000 ≈ 1.7e-46) and at a large n, the log-space sum keeps its figure.
        let ln = ln_binomial_upper_tail(1000, 0.9, 1000);
        assert!((ln - 1000.0 * 0.9f64.ln()).abs() < 1e-9, "{ln}");
        assert!(binomial_upper_tail(100_000, 0.9, 90_500).is_finite());
    }

    #[test]
    fn training_conditional_rank_and_minimum_n_have_their_exact_figures() {
        // (1 − α)^n ≤ δ: 0.9^22 = 0.0985 ≤ 0.1 < 0.9^21 = 0.1094.
        assert_eq!(min_calibration_episodes_conditional(0.1, 0.1), 22);
        assert_eq!(min_calibration_episodes_conditional(0.1, 0.05), 29);
        assert_eq!(min_calibration_episodes_conditional(0.05, 0.1), 45);
        assert_eq!(min_calibration_episodes_conditional(0.01, 0.01), 459);
        assert_eq!(training_conditional_rank(21, 0.1, 0.1), None);
        assert_eq!(training_conditional_rank(22, 0.1, 0.1), Some(22));
        // n = 69 at α = δ = 0.1: P(Bin(69, 0.9) ≥ 66) = 0.0762 ≤ 0.1 < P(≥ 65) = 0.1680; the
        // marginal rank is ⌈70 · 0.9⌉ = 63.
        assert_eq!(training_conditional_rank(69, 0.1, 0.1), Some(66));
        assert!((direct_tail(69, 0.9, 66) - 0.076234225).abs() < 1e-8);
        assert!((direct_tail(69, 0.9, 65) - 0.167967862).abs() < 1e-8);
        assert_eq!(training_conditional_rank(49, 0.1, 0.1), Some(48));
        assert_eq!(training_conditional_rank(138, 0.1, 0.1), Some(130));
        assert_eq!(training_conditional_rank(1000, 0.1, 0.1), Some(913));
        // Against the direct computation: the smallest k whose tail is at most δ.
        for (n, alpha, delta) in [(69, 0.1, 0.1), (100, 0.2, 0.05), (30, 0.1, 0.5)] {
            let want = (1..=n).find(|&k| direct_tail(n, 1.0 - alpha, k) <= delta);
            assert_eq!(training_conditional_rank(n, alpha, delta), want, "n {n} alpha {alpha} delta {delta}");
        }
    }

    #[test]
    fn training_conditional_threshold_takes_its_order_statistic_or_refuses() {
        let peaks: Vec<f64> = (1..=69).rev().map(|i| i as f64).collect();
        assert_eq!(training_conditional_threshold(&peaks, 0.1, 0.1).unwrap(), 66.0);
        assert_eq!(conformal_threshold(&peaks, 0.1).unwrap(), 63.0);
        assert_eq!(training_conditional_threshold(&peaks[47..], 0.1, 0.1).unwrap(), 22.0);
        let e = training_conditional_threshold(&peaks[48..], 0.1, 0.1).unwrap_err().to_string();
        assert!(e.contains("needs at least 22 successful episodes") && e.contains("got 21"), "{e}");
        // Peaks of episodes without steps do not count.
        let mut with_empty = peaks[47..].to_vec();
        with_empty[0] = f64::NEG_INFINITY;
        assert!(training_conditional_threshold(&with_empty, 0.1, 0.1).is_err());
        assert!(training_conditional_threshold(&peaks, 0.1, 1.0).is_err());
        assert!(training_conditional_threshold(&peaks, 0.0, 0.1).is_err());
    }

    #[test]
    fn held_out_exceedance_has_its_exact_figures() {
        // 138 peaks split 69/69 at α = 0.1 (more than 6.9 of 69 held-out alarms): the marginal
        // rank 63 exceeds in half the partitions (by symmetry: 7 or more held-out peaks above the
        // 7th largest of 69 calibration peaks), the training-conditional rank 66 (δ = 0.1) in 16.3%.
        assert!((held_out_exceedance(69, 69, 63, 0.1) - 0.5).abs() < 1e-9);
        assert!((held_out_exceedance(69, 69, 66, 0.1) - 0.162622357).abs() < 1e-8);
        assert!((held_out_exceedance(69, 69, 69, 0.1) - 0.006658983).abs() < 1e-8);
        // Against a direct count over all C(6, 3) = 20 partitions of 6 peaks (3 and 3), rank 2
        // at α = 0.4: more than 1.2 held-out peaks above the 2nd smallest calibration peak.
        let mut above = 0;
        for mask in 0u32..64 {
            if mask.count_ones() != 3 {
                continue;
            }
            let cal: Vec<u32> = (0..6).filter(|i| mask >> i & 1 == 1).collect();
            let tau = cal[1];
            let held: usize = (0..6).filter(|i| mask >> i & 1 == 0 && *i > tau).count();
            above += (held as f64 / 3.0 > 0.4) as usize;
        }
        assert!((held_out_exceedance(3, 3, 2, 0.4) - above as f64 / 20.0).abs() < 1e-12, "{above}");
    }

    #[test]
    fn ema_and_alarm_follow_the_rule() {
        let mut s = MonitorState::new(EMA, 0.5);
        let a = s.update(0.9); // risk 0.1
        assert!((a.statistic - 0.1).abs() < 1e-6 && !a.alarm);
        let b = s.update(0.0); // 0.7·0.1 + 0.3·1
        assert!((b.statistic - 0.37).abs() < 1e-6 && !b.alarm);
        let c = s.update(0.0); // 0.7·0.37 + 0.3
        assert!(c.alarm && c.first_alarm);
        assert!(!s.update(0.0).first_alarm);
        s.reset();
        assert!(!s.alarmed());
        assert_eq!(first_alarm(EMA, 0.5, &[0.9, 0.0, 0.0, 0.0]), Some(2));
        assert!((peak(EMA, &[0.9, 0.0, 0.0]) - c.statistic).abs() < 1e-12);
    }

    #[test]
    fn a_record_refuses_another_artifact() {
        let r = MonitorRecord {
            schema_version: 1,
            artifact_id: "aaaa".into(),
            policy: "p".into(),
            checkpoint: "c".into(),
            method: SPLIT_CONFORMAL_PEAK.into(),
            statistic: EMA,
            alpha: 0.1,
            confidence: None,
            threshold: 0.4,
            version: 1,
            seed: 0,
            calibration_episodes: vec![],
        };
        assert!(r.check_artifact(Some("aaaa")).is_ok());
        let e = r.check_artifact(Some("bbbb")).unwrap_err().to_string();
        assert!(e.contains("calibrated for verifier artifact aaaa") && e.contains("bbbb"), "{e}");
        assert!(r.check_artifact(None).is_err());
        let bytes = serde_json::to_vec(&r).unwrap();
        assert_eq!(MonitorRecord::from_json(&bytes).unwrap(), r);
        let bad = String::from_utf8(bytes).unwrap().replace("0.1", "1.5");
        assert!(MonitorRecord::from_json(bad.as_bytes()).is_err());
    }

    #[test]
    fn a_record_states_its_guarantee_and_old_records_keep_their_bytes() {
        // A record written before `confidence` existed reads back and serialises to the same
        // bytes (the store's id is their hash).
        let old = r#"{"schema_version":1,"artifact_id":"aaaa","policy":"p","checkpoint":"c","method":"split_conformal_peak","statistic":{"kind":"risk_ema","smoothing":0.8},"alpha":0.1,"threshold":0.4,"version":3,"seed":0,"calibration_episodes":["e1"]}"#;
        let r = MonitorRecord::from_json(old.as_bytes()).unwrap();
        assert_eq!(r.confidence, None);
        assert_eq!(serde_json::to_string(&r).unwrap(), old);
        assert!(r.guarantee().starts_with("marginal"), "{}", r.guarantee());

        let pac =
            MonitorRecord { method: SPLIT_CONFORMAL_PEAK_PAC.into(), confidence: Some(0.9), ..r.clone() };
        pac.check().unwrap();
        let json = serde_json::to_string(&pac).unwrap();
        assert!(json.contains(r#""alpha":0.1,"confidence":0.9,"threshold""#), "{json}");
        assert_eq!(MonitorRecord::from_json(json.as_bytes()).unwrap(), pac);
        assert!(pac.guarantee().contains("probability at least 0.9"), "{}", pac.guarantee());

        let refused = |r: MonitorRecord, want: &str| {
            let e = r.check().unwrap_err().to_string();
            assert!(e.contains(want), "{e}");
        };
        refused(MonitorRecord { confidence: None, ..pac.clone() }, "needs its confidence");
        refused(MonitorRecord { confidence: Some(1.0), ..pac.clone() }, "must be in (0, 1)");
        refused(MonitorRecord { confidence: Some(f64::NAN), ..pac.clone() }, "must be in (0, 1)");
        refused(MonitorRecord { confidence: Some(0.9), ..r.clone() }, "marginal guarantee");
        refused(MonitorRecord { method: "other".into(), ..r }, "unknown monitor method");
    }
}
