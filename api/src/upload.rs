//! `POST /v1/ingest`: the request body (a rollout file or archive) is streamed to a fresh file
//! under the server's upload dir — never held in memory — hashed on the way, and an `ingest`
//! job is queued whose spec names the server-side path. The runner does the ingest itself.
//!
//! Uploads do not pile up: the worker deletes an upload's folder once its job has finished
//! (succeeded or failed; a worker that dies leaves it for the retry), [`sweep`] deletes folders
//! of jobs that ended otherwise (cancelled, lost) and folders no job names, and an upload is
//! refused with 507 when the disk would be left with less than [`MIN_FREE_BYTES`].

use crate::auth::Caller;
use crate::error::{ApiError, ApiResult};
use crate::extract::{check_name, ApiQuery};
use crate::AppState;
use axum::body::Body;
use axum::extract::State;
use axum::http::{header, StatusCode};
use axum::{Extension, Json};
use futures::StreamExt;
use serde::Deserialize;
use serde_json::json;
use sha2::Digest;
use std::sync::atomic::Ordering;
use store::Role;
use store_artifacts::Artifacts;
use store_jobs::JobQueue;
use tokio::io::AsyncWriteExt;
use utoipa::IntoParams;

#[derive(Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct IngestQuery {
    /// The policy the rollouts belong to.
    policy: String,
    /// The checkpoint the rollouts belong to.
    checkpoint: String,
    /// The uploaded file's name (only its characters A-Z a-z 0-9 . _ - are kept; it tells the
    /// ingester the format by its extension). Default `upload.bin`.
    filename: Option<String>,
    /// The format, if the extension does not tell (`robomimic`, `lerobot`, `mcap`, ...).
    format: Option<String>,
    /// The evaluation run the rollouts belong to (see `GET /v1/scoreboard`). Default, when
    /// `steering`, `run_artifact` or `run_tags` is given: the steering as written (`base`,
    /// `bon:10`, ...); with none of them, the rollouts belong to no run.
    run: Option<String>,
    /// How the run was steered: `base`, `bon:N`, `cg:LAMBDA` or `flow:LAMBDA` (default `base`).
    steering: Option<String>,
    /// The verifier artifact that steered the run.
    run_artifact: Option<String>,
    /// The run's tags, comma-separated.
    run_tags: Option<String>,
    /// How image cameras are stored: `png` (default: lossless, one PNG per step) or `video`
    /// (one H.264 MP4 per episode and camera: lossy, a fraction of the bytes).
    #[param(inline)]
    images: Option<store::ImageStorage>,
}

/// Free space an upload must leave on the upload dir's filesystem.
pub const MIN_FREE_BYTES: u64 = 1 << 30;

/// Bytes available to us on the filesystem holding `dir`.
#[allow(unsafe_code, reason = "statvfs(3) has no safe wrapper in std")]
fn free_bytes(dir: &std::path::Path) -> Option<u64> {
    use std::os::unix::ffi::OsStrExt;
    let c = std::ffi::CString::new(dir.as_os_str().as_bytes()).ok()?;
    // SAFETY: statvfs is plain integers, for which all zeroes is a valid value.
    let mut st: libc::statvfs = unsafe { std::mem::zeroed() };
    // SAFETY: `c` is a valid NUL-terminated path and `st` a properly sized out-parameter.
    let rc = unsafe { libc::statvfs(c.as_ptr(), &mut st) };
    (rc == 0).then(|| (st.f_bavail as u64).saturating_mul(st.f_frsize as u64))
}

/// An upload folder is named by 32 hex digits (a v4 uuid) directly under the upload dir.
fn is_upload_folder(dir: &std::path::Path) -> bool {
    dir.file_name()
        .and_then(|n| n.to_str())
        .is_some_and(|n| n.len() == 32 && n.bytes().all(|b| b.is_ascii_hexdigit()))
}

