//! The monitor's false-alarm guarantee, by simulation: calibrate a threshold on n successful
//! episodes, measure how often it fires on fresh successes, over 200 resamplings of the
//! calibration set. Split conformal prediction promises `α − 1/(n + 1) ≤ P(alarm) ≤ α` on
//! average over calibration sets (the lower bound holds without ties, as with continuous scores).

use evalstats::splitmix::SplitMix64;
use verifier::monitor::{conformal_threshold, first_alarm, peak, Statistic};

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
