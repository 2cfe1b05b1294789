//! Garbage collection: deletes objects no committed version references (left by crashed or
//! aborted writers), after a grace period that protects writers still in flight.

use crate::catalog::RowExt;
use crate::{Store, StoreError};
use serde::Serialize;
use std::collections::HashSet;

#[derive(Debug, Clone, Serialize)]
pub struct GcReport {
    pub objects_scanned: usize,
    pub referenced: usize,
    pub deleted: Vec<String>,
    /// Unreferenced but younger than the grace period (maybe a writer in flight).
    pub kept_recent: usize,
}

/// The longest grace period gc accepts: ten years, far beyond any writer in flight.
pub const MAX_GRACE_SECONDS: u64 = 10 * 365 * 86_400;

impl Store {
    /// Paths of every object some catalog row points at.
    pub async fn referenced_objects(&self) -> Result<HashSet<String>, StoreError> {
        let pool = &self.db().pool;
        let mut set = HashSet::new();
        for r in sqlx::query("SELECT path FROM data_files").fetch_all(pool).await? {
            set.insert(r.s("path")?);
        }
        for r in sqlx::query("SELECT path FROM media_objects").fetch_all(pool).await? {
            set.insert(r.s("path")?);
        }
        for a in self.artifacts(None, None, None).await? {
            for f in &a.files {
                set.insert(format!("{}/{}", a.prefix, f.name));
            }
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
        let objects = self.objects().list_all().await?;
        let referenced = self.referenced_objects().await?;
        let mut report =
            GcReport { objects_scanned: objects.len(), referenced: 0, deleted: Vec::new(), kept_recent: 0 };
        for o in objects {
            if referenced.contains(&o.path) {
                report.referenced += 1;
            } else if o.last_modified_ms > cutoff {
                report.kept_recent += 1;
            } else {
                if !dry_run {
                    self.objects().delete(&o.path).await?;
                }
                report.deleted.push(o.path);
            }
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
}
