//! Labels: an append-only event log per episode (who, when, old → new, note, revision). The
//! current label is the latest event; optimistic concurrency via the expected revision.

use crate::catalog::{RowExt, Tx};
use crate::events::{EventKind, NewEvent};
use crate::versioning::counts::CountDeltas;
use crate::versioning::version::{
    finish_version, next_version, unfrozen_episodes, write_labels_file_ahead, LabelsFileAhead, VersionHead,
};
use crate::{now_rfc3339, Backend, CommitInfo, Label, Store, StoreError};
use serde::Serialize;

/// A label snapshot's labels file (the labels changed since the head), written ahead of the
/// version lock ([`Store::prepare_label_snapshot`]); commit it with [`Store::commit_label_snapshot`].
pub struct PreparedLabelSnapshot(LabelsFileAhead);

#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct LabelEvent {
    pub episode_id: String,
    pub revision: i64,
    pub old_label: Option<Label>,
    pub new_label: Label,
    pub source: String,
    pub actor: String,
    pub note: Option<String>,
    pub created_at: String,
    /// What the verdict carries besides the label (a failure cause, time spans, the votes it
    /// agreed from), as JSON; `None` for a plain label write.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub data: Option<serde_json::Value>,
}

/// One requested label change.
#[derive(Debug, Clone)]
pub struct LabelUpdate {
    pub episode_id: String,
    pub label: Label,
    /// Fail with a conflict unless the episode is at this revision.
    pub expect_revision: Option<i64>,
    pub note: Option<String>,
}

#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct LabelChange {
    pub episode_id: String,
    pub old_label: Label,
    pub label: Label,
    pub revision: i64,
    pub actor: String,
    pub changed: bool,
}

impl Store {
    /// Sets one episode's label (source `human` unless given), recording an audit event.
    pub async fn set_label(
        &self,
        update: LabelUpdate,
        actor: &str,
        source: &str,
    ) -> Result<LabelChange, StoreError> {
        let mut v = self.set_labels(vec![update], actor, source).await?;
        Ok(v.remove(0))
    }

    /// Sets many labels in one transaction: all succeed or none does.
    pub async fn set_labels(
        &self,
        updates: Vec<LabelUpdate>,
        actor: &str,
        source: &str,
    ) -> Result<Vec<LabelChange>, StoreError> {
        crate::model::check_name("actor", actor)?;
        if updates.is_empty() {
            return Ok(Vec::new());
        }
        let backend = self.backend();
        let mut tx = self.catalog().begin_write().await?;
        let mut out = Vec::with_capacity(updates.len());
        let mut counts = CountDeltas::default();
        let mut events = Vec::new();
        for u in updates {
            out.push(apply_one(&mut tx, backend, &u, actor, source, &mut counts, &mut events).await?);
        }
        counts.apply(&mut tx, backend).await?;
        self.commit_with_events(tx, &events).await?;
        Ok(out)
    }

    /// Group commit: many independent label writes `(update, actor)` in ONE transaction, each
    /// with its own outcome. An item that fails on its own (stale revision → `LabelConflict`,
    /// unknown episode, invalid note or actor) writes nothing and does not affect the others;
    /// the rest commit together, each with its audit event. Items run in the given order
    /// (on Postgres sorted by episode id, stably, so two batches lock rows in the same order),
    /// so two writes to one episode in a batch behave as if sent one after the other.
    /// `Err` (a catalog error) means nothing was committed.
    pub async fn set_labels_each(
        &self,
        items: Vec<(LabelUpdate, String)>,
        source: &str,
    ) -> Result<Vec<Result<LabelChange, StoreError>>, StoreError> {
        if items.is_empty() {
            return Ok(Vec::new());
        }
        let backend = self.backend();
        let mut order: Vec<usize> = (0..items.len()).collect();
        if backend == Backend::Postgres {
            order.sort_by(|&a, &b| items[a].0.episode_id.cmp(&items[b].0.episode_id));
        }
        let mut out: Vec<Option<Result<LabelChange, StoreError>>> = (0..items.len()).map(|_| None).collect();
        let mut tx = self.catalog().begin_write().await?;
        let mut counts = CountDeltas::default();
        let mut events = Vec::new();
        for i in order {
            let (u, actor) = &items[i];
            let r = match crate::model::check_name("actor", actor) {
                Ok(()) => apply_one(&mut tx, backend, u, actor, source, &mut counts, &mut events).await,
                Err(e) => Err(e),
            };
            match r {
                Err(e) if !item_error(&e) => return Err(e),
                r => out[i] = Some(r),
            }
        }
        counts.apply(&mut tx, backend).await?;
        self.commit_with_events(tx, &events).await?;
        Ok(out
            .into_iter()
            .map(|o| o.unwrap_or_else(|| Err(StoreError::Corrupt("label write without an outcome".into()))))
            .collect())
    }

