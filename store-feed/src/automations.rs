//! Automations: rules declared per policy that turn the change feed into jobs on the existing
//! queue, so the loop (label → split → train → publish → score → scoreboard) turns with no
//! command.
//!
//! * [`AutomationRule::TrainOnLabels`]: when a checkpoint has at least `min_labeled` labeled
//!   on-policy episodes (successes and failures both) and no verifier newer than its labels,
//!   queue a `train` job that freezes an on-policy split of the head and trains the paper's recipe
//!   (or the one given). One such job per checkpoint at a time; labels that arrive while it trains
//!   fire the next one when it ends. A job that failed fires again only after a newer label.
//! * [`AutomationRule::ScoreOnPublish`]: when a verifier is published for a checkpoint and it is
//!   the one that scores the checkpoint's review queue, queue a `score` job of that queue.
//! * [`AutomationRule::ScoreboardOnRunLabeled`]: when every episode of a run (a steered run, or
//!   any run) is labeled, queue a `scoreboard` job: it freezes the labels into a version and
//!   records the run's scoreboard rows at it ([`Automations::run_scoreboard_job`]).
//!
//! An automation is a cursor into the feed, like a webhook subscription: a server that holds its
//! lease ([`Store::claim_automations`]) reads the events after the cursor, updates the state of
//! each target the rule watches (a checkpoint, or a run) and, in one transaction with a fence on
//! the lease and the cursor, queues the jobs the rule fires, records an `automation.fired` event
//! for each and moves the cursor ([`Automations::advance_automation`]). So one event fires a rule at
//! most once whatever crashes, and the jobs run with the workers' own leases and fencing.
//!
//! "Newer than its labels" is read off the feed: a verifier covers its checkpoint's labels up to
//! the freeze of its split (the `split.frozen` event before its `artifact.published`; the publish
//! itself when that split was not seen), and a label change after that position makes it stale.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::future::Future;
use store::sql::{now_ms, now_rfc3339};
use store::sql::{RowExt, Tx};
use store::{CountFilter, Store, StoreError};
use store::{EventFilter, EventKind, NewEvent};
use store_compare::{ScoreboardRequest, Scoreboards};
use store_jobs::{insert_job, JobKind, JobQueue};
use store_labeling::ReviewQueue;

/// What an automation does.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AutomationRule {
    /// Freeze a split and train a verifier when a checkpoint has enough labels (params:
    /// [`TrainOnLabels`]).
    TrainOnLabels,
    /// Score a checkpoint's review queue when its verifier is published (params: [`ScoreOnPublish`]).
    ScoreOnPublish,
    /// Snapshot and compute a run's scoreboard rows when its episodes are all labeled (params:
    /// [`ScoreboardOnRunLabeled`]).
    ScoreboardOnRunLabeled,
}

impl AutomationRule {
    pub fn as_str(self) -> &'static str {
        match self {
            AutomationRule::TrainOnLabels => "train_on_labels",
            AutomationRule::ScoreOnPublish => "score_on_publish",
            AutomationRule::ScoreboardOnRunLabeled => "scoreboard_on_run_labeled",
        }
    }

    /// The feed's events the rule reads.
    fn kinds(self) -> Vec<EventKind> {
        use EventKind::*;
        match self {
            AutomationRule::TrainOnLabels => {
                vec![LabelSet, IngestCommitted, SplitFrozen, ArtifactPublished, JobChanged, AutomationCreated]
            }
            AutomationRule::ScoreOnPublish => vec![ArtifactPublished],
            AutomationRule::ScoreboardOnRunLabeled => vec![LabelSet, IngestCommitted, JobChanged],
        }
    }
}

impl std::str::FromStr for AutomationRule {
    type Err = StoreError;
    fn from_str(s: &str) -> Result<Self, StoreError> {
        Ok(match s {
            "train_on_labels" => AutomationRule::TrainOnLabels,
            "score_on_publish" => AutomationRule::ScoreOnPublish,
            "scoreboard_on_run_labeled" => AutomationRule::ScoreboardOnRunLabeled,
            _ => {
                return Err(StoreError::invalid(format!(
                    "unknown automation rule {s:?}: train_on_labels, score_on_publish or scoreboard_on_run_labeled"
                )))
            }
        })
    }
}

fn classifier() -> String {
    "classifier".into()
}
fn default_val_fraction() -> f64 {
    0.2
}

