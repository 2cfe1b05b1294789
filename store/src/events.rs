//! The change feed: every catalog change is an event with a sequence number, written in the
//! transaction that makes the change.
//!
//! A write path collects its [`NewEvent`]s and ends with [`Store::commit_with_events`], which
//! appends them as its last statement and commits. Sequence numbers come from the one row of
//! `event_head`: the update that takes them locks it until the commit, so numbers are handed out
//! in commit order (a reader that saw N never later finds a new event below N), and because it is
//! the last statement no transaction waits for another lock while holding it. Readers page with
//! [`Store::events_after`]; a server learns of its own commits at once through
//! [`Store::feed_watch`] and of other servers' by asking again. Retention
//! ([`Store::prune_events`]) deletes old events and remembers the highest number it deleted, so
//! a reader behind it gets [`StoreError::Gone`] instead of a silent gap.
//!
//! A request served under [`with_request`] with an idempotency key also marks that key as
//! committed in the same transaction (`idempotency.rs`): a retry after a crash then knows the
//! work was done even though the response was never stored.

use crate::catalog::{RowExt, Tx};
use crate::{now_ms, now_rfc3339, Store, StoreError};
use serde::{Deserialize, Serialize};

/// What changed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub enum EventKind {
    /// A source's episodes were committed as a new version (subject: the source's sha256).
    #[serde(rename = "ingest.committed")]
    IngestCommitted,
    /// An episode's label was written (subject: the episode id).
    #[serde(rename = "label.set")]
    LabelSet,
    /// A labeler's vote on an episode was recorded (subject: the episode id).
    #[serde(rename = "vote.cast")]
    VoteCast,
    /// A new store version (subject: its number).
    #[serde(rename = "version.created")]
    VersionCreated,
    /// A split was frozen (subject: the split id).
    #[serde(rename = "split.frozen")]
    SplitFrozen,
    /// A job was queued or changed state (subject: the job id; `data.state`).
    #[serde(rename = "job.changed")]
    JobChanged,
    /// A verifier artifact was published (subject: the artifact id).
    #[serde(rename = "artifact.published")]
    ArtifactPublished,
    /// An alias of an artifact, a monitor or a policy moved (subject: the alias's name;
    /// `data.target` says which).
    #[serde(rename = "alias.moved")]
    AliasMoved,
    /// An export job finished and its files are in the store (subject: the job id).
    #[serde(rename = "export.finished")]
    ExportFinished,
    /// A failure monitor was calibrated (subject: the monitor id).
    #[serde(rename = "monitor.created")]
    MonitorCreated,
    /// A checkpoint's review queue was scored by an artifact (subject: the artifact id).
    #[serde(rename = "review.scored")]
    ReviewScored,
    /// A policy's labeling campaign settings changed (subject: the policy).
    #[serde(rename = "campaign.set")]
    CampaignSet,
    /// An API token was created or revoked (subject: the token id; never its secret).
    #[serde(rename = "token.changed")]
    TokenChanged,
    /// An automation was declared (subject: its id; `data`: its rule and parameters).
    #[serde(rename = "automation.created")]
    AutomationCreated,
    /// An automation was deleted (subject: its id).
    #[serde(rename = "automation.deleted")]
    AutomationDeleted,
    /// An automation queued a job (subject: its id; `data`: rule, target, job id and kind, and
    /// the event that decided it).
    #[serde(rename = "automation.fired")]
    AutomationFired,
}

impl EventKind {
    pub const ALL: [EventKind; 16] = [
        EventKind::IngestCommitted,
        EventKind::LabelSet,
        EventKind::VoteCast,
        EventKind::VersionCreated,
        EventKind::SplitFrozen,
        EventKind::JobChanged,
        EventKind::ArtifactPublished,
        EventKind::AliasMoved,
        EventKind::ExportFinished,
        EventKind::MonitorCreated,
        EventKind::ReviewScored,
        EventKind::CampaignSet,
        EventKind::TokenChanged,
        EventKind::AutomationCreated,
        EventKind::AutomationDeleted,
        EventKind::AutomationFired,
    ];