    /// Every label event of an episode, oldest first.
    pub async fn label_history(&self, episode_id: &str) -> Result<Vec<LabelEvent>, StoreError> {
        let rows = sqlx::query(
            "SELECT episode_id, revision, old_label, new_label, source, actor, note, created_at, data \
             FROM label_events WHERE episode_id = $1 ORDER BY revision",
        )
        .bind(episode_id)
        .fetch_all(&self.catalog().pool)
        .await?;
        if rows.is_empty() {
            self.episode(episode_id, None).await?;
        }
        rows.iter().map(event_from_row).collect()
    }

    /// All label events after `after_id` (for replaying the audit log), with their ids.
    pub async fn label_events_since(
        &self,
        after_id: i64,
        limit: i64,
    ) -> Result<Vec<(i64, LabelEvent)>, StoreError> {
        let rows = sqlx::query(
            "SELECT id, episode_id, revision, old_label, new_label, source, actor, note, created_at, data \
             FROM label_events WHERE id > $1 ORDER BY id LIMIT $2",
        )
        .bind(after_id)
        .bind(limit)
        .fetch_all(&self.catalog().pool)
        .await?;
        rows.iter().map(|r| Ok((r.i("id")?, event_from_row(r)?))).collect()
    }

    /// Freezes the current labels into a new version.
    pub async fn snapshot_labels(&self, actor: &str, message: &str) -> Result<CommitInfo, StoreError> {
        let prepared = PreparedLabelSnapshot(write_labels_file_ahead(self).await?);
        self.commit_label_snapshot(prepared, actor, message).await
    }

    /// Freezes the current labels into a new version only if one changed since the head froze
    /// them: `(head, false)` otherwise, so a client repeating the request (or many clients) does
    /// not pile up identical versions.
    pub async fn snapshot_labels_if_changed(
        &self,
        actor: &str,
        message: &str,
    ) -> Result<(CommitInfo, bool), StoreError> {
        match self.prepare_label_snapshot().await? {
            None => Ok((self.head_commit().await?, false)),
            Some(p) => Ok((self.commit_label_snapshot(p, actor, message).await?, true)),
        }
    }

    /// A label snapshot's first step, outside the version lock: None when no label changed since
    /// the head froze them; otherwise the labels file of the changes, written to the object store
    /// now, so that label writes go on while it uploads (on SQLite the version lock stops them
    /// all). A caller that serialises writers (the API's write gate) holds its gate only for
    /// [`Store::commit_label_snapshot`].
    pub async fn prepare_label_snapshot(&self) -> Result<Option<PreparedLabelSnapshot>, StoreError> {
        if !self.labels_changed_since_head().await? && self.head_version().await? > 0 {
            return Ok(None);
        }
        Ok(Some(PreparedLabelSnapshot(write_labels_file_ahead(self).await?)))
    }

    /// A label snapshot's second step, under the version lock: the new version, freezing the
    /// labels changed since the head (its cost is theirs, not the store's), with the file written
    /// ahead if they did not change meanwhile (else with a new file).
    pub async fn commit_label_snapshot(
        &self,
        prepared: PreparedLabelSnapshot,
        actor: &str,
        message: &str,
    ) -> Result<CommitInfo, StoreError> {
        let mut tx = self.catalog().begin_version_write().await?;
        let version = next_version(&mut tx).await?;
        let head = VersionHead {
            version,
            kind: "label_snapshot",
            message: message.to_string(),
            actor: actor.to_string(),
            source_sha256: None,
            episodes_added: 0,
            episodes_removed: 0,
            events: Vec::new(),
        };
        finish_version(self, tx, head, CountDeltas::default(), Some(prepared.0)).await?;
        let info = self.version(version).await?;
        Ok(CommitInfo { version, episodes: info.episode_count as usize })
    }

