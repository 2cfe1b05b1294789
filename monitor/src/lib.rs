//! `monitor`: failure monitors calibrated and evaluated on stored episodes.
//!
//! It owns the calibration pool (a checkpoint's labeled, unsteered episodes at a store version,
//! less the episodes the verifier trained on), the random partition of its successes into calibration and
//! held-out parts, calibration ([`calibrate`]: the split-conformal threshold on the calibration
//! successes' peaks, or with a confidence the training-conditional one) and evaluation against
//! labels ([`evaluate`]: the false-alarm rate on held-out successes with its Wilson interval, the
//! detection rate on failures and the lead time before a failure's labeled span or the episode's
//! end), with per-step traces. [`calibration_draws`] repeats the calibration over many random
//! partitions of the pool (scored once) to show how each threshold's held-out false-alarm rate
//! spreads from one calibration draw to the next.
//!
//! The rule itself — the record, the running statistic, the threshold, the alarm — is the
//! verifier core's (`verifier::monitor`), which the robot (`steer::Monitor`) and the Python
//! package step the same way. The pool is selected through the store's selection path
//! (`store::select`) and scored by the verifier core (`verifier::stored::score_each_episode`),
//! whose error, [`StoredEpisodesError`], is this crate's.

use std::collections::{HashMap, HashSet};

use serde::Serialize;
use sha2::{Digest, Sha256};
use store::{EpisodeRecord, Label, Store};
use store_artifacts::ArtifactRecord;
use verifier::monitor::{
    conformal_rank, conformal_threshold, held_out_exceedance, peak, training_conditional_rank,
    training_conditional_threshold, MonitorRecord, MonitorStep, Statistic, MONITOR_SCHEMA_VERSION,
    SPLIT_CONFORMAL_PEAK, SPLIT_CONFORMAL_PEAK_PAC,
};
use verifier::stored::{score_each_episode, StoredEpisodesError};
use verifier::Verifier;

pub type Result<T, E = StoredEpisodesError> = std::result::Result<T, E>;

/// How to calibrate.
#[derive(Debug, Clone)]
pub struct CalibrateSpec {
    pub alpha: f64,
    /// 1 − δ: with it the threshold is training-conditional (this calibration's false-alarm rate
    /// is at most α with probability at least 1 − δ over the calibration draw); without it, the
    /// split-conformal one (at most α on average over calibration draws).
    pub confidence: Option<f64>,
    pub statistic: Statistic,
    /// Draws the calibration part of the pool's successes.
    pub seed: u64,
    /// The share of the pool's successes the threshold is calibrated on (the rest are held out
    /// to measure the false-alarm rate).
    pub calibration_fraction: f64,
    /// The store version whose labels to read (default: the head).
    pub version: Option<i64>,
}

impl Default for CalibrateSpec {
    fn default() -> Self {
        CalibrateSpec {
            alpha: 0.1,
            confidence: None,
            statistic: Statistic::RiskEma { smoothing: 0.8 },
            seed: 0,
            calibration_fraction: 0.5,
            version: None,
        }
    }
}

/// What evaluating a monitor against labels measured.
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize)]
pub struct Evaluation {
    pub version: i64,
    /// Held-out successful episodes, and how many of them raised the alarm.
    pub successes: u64,
    pub false_alarms: u64,
    pub false_alarm_rate: Option<f64>,
    /// Wilson 95% interval of the false-alarm rate.
    pub false_alarm_interval: (f64, f64),
    pub failures: u64,
    pub detected: u64,
    pub detection_rate: Option<f64>,
    pub detection_interval: (f64, f64),
    /// Failures whose alarm fired before their onset (lead time > 0).
    pub detected_before_onset: u64,
    /// Failures whose onset is a labeled span's start (the others' is the episode's end).
    pub failures_with_spans: u64,
    /// Lead time of detected failures in steps: onset − first alarm step (median, quartiles).
    pub lead_steps_median: Option<f64>,
    pub lead_steps_quartiles: Option<(f64, f64)>,
}

/// One evaluated episode, step by step.
#[derive(Debug, Clone, Serialize)]
pub struct EpisodeTrace {
    pub episode_id: String,
    pub label: Label,
    /// The failure's onset step: its first labeled span's start, else the episode's length.
    pub onset: Option<i64>,
    /// The onset is a labeled span's start.
    pub onset_from_span: bool,
    pub first_alarm: Option<usize>,
    pub steps: Vec<MonitorStep>,
}