    pub fn as_str(self) -> &'static str {
        match self {
            EventKind::IngestCommitted => "ingest.committed",
            EventKind::LabelSet => "label.set",
            EventKind::VoteCast => "vote.cast",
            EventKind::VersionCreated => "version.created",
            EventKind::SplitFrozen => "split.frozen",
            EventKind::JobChanged => "job.changed",
            EventKind::ArtifactPublished => "artifact.published",
            EventKind::AliasMoved => "alias.moved",
            EventKind::ExportFinished => "export.finished",
            EventKind::MonitorCreated => "monitor.created",
            EventKind::ReviewScored => "review.scored",
            EventKind::CampaignSet => "campaign.set",
            EventKind::TokenChanged => "token.changed",
            EventKind::AutomationCreated => "automation.created",
            EventKind::AutomationDeleted => "automation.deleted",
            EventKind::AutomationFired => "automation.fired",
        }
    }
}

impl std::str::FromStr for EventKind {
    type Err = StoreError;
    fn from_str(s: &str) -> Result<Self, StoreError> {
        EventKind::ALL.into_iter().find(|k| k.as_str() == s).ok_or_else(|| {
            let all: Vec<&str> = EventKind::ALL.iter().map(|k| k.as_str()).collect();
            StoreError::invalid(format!("unknown event kind {s:?}: expected one of {}", all.join(", ")))
        })
    }
}

/// An event a write path records; numbered when its transaction commits.
#[derive(Debug, Clone)]
pub struct NewEvent {
    pub kind: EventKind,
    pub subject: String,
    pub policy: Option<String>,
    pub checkpoint: Option<String>,
    pub data: serde_json::Value,
}

impl NewEvent {
    pub fn new(kind: EventKind, subject: impl Into<String>, data: serde_json::Value) -> Self {
        NewEvent { kind, subject: subject.into(), policy: None, checkpoint: None, data }
    }

    /// The policy (and checkpoint) the change belongs to, for filtering.
    pub fn of(mut self, policy: &str, checkpoint: Option<&str>) -> Self {
        self.policy = Some(policy.to_string());
        self.checkpoint = checkpoint.map(str::to_string);
        self
    }
}

/// One event of the feed.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct Event {
    /// Its place in the feed: increasing in commit order, never reused.
    pub seq: i64,
    pub kind: EventKind,
    pub subject: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub policy: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub checkpoint: Option<String>,
    /// What changed, per kind (documented in api/README.md, *Change feed*).
    #[cfg_attr(feature = "openapi", schema(value_type = Object))]
    pub data: serde_json::Value,
    pub created_at: String,
}

/// A page of the feed.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct EventPage {
    /// Events after the requested sequence number, oldest first.
    pub events: Vec<Event>,
    /// Where to continue from: the last event's `seq`, or the request's `after` when none
    /// matched (with a filter, the highest number looked at).
    pub next: i64,
    /// The feed's newest sequence number when this page was read.
    pub head: i64,
}

/// Which events a reader wants.
#[derive(Debug, Clone, Default)]
pub struct EventFilter {
    /// Only these kinds (empty: all).
    pub kinds: Vec<EventKind>,
    pub policy: Option<String>,
}

/// The largest page [`Store::events_after`] returns.
pub const MAX_EVENT_PAGE: i64 = 1000;

tokio::task_local! {
    static REQUEST: RequestContext;
}

/// What a request that is writing tells the write paths under it (see [`with_request`]).
#[derive(Debug, Clone, Default)]
pub struct RequestContext {
    /// `(principal, key)` of the request's `Idempotency-Key`.
    pub idempotency: Option<(String, String)>,
}

/// Runs `f` with `ctx` visible to every catalog write it makes on this task: a write that
/// records events also marks the request's idempotency key committed, in its transaction.
pub async fn with_request<F: std::future::Future>(ctx: RequestContext, f: F) -> F::Output {
    REQUEST.scope(ctx, f).await
}

