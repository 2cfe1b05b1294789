//! A version's labels as files, readable with nothing but the files (store/README.md, "Label
//! files"): each version writes the rows it changed (a `delta` file; removed episodes flagged),
//! and a `full` file now and then keeps the chain a reader applies short. The first version of a
//! store, every version written before deltas (migration 0019), and each checkpoint are full.
//!
//! Checkpoints are written after a version commits, outside the version lock, by the writer that
//! made the chain long (as Delta Lake's writers checkpoint their log): the labels of a committed
//! version never change, so the file can be built at leisure and attached to the version later.

use crate::catalog::{RowExt, Tx};
use crate::spans::covers;
use crate::steps::{self, LabelRow, LabelsKind};
use crate::{Store, StoreError};
use bytes::Bytes;
use std::collections::BTreeMap;

/// A checkpoint is due once this many delta files follow the last full one...
const CHECKPOINT_EVERY_VERSIONS: usize = 64;
/// ... or once the deltas hold this fraction of the version's episodes (and at least
/// [`CHECKPOINT_MIN_ROWS`] rows): a reader then reads less than twice the full file.
const CHECKPOINT_DELTA_FRACTION: f64 = 0.5;
const CHECKPOINT_MIN_ROWS: i64 = 10_000;

/// One version's file in a chain.
struct ChainLink {
    version: i64,
    path: String,
    full: bool,
    rows: i64,
}

/// The files that make up version `v`'s labels, newest first, back to (and with) a full one.
async fn chain(store: &Store, v: i64) -> Result<Vec<ChainLink>, StoreError> {
    let mut out = Vec::new();
    let mut before = v + 1;
    loop {
        let rows = sqlx::query(
            "SELECT v.version, v.labels_path, v.labels_kind, v.labels_checkpoint, d.num_rows FROM versions v \
             LEFT JOIN data_files d ON d.path = v.labels_path WHERE v.version < $1 ORDER BY v.version DESC LIMIT 256",
        )
        .bind(before)
        .fetch_all(&store.catalog().pool)
        .await?;
        if rows.is_empty() {
            return Err(StoreError::invalid(format!("version {v}: no full labels file starts its chain")));
        }
        for r in &rows {
            let version = r.i("version")?;
            before = version;
            if let Some(cp) = r.os("labels_checkpoint")? {
                out.push(ChainLink { version, path: cp, full: true, rows: 0 });
                return Ok(out);
            }
            let full = r.s("labels_kind")? == LabelsKind::Full.as_str();
            out.push(ChainLink {
                version,
                path: r.s("labels_path")?,
                full,
                rows: r.oi("num_rows")?.unwrap_or(0),
            });
            if full {
                return Ok(out);
            }
        }
    }
}

impl Store {
    /// The labels files of version `v`, in the order to apply them: a full file, then the deltas
    /// after it (a later row replaces an earlier one of the same episode; a removed one drops it).
    pub async fn labels_files(&self, v: i64) -> Result<Vec<String>, StoreError> {
        self.version(v).await?;
        Ok(chain(self, v).await?.into_iter().rev().map(|l| l.path).collect())
    }

    /// A full labels file of version `v`, written (and attached as its checkpoint) if it has none:
    /// for readers that want the version's labels in one file.
    pub async fn full_labels_file(&self, v: i64) -> Result<String, StoreError> {
        self.version(v).await?;
        // A try loses only to another writer attaching one first, or to an upload that outlived
        // its lease: the next look finds the other's file, or tries again.
        for _ in 0..3 {
            let links = chain(self, v).await?;
            if let [only] = links.as_slice() {
                return Ok(only.path.clone());
            }
            write_checkpoint(self, v).await?;
        }
        Err(StoreError::Conflict(format!("version {v}: could not attach a full labels file; retry")))
    }

    /// Version `v`'s labels read from its files alone, one row per visible episode in id order.
    pub async fn read_labels_files(&self, v: i64) -> Result<Vec<LabelRow>, StoreError> {
        let mut rows: BTreeMap<String, LabelRow> = BTreeMap::new();
        for (i, path) in self.labels_files(v).await?.into_iter().enumerate() {
            let (kind, file) = steps::read_labels_file(self.get_object(&path).await?)?;
            if (i == 0) != (kind == LabelsKind::Full) {
                return Err(StoreError::invalid(format!(
                    "labels file {path}: a {} file out of place",
                    kind.as_str()
                )));
            }
            for r in file {
                if r.removed {
                    rows.remove(&r.episode_id);
                } else {
                    rows.insert(r.episode_id.clone(), r);
                }
            }
        }
        Ok(rows.into_values().collect())
    }
}

