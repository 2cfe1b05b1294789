//! Several labelers per episode, on top of the label event log.
//!
//! A campaign is a policy's setting: how many independent verdicts an episode needs
//! (`labels_needed`, default 1) and whether labelers work blind. Each labeler's verdict is an
//! append-only vote (`label_votes`; a labeler's latest vote counts). When the latest votes of
//! `labels_needed` labelers agree, the episode's label moves to that verdict through the ordinary
//! label write (`store::sql::write_label`: revision, audit event, counts), so history,
//! snapshots and `version_labels` work as before; the event's data records the votes. When they
//! disagree the episode is disputed until an adjudicator settles it (an event with source
//! `adjudication`). With `labels_needed = 1` one vote is one label write, as a PUT is.
//!
//! Votes and events carry data: a failure cause from the task's taxonomy and time spans in steps.
//!
//! One file past 700 lines: campaign settings, votes and their resolution are one protocol over the
//! same tables.

use serde::{Deserialize, Serialize};
use serde_json::{json, Value};
use std::collections::{BTreeMap, HashSet};
use std::future::Future;
use std::sync::Arc;
use store::sql::{now_rfc3339, write_label, RowExt, Tx};
use store::{Backend, EventKind, Label, LabelChange, LabelUpdate, NewEvent, Store, StoreError};

/// The most labelers a campaign may require per episode.
pub const MAX_LABELS_NEEDED: i64 = 10;
/// Failure causes per task: one number key each (1-9).
pub const MAX_FAILURE_CAUSES: usize = 9;
/// Time spans per verdict.
pub const MAX_SPANS: usize = 64;

/// A policy's labeling settings.
#[derive(Debug, Clone, Serialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct Campaign {
    pub policy: String,
    /// Independent verdicts an episode needs before its label is the agreed verdict.
    pub labels_needed: i64,
    /// A labeler does not see the others' verdicts on an episode until they have given theirs.
    pub blind: bool,
    pub updated_by: Option<String>,
    pub updated_at: Option<String>,
}

/// A stretch of the episode a verdict points at, in steps (inclusive).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct Span {
    #[cfg_attr(feature = "openapi", schema(minimum = 0))]
    pub start_step: i64,
    #[cfg_attr(feature = "openapi", schema(minimum = 0))]
    pub end_step: i64,
}

impl Span {
    /// The same stretch with its ends in order (a labeler may mark the end first).
    pub fn ordered(self) -> Span {
        Span { start_step: self.start_step.min(self.end_step), end_step: self.start_step.max(self.end_step) }
    }
}

/// What a verdict carries besides the label.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct VerdictData {
    /// One of the task's failure causes (failure verdicts only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub failure_cause: Option<String>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub spans: Vec<Span>,
}

impl VerdictData {
    fn is_empty(&self) -> bool {
        self.failure_cause.is_none() && self.spans.is_empty()
    }
}

/// One labeler's verdict on an episode.
#[derive(Debug, Clone)]
pub struct NewVote {
    pub episode_id: String,
    pub label: Label,
    pub data: VerdictData,
    pub note: Option<String>,
    /// With `labels_needed = 1` the vote is a label write: fail with a conflict unless the
    /// episode is at this revision (as a PUT's If-Match).
    pub expect_revision: Option<i64>,
}

#[derive(Debug, Clone, Serialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct Vote {
    pub actor: String,
    pub label: Label,
    #[serde(flatten)]
    pub data: VerdictData,
    pub note: Option<String>,
    pub created_at: String,
}

/// Where an episode stands among its labelers.
#[derive(Debug, Clone, Copy, Serialize, PartialEq, Eq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[serde(rename_all = "lowercase")]
pub enum ConsensusState {
    /// Fewer than `labels_needed` labelers have voted.
    Pending,
    /// Enough labelers voted and agree: the episode's label is their verdict.
    Agreed,
    /// Enough labelers voted and disagree: waits for an adjudicator.
    Disputed,
    /// Disputed, then settled by an adjudicator after the latest vote.
    Settled,
}

