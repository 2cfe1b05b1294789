//! Exports: a version, split or filter of the store (optionally curated by a verifier's
//! episode scores) exported as a LeRobot v3.0 dataset or a robomimic HDF5 file by a worker, as a
//! job; its files are then listed and downloaded (with range requests) from the store, and
//! deleted when no longer wanted.

use super::*;
use axum::routing::delete;
use store_jobs::JobQueue;

/// The routes of this resource (behind the token check).
pub(crate) fn router() -> Router<AppState> {
    Router::new()
        .route("/v1/exports", get(list_exports).post(create_export.layer(need!(Role::Trainer))))
        .route("/v1/exports/{id}", get(get_export).merge(delete(delete_export.layer(need!(Role::Trainer)))))
        .route("/v1/exports/{id}/files/{*path}", get(export_file))
}

/// The formats an export writes: LeRobot v3.0 or a robomimic HDF5 file.
#[derive(ToSchema)]
#[schema(rename_all = "lowercase")]
#[allow(dead_code)]
pub enum ExportFormat {
    Lerobot,
    Robomimic,
}

/// A deleted export.
#[derive(Serialize, ToSchema)]
pub struct ExportDeleted {
    export_id: String,
    files_deleted: u64,
}

#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ExportCreate {
    #[schema(value_type = ExportFormat)]
    format: String,
    /// Store version (default: the head at the time the job runs; a split pins its own).
    version: Option<i64>,
    split: Option<String>,
    policy: Option<String>,
    checkpoint: Option<String>,
    task: Option<String>,
    /// The version's frozen labels.
    #[schema(value_type = Option<store::Label>)]
    label: Option<String>,
    tag: Option<String>,
    /// Keep only the episodes a verifier scores within a range.
    score: Option<ExportScore>,
    /// Layers to carry as observation columns (see `GET /v1/layers`); every selected episode
    /// must hold them.
    #[serde(default)]
    #[schema(max_items = 16)]
    layers: Vec<LayerName>,
}

/// A layer name (`GET /v1/layers`).
#[derive(Deserialize, ToSchema)]
#[schema(value_type = String, pattern = r"^[A-Za-z0-9._-]{1,120}$")]
pub struct LayerName(String);

/// An export's curation by a verifier: the episodes `artifact` scores in [min, max] (an
/// episode's score is its mean success probability or value over its steps).
#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ExportScore {
    /// The verifier: an artifact id or POLICY/CHECKPOINT/KIND@ALIAS (the alias is resolved when
    /// the export is queued, so the job names one artifact).
    artifact: String,
    /// The lowest score kept (default: no lower bound).
    min: Option<f64>,
    /// The highest score kept (default: no upper bound); at least `min`.
    max: Option<f64>,
}

/// An export job and, once it succeeded, its files.
#[derive(Serialize, ToSchema)]
pub struct ExportStatus {
    job: store_jobs::JobRecord,
    files: Vec<store::ExportFile>,
}

async fn export_job(s: &AppState, id: &str) -> ApiResult<store_jobs::JobRecord> {
    check_id("export id", id)?;
    let job = s.store().job(id).await?;
    if job.kind != store_jobs::JobKind::Export {
        return Err(ApiError::not_found(format!("export {id} not found")));
    }
    Ok(job)
}

/// Queues an export; the job's spec is `{format, selection}` (export::job::ExportJobSpec).
#[utoipa::path(post, path = "/v1/exports", tag = "exports", request_body = ExportCreate,
    responses((status = 201, description = "the queued export job", body = store_jobs::JobRecord),
              (status = 403, description = "the token's role is below trainer"), (status = 404, description = "no such split, version or artifact")))]