    /// The head version as a commit.
    pub async fn head_commit(&self) -> Result<CommitInfo, StoreError> {
        let head = self.head_version().await?;
        let episodes = if head > 0 { self.version(head).await?.episode_count as usize } else { 0 };
        Ok(CommitInfo { version: head, episodes })
    }

    /// Whether any label changed since the head version froze them (one probe of the index of
    /// unfrozen episodes).
    pub async fn labels_changed_since_head(&self) -> Result<bool, StoreError> {
        let (from, unfrozen) = unfrozen_episodes(self.backend() == Backend::Sqlite);
        let row = sqlx::query(&format!(
            "SELECT COUNT(*) AS n FROM (SELECT e.id FROM {from} WHERE {unfrozen} LIMIT 1) x"
        ))
        .fetch_one(&self.catalog().pool)
        .await?;
        Ok(row.i("n")? > 0)
    }

    /// Removes episodes from the next version (their data stays readable in older versions).
    pub async fn delete_episodes(
        &self,
        ids: &[String],
        actor: &str,
        message: &str,
    ) -> Result<CommitInfo, StoreError> {
        let mut tx = self.catalog().begin_version_write().await?;
        let version = next_version(&mut tx).await?;
        let mut counts = CountDeltas::default();
        for id in ids {
            // The label as of the row lock: a label write either committed before (its label is
            // read here) or finds the episode gone.
            let r = sqlx::query(
                "UPDATE episodes SET version_removed = $1 WHERE id = $2 AND version_removed IS NULL \
                 RETURNING policy, checkpoint, task, label",
            )
            .bind(version)
            .bind(id)
            .fetch_optional(&mut *tx)
            .await?
            .ok_or_else(|| StoreError::not_found("episode", id.clone()))?;
            counts.add(
                &r.s("policy")?,
                &r.s("checkpoint")?,
                r.os("task")?.as_deref(),
                r.s("label")?.parse()?,
                -1,
            );
        }
        let head = VersionHead {
            version,
            kind: "delete",
            message: message.to_string(),
            actor: actor.to_string(),
            source_sha256: None,
            episodes_added: 0,
            episodes_removed: ids.len() as i64,
            events: Vec::new(),
        };
        finish_version(self, tx, head, counts, None).await?;
        let info = self.version(version).await?;
        Ok(CommitInfo { version, episodes: info.episode_count as usize })
    }
}

/// One label write on SQLite, as one multi-statement query (one hand-off to sqlx's connection
/// thread, whatever the outcome): read the episode's current label state; insert the audit event
/// from that row only if the revision matches (`RETURNING` its revision and old label); move the
/// episode row on under the same condition, tied to the insert by `changes() = 1`. The
/// transaction holds the database write lock (`BEGIN IMMEDIATE`), so the three statements see the
/// same row. The `kind` column tells the result rows apart.
const SQLITE_APPLY: &str = "\
SELECT 'current' AS kind, label_revision AS revision, label AS old_label, label_actor, label_updated_at, \
policy, checkpoint, task FROM episodes WHERE id = $1 AND version_removed IS NULL; \
INSERT INTO label_events (episode_id, revision, old_label, new_label, source, actor, note, created_at) \
SELECT id, label_revision + 1, label, $2, $3, $4, $6, $5 FROM episodes \
WHERE id = $1 AND version_removed IS NULL AND ($7 IS NULL OR label_revision = $7) \
RETURNING 'event' AS kind, revision, old_label; \
UPDATE episodes SET label = $2, label_source = $3, label_revision = label_revision + 1, label_actor = $4, \
label_updated_at = $5 \
WHERE id = $1 AND version_removed IS NULL AND ($7 IS NULL OR label_revision = $7) AND changes() = 1 \
RETURNING 'episode' AS kind, label_revision AS revision";