/// An episode's votes (each labeler's latest) and their state.
#[derive(Debug, Clone, Serialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct EpisodeVotes {
    pub episode_id: String,
    pub policy: String,
    pub labels_needed: i64,
    pub blind: bool,
    pub state: ConsensusState,
    /// How many labelers have voted.
    pub voters: usize,
    /// The votes, or only the caller's own while the campaign is blind and the caller has not
    /// voted (see [`EpisodeVotes::hide_others`]).
    pub votes: Vec<Vote>,
    /// Whether other labelers' votes were withheld.
    pub hidden: bool,
}

impl EpisodeVotes {
    /// Blind mode: a labeler who has not voted on this episode sees no one else's vote.
    pub fn hide_others(&mut self, viewer: &str) {
        if self.blind && !self.votes.iter().any(|v| v.actor == viewer) && !self.votes.is_empty() {
            self.votes.clear();
            self.hidden = true;
        }
    }
}

/// The answer to a vote: the episode's votes and, when the vote moved the label, the change.
#[derive(Debug, Clone, Serialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct VoteOutcome {
    pub state: ConsensusState,
    pub voters: usize,
    pub labels_needed: i64,
    /// The episode's label and revision after the vote.
    pub label: Label,
    pub revision: i64,
    /// Set when the vote made the label the agreed verdict.
    pub change: Option<LabelChange>,
}

/// A disputed episode waiting for an adjudicator.
#[derive(Debug, Clone, Serialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct Dispute {
    pub episode_id: String,
    pub policy: String,
    pub label: Label,
    pub label_revision: i64,
    pub votes: Vec<Vote>,
}

/// One labeler's vote counts in a campaign.
#[derive(Debug, Clone, Serialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct LabelerCounts {
    pub actor: String,
    pub votes: u64,
    pub success: u64,
    pub failure: u64,
    pub unknown: u64,
}

/// Agreement of two labelers over the episodes both voted on.
#[derive(Debug, Clone, Serialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct PairAgreement {
    pub a: String,
    pub b: String,
    /// Episodes both voted on.
    pub episodes: u64,
    /// Share of those with the same verdict.
    pub observed: Option<f64>,
    /// Cohen's κ; `None` with no common episode or when κ is undefined (one label throughout).
    pub kappa: Option<f64>,
}

/// Agreement in a campaign, from each labeler's latest vote per episode.
#[derive(Debug, Clone, Serialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct Agreement {
    pub policy: String,
    pub labels_needed: i64,
    /// Episodes with at least one vote.
    pub episodes_voted: u64,
    pub agreed: u64,
    pub disputed: u64,
    pub settled: u64,
    pub pending: u64,
    pub labelers: Vec<LabelerCounts>,
    pub pairs: Vec<PairAgreement>,
    /// Krippendorff's α (nominal) over every episode with two or more votes, all labelers.
    pub krippendorff_alpha: Option<f64>,
}

/// A labeler's latest vote per episode from votes in id order.
fn latest_by_actor(votes: Vec<Vote>) -> Vec<Vote> {
    let mut by: BTreeMap<String, Vote> = BTreeMap::new();
    for v in votes {
        by.insert(v.actor.clone(), v);
    }
    by.into_values().collect()
}

fn state_of(latest: &[Vote], labels_needed: i64, adjudicated_after_last_vote: bool) -> ConsensusState {
    if (latest.len() as i64) < labels_needed {
        return ConsensusState::Pending;
    }
    if latest.windows(2).all(|w| w[0].label == w[1].label) {
        ConsensusState::Agreed
    } else if adjudicated_after_last_vote {
        ConsensusState::Settled
    } else {
        ConsensusState::Disputed
    }
}

/// The data of a consensus event: the agreed failure cause if the voters who gave one agree,
/// every voter's spans (with who marked them) and each vote.
fn merged_data(votes: &[Vote]) -> Value {
    let causes: Vec<&String> = votes.iter().filter_map(|v| v.data.failure_cause.as_ref()).collect();
    let cause = causes.first().filter(|c| causes.iter().all(|x| x == *c));
    let spans: Vec<Value> = votes
        .iter()
        .flat_map(|v| {
            v.data
                .spans
                .iter()
                .map(|s| json!({"start_step": s.start_step, "end_step": s.end_step, "actor": v.actor}))
        })
        .collect();
    let each: Vec<Value> = votes
        .iter()
        .map(|v| json!({"actor": v.actor, "label": v.label, "failure_cause": v.data.failure_cause}))
        .collect();
    let mut d = json!({"votes": each});
    if let Some(c) = cause {
        d["failure_cause"] = json!(c);
    }
    if !spans.is_empty() {
        d["spans"] = json!(spans);
    }
    d
}

