//! The version-commit protocol every write ends with (ingest, label snapshots, deletions, layers):
//! under the version lock, freeze the labels that changed since the head (spans of labels and
//! counts, migration 0019) and write them as the version's labels file, record the version row,
//! move the head, commit. Data files are written before it (put-if-absent, unreferenced until
//! this commit), so a crash leaves no visible partial version. A version costs what it changes.

use super::counts::CountDeltas;
use super::label_files::{label_cols, label_row, put_pending_labels_file};
use crate::catalog::{insert_rows, RowExt, Tx, Val};
use crate::steps::{self, LabelsKind};
use crate::{now_rfc3339, Label, Store, StoreError};
use bytes::Bytes;
use std::collections::BTreeMap;

/// Reads the head under the version lock and returns the next version number.
pub(crate) async fn next_version(tx: &mut Tx) -> Result<i64, StoreError> {
    let row = sqlx::query("SELECT version FROM store_head WHERE id = 1").fetch_one(&mut **tx).await?;
    Ok(row.i("version")? + 1)
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

/// The visible episodes whose label the head has not frozen (added since, or relabeled), as
/// `FROM` and `WHERE` parts that read them through the partial index `episodes_labels_unfrozen`.
/// SQLite's planner, without statistics, would rather scan the table in id order: told the
/// index (whose condition is this one word for word), it reads only them, and fails loudly if
/// the index could not serve. Postgres keeps the condition as a generated column with statistics
/// of its own (migration 0019).
pub(crate) fn unfrozen_episodes(sqlite: bool) -> (&'static str, &'static str) {
    if sqlite {
        (
            "episodes e INDEXED BY episodes_labels_unfrozen",
            "e.version_removed IS NULL AND (e.label_frozen_revision IS NULL OR \
             e.label_frozen_revision <> e.label_revision)",
        )
    } else {
        ("episodes e", "e.label_unfrozen")
    }
}

/// Episode ids per statement of an `IN (…)` list.
const IDS_PER_STATEMENT: usize = 500;

/// What one version changes: the episodes whose labels it freezes anew (with the label their
/// previous span froze, None for an episode it adds), and the ones it removes.
struct VersionChanges {
    changed: Vec<(steps::LabelRow, Option<String>, Option<Label>)>,
    removed: Vec<(steps::LabelRow, Option<String>)>,
}

async fn read_changes(tx: &mut Tx, v: i64) -> Result<VersionChanges, StoreError> {
    // Read once: on Postgres label writes go on beside this transaction, and every later step
    // works from these rows, not from what the episodes hold by then.
    let (from, unfrozen) = unfrozen_episodes(tx.backend_name().eq_ignore_ascii_case("sqlite"));
    let rows = sqlx::query(&format!(
        "SELECT {}, s.label AS old_label FROM {from} \
         LEFT JOIN version_labels s ON s.episode_id = e.id AND s.version_to IS NULL WHERE {unfrozen} ORDER BY e.id",
        label_cols("e", "label_revision"),
    ))
    .fetch_all(&mut **tx)
    .await?;
    let mut changed = Vec::with_capacity(rows.len());
    for r in &rows {
        let old = r.os("old_label")?.map(|l| l.parse::<Label>()).transpose()?;
        changed.push((label_row(r, false)?, r.os("run_id")?, old));
    }
    let rows = sqlx::query(&format!(
        "SELECT {} FROM episodes e JOIN version_labels s ON s.episode_id = e.id AND s.version_to IS NULL \
         WHERE e.version_removed = $1 ORDER BY e.id",
        label_cols("s", "revision")
    ))
    .bind(v)
    .fetch_all(&mut **tx)
    .await?;
    let mut removed = Vec::with_capacity(rows.len());
    for r in &rows {
        removed.push((label_row(r, true)?, r.os("run_id")?));
    }
    Ok(VersionChanges { changed, removed })
}

/// Runs `sql` (with `$1` bound to `v` and `{ids}` standing for an `IN` list) over `ids` in chunks.
async fn for_ids(tx: &mut Tx, sql: &str, v: i64, ids: &[&str]) -> Result<(), StoreError> {
    for chunk in ids.chunks(IDS_PER_STATEMENT) {
        let list = (0..chunk.len()).map(|i| format!("${}", i + 2)).collect::<Vec<_>>().join(", ");
        let sql = sql.replace("{ids}", &list);
        let mut q = sqlx::query(&sql).bind(v);
        for id in chunk {
            q = q.bind(*id);
        }
        q.execute(&mut **tx).await?;
    }
    Ok(())
}

/// Moves the frozen labels on to version `v`: closes the spans of the episodes it relabels or
/// removes, opens one per episode it adds or relabels, and records the revision frozen.
async fn write_label_spans(tx: &mut Tx, v: i64, c: &VersionChanges) -> Result<(), StoreError> {
    let closing: Vec<&str> = c
        .changed
        .iter()
        .filter(|(_, _, old)| old.is_some())
        .map(|(r, _, _)| r.episode_id.as_str())
        .chain(c.removed.iter().map(|(r, _)| r.episode_id.as_str()))
        .collect();
    for_ids(
        tx,
        "UPDATE version_labels SET version_to = $1 WHERE version_to IS NULL AND episode_id IN ({ids})",
        v,
        &closing,
    )
    .await?;
    let rows = c
        .changed
        .iter()
        .map(|(r, _, _)| {
            vec![
                Val::S(r.episode_id.clone()),
                Val::I(v),
                Val::S(r.label.as_str().into()),
                Val::S(r.label_source.clone()),
                Val::I(r.revision),
            ]
        })
        .collect();
    insert_rows(
        tx,
        "version_labels",
        &["episode_id", "version_from", "label", "label_source", "revision"],
        rows,
        "",
    )
    .await?;
    // The revision of the span just opened, not the episode's revision now (a label write may
    // have moved it on since the read: it stays unfrozen for the next version).
    let opened: Vec<&str> = c.changed.iter().map(|(r, _, _)| r.episode_id.as_str()).collect();
    for_ids(
        tx,
        "UPDATE episodes SET label_frozen_revision = (SELECT s.revision FROM version_labels s \
         WHERE s.episode_id = episodes.id AND s.version_from = $1) WHERE id IN ({ids})",
        v,
        &opened,
    )
    .await
}

/// Moves the frozen counts on to version `v`: for every group whose count the version changes,
/// closes its open span and opens one with the new count (none when it reaches zero). `table`
/// is `version_counts` or `version_run_counts`, keyed by `key_cols` then `label`.
async fn write_count_spans(
    tx: &mut Tx,
    table: &str,
    key_cols: &[&str],
    v: i64,
    deltas: BTreeMap<Vec<String>, i64>,
) -> Result<(), StoreError> {
    let key_cond = key_cols
        .iter()
        .enumerate()
        .map(|(i, c)| format!("{c} = ${}", i + 2))
        .collect::<Vec<_>>()
        .join(" AND ");
    let mut opened = Vec::new();
    let close =
        format!("UPDATE {table} SET version_to = $1 WHERE {key_cond} AND version_to IS NULL RETURNING n");
    for (key, delta) in deltas.into_iter().filter(|(_, d)| *d != 0) {
        let mut q = sqlx::query(&close).bind(v);
        for k in &key {
            q = q.bind(k.clone());
        }
        let before = match q.fetch_optional(&mut **tx).await? {
            Some(r) => r.i("n")?,
            None => 0,
        };
        let n = before + delta;
        if n < 0 {
            return Err(StoreError::Conflict(format!("{table}: a count of {key:?} would fall below zero")));
        }
        if n > 0 {
            let mut row: Vec<Val> = key.into_iter().map(Val::S).collect();
            row.extend([Val::I(v), Val::I(n)]);
            opened.push(row);
        }
    }
    let mut cols = key_cols.to_vec();
    cols.extend(["version_from", "n"]);
    insert_rows(tx, table, &cols, opened, "").await
}

/// The count changes of `c`, keyed (policy, checkpoint, task, [run,] label).
fn count_deltas(c: &VersionChanges, by_run: bool) -> BTreeMap<Vec<String>, i64> {
    let mut out: BTreeMap<Vec<String>, i64> = BTreeMap::new();
    let mut add = |r: &steps::LabelRow, run: &Option<String>, label: Label, n: i64| {
        let mut key = vec![r.policy.clone(), r.checkpoint.clone(), r.task.clone().unwrap_or_default()];
        if by_run {
            key.push(run.clone().unwrap_or_default());
        }
        key.push(label.as_str().to_string());
        *out.entry(key).or_default() += n;
    };
    for (r, run, old) in &c.changed {
        if let Some(old) = old {
            add(r, run, *old, -1);
        }
        add(r, run, r.label, 1);
    }
    for (r, run) in &c.removed {
        add(r, run, r.label, -1);
    }
    out
}

/// Writes a version's labels file: `rows` under a fresh name.
async fn put_labels_file(
    store: &Store,
    v: i64,
    kind: LabelsKind,
    rows: &[steps::LabelRow],
) -> Result<(String, i64), StoreError> {
    let data = steps::labels_file(v, kind, rows)?;
    let path = format!("labels/{}.parquet", uuid::Uuid::new_v4());
    let size = data.len() as i64;
    store.objects().put_new(&path, Bytes::from(data)).await?;
    Ok((path, size))
}

/// The episodes in the store before version `v` (0 for the first).
async fn episodes_before(tx: &mut Tx, v: i64) -> Result<i64, StoreError> {
    Ok(sqlx::query("SELECT episode_count FROM versions WHERE version = $1")
        .bind(v - 1)
        .fetch_optional(&mut **tx)
        .await?
        .map(|r| r.i("episode_count"))
        .transpose()?
        .unwrap_or(0))
}

/// A version's rows of its labels file, and its kind: a version over an empty store holds all
/// its labels, a full file where chains start.
fn file_rows(c: &VersionChanges, before: i64) -> (LabelsKind, Vec<steps::LabelRow>) {
    let kind = if before == 0 { LabelsKind::Full } else { LabelsKind::Delta };
    let rows =
        c.changed.iter().map(|(r, _, _)| r.clone()).chain(c.removed.iter().map(|(r, _)| r.clone())).collect();
    (kind, rows)
}

/// A version's labels file written before the version lock is taken (label snapshots): on
/// SQLite that lock stops every label write, and an upload to an object store can take seconds.
/// [`finish_version`] uses it if the changes under the lock are the ones it was built from, for
/// the version it was built for; otherwise it writes a new one and leaves this one to gc. The
/// object is pending (see `gc.rs`) until then, so gc keeps it meanwhile.
pub(crate) struct LabelsFileAhead {
    version: i64,
    kind: LabelsKind,
    rows: Vec<steps::LabelRow>,
    path: String,
    size: i64,
    writer: String,
}

pub(crate) async fn write_labels_file_ahead(store: &Store) -> Result<LabelsFileAhead, StoreError> {
    // A read transaction: the head and the changes read from one snapshot (no lock taken).
    let mut tx = store.catalog().pool.begin().await?;
    let version =
        sqlx::query("SELECT version FROM store_head WHERE id = 1").fetch_one(&mut *tx).await?.i("version")?
            + 1;
    let changes = read_changes(&mut tx, version).await?;
    let before = episodes_before(&mut tx, version).await?;
    tx.rollback().await?;
    let (kind, rows) = file_rows(&changes, before);
    let (path, size, writer) = put_pending_labels_file(store, version, kind, &rows).await?;
    Ok(LabelsFileAhead { version, kind, rows, path, size, writer })
}

/// The labels file of version `v`: the one written ahead if it holds exactly these rows and its
/// pending record is still within its lease (then no gc can have deleted it: gc deletes under
/// this lock, and only objects whose lease had lapsed); else a new one.
async fn labels_file_for(
    store: &Store,
    tx: &mut Tx,
    v: i64,
    kind: LabelsKind,
    rows: &[steps::LabelRow],
    ahead: Option<LabelsFileAhead>,
) -> Result<(String, i64), StoreError> {
    let Some(a) = ahead else { return put_labels_file(store, v, kind, rows).await };
    // Used or not, the early file is no longer pending: referenced now, or garbage for gc.
    let live = Store::release_pending(tx, &a.writer, &a.path).await?;
    if live && a.version == v && a.kind == kind && a.rows == rows {
        return Ok((a.path, a.size));
    }
    put_labels_file(store, v, kind, rows).await
}

/// Freezes the labels the version changes (spans of labels and counts, migration 0019), writes
/// its labels file (the rows it changed), records the version row, adds the write's `counts`
/// deltas to the maintained counts and moves the head — then commits. It reads and writes
/// O(changed) rows, whatever the store's size.
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
    let changes = read_changes(&mut tx, v).await?;
    write_label_spans(&mut tx, v, &changes).await?;
    write_count_spans(
        &mut tx,
        "version_counts",
        &["policy", "checkpoint", "task", "label"],
        v,
        count_deltas(&changes, false),
    )
    .await?;
    write_count_spans(
        &mut tx,
        "version_run_counts",
        &["policy", "checkpoint", "task", "run_id", "label"],
        v,
        count_deltas(&changes, true),
    )
    .await?;
    let before = episodes_before(&mut tx, v).await?;
    let added = changes.changed.iter().filter(|(_, _, old)| old.is_none()).count() as i64;
    let relabeled = changes.changed.len() as i64 - added;
    let episode_count = before + added - changes.removed.len() as i64;
    let (kind, rows) = file_rows(&changes, before);
    let (labels_path, size) = labels_file_for(store, &mut tx, v, kind, &rows, ahead).await?;
    sqlx::query(
        "INSERT INTO data_files (path, kind, size_bytes, num_rows, version_added) VALUES ($1, 'labels', $2, $3, $4)",
    )
    .bind(&labels_path)
    .bind(size)
    .bind(rows.len() as i64)
    .bind(v)
    .execute(&mut *tx)
    .await?;
    sqlx::query(
        "INSERT INTO versions (version, kind, message, actor, created_at, labels_path, source_sha256, \
         episodes_added, episodes_removed, labels_changed, episode_count, labels_kind) \
         VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, $12)",
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
    .bind(relabeled)
    .bind(episode_count)
    .bind(kind.as_str())
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
            "episode_count": episode_count,
        }),
    )];
    events.extend(head.events);
    store.commit_with_events(tx, &events).await?;
    // Committed: a checkpoint that fails now only leaves the chain longer for the next one.
    if let Err(e) = super::label_files::checkpoint_if_due(store, v).await {
        tracing::warn!("labels checkpoint of version {v} failed (the next version retries): {e}");
    }
    Ok(v)
}