/// A calibrated monitor with its held-out evaluation.
#[derive(Debug, Clone)]
pub struct Calibration {
    pub record: MonitorRecord,
    pub evaluation: Evaluation,
    pub traces: Vec<EpisodeTrace>,
    /// For comparison when the record's threshold is training-conditional: the split-conformal
    /// threshold of the same calibration episodes and its evaluation on the same held-out
    /// episodes (`None` for a split-conformal record, or when the episodes are too few for it).
    pub marginal: Option<(f64, Evaluation)>,
}

/// A threshold that could not be set, with the pool it was asked of.
fn too_few(
    e: impl std::fmt::Display,
    successes: usize,
    artifact: &ArtifactRecord,
    version: i64,
    spec: &CalibrateSpec,
) -> StoredEpisodesError {
    StoredEpisodesError::Invalid(format!(
        "{e} ({successes} labeled successes of {}/{} at version {version} that artifact {} did not train on, \
         {:.0}% of them for calibration)",
        artifact.policy,
        artifact.checkpoint,
        artifact.id,
        spec.calibration_fraction * 100.0
    ))
}

/// The pool at a version: the checkpoint's labeled episodes the verifier did not train on.
struct Pool {
    version: i64,
    successes: Vec<EpisodeRecord>,
    failures: Vec<EpisodeRecord>,
    onsets: HashMap<String, i64>,
}

async fn pool(store: &Store, artifact: &ArtifactRecord, version: Option<i64>) -> Result<Pool> {
    let selection = store::Selection {
        version,
        policy: Some(artifact.policy.clone()),
        checkpoint: Some(artifact.checkpoint.clone()),
        ..Default::default()
    };
    let selected = store::select(store, &selection).await?;
    let trained_on: HashSet<String> = match &artifact.split_id {
        Some(split) => store
            .split_episodes(split)
            .await?
            .into_iter()
            .filter(|m| m.part == "train")
            .map(|m| m.episode_id)
            .collect(),
        None => HashSet::new(),
    };
    // Only what the checkpoint's policy did on its own, as splits take: a steered run's episodes
    // are the policy plus a verifier, another distribution of scores.
    let steered: HashSet<String> = store
        .runs(None)
        .await?
        .into_iter()
        .filter(|r| r.steering != store::Steering::Base)
        .map(|r| r.id)
        .collect();
    let mut pool =
        Pool { version: selected.version, successes: vec![], failures: vec![], onsets: HashMap::new() };
    for e in selected.episodes {
        if trained_on.contains(&e.id) || e.run_id.as_ref().is_some_and(|r| steered.contains(r)) {
            continue;
        }
        match e.label {
            Label::Success => pool.successes.push(e),
            Label::Failure => {
                let span_start = selected
                    .label_data
                    .get(&e.id)
                    .and_then(|d| d.get("spans"))
                    .and_then(|s| s.as_array())
                    .and_then(|spans| spans.iter().filter_map(|s| s.get("start_step")?.as_i64()).min());
                if let Some(s) = span_start {
                    pool.onsets.insert(e.id.clone(), s);
                }
                pool.failures.push(e)
            }
            Label::Unknown => {}
        }
    }
    Ok(pool)
}

/// The sort key of an episode in the partition drawn by `seed`.
fn shuffle_key(seed: u64, id: &str) -> [u8; 32] {
    let mut h = Sha256::new();
    h.update(seed.to_le_bytes());
    h.update(id.as_bytes());
    h.finalize().into()
}

/// Orders episodes by a seeded hash of their id: a random partition any machine reproduces.
fn shuffled(mut eps: Vec<EpisodeRecord>, seed: u64) -> Vec<EpisodeRecord> {
    eps.sort_by_cached_key(|e| shuffle_key(seed, &e.id));
    eps
}

/// How many of `n` successes the calibration takes.
fn calibration_size(n: usize, fraction: f64) -> usize {
    ((n as f64 * fraction).round() as usize).min(n)
}

