//! Anytime-valid comparison of two arms: is B better than A yet, worse, or within a margin, and how
//! many more rollouts until we know — correct however often someone looks.
//!
//! **Method.** Rollouts of the two arms are taken in pairs (the i-th of A with the i-th of B in
//! arrival order, or the two rollouts that share an initial condition; [`pair_by_key`]). Each pair
//! gives Z = y_B − y_A in [−1, 1] (y a success label 0/1, or a progress score in [0, 1]); pairs are
//! independent and identically distributed, and E\[Z\] = Δ = p_B − p_A. For a null value m of Δ, the
//! capital of a gambler betting on X = (Z + 1)/2 against mean μ₀ = (m + 1)/2,
//! K⁺ₜ(m) = Πᵢ (1 + λᵢ (Xᵢ − μ₀)) with a predictable λᵢ ∈ [0, c/μ₀] (and K⁻ with −λ), is a
//! non-negative supermartingale when Δ ≤ m (Δ ≥ m), so by Ville's inequality it ever reaches
//! 2/α with probability at most α/2. Crossing it proves Δ > m (Δ < m) at every sample size at once:
//! this is the betting confidence sequence of Waudby-Smith & Ramdas (2024), "Estimating means of
//! bounded random variables by betting", JRSS-B 86(1):1–27, with its aGRAPA bet (their §B.2), or,
//! when the user plans an effect as a fixed-n power analysis would, the growth-optimal bet against
//! that alternative at the running estimate of A's rate (a sequential probability ratio-style bet;
//! any predictable bet keeps validity, the plan only buys speed). Claims that Δ lies on the side of a
//! margin nearer 0 average in a second gambler who bets as if the arms were equal (see
//! `Bettor`): on the demo's λ = 0.1 guidance row that decides "no practical difference" at
//! δ = 5 pp within its 1,000 paired rollouts, where the adaptive bet alone does not.
//!
//! Claims, all from the same family of tests, so that at most α of probability is ever spent on a
//! false one, whatever the true Δ (each false claim needs one process with the wrong sign to
//! cross, and for any Δ only the processes on one side of it can): B **better** (Δ > 0), B
//! **worse** (Δ < −δ), **no practical difference** (−δ < Δ < δ) and **not worse** (Δ > −δ), with δ
//! the margin. Once a claim's process crosses, the claim stands (the running intersection of the
//! confidence sequence). Several tasks: each task's sequence at α/K (Bonferroni over e-processes,
//! so the claims of all tasks hold together), the pooled one at α.

/// Bets are capped at this fraction of what would lose everything on one rollout (aGRAPA's c).
const BET_CAP: f64 = 0.5;
/// The planned bet's cap: the plan fixes the bet, so it may stake more.
const PLANNED_BET_CAP: f64 = 0.9;

/// What a comparison is asked.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SequentialConfig {
    /// The probability of ever making a false claim (0.05).
    pub alpha: f64,
    /// δ ≥ 0 in rate units (0.05 = 5 percentage points): "worse" means worse by more than δ, and
    /// with δ > 0 the comparison can also end in "no practical difference" or "not worse".
    pub margin: f64,
    /// The difference the evaluation is planned to detect (as a fixed-n power analysis is): bets
    /// are sized for it. `None`: bets adapt to the data (aGRAPA).
    pub plan_effect: Option<f64>,
}

impl Default for SequentialConfig {
    fn default() -> Self {
        SequentialConfig { alpha: 0.05, margin: 0.0, plan_effect: None }
    }
}

impl SequentialConfig {
    /// Checks α ∈ (0, 1), δ ∈ [0, 1), plan ∈ (0, 1].
    pub fn validate(&self) -> Result<(), String> {
        if !(self.alpha > 0.0 && self.alpha < 1.0) {
            return Err(format!("alpha must be in (0, 1), got {}", self.alpha));
        }
        if !(self.margin >= 0.0 && self.margin < 1.0) {
            return Err(format!("margin must be in [0, 1), got {}", self.margin));
        }
        if let Some(e) = self.plan_effect {
            if !(e > 0.0 && e <= 1.0) {
                return Err(format!("plan effect must be in (0, 1], got {e}"));
            }
        }
        Ok(())
    }
}

/// The comparison's answer.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Decision {
    Better,
    Worse,
    NoPracticalDifference,
    NotWorse,
    Undecided,
}

