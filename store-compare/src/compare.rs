//! Is B better than A yet? The anytime-valid comparison of two arms of a policy's evaluation (a
//! checkpoint, or one run of it), per task and pooled, read from a version's labels. The
//! statistics are `evalstats::sequential`'s; this module chooses the rollouts, pairs them (by a
//! metadata key when the arms share initial conditions, else in arrival order), and reports.
//!
//! Arrival order is the order the store received the rollouts: by the version that added them,
//! then their index in their source. Outcomes are success labels (1/0; unlabeled episodes wait)
//! or, with `progress`, a score in [0, 1] from each episode's metadata (partial credit).

use crate::NO_RUN;
use evalstats::sequential::{compare_pairs, pair_by_key, Decision, Pair, PairedCounts, SequentialConfig};
use serde::{Deserialize, Serialize};
use std::future::Future;
use store::sql::covers;
use store::sql::{bind_val, RowExt, Val};
use store::{Label, Store, StoreError};

/// The metadata field rollouts are paired by unless the request names another.
pub const DEFAULT_PAIR_KEY: &str = "pair_key";

/// One arm: a checkpoint, and optionally one run of it (`CHECKPOINT/RUN`; `-` the episodes
/// ingested without a run). Without a run, every episode of the checkpoint.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ArmSpec {
    pub checkpoint: String,
    pub run: Option<String>,
}

impl std::str::FromStr for ArmSpec {
    type Err = StoreError;
    fn from_str(s: &str) -> Result<Self, StoreError> {
        let (checkpoint, run) = match s.split_once('/') {
            Some((c, r)) => (c, Some(r)),
            None => (s, None),
        };
        store::model::check_name("checkpoint", checkpoint)?;
        if let Some(r) = run {
            if r != NO_RUN {
                store::model::check_name("run", r)?;
            }
        }
        Ok(ArmSpec { checkpoint: checkpoint.to_string(), run: run.map(str::to_string) })
    }
}

impl std::fmt::Display for ArmSpec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match &self.run {
            Some(r) => write!(f, "{}/{r}", self.checkpoint),
            None => f.write_str(&self.checkpoint),
        }
    }
}

/// What to compare, and how.
#[derive(Debug, Clone)]
pub struct CompareRequest {
    pub policy: String,
    /// The baseline.
    pub a: ArmSpec,
    /// The candidate.
    pub b: ArmSpec,
    /// The version whose labels count (default: the head).
    pub version: Option<i64>,
    /// Only this task (default: every task, each a slice, and pooled).
    pub task: Option<String>,
    pub alpha: f64,
    pub margin: f64,
    pub plan_effect: Option<f64>,
    /// The metadata field that pairs rollouts across arms (`None`: [`DEFAULT_PAIR_KEY`]; an empty
    /// string: no pairing, arrival order). `source_index` and `source_name` pair by the episode's
    /// place in its source (two evaluations run over the same list of seeds: LeRobot's
    /// `episode_index`, robomimic's `demo_N`).
    pub pair_key: Option<String>,
    /// A metadata field with a progress score in [0, 1] to compare instead of success labels.
    pub progress: Option<String>,
}

impl CompareRequest {
    pub fn new(policy: &str, a: ArmSpec, b: ArmSpec) -> Self {
        CompareRequest {
            policy: policy.to_string(),
            a,
            b,
            version: None,
            task: None,
            alpha: 0.05,
            margin: 0.0,
            plan_effect: None,
            pair_key: None,
            progress: None,
        }
    }

    fn config(&self, alpha: f64) -> SequentialConfig {
        SequentialConfig { alpha, margin: self.margin, plan_effect: self.plan_effect }
    }
}

/// e-values of the four claims (Δ = rate of B − rate of A).
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct EValues {
    /// Δ > 0.
    pub better: f64,
    /// Δ < −margin.
    pub worse: f64,
    /// Δ > −margin.
    pub above_margin: f64,
    /// Δ < margin.
    pub below_margin: f64,
}