fn check_spec(spec: &CalibrateSpec) -> Result<()> {
    spec.statistic.check()?;
    if !(spec.calibration_fraction > 0.0 && spec.calibration_fraction < 1.0) {
        return Err(StoredEpisodesError::Invalid(format!(
            "the calibration fraction must be in (0, 1), got {}",
            spec.calibration_fraction
        )));
    }
    if !(spec.alpha > 0.0 && spec.alpha < 1.0) {
        return Err(StoredEpisodesError::Invalid(format!("alpha must be in (0, 1), got {}", spec.alpha)));
    }
    if let Some(c) = spec.confidence {
        if !(c > 0.0 && c < 1.0) {
            return Err(StoredEpisodesError::Invalid(format!(
                "the confidence (1 - delta) must be in (0, 1), got {c}"
            )));
        }
    }
    Ok(())
}

/// The threshold `spec` asks for on these calibration peaks, and its method.
fn threshold_of(peaks: &[f64], spec: &CalibrateSpec) -> verifier::Result<(f64, &'static str)> {
    match spec.confidence {
        Some(c) => {
            Ok((training_conditional_threshold(peaks, spec.alpha, 1.0 - c)?, SPLIT_CONFORMAL_PEAK_PAC))
        }
        None => Ok((conformal_threshold(peaks, spec.alpha)?, SPLIT_CONFORMAL_PEAK)),
    }
}

/// Scores each episode's steps (in order) and hands back their scores.
async fn scores_of(store: &Store, verifier: &Verifier, eps: &[EpisodeRecord]) -> Result<Vec<Vec<f32>>> {
    let mut out = vec![Vec::new(); eps.len()];
    score_each_episode(store, eps, verifier, |i, _, s| {
        out[i] = s;
        Ok(())
    })
    .await?;
    Ok(out)
}

fn check_artifact(verifier: &Verifier, artifact: &ArtifactRecord) -> Result<()> {
    if verifier.id() != Some(artifact.id.as_str()) {
        return Err(StoredEpisodesError::Invalid(format!(
            "the verifier loaded ({}) is not artifact {}",
            verifier.id().unwrap_or("without an id"),
            artifact.id
        )));
    }
    Ok(())
}

/// Calibrates a monitor for `artifact` (loaded as `verifier`) on its checkpoint's episodes:
/// the pool's successes are split at random into a calibration part (the threshold) and a
/// held-out part, which with the pool's failures gives the evaluation.
pub async fn calibrate(
    store: &Store,
    verifier: &Verifier,
    artifact: &ArtifactRecord,
    spec: &CalibrateSpec,
) -> Result<Calibration> {
    check_artifact(verifier, artifact)?;
    check_spec(spec)?;
    let pool = pool(store, artifact, spec.version).await?;
    let successes = shuffled(pool.successes, spec.seed);
    let (cal, held_out) = successes.split_at(calibration_size(successes.len(), spec.calibration_fraction));
    let cal_scores = scores_of(store, verifier, cal).await?;
    let peaks: Vec<f64> = cal_scores.iter().map(|s| peak(spec.statistic, s)).collect();
    let (threshold, method) =
        threshold_of(&peaks, spec).map_err(|e| too_few(e, successes.len(), artifact, pool.version, spec))?;
    let mut calibration_episodes: Vec<String> = cal.iter().map(|e| e.id.clone()).collect();
    calibration_episodes.sort();
    let record = MonitorRecord {
        schema_version: MONITOR_SCHEMA_VERSION,
        artifact_id: artifact.id.clone(),
        policy: artifact.policy.clone(),
        checkpoint: artifact.checkpoint.clone(),
        method: method.into(),
        statistic: spec.statistic,
        alpha: spec.alpha,
        confidence: spec.confidence,
        threshold,
        version: pool.version,
        seed: spec.seed,
        calibration_episodes,
    };
    // Every consumer reads the threshold back from the record's JSON: evaluate with what they read.
    let json = serde_json::to_vec(&record).map_err(|e| StoredEpisodesError::Invalid(e.to_string()))?;
    let record = MonitorRecord::from_json(&json)?;
    let (evaluation, traces) =
        measure(store, verifier, &record, held_out, &pool.failures, &pool.onsets, pool.version).await?;
    // The split-conformal threshold of the same episodes, stepped over the same scores.
    let marginal = match record.confidence {
        Some(_) => conformal_threshold(&peaks, spec.alpha).ok().map(|tau| {
            let mut state = verifier::monitor::MonitorState::new(record.statistic, tau);
            let retraced: Vec<EpisodeTrace> = traces
                .iter()
                .map(|t| {
                    state.reset();
                    let steps: Vec<MonitorStep> = t.steps.iter().map(|s| state.update(s.score)).collect();
                    let first_alarm = steps.iter().position(|s| s.alarm);
                    EpisodeTrace { steps, first_alarm, ..t.clone() }
                })
                .collect();
            (tau, summarise(&retraced, pool.version))
        }),
        None => None,
    };
    Ok(Calibration { record, evaluation, traces, marginal })
}

