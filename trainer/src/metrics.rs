//! Evaluation metrics: rank-based ROC AUC (ties get average ranks) and Pearson correlation.

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