/// The paired 2×2 table of binary outcomes.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct PairTable {
    pub both: u64,
    pub only_a: u64,
    pub only_b: u64,
    pub neither: u64,
}

/// The comparison over one task's rollouts (or all of them, pooled).
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct ComparisonSlice {
    /// The task (none: pooled over tasks).
    pub task: Option<String>,
    /// The level this slice was tested at (α/K for K tasks, so all tasks' claims hold together).
    pub alpha: f64,
    /// `better`, `worse`, `no_practical_difference`, `not_worse` or `undecided`.
    pub decision: String,
    /// The pairs after which the decision was first reached (the rollouts it needed: twice that).
    pub decided_at_pairs: Option<u64>,
    /// Pairs compared.
    pub pairs: u64,
    /// Rollouts of A and of B without a partner (not compared).
    pub unpaired_a: u64,
    pub unpaired_b: u64,
    /// Rollouts of A and of B without an outcome yet (unlabeled, or no progress score).
    pub pending_a: u64,
    pub pending_b: u64,
    /// Mean outcome of A and of B over the pairs, and B − A.
    pub rate_a: f64,
    pub rate_b: f64,
    pub diff: f64,
    /// The (1 − alpha) anytime-valid confidence sequence of the difference, `[low, high]`.
    #[cfg_attr(feature = "openapi", schema(value_type = Vec<f64>))]
    pub confidence_sequence: (f64, f64),
    pub e_values: EValues,
    /// Pairs still needed for a decision if the pairs to come look like those so far (0 once
    /// decided; none when nothing points to one).
    pub more_pairs: Option<u64>,
    /// The paired table (binary outcomes only).
    pub pair_table: Option<PairTable>,
}

/// A comparison, as `ufops compare`, `GET /v1/compare` and an alias move's evidence report it.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct Comparison {
    pub version: i64,
    pub policy: String,
    pub a: ArmSpec,
    pub b: ArmSpec,
    pub alpha: f64,
    pub margin: f64,
    pub plan_effect: Option<f64>,
    /// How the rollouts were paired: `key:FIELD` or `arrival order`.
    pub pairing: String,
    /// What was compared: `success label` or `progress:FIELD`.
    pub outcome: String,
    /// The method, with its reference.
    pub method: String,
    /// Every task's rollouts together, at alpha.
    pub pooled: ComparisonSlice,
    /// One slice per task, each at alpha / (number of tasks).
    pub tasks: Vec<ComparisonSlice>,
    /// The gate's answer: `not_worse` (every task and the pool decided better, no practical
    /// difference or not worse), `worse` (one of them decided worse) or `undecided`.
    pub gate: String,
    /// 0 not worse, 1 worse, 2 undecided.
    pub exit_code: i32,
}

pub const METHOD: &str = "betting confidence sequence on paired differences (Waudby-Smith & Ramdas 2024, \
JRSS-B 86(1)), aGRAPA or planned bets; tasks Bonferroni-adjusted (alpha/K each)";

/// One rollout of an arm, as the comparison reads it.
struct Rollout {
    task: String,
    arrival: u64,
    key: Option<String>,
    outcome: Option<f64>,
}

/// Comparing two arms of a policy (checkpoints, runs, aliases) on a [`Store`].
pub trait Compare {
    /// Compares arm B with arm A (see the module docs).
    fn compare(&self, req: &CompareRequest) -> impl Future<Output = Result<Comparison, StoreError>> + Send;
}

