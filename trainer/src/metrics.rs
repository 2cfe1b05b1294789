//! Evaluation metrics: rank-based ROC AUC (ties get average ranks), Pearson correlation, and the
//! calibration of a classifier (accuracy, Brier score, ECE, reliability diagram).

/// ROC AUC of `scores` for binary `labels` (> 0.5 is positive), via the Mann-Whitney statistic
/// with average ranks for ties. `None` when one class is absent.
pub fn roc_auc(scores: &[f32], labels: &[f32]) -> Option<f64> {
    let n = scores.len();
    let mut idx: Vec<usize> = (0..n).collect();
    idx.sort_by(|&a, &b| scores[a].total_cmp(&scores[b]));
    let mut rank_sum_pos = 0f64;
    let mut i = 0;
    while i < n {
        let mut j = i;
        while j + 1 < n && scores[idx[j + 1]] == scores[idx[i]] {
            j += 1;
        }
        // ranks i+1 ..= j+1, average:
        let avg = (i + j + 2) as f64 / 2.0;
        for &k in &idx[i..=j] {
            if labels[k] > 0.5 {
                rank_sum_pos += avg;
            }
        }
        i = j + 1;
    }
    let p = labels.iter().filter(|&&l| l > 0.5).count() as f64;
    let q = n as f64 - p;
    if p == 0.0 || q == 0.0 {
        return None;
    }
    Some((rank_sum_pos - p * (p + 1.0) / 2.0) / (p * q))
}

/// Pearson correlation; `None` if either side has zero variance or fewer than 2 points.
pub fn pearson(x: &[f32], y: &[f32]) -> Option<f64> {
    let n = x.len().min(y.len());
    if n < 2 {
        return None;
    }
    let mx = x[..n].iter().map(|v| *v as f64).sum::<f64>() / n as f64;
    let my = y[..n].iter().map(|v| *v as f64).sum::<f64>() / n as f64;
    let (mut sxy, mut sxx, mut syy) = (0f64, 0f64, 0f64);
    for i in 0..n {
        let (a, b) = (x[i] as f64 - mx, y[i] as f64 - my);
        sxy += a * b;
        sxx += a * a;
        syy += b * b;
    }
    if sxx <= 0.0 || syy <= 0.0 {
        return None;
    }
    Some(sxy / (sxx * syy).sqrt())
}

/// One bin of a reliability diagram: the samples whose predicted probability falls in
/// `[lo, hi)` (the last bin includes 1), their mean prediction and their fraction of positives.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ReliabilityBin {
    pub lo: f64,
    pub hi: f64,
    pub count: usize,
    pub mean_predicted: Option<f64>,
    pub fraction_positive: Option<f64>,
}

/// How well a classifier's probabilities match the labels of a held-out set.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Calibration {
    pub samples: usize,
    /// Share of samples where `p > 0.5` agrees with the label.
    pub accuracy: f64,
    /// Mean of `(p − y)²`.
    pub brier: f64,
    /// Expected calibration error: Σ_bins (count / n) · |mean p − fraction positive|.
    pub ece: f64,
    pub bins: Vec<ReliabilityBin>,
}

/// Accuracy, Brier score, expected calibration error and the reliability diagram of
/// probabilities `probs` against binary `labels` (> 0.5 is positive), over `n_bins` equal-width
/// bins. `None` for no samples.
pub fn calibration(probs: &[f64], labels: &[f32], n_bins: usize) -> Option<Calibration> {
    let n = probs.len().min(labels.len());
    if n == 0 || n_bins == 0 {
        return None;
    }
    let mut sum_p = vec![0f64; n_bins];
    let mut sum_y = vec![0f64; n_bins];
    let mut count = vec![0usize; n_bins];
    let (mut correct, mut brier) = (0usize, 0f64);
    for (&p, &l) in probs[..n].iter().zip(&labels[..n]) {
        let p = p.clamp(0.0, 1.0);
        let y = if l > 0.5 { 1.0 } else { 0.0 };
        if (p > 0.5) == (y > 0.5) {
            correct += 1;
        }
        brier += (p - y) * (p - y);
        let b = ((p * n_bins as f64) as usize).min(n_bins - 1);
        sum_p[b] += p;
        sum_y[b] += y;
        count[b] += 1;
    }
    let mut ece = 0f64;
    let bins = (0..n_bins)
        .map(|b| {
            let c = count[b];
            let (mp, fp) =
                if c > 0 { (Some(sum_p[b] / c as f64), Some(sum_y[b] / c as f64)) } else { (None, None) };
            if let (Some(mp), Some(fp)) = (mp, fp) {
                ece += c as f64 / n as f64 * (mp - fp).abs();
            }
            ReliabilityBin {
                lo: b as f64 / n_bins as f64,
                hi: (b + 1) as f64 / n_bins as f64,
                count: c,
                mean_predicted: mp,
                fraction_positive: fp,
            }
        })
        .collect();
    Some(Calibration { samples: n, accuracy: correct as f64 / n as f64, brier: brier / n as f64, ece, bins })
}

