//! The demo's result table: success rate with its Wilson 95% interval, and the difference to the
//! base policy with Newcombe's (method 10) 95% interval, as Markdown and JSON.

use anyhow::Result;
use evalstats::{newcombe_diff, wilson};
use serde::Serialize;
use std::path::Path;

#[derive(Debug, Clone, Serialize)]
pub struct Row {
    pub method: String,
    pub verifier: String,
    /// Where the row's rollouts are in the store: their checkpoint of `nav-dp` and run name
    /// (`ufops scoreboard --policy nav-dp` gives the row back).
    pub checkpoint: String,
    pub run: String,
    pub successes: u64,
    pub episodes: u64,
    pub rate: f64,
    pub wilson_95: (f64, f64),
    /// Difference to the base policy and its Newcombe 95% interval (None for the base row).
    pub diff_to_base: Option<f64>,
    pub newcombe_95: Option<(f64, f64)>,
}

#[derive(Debug, Clone, Serialize)]
pub struct Report {
    pub rows: Vec<Row>,
    /// What each steered run did (guidance per denoising step, speed, gaps, outcomes).
    pub diagnostics: Vec<crate::diagnose::RunDiagnostics>,
    pub seconds: f64,
    pub meta: serde_json::Value,
    /// The failure alarm calibrated from the main classifier (`ufops monitor`).
    pub monitor: Option<MonitorSummary>,
    /// Each best-of-N row's verifier figures next to the gain its steering achieved.
    pub steering_quality: Option<SteeringQuality>,
    /// Counterfactual replays of the logged best-of-N steps (`ufops replay`).
    pub replays: Vec<ReplayRow>,
    /// One verifier against an ensemble of K on the same rows (`--ensemble K`).
    pub ensembles: Option<Ensembles>,
}

/// The ensemble rows of the demo and the one-verifier rows they are set against.
#[derive(Debug, Clone, Serialize)]
pub struct Ensembles {
    pub members: usize,
    /// Each ensemble artifact's id and its held-out figures (`metrics.ensemble`).
    pub artifacts: Vec<(String, serde_json::Value)>,
    pub rows: Vec<EnsembleRow>,
}

/// One setting (a method on a split) steered by one verifier and by an ensemble.
#[derive(Debug, Clone, Serialize)]
pub struct EnsembleRow {
    pub method: String,
    pub split: String,
    pub single: Row,
    pub ensemble: Row,
    /// Best-of-N only: re-planning steps at which the members disagreed, so the policy's own
    /// first candidate ran, out of all re-planning steps.
    pub fell_back: Option<(u64, u64)>,
}

impl EnsembleRow {
    /// The rows of runs `single_run` and `run` of the base checkpoint, already in `report`.
    pub fn new(
        report: &Report,
        method: &str,
        split: &str,
        single_run: &str,
        run: &str,
        fell_back: Option<(u64, u64)>,
    ) -> Result<Self> {
        let find = |name: &str| {
            report
                .rows
                .iter()
                .find(|r| r.checkpoint == crate::BASE && r.run == name)
                .cloned()
                .ok_or_else(|| anyhow::anyhow!("the report has no row for run {name}"))
        };
        Ok(EnsembleRow {
            method: method.into(),
            split: split.into(),
            single: find(single_run)?,
            ensemble: find(run)?,
            fell_back,
        })
    }
}

impl Ensembles {
    pub fn markdown(&self) -> String {
        let pct = |x: f64| format!("{:.1}", 100.0 * x);
        let cell = |r: &Row| {
            format!(
                "{}/{} = {}% | {} {}",
                r.successes,
                r.episodes,
                pct(r.rate),
                r.diff_to_base.map(|d| format!("{:+.1} pp", 100.0 * d)).unwrap_or_default(),
                r.newcombe_95
                    .map(|(lo, hi)| format!("[{:+.1}, {:+.1}]", 100.0 * lo, 100.0 * hi))
                    .unwrap_or_default()
            )
        };
        let mut s = format!(
            "| method | verifier trained on | one verifier: success | Δ to base [Newcombe 95%] | ensemble of {}: success | Δ to base [Newcombe 95%] | fell back |\n|---|---|---|---|---|---|---|\n",
            self.members
        );
        for r in &self.rows {
            let fb = r
                .fell_back
                .map_or("-".into(), |(f, n)| format!("{f}/{n} = {:.1}%", 100.0 * f as f64 / n.max(1) as f64));
            s.push_str(&format!(
                "| {} | {} | {} | {} | {} |\n",
                r.method,
                r.split,
                cell(&r.single),
                cell(&r.ensemble),
                fb
            ));
        }
        s
    }
}