impl Compare for Store {
    async fn compare(&self, req: &CompareRequest) -> Result<Comparison, StoreError> {
        store::model::check_name("policy", &req.policy)?;
        req.config(req.alpha).validate().map_err(StoreError::invalid)?;
        if req.a == req.b {
            return Err(StoreError::invalid(format!("arm A and arm B are both {}", req.a)));
        }
        let version = match req.version {
            Some(v) => {
                self.version(v).await?;
                v
            }
            None => self.head_version().await?,
        };
        let pair_key = match req.pair_key.as_deref() {
            None => Some(DEFAULT_PAIR_KEY),
            Some("") => None,
            Some(k) => Some(k),
        };
        let a = arm_rollouts(self, req, &req.a, version, pair_key).await?;
        let b = arm_rollouts(self, req, &req.b, version, pair_key).await?;
        if a.is_empty() || b.is_empty() {
            let which = if a.is_empty() { &req.a } else { &req.b };
            return Err(StoreError::not_found(
                "episodes of arm",
                format!("{}/{which} at version {version}", req.policy),
            ));
        }
        // Pair by key when the arms share initial conditions; arms rolled out from different
        // ones (no key in common) pair in arrival order.
        let keys_a: std::collections::HashSet<&str> = a.iter().filter_map(|r| r.key.as_deref()).collect();
        let keyed = b.iter().any(|r| r.key.as_deref().is_some_and(|k| keys_a.contains(k)));
        let mut tasks: Vec<String> = a.iter().chain(&b).map(|r| r.task.clone()).collect();
        tasks.sort();
        tasks.dedup();
        let k = tasks.len().max(1) as f64;
        let slice_of = |task: Option<&str>, alpha: f64| {
            let pick = |rs: &[Rollout]| -> Vec<(u64, Option<String>, Option<f64>)> {
                rs.iter()
                    .filter(|r| task.is_none_or(|t| r.task == t))
                    .map(|r| (r.arrival, if keyed { r.key.clone() } else { None }, r.outcome))
                    .collect()
            };
            slice(task, pick(&a), pick(&b), req.config(alpha), req.progress.is_none())
        };
        let pooled = slice_of(None, req.alpha);
        let per_task: Vec<ComparisonSlice> = tasks.iter().map(|t| slice_of(Some(t), req.alpha / k)).collect();
        let decisions: Vec<&str> = per_task.iter().chain([&pooled]).map(|s| s.decision.as_str()).collect();
        let (gate, exit_code) = if decisions.contains(&Decision::Worse.as_str()) {
            ("worse", 1)
        } else if decisions.iter().all(|d| ["better", "no_practical_difference", "not_worse"].contains(d)) {
            ("not_worse", 0)
        } else {
            ("undecided", 2)
        };
        Ok(Comparison {
            version,
            policy: req.policy.clone(),
            a: req.a.clone(),
            b: req.b.clone(),
            alpha: req.alpha,
            margin: req.margin,
            plan_effect: req.plan_effect,
            pairing: if keyed {
                format!("key:{}", pair_key.unwrap_or_default())
            } else {
                "arrival order".into()
            },
            outcome: req.progress.as_ref().map_or("success label".into(), |f| format!("progress:{f}")),
            method: METHOD.into(),
            pooled,
            tasks: per_task,
            gate: gate.into(),
            exit_code,
        })
    }
}

