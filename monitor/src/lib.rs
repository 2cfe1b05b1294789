//! `monitor`: failure monitors calibrated and evaluated on stored episodes.
//!
//! It owns the calibration pool (a checkpoint's labeled, unsteered episodes at a store version,
//! less the episodes the verifier trained on), the random partition of its successes into calibration and
//! held-out parts, calibration ([`calibrate`]: the split-conformal threshold on the calibration
//! successes' peaks) and evaluation against labels ([`evaluate`]: the false-alarm rate on
//! held-out successes with its Wilson interval, the detection rate on failures and the lead time
//! before a failure's labeled span or the episode's end), with per-step traces.
//!
//! The rule itself — the record, the running statistic, the threshold, the alarm — is the
//! verifier core's (`verifier::monitor`), which the robot (`steer::Monitor`) and the Python
//! package step the same way. Scoring a stored episode is `export::score_each_episode`.

use std::collections::{HashMap, HashSet};

use serde::Serialize;
use sha2::{Digest, Sha256};
use store::{ArtifactRecord, EpisodeRecord, Label, Store};
use verifier::monitor::{
    conformal_threshold, peak, MonitorRecord, MonitorStep, Statistic, MONITOR_SCHEMA_VERSION,
    SPLIT_CONFORMAL_PEAK,
};
use verifier::Verifier;

#[derive(Debug, thiserror::Error)]
pub enum MonitorError {
    #[error(transparent)]
    Store(#[from] store::StoreError),
    #[error(transparent)]
    Export(#[from] export::ExportError),
    #[error(transparent)]
    Verifier(#[from] verifier::VerifierError),
    #[error("{0}")]
    Invalid(String),
}

pub type Result<T, E = MonitorError> = std::result::Result<T, E>;

/// How to calibrate.
#[derive(Debug, Clone)]
pub struct CalibrateSpec {
    pub alpha: f64,
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
}

/// The pool at a version: the checkpoint's labeled episodes the verifier did not train on.
struct Pool {
    version: i64,
    successes: Vec<EpisodeRecord>,
    failures: Vec<EpisodeRecord>,
    onsets: HashMap<String, i64>,
}

async fn pool(store: &Store, artifact: &ArtifactRecord, version: Option<i64>) -> Result<Pool> {
    let selection = export::Selection {
        version,
        policy: Some(artifact.policy.clone()),
        checkpoint: Some(artifact.checkpoint.clone()),
        ..Default::default()
    };
    let selected = export::select(store, &selection).await?;
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

/// Orders episodes by a seeded hash of their id: a random partition any machine reproduces.
fn shuffled(mut eps: Vec<EpisodeRecord>, seed: u64) -> Vec<EpisodeRecord> {
    let key = |id: &str| -> [u8; 32] {
        let mut h = Sha256::new();
        h.update(seed.to_le_bytes());
        h.update(id.as_bytes());
        h.finalize().into()
    };
    eps.sort_by_cached_key(|e| key(&e.id));
    eps
}

/// Scores each episode's steps (in order) and hands back their scores.
async fn scores_of(store: &Store, verifier: &Verifier, eps: &[EpisodeRecord]) -> Result<Vec<Vec<f32>>> {
    let mut out = vec![Vec::new(); eps.len()];
    export::score_each_episode(store, eps, verifier, |i, _, s| {
        out[i] = s;
        Ok(())
    })
    .await?;
    Ok(out)
}

fn check_artifact(verifier: &Verifier, artifact: &ArtifactRecord) -> Result<()> {
    if verifier.id() != Some(artifact.id.as_str()) {
        return Err(MonitorError::Invalid(format!(
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
    spec.statistic.check()?;
    if !(spec.calibration_fraction > 0.0 && spec.calibration_fraction < 1.0) {
        return Err(MonitorError::Invalid(format!(
            "the calibration fraction must be in (0, 1), got {}",
            spec.calibration_fraction
        )));
    }
    let pool = pool(store, artifact, spec.version).await?;
    let successes = shuffled(pool.successes, spec.seed);
    let n_cal = ((successes.len() as f64) * spec.calibration_fraction).round() as usize;
    let (cal, held_out) = successes.split_at(n_cal.min(successes.len()));
    let cal_scores = scores_of(store, verifier, cal).await?;
    let peaks: Vec<f64> = cal_scores.iter().map(|s| peak(spec.statistic, s)).collect();
    let threshold = conformal_threshold(&peaks, spec.alpha).map_err(|e| {
        MonitorError::Invalid(format!(
            "{e} ({} labeled successes of {}/{} at version {} that artifact {} did not train on, {:.0}% of them for \
             calibration)",
            successes.len(),
            artifact.policy,
            artifact.checkpoint,
            pool.version,
            artifact.id,
            spec.calibration_fraction * 100.0
        ))
    })?;
    let mut calibration_episodes: Vec<String> = cal.iter().map(|e| e.id.clone()).collect();
    calibration_episodes.sort();
    let record = MonitorRecord {
        schema_version: MONITOR_SCHEMA_VERSION,
        artifact_id: artifact.id.clone(),
        policy: artifact.policy.clone(),
        checkpoint: artifact.checkpoint.clone(),
        method: SPLIT_CONFORMAL_PEAK.into(),
        statistic: spec.statistic,
        alpha: spec.alpha,
        threshold,
        version: pool.version,
        seed: spec.seed,
        calibration_episodes,
    };
    // Every consumer reads the threshold back from the record's JSON: evaluate with what they read.
    let json = serde_json::to_vec(&record).map_err(|e| MonitorError::Invalid(e.to_string()))?;
    let record = MonitorRecord::from_json(&json)?;
    let (evaluation, traces) =
        measure(store, verifier, &record, held_out, &pool.failures, &pool.onsets, pool.version).await?;
    Ok(Calibration { record, evaluation, traces })
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
