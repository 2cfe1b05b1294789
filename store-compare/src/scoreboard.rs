//! The evaluation scoreboard: success per policy × checkpoint × task × run at a version, with
//! Wilson 95% intervals, and each row against a baseline row: Newcombe's (method 10) interval of
//! the difference, the rollouts per arm that would separate the two at the observed rates, and how
//! many unlabeled episodes could change that answer. Each version freezes its counts per policy,
//! checkpoint, task, run and label when it is written (`version_run_counts`, spans of versions
//! moved on by the groups the version changes), so the scoreboard reads a few rows whatever the
//! number of episodes; [`Store::recount_scoreboard`] computes the same counts with a `GROUP BY`
//! over the version's frozen labels (the reference the tests hold it to). The arithmetic is
//! `evalstats`'.

use evalstats::{newcombe_diff, rollouts_to_separate, separates, unlabeled_to_flip, wilson, Arm};
use serde::Serialize;
use std::collections::BTreeMap;
use std::future::Future;
use store::sql::covers;
use store::sql::{bind_val, RowExt, Val};
use store::{sql::run_from_row, RunRecord};
use store::{Label, Store, StoreError};
use store_artifacts::{Artifacts, Monitors};

/// The run name the rows of episodes ingested without a run go by.
pub const NO_RUN: &str = "-";

/// What to tabulate.
#[derive(Debug, Clone, Default)]
pub struct ScoreboardRequest {
    pub policy: String,
    /// The version whose frozen labels count (default: the head).
    pub version: Option<i64>,
    pub checkpoint: Option<String>,
    pub task: Option<String>,
    /// The baseline's run name (default `base`; `-` for episodes without a run).
    pub baseline: Option<String>,
    /// The baseline's checkpoint; by default every row is compared with the baseline run of its
    /// own checkpoint (and task).
    pub baseline_checkpoint: Option<String>,
}

/// A row's comparison with its baseline row.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct BaselineComparison {
    pub checkpoint: String,
    pub run_name: String,
    pub run_id: Option<String>,
    /// This row's rate minus the baseline's, and its Newcombe (method 10) 95% interval.
    pub diff: f64,
    /// `[low, high]`.
    #[cfg_attr(feature = "openapi", schema(value_type = Vec<f64>))]
    pub newcombe_95: (f64, f64),
    /// Whether that interval excludes 0.
    pub separates: bool,
    /// Rollouts per arm for the interval to exclude 0 if both kept their observed rates (none
    /// when the rates are equal).
    pub rollouts_to_separate: Option<u64>,
    /// The fewest unlabeled episodes of the two rows whose labels could change `separates`
    /// (none: no labeling of them can).
    pub unlabeled_to_flip: Option<u64>,
}

#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct ScoreboardRow {
    pub policy: String,
    pub checkpoint: String,
    pub task: Option<String>,
    /// The run's name (`-` for episodes ingested without one) and its record.
    pub run_name: String,
    pub run: Option<RunRecord>,
    pub episodes: u64,
    pub successes: u64,
    pub failures: u64,
    pub unlabeled: u64,
    /// successes / (successes + failures); none when nothing is labeled.
    pub rate: Option<f64>,
    /// Wilson 95% interval of the rate over the labeled episodes ((0, 1) when none).
    #[cfg_attr(feature = "openapi", schema(value_type = Vec<f64>))]
    pub wilson_95: (f64, f64),
    pub is_baseline: bool,
    pub baseline: Option<BaselineComparison>,
    /// The quality of the run's verifier on its split's held-out episodes, from the artifact's
    /// training metrics: `{artifact_id, kind, auroc, accuracy, brier, ece, reliability, val_samples}`
    /// (calibration for classifiers only), how much the action chunk earns of that AUROC
    /// (`obs_only_auroc`, `action_auroc`, `auroc_gain`, `steering_flagged`, `steering_warning`:
    /// the trainer's observation-only twin, null for artifacts trained without it), and its
    /// latest failure monitor's held-out figures
    /// (`monitor`: `{id, alpha, false_alarm_rate, false_alarm_interval, successes, detection_rate,
    /// failures, lead_steps_median}`, null when it has none).
    pub verifier_quality: Option<serde_json::Value>,
}

