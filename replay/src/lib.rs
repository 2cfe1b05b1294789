//! `replay`: counterfactual replay of steering telemetry.
//!
//! A steered rollout can keep, with its episode, every best-of-N step it took — the N candidate
//! chunks, their scores, the chosen index, the artifact (the steps' steering column,
//! `verifier::telemetry`). This crate re-scores those logged steps without running the robot: with
//! another verifier artifact ("would verifier v2 pick differently?") and/or only the first K of
//! the N candidates ("would N = 8 have sufficed?"), and reports how often the choice changes, the
//! score margin the replayed verifier sees between its own pick and the logged one, and — replayed
//! with the logging artifact and N — whether every logged choice and score is reproduced.
//!
//! It owns which episodes a run names, the replay of one episode's log ([`replay_log`]) and the
//! report. The observation a logged step is scored on is built from the stored steps by the
//! verifier core (`verifier::steps::step_inputs`, as for training and the review queue); the choice
//! is the robot's own (`steer::select_best`, or an ensemble's `Verifier::pick`); reading is the
//! store's selection path (`store::for_each_episode_with_layers`), and the error,
//! [`StoredEpisodesError`], is the one of every crate that works on stored episodes
//! (`verifier::stored`).

use std::collections::BTreeSet;

use arrow::array::RecordBatch;
use serde::Serialize;
use store::{EpisodeFilter, EpisodeRecord, Store};
use verifier::steps::{steering_log, step_inputs};
use verifier::stored::StoredEpisodesError;
use verifier::{SteeringStep, Verifier};

pub type Result<T, E = StoredEpisodesError> = std::result::Result<T, E>;

fn invalid(m: impl Into<String>) -> StoredEpisodesError {
    StoredEpisodesError::Invalid(m.into())
}

/// What to replay.
#[derive(Debug, Clone, Default)]
pub struct ReplaySpec {
    /// A run id, or a run name (every run of that name, narrowed by policy and checkpoint).
    pub run: String,
    pub policy: Option<String>,
    pub checkpoint: Option<String>,
    /// The store version to read (default: the current state).
    pub version: Option<i64>,
    /// Score only the first `n` candidates of each logged step (default: all of them).
    pub n: Option<usize>,
}

/// The replay of a run's logged steering steps with one artifact.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct ReplayReport {
    /// The runs replayed (ids).
    pub runs: Vec<String>,
    /// The artifact the steps were replayed with.
    pub artifact_id: String,
    /// The artifacts that scored the logged steps.
    pub logged_artifacts: Vec<String>,
    /// Episodes of the runs, and those among them with no telemetry (not replayed).
    pub episodes: usize,
    pub episodes_without_telemetry: usize,
    /// Logged best-of-N steps replayed.
    pub steps: u64,
    /// The logged N (distinct values) and the N replayed (`None`: each step's own N).
    pub logged_n: Vec<usize>,
    pub replay_n: Option<usize>,
    /// Steps whose replayed choice differs from the logged one, their share and its Wilson 95%
    /// interval.
    pub changed: u64,
    pub changed_fraction: f64,
    pub changed_interval: (f64, f64),
    /// The replaying artifact's score of its own pick minus its score of the logged pick, over
    /// all steps (0 where the choice is the same): positive when it prefers its pick, negative
    /// when fewer candidates left out one it scores higher. Mean and median.
    pub mean_margin: f64,
    pub median_margin: f64,
    /// The logging artifact's score of the logged pick minus its score of the replayed pick,
    /// over the changed steps only: what the logged verifier thought the change gives up.
    pub mean_logged_regret: Option<f64>,
    /// How much the logged choice stood out from a random pick of its step's candidates, by the
    /// logging verifier: the chosen score minus the mean score, averaged over steps; and the mean
    /// spread (highest minus lowest score) of a step's candidates.
    pub mean_lift_over_random: f64,
    pub mean_score_spread: f64,
    /// With the logging artifact and every candidate: the largest difference between a logged
    /// and a replayed score (0 when the replay reproduces the robot bit for bit); `None` otherwise.
    pub max_score_difference: Option<f64>,
}

/// The replay of one logged step.
#[derive(Debug, Clone, PartialEq)]
pub struct StepReplay {
    pub t: u32,
    /// The replaying artifact's scores of every logged candidate (all N, so the logged pick
    /// has one even when the choice is among the first `n` only).
    pub scores: Vec<f32>,
    /// The replayed choice: the best of the first `n` candidates.
    pub chosen: usize,
}