/// One label write on Postgres, in one statement: lock the episode row (`FOR UPDATE` re-reads the
/// newest committed version under READ COMMITTED) and return its state; move it on if the
/// revision matches; insert the audit event with the old label from the locked row. A conflict
/// writes nothing and raises no error, so the transaction stays usable for the next item.
const POSTGRES_APPLY: &str = "\
WITH cur AS (SELECT id, label, label_revision, label_actor, label_updated_at, policy, checkpoint, task FROM episodes \
WHERE id = $1 AND version_removed IS NULL FOR UPDATE), \
upd AS (UPDATE episodes e SET label = $2, label_source = $3, label_revision = e.label_revision + 1, \
label_actor = $4, label_updated_at = $5 FROM cur \
WHERE e.id = cur.id AND ($7::BIGINT IS NULL OR e.label_revision = $7::BIGINT) \
RETURNING e.id, e.label_revision, cur.label AS old_label), \
ev AS (INSERT INTO label_events (episode_id, revision, old_label, new_label, source, actor, note, created_at) \
SELECT id, label_revision, old_label, $2, $3, $4, $6, $5 FROM upd RETURNING revision, old_label) \
SELECT 'current' AS kind, cur.label_revision AS revision, cur.label AS old_label, cur.label_actor, \
cur.label_updated_at, cur.policy, cur.checkpoint, cur.task, ev.revision AS event_revision, \
ev.old_label AS event_old_label \
FROM cur LEFT JOIN ev ON TRUE";

/// Whether a failed label write concerns only that item (a group commit records it and goes on
/// with the others): nothing was written for it. Catalog errors abort the whole transaction.
fn item_error(e: &StoreError) -> bool {
    matches!(
        e,
        StoreError::Invalid(_)
            | StoreError::NotFound { .. }
            | StoreError::LabelConflict { .. }
            | StoreError::Conflict(_)
    )
}

/// Applies one label change inside `tx` in one round trip. On success the episode row and its
/// audit event are written and the count change is added to `counts` (applied by the caller
/// before it commits); on an item error (invalid note, unknown episode, stale revision) nothing is.
pub(crate) async fn apply_one(
    tx: &mut Tx,
    backend: Backend,
    u: &LabelUpdate,
    actor: &str,
    source: &str,
    counts: &mut CountDeltas,
    events: &mut Vec<NewEvent>,
) -> Result<LabelChange, StoreError> {
    if let Some(n) = &u.note {
        if n.len() > 4000 {
            return Err(StoreError::invalid("label note is longer than 4000 bytes"));
        }
    }
    let now = now_rfc3339();
    let sql = match backend {
        Backend::Sqlite => SQLITE_APPLY,
        Backend::Postgres => POSTGRES_APPLY,
    };
    // `fetch_all`, not `fetch_optional`: on SQLite every statement of the query must run.
    let rows = sqlx::query(sql)
        .bind(&u.episode_id)
        .bind(u.label.as_str())
        .bind(source)
        .bind(actor)
        .bind(&now)
        .bind(u.note.clone())
        .bind(u.expect_revision)
        .fetch_all(&mut **tx)
        .await?;
    // (revision, label, actor, at) before the write; the event's (revision, old label); the
    // episode's new revision.
    let mut current: Option<(i64, String, String, String)> = None;
    // (policy, checkpoint, task): which counts the write moves.
    let mut group: Option<(String, String, Option<String>)> = None;
    let mut event: Option<(i64, Option<String>)> = None;
    let mut episode_revision: Option<i64> = None;
    for r in &rows {
        match r.s("kind")?.as_str() {
            "current" => {
                current = Some((
                    r.i("revision")?,
                    r.s("old_label")?,
                    r.s("label_actor")?,
                    r.s("label_updated_at")?,
                ));
                group = Some((r.s("policy")?, r.s("checkpoint")?, r.os("task")?));
                if backend == Backend::Postgres {
                    // One statement: the event exists only if the episode row was updated.
                    if let Some(rev) = r.oi("event_revision")? {
                        event = Some((rev, r.os("event_old_label")?));
                        episode_revision = Some(rev);
                    }
                }
            }
            "event" => event = Some((r.i("revision")?, r.os("old_label")?)),
            _ => episode_revision = Some(r.i("revision")?),
        }
    }
    let Some((revision, label, set_by, set_at)) = current else {
        if event.is_some() || episode_revision.is_some() {
            return Err(inconsistent(u));
        }
        return Err(StoreError::not_found("episode", u.episode_id.clone()));
    };
    let current_label: Label = label.parse()?;
    match (event, episode_revision) {
        (Some((rev, old)), Some(ep_rev))
            if rev == ep_rev && rev == revision + 1 && old.as_deref() == Some(current_label.as_str()) =>
        {
            let (policy, checkpoint, task) = group.ok_or_else(|| inconsistent(u))?;
            counts.relabel(&policy, &checkpoint, task.as_deref(), current_label, u.label);
            events.push(
                NewEvent::new(
                    EventKind::LabelSet,
                    u.episode_id.clone(),
                    serde_json::json!({
                        "revision": rev,
                        "label": u.label.as_str(),
                        "old_label": current_label.as_str(),
                        "source": source,
                        "actor": actor,
                        "task": task,
                    }),
                )
                .of(&policy, Some(&checkpoint)),
            );
            Ok(LabelChange {
                episode_id: u.episode_id.clone(),
                old_label: current_label,
                label: u.label,
                revision: rev,
                actor: actor.to_string(),
                changed: current_label != u.label,
            })
        }
        (None, None) => match u.expect_revision {
            Some(expected) if expected != revision => Err(StoreError::LabelConflict {
                episode_id: u.episode_id.clone(),
                expected,
                revision,
                label: current_label,
                actor: set_by,
                at: set_at,
            }),
            // Matched when read but not written: cannot happen under the row lock / write lock;
            // report a retryable conflict rather than guess.
            _ => Err(StoreError::Conflict(format!(
                "episode {} was relabeled concurrently; reload and retry",
                u.episode_id
            ))),
        },
        // Half a write: impossible under the lock, but never let it commit.
        _ => Err(inconsistent(u)),
    }
}