/// [`AutomationRule::TrainOnLabels`]'s parameters: the threshold, the split and the training job.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct TrainOnLabels {
    /// Only this checkpoint (default: each checkpoint of the policy).
    #[serde(default)]
    pub checkpoint: Option<String>,
    /// Labeled on-policy episodes (successes plus failures) a checkpoint needs.
    #[cfg_attr(feature = "openapi", schema(minimum = 2))]
    pub min_labeled: u64,
    /// The verifier kind: `classifier` (default) or `q`.
    #[serde(default = "classifier")]
    pub kind: String,
    /// The split's validation fraction (default 0.2).
    #[serde(default = "default_val_fraction")]
    pub val_fraction: f64,
    /// The split's seed (default 0).
    #[serde(default)]
    pub seed: u64,
    /// The training recipe, as `POST /v1/jobs` takes it (default: the paper's for the input).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "openapi", schema(value_type = Option<Object>))]
    pub config: Option<serde_json::Value>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub obs_keys: Option<Vec<String>>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub obs_history: Option<u32>,
    /// The policy's action chunk length, unless the episodes store chunks.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub chunk_len: Option<u32>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub step_stride: Option<u32>,
}

/// [`AutomationRule::ScoreOnPublish`]'s parameters.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ScoreOnPublish {
    /// Only this checkpoint (default: each checkpoint of the policy).
    #[serde(default)]
    pub checkpoint: Option<String>,
}

/// [`AutomationRule::ScoreboardOnRunLabeled`]'s parameters.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ScoreboardOnRunLabeled {
    /// Only runs of this name (default: every run of the policy).
    #[serde(default)]
    pub run: Option<String>,
    /// The baseline run's name the rows are compared with (default `base`).
    #[serde(default)]
    pub baseline: Option<String>,
}

/// Checks `params` for `rule` and returns them normalised (defaults filled in).
pub fn check_params(
    rule: AutomationRule,
    params: &serde_json::Value,
) -> Result<serde_json::Value, StoreError> {
    let params = if params.is_null() { serde_json::json!({}) } else { params.clone() };
    let bad = |e: serde_json::Error| StoreError::invalid(format!("{} params: {e}", rule.as_str()));
    let name =
        |what: &str, s: &Option<String>| s.as_deref().map_or(Ok(()), |s| store::model::check_name(what, s));
    Ok(match rule {
        AutomationRule::TrainOnLabels => {
            let p: TrainOnLabels = serde_json::from_value(params).map_err(bad)?;
            name("checkpoint", &p.checkpoint)?;
            if p.min_labeled < 2 {
                return Err(StoreError::invalid("min_labeled must be at least 2 (a success and a failure)"));
            }
            if p.kind != "classifier" && p.kind != "q" {
                return Err(StoreError::invalid(format!(
                    "unknown verifier kind {:?}: classifier or q",
                    p.kind
                )));
            }
            if !(0.0..=store::MAX_VAL_FRACTION).contains(&p.val_fraction) {
                return Err(StoreError::invalid("val_fraction must be in [0, 0.99]"));
            }
            if p.config.as_ref().is_some_and(|c| !c.is_object()) {
                return Err(StoreError::invalid("config must be a JSON object"));
            }
            if [p.obs_history, p.chunk_len, p.step_stride].contains(&Some(0)) {
                return Err(StoreError::invalid("obs_history, chunk_len and step_stride must be at least 1"));
            }
            serde_json::to_value(p)?
        }
        AutomationRule::ScoreOnPublish => {
            let p: ScoreOnPublish = serde_json::from_value(params).map_err(bad)?;
            name("checkpoint", &p.checkpoint)?;
            serde_json::to_value(p)?
        }
        AutomationRule::ScoreboardOnRunLabeled => {
            let p: ScoreboardOnRunLabeled = serde_json::from_value(params).map_err(bad)?;
            name("run", &p.run)?;
            name("baseline", &p.baseline)?;
            serde_json::to_value(p)?
        }
    })
}

/// An automation as the catalog holds it.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct AutomationRecord {
    pub id: String,
    pub policy: String,
    pub rule: AutomationRule,
    /// The rule's parameters, defaults filled in.
    #[cfg_attr(feature = "openapi", schema(value_type = Object))]
    pub params: serde_json::Value,
    /// The last feed event it has acted on.
    pub cursor_seq: i64,
    /// Jobs it has queued.
    pub fired: i64,
    pub created_by: String,
    pub created_at: String,
    /// What it knows of each target it has seen (a checkpoint, or a run id): why it fired or
    /// did not.
    pub targets: Vec<AutomationTarget>,
}