/// Appends `events` as the transaction's last statement; returns the last sequence number.
pub(crate) async fn append(tx: &mut Tx, events: &[NewEvent]) -> Result<Option<i64>, StoreError> {
    if events.is_empty() {
        return Ok(None);
    }
    let n = events.len() as i64;
    let last = sqlx::query("UPDATE event_head SET seq = seq + $1 WHERE id = 1 RETURNING seq")
        .bind(n)
        .fetch_one(&mut **tx)
        .await?
        .i("seq")?;
    let (now, ms) = (now_rfc3339(), now_ms());
    // Rows of 8 values, a statement per 64 rows (well under either backend's bind limit).
    for (c, chunk) in events.chunks(64).enumerate() {
        let mut sql = String::from(
            "INSERT INTO events (seq, kind, subject, policy, checkpoint, data, created_at, created_ms) VALUES ",
        );
        for i in 0..chunk.len() {
            let b = i * 8;
            if i > 0 {
                sql.push(',');
            }
            sql.push_str(&format!(
                "(${}, ${}, ${}, ${}, ${}, ${}, ${}, ${})",
                b + 1,
                b + 2,
                b + 3,
                b + 4,
                b + 5,
                b + 6,
                b + 7,
                b + 8
            ));
        }
        let mut q = sqlx::query(&sql);
        for (i, e) in chunk.iter().enumerate() {
            let seq = last - n + 1 + (c * 64 + i) as i64;
            q = q
                .bind(seq)
                .bind(e.kind.as_str())
                .bind(e.subject.clone())
                .bind(e.policy.clone())
                .bind(e.checkpoint.clone())
                .bind(serde_json::to_string(&e.data)?)
                .bind(now.clone())
                .bind(ms);
        }
        q.execute(&mut **tx).await?;
    }
    if let Ok(Some((principal, key))) = REQUEST.try_with(|c| c.idempotency.clone()) {
        crate::idempotency::mark_committed(tx, &principal, &key, last).await?;
    }
    Ok(Some(last))
}

fn event_from_row(r: &sqlx::any::AnyRow) -> Result<Event, StoreError> {
    Ok(Event {
        seq: r.i("seq")?,
        kind: r.s("kind")?.parse().map_err(|_| StoreError::Corrupt("unknown event kind".into()))?,
        subject: r.s("subject")?,
        policy: r.os("policy")?,
        checkpoint: r.os("checkpoint")?,
        data: serde_json::from_str(&r.s("data")?)
            .map_err(|e| StoreError::Corrupt(format!("event data: {e}")))?,
        created_at: r.s("created_at")?,
    })
}

impl Store {
    /// Appends `events` (numbered in commit order) and commits `tx`; the feed's watchers on this
    /// store hear of it at once.
    pub async fn commit_with_events(&self, mut tx: Tx, events: &[NewEvent]) -> Result<(), StoreError> {
        let last = append(&mut tx, events).await?;
        tx.commit().await?;
        if let Some(seq) = last {
            self.notify_feed(seq);
        }
        Ok(())
    }

    pub(crate) fn notify_feed(&self, seq: i64) {
        self.inner.feed.send_if_modified(|v| {
            let newer = seq > *v;
            if newer {
                *v = seq;
            }
            newer
        });
    }

    /// The highest sequence number this process has seen committed; changes when this store
    /// handle commits events (others' commits are seen by reading the feed).
    pub fn feed_watch(&self) -> tokio::sync::watch::Receiver<i64> {
        self.inner.feed.subscribe()
    }

    /// The feed's newest sequence number and the highest one retention deleted.
    pub async fn event_head(&self) -> Result<(i64, i64), StoreError> {
        let r = sqlx::query("SELECT seq, pruned_through FROM event_head WHERE id = 1")
            .fetch_one(&self.catalog().pool)
            .await?;
        Ok((r.i("seq")?, r.i("pruned_through")?))
    }