/// Evaluates a monitor against labels at `version` (default: the record's): on the pool's
/// successes outside its calibration set and the pool's failures. At the record's version it
/// reproduces what the calibration measured; at a later one it adds the episodes since.
pub async fn evaluate(
    store: &Store,
    verifier: &Verifier,
    artifact: &ArtifactRecord,
    record: &MonitorRecord,
    version: Option<i64>,
) -> Result<(Evaluation, Vec<EpisodeTrace>)> {
    check_artifact(verifier, artifact)?;
    record.check()?;
    record.check_artifact(Some(&artifact.id))?;
    let pool = pool(store, artifact, Some(version.unwrap_or(record.version))).await?;
    let calibrated: HashSet<&str> = record.calibration_episodes.iter().map(String::as_str).collect();
    let held_out: Vec<EpisodeRecord> = shuffled(pool.successes, record.seed)
        .into_iter()
        .filter(|e| !calibrated.contains(e.id.as_str()))
        .collect();
    measure(store, verifier, record, &held_out, &pool.failures, &pool.onsets, pool.version).await
}

async fn measure(
    store: &Store,
    verifier: &Verifier,
    record: &MonitorRecord,
    successes: &[EpisodeRecord],
    failures: &[EpisodeRecord],
    onsets: &HashMap<String, i64>,
    version: i64,
) -> Result<(Evaluation, Vec<EpisodeTrace>)> {
    let episodes: Vec<EpisodeRecord> = successes.iter().chain(failures).cloned().collect();
    let scores = scores_of(store, verifier, &episodes).await?;
    let mut traces = Vec::with_capacity(episodes.len());
    for (e, s) in episodes.iter().zip(scores) {
        traces.push(trace(record, e, &s, onsets.get(&e.id).copied()));
    }
    Ok((summarise(&traces, version), traces))
}

/// Steps the monitor through an episode's scores.
pub fn trace(
    record: &MonitorRecord,
    e: &EpisodeRecord,
    scores: &[f32],
    span_start: Option<i64>,
) -> EpisodeTrace {
    let mut state = record.state();
    let steps: Vec<MonitorStep> = scores.iter().map(|&x| state.update(x)).collect();
    let first_alarm = steps.iter().position(|s| s.alarm);
    let onset = (e.label == Label::Failure).then(|| span_start.unwrap_or(e.length));
    let onset_from_span = onset.is_some() && span_start.is_some();
    EpisodeTrace { episode_id: e.id.clone(), label: e.label, onset, onset_from_span, first_alarm, steps }
}

fn quantile(sorted: &[f64], q: f64) -> f64 {
    // Linear interpolation between order statistics (numpy's default).
    let pos = q * (sorted.len() - 1) as f64;
    let (lo, hi) = (pos.floor() as usize, pos.ceil() as usize);
    sorted[lo] + (sorted[hi] - sorted[lo]) * (pos - lo as f64)
}