/// Deletes the upload folder an ingest job's spec names (after the job finished).
pub(crate) async fn remove_upload(spec: &serde_json::Value) {
    let Some(dir) = spec.get("upload_dir").and_then(|v| v.as_str()).map(std::path::PathBuf::from) else {
        return;
    };
    if is_upload_folder(&dir) {
        if let Err(e) = tokio::fs::remove_dir_all(&dir).await {
            if e.kind() != std::io::ErrorKind::NotFound {
                tracing::warn!("cannot delete the upload {}: {e}", dir.display());
            }
        }
    }
}

/// Deletes upload folders nobody will ingest: those of ingest jobs that are no longer queued or
/// running, and those older than `orphan_age` that no job names (a server stopped between the
/// upload and queueing its job). Returns how many it deleted.
pub async fn sweep(
    store: &store::Store,
    upload_dir: &std::path::Path,
    orphan_age: std::time::Duration,
) -> anyhow::Result<usize> {
    use store_jobs::JobState::*;
    let Ok(mut rd) = tokio::fs::read_dir(upload_dir).await else { return Ok(0) };
    let mut live = std::collections::HashSet::new();
    let mut named = std::collections::HashSet::new();
    for j in store.jobs(None).await?.into_iter().filter(|j| j.kind == store_jobs::JobKind::Ingest) {
        if let Some(d) = j.spec.get("upload_dir").and_then(|v| v.as_str()) {
            named.insert(std::path::PathBuf::from(d));
            if matches!(j.state, Queued | Running) {
                live.insert(std::path::PathBuf::from(d));
            }
        }
    }
    let mut deleted = 0;
    while let Some(e) = rd.next_entry().await? {
        let dir = e.path();
        if !is_upload_folder(&dir) || live.contains(&dir) {
            continue;
        }
        let old = e
            .metadata()
            .await
            .ok()
            .and_then(|m| m.modified().ok())
            .and_then(|t| t.elapsed().ok())
            .is_some_and(|a| a >= orphan_age);
        if named.contains(&dir) || old {
            tokio::fs::remove_dir_all(&dir).await?;
            deleted += 1;
        }
    }
    Ok(deleted)
}

/// A file name safe to use under our own directory: no separators, no leading dots.
pub fn sanitize_filename(name: &str) -> String {
    let base = name.rsplit(['/', '\\']).next().unwrap_or("");
    let s: String = base
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() || c == '.' || c == '_' || c == '-' { c } else { '_' })
        .collect();
    let s = s.trim_start_matches('.');
    let s: String = s.chars().take(100).collect();
    if s.is_empty() {
        "upload.bin".into()
    } else {
        s
    }
}

/// Uploads a rollout file (raw request body) and queues an ingest job (admin).
#[utoipa::path(post, path = "/v1/ingest", tag = "admin", params(IngestQuery),
    request_body(content = crate::body_schemas::UploadBytes, content_type = "application/octet-stream", description = "the file, raw (not empty)"),
    responses((status = 202, description = "the queued ingest job", body = store_jobs::JobRecord),
              (status = 413, description = "larger than the server's upload limit"),
              (status = 404, description = "no such run artifact"),
              (status = 403, description = "the token's role is below admin"),
              (status = 507, description = "the upload would leave too little free disk")))]
