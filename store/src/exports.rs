//! Finished exports (`POST /v1/exports`) kept in the object store under `exports/<job id>/`, so
//! every API server and worker of a scale-out deployment sees the same files. An export's files
//! live as long as its job record says it is wanted: gc keeps them while the job is queued,
//! running or succeeded, and collects those of failed or cancelled jobs (a worker that died
//! mid-upload leaves a partial folder) after the grace period.

use crate::catalog::RowExt;
use crate::{Store, StoreError};
use serde::Serialize;
use std::collections::HashSet;

/// The object-store folder holding every export.
pub const EXPORTS_PREFIX: &str = "exports";

/// One file of an export: its path inside the exported dataset and its size.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Serialize)]
pub struct ExportFile {
    pub path: String,
    pub bytes: u64,
}

/// A path inside an export: relative, `/`-separated, no empty, `.` or `..` parts.
pub fn check_export_path(rel: &str) -> Result<(), StoreError> {
    let ok = !rel.is_empty()
        && rel.len() <= 1024
        && rel.split('/').all(|p| {
            !p.is_empty() && p != "." && p != ".." && !p.contains('\\') && !p.chars().any(char::is_control)
        });
    if ok {
        Ok(())
    } else {
        Err(StoreError::invalid(format!("{rel:?} is not a path inside an export")))
    }
}

fn export_folder(export_id: &str) -> Result<String, StoreError> {
    if export_id.is_empty() || !export_id.chars().all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_') {
        return Err(StoreError::invalid(format!("{export_id:?} is not an export id")));
    }
    Ok(format!("{EXPORTS_PREFIX}/{export_id}"))
}

impl Store {
    /// Copies one local file of a finished export into the store (streamed in parts).
    pub async fn put_export_file(
        &self,
        export_id: &str,
        rel: &str,
        local: &std::path::Path,
    ) -> Result<u64, StoreError> {
        check_export_path(rel)?;
        let path = format!("{}/{rel}", export_folder(export_id)?);
        self.objects().put_file(&path, local).await
    }

    /// The files of an export, by path.
    pub async fn export_files(&self, export_id: &str) -> Result<Vec<ExportFile>, StoreError> {
        let folder = export_folder(export_id)?;
        let mut files: Vec<ExportFile> = self
            .objects()
            .list_prefix(&folder)
            .await?
            .into_iter()
            .filter_map(|(p, bytes)| {
                p.strip_prefix(&format!("{folder}/")).map(|r| ExportFile { path: r.to_string(), bytes })
            })
            .collect();
        files.sort_by(|a, b| a.path.cmp(&b.path));
        Ok(files)
    }

    /// The object holding `rel` of an export (for serving it), checked to exist.
    pub async fn export_object(&self, export_id: &str, rel: &str) -> Result<(String, u64), StoreError> {
        check_export_path(rel)?;
        let path = format!("{}/{rel}", export_folder(export_id)?);
        let size = self.objects().size(&path).await.map_err(|e| match e {
            StoreError::NotFound { .. } => StoreError::not_found("export file", format!("{export_id}/{rel}")),
            e => e,
        })?;
        Ok((path, size))
    }

    /// Deletes an export's files; returns how many there were.
    pub async fn delete_export_files(&self, export_id: &str) -> Result<usize, StoreError> {
        let folder = export_folder(export_id)?;
        let files = self.objects().list_prefix(&folder).await?;
        for (p, _) in &files {
            self.objects().delete(p).await?;
        }
        Ok(files.len())
    }

    /// Export jobs whose files gc keeps: queued, running or succeeded (the jobs table is the
    /// catalog's; `store-jobs` queues and runs them).
    pub(crate) async fn live_export_ids(&self) -> Result<HashSet<String>, StoreError> {
        let rows = sqlx::query(
            "SELECT id FROM jobs WHERE kind = 'export' AND state IN ('queued', 'running', 'succeeded')",
        )
        .fetch_all(&self.catalog().pool)
        .await?;
        rows.iter().map(|r| r.s("id")).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn export_paths_stay_inside_the_export() {
        for ok in ["meta/info.json", "data/chunk-000/file-000.parquet", "a.hdf5"] {
            assert!(check_export_path(ok).is_ok(), "{ok}");
        }
        for bad in ["", "/etc/passwd", "a/../../b", "./a", "a//b", "a\\b", "a/\n", ".."] {
            assert!(check_export_path(bad).is_err(), "{bad:?}");
        }
        assert!(export_folder("job-1a2b").is_ok());
        assert!(export_folder("../x").is_err() && export_folder("").is_err());
    }
}