impl Decision {
    pub fn as_str(&self) -> &'static str {
        match self {
            Decision::Better => "better",
            Decision::Worse => "worse",
            Decision::NoPracticalDifference => "no_practical_difference",
            Decision::NotWorse => "not_worse",
            Decision::Undecided => "undecided",
        }
    }
    /// A gate's exit status: 0 B not worse, 1 B worse, 2 undecided.
    pub fn exit_code(&self) -> i32 {
        match self {
            Decision::Better | Decision::NoPracticalDifference | Decision::NotWorse => 0,
            Decision::Worse => 1,
            Decision::Undecided => 2,
        }
    }
}

/// One pair of outcomes in [0, 1]: A's and B's.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pair {
    pub a: f64,
    pub b: f64,
}

/// A one-sided test of Δ against `m` by betting: `up` proves Δ > m, otherwise Δ < m.
///
/// Where the claim is that Δ lies on the side of `m` nearer 0 (Δ > m for m < 0, Δ < m for m > 0:
/// "not worse by more than δ", "not better by more than δ"), the capital is the average of two
/// gamblers' — the adaptive (or planned) one and one who bets as if the arms were equal (Δ = 0,
/// what an equivalence or non-inferiority design is powered for), sized by the running variance,
/// which wins where the margin is small and the running mean's noise costs the adaptive bet most.
/// An average of test supermartingales is one, so validity is unchanged; the confidence sequence
/// is made of the same processes, so it agrees with every decision.
#[derive(Debug, Clone)]
struct Bettor {
    mu0: f64,
    up: bool,
    mixed: bool,
    /// The log capital of each gambler (the second only when `mixed`).
    log_k: [f64; 2],
    /// The first pair count at which the capital reached the threshold.
    crossed_at: Option<u64>,
}

impl Bettor {
    fn new(m: f64, up: bool) -> Self {
        let mixed = (up && m < 0.0) || (!up && m > 0.0);
        Bettor { mu0: (m + 1.0) / 2.0, up, mixed, log_k: [0.0; 2], crossed_at: None }
    }

    /// ln of the capital: the one gambler's, or the average of the two.
    fn log_capital(&self) -> f64 {
        if !self.mixed {
            return self.log_k[0];
        }
        let hi = self.log_k[0].max(self.log_k[1]);
        hi + (0.5 * ((self.log_k[0] - hi).exp() + (self.log_k[1] - hi).exp())).ln()
    }

    /// The stakes for the next pair, from what came before (predictable).
    fn stakes(&self, state: &Running, plan: Option<f64>) -> [f64; 2] {
        let mu0 = self.mu0;
        // Staking λ on X − μ₀ (or on μ₀ − X): at most c/μ₀ (c/(1 − μ₀)) keeps 1 + λ(·) > 0.
        let room = if self.up { 1.0 / mu0 } else { 1.0 / (1.0 - mu0) };
        let towards = |mean: f64| {
            let d = mean - mu0;
            let lam = d / (state.variance() + d * d);
            let lam = if self.up { lam } else { -lam };
            lam.clamp(0.0, BET_CAP * room)
        };
        let first = match plan {
            None => towards(state.mean()),
            Some(effect) => planned_stake(state.rate_a(), effect, mu0, self.up, PLANNED_BET_CAP * room),
        };
        // The arms equal: X has mean 1/2.
        [first, if self.mixed { towards(0.5) } else { 0.0 }]
    }

    fn update(&mut self, x: f64, stakes: [f64; 2], n: u64, log_threshold: f64) {
        let gain = if self.up { x - self.mu0 } else { self.mu0 - x };
        for (k, stake) in self.log_k.iter_mut().zip(stakes) {
            *k += (stake * gain).ln_1p();
        }
        if self.crossed_at.is_none() && self.log_capital() >= log_threshold {
            self.crossed_at = Some(n);
        }
    }
}