/// The evaluation of a set of traces.
pub fn summarise(traces: &[EpisodeTrace], version: i64) -> Evaluation {
    let succ: Vec<&EpisodeTrace> = traces.iter().filter(|t| t.label == Label::Success).collect();
    let fail: Vec<&EpisodeTrace> = traces.iter().filter(|t| t.label == Label::Failure).collect();
    let false_alarms = succ.iter().filter(|t| t.first_alarm.is_some()).count() as u64;
    let detected: Vec<&&EpisodeTrace> = fail.iter().filter(|t| t.first_alarm.is_some()).collect();
    let mut leads: Vec<f64> =
        detected.iter().filter_map(|t| Some((t.onset? - t.first_alarm? as i64) as f64)).collect();
    leads.sort_by(f64::total_cmp);
    let rate = |k: u64, n: usize| (n > 0).then(|| k as f64 / n as f64);
    Evaluation {
        version,
        successes: succ.len() as u64,
        false_alarms,
        false_alarm_rate: rate(false_alarms, succ.len()),
        false_alarm_interval: evalstats::wilson(false_alarms, succ.len() as u64),
        failures: fail.len() as u64,
        detected: detected.len() as u64,
        detection_rate: rate(detected.len() as u64, fail.len()),
        detection_interval: evalstats::wilson(detected.len() as u64, fail.len() as u64),
        detected_before_onset: leads.iter().filter(|&&l| l > 0.0).count() as u64,
        failures_with_spans: fail.iter().filter(|t| t.onset_from_span).count() as u64,
        lead_steps_median: (!leads.is_empty()).then(|| quantile(&leads, 0.5)),
        lead_steps_quartiles: (!leads.is_empty()).then(|| (quantile(&leads, 0.25), quantile(&leads, 0.75))),
    }
}

/// One threshold's figures in one calibration draw.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct DrawFigures {
    pub threshold: f64,
    /// Share of the draw's held-out successes whose alarm fires.
    pub false_alarm_rate: f64,
    /// Share of the pool's failures whose alarm fires.
    pub detection_rate: Option<f64>,
}

/// One calibration draw: the pool's successes partitioned by `seed` (as [`calibrate`] with that
/// seed does), calibrated both ways.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Draw {
    pub seed: u64,
    /// The split-conformal threshold (marginal guarantee).
    pub marginal: DrawFigures,
    /// The training-conditional threshold at the spec's confidence.
    pub conditional: DrawFigures,
}

/// One threshold's figures over all draws.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct DrawSummary {
    /// The threshold's rank among the calibration peaks (when every episode has steps).
    pub rank: Option<usize>,
    /// Share of draws whose held-out false-alarm rate exceeds α.
    pub above_alpha: f64,
    /// That share over all partitions of the pool when the peaks are distinct: exact, and a
    /// property of the sizes and the rank alone ([`held_out_exceedance`]). The held-out rate is
    /// measured on finitely many episodes: even a threshold whose rate on fresh successes is at
    /// most α exceeds α on them this often.
    pub above_alpha_expected: Option<f64>,
    pub false_alarm_rate_mean: f64,
    pub false_alarm_rate_median: f64,
    pub detection_rate_median: Option<f64>,
    pub threshold_median: f64,
}

/// Calibrations on resamples of the pool, the pool's successes standing for the population:
/// each draw takes n calibration peaks independently (with replacement) from the pool's
/// successes, and its false-alarm rate is the share of all the pool's successes above its
/// threshold: the rate on fresh successes, exactly, for that population. This is the quantity
/// the guarantees are about, free of a held-out sample's noise.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Resampled {
    pub draws: u64,
    /// Share of draws whose false-alarm rate exceeds α.
    pub marginal_above_alpha: f64,
    pub conditional_above_alpha: f64,
    /// `P(Binomial(n, 1 − α) ≥ k)` for each rank: that share with continuous peaks (ties, as
    /// resampling makes, only lower it).
    pub marginal_expected: Option<f64>,
    pub conditional_expected: Option<f64>,
    pub marginal_false_alarm_rate_mean: f64,
    pub conditional_false_alarm_rate_mean: f64,
}

