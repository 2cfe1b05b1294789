//! An export run as a job (`POST /v1/exports`): the selection is exported into a temporary
//! folder on the worker, then each file is copied into the store under `exports/<job id>/`
//! (streamed, so a multi-gigabyte video never sits in memory), where any API server can serve
//! it. A failed or cancelled export removes what it had copied; a worker that dies leaves files
//! that gc collects once the job is no longer live (store/src/exports.rs).

use crate::{ExportError, Result};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use store::{select, ExportFile, Selection, Store};
use verifier::stored::filter_by_score;
use verifier::StepScorer;

/// The job's spec as the API queues it.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ExportJobSpec {
    /// `lerobot` (v3.0) or `robomimic`.
    pub format: String,
    #[serde(default)]
    pub selection: Selection,
}

/// The file name of a robomimic export inside its job folder.
pub const ROBOMIMIC_FILE: &str = "rollouts.hdf5";

impl ExportJobSpec {
    pub fn check(&self) -> Result<()> {
        match self.format.as_str() {
            "lerobot" | "robomimic" => Ok(()),
            f => Err(ExportError::invalid(format!("format {f:?}: expected lerobot or robomimic"))),
        }
    }
}

/// What the job reports: the export's report, the files now in the store, and how many
/// episodes a score filter looked at.
#[derive(Debug, Clone, Serialize)]
pub struct ExportJobResult {
    pub report: crate::ExportReport,
    pub files: Vec<ExportFile>,
    pub episodes_scored: Option<usize>,
}

fn files_under(root: &Path, dir: &Path, out: &mut Vec<(String, PathBuf)>) -> Result<()> {
    for e in std::fs::read_dir(dir).map_err(|e| ExportError::io(dir, e))? {
        let e = e.map_err(|err| ExportError::io(dir, err))?;
        let p = e.path();
        if e.file_type().map_err(|err| ExportError::io(&p, err))?.is_dir() {
            files_under(root, &p, out)?;
        } else {
            let rel = p.strip_prefix(root).expect("under root").to_string_lossy().replace('\\', "/");
            out.push((rel, p));
        }
    }
    Ok(())
}

/// Runs an export job: `progress` gets `{phase, done, total}` updates, `cancelled` is polled
/// between files and phases.
pub async fn run_export_job(
    store: &Store,
    job_id: &str,
    spec: &ExportJobSpec,
    scorer: Option<&dyn StepScorer>,
    progress: &(dyn Fn(serde_json::Value) + Send + Sync),
    cancelled: &(dyn Fn() -> bool + Send + Sync),
) -> Result<ExportJobResult> {
    spec.check()?;
    let mut sel = select(store, &spec.selection).await?;
    if let Some(s) = scorer {
        let tick = |done: usize, total: usize| {
            progress(serde_json::json!({"phase": "scoring", "done": done, "total": total}))
        };
        filter_by_score(store, &mut sel, s, Some(&tick)).await?;
    } else if spec.selection.score.is_some() {
        return Err(ExportError::invalid("the selection has a score range but no scorer was given"));
    }
    if cancelled() {
        return Err(ExportError::invalid("cancelled"));
    }
    let tmp = tempfile::tempdir().map_err(|e| ExportError::io(&std::env::temp_dir(), e))?;
    let tick = |done: usize, total: usize| {
        progress(serde_json::json!({"phase": "exporting", "done": done, "total": total}))
    };
    let (mut report, root) = if spec.format == "lerobot" {
        let out = tmp.path().join("dataset");
        (crate::lerobot::export(store, &sel, &out, Some(&tick)).await?, out)
    } else {
        let out = tmp.path().join(ROBOMIMIC_FILE);
        (crate::robomimic::export(store, &sel, &out, Some(&tick)).await?, tmp.path().to_path_buf())
    };
    let mut local = Vec::new();
    files_under(&root, &root, &mut local)?;
    local.sort();
    let total = local.len();
    let copied: Result<Vec<ExportFile>> = async {
        let mut files = Vec::with_capacity(total);
        for (i, (rel, path)) in local.iter().enumerate() {
            if cancelled() {
                return Err(ExportError::invalid("cancelled"));
            }
            let bytes = store.put_export_file(job_id, rel, path).await?;
            files.push(ExportFile { path: rel.clone(), bytes });
            progress(serde_json::json!({"phase": "uploading", "done": i + 1, "total": total}));
        }
        Ok(files)
    }
    .await;
    match copied {
        Ok(files) => {
            report.path = PathBuf::from(format!("{}/{job_id}", store::EXPORTS_PREFIX));
            Ok(ExportJobResult { report, files, episodes_scored: sel.scored })
        }
        Err(e) => {
            let _ = store.delete_export_files(job_id).await;
            Err(e)
        }
    }
}