/// Not an item error: the whole transaction is rolled back.
fn inconsistent(u: &LabelUpdate) -> StoreError {
    StoreError::Corrupt(format!(
        "label write on {} updated the event log and the episode inconsistently",
        u.episode_id
    ))
}

fn event_from_row(r: &sqlx::any::AnyRow) -> Result<LabelEvent, StoreError> {
    Ok(LabelEvent {
        episode_id: r.s("episode_id")?,
        revision: r.i("revision")?,
        old_label: r.os("old_label")?.map(|s| s.parse()).transpose()?,
        new_label: r.s("new_label")?.parse()?,
        source: r.s("source")?,
        actor: r.s("actor")?,
        note: r.os("note")?,
        created_at: r.s("created_at")?,
        data: match r.os("data")? {
            Some(t) => Some(
                serde_json::from_str(&t)
                    .map_err(|e| StoreError::Corrupt(format!("label event data: {e}")))?,
            ),
            None => None,
        },
    })
}

/// A label write with data, inside `tx`: the ordinary write (revision, audit event, counts) and
/// the event's data (a failure cause, spans, the votes behind a consensus), in the same
/// transaction. The labelers' protocol (`store-labeling`) writes its verdicts through it.
pub async fn write_label(
    tx: &mut Tx,
    backend: Backend,
    update: &LabelUpdate,
    actor: &str,
    source: &str,
    data: Option<serde_json::Value>,
    events: &mut Vec<NewEvent>,
) -> Result<LabelChange, StoreError> {
    let mut counts = CountDeltas::default();
    let change = apply_one(tx, backend, update, actor, source, &mut counts, events).await?;
    counts.apply(tx, backend).await?;
    if let Some(d) = data {
        sqlx::query("UPDATE label_events SET data = $1 WHERE episode_id = $2 AND revision = $3")
            .bind(d.to_string())
            .bind(&update.episode_id)
            .bind(change.revision)
            .execute(&mut **tx)
            .await?;
    }
    Ok(change)
}

