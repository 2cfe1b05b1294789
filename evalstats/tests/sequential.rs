//! The sequential comparison: published worked examples, an independent computation in Python
//! (scipy), and its guarantees by simulation at a size a unit test affords (the full-size
//! simulation is `cargo bench -p evalstats --bench sequential`).
#![allow(
    clippy::unwrap_used,
    clippy::too_many_lines,
    reason = "tests: a failed unwrap is a failed test, and a scenario reads top to bottom"
)]

use evalstats::sequential::{confidence_sequence, fisher_exact_two_sided};
use evalstats::{compare_pairs, pair_by_key, Decision, Pair, PairedCounts, SequentialConfig, SequentialTest};
use std::io::Write;
use std::process::{Command, Stdio};

use evalstats::splitmix::SplitMix64 as Rng;

/// Agresti, Categorical Data Analysis (3rd ed., 2013), Table 11.1: approval of the US president's
/// performance in two surveys of the same 1,600 people (794 approve both times, 150 approve then
/// disapprove, 86 disapprove then approve, 570 disapprove both). §11.1: the difference of the
/// marginal proportions is 0.55 − 0.59 = −0.04, its standard error 0.0095, McNemar's z = −4.17.
#[test]
fn paired_counts_match_agresti_table_11_1() {
    let mut pairs = Vec::new();
    for (a, b, n) in [(1.0, 1.0, 794), (1.0, 0.0, 150), (0.0, 1.0, 86), (0.0, 0.0, 570)] {
        pairs.extend(std::iter::repeat_n(Pair { a, b }, n));
    }
    let c = PairedCounts::of(&pairs);
    assert_eq!((c.both, c.only_a, c.only_b, c.neither), (794, 150, 86, 570));
    assert!((c.difference() - -0.04).abs() < 1e-12);
    assert_eq!((c.standard_error() * 1e4).round() / 1e4, 0.0095);
    assert_eq!((c.mcnemar_z() * 100.0).round() / 100.0, -4.17);
    // Unpaired, the same margins would have a standard error of √(p1q1/n + p2q2/n) = 0.0175: the
    // pairing's concordant pairs remove most of the variance.
    let unpaired = (0.59f64 * 0.41 / 1600.0 + 0.55 * 0.45 / 1600.0).sqrt();
    assert!(c.standard_error() < 0.6 * unpaired, "{} vs {unpaired}", c.standard_error());
}

/// Fisher's tea-tasting experiment (Fisher 1935; Agresti 2013 §3.5.1): 3 of 4 cups guessed right
/// each way, two-sided P = 0.486.
#[test]
fn fisher_exact_matches_the_tea_tasting_experiment() {
    assert_eq!((fisher_exact_two_sided(3, 4, 1, 4) * 1000.0).round() / 1000.0, 0.486);
    assert_eq!(fisher_exact_two_sided(4, 4, 4, 4), 1.0);
}

fn draw(rng: &mut Rng, pa: f64, pb: f64, n: usize) -> Vec<Pair> {
    (0..n).map(|_| Pair { a: rng.bernoulli(pa), b: rng.bernoulli(pb) }).collect()
}