/// One replay of a run's logged best-of-N steps, and the question it answers.
#[derive(Debug, Clone, Serialize)]
pub struct ReplayRow {
    pub question: String,
    pub run: String,
    pub report: replay::ReplayReport,
}

/// The replays as a Markdown table.
pub fn replays_markdown(rows: &[ReplayRow]) -> String {
    let mut s = String::from(
        "| question | run | replayed with | N | steps | choice changed (Wilson 95%) | mean margin | logged pick over a random candidate | max score difference |\n\
         |---|---|---|---|---|---|---|---|---|\n",
    );
    for r in rows {
        let p = &r.report;
        s.push_str(&format!(
            "| {} | {} | {} | {} | {} | {}/{} = {:.1}% [{:.1}, {:.1}] | {:.4} | {:+.4} | {} |\n",
            r.question,
            r.run,
            p.artifact_id,
            p.replay_n.map_or_else(
                || p.logged_n.iter().map(usize::to_string).collect::<Vec<_>>().join(","),
                |k| k.to_string()
            ),
            p.steps,
            p.changed,
            p.steps,
            100.0 * p.changed_fraction,
            100.0 * p.changed_interval.0,
            100.0 * p.changed_interval.1,
            p.mean_margin,
            p.mean_lift_over_random,
            p.max_score_difference.map_or("-".into(), |d| format!("{d:e}")),
        ));
    }
    s
}

/// A best-of-N row of the base policy: its verifier's held-out figures and what steering with it
/// gained over the base policy.
#[derive(Debug, Clone, Serialize)]
pub struct SteeringQualityRow {
    pub run: String,
    pub n: u32,
    pub artifact_id: String,
    pub kind: String,
    /// Episodes the verifier trained on (its split's train part).
    pub train_episodes: Option<u64>,
    /// Success rate minus the base policy's.
    pub gain: f64,
    /// Held-out AUROC over every (obs, chunk, t) sample.
    pub auroc: Option<f64>,
    /// The action-sensitivity figure: the AUROC of the verifier's excess over its
    /// observation-only twin, among held-out samples the twin scores alike.
    pub action_auroc: Option<f64>,
    pub obs_only_auroc: Option<f64>,
    pub flagged: bool,
}

/// Does a verifier figure predict what best-of-N gains? Spearman's rank correlation of each
/// figure with the gain, over the rows.
#[derive(Debug, Clone, Serialize)]
pub struct SteeringQuality {
    pub rows: Vec<SteeringQualityRow>,
    pub spearman_auroc: Option<f64>,
    pub spearman_action_auroc: Option<f64>,
}

impl SteeringQuality {
    /// From the report's rows and the best-of-N runs' `(run, n, artifact)` (rows of other
    /// checkpoints than the base are left out: their gain is another policy's).
    pub fn new(rows: &[Row], runs: &[(String, u32, store_artifacts::ArtifactRecord)]) -> Self {
        let rows: Vec<SteeringQualityRow> = runs
            .iter()
            .filter_map(|(run, n, a)| {
                let row = rows.iter().find(|r| r.checkpoint == crate::BASE && &r.run == run)?;
                let m = &a.config["metrics"];
                let s = steer::verifier::ActionSensitivity::from_metrics(m);
                Some(SteeringQualityRow {
                    run: run.clone(),
                    n: *n,
                    artifact_id: a.id.clone(),
                    kind: a.kind.clone(),
                    train_episodes: a.config["lineage"]["train_episodes"].as_u64(),
                    gain: row.diff_to_base?,
                    auroc: m["final"]["val_auc"].as_f64(),
                    action_auroc: s.as_ref().and_then(|s| s.action_auc),
                    obs_only_auroc: s.as_ref().and_then(|s| s.obs_only_auc),
                    flagged: s.is_some_and(|s| s.flagged),
                })
            })
            .collect();
        let gains: Vec<f64> = rows.iter().map(|r| r.gain).collect();
        let figure = |f: fn(&SteeringQualityRow) -> Option<f64>| -> Option<f64> {
            let x: Option<Vec<f64>> = rows.iter().map(f).collect();
            evalstats::spearman(&x?, &gains)
        };
        SteeringQuality {
            spearman_auroc: figure(|r| r.auroc),
            spearman_action_auroc: figure(|r| r.action_auroc),
            rows,
        }
    }