/// The [`Resampled`] figures of `draws` calibrations of `n_cal` peaks drawn with replacement from
/// `success_peaks` (those of episodes with steps) by a generator seeded `seed`.
pub fn resampled_draws(
    success_peaks: &[f64],
    n_cal: usize,
    alpha: f64,
    confidence: f64,
    draws: u64,
    seed: u64,
) -> Result<Resampled> {
    let mut population: Vec<f64> = success_peaks.iter().copied().filter(|p| p.is_finite()).collect();
    if population.is_empty() || draws == 0 {
        return Err(StoredEpisodesError::Invalid(
            "resampled draws need successes with steps and a draw".into(),
        ));
    }
    population.sort_by(f64::total_cmp);
    let rate = |tau: f64| {
        (population.len() - population.partition_point(|&p| p <= tau)) as f64 / population.len() as f64
    };
    let mut rng = evalstats::splitmix::SplitMix64(seed);
    let (mut above, mut sum) = ([0usize; 2], [0.0f64; 2]);
    for _ in 0..draws {
        let cal: Vec<f64> =
            (0..n_cal).map(|_| population[(rng.next_u64() % population.len() as u64) as usize]).collect();
        let taus = [
            conformal_threshold(&cal, alpha)?,
            training_conditional_threshold(&cal, alpha, 1.0 - confidence)?,
        ];
        for (i, tau) in taus.into_iter().enumerate() {
            let r = rate(tau);
            above[i] += (r > alpha) as usize;
            sum[i] += r;
        }
    }
    let d = draws as f64;
    let expected =
        |k: Option<usize>| k.map(|k| verifier::monitor::binomial_upper_tail(n_cal, 1.0 - alpha, k));
    Ok(Resampled {
        draws,
        marginal_above_alpha: above[0] as f64 / d,
        conditional_above_alpha: above[1] as f64 / d,
        marginal_expected: expected(conformal_rank(n_cal, alpha)),
        conditional_expected: expected(training_conditional_rank(n_cal, alpha, 1.0 - confidence)),
        marginal_false_alarm_rate_mean: sum[0] / d,
        conditional_false_alarm_rate_mean: sum[1] / d,
    })
}

/// [`calibration_draws`]' result.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Draws {
    pub artifact_id: String,
    pub version: i64,
    pub alpha: f64,
    pub confidence: f64,
    pub statistic: Statistic,
    /// The pool's successes, how many each draw calibrates on and holds out, and its failures.
    pub successes: usize,
    pub calibration: usize,
    pub held_out: usize,
    pub failures: usize,
    pub marginal: DrawSummary,
    pub conditional: DrawSummary,
    /// The same number of calibrations on resamples of the pool ([`Resampled`]).
    pub resampled: Resampled,
    pub draws: Vec<Draw>,
}

/// The figures of `draws` calibration draws (seeds 0, 1, …) on a pool given as its successes'
/// ids and peaks and its failures' peaks: alarms fire on an episode iff its peak exceeds the
/// threshold, so the pool is scored once, not per draw.
pub fn draws_from_peaks(
    successes: &[(String, f64)],
    failure_peaks: &[f64],
    spec: &CalibrateSpec,
    draws: u64,
) -> Result<Vec<Draw>> {
    check_spec(spec)?;
    let confidence = spec.confidence.ok_or_else(|| {
        StoredEpisodesError::Invalid(
            "calibration draws compare against the training-conditional threshold: give a confidence".into(),
        )
    })?;
    let n_cal = calibration_size(successes.len(), spec.calibration_fraction);
    if n_cal == successes.len() {
        return Err(StoredEpisodesError::Invalid(format!(
            "{} successes leave none held out at a calibration fraction of {}",
            successes.len(),
            spec.calibration_fraction
        )));
    }
    let rate = |fired: usize, n: usize| fired as f64 / n as f64;
    let figures = |tau: f64, held_out: &[f64]| DrawFigures {
        threshold: tau,
        false_alarm_rate: rate(held_out.iter().filter(|&&p| p > tau).count(), held_out.len()),
        detection_rate: (!failure_peaks.is_empty())
            .then(|| rate(failure_peaks.iter().filter(|&&p| p > tau).count(), failure_peaks.len())),
    };
    let mut out = Vec::with_capacity(draws as usize);
    let mut order: Vec<&(String, f64)> = successes.iter().collect();
    for seed in 0..draws {
        order.sort_by_cached_key(|(id, _)| shuffle_key(seed, id));
        let peaks: Vec<f64> = order.iter().map(|(_, p)| *p).collect();
        let (cal, held_out) = peaks.split_at(n_cal);
        let marginal = conformal_threshold(cal, spec.alpha)?;
        let conditional = training_conditional_threshold(cal, spec.alpha, 1.0 - confidence)?;
        out.push(Draw {
            seed,
            marginal: figures(marginal, held_out),
            conditional: figures(conditional, held_out),
        });
    }
    Ok(out)
}

