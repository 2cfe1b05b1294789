//! Labels: an append-only event log per episode (who, when, old → new, note, revision). The
//! current label is the latest event; optimistic concurrency via the expected revision.

use crate::catalog::{RowExt, Tx};
use crate::writer::{finish_version, next_version, VersionHead};
use crate::{now_rfc3339, CommitInfo, Label, Store, StoreError};
use serde::Serialize;

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
    pub async fn set_label(&self, update: LabelUpdate, actor: &str, source: &str) -> Result<LabelChange, StoreError> {
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
        crate::writer::check_name("actor", actor)?;
        if updates.is_empty() {
            return Ok(Vec::new());
        }
        let mut tx = self.db().begin_write().await?;
        let mut out = Vec::with_capacity(updates.len());
        for u in updates {
            out.push(apply_one(&mut tx, &u, actor, source).await?);
        }
        tx.commit().await?;
        Ok(out)
    }

    /// Every label event of an episode, oldest first.
    pub async fn label_history(&self, episode_id: &str) -> Result<Vec<LabelEvent>, StoreError> {
        let rows = sqlx::query(
            "SELECT episode_id, revision, old_label, new_label, source, actor, note, created_at \
             FROM label_events WHERE episode_id = $1 ORDER BY revision",
        )
        .bind(episode_id)
        .fetch_all(&self.db().pool)
        .await?;
        if rows.is_empty() {
            self.episode(episode_id, None).await?;
        }
        rows.iter().map(event_from_row).collect()
    }

    /// All label events after `after_id` (for replaying the audit log), with their ids.
    pub async fn label_events_since(&self, after_id: i64, limit: i64) -> Result<Vec<(i64, LabelEvent)>, StoreError> {
        let rows = sqlx::query(
            "SELECT id, episode_id, revision, old_label, new_label, source, actor, note, created_at \
             FROM label_events WHERE id > $1 ORDER BY id LIMIT $2",
        )
        .bind(after_id)
        .bind(limit)
        .fetch_all(&self.db().pool)
        .await?;
        rows.iter().map(|r| Ok((r.i("id")?, event_from_row(r)?))).collect()
    }

    /// Freezes the current labels into a new version.
    pub async fn snapshot_labels(&self, actor: &str, message: &str) -> Result<CommitInfo, StoreError> {
        let mut tx = self.db().begin_version_write().await?;
        let version = next_version(&mut tx).await?;
        let head = VersionHead {
            version,
            kind: "label_snapshot",
            message: message.to_string(),
            actor: actor.to_string(),
            source_sha256: None,
            episodes_added: 0,
            episodes_removed: 0,
        };
        finish_version(self, tx, head).await?;
        let info = self.version(version).await?;
        Ok(CommitInfo { version, episodes: info.episode_count as usize })
    }

    /// Whether any label changed since the head version froze them.
    pub async fn labels_changed_since_head(&self) -> Result<bool, StoreError> {
        let row = sqlx::query(
            "SELECT COUNT(*) AS n FROM episodes e LEFT JOIN version_labels l \
             ON l.episode_id = e.id AND l.version = (SELECT version FROM store_head WHERE id = 1) \
             WHERE e.version_removed IS NULL AND (l.revision IS NULL OR l.revision <> e.label_revision)",
        )
        .fetch_one(&self.db().pool)
        .await?;
        Ok(row.i("n")? > 0)
    }

    /// Removes episodes from the next version (their data stays readable in older versions).
    pub async fn delete_episodes(&self, ids: &[String], actor: &str, message: &str) -> Result<CommitInfo, StoreError> {
        let mut tx = self.db().begin_version_write().await?;
        let version = next_version(&mut tx).await?;
        for id in ids {
            let r = sqlx::query("UPDATE episodes SET version_removed = $1 WHERE id = $2 AND version_removed IS NULL")
                .bind(version)
                .bind(id)
                .execute(&mut *tx)
                .await?;
            if r.rows_affected() != 1 {
                return Err(StoreError::not_found("episode", id.clone()));
            }
        }
        let head = VersionHead {
            version,
            kind: "delete",
            message: message.to_string(),
            actor: actor.to_string(),
            source_sha256: None,
            episodes_added: 0,
            episodes_removed: ids.len() as i64,
        };
        finish_version(self, tx, head).await?;
        let info = self.version(version).await?;
        Ok(CommitInfo { version, episodes: info.episode_count as usize })
    }
}

async fn apply_one(tx: &mut Tx, u: &LabelUpdate, actor: &str, source: &str) -> Result<LabelChange, StoreError> {
    if let Some(n) = &u.note {
        if n.len() > 4000 {
            return Err(StoreError::invalid("label note is longer than 4000 bytes"));
        }
    }
    let row = sqlx::query(
        "SELECT label, label_revision, label_actor, label_updated_at FROM episodes \
         WHERE id = $1 AND version_removed IS NULL",
    )
    .bind(&u.episode_id)
    .fetch_optional(&mut **tx)
    .await?
    .ok_or_else(|| StoreError::not_found("episode", u.episode_id.clone()))?;
    let current: Label = row.s("label")?.parse()?;
    let revision = row.i("label_revision")?;
    let conflict = |revision: i64, label: Label, actor: String, at: String, expected: i64| StoreError::LabelConflict {
        episode_id: u.episode_id.clone(),
        expected,
        revision,
        label,
        actor,
        at,
    };
    if let Some(expected) = u.expect_revision {
        if expected != revision {
            return Err(conflict(revision, current, row.s("label_actor")?, row.s("label_updated_at")?, expected));
        }
    }
    let now = now_rfc3339();
    let new_rev = revision + 1;
    let updated = sqlx::query(
        "UPDATE episodes SET label = $1, label_source = $2, label_revision = $3, label_actor = $4, \
         label_updated_at = $5 WHERE id = $6 AND label_revision = $7",
    )
    .bind(u.label.as_str())
    .bind(source)
    .bind(new_rev)
    .bind(actor)
    .bind(&now)
    .bind(&u.episode_id)
    .bind(revision)
    .execute(&mut **tx)
    .await?;
    if updated.rows_affected() != 1 {
        // Someone else moved the revision between our read and our write (Postgres).
        return Err(StoreError::Conflict(format!(
            "episode {} was relabeled concurrently; reload and retry",
            u.episode_id
        )));
    }
    sqlx::query(
        "INSERT INTO label_events (episode_id, revision, old_label, new_label, source, actor, note, created_at) \
         VALUES ($1, $2, $3, $4, $5, $6, $7, $8)",
    )
    .bind(&u.episode_id)
    .bind(new_rev)
    .bind(current.as_str())
    .bind(u.label.as_str())
    .bind(source)
    .bind(actor)
    .bind(u.note.clone())
    .bind(&now)
    .execute(&mut **tx)
    .await?;
    Ok(LabelChange {
        episode_id: u.episode_id.clone(),
        old_label: current,
        label: u.label,
        revision: new_rev,
        actor: actor.to_string(),
        changed: current != u.label,
    })
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
    })
}