impl Store {
    /// The data of the label events `(episode id, revision)` that have any (exports record the
    /// failure cause and spans behind each label), by episode id.
    pub async fn label_event_data(
        &self,
        keys: &[(String, i64)],
    ) -> Result<std::collections::HashMap<String, serde_json::Value>, StoreError> {
        let mut out = std::collections::HashMap::new();
        for chunk in keys.chunks(500) {
            let sql = format!(
                "SELECT episode_id, revision, data FROM label_events WHERE data IS NOT NULL AND episode_id IN ({})",
                crate::catalog::placeholders(chunk.len())
            );
            let mut q = sqlx::query(&sql);
            for (id, _) in chunk {
                q = q.bind(id);
            }
            let wanted: std::collections::HashMap<&str, i64> =
                chunk.iter().map(|(id, rev)| (id.as_str(), *rev)).collect();
            for r in q.fetch_all(&self.catalog().pool).await? {
                let id = r.s("episode_id")?;
                if wanted.get(id.as_str()) == Some(&r.i("revision")?) {
                    let d = serde_json::from_str(&r.s("data")?)
                        .map_err(|e| StoreError::Corrupt(format!("label event data: {e}")))?;
                    out.insert(id, d);
                }
            }
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use crate::*;

    async fn store_with_episodes(db: Backend, dir: &std::path::Path) -> (Store, Vec<String>) {
        let cfg = match db {
            Backend::Sqlite => StoreConfig::local(dir),
            Backend::Postgres => StoreConfig {
                data_dir: dir.into(),
                database_url: Some(
                    create_test_schema("labels").await.expect("the Postgres tests need a server"),
                ),
                object_store_url: None,
            },
        };
        let store = Store::open(&cfg).await.unwrap();
        let src = SourceInput {
            path: "/tmp/labels-test".into(),
            sha256: sha256_hex(b"labels-test"),
            format: "test".into(),
            size_bytes: 1,
            metadata: serde_json::json!({}),
        };
        let mut w = store.begin_ingest(src, "pol", "c1").await.unwrap();
        let mut ids = Vec::new();
        for i in 0..3u32 {
            ids.push(
                w.add_episode(crate::test_support::two_step_episode(
                    i,
                    None,
                    if i % 2 == 0 { Label::Success } else { Label::Failure },
                ))
                .await
                .unwrap(),
            );
        }
        w.commit("labels test").await.unwrap();
        (store, ids)
    }

    fn upd(id: &str, label: Label, expect: Option<i64>) -> LabelUpdate {
        LabelUpdate {
            episode_id: id.to_string(),
            label,
            expect_revision: expect,
            note: Some(label.as_str().to_string()),
        }
    }

    async fn group_commit_keeps_per_item_outcomes(db: Backend) {
        let dir = tempfile::tempdir().unwrap();
        let (store, ids) = store_with_episodes(db, dir.path()).await;
        let (a, b, c) = (&ids[0], &ids[1], &ids[2]);
        let mut long = upd(c, Label::Failure, None);
        long.note = Some("x".repeat(4001));
        let items = vec![
            (upd(a, Label::Failure, Some(1)), "alice".to_string()),
            (upd(b, Label::Success, Some(7)), "bob".to_string()),
            (upd("no-such-episode", Label::Success, Some(1)), "bob".to_string()),
            (upd(a, Label::Unknown, Some(2)), "bob".to_string()),
            (upd(a, Label::Success, Some(2)), "carol".to_string()),
            (upd(c, Label::Failure, None), " bad actor".to_string()),
            (long, "carol".to_string()),
            (upd(c, Label::Failure, None), "carol".to_string()),
        ];
        let out = store.set_labels_each(items, "human").await.unwrap();
        assert_eq!(out.len(), 8);
        let ok = |i: usize| out[i].as_ref().unwrap_or_else(|e| panic!("item {i}: {e}")).clone();
        assert_eq!(
            (ok(0).old_label, ok(0).label, ok(0).revision, ok(0).changed),
            (Label::Success, Label::Failure, 2, true)
        );
        match &out[1] {
            Err(StoreError::LabelConflict { expected, revision, label, actor, at, .. }) => {
                let eb = store.episode(b, None).await.unwrap();
                assert_eq!((*expected, *revision, *label), (7, 1, Label::Failure));
                assert_eq!((actor, at), (&eb.label_actor, &eb.label_updated_at));
            }
            other => panic!("item 1: {other:?}"),
        }
        assert!(matches!(out[2], Err(StoreError::NotFound { .. })), "{:?}", out[2]);
        // Items of one batch apply in order: the second write to `a` sees the first.
        assert_eq!((ok(3).old_label, ok(3).revision, ok(3).actor.as_str()), (Label::Failure, 3, "bob"));
        match &out[4] {
            Err(StoreError::LabelConflict {
                expected: 2, revision: 3, label: Label::Unknown, actor, ..
            }) => {
                assert_eq!(actor, "bob")
            }
            other => panic!("item 4: {other:?}"),
        }
        assert!(matches!(out[5], Err(StoreError::Invalid(_))), "{:?}", out[5]);
        assert!(matches!(out[6], Err(StoreError::Invalid(_))), "{:?}", out[6]);
        assert_eq!(
            (ok(7).old_label, ok(7).label, ok(7).revision, ok(7).changed),
            (Label::Success, Label::Failure, 2, true)
        );

        // The audit log holds exactly the applied writes, chained old → new.
        let ha = store.label_history(a).await.unwrap();
        let got: Vec<_> =
            ha.iter().map(|e| (e.revision, e.old_label, e.new_label, e.actor.as_str())).collect();
        assert_eq!(
            got[1..],
            [
                (2, Some(Label::Success), Label::Failure, "alice"),
                (3, Some(Label::Failure), Label::Unknown, "bob")
            ]
        );
        assert_eq!(ha[2].note.as_deref(), Some("unknown"));
        assert_eq!(store.label_history(b).await.unwrap().len(), 1);
        assert_eq!(store.label_history(c).await.unwrap().len(), 2);
        let ea = store.episode(a, None).await.unwrap();
        assert_eq!((ea.label, ea.label_revision, ea.label_actor.as_str()), (Label::Unknown, 3, "bob"));

        // Bulk labeling stays all-or-nothing: one stale item and nothing is written.
        let bulk = vec![upd(b, Label::Success, Some(1)), upd(c, Label::Success, Some(1))];
        assert!(matches!(
            store.set_labels(bulk, "dave", "human").await,
            Err(StoreError::LabelConflict { .. })
        ));
        assert_eq!(store.episode(b, None).await.unwrap().label_revision, 1);
        assert_eq!(store.label_history(b).await.unwrap().len(), 1);
        let bulk = vec![upd(b, Label::Success, Some(1)), upd(c, Label::Success, Some(2))];
        let done = store.set_labels(bulk, "dave", "human").await.unwrap();
        assert_eq!(done.iter().map(|c| c.revision).collect::<Vec<_>>(), [2, 3]);
        assert!(store.set_labels_each(vec![], "human").await.unwrap().is_empty());
    }

    /// Many concurrent unconditional writers on one episode: revisions stay dense and every
    /// event starts from the label the previous one set (the old label is read under the lock).
    async fn concurrent_writers_chain_the_log(db: Backend) {
        let dir = tempfile::tempdir().unwrap();
        let (store, ids) = store_with_episodes(db, dir.path()).await;
        let id = ids[0].clone();
        let mut tasks = Vec::new();
        for t in 0..8u32 {
            let store = store.clone();
            let id = id.clone();
            tasks.push(tokio::spawn(async move {
                for k in 0..10u32 {
                    let label = [Label::Success, Label::Failure, Label::Unknown][((t + k) % 3) as usize];
                    if k % 2 == 0 {
                        store.set_label(upd(&id, label, None), &format!("w{t}"), "human").await.unwrap();
                    } else {
                        let items = vec![(upd(&id, label, None), format!("w{t}"))];
                        let out = store.set_labels_each(items, "human").await.unwrap();
                        out.into_iter().next().unwrap().unwrap();
                    }
                }
            }));
        }
        for t in tasks {
            t.await.unwrap();
        }
        let h = store.label_history(&id).await.unwrap();
        assert_eq!(h.len(), 81);
        for (i, w) in h.windows(2).enumerate() {
            assert_eq!(w[1].revision, i as i64 + 2);
            assert_eq!(
                w[1].old_label,
                Some(w[0].new_label),
                "event {} does not start from the previous label",
                w[1].revision
            );
        }
        let e = store.episode(&id, None).await.unwrap();
        assert_eq!((e.label, e.label_revision), (h[80].new_label, 81));
    }

    #[tokio::test]
    async fn group_commit_sqlite() {
        group_commit_keeps_per_item_outcomes(Backend::Sqlite).await;
    }
    #[tokio::test]
    async fn group_commit_postgres() {
        if !crate::test_support::require_postgres() {
            return;
        }
        group_commit_keeps_per_item_outcomes(Backend::Postgres).await;
    }
    #[tokio::test(flavor = "multi_thread", worker_threads = 4)]
    async fn concurrent_label_writers_sqlite() {
        concurrent_writers_chain_the_log(Backend::Sqlite).await;
    }
    #[tokio::test(flavor = "multi_thread", worker_threads = 4)]
    async fn concurrent_label_writers_postgres() {
        if !crate::test_support::require_postgres() {
            return;
        }
        concurrent_writers_chain_the_log(Backend::Postgres).await;
    }
}
