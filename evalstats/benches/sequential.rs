//! The anytime-valid comparison of [`evalstats::sequential`] by simulation: two claims, two tables.
//!
//! **Method under test.** Pairs of rollouts (one of A, one of B) are fed to
//! [`SequentialTest`], which bets against "B is no better than A" (and against "no worse") with the
//! betting confidence sequences of Waudby-Smith & Ramdas (2024), "Estimating means of bounded
//! random variables by betting", JRSS-B 86(1):1–27 — the aGRAPA bet ("adaptive",
//! `plan_effect: None`) or the growth-optimal bet against a planned effect ("planned",
//! `plan_effect: Some(p_B − p_A)`); see the module doc of `evalstats::sequential`. A claim is made
//! when a bettor's capital reaches 2/α; α = 0.05, margin 0 throughout.
//!
//! 1. **Validity under peeking.** For p = 0.2, 0.3, …, 0.9, 10,000 comparisons of two arms with the
//!    same rate p, looked at after every pair up to 500 pairs. The fraction ever declared different
//!    (any decision other than undecided) must be at most α. Against it: the fixed-n rule "the
//!    Newcombe (method 10) 95% interval of p_B − p_A excludes 0", applied after every pair
//!    (n = 1 … 500; this is what peeking at a fixed-n interval does, and it exceeds α), and applied
//!    once at n = 500 (≈ α).
//! 2. **Efficiency against a fixed-n Fisher test sized in advance.** For each (p_A, p_B), the
//!    Fisher reference is the smallest n per arm whose *exact* power (two-sided Fisher exact test
//!    at α = 0.05, independent Binomial(n, p_A) and Binomial(n, p_B) arms) is at least 0.8 — the
//!    first such n scanning upward from below the normal-approximation size (power is not exactly
//!    monotone in n; the footnote says where n+1 … n+5 are not all ≥ 0.8 as well). Exact power:
//!    for each total s = k₁ + k₂ the conditional (hypergeometric) null distribution is fixed, so
//!    the p-value of every k₁ given s comes from one pass over the pmf in ascending order (the pmf
//!    is unimodal: merge its two tails), and power = Σ over rejected (k₁, k₂) of
//!    Binom(n, p_A)(k₁)·Binom(n, p_B)(k₂); a few of those p-values are checked against
//!    `fisher_exact_two_sided`. The same n is the reference for the paired rows (correlation
//!    ρ = 0.5 between the two outcomes of a pair: P(both) = p_A p_B + ρ√(p_A q_A p_B q_B)), whose
//!    fixed-n test, sized in advance without knowing the correlation, is the same Fisher test.
//!    (Most of the paired rows' saving is the pairing's: a McNemar test sized knowing ρ = 0.5
//!    needs about half n_Fisher pairs by the normal approximation — 198 rather than 404 at
//!    (0.5, 0.6) — which is fewer than the sequential test's mean.)
//!    The sequential test runs 4,000 times per row and variant, each up to 8 × n_Fisher pairs.
//!    τ is the first pair count at which the decision is "better" (a "worse" decision, or none,
//!    counts as not detected). **n_max** is the smallest pair count with P(τ ≤ n_max) ≥ 0.8: the
//!    truncation at which the sequential test has power 0.8, as STEP (a sequential test truncated
//!    for a target power) chooses it; simulated here rather than computed. The cost reported is
//!    the mean over runs of min(stopping time, n_max), the stopping time being the first decision
//!    of any kind (never decided: n_max), as a ratio to n_Fisher. Last, the false-positive check:
//!    the planned variant with p_A = p_B = 0.5 (4,000 runs of 500 pairs).
//!
//! Runs are seeded (SplitMix64) per run from a fixed master seed, so the tables do not depend on
//! the number of threads. Tables go to stdout and to `target/bench/sequential.md`; timings to
//! stderr.
//!
//! `cargo bench -p evalstats --bench sequential` (about a minute on 2 cores).
#![allow(
    clippy::unwrap_used,
    clippy::too_many_lines,
    reason = "benchmarks: a failed unwrap is a failed run, and a measurement reads top to bottom"
)]