    pub fn markdown(&self) -> String {
        let n = |x: Option<f64>| x.map_or("-".into(), |v| format!("{v:.3}"));
        let mut s = String::from(
            "| run | N | verifier | trained on | Δ to base | held-out AUROC | action AUROC | obs-only twin AUROC | flagged |\n\
             |---|---|---|---|---|---|---|---|---|\n",
        );
        for r in &self.rows {
            s.push_str(&format!(
                "| {} | {} | {} {} | {} | {:+.1} pp | {} | {} | {} | {} |\n",
                r.run,
                r.n,
                r.kind,
                r.artifact_id,
                r.train_episodes.map_or("-".into(), |e| e.to_string()),
                100.0 * r.gain,
                n(r.auroc),
                n(r.action_auroc),
                n(r.obs_only_auroc),
                if r.flagged { "yes" } else { "" },
            ));
        }
        s.push_str(&format!(
            "\nRank correlation with the gain over these {} rows (Spearman): held-out AUROC {}, action AUROC {}.\n",
            self.rows.len(),
            n(self.spearman_auroc),
            n(self.spearman_action_auroc)
        ));
        s
    }
}

/// The demo's failure monitor: its record's headline and what it measured on held-out episodes.
#[derive(Debug, Clone, Serialize)]
pub struct MonitorSummary {
    pub id: String,
    pub artifact_id: String,
    pub alpha: f64,
    pub threshold: f64,
    pub calibration_episodes: usize,
    pub evaluation: monitor::Evaluation,
}

impl Report {
    pub fn new(base: &[sim::Episode]) -> Self {
        let (k, n, rate) = sim::success_rate(base);
        let row = Row {
            method: "base (DDPM)".into(),
            verifier: "-".into(),
            checkpoint: crate::BASE.into(),
            run: crate::BASE.into(),
            successes: k,
            episodes: n,
            rate,
            wilson_95: wilson(k, n),
            diff_to_base: None,
            newcombe_95: None,
        };
        Report {
            rows: vec![row],
            diagnostics: vec![],
            seconds: 0.0,
            meta: serde_json::Value::Null,
            monitor: None,
            steering_quality: None,
            replays: Vec::new(),
            ensembles: None,
        }
    }

    pub fn add(&mut self, method: &str, verifier: &str, checkpoint: &str, run: &str, eps: &[sim::Episode]) {
        let base = &self.rows[0];
        let (k, n, rate) = sim::success_rate(eps);
        let row = Row {
            method: method.into(),
            verifier: verifier.into(),
            checkpoint: checkpoint.into(),
            run: run.into(),
            successes: k,
            episodes: n,
            rate,
            wilson_95: wilson(k, n),
            diff_to_base: Some(rate - base.rate),
            newcombe_95: Some(newcombe_diff(k, n, base.successes, base.episodes)),
        };
        self.rows.push(row);
    }

    /// Checks every row against the store's scoreboard of the demo's policy (baseline: the base
    /// run of the base checkpoint): same counts, rate, Wilson and Newcombe intervals.
    pub fn check_against(&self, sb: &store_compare::Scoreboard) -> Result<()> {
        for r in &self.rows {
            let s = sb.rows.iter().find(|s| s.checkpoint == r.checkpoint && s.run_name == r.run).ok_or_else(
                || anyhow::anyhow!("the store has no scoreboard row for {}/{}", r.checkpoint, r.run),
            )?;
            let same = s.successes == r.successes
                && s.successes + s.failures == r.episodes
                && s.rate == Some(r.rate)
                && s.wilson_95 == r.wilson_95
                && s.baseline.as_ref().map(|b| b.newcombe_95) == r.newcombe_95;
            anyhow::ensure!(
                same,
                "the store's scoreboard disagrees with the report on {} / {}: {s:?}",
                r.method,
                r.verifier
            );
        }
        Ok(())
    }

    pub fn row(&self, method: &str, verifier_prefix: &str) -> Option<&Row> {
        self.rows.iter().find(|r| r.method == method && r.verifier.starts_with(verifier_prefix))
    }