/// Summarises one threshold's figures over draws (`rank` and `above_alpha_expected` are left
/// `None`: they need the pool's sizes).
pub fn summarise_draws(draws: &[Draw], alpha: f64, conditional: bool) -> DrawSummary {
    let pick = |d: &Draw| if conditional { d.conditional } else { d.marginal };
    let sorted = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v
    };
    let median = |v: Vec<f64>| (!v.is_empty()).then(|| quantile(&sorted(v), 0.5));
    let fa: Vec<f64> = draws.iter().map(|d| pick(d).false_alarm_rate).collect();
    let n = draws.len().max(1) as f64;
    DrawSummary {
        rank: None,
        above_alpha: fa.iter().filter(|&&r| r > alpha).count() as f64 / n,
        above_alpha_expected: None,
        false_alarm_rate_mean: fa.iter().sum::<f64>() / n,
        false_alarm_rate_median: median(fa).unwrap_or(f64::NAN),
        detection_rate_median: median(draws.iter().filter_map(|d| pick(d).detection_rate).collect()),
        threshold_median: median(draws.iter().map(|d| pick(d).threshold).collect()).unwrap_or(f64::NAN),
    }
}

/// Repeats the calibration `draws` times on `artifact`'s pool (seeds 0, 1, …; `spec.seed` is not
/// used): each draw partitions the pool's successes as [`calibrate`] would with its seed, sets the
/// split-conformal and the training-conditional threshold (at `spec.confidence`, required) on
/// the calibration part, and measures each on the held-out successes (false-alarm rate) and the
/// pool's failures (detection rate); and as many calibrations on resamples of the pool
/// ([`resampled_draws`], seed 0). Every episode is scored once.
pub async fn calibration_draws(
    store: &Store,
    verifier: &Verifier,
    artifact: &ArtifactRecord,
    spec: &CalibrateSpec,
    draws: u64,
) -> Result<Draws> {
    check_artifact(verifier, artifact)?;
    check_spec(spec)?;
    let confidence = spec.confidence.ok_or_else(|| {
        StoredEpisodesError::Invalid("calibration draws need a confidence (1 - delta)".into())
    })?;
    if draws == 0 {
        return Err(StoredEpisodesError::Invalid("calibration draws: give at least one".into()));
    }
    let pool = pool(store, artifact, spec.version).await?;
    let peaks_of =
        |scores: Vec<Vec<f32>>| -> Vec<f64> { scores.iter().map(|s| peak(spec.statistic, s)).collect() };
    let success_peaks = peaks_of(scores_of(store, verifier, &pool.successes).await?);
    let failure_peaks = peaks_of(scores_of(store, verifier, &pool.failures).await?);
    let successes: Vec<(String, f64)> =
        pool.successes.iter().map(|e| e.id.clone()).zip(success_peaks).collect();
    let all = draws_from_peaks(&successes, &failure_peaks, spec, draws)
        .map_err(|e| too_few(e, successes.len(), artifact, pool.version, spec))?;
    let n_cal = calibration_size(successes.len(), spec.calibration_fraction);
    let held_out = successes.len() - n_cal;
    let with_expectation = |mut s: DrawSummary, rank: Option<usize>| {
        // Episodes without steps have no peak: the rank would vary from draw to draw.
        if successes.iter().all(|(_, p)| p.is_finite()) {
            s.rank = rank;
            s.above_alpha_expected = rank.map(|k| held_out_exceedance(n_cal, held_out, k, spec.alpha));
        }
        s
    };
    let marginal =
        with_expectation(summarise_draws(&all, spec.alpha, false), conformal_rank(n_cal, spec.alpha));
    let conditional = with_expectation(
        summarise_draws(&all, spec.alpha, true),
        training_conditional_rank(n_cal, spec.alpha, 1.0 - confidence),
    );
    let peaks: Vec<f64> = successes.iter().map(|(_, p)| *p).collect();
    let resampled = resampled_draws(&peaks, n_cal, spec.alpha, confidence, draws, 0)?;
    Ok(Draws {
        artifact_id: artifact.id.clone(),
        version: pool.version,
        alpha: spec.alpha,
        confidence,
        statistic: spec.statistic,
        successes: successes.len(),
        calibration: n_cal,
        held_out,
        failures: failure_peaks.len(),
        marginal,
        conditional,
        resampled,
        draws: all,
    })
}