/// The growth-optimal stake against the planned alternative: A at its running rate `pa`, B at
/// `pa ± effect` (independent arms), maximising E log(1 + λ(X − μ₀)) over λ ∈ [0, cap] — a concave
/// function, so a bisection of its derivative finds it.
fn planned_stake(pa: f64, effect: f64, mu0: f64, up: bool, cap: f64) -> f64 {
    let pa = pa.clamp(0.0, 1.0);
    let pb = if up { (pa + effect).min(1.0) } else { (pa - effect).max(0.0) };
    // X = (Z + 1)/2 with Z ∈ {1, 0, −1}.
    let (q_up, q_down) = (pb * (1.0 - pa), pa * (1.0 - pb));
    let q_mid = 1.0 - q_up - q_down;
    let sign = if up { 1.0 } else { -1.0 };
    let outcomes = [(q_up, sign * (1.0 - mu0)), (q_mid, sign * (0.5 - mu0)), (q_down, sign * (0.0 - mu0))];
    let slope = |lam: f64| outcomes.iter().map(|&(q, g)| q * g / (1.0 + lam * g)).sum::<f64>();
    if slope(0.0) <= 0.0 {
        return 0.0;
    }
    if slope(cap) >= 0.0 {
        return cap;
    }
    let (mut lo, mut hi) = (0.0, cap);
    for _ in 0..50 {
        let mid = 0.5 * (lo + hi);
        if slope(mid) > 0.0 {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    lo
}

/// Running estimates the bets read (WSR's regularised mean and variance of X, and A's rate).
#[derive(Debug, Clone, Default)]
struct Running {
    n: u64,
    sum_x: f64,
    sum_sq_dev: f64,
    sum_a: f64,
}

impl Running {
    fn mean(&self) -> f64 {
        (0.5 + self.sum_x) / (self.n as f64 + 1.0)
    }
    fn variance(&self) -> f64 {
        (0.25 + self.sum_sq_dev) / (self.n as f64 + 1.0)
    }
    fn rate_a(&self) -> f64 {
        (0.5 + self.sum_a) / (self.n as f64 + 1.0)
    }
    /// WSR's σ̂²ₜ sums the squared deviations from μ̂ᵢ, the mean including the i-th value.
    fn push(&mut self, p: Pair, x: f64) {
        self.sum_x += x;
        self.sum_a += p.a;
        self.n += 1;
        let mean = self.mean();
        self.sum_sq_dev += (x - mean) * (x - mean);
    }
}

/// The comparison of a stream of pairs, updated one pair at a time.
#[derive(Debug, Clone)]
pub struct SequentialTest {
    config: SequentialConfig,
    log_threshold: f64,
    running: Running,
    /// Δ > 0, Δ < −δ, Δ > −δ, Δ < δ.
    better: Bettor,
    worse: Bettor,
    above_margin: Bettor,
    below_margin: Bettor,
}

impl SequentialTest {
    /// # Panics
    /// If the configuration does not validate.
    pub fn new(config: SequentialConfig) -> Self {
        if let Err(e) = config.validate() {
            panic!("{e}");
        }
        let d = config.margin;
        SequentialTest {
            config,
            log_threshold: (2.0 / config.alpha).ln(),
            running: Running::default(),
            better: Bettor::new(0.0, true),
            worse: Bettor::new(-d, false),
            above_margin: Bettor::new(-d, true),
            below_margin: Bettor::new(d, false),
        }
    }

    /// Adds one pair (outcomes clamped to [0, 1]; a NaN counts as 0).
    pub fn push(&mut self, pair: Pair) {
        let clean = |v: f64| if v.is_nan() { 0.0 } else { v.clamp(0.0, 1.0) };
        let pair = Pair { a: clean(pair.a), b: clean(pair.b) };
        let x = (pair.b - pair.a + 1.0) / 2.0;
        let n = self.running.n + 1;
        let plan = self.config.plan_effect;
        for bettor in [&mut self.better, &mut self.worse, &mut self.above_margin, &mut self.below_margin] {
            let stakes = bettor.stakes(&self.running, plan);
            bettor.update(x, stakes, n, self.log_threshold);
        }
        self.running.push(pair, x);
    }

    /// The decision now, and the pair count at which it was first reached.
    pub fn decision(&self) -> (Decision, Option<u64>) {
        let margin = self.config.margin > 0.0;
        if let Some(n) = self.better.crossed_at {
            return (Decision::Better, Some(n));
        }
        if let Some(n) = self.worse.crossed_at {
            return (Decision::Worse, Some(n));
        }
        if margin {
            if let (Some(a), Some(b)) = (self.above_margin.crossed_at, self.below_margin.crossed_at) {
                return (Decision::NoPracticalDifference, Some(a.max(b)));
            }
            if let Some(n) = self.above_margin.crossed_at {
                return (Decision::NotWorse, Some(n));
            }
        }
        (Decision::Undecided, None)
    }

    /// How many more pairs until the claim the data lean to is decided, if the pairs to come looked
    /// like those so far: each open claim's log capital grows per pair by the mean of
    /// log(1 + λ·gain) over the pairs seen, at the current stake. `None` before any pair, or when
    /// no claim's capital grows.
    pub fn more_pairs_needed(&self, pairs: &[Pair]) -> Option<u64> {
        if self.decision().0 != Decision::Undecided {
            return Some(0);
        }
        if pairs.is_empty() {
            return None;
        }
        let plan = self.config.plan_effect;
        let needed = |b: &Bettor| -> Option<f64> {
            if b.crossed_at.is_some() {
                return Some(0.0);
            }
            // Each gambler's growth at its current stake; a mixed bettor's capital reaches the
            // threshold when one gambler's reaches it plus ln 2 (the other's half aside).
            let stakes = b.stakes(&self.running, plan);
            let gamblers = if b.mixed { 2 } else { 1 };
            (0..gamblers)
                .filter_map(|i| {
                    let growth = pairs
                        .iter()
                        .map(|p| {
                            let x = (p.b - p.a + 1.0) / 2.0;
                            let gain = if b.up { x - b.mu0 } else { b.mu0 - x };
                            (stakes[i] * gain).ln_1p()
                        })
                        .sum::<f64>()
                        / pairs.len() as f64;
                    let target = self.log_threshold + if b.mixed { std::f64::consts::LN_2 } else { 0.0 };
                    (growth > 0.0).then(|| ((target - b.log_k[i]) / growth).max(0.0))
                })
                .min_by(f64::total_cmp)
        };
        let mut options = vec![needed(&self.better), needed(&self.worse)];
        if self.config.margin > 0.0 {
            options.push(needed(&self.above_margin));
            options.push(match (needed(&self.above_margin), needed(&self.below_margin)) {
                (Some(x), Some(y)) => Some(x.max(y)),
                _ => None,
            });
        }
        options.into_iter().flatten().map(|x| x.ceil() as u64).min()
    }

    /// Pairs so far.
    pub fn pairs(&self) -> u64 {
        self.running.n
    }

    /// The current e-values (capitals) of the four claims: Δ > 0, Δ < −δ, Δ > −δ, Δ < δ.
    pub fn e_values(&self) -> [f64; 4] {
        [&self.better, &self.worse, &self.above_margin, &self.below_margin].map(|b| b.log_capital().exp())
    }
}

/// Everything a comparison reports.
#[derive(Debug, Clone, PartialEq)]
pub struct SequentialResult {
    pub decision: Decision,
    /// The pair count at which the decision was first reached (the rollouts it needed: twice that).
    pub decided_at: Option<u64>,
    pub pairs: u64,
    pub mean_a: f64,
    pub mean_b: f64,
    /// The anytime-valid (1 − α) confidence sequence of Δ after all pairs (running intersection).
    pub confidence_sequence: (f64, f64),
    /// e-values of Δ > 0, Δ < −δ, Δ > −δ, Δ < δ.
    pub e_values: [f64; 4],
    /// More pairs until a decision at the observed outcomes (0 once decided).
    pub more_pairs: Option<u64>,
}

/// Runs the test over `pairs` in order.
pub fn compare_pairs(pairs: &[Pair], config: SequentialConfig) -> SequentialResult {
    let mut test = SequentialTest::new(config);
    for &p in pairs {
        test.push(p);
    }
    let (decision, decided_at) = test.decision();
    let n = pairs.len().max(1) as f64;
    SequentialResult {
        decision,
        decided_at,
        pairs: test.pairs(),
        mean_a: pairs.iter().map(|p| p.a).sum::<f64>() / n,
        mean_b: pairs.iter().map(|p| p.b).sum::<f64>() / n,
        confidence_sequence: confidence_sequence(pairs, config),
        e_values: test.e_values(),
        more_pairs: test.more_pairs_needed(pairs),
    }
}

/// Whether the betting process against `m` in direction `up` ever crossed 2/α over `pairs`.
fn excluded(pairs: &[Pair], m: f64, up: bool, config: &SequentialConfig) -> bool {
    let mut running = Running::default();
    let mut bettor = Bettor::new(m, up);
    let log_threshold = (2.0 / config.alpha).ln();
    for (i, &p) in pairs.iter().enumerate() {
        let x = (p.b - p.a + 1.0) / 2.0;
        let stakes = bettor.stakes(&running, config.plan_effect);
        bettor.update(x, stakes, i as u64 + 1, log_threshold);
        if bettor.crossed_at.is_some() {
            return true;
        }
        running.push(p, x);
    }
    false
}

/// The (1 − α) confidence sequence of Δ after `pairs`, intersected over time: the lowest m not
/// proved exceeded and the highest not proved undercut, each by bisection (a process betting
/// against m crosses sooner the further m lies from Δ). 40 steps of O(pairs) each per end.
pub fn confidence_sequence(pairs: &[Pair], config: SequentialConfig) -> (f64, f64) {
    if pairs.is_empty() {
        return (-1.0, 1.0);
    }
    let n = pairs.len() as f64;
    let centre = pairs.iter().map(|p| p.b - p.a).sum::<f64>() / n;
    let bisect = |up: bool| {
        // `far` is excluded (or the bound itself), `near` is not.
        let (mut far, mut near) = if up { (-1.0, centre) } else { (1.0, centre) };
        if !excluded(pairs, far * (1.0 - 1e-9), up, &config) {
            return far;
        }
        for _ in 0..40 {
            let mid = 0.5 * (far + near);
            if excluded(pairs, mid, up, &config) {
                far = mid;
            } else {
                near = mid;
            }
        }
        far
    };
    (bisect(true), bisect(false))
}

/// Pairs two arms' outcomes. Each item is `(arrival, key, outcome)`; with keys, the rollouts that
/// share a key are paired (the k-th of A with that key with the k-th of B), without, the i-th of
/// A with the i-th of B. A pair is complete when its later rollout arrives, and pairs come out in
/// that order. Returns the pairs and the rollouts of A and of B left without a partner.
pub fn pair_by_key<K: Eq + std::hash::Hash + Clone>(
    a: &[(u64, Option<K>, f64)],
    b: &[(u64, Option<K>, f64)],
) -> (Vec<Pair>, usize, usize) {
    use std::collections::HashMap;
    let by_arrival = |items: &[(u64, Option<K>, f64)]| {
        let mut v: Vec<_> = items.to_vec();
        v.sort_by_key(|x| x.0);
        v
    };
    let (a, b) = (by_arrival(a), by_arrival(b));
    let mut out: Vec<(u64, Pair)> = Vec::new();
    let (mut used_a, mut used_b) = (0usize, 0usize);
    // Keyed rollouts: queue A's by key, match B's against them (and then the other way round).
    let mut waiting: HashMap<K, std::collections::VecDeque<(u64, f64)>> = HashMap::new();
    for (t, k, y) in a.iter().filter_map(|(t, k, y)| k.clone().map(|k| (*t, k, *y))) {
        waiting.entry(k).or_default().push_back((t, y));
    }
    for (t, k, y) in b.iter().filter_map(|(t, k, y)| k.clone().map(|k| (*t, k, *y))) {
        if let Some((ta, ya)) = waiting.get_mut(&k).and_then(|q| q.pop_front()) {
            out.push((ta.max(t), Pair { a: ya, b: y }));
            used_a += 1;
            used_b += 1;
        }
    }
    // Rollouts without a key: in arrival order.
    let plain_a: Vec<_> = a.iter().filter(|x| x.1.is_none()).collect();
    let plain_b: Vec<_> = b.iter().filter(|x| x.1.is_none()).collect();
    for (x, y) in plain_a.iter().zip(plain_b.iter()) {
        out.push((x.0.max(y.0), Pair { a: x.2, b: y.2 }));
        used_a += 1;
        used_b += 1;
    }
    out.sort_by_key(|x| x.0);
    (out.into_iter().map(|x| x.1).collect(), a.len() - used_a, b.len() - used_b)
}

/// The 2×2 table of paired binary outcomes: the discordant pairs carry the difference.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct PairedCounts {
    /// Both succeeded.
    pub both: u64,
    /// Only A succeeded.
    pub only_a: u64,
    /// Only B succeeded.
    pub only_b: u64,
    /// Both failed.
    pub neither: u64,
}

impl PairedCounts {
    /// Tallies pairs of 0/1 outcomes (anything ≥ 0.5 counts as a success).
    pub fn of(pairs: &[Pair]) -> Self {
        let mut c = PairedCounts::default();
        for p in pairs {
            match (p.a >= 0.5, p.b >= 0.5) {
                (true, true) => c.both += 1,
                (true, false) => c.only_a += 1,
                (false, true) => c.only_b += 1,
                (false, false) => c.neither += 1,
            }
        }
        c
    }
    pub fn n(&self) -> u64 {
        self.both + self.only_a + self.only_b + self.neither
    }
    /// p_B − p_A = (only_b − only_a)/n: the concordant pairs cancel.
    pub fn difference(&self) -> f64 {
        (self.only_b as f64 - self.only_a as f64) / self.n().max(1) as f64
    }
    /// The standard error of that difference for paired data,
    /// √((only_a + only_b) − (only_b − only_a)²/n) / n; the unpaired one would add back the
    /// concordant pairs' covariance.
    pub fn standard_error(&self) -> f64 {
        let n = self.n() as f64;
        if n == 0.0 {
            return 0.0;
        }
        let d = self.only_b as f64 - self.only_a as f64;
        (((self.only_a + self.only_b) as f64) - d * d / n).max(0.0).sqrt() / n
    }
    /// McNemar's statistic (only_b − only_a)/√(only_a + only_b) (0 with no discordant pair).
    pub fn mcnemar_z(&self) -> f64 {
        let disc = (self.only_a + self.only_b) as f64;
        if disc == 0.0 {
            return 0.0;
        }
        (self.only_b as f64 - self.only_a as f64) / disc.sqrt()
    }
}

/// Fisher's exact test, two-sided (the tables at most as probable as the observed one), of
/// k1/n1 against k2/n2: the fixed-n reference the sequential test is benchmarked against.
pub fn fisher_exact_two_sided(k1: u64, n1: u64, k2: u64, n2: u64) -> f64 {
    let s = k1 + k2;
    let n = n1 + n2;
    let lo = s.saturating_sub(n2);
    let hi = s.min(n1);
    let pmf: Vec<f64> = (lo..=hi).map(|k| hypergeometric_ln(k, n1, s, n).exp()).collect();
    let observed = pmf[(k1 - lo) as usize];
    let total: f64 = pmf.iter().sum();
    // Ties within a relative 1e-7 count as at most as probable (as R and scipy do).
    pmf.iter().filter(|&&q| q <= observed * (1.0 + 1e-7)).sum::<f64>() / total
}

/// ln P(X = k) for X hypergeometric: k successes among n1 drawn from n with s successes.
fn hypergeometric_ln(k: u64, n1: u64, s: u64, n: u64) -> f64 {
    ln_choose(s, k) + ln_choose(n - s, n1 - k) - ln_choose(n, n1)
}

/// ln C(n, k) by the log-gamma of Lanczos (g = 7, 9 terms; ~1e-15 relative).
pub fn ln_choose(n: u64, k: u64) -> f64 {
    ln_gamma(n as f64 + 1.0) - ln_gamma(k as f64 + 1.0) - ln_gamma((n - k) as f64 + 1.0)
}

fn ln_gamma(x: f64) -> f64 {
    const G: f64 = 7.0;
    const C: [f64; 9] = [
        0.999_999_999_999_809_9,
        676.520_368_121_885_1,
        -1_259.139_216_722_402_8,
        771.323_428_777_653_1,
        -176.615_029_162_140_6,
        12.507_343_278_686_905,
        -0.138_571_095_265_720_12,
        9.984_369_578_019_572e-6,
        1.505_632_735_149_311_6e-7,
    ];
    if x < 0.5 {
        return (std::f64::consts::PI / (std::f64::consts::PI * x).sin()).ln() - ln_gamma(1.0 - x);
    }
    let x = x - 1.0;
    let mut a = C[0];
    let t = x + G + 0.5;
    for (i, c) in C.iter().enumerate().skip(1) {
        a += c / (x + i as f64);
    }
    0.5 * (2.0 * std::f64::consts::PI).ln() + (x + 0.5) * t.ln() - t + a.ln()
}