impl ScoreboardRow {
    fn arm(&self) -> Arm {
        Arm { successes: self.successes, failures: self.failures, unlabeled: self.unlabeled }
    }
}

#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Scoreboard {
    pub version: i64,
    pub policy: String,
    pub baseline: String,
    pub baseline_checkpoint: Option<String>,
    pub rows: Vec<ScoreboardRow>,
}

impl Scoreboard {
    /// The rows as CSV (one header line; intervals as `_lo`/`_hi` columns; empty cells for none).
    pub fn to_csv(&self) -> String {
        let mut s = String::from(
            "version,policy,checkpoint,task,run,steering,artifact_id,run_tags,episodes,successes,failures,unlabeled,\
             rate,wilson_lo,wilson_hi,baseline_checkpoint,baseline_run,diff,newcombe_lo,newcombe_hi,separates,\
             rollouts_to_separate,unlabeled_to_flip,verifier_auroc,verifier_ece,verifier_action_auroc,\
             verifier_obs_only_auroc,verifier_steering_flagged\n",
        );
        let q = |x: &str| {
            if x.contains([',', '"', '\n', '\r']) {
                format!("\"{}\"", x.replace('"', "\"\""))
            } else {
                x.to_string()
            }
        };
        let f = |x: f64| format!("{x}");
        let vq = |r: &ScoreboardRow, k: &str| {
            r.verifier_quality
                .as_ref()
                .and_then(|v| v[k].as_f64())
                .map(|x| format!("{x}"))
                .unwrap_or_default()
        };
        for r in &self.rows {
            let run = r.run.as_ref();
            let b = r.baseline.as_ref();
            let cells: Vec<String> = vec![
                self.version.to_string(),
                q(&r.policy),
                q(&r.checkpoint),
                q(r.task.as_deref().unwrap_or("")),
                q(&r.run_name),
                run.map(|x| x.steering.to_string()).unwrap_or_default(),
                q(run.and_then(|x| x.artifact_id.as_deref()).unwrap_or("")),
                q(&run.map(|x| x.tags.join(";")).unwrap_or_default()),
                r.episodes.to_string(),
                r.successes.to_string(),
                r.failures.to_string(),
                r.unlabeled.to_string(),
                r.rate.map(f).unwrap_or_default(),
                f(r.wilson_95.0),
                f(r.wilson_95.1),
                q(b.map(|b| b.checkpoint.as_str()).unwrap_or("")),
                q(b.map(|b| b.run_name.as_str()).unwrap_or("")),
                b.map(|b| f(b.diff)).unwrap_or_default(),
                b.map(|b| f(b.newcombe_95.0)).unwrap_or_default(),
                b.map(|b| f(b.newcombe_95.1)).unwrap_or_default(),
                b.map(|b| b.separates.to_string()).unwrap_or_default(),
                b.and_then(|b| b.rollouts_to_separate).map(|n| n.to_string()).unwrap_or_default(),
                b.and_then(|b| b.unlabeled_to_flip).map(|n| n.to_string()).unwrap_or_default(),
                vq(r, "auroc"),
                vq(r, "ece"),
                vq(r, "action_auroc"),
                vq(r, "obs_only_auroc"),
                r.verifier_quality
                    .as_ref()
                    .and_then(|v| v["steering_flagged"].as_bool())
                    .map(|b| b.to_string())
                    .unwrap_or_default(),
            ];
            s.push_str(&cells.join(","));
            s.push('\n');
        }
        s
    }
}

/// What the scoreboard shows of an artifact's training metrics (`config.metrics.final`).
fn verifier_quality(a: &store_artifacts::ArtifactRecord) -> serde_json::Value {
    let m = &a.config["metrics"]["final"];
    let c = &m["val_calibration"];
    serde_json::json!({
        "artifact_id": a.id,
        "kind": a.kind,
        "auroc": m["val_auc"],
        "accuracy": c["accuracy"],
        "brier": c["brier"],
        "ece": c["ece"],
        "reliability": c["bins"],
        "val_samples": m["val_samples"],
        // How much the chunk matters (the trainer's observation-only twin); absent for older
        // artifacts.
        "obs_only_auroc": m["action_sensitivity"]["obs_only_auc"],
        "action_auroc": m["action_sensitivity"]["action_auc"],
        "auroc_gain": m["action_sensitivity"]["auc_gain"],
        "steering_flagged": m["action_sensitivity"]["flagged"],
        "steering_warning": m["action_sensitivity"]["reason"],
    })
}

