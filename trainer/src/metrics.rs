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