use evalstats::sequential::{fisher_exact_two_sided, ln_choose};
use evalstats::splitmix::SplitMix64 as Rng;
use evalstats::{newcombe_diff, separates, wilson, Decision, Pair, SequentialConfig, SequentialTest};
use std::fmt::Write as _;
use std::time::Instant;

const ALPHA: f64 = 0.05;
const TARGET_POWER: f64 = 0.8;

/// `f` over `runs` runs, each with its own generator seeded from `seed`'s stream, on all cores;
/// results in run order.
fn simulate<T: Send>(runs: usize, seed: u64, f: impl Fn(&mut Rng) -> T + Sync) -> Vec<T> {
    let mut master = Rng(seed);
    let seeds: Vec<u64> = (0..runs).map(|_| master.next_u64()).collect();
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get()).min(runs.max(1));
    let chunk = runs.div_ceil(threads).max(1);
    let f = &f;
    std::thread::scope(|scope| {
        let handles: Vec<_> = seeds
            .chunks(chunk)
            .map(|seeds| scope.spawn(move || seeds.iter().map(|&s| f(&mut Rng(s))).collect::<Vec<T>>()))
            .collect();
        handles.into_iter().flat_map(|h| h.join().unwrap()).collect()
    })
}

/// How the two outcomes of a pair are drawn.
#[derive(Clone, Copy, PartialEq)]
enum Pairing {
    /// Independent arms.
    Unpaired,
    /// Correlation ρ between A's and B's outcome of a pair.
    Paired(f64),
}

impl Pairing {
    fn label(&self) -> String {
        match self {
            Pairing::Unpaired => "unpaired".into(),
            Pairing::Paired(rho) => format!("paired ρ={rho}"),
        }
    }
}