#[cfg(test)]
mod calibration_tests {
    use super::*;

    #[test]
    fn calibration_by_hand() {
        // Four samples: p 0.1 (neg), 0.3 (pos), 0.8 (pos), 0.95 (neg); 2 bins [0, .5), [.5, 1].
        let c = calibration(&[0.1, 0.3, 0.8, 0.95], &[0.0, 1.0, 1.0, 0.0], 2).unwrap();
        assert_eq!(c.samples, 4);
        assert_eq!(c.accuracy, 0.5);
        let brier = (0.01 + 0.49 + 0.04 + 0.9025) / 4.0;
        assert!((c.brier - brier).abs() < 1e-12);
        // bin 0: mean p 0.2, positives 0.5; bin 1: mean p 0.875, positives 0.5.
        let ece = 0.5 * (0.2f64 - 0.5).abs() + 0.5 * (0.875f64 - 0.5).abs();
        assert!((c.ece - ece).abs() < 1e-12);
        assert_eq!(c.bins[1].count, 2);
        assert!((c.bins[1].mean_predicted.unwrap() - 0.875).abs() < 1e-12);
        assert_eq!(c.bins[0].fraction_positive, Some(0.5));
        // A perfectly calibrated, perfectly sharp classifier.
        let c = calibration(&[0.0, 1.0, 1.0], &[0.0, 1.0, 1.0], 10).unwrap();
        assert_eq!((c.accuracy, c.brier, c.ece), (1.0, 0.0, 0.0));
        assert_eq!(c.bins.iter().filter(|b| b.count > 0).count(), 2);
        assert!(calibration(&[], &[], 10).is_none());
    }
}

/// The action-sensitivity figure ([`verifier::quality`]) from held-out scores of the full
/// verifier (`full`) and its observation-only twin (`twin`) on the same samples in the same order,
/// with their binary `labels`: the twin's AUROC, the full one's gain over it, and the AUROC of
/// the full score's excess over the twin's (`full − twin`, what differs between candidate chunks at
/// one observation) within `strata` equal-count bins of the twin's score (pooled, weighted by each
/// bin's positive-negative pairs); and both AUROCs on the bins the twin leaves open. Flagged by
/// [`verifier::ActionSensitivity::flag`].
pub fn action_sensitivity(
    full: &[f32],
    twin: &[f32],
    labels: &[f32],
    strata: usize,
) -> verifier::ActionSensitivity {
    let n = full.len().min(twin.len()).min(labels.len());
    let (full, twin, labels) = (&full[..n], &twin[..n], &labels[..n]);
    let full_auc = roc_auc(full, labels);
    let obs_only_auc = roc_auc(twin, labels);
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&a, &b| twin[a].total_cmp(&twin[b]));
    let strata = strata.clamp(1, n.max(1));
    let (lo, hi) = verifier::quality::UNSURE_POSITIVE_SHARE;
    let (mut weighted, mut pairs) = (0f64, 0f64);
    let mut unsure: Vec<usize> = Vec::new();
    for s in 0..strata {
        let bin = &order[s * n / strata..(s + 1) * n / strata];
        let y: Vec<f32> = bin.iter().map(|&i| labels[i]).collect();
        let pos = y.iter().filter(|&&l| l > 0.5).count() as f64;
        let neg = bin.len() as f64 - pos;
        if bin.is_empty() {
            continue;
        }
        let share = pos / bin.len() as f64;
        if (lo..=hi).contains(&share) {
            unsure.extend_from_slice(bin);
        }
        // What a steering step compares: at one observation the twin's score is shared by every
        // candidate, so candidates differ by the full score's excess over the twin's.
        let scores: Vec<f32> = bin.iter().map(|&i| full[i] - twin[i]).collect();
        if let Some(a) = roc_auc(&scores, &y) {
            weighted += a * pos * neg;
            pairs += pos * neg;
        }
    }
    let pick = |v: &[f32], idx: &[usize]| idx.iter().map(|&i| v[i]).collect::<Vec<f32>>();
    let unsure_labels = pick(labels, &unsure);
    verifier::ActionSensitivity {
        obs_only_auc,
        auc_gain: full_auc.zip(obs_only_auc).map(|(f, t)| f - t),
        action_auc: (pairs > 0.0).then(|| weighted / pairs),
        strata,
        unsure_fraction: if n == 0 { 0.0 } else { unsure.len() as f64 / n as f64 },
        unsure_auc: roc_auc(&pick(full, &unsure), &unsure_labels),
        unsure_obs_only_auc: roc_auc(&pick(twin, &unsure), &unsure_labels),
        flagged: false,
        reason: None,
        twin_seconds: 0.0,
    }
    .flag()
}