fn vote_from_row(r: &sqlx::any::AnyRow) -> Result<Vote, StoreError> {
    let data = match r.os("data")? {
        Some(t) => serde_json::from_str(&t).map_err(|e| StoreError::Corrupt(format!("vote data: {e}")))?,
        None => VerdictData::default(),
    };
    Ok(Vote {
        actor: r.s("actor")?,
        label: r.s("label")?.parse()?,
        data,
        note: r.os("note")?,
        created_at: r.s("created_at")?,
    })
}

/// The episode row a vote or adjudication works on, locked on Postgres.
struct EpisodeHead {
    policy: String,
    task: Option<String>,
    length: i64,
    label: Label,
    revision: i64,
}

async fn episode_head(tx: &mut Tx, backend: Backend, id: &str) -> Result<EpisodeHead, StoreError> {
    let lock = if backend == Backend::Postgres { " FOR UPDATE" } else { "" };
    let r = sqlx::query(&format!(
        "SELECT policy, task, length, label, label_revision FROM episodes WHERE id = $1 AND version_removed IS NULL{lock}"
    ))
    .bind(id)
    .fetch_optional(&mut **tx)
    .await?
    .ok_or_else(|| StoreError::not_found("episode", id.to_string()))?;
    Ok(EpisodeHead {
        policy: r.s("policy")?,
        task: r.os("task")?,
        length: r.i("length")?,
        label: r.s("label")?.parse()?,
        revision: r.i("label_revision")?,
    })
}

async fn campaign_in(tx: &mut Tx, policy: &str) -> Result<Campaign, StoreError> {
    let r =
        sqlx::query("SELECT labels_needed, blind, updated_by, updated_at FROM campaigns WHERE policy = $1")
            .bind(policy)
            .fetch_optional(&mut **tx)
            .await?;
    campaign_from(policy, r)
}

fn campaign_from(policy: &str, r: Option<sqlx::any::AnyRow>) -> Result<Campaign, StoreError> {
    Ok(match r {
        Some(r) => Campaign {
            policy: policy.to_string(),
            labels_needed: r.i("labels_needed")?,
            blind: r.i("blind")? != 0,
            updated_by: Some(r.s("updated_by")?),
            updated_at: Some(r.s("updated_at")?),
        },
        None => Campaign {
            policy: policy.to_string(),
            labels_needed: 1,
            blind: false,
            updated_by: None,
            updated_at: None,
        },
    })
}

async fn votes_in(tx: &mut Tx, id: &str) -> Result<Vec<Vote>, StoreError> {
    let rows = sqlx::query(
        "SELECT actor, label, data, note, created_at FROM label_votes WHERE episode_id = $1 ORDER BY id",
    )
    .bind(id)
    .fetch_all(&mut **tx)
    .await?;
    rows.iter().map(vote_from_row).collect()
}

/// How long the set of multi-labeler policies is trusted without reading `campaigns` again.
pub const CAMPAIGN_CACHE_TTL: std::time::Duration = std::time::Duration::from_secs(1);

/// The policies whose campaign needs several labelers, and when they were read.
#[derive(Default)]
struct MultiLabelerCache(std::sync::Mutex<Option<(std::time::Instant, Arc<HashSet<String>>)>>);

impl MultiLabelerCache {
    fn fresh(&self) -> Option<Arc<HashSet<String>>> {
        let g = self.0.lock().unwrap_or_else(|e| e.into_inner());
        g.as_ref().filter(|(at, _)| at.elapsed() < CAMPAIGN_CACHE_TTL).map(|(_, p)| p.clone())
    }
    fn store(&self, policies: Arc<HashSet<String>>) {
        *self.0.lock().unwrap_or_else(|e| e.into_inner()) = Some((std::time::Instant::now(), policies));
    }
    fn clear(&self) {
        *self.0.lock().unwrap_or_else(|e| e.into_inner()) = None;
    }
}