pub async fn create_export(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiJson(b): ApiJson<ExportCreate>,
) -> ApiResult<(StatusCode, Json<store_jobs::JobRecord>)> {
    caller.require(Role::Trainer)?;
    for (what, v) in
        [("policy", &b.policy), ("checkpoint", &b.checkpoint), ("task", &b.task), ("tag", &b.tag)]
    {
        if let Some(v) = v {
            check_name(what, v)?;
        }
    }
    if let Some(split) = &b.split {
        check_id("split id", split)?;
        s.store().split(split).await?;
    }
    if let Some(v) = b.version {
        s.store().version(v).await?;
    }
    if b.layers.len() > 16 {
        return Err(ApiError::bad_request("at most 16 layers"));
    }
    for l in &b.layers {
        store::check_layer_name(&l.0)?;
    }
    let label = b.label.as_deref().map(parse_label).transpose()?;
    let score = match &b.score {
        Some(r) => {
            let artifact = s.store().resolve_artifact(&r.artifact).await?.id;
            if r.min.zip(r.max).is_some_and(|(lo, hi)| lo > hi) {
                return Err(ApiError::bad_request("score: min must not exceed max"));
            }
            Some(store::ScoreRange { artifact, min: r.min, max: r.max })
        }
        None => None,
    };
    let spec = ::export::job::ExportJobSpec {
        format: b.format,
        selection: store::Selection {
            version: b.version,
            split: b.split,
            policy: b.policy,
            checkpoint: b.checkpoint,
            task: b.task,
            label,
            tag: b.tag,
            score,
            layers: b.layers.into_iter().map(|l| l.0).collect(),
        },
    };
    spec.check().map_err(|e| ApiError::bad_request(e.to_string()))?;
    let spec = serde_json::to_value(&spec).map_err(|e| ApiError::internal(e.to_string()))?;
    let job = s.store().create_job(store_jobs::JobKind::Export, &spec, &caller.name).await?;
    Ok((StatusCode::CREATED, Json(job)))
}

/// Export jobs, newest first.
#[utoipa::path(get, path = "/v1/exports", tag = "exports",
    responses((status = 200, body = Vec<store_jobs::JobRecord>)))]
pub async fn list_exports(State(s): State<AppState>) -> ApiResult<Json<Vec<store_jobs::JobRecord>>> {
    let mut jobs: Vec<store_jobs::JobRecord> =
        s.store().jobs(None).await?.into_iter().filter(|j| j.kind == store_jobs::JobKind::Export).collect();
    jobs.sort_by(|a, b| b.created_at.cmp(&a.created_at));
    Ok(Json(jobs))
}

/// An export: its job (state, progress, result) and, once it succeeded, its files.
#[utoipa::path(get, path = "/v1/exports/{id}", tag = "exports", params(("id" = String, Path)),
    responses((status = 200, body = ExportStatus), (status = 404, description = "no such export")))]
pub async fn get_export(
    State(s): State<AppState>,
    ApiPath(id): ApiPath<String>,
) -> ApiResult<Json<ExportStatus>> {
    let job = export_job(&s, &id).await?;
    let files = if job.state == store_jobs::JobState::Succeeded {
        s.store().export_files(&id).await?
    } else {
        Vec::new()
    };
    Ok(Json(ExportStatus { job, files }))
}

/// One file of a finished export (range requests supported).
#[utoipa::path(get, path = "/v1/exports/{id}/files/{path}", tag = "exports",
    params(("id" = String, Path), ("path" = String, Path, description = "a path inside the export, e.g. meta/info.json")),
    responses((status = 200, description = "the file", content_type = "*/*", body = FileBytes),
              (status = 206, description = "a range of the file", content_type = "*/*", body = FileBytes),
              (status = 404, description = "no such export or file"), (status = 416, description = "the range is outside the file")))]
pub async fn export_file(
    State(s): State<AppState>,
    ApiPath((id, path)): ApiPath<(String, String)>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    let job = export_job(&s, &id).await?;
    if job.state != store_jobs::JobState::Succeeded {
        return Err(ApiError::not_found(format!("export {id} has no files (job {})", job.state.as_str())));
    }
    let (object, size) = s.store().export_object(&id, &path).await?;
    crate::media::serve_object(s.store(), &object, Some(size), headers.get(header::RANGE)).await
}

/// Deletes a finished export's files (the job record stays, for its history).
#[utoipa::path(delete, path = "/v1/exports/{id}", tag = "exports", params(("id" = String, Path)),
    responses((status = 200, body = ExportDeleted), (status = 403, description = "the token's role is below trainer"),
              (status = 404, description = "no such export"), (status = 409, description = "the export is queued or running")))]
pub async fn delete_export(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiPath(id): ApiPath<String>,
) -> ApiResult<Json<ExportDeleted>> {
    caller.require(Role::Trainer)?;
    let job = export_job(&s, &id).await?;
    if matches!(job.state, store_jobs::JobState::Queued | store_jobs::JobState::Running) {
        return Err(ApiError::new(
            StatusCode::CONFLICT,
            "conflict",
            format!("export {id} is {}: cancel it first", job.state.as_str()),
        ));
    }
    let n = s.store().delete_export_files(&id).await?;
    Ok(Json(ExportDeleted { export_id: id, files_deleted: n as u64 }))
}
