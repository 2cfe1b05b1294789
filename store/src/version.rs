//! The version-commit protocol every write ends with (ingest, label snapshots, layers): under
//! the version lock, freeze the visible episodes' labels into a labels file, record the version
//! row and its counts, move the head, commit. Data files are written before it (put-if-absent,
//! unreferenced until this commit), so a crash leaves no visible partial version.

use crate::catalog::{RowExt, Tx};
use crate::counts::{insert_version_counts, CountDeltas};
use crate::steps;
use crate::{now_rfc3339, Store, StoreError};
use bytes::Bytes;

/// Reads the head under the version lock and returns the next version number.
pub(crate) async fn next_version(tx: &mut Tx) -> Result<i64, StoreError> {
    let row = sqlx::query("SELECT version FROM store_head WHERE id = 1").fetch_one(&mut **tx).await?;
    Ok(row.i("version")? + 1)
}

/// Registers the policy and its checkpoint if they are new (inside the version's transaction).
pub(crate) async fn ensure_checkpoint(
    tx: &mut Tx,
    policy: &str,
    checkpoint: &str,
    now: &str,
) -> Result<(), StoreError> {
    sqlx::query("INSERT INTO policies (name, created_at) VALUES ($1, $2) ON CONFLICT DO NOTHING")
        .bind(policy)
        .bind(now)
        .execute(&mut **tx)
        .await?;
    sqlx::query(
        "INSERT INTO checkpoints (policy, name, created_at) VALUES ($1, $2, $3) ON CONFLICT DO NOTHING",
    )
    .bind(policy)
    .bind(checkpoint)
    .bind(now)
    .execute(&mut **tx)
    .await?;
    Ok(())
}

/// The row a new version adds to `versions`, and the head it moves to.
pub(crate) struct VersionHead {
    pub version: i64,
    pub kind: &'static str,
    pub message: String,
    pub actor: String,
    pub source_sha256: Option<String>,
    pub episodes_added: i64,
    pub episodes_removed: i64,
    /// What else the version's transaction records in the feed (after `version.created`).
    pub events: Vec<crate::events::NewEvent>,
}

/// One visible episode's row of a labels file, from a query selecting the columns of
/// [`LIVE_LABEL_ROWS`].
fn label_row(r: &sqlx::any::AnyRow) -> Result<steps::LabelRow, StoreError> {
    Ok(steps::LabelRow {
        episode_id: r.s("id")?,
        policy: r.s("policy")?,
        checkpoint: r.s("checkpoint")?,
        task: r.os("task")?,
        length: r.i("length")?,
        label: r.s("label")?.parse()?,
        label_source: r.s("label_source")?,
        revision: r.i("revision")?,
        data_file: r.s("data_file")?,
        row_group: r.i("row_group")?,
        row_offset: r.i("row_offset")?,
        row_count: r.i("row_count")?,
    })
}

/// The current labels of every visible episode, as a labels file holds them (outside any lock).
const LIVE_LABEL_ROWS: &str = "SELECT e.id, e.policy, e.checkpoint, e.task, e.length, e.label, e.label_source, \
     e.label_revision AS revision, e.data_file, e.row_group, COALESCE(e.row_offset, 0) AS row_offset, \
     COALESCE(e.row_count, e.length) AS row_count FROM episodes e WHERE e.version_removed IS NULL ORDER BY e.id";

/// What a labels file holds, in 32 bytes: the version it is written for and every row.
fn label_rows_digest(version: i64, rows: &[steps::LabelRow]) -> [u8; 32] {
    use sha2::Digest;
    let mut h = sha2::Sha256::new();
    let mut text = |s: &str| {
        h.update((s.len() as u64).to_le_bytes());
        h.update(s.as_bytes());
    };
    text(&version.to_string());
    for r in rows {
        text(&r.episode_id);
        text(&r.policy);
        text(&r.checkpoint);
        text(r.task.as_deref().unwrap_or("\u{0}none"));
        text(&r.label.to_string());
        text(&r.label_source);
        text(&r.data_file);
        for n in [r.length, r.revision, r.row_group, r.row_offset, r.row_count] {
            text(&n.to_string());
        }
    }
    h.finalize().into()
}