pub async fn ingest(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiQuery(q): ApiQuery<IngestQuery>,
    headers: axum::http::HeaderMap,
    body: Body,
) -> ApiResult<(StatusCode, Json<store_jobs::JobRecord>)> {
    caller.require(Role::Admin)?;
    check_name("policy", &q.policy)?;
    check_name("checkpoint", &q.checkpoint)?;
    if let Some(f) = &q.format {
        crate::extract::check_id("format", f)?;
    }
    let run_tags: Vec<String> = q
        .run_tags
        .as_deref()
        .map(|t| t.split(',').filter(|x| !x.is_empty()).map(String::from).collect())
        .unwrap_or_default();
    let run = store::RunInput::from_parts(
        q.run.as_deref(),
        q.steering.as_deref(),
        q.run_artifact.as_deref(),
        &run_tags,
    )?;
    if let Some(a) = run.as_ref().and_then(|r| r.artifact_id.as_ref()) {
        s.store().artifact(a).await?;
    }
    let filename = sanitize_filename(q.filename.as_deref().unwrap_or("upload.bin"));
    // Refuse what would fill the disk (the declared length; the floor alone without one).
    let declared =
        headers.get(header::CONTENT_LENGTH).and_then(|v| v.to_str().ok()).and_then(|v| v.parse::<u64>().ok());
    if let Some(free) = free_bytes(&s.inner.cfg.upload_dir) {
        let need = declared.unwrap_or(0).saturating_add(MIN_FREE_BYTES);
        if free < need {
            return Err(ApiError::new(
                StatusCode::INSUFFICIENT_STORAGE,
                "insufficient-storage",
                format!(
                    "the server has {} MB free for uploads; this one needs {} MB (with {} MB to spare)",
                    free >> 20,
                    need >> 20,
                    MIN_FREE_BYTES >> 20
                ),
            ));
        }
    }
    let dir = s.inner.cfg.upload_dir.join(uuid::Uuid::new_v4().simple().to_string());
    tokio::fs::create_dir_all(&dir)
        .await
        .map_err(|e| ApiError::internal(format!("cannot create the upload dir: {e}")))?;
    let path = dir.join(&filename);
    let part = dir.join(format!(".{filename}.part"));
    let result = receive(&s, body, &part).await;
    let (size, sha) = match result {
        Ok(v) => v,
        Err(e) => {
            let _ = tokio::fs::remove_dir_all(&dir).await;
            return Err(e);
        }
    };
    tokio::fs::rename(&part, &path)
        .await
        .map_err(|e| ApiError::internal(format!("cannot place the upload: {e}")))?;
    let spec = json!({
        "path": path.display().to_string(),
        "upload_dir": dir.display().to_string(),
        "filename": filename,
        "policy": q.policy,
        "checkpoint": q.checkpoint,
        "format": q.format,
        "sha256": sha,
        "size_bytes": size,
        "run": run.as_ref().map(|r| &r.name),
        "steering": run.as_ref().map(|r| r.steering.to_string()),
        "run_artifact": q.run_artifact,
        "run_tags": run_tags,
        "images": q.images.map(store::ImageStorage::as_str),
    });
    let job = s.store().create_job(store_jobs::JobKind::Ingest, &spec, &caller.name).await?;
    Ok((StatusCode::ACCEPTED, Json(job)))
}

async fn receive(s: &AppState, body: Body, part: &std::path::Path) -> ApiResult<(u64, String)> {
    let limit = s.inner.cfg.upload_limit_bytes;
    let mut file = tokio::fs::File::create(part)
        .await
        .map_err(|e| ApiError::internal(format!("cannot create the upload file: {e}")))?;
    let mut hasher = sha2::Sha256::new();
    let mut size: u64 = 0;
    let mut stream = body.into_data_stream();
    while let Some(chunk) = stream.next().await {
        let chunk = chunk.map_err(|e| ApiError::bad_request(format!("upload interrupted: {e}")))?;
        size += chunk.len() as u64;
        if size > limit {
            return Err(ApiError::new(
                StatusCode::PAYLOAD_TOO_LARGE,
                "too-large",
                format!("the upload is larger than the server's limit of {limit} bytes"),
            ));
        }
        hasher.update(&chunk);
        file.write_all(&chunk)
            .await
            .map_err(|e| ApiError::internal(format!("cannot write the upload: {e}")))?;
        s.inner.metrics.uploads_bytes.fetch_add(chunk.len() as u64, Ordering::Relaxed);
    }
    if size == 0 {
        return Err(ApiError::bad_request("the upload is empty"));
    }
    file.sync_all().await.map_err(|e| ApiError::internal(format!("cannot sync the upload: {e}")))?;
    Ok((size, hex::encode(hasher.finalize())))
}