/// Every e-value, the confidence sequence's ends and Fisher's P against an independent computation
/// in Python (scipy's minimiser for the planned bet, scipy's Fisher test).
#[test]
fn matches_an_independent_computation_in_python() {
    if !store::test_support::require_python(&["numpy", "scipy"]) {
        return;
    }
    let mut rng = Rng(7);
    let mut cases = Vec::new();
    let mut ours = Vec::new();
    for (pa, pb, n, margin, plan) in [
        (0.5, 0.7, 120, 0.0, None),
        (0.6, 0.6, 300, 0.05, None),
        (0.8, 0.5, 60, 0.1, None),
        (0.4, 0.6, 150, 0.0, Some(0.2)),
        (0.7, 0.7, 200, 0.05, Some(0.1)),
    ] {
        let mut pairs = draw(&mut rng, pa, pb, n);
        // Partial credit: a third of B's outcomes are progress scores.
        for p in pairs.iter_mut().step_by(3) {
            p.b = (p.b + rng.next_f64()) / 2.0;
        }
        let config = SequentialConfig { alpha: 0.05, margin, plan_effect: plan };
        let r = compare_pairs(&pairs, config);
        cases.push(format!(
            r#"{{"kind":"seq","a":{:?},"b":{:?},"margin":{margin},"alpha":0.05,"plan":{}}}"#,
            pairs.iter().map(|p| p.a).collect::<Vec<_>>(),
            pairs.iter().map(|p| p.b).collect::<Vec<_>>(),
            plan.map_or("null".to_string(), |e| e.to_string()),
        ));
        ours.push((r.e_values.map(f64::ln), r.confidence_sequence));
    }
    let fisher = [(8u64, 10u64, 1u64, 6u64), (30, 50, 20, 50), (0, 10, 5, 10), (45, 100, 60, 100)];
    for (k1, n1, k2, n2) in fisher {
        cases.push(format!(r#"{{"kind":"fisher","k1":{k1},"n1":{n1},"k2":{k2},"n2":{n2}}}"#));
    }
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/sequential_reference.py");
    let mut child =
        match Command::new("python3").arg(script).stdin(Stdio::piped()).stdout(Stdio::piped()).spawn() {
            Ok(c) => c,
            Err(e) => panic!("python3 was found a moment ago and cannot be started now: {e}"),
        };
    child.stdin.take().unwrap().write_all(format!("[{}]", cases.join(",")).as_bytes()).unwrap();
    let out = child.wait_with_output().unwrap();
    assert!(out.status.success(), "the Python reference failed (needs numpy and scipy)");
    let text = String::from_utf8(out.stdout).unwrap();
    // A tiny reader for the reference's flat JSON: every number in order.
    let numbers: Vec<f64> = text
        .split(|c: char| !(c.is_ascii_digit() || c == '.' || c == '-' || c == 'e' || c == 'E'))
        .filter(|s| !s.is_empty() && s.chars().any(|c| c.is_ascii_digit()))
        .map(|s| s.parse().unwrap())
        .collect();
    let mut it = numbers.into_iter();
    for (i, (log_e, cs)) in ours.iter().enumerate() {
        for (k, ours) in log_e.iter().enumerate() {
            let theirs = it.next().unwrap();
            assert!(
                (ours - theirs).abs() < 1e-6 * (1.0 + theirs.abs()),
                "case {i} log e-value {k}: {ours} vs {theirs}"
            );
        }
        for ours in [cs.0, cs.1] {
            let theirs = it.next().unwrap();
            assert!((ours - theirs).abs() < 1e-6, "case {i} confidence sequence: {ours} vs {theirs}");
        }
    }
    for (k1, n1, k2, n2) in fisher {
        let theirs = it.next().unwrap();
        let ours = fisher_exact_two_sided(k1, n1, k2, n2);
        assert!(
            (ours - theirs).abs() < 1e-9 * (1.0 + theirs),
            "fisher {k1}/{n1} {k2}/{n2}: {ours} vs {theirs}"
        );
    }
}

/// Checked after every pair up to 300, arms with equal rates are declared different (better or
/// worse) in at most α of 1,000 comparisons (plus three standard errors of the simulation), while a
/// Newcombe interval looked at after every pair does so far more often.
#[test]
fn peeking_after_every_pair_keeps_the_error_rate() {
    let mut rng = Rng(11);
    for p in [0.3, 0.8] {
        let (mut ours, mut naive) = (0u32, 0u32);
        for _ in 0..1000 {
            let mut test = SequentialTest::new(SequentialConfig::default());
            let (mut ka, mut kb) = (0u64, 0u64);
            let mut naive_hit = false;
            for n in 1..=300u64 {
                let pair = Pair { a: rng.bernoulli(p), b: rng.bernoulli(p) };
                ka += pair.a as u64;
                kb += pair.b as u64;
                test.push(pair);
                naive_hit |= n >= 10 && evalstats::separates(evalstats::newcombe_diff(kb, n, ka, n));
            }
            ours += u32::from(test.decision().0 != Decision::Undecided);
            naive += u32::from(naive_hit);
        }
        let bound = 0.05 + 3.0 * (0.05f64 * 0.95 / 1000.0).sqrt();
        assert!(f64::from(ours) / 1000.0 <= bound, "p = {p}: {ours}/1000 declared different");
        assert!(naive > 2 * ours.max(25), "p = {p}: naive {naive} vs sequential {ours}");
    }
}

/// A real difference is found, in the right direction, and the more-pairs estimate is finite
/// before that.
#[test]
fn finds_a_real_difference_and_says_how_far_it_is() {
    let mut rng = Rng(3);
    let mut decided = 0;
    for _ in 0..200 {
        let pairs = draw(&mut rng, 0.5, 0.8, 300);
        let early = compare_pairs(&pairs[..20], SequentialConfig::default());
        if early.decision == Decision::Undecided && early.mean_b != early.mean_a {
            assert!(early.more_pairs.is_some_and(|m| m > 0), "{early:?}");
        }
        let r = compare_pairs(&pairs, SequentialConfig::default());
        assert_ne!(r.decision, Decision::Worse);
        if r.decision == Decision::Better {
            decided += 1;
            let at = r.decided_at.unwrap();
            assert_eq!(
                compare_pairs(&pairs[..at as usize], SequentialConfig::default()).decision,
                Decision::Better
            );
            assert_eq!(
                compare_pairs(&pairs[..at as usize - 1], SequentialConfig::default()).decision,
                Decision::Undecided
            );
            assert!(r.confidence_sequence.0 > 0.0, "{r:?}");
        }
    }
    assert!(decided >= 190, "{decided}/200 decided better");
}

/// Identical behaviour (every pair concordant) is "no practical difference" at δ = 5 pp, and a
/// one-sided lead within the margin is "not worse"; the worse arm at δ is "worse".
#[test]
fn margins_give_equivalence_non_inferiority_and_worse() {
    let mut rng = Rng(5);
    let same: Vec<Pair> = (0..400).map(|_| rng.bernoulli(0.6)).map(|y| Pair { a: y, b: y }).collect();
    let config = SequentialConfig { margin: 0.05, ..Default::default() };
    let r = compare_pairs(&same, config);
    assert_eq!(r.decision, Decision::NoPracticalDifference, "{r:?}");
    assert!(r.confidence_sequence.0 > -0.05 && r.confidence_sequence.1 < 0.05, "{r:?}");
    let worse = draw(&mut rng, 0.7, 0.3, 200);
    assert_eq!(compare_pairs(&worse, config).decision, Decision::Worse);
    assert_eq!(compare_pairs(&worse, config).decision.exit_code(), 1);
    // B never below A, rarely above: not worse by more than 5 pp, not shown better yet.
    let mut lead: Vec<Pair> = same[..150].to_vec();
    lead[7] = Pair { a: 0.0, b: 1.0 };
    let r = compare_pairs(&lead, SequentialConfig { margin: 0.05, ..Default::default() });
    assert!(matches!(r.decision, Decision::NotWorse | Decision::NoPracticalDifference), "{r:?}");
    assert_eq!(r.decision.exit_code(), 0);
}

#[test]
fn confidence_sequence_covers_and_narrows() {
    let mut rng = Rng(9);
    let pairs = draw(&mut rng, 0.4, 0.6, 2000);
    let config = SequentialConfig::default();
    let (l1, u1) = confidence_sequence(&pairs[..200], config);
    let (l2, u2) = confidence_sequence(&pairs, config);
    assert!(l1 < 0.2 && 0.2 < u1 && l2 < 0.2 && 0.2 < u2, "({l1}, {u1}) ({l2}, {u2})");
    assert!(u2 - l2 < 0.6 * (u1 - l1), "({l1}, {u1}) ({l2}, {u2})");
    assert_eq!(confidence_sequence(&[], config), (-1.0, 1.0));
}

/// Keyed rollouts pair by key (the k-th of each key), the rest in arrival order; a pair comes out
/// when its later rollout arrives; rollouts without a partner are counted.
#[test]
fn pairs_by_key_and_by_arrival() {
    let a = [(1, Some("s1"), 1.0), (2, Some("s2"), 0.0), (3, None, 1.0), (9, Some("s9"), 1.0)];
    let b = [(4, Some("s2"), 1.0), (5, Some("s1"), 0.0), (6, None, 0.0), (7, None, 1.0)];
    let (pairs, left_a, left_b) = pair_by_key(&a, &b);
    assert_eq!(pairs, vec![Pair { a: 0.0, b: 1.0 }, Pair { a: 1.0, b: 0.0 }, Pair { a: 1.0, b: 0.0 }]);
    assert_eq!((left_a, left_b), (1, 1));
}

#[test]
fn bad_configurations_are_named() {
    assert!(SequentialConfig { alpha: 0.0, ..Default::default() }.validate().unwrap_err().contains("alpha"));
    assert!(SequentialConfig { margin: -0.1, ..Default::default() }
        .validate()
        .unwrap_err()
        .contains("margin"));
    assert!(SequentialConfig { plan_effect: Some(0.0), ..Default::default() }
        .validate()
        .unwrap_err()
        .contains("plan"));
}