/// A version's labels file written before the version lock is taken (label snapshots): on
/// SQLite that lock stops every label write, and an upload to an object store can take seconds.
/// [`finish_version`] uses it if the labels under the lock are the ones it was built from, for
/// the version it was built for; otherwise it writes a new one and leaves this one to gc. The
/// object is pending (see `gc.rs`) until then, so gc keeps it meanwhile.
pub(crate) struct LabelsFileAhead {
    version: i64,
    digest: [u8; 32],
    path: String,
    size: i64,
    writer: String,
}

pub(crate) async fn write_labels_file_ahead(store: &Store) -> Result<LabelsFileAhead, StoreError> {
    let version = store.head_version().await? + 1;
    let rows = sqlx::query(LIVE_LABEL_ROWS).fetch_all(&store.db().pool).await?;
    let label_rows = rows.iter().map(label_row).collect::<Result<Vec<_>, _>>()?;
    drop(rows);
    let digest = label_rows_digest(version, &label_rows);
    let data = steps::labels_file(version, &label_rows)?;
    drop(label_rows);
    let path = format!("labels/{}.parquet", uuid::Uuid::new_v4());
    let writer = format!("labels-{}", uuid::Uuid::new_v4().simple());
    store.register_pending(&writer, &path).await?;
    let size = data.len() as i64;
    store.objects().put_new(&path, Bytes::from(data)).await?;
    // The upload may have outlasted the lease: renewed, it holds until the commit checks it.
    store.renew_pending(&writer).await?;
    Ok(LabelsFileAhead { version, digest, path, size, writer })
}