/// An automation's view of one target, as `GET /v1/automations/{id}` shows it.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct AutomationTarget {
    /// A checkpoint (`train_on_labels`, `score_on_publish`) or a run id.
    pub target: String,
    /// The last event that changed what the rule counts.
    pub changed_seq: i64,
    /// The feed position its newest verifier covers (`train_on_labels`: the freeze of its split).
    pub covered_seq: i64,
    /// The feed position of its last firing (0: never), and the job it queued then.
    pub fired_seq: i64,
    pub job_id: Option<String>,
}

/// What an automation knows of one target (a checkpoint, or a run).
#[derive(Debug, Clone, Default, PartialEq)]
struct TargetState {
    changed_seq: i64,
    covered_seq: i64,
    split_id: Option<String>,
    split_seq: i64,
    fired_seq: i64,
    job_id: Option<String>,
    /// Whether this page gave a reason to look at it again.
    dirty: bool,
}

/// A job a rule decided to queue.
struct Fire {
    target: String,
    checkpoint: Option<String>,
    kind: JobKind,
    spec: serde_json::Value,
    because: i64,
}

const COLS: &str = "id, policy, rule, params, cursor_seq, fired, created_by, created_at";

fn from_row(r: &sqlx::any::AnyRow) -> Result<AutomationRecord, StoreError> {
    Ok(AutomationRecord {
        id: r.s("id")?,
        policy: r.s("policy")?,
        rule: r.s("rule")?.parse()?,
        params: serde_json::from_str(&r.s("params")?)?,
        cursor_seq: r.i("cursor_seq")?,
        fired: r.i("fired")?,
        created_by: r.s("created_by")?,
        created_at: r.s("created_at")?,
        targets: Vec::new(),
    })
}

/// Events read per step.
const PAGE: i64 = 500;

/// Automations on a [`Store`]: rules that read the change feed and queue jobs (train on new
/// labels, score on publish, a run's scoreboard once it is labeled), claimed by one runner at
/// a time.
pub trait Automations {
    /// Declares an automation; it acts on the events after this moment (a `train_on_labels` one
    /// also looks once at each checkpoint it watches, through its own `automation.created`).
    fn create_automation(
        &self,
        policy: &str,
        rule: AutomationRule,
        params: &serde_json::Value,
        actor: &str,
    ) -> impl Future<Output = Result<AutomationRecord, StoreError>> + Send;

    fn automation(&self, id: &str) -> impl Future<Output = Result<AutomationRecord, StoreError>> + Send;

    /// Every automation, oldest first; `policy` filters.
    fn automations(
        &self,
        policy: Option<&str>,
    ) -> impl Future<Output = Result<Vec<AutomationRecord>, StoreError>> + Send;

    /// Whether any automation exists.
    fn has_automations(&self) -> impl Future<Output = Result<bool, StoreError>> + Send;

    /// Deletes an automation (the jobs it queued go on).
    fn delete_automation(&self, id: &str, actor: &str)
        -> impl Future<Output = Result<(), StoreError>> + Send;

    /// Takes the lease of every automation the feed has gone past that no live lease holds.
    fn claim_automations(
        &self,
        owner: &str,
        lease_ms: i64,
    ) -> impl Future<Output = Result<Vec<AutomationRecord>, StoreError>> + Send;

    /// Gives a held automation's lease back.
    fn release_automation(
        &self,
        id: &str,
        owner: &str,
    ) -> impl Future<Output = Result<(), StoreError>> + Send;

    /// Acts on the next page of events after the automation's cursor while `owner` holds its
    /// lease: `Ok(Some(cursor))` with the new cursor (equal to the old one when the feed has
    /// nothing after it), `Ok(None)` when the lease or the cursor moved under it (another server
    /// has it now; nothing was written).
    fn advance_automation(
        &self,
        a: &AutomationRecord,
        owner: &str,
    ) -> impl Future<Output = Result<Option<i64>, StoreError>> + Send;

    /// A `scoreboard` job: freezes the labels into a version (when one changed since the head)
    /// and returns the run's scoreboard rows at it, compared with the baseline run.
    fn run_scoreboard_job(
        &self,
        spec: &serde_json::Value,
    ) -> impl Future<Output = Result<serde_json::Value, StoreError>> + Send;
}