/// Whether the latest label event of the episode is an adjudication newer than its latest vote.
async fn adjudicated_after_votes(tx: &mut Tx, id: &str) -> Result<bool, StoreError> {
    let r = sqlx::query(
        "SELECT (SELECT MAX(id) FROM label_events WHERE episode_id = $1 AND source = 'adjudication') AS adj, \
         (SELECT MAX(id) FROM label_events WHERE episode_id = $1) AS last_event, \
         (SELECT MAX(created_at) FROM label_votes WHERE episode_id = $1) AS last_vote, \
         (SELECT MAX(created_at) FROM label_events WHERE episode_id = $1 AND source = 'adjudication') AS adj_at",
    )
    .bind(id)
    .fetch_one(&mut **tx)
    .await?;
    let (adj, last) = (r.oi("adj")?, r.oi("last_event")?);
    Ok(adj.is_some() && adj == last && r.os("adj_at")? >= r.os("last_vote")?)
}

/// Several labelers per episode on a [`Store`]: campaign settings, failure-cause taxonomies,
/// votes, their consensus and its adjudication, and the labelers' agreement.
pub trait Consensus {
    /// A policy's campaign settings (defaults when none were set).
    fn campaign(&self, policy: &str) -> impl Future<Output = Result<Campaign, StoreError>> + Send;

    /// Whether the episode's campaign needs several labelers (a plain label write would bypass
    /// their votes). Asks the catalog only when some campaign does (the policies whose
    /// campaigns do are cached for [`CAMPAIGN_CACHE_TTL`]; this process's own campaign changes
    /// are seen at once, another server's within that time).
    fn votes_required(&self, episode_id: &str) -> impl Future<Output = Result<bool, StoreError>> + Send;

    /// Whether any campaign needs several labelers (cached as [`Consensus::votes_required`] says).
    fn any_multi_labeler_campaign(&self) -> impl Future<Output = Result<bool, StoreError>> + Send;

    /// Sets a policy's campaign settings.
    fn set_campaign(
        &self,
        policy: &str,
        labels_needed: i64,
        blind: bool,
        actor: &str,
    ) -> impl Future<Output = Result<Campaign, StoreError>> + Send;

    /// The failure causes of a task, in number-key order (the `*` taxonomy when the task has
    /// none of its own; empty when neither exists).
    fn failure_causes(&self, task: &str) -> impl Future<Output = Result<Vec<String>, StoreError>> + Send;

    /// Sets a task's failure causes (`*`: every task without its own).
    fn set_failure_causes(
        &self,
        task: &str,
        causes: &[String],
        actor: &str,
    ) -> impl Future<Output = Result<Vec<String>, StoreError>> + Send;

    /// Records one labeler's verdict; moves the episode's label when enough labelers agree.
    fn cast_vote(
        &self,
        vote: NewVote,
        actor: &str,
    ) -> impl Future<Output = Result<VoteOutcome, StoreError>> + Send;

    /// An episode's votes (each labeler's latest) and their state, unfiltered: the API hides
    /// the others' votes from a blind labeler with [`EpisodeVotes::hide_others`].
    fn episode_votes(
        &self,
        episode_id: &str,
    ) -> impl Future<Output = Result<EpisodeVotes, StoreError>> + Send;

    /// Settles an episode: its label becomes `label` (source `adjudication`); the event's data
    /// is the adjudicator's if given, else the votes'.
    fn adjudicate(
        &self,
        episode_id: &str,
        label: Label,
        data: VerdictData,
        note: Option<String>,
        actor: &str,
    ) -> impl Future<Output = Result<LabelChange, StoreError>> + Send;

    /// Disputed episodes of a policy (or all), oldest episode id first.
    fn adjudication_queue(
        &self,
        policy: Option<&str>,
        limit: usize,
    ) -> impl Future<Output = Result<Vec<Dispute>, StoreError>> + Send;

    /// Per-labeler counts, pairwise Cohen's κ and Krippendorff's α in a campaign.
    fn agreement(&self, policy: &str) -> impl Future<Output = Result<Agreement, StoreError>> + Send;
}

impl Consensus for Store {
    async fn campaign(&self, policy: &str) -> Result<Campaign, StoreError> {
        let r = sqlx::query(
            "SELECT labels_needed, blind, updated_by, updated_at FROM campaigns WHERE policy = $1",
        )
        .bind(policy)
        .fetch_optional(&self.catalog().pool)
        .await?;
        campaign_from(policy, r)
    }