/// What the scoreboard shows of the artifact's latest failure monitor: its α and what its
/// calibration measured on held-out episodes.
fn monitor_summary(m: &store_artifacts::MonitorEntry) -> serde_json::Value {
    let e = m.evaluation.clone().unwrap_or(serde_json::Value::Null);
    serde_json::json!({
        "id": m.id,
        "alpha": m.alpha,
        "false_alarm_rate": e["false_alarm_rate"],
        "false_alarm_interval": e["false_alarm_interval"],
        "successes": e["successes"],
        "detection_rate": e["detection_rate"],
        "failures": e["failures"],
        "lead_steps_median": e["lead_steps_median"],
    })
}

/// Counts per (checkpoint, task, run id) of one policy: [successes, failures, unlabeled].
type Cells = BTreeMap<(String, Option<String>, Option<String>), [u64; 3]>;

fn add_cell(
    cells: &mut Cells,
    checkpoint: String,
    task: Option<String>,
    run: Option<String>,
    label: Label,
    n: i64,
) {
    let c = cells.entry((checkpoint, task, run)).or_default();
    let n = u64::try_from(n).unwrap_or(0);
    match label {
        Label::Success => c[0] += n,
        Label::Failure => c[1] += n,
        Label::Unknown => c[2] += n,
    }
}

/// The scoreboard of a policy on a [`Store`]: success counts per checkpoint and run, with
/// their intervals and verifier quality.
pub trait Scoreboards {
    /// The scoreboard's counts computed from the version's labels (O(episodes)): the reference
    /// the frozen counts are checked against (tests, the scoreboard bench). Rows of
    /// `(checkpoint, task, run id, [successes, failures, unlabeled])`.
    #[allow(clippy::type_complexity)]
    fn recount_scoreboard(
        &self,
        req: &ScoreboardRequest,
        version: i64,
    ) -> impl Future<Output = Result<Vec<(String, Option<String>, Option<String>, [u64; 3])>, StoreError>> + Send;

    /// The frozen counts in the same shape as [`Self::recount_scoreboard`].
    #[allow(clippy::type_complexity)]
    fn scoreboard_counts(
        &self,
        req: &ScoreboardRequest,
        version: i64,
    ) -> impl Future<Output = Result<Vec<(String, Option<String>, Option<String>, [u64; 3])>, StoreError>> + Send;

    /// The scoreboard of a policy at a version (see the module docs).
    fn scoreboard(
        &self,
        req: &ScoreboardRequest,
    ) -> impl Future<Output = Result<Scoreboard, StoreError>> + Send;
}

impl Scoreboards for Store {
    #[allow(clippy::type_complexity)]
    async fn recount_scoreboard(
        &self,
        req: &ScoreboardRequest,
        version: i64,
    ) -> Result<Vec<(String, Option<String>, Option<String>, [u64; 3])>, StoreError> {
        self.version(version).await?;
        let cells = scoreboard_cells(self, req, version, true).await?;
        Ok(cells.into_iter().map(|((c, t, r), n)| (c, t, r, n)).collect())
    }

    #[allow(clippy::type_complexity)]
    async fn scoreboard_counts(
        &self,
        req: &ScoreboardRequest,
        version: i64,
    ) -> Result<Vec<(String, Option<String>, Option<String>, [u64; 3])>, StoreError> {
        self.version(version).await?;
        let cells = scoreboard_cells(self, req, version, false).await?;
        Ok(cells.into_iter().map(|((c, t, r), n)| (c, t, r, n)).collect())
    }