impl Automations for Store {
    async fn create_automation(
        &self,
        policy: &str,
        rule: AutomationRule,
        params: &serde_json::Value,
        actor: &str,
    ) -> Result<AutomationRecord, StoreError> {
        store::model::check_name("policy", policy)?;
        store::model::check_name("actor", actor)?;
        let params = check_params(rule, params)?;
        let id = format!("auto_{}", &uuid::Uuid::new_v4().simple().to_string()[..12]);
        let mut tx = self.catalog().begin_write().await?;
        let head =
            sqlx::query("SELECT seq FROM event_head WHERE id = 1").fetch_one(&mut *tx).await?.i("seq")?;
        sqlx::query(&format!(
            "INSERT INTO automations ({COLS}, lease_owner, lease_until_ms) VALUES ($1, $2, $3, $4, $5, 0, $6, $7, NULL, 0)"
        ))
        .bind(&id)
        .bind(policy)
        .bind(rule.as_str())
        .bind(serde_json::to_string(&params)?)
        .bind(head)
        .bind(actor)
        .bind(now_rfc3339())
        .execute(&mut *tx)
        .await?;
        let event = NewEvent::new(
            EventKind::AutomationCreated,
            id.clone(),
            serde_json::json!({"rule": rule, "params": params, "actor": actor}),
        )
        .of(policy, None);
        self.commit_with_events(tx, &[event]).await?;
        self.automation(&id).await
    }

    async fn automation(&self, id: &str) -> Result<AutomationRecord, StoreError> {
        let row = sqlx::query(&format!("SELECT {COLS} FROM automations WHERE id = $1"))
            .bind(id)
            .fetch_optional(&self.catalog().pool)
            .await?
            .ok_or_else(|| StoreError::not_found("automation", id))?;
        let mut a = from_row(&row)?;
        a.targets = automation_targets(self, id).await?;
        Ok(a)
    }

    async fn automations(&self, policy: Option<&str>) -> Result<Vec<AutomationRecord>, StoreError> {
        let rows = sqlx::query(&format!(
            "SELECT {COLS} FROM automations WHERE ($1 = '' OR policy = $1) ORDER BY created_at, id"
        ))
        .bind(policy.unwrap_or(""))
        .fetch_all(&self.catalog().pool)
        .await?;
        let mut out = Vec::with_capacity(rows.len());
        for r in &rows {
            let mut a = from_row(r)?;
            a.targets = automation_targets(self, &a.id).await?;
            out.push(a);
        }
        Ok(out)
    }

    async fn has_automations(&self) -> Result<bool, StoreError> {
        let row =
            sqlx::query("SELECT id FROM automations LIMIT 1").fetch_optional(&self.catalog().pool).await?;
        Ok(row.is_some())
    }

    async fn delete_automation(&self, id: &str, actor: &str) -> Result<(), StoreError> {
        let mut tx = self.catalog().begin_write().await?;
        let row = sqlx::query("SELECT policy FROM automations WHERE id = $1")
            .bind(id)
            .fetch_optional(&mut *tx)
            .await?
            .ok_or_else(|| StoreError::not_found("automation", id))?;
        sqlx::query("DELETE FROM automation_targets WHERE automation_id = $1")
            .bind(id)
            .execute(&mut *tx)
            .await?;
        sqlx::query("DELETE FROM automations WHERE id = $1").bind(id).execute(&mut *tx).await?;
        let event = NewEvent::new(EventKind::AutomationDeleted, id, serde_json::json!({"actor": actor}))
            .of(&row.s("policy")?, None);
        self.commit_with_events(tx, &[event]).await
    }

    async fn claim_automations(
        &self,
        owner: &str,
        lease_ms: i64,
    ) -> Result<Vec<AutomationRecord>, StoreError> {
        let now = now_ms();
        let rows = sqlx::query(&format!(
            "UPDATE automations SET lease_owner = $1, lease_until_ms = $2 \
             WHERE lease_until_ms < $3 AND cursor_seq < (SELECT seq FROM event_head WHERE id = 1) RETURNING {COLS}"
        ))
        .bind(owner)
        .bind(now + lease_ms)
        .bind(now)
        .fetch_all(&self.catalog().pool)
        .await?;
        rows.iter().map(from_row).collect()
    }

    async fn release_automation(&self, id: &str, owner: &str) -> Result<(), StoreError> {
        sqlx::query("UPDATE automations SET lease_owner = NULL, lease_until_ms = 0 WHERE id = $1 AND lease_owner = $2")
            .bind(id)
            .bind(owner)
            .execute(&self.catalog().pool)
            .await?;
        Ok(())
    }