    async fn votes_required(&self, episode_id: &str) -> Result<bool, StoreError> {
        if multi_labeler_policies(self).await?.is_empty() {
            return Ok(false);
        }
        let r = sqlx::query(
            "SELECT c.labels_needed FROM episodes e JOIN campaigns c ON c.policy = e.policy WHERE e.id = $1",
        )
        .bind(episode_id)
        .fetch_optional(&self.catalog().pool)
        .await?;
        Ok(match r {
            Some(r) => r.i("labels_needed")? > 1,
            None => false,
        })
    }

    async fn any_multi_labeler_campaign(&self) -> Result<bool, StoreError> {
        Ok(!multi_labeler_policies(self).await?.is_empty())
    }

    async fn set_campaign(
        &self,
        policy: &str,
        labels_needed: i64,
        blind: bool,
        actor: &str,
    ) -> Result<Campaign, StoreError> {
        store::model::check_name("policy", policy)?;
        store::model::check_name("actor", actor)?;
        if !(1..=MAX_LABELS_NEEDED).contains(&labels_needed) {
            return Err(StoreError::invalid(format!(
                "labels_needed must be 1 to {MAX_LABELS_NEEDED}, not {labels_needed}"
            )));
        }
        let mut tx = self.catalog().begin_write().await?;
        sqlx::query(
            "INSERT INTO campaigns (policy, labels_needed, blind, updated_by, updated_at) VALUES ($1, $2, $3, $4, $5) \
             ON CONFLICT (policy) DO UPDATE SET labels_needed = excluded.labels_needed, blind = excluded.blind, \
             updated_by = excluded.updated_by, updated_at = excluded.updated_at",
        )
        .bind(policy)
        .bind(labels_needed)
        .bind(blind as i64)
        .bind(actor)
        .bind(now_rfc3339())
        .execute(&mut *tx)
        .await?;
        let c = campaign_in(&mut tx, policy).await?;
        let event = NewEvent::new(
            EventKind::CampaignSet,
            policy,
            json!({"labels_needed": labels_needed, "blind": blind, "actor": actor}),
        )
        .of(policy, None);
        self.commit_with_events(tx, &[event]).await?;
        self.extension::<MultiLabelerCache>().clear();
        Ok(c)
    }

    async fn failure_causes(&self, task: &str) -> Result<Vec<String>, StoreError> {
        let rows = sqlx::query("SELECT task, causes FROM failure_causes WHERE task = $1 OR task = '*'")
            .bind(task)
            .fetch_all(&self.catalog().pool)
            .await?;
        let pick = rows.iter().find(|r| r.s("task").ok().as_deref() == Some(task)).or_else(|| rows.first());
        match pick {
            Some(r) => serde_json::from_str(&r.s("causes")?)
                .map_err(|e| StoreError::Corrupt(format!("failure causes: {e}"))),
            None => Ok(Vec::new()),
        }
    }