/// Writes a full labels file for version `v` if its chain has grown long (see the constants),
/// and attaches it to the version. Runs after the version committed, outside the lock.
pub(crate) async fn checkpoint_if_due(store: &Store, v: i64) -> Result<bool, StoreError> {
    let links = chain(store, v).await?;
    let deltas = links.iter().filter(|l| !l.full).count();
    let delta_rows: i64 = links.iter().filter(|l| !l.full).map(|l| l.rows).sum();
    let episodes = store.version(v).await?.episode_count;
    let by_rows =
        delta_rows >= CHECKPOINT_MIN_ROWS && delta_rows as f64 >= CHECKPOINT_DELTA_FRACTION * episodes as f64;
    if deltas < CHECKPOINT_EVERY_VERSIONS && !by_rows {
        return Ok(false);
    }
    debug_assert!(links.first().is_some_and(|l| l.version == v));
    write_checkpoint(store, v).await
}

/// Writes and attaches version `v`'s full labels file (false if another writer attached one).
pub(crate) async fn write_checkpoint(store: &Store, v: i64) -> Result<bool, StoreError> {
    let rows = sqlx::query(&format!(
        "SELECT {} FROM version_labels l JOIN episodes e ON e.id = l.episode_id WHERE {} ORDER BY e.id",
        label_cols("l", "revision"),
        covers("l", "$1")
    ))
    .bind(v)
    .fetch_all(&store.catalog().pool)
    .await?;
    let labels = rows.iter().map(|r| label_row(r, false)).collect::<Result<Vec<_>, _>>()?;
    drop(rows);
    let (path, size, writer) = put_pending_labels_file(store, v, LabelsKind::Full, &labels).await?;
    let mut tx = store.catalog().begin_version_write().await?;
    // Attached or not, the file is no longer pending: referenced now, or garbage for gc.
    let live = Store::release_pending(&mut tx, &writer, &path).await?;
    let attached = live && attach(&mut tx, v, &path, size, labels.len() as i64).await?;
    tx.commit().await?;
    Ok(attached)
}

async fn attach(tx: &mut Tx, v: i64, path: &str, size: i64, rows: i64) -> Result<bool, StoreError> {
    let set = sqlx::query(
        "UPDATE versions SET labels_checkpoint = $1 WHERE version = $2 AND labels_checkpoint IS NULL",
    )
    .bind(path)
    .bind(v)
    .execute(&mut **tx)
    .await?;
    if set.rows_affected() != 1 {
        return Ok(false);
    }
    sqlx::query(
        "INSERT INTO data_files (path, kind, size_bytes, num_rows, version_added) VALUES ($1, 'labels', $2, $3, $4)",
    )
    .bind(path)
    .bind(size)
    .bind(rows)
    .bind(v)
    .execute(&mut **tx)
    .await?;
    Ok(true)
}

/// One row of a labels file, from a query selecting the columns of [`label_cols`].
pub(crate) fn label_row(r: &sqlx::any::AnyRow, removed: bool) -> Result<steps::LabelRow, StoreError> {
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
        removed,
    })
}

/// The columns [`label_row`] reads, the label ones from table alias `l` (`e` is the episode).
pub(crate) fn label_cols(l: &str, revision: &str) -> String {
    format!(
        "e.id, e.policy, e.checkpoint, e.task, e.length, {l}.label AS label, {l}.label_source AS label_source, \
         {l}.{revision} AS revision, e.run_id, e.data_file, e.row_group, COALESCE(e.row_offset, 0) AS row_offset, \
         COALESCE(e.row_count, e.length) AS row_count"
    )
}

/// Writes a labels file outside the version lock, recorded as pending (gc keeps it) under a
/// writer of its own until a transaction references it: its path, size and writer.
pub(crate) async fn put_pending_labels_file(
    store: &Store,
    v: i64,
    kind: LabelsKind,
    rows: &[steps::LabelRow],
) -> Result<(String, i64, String), StoreError> {
    let data = steps::labels_file(v, kind, rows)?;
    let path = format!("labels/{}.parquet", uuid::Uuid::new_v4());
    let writer = format!("labels-{}", uuid::Uuid::new_v4().simple());
    store.register_pending(&writer, &path).await?;
    let size = data.len() as i64;
    store.objects().put_new(&path, Bytes::from(data)).await?;
    // The upload may have outlasted the lease: renewed, it holds until the commit checks it.
    store.renew_pending(&writer).await?;
    Ok((path, size, writer))
}