    #[allow(
        clippy::too_many_lines,
        reason = "one automation's pass over the feed, decided per rule in the transaction that queues"
    )]
    async fn advance_automation(&self, a: &AutomationRecord, owner: &str) -> Result<Option<i64>, StoreError> {
        let filter = EventFilter { kinds: a.rule.kinds(), policy: Some(a.policy.clone()) };
        let page = match self.events_after(a.cursor_seq, PAGE, &filter).await {
            // Retention deleted events it had not read (a server that ran none for a month):
            // they are gone, so it goes on from the oldest left, as a reader of the feed must.
            Err(StoreError::Gone(_)) => {
                let (_, pruned_through) = self.event_head().await?;
                tracing::warn!(
                    "automation {}: events up to {pruned_through} are gone; going on from there",
                    a.id
                );
                let moved = sqlx::query(
                    "UPDATE automations SET cursor_seq = $1 WHERE id = $2 AND lease_owner = $3 AND cursor_seq = $4",
                )
                .bind(pruned_through)
                .bind(&a.id)
                .bind(owner)
                .bind(a.cursor_seq)
                .execute(&self.catalog().pool)
                .await?;
                return Ok((moved.rows_affected() == 1).then_some(pruned_through));
            }
            r => r?,
        };
        if page.next <= a.cursor_seq {
            return Ok(Some(a.cursor_seq));
        }
        let mut targets: BTreeMap<String, TargetState> = BTreeMap::new();
        let mut fires = Vec::new();
        match a.rule {
            AutomationRule::TrainOnLabels => {
                let p: TrainOnLabels = serde_json::from_value(a.params.clone())?;
                read_train_events(self, a, &p, &page.events, &mut targets).await?;
                for (checkpoint, t) in targets.iter().filter(|(_, t)| t.dirty) {
                    if let Some(f) = train_fire(self, a, &p, checkpoint, t).await? {
                        fires.push(f);
                    }
                }
            }
            AutomationRule::ScoreOnPublish => {
                let p: ScoreOnPublish = serde_json::from_value(a.params.clone())?;
                for e in &page.events {
                    let Some(checkpoint) = e.checkpoint.as_deref() else { continue };
                    if p.checkpoint.as_deref().is_some_and(|c| c != checkpoint) {
                        continue;
                    }
                    // The queue is scored by one artifact; a verifier that is not it changes nothing.
                    if self.review_artifact_for(&a.policy, checkpoint).await?.as_deref() != Some(&e.subject) {
                        continue;
                    }
                    fires.push(Fire {
                        target: checkpoint.to_string(),
                        checkpoint: Some(checkpoint.to_string()),
                        kind: JobKind::Score,
                        spec: serde_json::json!({
                            "artifact_id": e.subject, "policy": a.policy, "checkpoint": checkpoint,
                        }),
                        because: e.seq,
                    });
                }
            }
            AutomationRule::ScoreboardOnRunLabeled => {
                let p: ScoreboardOnRunLabeled = serde_json::from_value(a.params.clone())?;
                read_run_events(self, a, &p, &page.events, &mut targets).await?;
                for (run_id, t) in targets.iter().filter(|(_, t)| t.dirty) {
                    if let Some(f) = scoreboard_fire(self, a, &p, run_id, t).await? {
                        fires.push(f);
                    }
                }
            }
        }
        let mut tx = self.catalog().begin_write().await?;
        let moved = sqlx::query(
            "UPDATE automations SET cursor_seq = $1, fired = fired + $2 \
             WHERE id = $3 AND lease_owner = $4 AND lease_until_ms >= $5 AND cursor_seq = $6",
        )
        .bind(page.next)
        .bind(fires.len() as i64)
        .bind(&a.id)
        .bind(owner)
        .bind(now_ms())
        .bind(a.cursor_seq)
        .execute(&mut *tx)
        .await?;
        if moved.rows_affected() != 1 {
            return Ok(None);
        }
        let mut events = Vec::new();
        for f in fires {
            let (job_id, job_events) =
                insert_job(&mut tx, f.kind, &f.spec, &format!("automation:{}", a.id)).await?;
            events.push(
                NewEvent::new(
                    EventKind::AutomationFired,
                    a.id.clone(),
                    serde_json::json!({
                        "rule": a.rule, "target": f.target, "job_id": job_id, "job_kind": f.kind, "because_seq": f.because,
                    }),
                )
                .of(&a.policy, f.checkpoint.as_deref()),
            );
            events.extend(job_events);
            let t = targets.entry(f.target).or_default();
            t.job_id = Some(job_id);
            t.fired_seq = page.next;
        }
        for (target, t) in &targets {
            upsert_target(&mut tx, &a.id, target, t).await?;
        }
        self.commit_with_events(tx, &events).await?;
        Ok(Some(page.next))
    }

    async fn run_scoreboard_job(&self, spec: &serde_json::Value) -> Result<serde_json::Value, StoreError> {
        let text = |k: &str| spec.get(k).and_then(|v| v.as_str()).map(String::from);
        let policy = text("policy").ok_or_else(|| StoreError::invalid("scoreboard job has no policy"))?;
        let run_id = text("run_id").ok_or_else(|| StoreError::invalid("scoreboard job has no run_id"))?;
        let run = self.run(&run_id).await?;
        let (commit, created) = self
            .snapshot_labels_if_changed(
                "automation",
                &format!("labels of run {} ({run_id}) complete", run.name),
            )
            .await?;
        let board = self
            .scoreboard(&ScoreboardRequest {
                policy: policy.clone(),
                version: Some(commit.version),
                baseline: text("baseline"),
                ..Default::default()
            })
            .await?;
        let rows: Vec<_> =
            board.rows.into_iter().filter(|r| r.run.as_ref().is_some_and(|x| x.id == run_id)).collect();
        Ok(serde_json::json!({
            "policy": policy, "run_id": run_id, "run_name": run.name, "version": commit.version,
            "snapshot_created": created, "baseline": board.baseline, "rows": rows,
        }))
    }
}