    pub fn markdown(&self) -> String {
        let pct = |x: f64| format!("{:.1}", 100.0 * x);
        let mut s = String::from(
            "| method | verifier | success | 95% CI (Wilson) | Δ to base | 95% CI of Δ (Newcombe) |\n|---|---|---|---|---|---|\n",
        );
        for r in &self.rows {
            s.push_str(&format!(
                "| {} | {} | {}/{} = {}% | [{}, {}] | {} | {} |\n",
                r.method,
                r.verifier,
                r.successes,
                r.episodes,
                pct(r.rate),
                pct(r.wilson_95.0),
                pct(r.wilson_95.1),
                r.diff_to_base.map(|d| format!("{:+.1} pp", 100.0 * d)).unwrap_or_else(|| "-".into()),
                r.newcombe_95
                    .map(|(lo, hi)| format!("[{:+.1}, {:+.1}]", 100.0 * lo, 100.0 * hi))
                    .unwrap_or_else(|| "-".into()),
            ));
        }
        s
    }

    /// The failure alarm's figures in one paragraph (empty without a monitor).
    pub fn monitor_markdown(&self) -> String {
        let Some(m) = &self.monitor else { return String::new() };
        let e = &m.evaluation;
        let pct = |x: Option<f64>| x.map_or("-".into(), |x| format!("{:.1}%", 100.0 * x));
        format!(
            "Failure alarm (monitor {}, classifier {}, alpha {}): threshold {:.4} calibrated on {} successes; \
             false alarms on {} held-out successes {} (Wilson 95% [{:.1}, {:.1}]%); failures caught {}/{} = {} \
             ({} before their end), median lead {} steps.\n",
            m.id,
            m.artifact_id,
            m.alpha,
            m.threshold,
            m.calibration_episodes,
            e.successes,
            pct(e.false_alarm_rate),
            100.0 * e.false_alarm_interval.0,
            100.0 * e.false_alarm_interval.1,
            e.detected,
            e.failures,
            pct(e.detection_rate),
            e.detected_before_onset,
            e.lead_steps_median.map_or("-".into(), |l| format!("{l:.0}")),
        )
    }

    pub fn write(&self, dir: &Path) -> Result<()> {
        let md = format!(
            "# ufops demo: two-gap navigation\n\n{}\nEvery row's rollouts are in the store as a run (`checkpoint`/`run` in `report.json`): \
             `ufops scoreboard --policy nav-dp --baseline-checkpoint base` gives this table back.\n\n{}\n\
             ## Which verifier steers well\n\nThe held-out AUROC over every (obs, chunk, t) sample next to the \
             action AUROC (the AUROC of the verifier's score in excess of its observation-only twin's, among held-out \
             samples the twin scores alike), \
             for every best-of-N row of the base policy.\n\n{}\n\
             ## Replaying the logged steps\n\nEvery best-of-N step of the C, Q and off-policy rows logged its \
             candidates, scores and choice with the episode. `ufops replay` re-scores them without the robot: the \
             margin is the replaying verifier's score of its own pick minus its score of the logged pick; the logged \
             pick over a random candidate is the logging verifier's score of its choice minus its mean score of the \
             step's candidates.\n\n{}\n\
             {}## What steering did\n\n{}\nTotal runtime: {:.0} s. Figure: `trajectories.png` (success green, failure red).\n",
            self.markdown(),
            self.monitor_markdown(),
            self.steering_quality.as_ref().map(SteeringQuality::markdown).unwrap_or_default(),
            replays_markdown(&self.replays),
            self.ensembles.as_ref().map_or(String::new(), |e| format!(
                "## Ensembles\n\nThe same rows steered by one verifier and by an ensemble of {} (seeds seed+k, bootstrap \
                 resamples of the split's training episodes; best-of-N ranks by mean − κ·spread and keeps the policy's own \
                 first candidate when fewer than 80% of the members prefer the pick; guidance is scaled by the members' \
                 gradient agreement).\n\n{}\n",
                e.members,
                e.markdown()
            )),
            crate::diagnose::markdown(&self.diagnostics),
            self.seconds
        );
        std::fs::write(dir.join("report.md"), md)?;
        std::fs::write(dir.join("report.json"), serde_json::to_vec_pretty(self)?)?;
        Ok(())
    }
}