    async fn scoreboard(&self, req: &ScoreboardRequest) -> Result<Scoreboard, StoreError> {
        store::model::check_name("policy", &req.policy)?;
        let version = match req.version {
            Some(v) => {
                self.version(v).await?;
                v
            }
            None => self.head_version().await?,
        };
        let baseline = req.baseline.clone().unwrap_or_else(|| "base".to_string());
        // A baseline of another checkpoint than the one asked for: count both, show the asked one
        // and the baseline's row.
        let other_baseline = match (&req.checkpoint, &req.baseline_checkpoint) {
            (Some(c), Some(b)) if c != b => Some(c.clone()),
            _ => None,
        };
        let cells = match &other_baseline {
            Some(_) => {
                scoreboard_cells(self, &ScoreboardRequest { checkpoint: None, ..req.clone() }, version, false)
                    .await?
            }
            None => scoreboard_cells(self, req, version, false).await?,
        };
        let runs = scoreboard_runs(self, &cells).await?;
        let mut rows = scoreboard_rows(req, &baseline, cells, &runs);
        compare_with_baselines(&mut rows, req.baseline_checkpoint.as_ref());
        if let Some(c) = &other_baseline {
            rows.retain(|r| &r.checkpoint == c || r.is_baseline);
        }
        attach_verifier_quality(self, &mut rows).await?;
        Ok(Scoreboard {
            version,
            policy: req.policy.clone(),
            baseline,
            baseline_checkpoint: req.baseline_checkpoint.clone(),
            rows,
        })
    }
}

/// The counts per (checkpoint, task, run) of `req.policy` at `version`: from the frozen
/// `version_run_counts`, or (`recount`) with a `GROUP BY` over the version's labels.
async fn scoreboard_cells(
    store: &Store,
    req: &ScoreboardRequest,
    version: i64,
    recount: bool,
) -> Result<Cells, StoreError> {
    let mut args = vec![Val::I(version), Val::S(req.policy.clone())];
    let (mut sql, col) = if recount {
        (
            format!(
                "SELECT e.checkpoint AS checkpoint, COALESCE(e.task, '') AS task, COALESCE(e.run_id, '') AS run_id, \
                 l.label AS label, COUNT(*) AS n FROM version_labels l JOIN episodes e ON e.id = l.episode_id \
                 WHERE {} AND e.policy = $2",
                covers("l", "$1")
            ),
            "e.",
        )
    } else {
        (
            format!(
                "SELECT checkpoint, task, run_id, label, n FROM version_run_counts WHERE {} AND policy = $2",
                covers("", "$1")
            ),
            "",
        )
    };
    for (name, v) in [("checkpoint", &req.checkpoint), ("task", &req.task)] {
        if let Some(v) = v {
            args.push(Val::S(v.clone()));
            sql.push_str(&format!(" AND {col}{name} = ${}", args.len()));
        }
    }
    if recount {
        sql.push_str(" GROUP BY e.checkpoint, COALESCE(e.task, ''), COALESCE(e.run_id, ''), l.label");
    }
    let mut q = sqlx::query(&sql);
    for a in args {
        q = bind_val(q, a);
    }
    let mut cells = Cells::new();
    let some = |s: String| if s.is_empty() { None } else { Some(s) };
    for r in q.fetch_all(&store.catalog().pool).await? {
        add_cell(
            &mut cells,
            r.s("checkpoint")?,
            some(r.s("task")?),
            some(r.s("run_id")?),
            r.s("label")?.parse()?,
            r.i("n")?,
        );
    }
    Ok(cells)
}

/// The runs named by the cells (a few dozen at most), by id.
async fn scoreboard_runs(store: &Store, cells: &Cells) -> Result<BTreeMap<String, RunRecord>, StoreError> {
    let ids: std::collections::BTreeSet<String> = cells.keys().filter_map(|k| k.2.clone()).collect();
    let mut runs: BTreeMap<String, RunRecord> = BTreeMap::new();
    for id in ids {
        let row =
            sqlx::query("SELECT id, name, steering, artifact_id, tags, created_at FROM runs WHERE id = $1")
                .bind(&id)
                .fetch_one(&store.catalog().pool)
                .await?;
        runs.insert(id, run_from_row(&row)?);
    }
    Ok(runs)
}