async fn automation_targets(store: &Store, id: &str) -> Result<Vec<AutomationTarget>, StoreError> {
    let rows = sqlx::query(
        "SELECT target, changed_seq, covered_seq, fired_seq, job_id FROM automation_targets \
         WHERE automation_id = $1 ORDER BY target",
    )
    .bind(id)
    .fetch_all(&store.catalog().pool)
    .await?;
    rows.iter()
        .map(|r| {
            Ok(AutomationTarget {
                target: r.s("target")?,
                changed_seq: r.i("changed_seq")?,
                covered_seq: r.i("covered_seq")?,
                fired_seq: r.i("fired_seq")?,
                job_id: r.os("job_id")?,
            })
        })
        .collect()
}

/// The state of a target, as stored (default: never seen).
async fn target_state(store: &Store, automation: &str, target: &str) -> Result<TargetState, StoreError> {
    let row = sqlx::query(
        "SELECT changed_seq, covered_seq, split_id, split_seq, fired_seq, job_id FROM automation_targets \
         WHERE automation_id = $1 AND target = $2",
    )
    .bind(automation)
    .bind(target)
    .fetch_optional(&store.catalog().pool)
    .await?;
    Ok(match row {
        None => TargetState::default(),
        Some(r) => TargetState {
            changed_seq: r.i("changed_seq")?,
            covered_seq: r.i("covered_seq")?,
            split_id: r.os("split_id")?,
            split_seq: r.i("split_seq")?,
            fired_seq: r.i("fired_seq")?,
            job_id: r.os("job_id")?,
            dirty: false,
        },
    })
}

async fn target_entry<'t>(
    store: &Store,
    targets: &'t mut BTreeMap<String, TargetState>,
    automation: &str,
    target: &str,
) -> Result<&'t mut TargetState, StoreError> {
    if !targets.contains_key(target) {
        let t = target_state(store, automation, target).await?;
        targets.insert(target.to_string(), t);
    }
    Ok(targets.get_mut(target).expect("inserted above"))
}

/// A job changed state: if it is the last one the automation queued for a target, that
/// target is looked at again (labels that came while it ran may fire the next).
async fn job_ended(
    store: &Store,
    a: &AutomationRecord,
    job_id: &str,
    targets: &mut BTreeMap<String, TargetState>,
) -> Result<(), StoreError> {
    if let Some(t) = targets.values_mut().find(|t| t.job_id.as_deref() == Some(job_id)) {
        t.dirty = true;
        return Ok(());
    }
    let row = sqlx::query("SELECT target FROM automation_targets WHERE automation_id = $1 AND job_id = $2")
        .bind(&a.id)
        .bind(job_id)
        .fetch_optional(&store.catalog().pool)
        .await?;
    if let Some(r) = row {
        let target = r.s("target")?;
        target_entry(store, targets, &a.id, &target).await?.dirty = true;
    }
    Ok(())
}