    async fn set_failure_causes(
        &self,
        task: &str,
        causes: &[String],
        actor: &str,
    ) -> Result<Vec<String>, StoreError> {
        store::model::check_name("task", task)?;
        store::model::check_name("actor", actor)?;
        if causes.len() > MAX_FAILURE_CAUSES {
            return Err(StoreError::invalid(format!(
                "at most {MAX_FAILURE_CAUSES} failure causes (one number key each)"
            )));
        }
        for (i, c) in causes.iter().enumerate() {
            store::model::check_name("failure cause", c)?;
            if causes[..i].contains(c) {
                return Err(StoreError::invalid(format!("failure cause {c:?} is listed twice")));
            }
        }
        let text = serde_json::to_string(causes).map_err(|e| StoreError::invalid(e.to_string()))?;
        let mut tx = self.catalog().begin_write().await?;
        sqlx::query(
            "INSERT INTO failure_causes (task, causes, updated_by, updated_at) VALUES ($1, $2, $3, $4) \
             ON CONFLICT (task) DO UPDATE SET causes = excluded.causes, updated_by = excluded.updated_by, \
             updated_at = excluded.updated_at",
        )
        .bind(task)
        .bind(&text)
        .bind(actor)
        .bind(now_rfc3339())
        .execute(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(causes.to_vec())
    }

    async fn cast_vote(&self, vote: NewVote, actor: &str) -> Result<VoteOutcome, StoreError> {
        store::model::check_name("actor", actor)?;
        if vote.note.as_ref().is_some_and(|n| n.len() > 4000) {
            return Err(StoreError::invalid("label note is longer than 4000 bytes"));
        }
        let backend = self.backend();
        // The taxonomy is read outside the write transaction (SQLite has one connection writing).
        let pre = {
            let mut tx = self.catalog().pool.begin().await?;
            let h = episode_head(&mut tx, Backend::Sqlite, &vote.episode_id).await?;
            tx.rollback().await?;
            h
        };
        check_data(self, &pre, vote.label, &vote.data).await?;
        let mut tx = self.catalog().begin_write().await?;
        let head = episode_head(&mut tx, backend, &vote.episode_id).await?;
        let campaign = campaign_in(&mut tx, &head.policy).await?;
        let data_text = if vote.data.is_empty() {
            None
        } else {
            Some(serde_json::to_string(&vote.data).expect("plain data"))
        };
        sqlx::query(
            "INSERT INTO label_votes (episode_id, actor, label, data, note, created_at) VALUES ($1, $2, $3, $4, $5, $6)",
        )
        .bind(&vote.episode_id)
        .bind(actor)
        .bind(vote.label.as_str())
        .bind(data_text)
        .bind(vote.note.clone())
        .bind(now_rfc3339())
        .execute(&mut *tx)
        .await?;
        let latest = latest_by_actor(votes_in(&mut tx, &vote.episode_id).await?);
        let state = state_of(&latest, campaign.labels_needed, false);
        let mut events = vec![NewEvent::new(
            EventKind::VoteCast,
            vote.episode_id.clone(),
            json!({"label": vote.label.as_str(), "actor": actor, "state": state, "voters": latest.len()}),
        )
        .of(&head.policy, None)];
        let mut out = VoteOutcome {
            state,
            voters: latest.len(),
            labels_needed: campaign.labels_needed,
            label: head.label,
            revision: head.revision,
            change: None,
        };
        // The vote that completes the agreement writes the label; later agreeing votes only
        // when the label is not (or no longer) the agreed verdict.
        let completes = latest.len() as i64 == campaign.labels_needed;
        if state == ConsensusState::Agreed && (completes || head.label != vote.label) {
            let (source, data, expect) = if campaign.labels_needed == 1 {
                ("human", serde_json::to_value(&vote.data).expect("plain data"), vote.expect_revision)
            } else {
                ("consensus", merged_data(&latest), None)
            };
            let data = if campaign.labels_needed == 1 && vote.data.is_empty() { None } else { Some(data) };
            let update = LabelUpdate {
                episode_id: vote.episode_id.clone(),
                label: vote.label,
                expect_revision: expect,
                note: vote.note.clone(),
            };
            let change = write_label(&mut tx, backend, &update, actor, source, data, &mut events).await?;
            out.label = change.label;
            out.revision = change.revision;
            out.change = Some(change);
        }
        self.commit_with_events(tx, &events).await?;
        Ok(out)
    }

    async fn episode_votes(&self, episode_id: &str) -> Result<EpisodeVotes, StoreError> {
        let mut tx = self.catalog().pool.begin().await?;
        let head = episode_head(&mut tx, Backend::Sqlite, episode_id).await?;
        let campaign = campaign_in(&mut tx, &head.policy).await?;
        let latest = latest_by_actor(votes_in(&mut tx, episode_id).await?);
        let adjudicated = adjudicated_after_votes(&mut tx, episode_id).await?;
        tx.rollback().await?;
        Ok(EpisodeVotes {
            episode_id: episode_id.to_string(),
            policy: head.policy,
            labels_needed: campaign.labels_needed,
            blind: campaign.blind,
            state: state_of(&latest, campaign.labels_needed, adjudicated),
            voters: latest.len(),
            votes: latest,
            hidden: false,
        })
    }

    async fn adjudicate(
        &self,
        episode_id: &str,
        label: Label,
        data: VerdictData,
        note: Option<String>,
        actor: &str,
    ) -> Result<LabelChange, StoreError> {
        store::model::check_name("actor", actor)?;
        if note.as_ref().is_some_and(|n| n.len() > 4000) {
            return Err(StoreError::invalid("label note is longer than 4000 bytes"));
        }
        let pre = {
            let mut tx = self.catalog().pool.begin().await?;
            let h = episode_head(&mut tx, Backend::Sqlite, episode_id).await?;
            tx.rollback().await?;
            h
        };
        check_data(self, &pre, label, &data).await?;
        let backend = self.backend();
        let mut tx = self.catalog().begin_write().await?;
        episode_head(&mut tx, backend, episode_id).await?;
        let latest = latest_by_actor(votes_in(&mut tx, episode_id).await?);
        let mut d = merged_data(&latest);
        if !data.is_empty() {
            d = json!({"failure_cause": data.failure_cause, "spans": data.spans, "votes": d["votes"]});
        }
        let update = LabelUpdate { episode_id: episode_id.to_string(), label, expect_revision: None, note };
        let mut events = Vec::new();
        let change =
            write_label(&mut tx, backend, &update, actor, "adjudication", Some(d), &mut events).await?;
        self.commit_with_events(tx, &events).await?;
        Ok(change)
    }

    async fn adjudication_queue(
        &self,
        policy: Option<&str>,
        limit: usize,
    ) -> Result<Vec<Dispute>, StoreError> {
        let votes = policy_votes(self, policy).await?;
        let mut out = Vec::new();
        let mut tx = self.catalog().pool.begin().await?;
        for (id, (pol, label, revision, latest)) in votes {
            if out.len() >= limit {
                break;
            }
            let needed = campaign_in(&mut tx, &pol).await?.labels_needed;
            if state_of(&latest, needed, false) != ConsensusState::Disputed {
                continue;
            }
            if adjudicated_after_votes(&mut tx, &id).await? {
                continue;
            }
            out.push(Dispute { episode_id: id, policy: pol, label, label_revision: revision, votes: latest });
        }
        tx.rollback().await?;
        Ok(out)
    }

    async fn agreement(&self, policy: &str) -> Result<Agreement, StoreError> {
        let campaign = self.campaign(policy).await?;
        let votes = policy_votes(self, Some(policy)).await?;
        let mut counts: BTreeMap<String, LabelerCounts> = BTreeMap::new();
        let mut by_pair: BTreeMap<(String, String), Vec<(Label, Label)>> = BTreeMap::new();
        let mut units: Vec<Vec<&'static str>> = Vec::new();
        let mut agg = Agreement {
            policy: policy.to_string(),
            labels_needed: campaign.labels_needed,
            episodes_voted: votes.len() as u64,
            agreed: 0,
            disputed: 0,
            settled: 0,
            pending: 0,
            labelers: Vec::new(),
            pairs: Vec::new(),
            krippendorff_alpha: None,
        };
        let mut tx = self.catalog().pool.begin().await?;
        for (id, (_, _, _, latest)) in &votes {
            let mut state = state_of(latest, campaign.labels_needed, false);
            if state == ConsensusState::Disputed && adjudicated_after_votes(&mut tx, id).await? {
                state = ConsensusState::Settled;
            }
            match state {
                ConsensusState::Agreed => agg.agreed += 1,
                ConsensusState::Disputed => agg.disputed += 1,
                ConsensusState::Settled => agg.settled += 1,
                ConsensusState::Pending => agg.pending += 1,
            }
            for v in latest {
                let c = counts.entry(v.actor.clone()).or_insert_with(|| LabelerCounts {
                    actor: v.actor.clone(),
                    votes: 0,
                    success: 0,
                    failure: 0,
                    unknown: 0,
                });
                c.votes += 1;
                match v.label {
                    Label::Success => c.success += 1,
                    Label::Failure => c.failure += 1,
                    Label::Unknown => c.unknown += 1,
                }
            }
            // `latest` is sorted by actor, so (a, b) pairs come with a < b.
            for (i, a) in latest.iter().enumerate() {
                for b in &latest[i + 1..] {
                    by_pair.entry((a.actor.clone(), b.actor.clone())).or_default().push((a.label, b.label));
                }
            }
            units.push(latest.iter().map(|v| v.label.as_str()).collect());
        }
        tx.rollback().await?;
        let actors: Vec<String> = counts.keys().cloned().collect();
        for (i, a) in actors.iter().enumerate() {
            for b in &actors[i + 1..] {
                let pairs = by_pair.remove(&(a.clone(), b.clone())).unwrap_or_default();
                let same = pairs.iter().filter(|(x, y)| x == y).count();
                let labels: Vec<(&str, &str)> = pairs.iter().map(|(x, y)| (x.as_str(), y.as_str())).collect();
                agg.pairs.push(PairAgreement {
                    a: a.clone(),
                    b: b.clone(),
                    episodes: pairs.len() as u64,
                    observed: (!pairs.is_empty()).then(|| same as f64 / pairs.len() as f64),
                    kappa: evalstats::cohen_kappa(&labels),
                });
            }
        }
        agg.labelers = counts.into_values().collect();
        agg.krippendorff_alpha = evalstats::krippendorff_alpha_nominal(&units);
        Ok(agg)
    }
}

/// The policies whose campaign needs several labelers, from the cache when it is fresh.
async fn multi_labeler_policies(store: &Store) -> Result<Arc<HashSet<String>>, StoreError> {
    let cache = store.extension::<MultiLabelerCache>();
    if let Some(p) = cache.fresh() {
        return Ok(p);
    }
    let rows = sqlx::query("SELECT policy FROM campaigns WHERE labels_needed > 1")
        .fetch_all(&store.catalog().pool)
        .await?;
    let policies = Arc::new(rows.iter().map(|r| r.s("policy")).collect::<Result<HashSet<_>, _>>()?);
    cache.store(policies.clone());
    Ok(policies)
}

/// Checks a verdict's data against the episode: the cause is in the task's taxonomy and
/// goes with a failure, spans lie inside the episode.
async fn check_data(
    store: &Store,
    head: &EpisodeHead,
    label: Label,
    d: &VerdictData,
) -> Result<(), StoreError> {
    if let Some(c) = &d.failure_cause {
        if label != Label::Failure {
            return Err(StoreError::invalid("a failure cause goes with a failure verdict"));
        }
        let causes = store.failure_causes(head.task.as_deref().unwrap_or("*")).await?;
        if !causes.contains(c) {
            // The taxonomy is the campaign's state, not the request's shape: 409.
            return Err(StoreError::Conflict(format!(
                "{c:?} is not a failure cause of this task (causes: {causes:?})"
            )));
        }
    }
    if d.spans.len() > MAX_SPANS {
        return Err(StoreError::invalid(format!("at most {MAX_SPANS} spans per verdict")));
    }
    for s in &d.spans {
        if s.start_step < 0 || s.end_step < s.start_step {
            return Err(StoreError::invalid(format!(
                "span {}..{}: steps from 0, start before end",
                s.start_step, s.end_step
            )));
        }
        if s.end_step >= head.length {
            // The episode's length is its state: a span past its end is a conflict (409).
            return Err(StoreError::Conflict(format!(
                "span {}..{} is not inside the episode's steps 0..{}",
                s.start_step,
                s.end_step,
                head.length - 1
            )));
        }
    }
    Ok(())
}

/// Each labeler's latest vote per episode of a policy (or all): id → (policy, label,
/// revision, votes).
#[allow(clippy::type_complexity)]
async fn policy_votes(
    store: &Store,
    policy: Option<&str>,
) -> Result<BTreeMap<String, (String, Label, i64, Vec<Vote>)>, StoreError> {
    let rows = sqlx::query(
        "SELECT v.episode_id, e.policy, e.label AS episode_label, e.label_revision, v.actor, v.label, v.data, v.note, \
         v.created_at FROM label_votes v JOIN episodes e ON e.id = v.episode_id \
         WHERE e.version_removed IS NULL AND (CAST($1 AS TEXT) IS NULL OR e.policy = $1) ORDER BY v.id",
    )
    .bind(policy)
    .fetch_all(&store.catalog().pool)
    .await?;
    let mut all: BTreeMap<String, (String, Label, i64, Vec<Vote>)> = BTreeMap::new();
    for r in &rows {
        let e = all.entry(r.s("episode_id")?).or_insert((
            r.s("policy")?,
            r.s("episode_label")?.parse()?,
            r.i("label_revision")?,
            Vec::new(),
        ));
        e.3.push(vote_from_row(r)?);
    }
    for e in all.values_mut() {
        e.3 = latest_by_actor(std::mem::take(&mut e.3));
    }
    Ok(all)
}