/// Re-scores one episode's logged steps (`log`, from its `steps`) with `verifier` and picks the
/// best of the first `n` candidates of each (all with `None`). The observation of step `t` is the verifier's input
/// built from the stored steps; the candidates are raw actions, put into the space the verifier
/// takes as the robot's best-of-N did.
pub fn replay_log(
    verifier: &Verifier,
    steps: &RecordBatch,
    log: &[SteeringStep],
    n: Option<usize>,
) -> Result<Vec<StepReplay>> {
    if log.is_empty() {
        return Ok(Vec::new());
    }
    let cfg = verifier.config();
    let samples = step_inputs(cfg, steps)?;
    let (od, ad) = (verifier.obs_dim(), verifier.act_dim());
    let action_dim = cfg.input.layout.action_dim;
    let mut row_of = vec![None; samples.t.iter().map(|&t| t as usize + 1).max().unwrap_or(0)];
    for (row, &t) in samples.t.iter().enumerate() {
        row_of[t as usize] = Some(row);
    }
    let mut out = Vec::with_capacity(log.len());
    for s in log {
        let k = n.unwrap_or(s.n()).min(s.n());
        if k == 0 {
            return Err(invalid("replaying with n = 0 candidates"));
        }
        if s.chunk_len() != ad {
            return Err(invalid(format!(
                "step t={} logged chunks of {} values; artifact {} takes {ad}",
                s.t,
                s.chunk_len(),
                verifier.id().unwrap_or("-")
            )));
        }
        let row =
            row_of.get(s.t as usize).copied().flatten().ok_or_else(|| {
                invalid(format!("step t={} has no verifier input in the stored steps", s.t))
            })?;
        let mut cands = s.candidates.clone();
        cfg.input.action_space.raw_to_input(&mut cands, action_dim);
        let obs = &samples.obs[row * od..(row + 1) * od];
        let scores = verifier.score(obs, &[samples.t[row]], &cands, s.n())?;
        // The robot's own rule over the first k: the argmax for one network, an ensemble's
        // pessimistic pick with its fall-back.
        let chosen = if verifier.members() > 1 {
            verifier.pick(obs, &[], &[samples.t[row]], &cands[..k * ad], k)?.index[0]
        } else {
            steer::select_best(&scores[..k])
        };
        out.push(StepReplay { t: s.t, scores, chosen });
    }
    Ok(out)
}

/// The run with id `run`, else every run named `run`; an error when there is none.
pub async fn runs_named(store: &Store, run: &str) -> Result<Vec<store::RunRecord>> {
    let runs = match store.run(run).await {
        Ok(r) => vec![r],
        Err(store::StoreError::NotFound { .. }) => store.runs(Some(run)).await?,
        Err(e) => return Err(e.into()),
    };
    if runs.is_empty() {
        return Err(invalid(format!("no run is named or has the id {run:?}")));
    }
    Ok(runs)
}

/// The episodes of the runs `spec` names (at its version), and the run ids.
pub async fn run_episodes(store: &Store, spec: &ReplaySpec) -> Result<(Vec<String>, Vec<EpisodeRecord>)> {
    let mut runs: Vec<String> = runs_named(store, &spec.run).await?.into_iter().map(|r| r.id).collect();
    runs.sort();
    let filter = EpisodeFilter {
        version: spec.version,
        policy: spec.policy.clone(),
        checkpoint: spec.checkpoint.clone(),
        run_ids: runs.clone(),
        ..Default::default()
    };
    let episodes = store.episodes(&filter).await?;
    let runs: Vec<String> = {
        let present: BTreeSet<&str> = episodes.iter().filter_map(|e| e.run_id.as_deref()).collect();
        runs.into_iter().filter(|r| present.contains(r.as_str())).collect()
    };
    if episodes.is_empty() {
        return Err(invalid(format!(
            "run {:?} has no episodes (with the policy and checkpoint given)",
            spec.run
        )));
    }
    Ok((runs, episodes))
}