async fn read_train_events(
    store: &Store,
    a: &AutomationRecord,
    p: &TrainOnLabels,
    events: &[store::Event],
    targets: &mut BTreeMap<String, TargetState>,
) -> Result<(), StoreError> {
    for e in events {
        if e.kind == EventKind::AutomationCreated {
            if e.subject != a.id {
                continue;
            }
            // Declared: look once at every checkpoint it watches.
            let checkpoints = match &p.checkpoint {
                Some(c) => vec![c.clone()],
                None => checkpoints_of(store, &a.policy).await?,
            };
            for c in checkpoints {
                let t = target_entry(store, targets, &a.id, &c).await?;
                t.changed_seq = e.seq;
                t.dirty = true;
            }
            continue;
        }
        let Some(checkpoint) = e.checkpoint.as_deref() else { continue };
        if p.checkpoint.as_deref().is_some_and(|c| c != checkpoint) {
            continue;
        }
        let data = |k: &str| e.data.get(k).and_then(|v| v.as_str());
        match e.kind {
            EventKind::LabelSet | EventKind::IngestCommitted => {
                let t = target_entry(store, targets, &a.id, checkpoint).await?;
                t.changed_seq = e.seq;
                t.dirty = true;
            }
            EventKind::SplitFrozen if data("mode") == Some("on_policy") => {
                let t = target_entry(store, targets, &a.id, checkpoint).await?;
                t.split_id = Some(e.subject.clone());
                t.split_seq = e.seq;
            }
            EventKind::ArtifactPublished
                if data("kind") == Some(p.kind.as_str())
                    && e.data.get("off_policy").and_then(|v| v.as_bool()) != Some(true) =>
            {
                let t = target_entry(store, targets, &a.id, checkpoint).await?;
                let from_seen_split = t.split_id.is_some() && data("split_id") == t.split_id.as_deref();
                t.covered_seq = t.covered_seq.max(if from_seen_split { t.split_seq } else { e.seq });
                t.dirty = true;
            }
            EventKind::JobChanged => job_ended(store, a, &e.subject, targets).await?,
            _ => {}
        }
    }
    Ok(())
}

async fn train_fire(
    store: &Store,
    a: &AutomationRecord,
    p: &TrainOnLabels,
    checkpoint: &str,
    t: &TargetState,
) -> Result<Option<Fire>, StoreError> {
    if t.changed_seq <= t.covered_seq {
        return Ok(None); // a verifier newer than its labels
    }
    if let Some(job) = &t.job_id {
        match store.job(job).await {
            Ok(j) if matches!(j.state, store_jobs::JobState::Queued | store_jobs::JobState::Running) => {
                return Ok(None)
            }
            // A failed (or cancelled) job fires again only for labels newer than its firing.
            Ok(j) if j.state != store_jobs::JobState::Succeeded && t.changed_seq <= t.fired_seq => {
                return Ok(None)
            }
            _ => {}
        }
    }
    let counts = store
        .episode_counts(&CountFilter {
            policy: Some(a.policy.clone()),
            checkpoint: Some(checkpoint.to_string()),
            ..Default::default()
        })
        .await?;
    if ((counts.success + counts.failure) as u64) < p.min_labeled
        || counts.success == 0
        || counts.failure == 0
    {
        return Ok(None);
    }
    let mut spec = serde_json::json!({
        "freeze": {"val_fraction": p.val_fraction, "seed": p.seed},
        "kind": p.kind, "policy": a.policy, "checkpoint": checkpoint, "automation": a.id,
    });
    let input = [
        ("config", p.config.clone()),
        ("obs_keys", p.obs_keys.as_ref().map(|k| serde_json::json!(k))),
        ("obs_history", p.obs_history.map(|n| serde_json::json!(n))),
        ("chunk_len", p.chunk_len.map(|n| serde_json::json!(n))),
        ("step_stride", p.step_stride.map(|n| serde_json::json!(n))),
    ];
    for (key, value) in input {
        if let Some(v) = value {
            spec[key] = v;
        }
    }
    Ok(Some(Fire {
        target: checkpoint.to_string(),
        checkpoint: Some(checkpoint.to_string()),
        kind: JobKind::Train,
        spec,
        because: t.changed_seq,
    }))
}

