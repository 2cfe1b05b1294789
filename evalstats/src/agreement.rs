//! Inter-rater agreement on nominal categories: Cohen's κ for two raters and Krippendorff's α
//! (nominal metric, any number of raters, missing values allowed). Categories are any `Ord`
//! values (the store passes label strings).

use std::collections::BTreeMap;

/// Cohen's κ of two raters over the units both rated: `pairs[i] = (rater A's category, rater
/// B's)`. κ = (p_o − p_e) / (1 − p_e) with p_e from each rater's own category shares. `None` with
/// no pairs, or when p_e = 1 (both raters always used one same category: κ is undefined).
pub fn cohen_kappa<C: Ord + Clone>(pairs: &[(C, C)]) -> Option<f64> {
    if pairs.is_empty() {
        return None;
    }
    let n = pairs.len() as f64;
    let mut a: BTreeMap<&C, f64> = BTreeMap::new();
    let mut b: BTreeMap<&C, f64> = BTreeMap::new();
    let mut agree = 0.0;
    for (x, y) in pairs {
        *a.entry(x).or_default() += 1.0;
        *b.entry(y).or_default() += 1.0;
        if x == y {
            agree += 1.0;
        }
    }
    let po = agree / n;
    let pe: f64 = a.iter().map(|(c, na)| na / n * b.get(c).copied().unwrap_or(0.0) / n).sum();
    if (1.0 - pe).abs() < 1e-12 {
        return None;
    }
    Some((po - pe) / (1.0 - pe))
}

/// Krippendorff's α with the nominal metric. `units[u]` holds the values the raters gave unit u
/// (missing ratings simply absent); units with fewer than two values are not pairable and are
/// left out. Computed from the coincidence matrix: α = 1 − (n − 1) Σ_{c≠k} o_ck / Σ_{c≠k} n_c n_k.
/// `None` when fewer than two values are pairable or only one category occurs (no expected
/// disagreement).
pub fn krippendorff_alpha_nominal<C: Ord + Clone>(units: &[Vec<C>]) -> Option<f64> {
    // Observed disagreement mass Σ_{c≠k} o_ck and the marginals n_c.
    let mut disagree = 0.0;
    let mut marg: BTreeMap<&C, f64> = BTreeMap::new();
    for values in units {
        let m = values.len();
        if m < 2 {
            continue;
        }
        let w = 1.0 / (m as f64 - 1.0);
        for (i, c) in values.iter().enumerate() {
            *marg.entry(c).or_default() += 1.0;
            for (j, k) in values.iter().enumerate() {
                if i != j && c != k {
                    disagree += w;
                }
            }
        }
    }
    let n: f64 = marg.values().sum();
    let total_sq: f64 = marg.values().map(|x| x * x).sum();
    let expected = n * n - total_sq; // Σ_{c≠k} n_c n_k
    if n < 2.0 || expected <= 0.0 {
        return None;
    }
    Some(1.0 - (n - 1.0) * disagree / expected)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn r3(x: f64) -> f64 {
        (x * 1e3).round() / 1e3
    }

    /// Wikipedia, "Cohen's kappa", worked example: 50 grant proposals read by two readers, 20
    /// yes/yes, 5 yes/no (A yes, B no), 10 no/yes, 15 no/no: p_o = 0.7, p_e = 0.5, κ = 0.4.
    #[test]
    fn kappa_matches_the_worked_example() {
        let mut pairs = Vec::new();
        pairs.extend(std::iter::repeat_n(("yes", "yes"), 20));
        pairs.extend(std::iter::repeat_n(("yes", "no"), 5));
        pairs.extend(std::iter::repeat_n(("no", "yes"), 10));
        pairs.extend(std::iter::repeat_n(("no", "no"), 15));
        assert_eq!(r3(cohen_kappa(&pairs).unwrap()), 0.4);
    }

    /// Perfect agreement is 1, agreement no better than the marginals predict is 0, and one
    /// category throughout is undefined.
    #[test]
    fn kappa_edge_cases() {
        assert_eq!(cohen_kappa(&[(1, 1), (2, 2), (1, 1)]), Some(1.0));
        assert_eq!(cohen_kappa(&[(1, 1), (1, 2), (2, 1), (2, 2)]), Some(0.0));
        assert_eq!(cohen_kappa(&[(1, 1), (1, 1)]), None);
        assert_eq!(cohen_kappa::<u8>(&[]), None);
    }

    /// Krippendorff (2011), "Computing Krippendorff's Alpha-Reliability", section A: two
    /// observers, binary data, ten units: α = 0.095.
    #[test]
    fn alpha_matches_krippendorff_2011_binary_example() {
        let a = [0, 1, 0, 0, 0, 0, 0, 0, 1, 0];
        let b = [1, 1, 1, 0, 0, 1, 0, 0, 0, 0];
        let units: Vec<Vec<u8>> = a.iter().zip(b).map(|(&x, y)| vec![x, y]).collect();
        assert_eq!(r3(krippendorff_alpha_nominal(&units).unwrap()), 0.095);
    }

    /// Krippendorff (2011), section C: four observers, twelve units, missing values, nominal
    /// metric: α = 0.743.
    #[test]
    fn alpha_matches_krippendorff_2011_missing_values_example() {
        let obs: [[u8; 12]; 4] = [
            [1, 2, 3, 3, 2, 1, 4, 1, 2, 0, 0, 0],
            [1, 2, 3, 3, 2, 2, 4, 1, 2, 5, 0, 3],
            [0, 3, 3, 3, 2, 3, 4, 2, 2, 5, 1, 0],
            [1, 2, 3, 3, 2, 4, 4, 1, 2, 5, 1, 0],
        ]; // 0 = missing
        let units: Vec<Vec<u8>> =
            (0..12).map(|u| obs.iter().map(|o| o[u]).filter(|&v| v != 0).collect()).collect();
        assert_eq!(r3(krippendorff_alpha_nominal(&units).unwrap()), 0.743);
    }

    /// For two raters without missing values α and κ differ only in how p_e is estimated:
    /// α = 1 − (n−1)(1−p_o) / (n − Σ n_c²/n) with n = 2N pooled values (a rearrangement of the
    /// coincidence-matrix form, checked here on a random-ish table).
    #[test]
    fn alpha_for_two_raters_matches_the_pooled_closed_form() {
        let pairs: Vec<(u8, u8)> =
            (0..40u32).map(|i| (((i * 7) % 3) as u8, ((i * 5 + i / 4) % 3) as u8)).collect();
        let units: Vec<Vec<u8>> = pairs.iter().map(|&(a, b)| vec![a, b]).collect();
        let nn = 2.0 * pairs.len() as f64;
        let po = pairs.iter().filter(|(a, b)| a == b).count() as f64 / pairs.len() as f64;
        let mut nc = [0.0f64; 3];
        for &(a, b) in &pairs {
            nc[a as usize] += 1.0;
            nc[b as usize] += 1.0;
        }
        let expected = 1.0 - (nn - 1.0) * (1.0 - po) * nn / (nn * nn - nc.iter().map(|x| x * x).sum::<f64>());
        let got = krippendorff_alpha_nominal(&units).unwrap();
        assert!((got - expected).abs() < 1e-12, "{got} vs {expected}");
        assert_eq!(krippendorff_alpha_nominal(&[vec![1u8, 1], vec![1]]), None);
    }
}