/// Replays every logged step of the runs `spec` names with `verifier` (an artifact of the store,
/// `artifact_id`).
pub async fn replay(
    store: &Store,
    verifier: &Verifier,
    artifact_id: &str,
    spec: &ReplaySpec,
) -> Result<ReplayReport> {
    if spec.n == Some(0) {
        return Err(invalid("--n must be at least 1"));
    }
    let (runs, episodes) = run_episodes(store, spec).await?;
    let layers = verifier::StepScorer::layers(verifier);
    let mut acc = Accumulator::default();
    store::for_each_episode_with_layers(
        store,
        &episodes,
        &layers,
        spec.version,
        |_, e, steps| -> Result<()> {
            let log = steering_log(&steps).map_err(|m| invalid(format!("episode {}: {m}", e.id)))?;
            let replayed = replay_log(verifier, &steps, &log, spec.n)
                .map_err(|m| invalid(format!("episode {}: {m}", e.id)))?;
            acc.add(&log, &replayed, artifact_id, spec.n);
            Ok(())
        },
    )
    .await?;
    if acc.steps == 0 {
        return Err(invalid(format!(
            "run {:?} holds no steering telemetry ({} episodes, none logged its best-of-N steps)",
            spec.run,
            episodes.len()
        )));
    }
    Ok(acc.report(runs, artifact_id, episodes.len(), spec.n))
}

#[derive(Default)]
struct Accumulator {
    logged_artifacts: BTreeSet<String>,
    logged_n: BTreeSet<usize>,
    episodes_with: usize,
    steps: u64,
    changed: u64,
    margins: Vec<f64>,
    regrets: Vec<f64>,
    lift: f64,
    spread: f64,
    /// The largest difference between a logged and a replayed score…
    max_diff: f64,
    /// …which means nothing once a step was replayed with another artifact or fewer candidates.
    inexact: bool,
}

impl Accumulator {
    fn add(&mut self, log: &[SteeringStep], replayed: &[StepReplay], artifact_id: &str, n: Option<usize>) {
        if log.is_empty() {
            return;
        }
        self.episodes_with += 1;
        for (s, r) in log.iter().zip(replayed) {
            self.steps += 1;
            self.logged_artifacts.insert(s.artifact_id.clone());
            self.logged_n.insert(s.n());
            let logged = s.chosen as usize;
            if r.chosen != logged {
                self.changed += 1;
                self.regrets.push(f64::from(s.scores[logged]) - f64::from(s.scores[r.chosen]));
            }
            self.margins.push(f64::from(r.scores[r.chosen]) - f64::from(r.scores[logged]));
            let mean = s.scores.iter().map(|&x| f64::from(x)).sum::<f64>() / s.n() as f64;
            let (lo, hi) =
                s.scores.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(l, h), &x| (l.min(x), h.max(x)));
            self.lift += f64::from(s.scores[logged]) - mean;
            self.spread += f64::from(hi - lo);
            self.inexact |= s.artifact_id != artifact_id || n.is_some_and(|k| k < s.n());
            for (a, b) in s.scores.iter().zip(&r.scores) {
                self.max_diff = self.max_diff.max(f64::from((a - b).abs()));
            }
        }
    }

    fn report(
        mut self,
        runs: Vec<String>,
        artifact_id: &str,
        episodes: usize,
        n: Option<usize>,
    ) -> ReplayReport {
        let steps = self.steps;
        let median = |v: &mut Vec<f64>| {
            v.sort_by(f64::total_cmp);
            match v.len() {
                0 => 0.0,
                l if l % 2 == 1 => v[l / 2],
                l => 0.5 * (v[l / 2 - 1] + v[l / 2]),
            }
        };
        fn mean(v: &[f64]) -> Option<f64> {
            (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
        }
        ReplayReport {
            runs,
            artifact_id: artifact_id.to_string(),
            logged_artifacts: self.logged_artifacts.into_iter().collect(),
            episodes,
            episodes_without_telemetry: episodes - self.episodes_with,
            steps,
            logged_n: self.logged_n.into_iter().collect(),
            replay_n: n,
            changed: self.changed,
            changed_fraction: self.changed as f64 / steps as f64,
            changed_interval: evalstats::wilson(self.changed, steps),
            mean_margin: mean(&self.margins).unwrap_or(0.0),
            median_margin: median(&mut self.margins),
            mean_logged_regret: mean(&self.regrets),
            mean_lift_over_random: self.lift / steps as f64,
            mean_score_spread: self.spread / steps as f64,
            max_score_difference: (!self.inexact).then_some(self.max_diff),
        }
    }
}