#[cfg(test)]
mod action_sensitivity_tests {
    use super::*;

    /// Outcome = (observation good) and (chunk good): the twin sees only the observation.
    fn data(chunk_matters: bool) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let (mut full, mut twin, mut labels) = (vec![], vec![], vec![]);
        for i in 0..400u32 {
            let obs = (i % 20) as f32 / 20.0; // observation risk, 20 levels
            let chunk_good = (i / 20) % 2 == 0;
            let success = obs > 0.3 && (chunk_good || !chunk_matters) || obs > 0.9;
            twin.push(obs);
            full.push(obs + if chunk_good && chunk_matters { 0.5 } else { 0.0 });
            labels.push(if success { 1.0 } else { 0.0 });
        }
        (full, twin, labels)
    }

    #[test]
    fn a_chunk_that_decides_scores_high_and_one_that_does_not_scores_near_chance() {
        let (full, twin, labels) = data(true);
        let s = action_sensitivity(&full, &twin, &labels, 10);
        assert!(s.action_auc.unwrap() > 0.9, "{s:?}");
        assert!(s.auc_gain.unwrap() > 0.1 && !s.flagged, "{s:?}");
        assert!(s.unsure_fraction > 0.0 && s.unsure_auc.unwrap() > s.unsure_obs_only_auc.unwrap());

        // The full verifier's score is the twin's plus noise unrelated to the outcome.
        let (_, twin, labels) = data(false);
        let full: Vec<f32> =
            twin.iter().enumerate().map(|(i, t)| t + 0.01 * ((i * 7919) % 13) as f32).collect();
        let s = action_sensitivity(&full, &twin, &labels, 10);
        assert!(s.action_auc.is_none_or(|a| a < 0.6), "{s:?}");
        assert!(s.auc_gain.unwrap().abs() < 0.05, "{s:?}");
    }

    #[test]
    fn a_twin_that_separates_every_stratum_leaves_nothing_to_the_chunk() {
        let s = action_sensitivity(&[0.1, 0.9], &[0.1, 0.9], &[0.0, 1.0], 2);
        assert_eq!(s.action_auc, None);
        assert_eq!(s.obs_only_auc, Some(1.0));
        assert!(s.flagged, "{s:?}");
        // One outcome only: no verdict.
        let s = action_sensitivity(&[0.1, 0.9], &[0.1, 0.9], &[1.0, 1.0], 2);
        assert!(s.obs_only_auc.is_none() && !s.flagged, "{s:?}");
    }
}

/// What an ensemble measured on the split's held-out samples (`metrics.ensemble`).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct EnsembleMetrics {
    pub members: usize,
    /// Member `k`'s training seed.
    pub seeds: Vec<u64>,
    /// Training episodes, and how many distinct ones each member's resample drew.
    pub train_episodes: usize,
    pub distinct_episodes: Vec<usize>,
    /// Held-out AUROC of the ensemble's score (the members' mean) against success, and of each
    /// member's.
    pub val_auc: Option<f64>,
    pub member_val_auc: Vec<Option<f64>>,
    /// Q only: Pearson correlation of the mean value with the discounted target.
    pub val_pearson: Option<f64>,
    /// Mean over held-out samples of the members' spread.
    pub val_mean_spread: Option<f64>,
    /// Wall time of all members' training.
    pub seconds: f64,
}
