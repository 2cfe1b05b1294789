//! The monitor's false-alarm guarantee, by simulation: calibrate a threshold on n successful
//! episodes, measure how often it fires on fresh successes, over 200 resamplings of the
//! calibration set. Split conformal prediction promises `α − 1/(n + 1) ≤ P(alarm) ≤ α` on
//! average over calibration sets (the lower bound holds without ties, as with continuous scores).
//! The training-conditional threshold promises more of each calibration: its false-alarm rate is
//! at most α with probability at least 1 − δ over the calibration draw.

use evalstats::splitmix::SplitMix64;
use verifier::monitor::{
    binomial_upper_tail, conformal_threshold, first_alarm, peak, training_conditional_rank,
    training_conditional_threshold, Statistic,
};

const STAT: Statistic = Statistic::RiskEma { smoothing: 0.8 };

/// A successful episode's scores: a verifier fairly sure of success, with an autocorrelated
/// dip now and then (the kind of series that makes a raw threshold fire).
fn success_scores(rng: &mut SplitMix64) -> Vec<f32> {
    let len = 40 + (rng.next_u64() % 80) as usize;
    let mut dip = 0.0f64;
    (0..len)
        .map(|_| {
            dip = 0.9 * dip + 0.1 * rng.next_f64().powi(3) * 4.0;
            let noise = (rng.next_f64() - 0.5) * 0.1;
            (0.9 - dip + noise).clamp(0.0, 1.0) as f32
        })
        .collect()
}

#[test]
fn false_alarm_rate_on_fresh_successes_is_at_most_alpha_over_200_calibrations() {
    let mut rng = SplitMix64(20261127);
    for (alpha, n) in [(0.1, 49), (0.2, 30)] {
        let fresh = 400;
        let mut rates = Vec::new();
        for _ in 0..200 {
            let peaks: Vec<f64> = (0..n).map(|_| peak(STAT, &success_scores(&mut rng))).collect();
            let tau = conformal_threshold(&peaks, alpha).unwrap();
            let fired =
                (0..fresh).filter(|_| first_alarm(STAT, tau, &success_scores(&mut rng)).is_some()).count();
            rates.push(fired as f64 / fresh as f64);
        }
        let mean = rates.iter().sum::<f64>() / rates.len() as f64;
        // 80,000 fresh episodes in all: the mean's standard error is under 0.0015 at α = 0.2.
        let lo = alpha - 1.0 / (n as f64 + 1.0);
        let (min, max) = rates.iter().fold((1.0f64, 0.0f64), |(a, b), &r| (a.min(r), b.max(r)));
        eprintln!("alpha {alpha}, n {n}: mean false-alarm rate {mean:.4} over 200 calibrations (range {min:.3}-{max:.3})");
        assert!(mean <= alpha + 0.006, "alpha {alpha}: mean false-alarm rate {mean:.4} exceeds alpha");
        assert!(
            mean >= lo - 0.006,
            "alpha {alpha}: mean false-alarm rate {mean:.4} below {lo:.4}: too conservative"
        );
    }
}

#[test]
fn a_threshold_taken_from_the_calibration_maximum_of_a_few_episodes_is_not_conformal() {
    // The test can fail: the empirical (1 − α) quantile without the (n + 1) correction fires
    // more often than α on fresh successes at small n.
    let mut rng = SplitMix64(7);
    let (alpha, n) = (0.1, 9);
    let mut fired = 0usize;
    let mut total = 0usize;
    for _ in 0..200 {
        let mut peaks: Vec<f64> = (0..n).map(|_| peak(STAT, &success_scores(&mut rng))).collect();
        peaks.sort_by(f64::total_cmp);
        let naive = peaks[((n as f64) * (1.0 - alpha)).floor() as usize - 1];
        for _ in 0..200 {
            total += 1;
            fired += first_alarm(STAT, naive, &success_scores(&mut rng)).is_some() as usize;
        }
    }
    assert!(fired as f64 / total as f64 > alpha + 0.03, "naive rate {}", fired as f64 / total as f64);
}

#[test]
fn the_training_conditional_threshold_exceeds_alpha_in_at_most_delta_of_200_calibrations() {
    // The test can fail: each calibration's false-alarm rate is measured on the same 20,000 fresh
    // successes (its standard error under 0.0025 at 0.1), and the share of calibrations above α
    // must stay within δ where the split-conformal threshold's is several times δ.
    let mut rng = SplitMix64(20261128);
    let mut fresh: Vec<f64> = (0..20_000).map(|_| peak(STAT, &success_scores(&mut rng))).collect();
    fresh.sort_by(f64::total_cmp);
    // The alarm fires on an episode iff its peak exceeds the threshold.
    let rate = |tau: f64| (fresh.len() - fresh.partition_point(|&p| p <= tau)) as f64 / fresh.len() as f64;
    let delta = 0.1;
    for (alpha, n) in [(0.1, 69), (0.2, 30)] {
        let (mut above_marginal, mut above_conditional) = (0usize, 0usize);
        let (mut sum_marginal, mut sum_conditional) = (0.0, 0.0);
        for _ in 0..200 {
            let peaks: Vec<f64> = (0..n).map(|_| peak(STAT, &success_scores(&mut rng))).collect();
            let marginal = rate(conformal_threshold(&peaks, alpha).unwrap());
            let conditional = rate(training_conditional_threshold(&peaks, alpha, delta).unwrap());
            above_marginal += (marginal > alpha) as usize;
            above_conditional += (conditional > alpha) as usize;
            sum_marginal += marginal;
            sum_conditional += conditional;
        }
        let (fm, fc) = (above_marginal as f64 / 200.0, above_conditional as f64 / 200.0);
        // What the order statistics promise with continuous scores: P(rate > α) = P(Bin(n, 1 − α) ≥ k).
        let k_cond = training_conditional_rank(n, alpha, delta).unwrap();
        let k_marg = ((n as f64 + 1.0) * (1.0 - alpha) - 1e-9).ceil() as usize;
        let (pc, pm) =
            (binomial_upper_tail(n, 1.0 - alpha, k_cond), binomial_upper_tail(n, 1.0 - alpha, k_marg));
        eprintln!(
            "alpha {alpha}, delta {delta}, n {n}: calibrations whose false-alarm rate exceeds alpha: \
             training-conditional (k = {k_cond}) {fc:.3} (theory {pc:.3}), split conformal (k = {k_marg}) {fm:.3} \
             (theory {pm:.3}); mean false-alarm rate {:.4} vs {:.4}",
            sum_conditional / 200.0,
            sum_marginal / 200.0
        );
        // Slack for the 200 calibrations (the share's standard error is about 0.02 at δ) and the
        // fresh sample.
        assert!(
            fc <= delta + 0.03,
            "alpha {alpha}, n {n}: {fc} of calibrations exceed alpha, more than delta"
        );
        assert!(
            fm >= 2.0 * delta,
            "alpha {alpha}, n {n}: the split-conformal share {fm} should be well above delta"
        );
        assert!(fm > fc + 0.1, "the test does not tell the thresholds apart: {fm} vs {fc}");
    }
}
