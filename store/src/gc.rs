//! Garbage collection: deletes objects no committed version references (left by crashed or
//! aborted writers), after a grace period.
//!
//! Writers in flight are protected whatever the grace period: a writer records each object in
//! `pending_objects` before it uploads it or decides to re-use an existing one (content-addressed
//! media and artifact files), renews its records while it lives (a lease, [`writer_lease_ms`](crate::objects::writer_lease_ms)),
//! and deletes them in the transaction that makes the objects referenced. A killed writer's
//! records lapse with its lease, and gc collects what it left. gc re-checks every candidate in small batches inside the version write lock
//! (Postgres: also an exclusive lock on `pending_objects`, which SQLite's single write lock gives
//! already) and deletes the batch before releasing it. So a writer's registration comes either
//! before the batch (the object is kept) or after it (the object is already gone, the writer's
//! existence check says so, and it uploads the object again).

use crate::catalog::RowExt;
use crate::objects::writer_lease_ms;
use crate::{Store, StoreError};
use bytes::Bytes;
use serde::Serialize;
use std::collections::HashSet;

#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize)]
pub struct GcReport {
    pub objects_scanned: usize,
    pub referenced: usize,
    pub deleted: Vec<String>,
    /// Unreferenced but younger than the grace period (maybe a writer in flight).
    pub kept_recent: usize,
    /// Unreferenced but recorded by a writer in flight (`pending_objects`).
    pub kept_pending: usize,
    /// Incomplete multipart uploads aborted (S3: their writer died mid-upload), as
    /// `path (upload id)`.
    pub uploads_aborted: Vec<String>,
    /// Multipart uploads in flight left alone: their writer renews their record, or they are
    /// younger than the grace period.
    pub uploads_in_flight: usize,
}

/// What one locked batch of [`Store::gc`] did.
struct BatchOutcome {
    referenced: usize,
    pending: usize,
    deleted: Vec<String>,
}

/// The longest grace period gc accepts: ten years, far beyond any writer in flight.
pub const MAX_GRACE_SECONDS: u64 = 10 * 365 * 86_400;
/// Candidates re-checked and deleted per locked batch (short lock holds; few SQL parameters).
const GC_BATCH: usize = 200;

impl Store {
    /// Paths of every object some catalog row points at.
    pub async fn referenced_objects(&self) -> Result<HashSet<String>, StoreError> {
        let pool = &self.catalog().pool;
        let mut set = HashSet::new();
        for r in sqlx::query("SELECT path FROM data_files").fetch_all(pool).await? {
            set.insert(r.s("path")?);
        }
        for r in sqlx::query("SELECT path FROM media_objects").fetch_all(pool).await? {
            set.insert(r.s("path")?);
        }
        for r in sqlx::query("SELECT prefix, files FROM artifacts").fetch_all(pool).await? {
            set.extend(artifact_paths(&r)?);
        }
        Ok(set)
    }

    /// Removes unreferenced objects older than `grace_seconds` (at most [`MAX_GRACE_SECONDS`]).
    pub async fn gc(&self, grace_seconds: u64, dry_run: bool) -> Result<GcReport, StoreError> {
        // Checked before anything is listed: a grace that overflowed the cutoff used to wrap into
        // the future and delete every unreferenced object, in-flight writers' included.
        let cutoff = i64::try_from(grace_seconds)
            .ok()
            .filter(|g| *g <= MAX_GRACE_SECONDS as i64)
            .and_then(|g| crate::now_ms().checked_sub(g * 1000))
            .ok_or_else(|| {
                StoreError::invalid(format!(
                    "gc grace period of {grace_seconds} s is more than the maximum of {MAX_GRACE_SECONDS} s (10 years)"
                ))
            })?;
        // List first, then read the references: an object committed in between is then
        // seen as referenced, never deleted.
        // Upload records (S3 multipart uploads in flight) are not data objects: handled apart.
        let record_prefix = format!("{}/", crate::objects::UPLOADS_PREFIX);
        let (records, objects): (Vec<_>, Vec<_>) =
            self.objects().list_all().await?.into_iter().partition(|o| o.path.starts_with(&record_prefix));
        let referenced = self.referenced_objects().await?;
        // An export's files are referenced by its job (store/src/exports.rs).
        let live_exports = self.live_export_ids().await?;
        let export_is_live = |path: &str| {
            path.strip_prefix(crate::EXPORTS_PREFIX)
                .and_then(|r| r.strip_prefix('/'))
                .and_then(|r| r.split('/').next())
                .is_some_and(|id| live_exports.contains(id))
        };
        let mut report = GcReport {
            objects_scanned: objects.len(),
            referenced: 0,
            deleted: Vec::new(),
            kept_recent: 0,
            kept_pending: 0,
            uploads_aborted: Vec::new(),
            uploads_in_flight: 0,
        };
        self.abort_lapsed_uploads(records, cutoff, dry_run, &mut report).await?;
        let mut candidates = Vec::new();
        for o in objects {
            if referenced.contains(&o.path) || export_is_live(&o.path) {
                report.referenced += 1;
            } else if o.last_modified_ms > cutoff {
                report.kept_recent += 1;
            } else {
                candidates.push(o.path);
            }
        }
        for batch in candidates.chunks(GC_BATCH) {
            let kept = self.delete_unreferenced(batch, dry_run).await?;
            report.referenced += kept.referenced;
            report.kept_pending += kept.pending;
            report.deleted.extend(kept.deleted);
        }
        for (path, modified_ms) in self.objects().local_staging_files() {
            if modified_ms > cutoff {
                report.kept_recent += 1;
                continue;
            }
            if !dry_run {
                let _ = std::fs::remove_file(&path);
            }
            report.deleted.push(path.display().to_string());
        }
        Ok(report)
    }