/// An arm's rollouts at `version`, in arrival order.
async fn arm_rollouts(
    store: &Store,
    req: &CompareRequest,
    arm: &ArmSpec,
    version: i64,
    pair_key: Option<&str>,
) -> Result<Vec<Rollout>, StoreError> {
    let mut args = vec![Val::I(version), Val::S(req.policy.clone()), Val::S(arm.checkpoint.clone())];
    let mut sql = format!(
        "SELECT COALESCE(e.task, '') AS task, e.metadata AS metadata, e.version_added AS version_added, \
         e.source_index AS source_index, e.source_name AS source_name, l.label AS label FROM version_labels l \
         JOIN episodes e ON e.id = l.episode_id LEFT JOIN runs r ON r.id = e.run_id \
         WHERE {} AND e.policy = $2 AND e.checkpoint = $3",
        covers("l", "$1")
    );
    match arm.run.as_deref() {
        Some(NO_RUN) => sql.push_str(" AND e.run_id IS NULL"),
        Some(run) => {
            args.push(Val::S(run.to_string()));
            sql.push_str(&format!(" AND r.name = ${}", args.len()));
        }
        None => {}
    }
    if let Some(t) = &req.task {
        args.push(Val::S(t.clone()));
        sql.push_str(&format!(" AND e.task = ${}", args.len()));
    }
    sql.push_str(" ORDER BY e.version_added, e.source_index, e.id");
    let mut q = sqlx::query(&sql);
    for v in args {
        q = bind_val(q, v);
    }
    let rows = q.fetch_all(&store.catalog().pool).await?;
    let mut out = Vec::with_capacity(rows.len());
    for r in rows {
        let metadata: serde_json::Value = serde_json::from_str(&r.s("metadata")?)?;
        let outcome = match &req.progress {
            Some(field) => match metadata.get(field) {
                None | Some(serde_json::Value::Null) => None,
                Some(v) => Some(v.as_f64().filter(|x| (0.0..=1.0).contains(x)).ok_or_else(|| {
                    StoreError::invalid(format!("progress field {field:?} holds {v}, not a number in [0, 1]"))
                })?),
            },
            None => match r.s("label")?.parse::<Label>()? {
                Label::Success => Some(1.0),
                Label::Failure => Some(0.0),
                Label::Unknown => None,
            },
        };
        let key = match pair_key {
            None => None,
            Some("source_index") => Some(r.i("source_index")?.to_string()),
            Some("source_name") => Some(r.s("source_name")?),
            Some(k) => metadata.get(k).and_then(|v| match v {
                serde_json::Value::Null => None,
                serde_json::Value::String(s) => Some(s.clone()),
                other => Some(other.to_string()),
            }),
        };
        // Arrival: the version that added the rollout, then its index in its source (both
        // far below 2^32 in practice).
        let arrival =
            (r.i("version_added")?.max(0) as u64) << 32 | (r.i("source_index")?.max(0) as u64 & 0xffff_ffff);
        out.push(Rollout { task: r.s("task")?, arrival, key, outcome });
    }
    Ok(out)
}

fn slice(
    task: Option<&str>,
    a: Vec<(u64, Option<String>, Option<f64>)>,
    b: Vec<(u64, Option<String>, Option<f64>)>,
    config: SequentialConfig,
    binary: bool,
) -> ComparisonSlice {
    let pending =
        |v: &[(u64, Option<String>, Option<f64>)]| v.iter().filter(|x| x.2.is_none()).count() as u64;
    let (pending_a, pending_b) = (pending(&a), pending(&b));
    let ready = |v: Vec<(u64, Option<String>, Option<f64>)>| -> Vec<(u64, Option<String>, f64)> {
        v.into_iter().filter_map(|(t, k, y)| y.map(|y| (t, k, y))).collect()
    };
    let (a, b) = (ready(a), ready(b));
    let (pairs, unpaired_a, unpaired_b): (Vec<Pair>, usize, usize) = pair_by_key(&a, &b);
    let r = compare_pairs(&pairs, config);
    let c = PairedCounts::of(&pairs);
    let [better, worse, above_margin, below_margin] = r.e_values;
    ComparisonSlice {
        task: task.filter(|t| !t.is_empty()).map(str::to_string),
        alpha: config.alpha,
        decision: r.decision.as_str().into(),
        decided_at_pairs: r.decided_at,
        pairs: r.pairs,
        unpaired_a: unpaired_a as u64,
        unpaired_b: unpaired_b as u64,
        pending_a,
        pending_b,
        rate_a: r.mean_a,
        rate_b: r.mean_b,
        diff: r.mean_b - r.mean_a,
        confidence_sequence: r.confidence_sequence,
        e_values: EValues { better, worse, above_margin, below_margin },
        more_pairs: r.more_pairs,
        pair_table: binary.then_some(PairTable {
            both: c.both,
            only_a: c.only_a,
            only_b: c.only_b,
            neither: c.neither,
        }),
    }
}