/// Freezes the current labels of every visible episode into the version (and their counts),
/// writes the label snapshot file, records the version row, adds the write's `counts` deltas to
/// the maintained counts and moves the head — then commits.
// Past 100 lines on purpose: one transaction's steps under the version lock, in the order the
// crash-safety argument needs them (labels file, version row, counts, head, commit).
pub(crate) async fn finish_version(
    store: &Store,
    mut tx: Tx,
    head: VersionHead,
    counts: CountDeltas,
    ahead: Option<LabelsFileAhead>,
) -> Result<i64, StoreError> {
    let v = head.version;
    sqlx::query(
        "INSERT INTO version_labels (version, episode_id, label, label_source, revision) \
         SELECT $1, id, label, label_source, label_revision FROM episodes WHERE version_removed IS NULL",
    )
    .bind(v)
    .execute(&mut *tx)
    .await?;
    let rows = sqlx::query(
        "SELECT e.id, e.policy, e.checkpoint, e.task, e.length, l.label, l.label_source, l.revision, e.run_id, \
         e.data_file, e.row_group, COALESCE(e.row_offset, 0) AS row_offset, \
         COALESCE(e.row_count, e.length) AS row_count FROM version_labels l JOIN episodes e ON e.id = l.episode_id \
         WHERE l.version = $1 ORDER BY e.id",
    )
    .bind(v)
    .fetch_all(&mut *tx)
    .await?;
    let mut label_rows = Vec::with_capacity(rows.len());
    let mut run_ids = Vec::with_capacity(rows.len());
    for r in &rows {
        run_ids.push(r.os("run_id")?);
        label_rows.push(label_row(r)?);
    }
    drop(rows);
    let frozen =
        label_rows.iter().map(|r| (r.policy.as_str(), r.checkpoint.as_str(), r.task.as_deref(), r.label));
    insert_version_counts(&mut tx, v, frozen).await?;
    let by_run = label_rows.iter().zip(&run_ids).map(|(r, run)| {
        (r.policy.as_str(), r.checkpoint.as_str(), r.task.as_deref(), run.as_deref(), r.label)
    });
    crate::scoreboard::insert_version_run_counts(&mut tx, v, by_run).await?;
    let changed = sqlx::query(
        "SELECT COUNT(*) AS n FROM version_labels a JOIN version_labels b \
         ON b.episode_id = a.episode_id AND b.version = $2 WHERE a.version = $1 AND a.revision <> b.revision",
    )
    .bind(v)
    .bind(v - 1)
    .fetch_one(&mut *tx)
    .await?
    .i("n")?;
    // The file written ahead of the lock, if it holds exactly these labels for this version.
    let ahead_writer = ahead.as_ref().map(|a| a.writer.clone());
    // Its pending record must still be within its lease: then no gc can have deleted it (gc
    // deletes under this lock, and only objects whose lease had lapsed).
    let usable = match &ahead {
        Some(a) if a.version == v && a.digest == label_rows_digest(v, &label_rows) => sqlx::query(
            "SELECT COUNT(*) AS n FROM pending_objects WHERE writer = $1 AND path = $2 AND created_ms >= $3",
        )
        .bind(&a.writer)
        .bind(&a.path)
        .bind(crate::now_ms() - crate::gc::writer_lease_ms())
        .fetch_one(&mut *tx)
        .await?
        .i("n")?
            > 0,
        _ => false,
    };
    let (labels_path, size) = match ahead {
        Some(a) if usable => (a.path, a.size),
        _ => {
            let data = steps::labels_file(v, &label_rows)?;
            let labels_path = format!("labels/{}.parquet", uuid::Uuid::new_v4());
            let size = data.len() as i64;
            store.objects().put_new(&labels_path, Bytes::from(data)).await?;
            (labels_path, size)
        }
    };
    if let Some(w) = &ahead_writer {
        // Used or not, the early file is no longer pending: referenced now, or garbage for gc.
        sqlx::query("DELETE FROM pending_objects WHERE writer = $1").bind(w).execute(&mut *tx).await?;
    }
    sqlx::query(
        "INSERT INTO data_files (path, kind, size_bytes, num_rows, version_added) VALUES ($1, 'labels', $2, $3, $4)",
    )
    .bind(&labels_path)
    .bind(size)
    .bind(label_rows.len() as i64)
    .bind(v)
    .execute(&mut *tx)
    .await?;
    sqlx::query(
        "INSERT INTO versions (version, kind, message, actor, created_at, labels_path, source_sha256, \
         episodes_added, episodes_removed, labels_changed, episode_count) \
         VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11)",
    )
    .bind(v)
    .bind(head.kind)
    .bind(&head.message)
    .bind(&head.actor)
    .bind(now_rfc3339())
    .bind(&labels_path)
    .bind(head.source_sha256.clone())
    .bind(head.episodes_added)
    .bind(head.episodes_removed)
    .bind(changed)
    .bind(label_rows.len() as i64)
    .execute(&mut *tx)
    .await?;
    // Last: on Postgres the counter rows stay locked until the commit.
    counts.apply(&mut tx, store.backend()).await?;
    let moved = sqlx::query("UPDATE store_head SET version = $1 WHERE id = 1 AND version = $2")
        .bind(v)
        .bind(v - 1)
        .execute(&mut *tx)
        .await?;
    if moved.rows_affected() != 1 {
        return Err(StoreError::Conflict(format!("another writer committed version {v} first; retry")));
    }
    let mut events = vec![crate::events::NewEvent::new(
        crate::events::EventKind::VersionCreated,
        v.to_string(),
        serde_json::json!({
            "version": v,
            "kind": head.kind,
            "message": head.message,
            "actor": head.actor,
            "episodes_added": head.episodes_added,
            "episodes_removed": head.episodes_removed,
            "episode_count": label_rows.len(),
        }),
    )];
    events.extend(head.events);
    store.commit_with_events(tx, &events).await?;
    Ok(v)
}