    /// Aborts the multipart uploads whose record lapsed (its writer stopped renewing it) and
    /// that are older than the grace period; a record that does not parse is removed once it is
    /// older than the grace period.
    async fn abort_lapsed_uploads(
        &self,
        records: Vec<crate::objects::ObjectEntry>,
        cutoff_ms: i64,
        dry_run: bool,
        report: &mut GcReport,
    ) -> Result<(), StoreError> {
        let now = crate::now_ms();
        for entry in records {
            let bytes = match self.objects().get(&entry.path).await {
                Ok(b) => b,
                Err(StoreError::NotFound { .. }) => continue, // finished meanwhile
                Err(e) => return Err(e),
            };
            let Ok(record) = serde_json::from_slice::<crate::objects::UploadRecord>(&bytes) else {
                if entry.last_modified_ms <= cutoff_ms {
                    if !dry_run {
                        self.objects().delete(&entry.path).await?;
                    }
                    report.deleted.push(entry.path);
                } else {
                    report.kept_recent += 1;
                }
                continue;
            };
            if record.expires_ms > now || record.created_ms > cutoff_ms {
                report.uploads_in_flight += 1;
                continue;
            }
            if !dry_run {
                self.objects().abort_recorded_upload(&entry.path, &record).await?;
            }
            report.uploads_aborted.push(format!("{} ({})", record.path, record.upload_id));
        }
        Ok(())
    }

    /// Re-checks `paths` under the version write lock (and, on Postgres, with writers' new
    /// pending records blocked) and deletes those still unreferenced and not pending before
    /// releasing it.
    async fn delete_unreferenced(&self, paths: &[String], dry_run: bool) -> Result<BatchOutcome, StoreError> {
        let mut tx = self.catalog().begin_version_write().await?;
        if self.backend() == crate::Backend::Postgres {
            sqlx::query("LOCK TABLE pending_objects IN EXCLUSIVE MODE").execute(&mut *tx).await?;
        }
        let list = (1..=paths.len()).map(|i| format!("${i}")).collect::<Vec<_>>().join(", ");
        let mut referenced = HashSet::new();
        for table in ["data_files", "media_objects"] {
            let sql = format!("SELECT path FROM {table} WHERE path IN ({list})");
            let mut q = sqlx::query(&sql);
            for p in paths {
                q = q.bind(p);
            }
            for r in q.fetch_all(&mut *tx).await? {
                referenced.insert(r.s("path")?);
            }
        }
        let sql = format!(
            "SELECT path FROM pending_objects WHERE created_ms > ${} AND path IN ({list})",
            paths.len() + 1
        );
        let mut q = sqlx::query(&sql);
        for p in paths {
            q = q.bind(p);
        }
        let mut pending = HashSet::new();
        for r in q.bind(crate::now_ms() - writer_lease_ms()).fetch_all(&mut *tx).await? {
            pending.insert(r.s("path")?);
        }
        // Artifacts published since the listing (few rows: read them all).
        for r in sqlx::query("SELECT prefix, files FROM artifacts").fetch_all(&mut *tx).await? {
            referenced.extend(artifact_paths(&r)?);
        }
        let mut out = BatchOutcome { referenced: 0, pending: 0, deleted: Vec::new() };
        for p in paths {
            if referenced.contains(p) {
                out.referenced += 1;
            } else if pending.contains(p) {
                out.pending += 1;
            } else {
                if !dry_run {
                    self.objects().delete(p).await?;
                }
                out.deleted.push(p.clone());
            }
        }
        tx.commit().await?;
        Ok(out)
    }