fn draw(rng: &mut Rng, pa: f64, pb: f64, pairing: Pairing) -> Pair {
    match pairing {
        Pairing::Unpaired => Pair { a: rng.bernoulli(pa), b: rng.bernoulli(pb) },
        Pairing::Paired(rho) => {
            let both = pa * pb + rho * (pa * (1.0 - pa) * pb * (1.0 - pb)).sqrt();
            let (only_a, only_b) = (pa - both, pb - both);
            assert!(both >= 0.0 && only_a >= -1e-12 && only_b >= -1e-12 && both + only_a + only_b <= 1.0);
            let u = rng.next_f64();
            if u < both {
                Pair { a: 1.0, b: 1.0 }
            } else if u < both + only_a {
                Pair { a: 1.0, b: 0.0 }
            } else if u < both + only_a + only_b {
                Pair { a: 0.0, b: 1.0 }
            } else {
                Pair { a: 0.0, b: 0.0 }
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// 1. Validity under peeking.

const PEEK_RUNS: usize = 10_000;
const PEEK_PAIRS: u64 = 500;

struct Peek {
    sequential: bool,
    newcombe_any: bool,
    newcombe_final: bool,
}

fn peek_run(rng: &mut Rng, p: f64) -> Peek {
    let mut test = SequentialTest::new(SequentialConfig::default());
    let (mut ka, mut kb) = (0u64, 0u64);
    let (mut sequential, mut newcombe_any) = (false, false);
    for n in 1..=PEEK_PAIRS {
        let pair = draw(rng, p, p, Pairing::Unpaired);
        ka += pair.a as u64;
        kb += pair.b as u64;
        if !sequential {
            test.push(pair);
            sequential = test.decision().0 != Decision::Undecided;
        }
        newcombe_any = newcombe_any || separates(newcombe_diff(kb, n, ka, n));
    }
    let newcombe_final = separates(newcombe_diff(kb, PEEK_PAIRS, ka, PEEK_PAIRS));
    Peek { sequential, newcombe_any, newcombe_final }
}

fn validity_table() -> String {
    let mut out = String::new();
    writeln!(
        out,
        "### Validity under peeking: equal rates, looked at after every pair ({PEEK_RUNS} comparisons \
         of up to {PEEK_PAIRS} pairs, α = {ALPHA})\n"
    )
    .unwrap();
    writeln!(
        out,
        "| p | sequential: ever declared different [95% CI] | Newcombe 95% CI after every pair: ever \
         excludes 0 | Newcombe 95% CI at n = {PEEK_PAIRS} only |"
    )
    .unwrap();
    writeln!(out, "|---|---|---|---|").unwrap();
    let mut worst: f64 = 0.0;
    for (i, p) in [0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9].into_iter().enumerate() {
        let runs = simulate(PEEK_RUNS, 0x5EED_0001 + i as u64, |rng| peek_run(rng, p));
        let count = |f: fn(&Peek) -> bool| runs.iter().filter(|r| f(r)).count() as u64;
        let (seq, any, fin) =
            (count(|r| r.sequential), count(|r| r.newcombe_any), count(|r| r.newcombe_final));
        let n = PEEK_RUNS as u64;
        let (lo, hi) = wilson(seq, n);
        let frac = |k: u64| k as f64 / n as f64;
        worst = worst.max(frac(seq));
        writeln!(
            out,
            "| {p:.1} | {:.4} [{lo:.4}, {hi:.4}] | {:.4} | {:.4} |",
            frac(seq),
            frac(any),
            frac(fin)
        )
        .unwrap();
    }
    writeln!(out, "\nLargest sequential fraction: {worst:.4} (α = {ALPHA}).").unwrap();
    out
}

// ---------------------------------------------------------------------------------------------
// 2. Efficiency against Fisher's exact test sized in advance.

/// ln k! for k = 0 ..= max.
fn ln_factorials(max: usize) -> Vec<f64> {
    let mut t = vec![0.0; max + 1];
    for k in 1..=max {
        t[k] = t[k - 1] + (k as f64).ln();
    }
    t
}

/// Fisher's two-sided p-value of every k₁ (k₁ = lo ..= hi) given the total s, with n per arm:
/// the conditional pmf is hypergeometric and unimodal, so merging its two tails lists it in
/// ascending order, and each p-value (the mass at most as probable, ties within a relative 1e-7,
/// as `fisher_exact_two_sided`) is a running sum. Returns lo; `p_values[k₁ − lo]`.
fn conditional_p_values(
    n: usize,
    s: usize,
    lnf: &[f64],
    pmf: &mut Vec<f64>,
    order: &mut Vec<usize>,
    p_values: &mut Vec<f64>,
) -> usize {
    let (lo, hi) = (s.saturating_sub(n), s.min(n));
    // ln C(s, k) + ln C(2n − s, n − k), up to the constant ln C(2n, n).
    let ln_q = |k: usize| lnf[s] - lnf[k] - lnf[s - k] + lnf[2 * n - s] - lnf[n - k] - lnf[n - s + k];
    pmf.clear();
    pmf.extend((lo..=hi).map(ln_q));
    let top = pmf.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    pmf.iter_mut().for_each(|x| *x = (*x - top).exp());
    let total: f64 = pmf.iter().sum();
    order.clear();
    let (mut i, mut j) = (0usize, pmf.len() - 1);
    loop {
        if pmf[i] <= pmf[j] {
            order.push(i);
            if i == j {
                break;
            }
            i += 1;
        } else {
            order.push(j);
            j -= 1;
        }
    }
    p_values.clear();
    p_values.resize(pmf.len(), 0.0);
    let (mut last, mut cum) = (0usize, pmf[order[0]]);
    for m in 0..order.len() {
        let v = pmf[order[m]] * (1.0 + 1e-7);
        while last + 1 < order.len() && pmf[order[last + 1]] <= v {
            last += 1;
            cum += pmf[order[last]];
        }
        p_values[order[m]] = (cum / total).min(1.0);
    }
    lo
}

/// The exact power of the two-sided Fisher test at level α with n per arm at (p_A, p_B).
fn fisher_power(n: usize, pa: f64, pb: f64, lnf: &[f64]) -> f64 {
    let binom = |p: f64| -> Vec<f64> {
        (0..=n)
            .map(|k| {
                (lnf[n] - lnf[k] - lnf[n - k] + k as f64 * p.ln() + (n - k) as f64 * (1.0 - p).ln()).exp()
            })
            .collect()
    };
    let (ba, bb) = (binom(pa), binom(pb));
    let (mut pmf, mut order, mut p_values) = (Vec::new(), Vec::new(), Vec::new());
    let mut power = 0.0;
    for s in 0..=2 * n {
        let lo = conditional_p_values(n, s, lnf, &mut pmf, &mut order, &mut p_values);
        for (i, &p) in p_values.iter().enumerate() {
            if p <= ALPHA {
                let k1 = lo + i;
                power += ba[k1] * bb[s - k1];
            }
        }
    }
    power
}

/// The normal-approximation n per arm (pooled variance under the null).
fn normal_approx_n(pa: f64, pb: f64) -> f64 {
    let (za, zb) = (1.959963984540054, 0.8416212335729143);
    let pbar = (pa + pb) / 2.0;
    let x = za * (2.0 * pbar * (1.0 - pbar)).sqrt() + zb * (pa * (1.0 - pa) + pb * (1.0 - pb)).sqrt();
    (x / (pb - pa)).powi(2)
}

/// The smallest n per arm with exact Fisher power ≥ 0.8, and whether n+1 … n+5 are all ≥ 0.8 too
/// (if not, the smallest n for which they are).
fn fisher_n(pa: f64, pb: f64, lnf: &[f64]) -> (usize, Option<usize>) {
    let mut start = (0.7 * normal_approx_n(pa, pb)).floor().max(2.0) as usize;
    while start > 2 && fisher_power(start, pa, pb, lnf) >= TARGET_POWER {
        start /= 2;
    }
    // Upward from `start` (below the answer) until six sizes in a row reach the target.
    let (mut first, mut run) = (None, 0);
    for n in start.. {
        if fisher_power(n, pa, pb, lnf) >= TARGET_POWER {
            first = first.or(Some(n));
            run += 1;
            if run == 6 {
                let stable = n - 5;
                let first = first.unwrap();
                return (first, (stable != first).then_some(stable));
            }
        } else {
            run = 0;
        }
    }
    unreachable!()
}

/// Checks the enumeration's p-values against `fisher_exact_two_sided` at a few tables.
fn check_p_values(n: usize, lnf: &[f64]) {
    let (mut pmf, mut order, mut p_values) = (Vec::new(), Vec::new(), Vec::new());
    for s in [n / 3, n, n + n / 2, 2 * n - 1] {
        let lo = conditional_p_values(n, s, lnf, &mut pmf, &mut order, &mut p_values);
        for (i, &ours) in p_values.iter().enumerate().step_by((p_values.len() / 7).max(1)) {
            let k1 = (lo + i) as u64;
            let theirs = fisher_exact_two_sided(k1, n as u64, s as u64 - k1, n as u64);
            assert!((ours - theirs).abs() < 1e-9 * (1.0 + theirs), "n {n} s {s} k1 {k1}: {ours} vs {theirs}");
        }
    }
    // The table of log-factorials against ln_choose.
    let (a, b) = (2 * n, n);
    assert!((lnf[a] - lnf[b] - lnf[a - b] - ln_choose(a as u64, b as u64)).abs() < 1e-9);
}

const EFF_RUNS: usize = 4_000;
const HORIZON_FACTOR: usize = 8;

struct SeqRun {
    /// First pair count at which the decision is "better".
    tau: Option<u64>,
    /// First decision of any kind.
    stop: Option<u64>,
}

fn seq_run(
    rng: &mut Rng,
    pa: f64,
    pb: f64,
    pairing: Pairing,
    config: SequentialConfig,
    max_pairs: u64,
) -> SeqRun {
    let mut test = SequentialTest::new(config);
    for n in 1..=max_pairs {
        test.push(draw(rng, pa, pb, pairing));
        match test.decision().0 {
            Decision::Undecided => {}
            Decision::Better => return SeqRun { tau: Some(n), stop: Some(n) },
            _ => return SeqRun { tau: None, stop: Some(n) },
        }
    }
    SeqRun { tau: None, stop: None }
}

/// n_max (None: power 0.8 not reached within the horizon) and the mean of min(stop, n_max).
fn summarise(runs: &[SeqRun], horizon: u64) -> (Option<u64>, f64) {
    let mut taus: Vec<u64> = runs.iter().filter_map(|r| r.tau).collect();
    taus.sort_unstable();
    let need = (TARGET_POWER * runs.len() as f64).ceil() as usize;
    let n_max = (taus.len() >= need).then(|| taus[need - 1]);
    let cap = n_max.unwrap_or(horizon);
    let mean = runs.iter().map(|r| r.stop.unwrap_or(cap).min(cap) as f64).sum::<f64>() / runs.len() as f64;
    (n_max, mean)
}

fn efficiency_table() -> String {
    let grid = [(0.5, 0.6), (0.5, 0.7), (0.7, 0.9), (0.3, 0.5), (0.2, 0.5)];
    let lnf = ln_factorials(4 * 2048);
    let mut out = String::new();
    writeln!(
        out,
        "### Efficiency against Fisher's exact test sized in advance (power 0.8, α = {ALPHA} two-sided; \
         {EFF_RUNS} sequential runs per row and variant, up to {HORIZON_FACTOR} × n_Fisher pairs)\n"
    )
    .unwrap();
    writeln!(
        out,
        "| p_A | p_B | pairing | Fisher n/arm | planned n_max | planned mean pairs | planned ratio | \
         adaptive n_max | adaptive mean pairs | adaptive ratio |"
    )
    .unwrap();
    writeln!(out, "|---|---|---|---|---|---|---|---|---|---|").unwrap();
    let mut notes = Vec::new();
    let mut ratios: Vec<(Pairing, f64, f64)> = Vec::new();
    let t = Instant::now();
    let fisher: Vec<(usize, Option<usize>)> = grid.iter().map(|&(pa, pb)| fisher_n(pa, pb, &lnf)).collect();
    check_p_values(fisher[0].0, &lnf);
    eprintln!("Fisher sizes in {:.1?}", t.elapsed());
    for (&(pa, pb), &(n, _)) in grid.iter().zip(&fisher) {
        let (below, at) = (fisher_power(n - 1, pa, pb, &lnf), fisher_power(n, pa, pb, &lnf));
        eprintln!("  ({pa}, {pb}): exact power {below:.12} at n = {}, {at:.12} at n = {n}", n - 1);
    }
    for (g, &(pa, pb)) in grid.iter().enumerate() {
        let (nf, stable) = fisher[g];
        if let Some(s) = stable {
            notes.push(format!(
                "({pa}, {pb}): power ≥ 0.8 first at n = {nf}, at n … n+5 all first at n = {s}"
            ));
        }
        for (k, pairing) in [Pairing::Unpaired, Pairing::Paired(0.5)].into_iter().enumerate() {
            let horizon = (HORIZON_FACTOR * nf) as u64;
            let mut cells = Vec::new();
            let mut row_ratios = Vec::new();
            for (v, plan) in [Some(pb - pa), None].into_iter().enumerate() {
                let config = SequentialConfig { alpha: ALPHA, margin: 0.0, plan_effect: plan };
                let seed = 0x5EED_1000 + (g * 4 + k * 2 + v) as u64;
                let t = Instant::now();
                let runs = simulate(EFF_RUNS, seed, |rng| seq_run(rng, pa, pb, pairing, config, horizon));
                let (n_max, mean) = summarise(&runs, horizon);
                eprintln!(
                    "({pa}, {pb}) {} {}: {:.1?}",
                    pairing.label(),
                    if plan.is_some() { "planned" } else { "adaptive" },
                    t.elapsed()
                );
                let ratio = mean / nf as f64;
                row_ratios.push(ratio);
                let n_max = n_max.map_or(format!("> {horizon}"), |n| n.to_string());
                cells.push(format!("{n_max} | {mean:.1} | {ratio:.2}"));
            }
            ratios.push((pairing, row_ratios[0], row_ratios[1]));
            writeln!(out, "| {pa} | {pb} | {} | {nf} | {} | {} |", pairing.label(), cells[0], cells[1])
                .unwrap();
        }
    }
    let avg = |f: &dyn Fn(&Pairing) -> bool| {
        let sel: Vec<_> = ratios.iter().filter(|r| f(&r.0)).collect();
        let n = sel.len() as f64;
        (sel.iter().map(|r| r.1).sum::<f64>() / n, sel.iter().map(|r| r.2).sum::<f64>() / n)
    };
    writeln!(out).unwrap();
    writeln!(out, "| average ratio to Fisher n | planned | adaptive |").unwrap();
    writeln!(out, "|---|---|---|").unwrap();
    for (label, f) in [
        ("unpaired rows", &(|p: &Pairing| *p == Pairing::Unpaired) as &dyn Fn(&Pairing) -> bool),
        ("paired rows (ρ = 0.5)", &|p: &Pairing| *p != Pairing::Unpaired),
        ("all rows", &|_: &Pairing| true),
    ] {
        let (p, a) = avg(f);
        writeln!(out, "| {label} | {p:.2} | {a:.2} |").unwrap();
    }

    // False positives of the planned variant under equal rates.
    writeln!(out).unwrap();
    writeln!(out, "| false-positive check: p_A = p_B = 0.5, {EFF_RUNS} runs of {PEEK_PAIRS} pairs | better or worse [95% CI] |").unwrap();
    writeln!(out, "|---|---|").unwrap();
    for (i, (plan, pairing)) in
        [(0.1, Pairing::Unpaired), (0.2, Pairing::Unpaired), (0.1, Pairing::Paired(0.5))]
            .into_iter()
            .enumerate()
    {
        let config = SequentialConfig { alpha: ALPHA, margin: 0.0, plan_effect: Some(plan) };
        let t = Instant::now();
        let runs = simulate(EFF_RUNS, 0x5EED_2000 + i as u64, |rng| {
            seq_run(rng, 0.5, 0.5, pairing, config, PEEK_PAIRS)
        });
        eprintln!("false positives plan {plan} {}: {:.1?}", pairing.label(), t.elapsed());
        let k = runs.iter().filter(|r| r.stop.is_some()).count() as u64;
        let (lo, hi) = wilson(k, EFF_RUNS as u64);
        writeln!(
            out,
            "| planned, plan effect {plan}, {} | {:.4} [{lo:.4}, {hi:.4}] |",
            pairing.label(),
            k as f64 / EFF_RUNS as f64
        )
        .unwrap();
    }
    if !notes.is_empty() {
        writeln!(out, "\nFisher power is not monotone in n: {}.", notes.join("; ")).unwrap();
    }
    out
}

fn main() {
    let start = Instant::now();
    let t = Instant::now();
    let validity = validity_table();
    eprintln!("validity: {:.1?}", t.elapsed());
    print!("{validity}");
    println!();
    let t = Instant::now();
    let efficiency = efficiency_table();
    eprintln!("efficiency: {:.1?}", t.elapsed());
    print!("{efficiency}");
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/../target/bench");
    std::fs::create_dir_all(dir).expect("create target/bench");
    let path = format!("{dir}/sequential.md");
    std::fs::write(&path, format!("## Sequential comparison (`cargo bench -p evalstats --bench sequential`)\n\n{validity}\n{efficiency}"))
        .expect("write sequential.md");
    eprintln!("wrote {path} in {:.1?}", start.elapsed());
}