/// Sets each row's verifier quality from its run's artifact, reading each artifact once
/// (none when the artifact is gone).
async fn attach_verifier_quality(store: &Store, rows: &mut [ScoreboardRow]) -> Result<(), StoreError> {
    let mut quality: BTreeMap<String, Option<serde_json::Value>> = BTreeMap::new();
    for r in rows.iter_mut() {
        let Some(id) = r.run.as_ref().and_then(|x| x.artifact_id.clone()) else { continue };
        if !quality.contains_key(&id) {
            let q = match store.artifact(&id).await {
                Ok(a) => {
                    let mut q = verifier_quality(&a);
                    q["monitor"] = store
                        .latest_monitor(&id)
                        .await?
                        .map_or(serde_json::Value::Null, |m| monitor_summary(&m));
                    Some(q)
                }
                Err(StoreError::NotFound { .. }) => None,
                Err(e) => return Err(e),
            };
            quality.insert(id.clone(), q);
        }
        r.verifier_quality = quality[&id].clone();
    }
    Ok(())
}

/// One row per cell with its rate and Wilson interval (compared with its baseline later), in
/// display order.
fn scoreboard_rows(
    req: &ScoreboardRequest,
    baseline: &str,
    cells: Cells,
    runs: &BTreeMap<String, RunRecord>,
) -> Vec<ScoreboardRow> {
    let mut rows: Vec<ScoreboardRow> = cells
        .into_iter()
        .map(|((checkpoint, task, run_id), [s, f, u])| {
            let run = run_id.and_then(|id| runs.get(&id).cloned());
            let run_name = run.as_ref().map_or(NO_RUN.to_string(), |r| r.name.clone());
            let labeled = s + f;
            ScoreboardRow {
                policy: req.policy.clone(),
                is_baseline: run_name == baseline
                    && req.baseline_checkpoint.as_ref().is_none_or(|c| *c == checkpoint),
                checkpoint,
                task,
                run_name,
                run,
                episodes: s + f + u,
                successes: s,
                failures: f,
                unlabeled: u,
                rate: (labeled > 0).then(|| s as f64 / labeled as f64),
                wilson_95: wilson(s, labeled),
                baseline: None,
                verifier_quality: None,
            }
        })
        .collect();
    // The baseline first within each checkpoint and task, then by run name. Checkpoints and runs
    // sort naturally, numbers by value: `e100, e600, e1000` and `bon4, bon8, bon16`.
    fn natural(a: &str, b: &str) -> std::cmp::Ordering {
        alphanumeric_sort::compare_str(a, b)
    }
    rows.sort_by(|a, b| {
        natural(&a.checkpoint, &b.checkpoint)
            .then_with(|| a.task.cmp(&b.task))
            .then_with(|| b.is_baseline.cmp(&a.is_baseline))
            .then_with(|| natural(&a.run_name, &b.run_name))
            .then_with(|| a.run.as_ref().map(|r| &r.id).cmp(&b.run.as_ref().map(|r| &r.id)))
    });
    rows
}

/// Compares each row with the one baseline row of its task and checkpoint (`baseline_checkpoint`
/// when given, else its own); none for the baseline itself or when several rows share the
/// baseline's name.
fn compare_with_baselines(rows: &mut [ScoreboardRow], baseline_checkpoint: Option<&String>) {
    let comparisons: Vec<Option<BaselineComparison>> = rows
        .iter()
        .map(|r| {
            let want_ckpt = baseline_checkpoint.unwrap_or(&r.checkpoint);
            let mut cands =
                rows.iter().filter(|b| b.is_baseline && b.task == r.task && &b.checkpoint == want_ckpt);
            let base = cands.next()?;
            if cands.next().is_some() || std::ptr::eq(base, r) {
                return None; // ambiguous (one name, several runs), or the baseline itself
            }
            let (a, b) = (r.arm(), base.arm());
            let ci = newcombe_diff(a.successes, a.labeled(), b.successes, b.labeled());
            Some(BaselineComparison {
                checkpoint: base.checkpoint.clone(),
                run_name: base.run_name.clone(),
                run_id: base.run.as_ref().map(|x| x.id.clone()),
                diff: r.rate.unwrap_or(0.0) - base.rate.unwrap_or(0.0),
                newcombe_95: ci,
                separates: separates(ci),
                rollouts_to_separate: match (r.rate, base.rate) {
                    (Some(p1), Some(p2)) => rollouts_to_separate(p1, p2),
                    _ => None,
                },
                unlabeled_to_flip: unlabeled_to_flip(&a, &b),
            })
        })
        .collect();
    for (r, c) in rows.iter_mut().zip(comparisons) {
        r.baseline = c;
    }
}