    /// Events after `after` matching `filter`, oldest first, at most `limit` (≤
    /// [`MAX_EVENT_PAGE`]). [`StoreError::Gone`] when retention deleted events after `after`.
    pub async fn events_after(
        &self,
        after: i64,
        limit: i64,
        filter: &EventFilter,
    ) -> Result<EventPage, StoreError> {
        let limit = limit.clamp(1, MAX_EVENT_PAGE);
        // One statement (one snapshot, one round trip): the head row, joined to the events
        // after `after` up to it; a row with no event when none matches.
        let mut sql = String::from(
            "SELECT h.seq AS head_seq, h.pruned_through, e.seq, e.kind, e.subject, e.policy, e.checkpoint, e.data, \
             e.created_at FROM event_head h LEFT JOIN events e ON e.seq > $1 AND e.seq <= h.seq \
             AND ($2 = '' OR e.policy = $2)",
        );
        if !filter.kinds.is_empty() {
            let list: Vec<String> = (0..filter.kinds.len()).map(|i| format!("${}", i + 4)).collect();
            sql.push_str(&format!(" AND e.kind IN ({})", list.join(", ")));
        }
        sql.push_str(" WHERE h.id = 1 ORDER BY e.seq LIMIT $3");
        let mut q = sqlx::query(&sql).bind(after).bind(filter.policy.clone().unwrap_or_default()).bind(limit);
        for k in &filter.kinds {
            q = q.bind(k.as_str());
        }
        let rows = q.fetch_all(&self.catalog().pool).await?;
        let first =
            rows.first().ok_or_else(|| StoreError::Corrupt("the event_head row is missing".into()))?;
        let (head, pruned_through) = (first.i("head_seq")?, first.i("pruned_through")?);
        if after < pruned_through {
            return Err(StoreError::Gone(format!(
                "events up to {pruned_through} were deleted by retention; read from after={pruned_through} \
                 (and re-read current state: changes between {after} and {pruned_through} are gone)"
            )));
        }
        let mut events = Vec::with_capacity(rows.len());
        for r in &rows {
            if r.oi("seq")?.is_some() {
                events.push(event_from_row(r)?);
            }
        }
        // A short page looked at everything up to the head.
        let next = match events.last() {
            Some(e) if events.len() as i64 == limit => e.seq,
            _ => head.max(after),
        };
        Ok(EventPage { events, next, head })
    }

    /// [`Self::events_after`], waiting up to `wait` when nothing matches yet (long polling):
    /// returns as soon as a matching event commits. This process's commits wake it at once,
    /// other processes' within `poll`. An empty page comes only after `wait` without one.
    pub async fn wait_for_events(
        &self,
        mut after: i64,
        limit: i64,
        filter: &EventFilter,
        wait: std::time::Duration,
        poll: std::time::Duration,
    ) -> Result<EventPage, StoreError> {
        let deadline = tokio::time::Instant::now() + wait;
        let mut commits = self.feed_watch();
        loop {
            // Before the read: a commit after it wakes the wait below at once.
            commits.mark_unchanged();
            let page = self.events_after(after, limit, filter).await?;
            let left = deadline.saturating_duration_since(tokio::time::Instant::now());
            if !page.events.is_empty() || left.is_zero() {
                return Ok(page);
            }
            // Nothing yet: everything up to the head was looked at.
            after = page.next;
            tokio::select! {
                r = commits.changed() => if r.is_err() { tokio::time::sleep(left.min(poll)).await },
                _ = tokio::time::sleep(left.min(poll)) => {}
            }
        }
    }

    /// Deletes events created more than `older_than` ago and returns how many went.
    pub async fn prune_events(&self, older_than: std::time::Duration) -> Result<u64, StoreError> {
        let cutoff = now_ms() - older_than.as_millis() as i64;
        // The last event created before the cutoff, by bisection on `seq` (`created_ms` does not
        // decrease along it: both are taken under the `event_head` lock). Invariant: every
        // event up to `lo` is older than the cutoff (or gone already); none after `hi` is.
        let (head, pruned) = self.event_head().await?;
        let (mut lo, mut hi) = (pruned, head);
        while lo < hi {
            let mid = lo + (hi - lo + 1) / 2;
            let created = sqlx::query("SELECT created_ms FROM events WHERE seq >= $1 ORDER BY seq LIMIT 1")
                .bind(mid)
                .fetch_optional(&self.catalog().pool)
                .await?
                .map(|r| r.i("created_ms"))
                .transpose()?;
            match created {
                Some(ms) if ms < cutoff => lo = mid,
                _ => hi = mid - 1,
            }
        }
        if lo <= pruned {
            return Ok(0);
        }
        let mut tx = self.catalog().begin_write().await?;
        let deleted = sqlx::query("DELETE FROM events WHERE seq <= $1").bind(lo).execute(&mut *tx).await?;
        sqlx::query("UPDATE event_head SET pruned_through = $1 WHERE id = 1 AND pruned_through < $1")
            .bind(lo)
            .execute(&mut *tx)
            .await?;
        tx.commit().await?;
        Ok(deleted.rows_affected())
    }
}