    /// Records that `writer` is about to upload or re-use the object `path` (see the module docs).
    pub(crate) async fn register_pending(&self, writer: &str, path: &str) -> Result<(), StoreError> {
        sqlx::query("INSERT INTO pending_objects (path, writer, created_ms) VALUES ($1, $2, $3) ON CONFLICT DO NOTHING")
            .bind(path)
            .bind(writer)
            .bind(crate::now_ms())
            .execute(&self.catalog().pool)
            .await?;
        Ok(())
    }

    /// Writes content-addressed objects that `writer` is about to reference from a row: each is
    /// recorded as pending first, so gc keeps it until that row commits in a transaction that
    /// also runs [`forget_pending`] (as an artifact's publication does).
    pub async fn put_pending_content(
        &self,
        writer: &str,
        objects: Vec<(String, Bytes)>,
    ) -> Result<(), StoreError> {
        for (path, _) in &objects {
            self.register_pending(writer, path).await?;
        }
        for (path, data) in objects {
            self.objects().put_content_addressed(&path, data).await?;
        }
        Ok(())
    }

    /// Renews a writer's pending records (its lease): see [`writer_lease_ms`](crate::objects::writer_lease_ms).
    pub(crate) async fn renew_pending(&self, writer: &str) -> Result<(), StoreError> {
        sqlx::query("UPDATE pending_objects SET created_ms = $1 WHERE writer = $2")
            .bind(crate::now_ms())
            .bind(writer)
            .execute(&self.catalog().pool)
            .await?;
        Ok(())
    }

    /// Forgets a writer's pending records inside `tx`, which holds the version lock and is about
    /// to reference `path` (or leave it to gc): true if `path`'s record was still within its
    /// lease, so no gc can have deleted the object (gc deletes under that lock, and only objects
    /// whose lease had lapsed).
    pub(crate) async fn release_pending(
        tx: &mut crate::catalog::Tx,
        writer: &str,
        path: &str,
    ) -> Result<bool, StoreError> {
        let rows = sqlx::query("DELETE FROM pending_objects WHERE writer = $1 RETURNING path, created_ms")
            .bind(writer)
            .fetch_all(&mut **tx)
            .await?;
        let since = crate::now_ms() - writer_lease_ms();
        let mut live = false;
        for r in &rows {
            live |= r.s("path")? == path && r.i("created_ms")? >= since;
        }
        Ok(live)
    }

    /// Forgets a writer's pending records outside a commit (after a publish, or an abort).
    pub(crate) async fn clear_pending(&self, writer: &str) -> Result<(), StoreError> {
        sqlx::query("DELETE FROM pending_objects WHERE writer = $1")
            .bind(writer)
            .execute(&self.catalog().pool)
            .await?;
        Ok(())
    }
}

/// Forgets all of `writer`'s pending records inside `tx`, the transaction that commits the rows
/// referencing its objects ([`Store::put_pending_content`]).
pub async fn forget_pending(tx: &mut crate::catalog::Tx, writer: &str) -> Result<(), StoreError> {
    sqlx::query("DELETE FROM pending_objects WHERE writer = $1").bind(writer).execute(&mut **tx).await?;
    Ok(())
}

/// The object paths of an artifact row (`prefix`, `files`: the JSON list of its files, each
/// named inside the prefix; `store-artifacts` writes them).
fn artifact_paths(r: &sqlx::any::AnyRow) -> Result<Vec<String>, StoreError> {
    #[derive(serde::Deserialize)]
    struct Named {
        name: String,
    }
    let prefix = r.s("prefix")?;
    let files: Vec<Named> = serde_json::from_str(&r.s("files")?)?;
    Ok(files.into_iter().map(|f| format!("{prefix}/{}", f.name)).collect())
}