async fn read_run_events(
    store: &Store,
    a: &AutomationRecord,
    p: &ScoreboardOnRunLabeled,
    events: &[store::Event],
    targets: &mut BTreeMap<String, TargetState>,
) -> Result<(), StoreError> {
    let named: Option<Vec<String>> = match &p.run {
        Some(name) => Some(store.runs(Some(name)).await?.into_iter().map(|r| r.id).collect()),
        None => None,
    };
    let wanted = |run: &str| named.as_ref().is_none_or(|n| n.iter().any(|r| r == run));
    // Label changes name episodes: their runs in one read per page.
    let labeled: Vec<&str> =
        events.iter().filter(|e| e.kind == EventKind::LabelSet).map(|e| e.subject.as_str()).collect();
    let runs_of = runs_of_episodes(store, &labeled).await?;
    for e in events {
        let run = match e.kind {
            EventKind::LabelSet => runs_of.get(&e.subject).cloned(),
            EventKind::IngestCommitted => e.data.get("run_id").and_then(|v| v.as_str()).map(String::from),
            EventKind::JobChanged => {
                job_ended(store, a, &e.subject, targets).await?;
                None
            }
            _ => None,
        };
        if let Some(run) = run.filter(|r| wanted(r)) {
            let t = target_entry(store, targets, &a.id, &run).await?;
            t.changed_seq = e.seq;
            t.dirty = true;
        }
    }
    Ok(())
}

async fn scoreboard_fire(
    store: &Store,
    a: &AutomationRecord,
    p: &ScoreboardOnRunLabeled,
    run_id: &str,
    t: &TargetState,
) -> Result<Option<Fire>, StoreError> {
    if t.changed_seq <= t.fired_seq {
        return Ok(None);
    }
    if let Some(job) = &t.job_id {
        if let Ok(j) = store.job(job).await {
            if matches!(j.state, store_jobs::JobState::Queued | store_jobs::JobState::Running) {
                return Ok(None);
            }
        }
    }
    let row = sqlx::query(
        "SELECT COUNT(*) AS n, COUNT(CASE WHEN label = 'unknown' THEN 1 END) AS unknown FROM episodes \
         WHERE run_id = $1 AND policy = $2 AND version_removed IS NULL",
    )
    .bind(run_id)
    .bind(&a.policy)
    .fetch_one(&store.catalog().pool)
    .await?;
    if row.i("n")? == 0 || row.i("unknown")? > 0 {
        return Ok(None);
    }
    Ok(Some(Fire {
        target: run_id.to_string(),
        checkpoint: None,
        kind: JobKind::Scoreboard,
        spec: serde_json::json!({
            "policy": a.policy, "run_id": run_id, "baseline": p.baseline, "automation": a.id,
        }),
        because: t.changed_seq,
    }))
}

/// The checkpoints of a policy that have episodes.
async fn checkpoints_of(store: &Store, policy: &str) -> Result<Vec<String>, StoreError> {
    let rows = sqlx::query(
        "SELECT DISTINCT checkpoint FROM episodes WHERE policy = $1 AND version_removed IS NULL ORDER BY checkpoint",
    )
    .bind(policy)
    .fetch_all(&store.catalog().pool)
    .await?;
    rows.iter().map(|r| r.s("checkpoint")).collect()
}

/// The run of each of these episodes that has one.
async fn runs_of_episodes(store: &Store, ids: &[&str]) -> Result<BTreeMap<String, String>, StoreError> {
    let mut out = BTreeMap::new();
    for chunk in ids.chunks(500) {
        let list: Vec<String> = (1..=chunk.len()).map(|i| format!("${i}")).collect();
        let sql = format!(
            "SELECT id, run_id FROM episodes WHERE id IN ({}) AND run_id IS NOT NULL",
            list.join(", ")
        );
        let mut q = sqlx::query(&sql);
        for id in chunk {
            q = q.bind(*id);
        }
        for r in q.fetch_all(&store.catalog().pool).await? {
            out.insert(r.s("id")?, r.s("run_id")?);
        }
    }
    Ok(out)
}

async fn upsert_target(
    tx: &mut Tx,
    automation: &str,
    target: &str,
    t: &TargetState,
) -> Result<(), StoreError> {
    sqlx::query(
        "INSERT INTO automation_targets (automation_id, target, changed_seq, covered_seq, split_id, split_seq, \
         fired_seq, job_id) VALUES ($1, $2, $3, $4, $5, $6, $7, $8) ON CONFLICT (automation_id, target) DO UPDATE SET \
         changed_seq = excluded.changed_seq, covered_seq = excluded.covered_seq, split_id = excluded.split_id, \
         split_seq = excluded.split_seq, fired_seq = excluded.fired_seq, job_id = excluded.job_id",
    )
    .bind(automation)
    .bind(target)
    .bind(t.changed_seq)
    .bind(t.covered_seq)
    .bind(t.split_id.clone())
    .bind(t.split_seq)
    .bind(t.fired_seq)
    .bind(t.job_id.clone())
    .execute(&mut **tx)
    .await?;
    Ok(())
}
