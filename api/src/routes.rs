//! The `/v1` handlers. Each one checks the caller's role, validates ids and calls the store:
//! every rule (label revisions, splits, leases, aliases) lives in the store, not here.

use crate::auth::Caller;
use crate::error::{ApiError, ApiResult, Problem};
use crate::extract::{check_id, check_name, ApiJson, ApiPath, ApiQuery};
use crate::AppState;
use axum::body::Body;
use axum::extract::State;
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::{Extension, Json};
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};
use std::sync::atomic::Ordering;
use store::{EpisodeFilter, Label, LabelUpdate, Role};
use utoipa::{IntoParams, ToSchema};

pub const ARROW_STREAM: &str = "application/vnd.apache.arrow.stream";

fn parse_label(s: &str) -> ApiResult<Label> {
    s.parse::<Label>().map_err(ApiError::from)
}

// ---------------------------------------------------------------- catalog

/// Policy names.
#[utoipa::path(get, path = "/v1/policies", tag = "catalog",
    responses((status = 200, body = Vec<String>), (status = 401, body = Problem)))]
pub async fn list_policies(State(s): State<AppState>) -> ApiResult<Json<Vec<String>>> {
    Ok(Json(s.store().policies().await?))
}

#[derive(Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct CheckpointQuery {
    /// Only this policy's checkpoints.
    policy: Option<String>,
}

#[derive(Serialize, ToSchema)]
pub struct CheckpointRef {
    policy: String,
    checkpoint: String,
}

/// `(policy, checkpoint)` pairs.
#[utoipa::path(get, path = "/v1/checkpoints", tag = "catalog", params(CheckpointQuery),
    responses((status = 200, body = Vec<CheckpointRef>), (status = 401, body = Problem)))]
pub async fn list_checkpoints(
    State(s): State<AppState>,
    ApiQuery(q): ApiQuery<CheckpointQuery>,
) -> ApiResult<Json<Vec<CheckpointRef>>> {
    let v = s.store().checkpoints(q.policy.as_deref()).await?;
    Ok(Json(v.into_iter().map(|(policy, checkpoint)| CheckpointRef { policy, checkpoint }).collect()))
}

/// Task names.
#[utoipa::path(get, path = "/v1/tasks", tag = "catalog",
    responses((status = 200, body = Vec<String>), (status = 401, body = Problem)))]
pub async fn list_tasks(State(s): State<AppState>) -> ApiResult<Json<Vec<String>>> {
    Ok(Json(s.store().tasks().await?))
}

/// Every committed version, oldest first.
#[utoipa::path(get, path = "/v1/versions", tag = "versions",
    responses((status = 200, description = "VersionInfo list", body = Vec<Object>), (status = 401, body = Problem)))]
pub async fn list_versions(State(s): State<AppState>) -> ApiResult<Json<Vec<store::VersionInfo>>> {
    Ok(Json(s.store().versions().await?))
}

/// One version.
#[utoipa::path(get, path = "/v1/versions/{version}", tag = "versions",
    params(("version" = i64, Path)),
    responses((status = 200, description = "VersionInfo", body = Object), (status = 404, body = Problem)))]
pub async fn get_version(State(s): State<AppState>, ApiPath(v): ApiPath<i64>) -> ApiResult<Json<store::VersionInfo>> {
    Ok(Json(s.store().version(v).await?))
}

/// Episodes added/removed and labels changed between two versions.
#[utoipa::path(get, path = "/v1/versions/{from}/diff/{to}", tag = "versions",
    params(("from" = i64, Path), ("to" = i64, Path)),
    responses((status = 200, description = "VersionDiff", body = Object), (status = 404, body = Problem)))]
pub async fn diff_versions(State(s): State<AppState>, ApiPath((from, to)): ApiPath<(i64, i64)>) -> ApiResult<Json<Value>> {
    let d = s.store().diff(from, to).await?;
    Ok(Json(json!({
        "from": d.from, "to": d.to,
        "episodes_added": d.episodes_added,
        "episodes_removed": d.episodes_removed,
        "labels_changed": d.labels_changed.iter()
            .map(|(id, a, b)| json!({"episode_id": id, "from": a, "to": b})).collect::<Vec<_>>(),
    })))
}

// ---------------------------------------------------------------- episodes

#[derive(Deserialize, IntoParams, Default)]
#[into_params(parameter_in = Query)]
pub struct EpisodeQuery {
    policy: Option<String>,
    checkpoint: Option<String>,
    task: Option<String>,
    /// `success`, `failure` or `unknown`.
    label: Option<String>,
    label_source: Option<String>,
    tag: Option<String>,
    /// Read the store as of this version (labels frozen in it); default: now.
    version: Option<i64>,
    /// Cursor: the `next_cursor` of the previous page.
    after: Option<String>,
    /// Page size, 1-1000 (default 100).
    limit: Option<i64>,
    /// Sort order; only `id` (ascending, the cursor order) is supported.
    sort: Option<String>,
}

#[derive(Serialize, ToSchema)]
pub struct EpisodePage {
    #[schema(value_type = Vec<Object>)]
    episodes: Vec<store::EpisodeRecord>,
    /// Pass as `after` for the next page; absent on the last page.
    next_cursor: Option<String>,
}

/// Lists episodes with filters and cursor pagination.
#[utoipa::path(get, path = "/v1/episodes", tag = "episodes", params(EpisodeQuery),
    responses((status = 200, body = EpisodePage), (status = 400, body = Problem), (status = 401, body = Problem)))]
pub async fn list_episodes(State(s): State<AppState>, ApiQuery(q): ApiQuery<EpisodeQuery>) -> ApiResult<Json<EpisodePage>> {
    match q.sort.as_deref() {
        None | Some("id") => {}
        Some(other) => {
            return Err(ApiError::bad_request(format!("unsupported sort {other:?}: only \"id\" (the cursor order)")))
        }
    }
    let limit = q.limit.unwrap_or(100);
    if !(1..=1000).contains(&limit) {
        return Err(ApiError::bad_request(format!("limit {limit} must be in 1..=1000")));
    }
    if let Some(a) = &q.after {
        check_id("cursor", a)?;
    }
    let filter = EpisodeFilter {
        version: q.version,
        id: None,
        policy: q.policy,
        checkpoint: q.checkpoint,
        task: q.task,
        label: q.label.as_deref().map(parse_label).transpose()?,
        label_source: q.label_source,
        tag: q.tag,
        after: q.after,
        limit: Some(limit + 1),
    };
    let mut episodes = s.store().episodes(&filter).await?;
    let next_cursor = if episodes.len() as i64 > limit {
        episodes.truncate(limit as usize);
        episodes.last().map(|e| e.id.clone())
    } else {
        None
    };
    Ok(Json(EpisodePage { episodes, next_cursor }))
}

#[derive(Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct VersionQuery {
    /// As of this version; default: now.
    version: Option<i64>,
}

fn etag(revision: i64) -> HeaderValue {
    HeaderValue::from_str(&format!("\"{revision}\"")).expect("digits are a valid header")
}

/// An episode: metadata, current label (its revision is also the `ETag`) and label history.
#[utoipa::path(get, path = "/v1/episodes/{id}", tag = "episodes",
    params(("id" = String, Path), VersionQuery),
    responses((status = 200, description = "{episode, history}", body = Object), (status = 404, body = Problem)))]
pub async fn get_episode(
    State(s): State<AppState>,
    ApiPath(id): ApiPath<String>,
    ApiQuery(q): ApiQuery<VersionQuery>,
) -> ApiResult<Response> {
    check_id("episode id", &id)?;
    let ep = s.store().episode(&id, q.version).await?;
    let history = s.store().label_history(&id).await?;
    let rev = ep.label_revision;
    let mut resp = Json(json!({"episode": ep, "history": history})).into_response();
    resp.headers_mut().insert(header::ETAG, etag(rev));
    Ok(resp)
}

/// The step table: JSON (columnar) or, with `Accept: application/vnd.apache.arrow.stream`, Arrow IPC.
#[utoipa::path(get, path = "/v1/episodes/{id}/steps", tag = "episodes",
    params(("id" = String, Path), VersionQuery),
    responses(
        (status = 200, description = "columnar JSON {episode_id, num_rows, columns, omitted}", body = Object,
         content_type = "application/json"),
        (status = 200, description = "Arrow IPC stream", content_type = "application/vnd.apache.arrow.stream"),
        (status = 404, body = Problem)))]
pub async fn get_steps(
    State(s): State<AppState>,
    ApiPath(id): ApiPath<String>,
    ApiQuery(q): ApiQuery<VersionQuery>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    check_id("episode id", &id)?;
    let batch = s.store().read_steps(&id, q.version).await?;
    let wants_arrow = headers
        .get(header::ACCEPT)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|a| a.split(',').any(|p| p.trim().starts_with(ARROW_STREAM)));
    if wants_arrow {
        let mut buf = Vec::new();
        {
            let mut w = arrow::ipc::writer::StreamWriter::try_new(&mut buf, &batch.schema())
                .map_err(|e| ApiError::internal(e.to_string()))?;
            w.write(&batch).map_err(|e| ApiError::internal(e.to_string()))?;
            w.finish().map_err(|e| ApiError::internal(e.to_string()))?;
        }
        return Ok(([(header::CONTENT_TYPE, ARROW_STREAM)], buf).into_response());
    }
    let (columns, omitted) = crate::steps_json::columns(&batch);
    Ok(Json(json!({"episode_id": id, "num_rows": batch.num_rows(), "columns": columns, "omitted": omitted}))
        .into_response())
}

/// The episode's video `key` (a `media.<key>.path` column of its steps), with HTTP range requests.
#[utoipa::path(get, path = "/v1/episodes/{id}/media/{key}", tag = "episodes",
    params(("id" = String, Path), ("key" = String, Path), ("Range" = Option<String>, Header)),
    responses((status = 200, description = "the whole file"), (status = 206, description = "a byte range"),
              (status = 416, body = Problem), (status = 404, body = Problem)))]
pub async fn get_media(
    State(s): State<AppState>,
    ApiPath((id, key)): ApiPath<(String, String)>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    check_id("episode id", &id)?;
    check_id("media key", &key)?;
    let batch = s.store().read_steps(&id, None).await?;
    let col = batch
        .column_by_name(&format!("{}{key}.path", store::steps::MEDIA_PREFIX))
        .ok_or_else(|| ApiError::not_found(format!("episode {id} has no media {key:?}")))?;
    let paths = col
        .as_any()
        .downcast_ref::<arrow::array::StringArray>()
        .ok_or_else(|| ApiError::internal("media path column is not utf8"))?;
    if arrow::array::Array::is_empty(paths) || arrow::array::Array::is_null(paths, 0) {
        return Err(ApiError::not_found(format!("episode {id} has no media {key:?}")));
    }
    let path = paths.value(0).to_string();
    crate::media::serve_object(s.store(), &path, headers.get(header::RANGE)).await
}

// ---------------------------------------------------------------- labels

#[derive(Deserialize, ToSchema)]
pub struct LabelRequest {
    /// `success`, `failure` or `unknown`.
    label: String,
    note: Option<String>,
}

fn if_match(headers: &HeaderMap) -> ApiResult<i64> {
    let v = headers.get(header::IF_MATCH).ok_or_else(|| {
        ApiError::new(
            StatusCode::PRECONDITION_REQUIRED,
            "if-match-required",
            "PUT a label with If-Match: <label revision> (the ETag of GET /v1/episodes/{id})",
        )
    })?;
    let s = v.to_str().unwrap_or("").trim();
    let s = s.strip_prefix("W/").unwrap_or(s).trim_matches('"');
    s.parse::<i64>()
        .map_err(|_| ApiError::bad_request(format!("If-Match {s:?} is not a label revision (an integer)")))
}

/// Sets an episode's label; `If-Match: <revision>` is required, a stale revision gets 409 with
/// the current label, its revision and who set it when.
#[utoipa::path(put, path = "/v1/episodes/{id}/label", tag = "labels",
    params(("id" = String, Path), ("If-Match" = String, Header, description = "the label revision you read")),
    request_body = LabelRequest,
    responses((status = 200, description = "LabelChange; ETag = the new revision", body = Object),
              (status = 409, body = Problem), (status = 428, body = Problem), (status = 403, body = Problem)))]
pub async fn put_label(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiPath(id): ApiPath<String>,
    headers: HeaderMap,
    ApiJson(body): ApiJson<LabelRequest>,
) -> ApiResult<Response> {
    caller.require(Role::Labeler)?;
    check_id("episode id", &id)?;
    let expect = if_match(&headers)?;
    let update =
        LabelUpdate { episode_id: id, label: parse_label(&body.label)?, expect_revision: Some(expect), note: body.note };
    // SQLite: group-committed with concurrent PUTs (one transaction per batch, one outcome each).
    let change = crate::label_writer::set_label(&s, update, &caller.name).await;
    let change = s.count_label_result(change)?;
    let rev = change.revision;
    let mut resp = Json(change).into_response();
    resp.headers_mut().insert(header::ETAG, etag(rev));
    Ok(resp)
}

#[derive(Deserialize, ToSchema)]
pub struct BulkLabelItem {
    episode_id: String,
    label: String,
    /// Fail the whole request unless the episode is at this revision.
    expect_revision: Option<i64>,
    note: Option<String>,
}

#[derive(Deserialize, ToSchema)]
pub struct BulkLabelRequest {
    updates: Vec<BulkLabelItem>,
}

/// Labels many episodes in one transaction: all succeed or none does.
#[utoipa::path(post, path = "/v1/labels/bulk", tag = "labels", request_body = BulkLabelRequest,
    responses((status = 200, description = "LabelChange list", body = Vec<Object>), (status = 409, body = Problem),
              (status = 404, body = Problem), (status = 403, body = Problem)))]
pub async fn bulk_labels(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiJson(body): ApiJson<BulkLabelRequest>,
) -> ApiResult<Json<Vec<store::LabelChange>>> {
    caller.require(Role::Labeler)?;
    if body.updates.len() > 10_000 {
        return Err(ApiError::bad_request("at most 10000 updates per request"));
    }
    let mut updates = Vec::with_capacity(body.updates.len());
    for u in body.updates {
        check_id("episode id", &u.episode_id)?;
        updates.push(LabelUpdate {
            episode_id: u.episode_id,
            label: parse_label(&u.label)?,
            expect_revision: u.expect_revision,
            note: u.note,
        });
    }
    let changes = {
        let _gate = s.write_gate().await;
        s.store().set_labels(updates, &caller.name, "human").await
    };
    let changes = s.count_labels_result(changes)?;
    Ok(Json(changes))
}

#[derive(Deserialize, ToSchema, Default)]
pub struct SnapshotRequest {
    message: Option<String>,
}

/// Freezes the current labels into a new version.
#[utoipa::path(post, path = "/v1/label-snapshots", tag = "labels", request_body = SnapshotRequest,
    responses((status = 201, description = "{version, episodes}", body = Object), (status = 403, body = Problem)))]
pub async fn create_snapshot(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiJson(body): ApiJson<SnapshotRequest>,
) -> ApiResult<(StatusCode, Json<store::CommitInfo>)> {
    caller.require(Role::Labeler)?;
    let msg = body.message.unwrap_or_else(|| "label snapshot".into());
    if msg.len() > 4000 {
        return Err(ApiError::bad_request("message is longer than 4000 bytes"));
    }
    let info = {
        let _gate = s.write_gate().await;
        s.store().snapshot_labels(&caller.name, &msg).await?
    };
    Ok((StatusCode::CREATED, Json(info)))
}

// ---------------------------------------------------------------- splits

#[derive(Deserialize, ToSchema)]
pub struct SplitCreate {
    policy: String,
    checkpoint: String,
    /// Pin to this version; default: the head, after freezing unsnapshotted label changes.
    version: Option<i64>,
    /// Off-policy: take the episodes of these checkpoints instead.
    #[serde(default)]
    off_policy_from: Vec<CheckpointRefIn>,
    /// Default 0.2.
    val_fraction: Option<f64>,
    /// Default 0.
    seed: Option<u64>,
}

#[derive(Deserialize, ToSchema)]
pub struct CheckpointRefIn {
    policy: String,
    checkpoint: String,
}

/// Creates a split (on-policy for a checkpoint, or off-policy from other checkpoints).
#[utoipa::path(post, path = "/v1/splits", tag = "splits", request_body = SplitCreate,
    responses((status = 201, description = "SplitRecord", body = Object), (status = 400, body = Problem),
              (status = 403, body = Problem)))]
pub async fn create_split(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiJson(b): ApiJson<SplitCreate>,
) -> ApiResult<(StatusCode, Json<store::SplitRecord>)> {
    caller.require(Role::Trainer)?;
    check_name("policy", &b.policy)?;
    check_name("checkpoint", &b.checkpoint)?;
    let req = store::SplitRequest {
        policy: b.policy,
        checkpoint: b.checkpoint,
        version: b.version,
        off_policy_from: b.off_policy_from.into_iter().map(|c| (c.policy, c.checkpoint)).collect(),
        val_fraction: b.val_fraction.unwrap_or(0.2),
        seed: b.seed.unwrap_or(0),
        actor: caller.name.clone(),
    };
    let rec = {
        let _gate = s.write_gate().await;
        s.store().create_split(&req).await?
    };
    Ok((StatusCode::CREATED, Json(rec)))
}

/// All splits.
#[utoipa::path(get, path = "/v1/splits", tag = "splits",
    responses((status = 200, description = "SplitRecord list", body = Vec<Object>)))]
pub async fn list_splits(State(s): State<AppState>) -> ApiResult<Json<Vec<store::SplitRecord>>> {
    Ok(Json(s.store().splits().await?))
}

/// A split and its episodes (train/val, label).
#[utoipa::path(get, path = "/v1/splits/{id}", tag = "splits", params(("id" = String, Path)),
    responses((status = 200, description = "{split, episodes}", body = Object), (status = 404, body = Problem)))]
pub async fn get_split(State(s): State<AppState>, ApiPath(id): ApiPath<String>) -> ApiResult<Json<Value>> {
    check_id("split id", &id)?;
    let split = s.store().split(&id).await?;
    let episodes = s.store().split_episodes(&id).await?;
    Ok(Json(json!({"split": split, "episodes": episodes})))
}

// ---------------------------------------------------------------- jobs

#[derive(Deserialize, ToSchema)]
pub struct JobCreate {
    split_id: String,
    /// Verifier kind: `classifier` or `q`.
    kind: String,
    /// Training configuration (hyper-parameters), passed to the trainer.
    #[serde(default)]
    #[schema(value_type = Object)]
    config: Value,
}

/// Queues a training job; the job's spec is `{split_id, kind, config, policy, checkpoint}`.
#[utoipa::path(post, path = "/v1/jobs", tag = "jobs", request_body = JobCreate,
    responses((status = 201, description = "JobRecord", body = Object), (status = 400, body = Problem),
              (status = 403, body = Problem)))]
pub async fn create_job(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiJson(b): ApiJson<JobCreate>,
) -> ApiResult<(StatusCode, Json<store::JobRecord>)> {
    caller.require(Role::Trainer)?;
    check_id("split id", &b.split_id)?;
    if b.kind != "classifier" && b.kind != "q" {
        return Err(ApiError::bad_request(format!("unknown verifier kind {:?}: classifier or q", b.kind)));
    }
    let config = match b.config {
        Value::Null => json!({}),
        v @ Value::Object(_) => v,
        _ => return Err(ApiError::bad_request("config must be a JSON object")),
    };
    let split = s.store().split(&b.split_id).await?;
    let spec = json!({
        "split_id": split.id, "kind": b.kind, "config": config,
        "policy": split.policy, "checkpoint": split.checkpoint,
    });
    let job = s.store().create_job("train", &spec, &caller.name).await?;
    Ok((StatusCode::CREATED, Json(job)))
}

#[derive(Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct JobQuery {
    /// queued, running, succeeded, failed or cancelled.
    state: Option<String>,
}

fn parse_state(s: &str) -> ApiResult<store::JobState> {
    use store::JobState::*;
    Ok(match s {
        "queued" => Queued,
        "running" => Running,
        "succeeded" => Succeeded,
        "failed" => Failed,
        "cancelled" => Cancelled,
        _ => return Err(ApiError::bad_request(format!("unknown job state {s:?}"))),
    })
}

/// Jobs, optionally by state.
#[utoipa::path(get, path = "/v1/jobs", tag = "jobs", params(JobQuery),
    responses((status = 200, description = "JobRecord list", body = Vec<Object>)))]
pub async fn list_jobs(State(s): State<AppState>, ApiQuery(q): ApiQuery<JobQuery>) -> ApiResult<Json<Vec<store::JobRecord>>> {
    let state = q.state.as_deref().map(parse_state).transpose()?;
    Ok(Json(s.store().jobs(state).await?))
}

/// A job: state, progress (epoch, losses), result (metrics, artifact), error.
#[utoipa::path(get, path = "/v1/jobs/{id}", tag = "jobs", params(("id" = String, Path)),
    responses((status = 200, description = "JobRecord", body = Object), (status = 404, body = Problem)))]
pub async fn get_job(State(s): State<AppState>, ApiPath(id): ApiPath<String>) -> ApiResult<Json<store::JobRecord>> {
    check_id("job id", &id)?;
    Ok(Json(s.store().job(&id).await?))
}

/// Cancels a job: at once when queued, at its next heartbeat when running.
#[utoipa::path(post, path = "/v1/jobs/{id}/cancel", tag = "jobs", params(("id" = String, Path)),
    responses((status = 200, description = "JobRecord", body = Object), (status = 404, body = Problem),
              (status = 403, body = Problem)))]
pub async fn cancel_job(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiPath(id): ApiPath<String>,
) -> ApiResult<Json<store::JobRecord>> {
    caller.require(Role::Trainer)?;
    check_id("job id", &id)?;
    Ok(Json(s.store().cancel_job(&id).await?))
}

// ---------------------------------------------------------------- artifacts

#[derive(Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct ArtifactQuery {
    policy: Option<String>,
    checkpoint: Option<String>,
    kind: Option<String>,
}

/// Artifacts, optionally filtered.
#[utoipa::path(get, path = "/v1/artifacts", tag = "artifacts", params(ArtifactQuery),
    responses((status = 200, description = "ArtifactRecord list", body = Vec<Object>)))]
pub async fn list_artifacts(
    State(s): State<AppState>,
    ApiQuery(q): ApiQuery<ArtifactQuery>,
) -> ApiResult<Json<Vec<store::ArtifactRecord>>> {
    Ok(Json(s.store().artifacts(q.policy.as_deref(), q.checkpoint.as_deref(), q.kind.as_deref()).await?))
}

/// An artifact by id.
#[utoipa::path(get, path = "/v1/artifacts/{id}", tag = "artifacts", params(("id" = String, Path)),
    responses((status = 200, description = "ArtifactRecord", body = Object), (status = 404, body = Problem)))]
pub async fn get_artifact(State(s): State<AppState>, ApiPath(id): ApiPath<String>) -> ApiResult<Json<store::ArtifactRecord>> {
    check_id("artifact id", &id)?;
    Ok(Json(s.store().artifact(&id).await?))
}

/// One file of an artifact, checked against its sha256 (sent as `X-Checksum-Sha256` and `ETag`).
#[utoipa::path(get, path = "/v1/artifacts/{id}/files/{name}", tag = "artifacts",
    params(("id" = String, Path), ("name" = String, Path)),
    responses((status = 200, description = "the file", headers(("X-Checksum-Sha256" = String))),
              (status = 404, body = Problem)))]
pub async fn artifact_file(State(s): State<AppState>, ApiPath((id, name)): ApiPath<(String, String)>) -> ApiResult<Response> {
    check_id("artifact id", &id)?;
    check_id("file name", &name)?;
    let a = s.store().artifact(&id).await?;
    send_artifact_file(&s, &a, &name).await
}

async fn send_artifact_file(s: &AppState, a: &store::ArtifactRecord, name: &str) -> ApiResult<Response> {
    let f = a
        .files
        .iter()
        .find(|f| f.name == name)
        .ok_or_else(|| ApiError::not_found(format!("artifact {} has no file {name:?}", a.id)))?;
    let data = s.store().get_object(&format!("{}/{}", a.prefix, f.name)).await?;
    if store::sha256_hex(&data) != f.sha256 {
        return Err(ApiError::internal(format!("artifact {} file {} fails its sha256 check", a.id, f.name)));
    }
    let ctype = if name.ends_with(".json") { "application/json" } else { "application/octet-stream" };
    let mut resp = Response::new(Body::from(data));
    let h = resp.headers_mut();
    h.insert(header::CONTENT_TYPE, HeaderValue::from_static(ctype));
    h.insert("x-checksum-sha256", HeaderValue::from_str(&f.sha256).map_err(|e| ApiError::internal(e.to_string()))?);
    h.insert(header::ETAG, HeaderValue::from_str(&format!("\"{}\"", f.sha256)).map_err(|e| ApiError::internal(e.to_string()))?);
    h.insert("x-artifact-id", HeaderValue::from_str(&a.id).map_err(|e| ApiError::internal(e.to_string()))?);
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("private, max-age=31536000, immutable"));
    Ok(resp)
}

fn split_kind_alias(s: &str) -> ApiResult<(&str, &str)> {
    let (kind, alias) = s
        .split_once('@')
        .ok_or_else(|| ApiError::bad_request(format!("expected KIND@ALIAS, got {s:?}")))?;
    check_id("verifier kind", kind)?;
    check_id("alias", alias)?;
    Ok((kind, alias))
}

/// Resolves `policies/{p}/checkpoints/{c}/verifiers/{kind}@{alias}` to an artifact.
#[utoipa::path(get, path = "/v1/policies/{policy}/checkpoints/{checkpoint}/verifiers/{kind_at_alias}", tag = "artifacts",
    params(("policy" = String, Path), ("checkpoint" = String, Path),
           ("kind_at_alias" = String, Path, description = "e.g. classifier@latest")),
    responses((status = 200, description = "ArtifactRecord", body = Object), (status = 404, body = Problem)))]
pub async fn resolve_verifier(
    State(s): State<AppState>,
    ApiPath((policy, checkpoint, ka)): ApiPath<(String, String, String)>,
) -> ApiResult<Json<store::ArtifactRecord>> {
    check_name("policy", &policy)?;
    check_name("checkpoint", &checkpoint)?;
    let (kind, alias) = split_kind_alias(&ka)?;
    Ok(Json(s.store().resolve_alias(&policy, &checkpoint, kind, alias).await?))
}

/// Downloads a file of the artifact an alias points at.
#[utoipa::path(get, path = "/v1/policies/{policy}/checkpoints/{checkpoint}/verifiers/{kind_at_alias}/files/{name}",
    tag = "artifacts",
    params(("policy" = String, Path), ("checkpoint" = String, Path), ("kind_at_alias" = String, Path),
           ("name" = String, Path)),
    responses((status = 200, description = "the file", headers(("X-Checksum-Sha256" = String), ("X-Artifact-Id" = String))),
              (status = 404, body = Problem)))]
pub async fn resolve_verifier_file(
    State(s): State<AppState>,
    ApiPath((policy, checkpoint, ka, name)): ApiPath<(String, String, String, String)>,
) -> ApiResult<Response> {
    check_name("policy", &policy)?;
    check_name("checkpoint", &checkpoint)?;
    check_id("file name", &name)?;
    let (kind, alias) = split_kind_alias(&ka)?;
    let a = s.store().resolve_alias(&policy, &checkpoint, kind, alias).await?;
    send_artifact_file(&s, &a, &name).await
}

/// Points an alias of the artifact's (policy, checkpoint, kind) at it.
#[utoipa::path(put, path = "/v1/artifacts/{id}/aliases/{alias}", tag = "artifacts",
    params(("id" = String, Path), ("alias" = String, Path)),
    responses((status = 200, description = "ArtifactRecord", body = Object), (status = 404, body = Problem),
              (status = 403, body = Problem)))]
pub async fn set_alias(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiPath((id, alias)): ApiPath<(String, String)>,
) -> ApiResult<Json<store::ArtifactRecord>> {
    caller.require(Role::Trainer)?;
    check_id("artifact id", &id)?;
    check_id("alias", &alias)?;
    Ok(Json(s.store().set_alias(&alias, &id).await?))
}

// ---------------------------------------------------------------- admin

#[derive(Deserialize, ToSchema)]
pub struct GcRequest {
    /// Keep unreferenced objects younger than this (default 3600).
    grace_seconds: Option<u64>,
    /// Only report (default false).
    dry_run: Option<bool>,
}

/// Deletes objects no committed version references (admin).
#[utoipa::path(post, path = "/v1/gc", tag = "admin", request_body = GcRequest,
    responses((status = 200, description = "GcReport", body = Object), (status = 403, body = Problem)))]
pub async fn gc(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiJson(b): ApiJson<GcRequest>,
) -> ApiResult<Json<store::GcReport>> {
    caller.require(Role::Admin)?;
    Ok(Json(s.store().gc(b.grace_seconds.unwrap_or(3600), b.dry_run.unwrap_or(false)).await?))
}

#[derive(Deserialize, ToSchema)]
pub struct TokenCreate {
    name: String,
    /// viewer, labeler, trainer or admin.
    role: String,
}

/// Creates a token; the secret is in the response only (admin).
#[utoipa::path(post, path = "/v1/tokens", tag = "admin", request_body = TokenCreate,
    responses((status = 201, description = "{token, record}", body = Object), (status = 403, body = Problem)))]
pub async fn create_token(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiJson(b): ApiJson<TokenCreate>,
) -> ApiResult<(StatusCode, Json<Value>)> {
    caller.require(Role::Admin)?;
    let role: Role = b.role.parse()?;
    let (secret, rec) = s.store().create_token(&b.name, role).await?;
    Ok((StatusCode::CREATED, Json(json!({"token": secret, "record": rec}))))
}

/// Tokens (never their secrets) (admin).
#[utoipa::path(get, path = "/v1/tokens", tag = "admin",
    responses((status = 200, description = "TokenRecord list", body = Vec<Object>), (status = 403, body = Problem)))]
pub async fn list_tokens(State(s): State<AppState>, Extension(caller): Extension<Caller>) -> ApiResult<Json<Vec<store::TokenRecord>>> {
    caller.require(Role::Admin)?;
    Ok(Json(s.store().tokens().await?))
}

/// Revokes a token (admin).
#[utoipa::path(delete, path = "/v1/tokens/{id}", tag = "admin", params(("id" = String, Path)),
    responses((status = 204), (status = 404, body = Problem), (status = 403, body = Problem)))]
pub async fn revoke_token(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiPath(id): ApiPath<String>,
) -> ApiResult<StatusCode> {
    caller.require(Role::Admin)?;
    check_id("token id", &id)?;
    s.store().revoke_token(&id).await?;
    s.inner.tokens.clear();
    Ok(StatusCode::NO_CONTENT)
}

// ---------------------------------------------------------------- open + infra

/// Liveness (no token needed).
#[utoipa::path(get, path = "/healthz", tag = "infra", security(()),
    responses((status = 200, description = "ok")))]
pub async fn healthz() -> Json<Value> {
    Json(json!({"status": "ok"}))
}

/// Prometheus metrics (text format).
#[utoipa::path(get, path = "/metrics", tag = "infra",
    responses((status = 200, description = "Prometheus text", content_type = "text/plain")))]
pub async fn metrics(State(s): State<AppState>) -> ApiResult<Response> {
    let mut by_state = std::collections::BTreeMap::new();
    for st in ["queued", "running", "succeeded", "failed", "cancelled"] {
        by_state.insert(st.to_string(), 0u64);
    }
    for j in s.store().jobs(None).await? {
        *by_state.entry(j.state.as_str().to_string()).or_insert(0) += 1;
    }
    let text = s.inner.metrics.render(&by_state);
    Ok(([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], text).into_response())
}

pub async fn not_found() -> ApiError {
    ApiError::not_found("no such route")
}

impl AppState {
    fn count_label_result(&self, r: Result<store::LabelChange, store::StoreError>) -> ApiResult<store::LabelChange> {
        self.count_labels_result(r.map(|c| vec![c])).map(|mut v| v.remove(0))
    }
    fn count_labels_result(
        &self,
        r: Result<Vec<store::LabelChange>, store::StoreError>,
    ) -> ApiResult<Vec<store::LabelChange>> {
        let m = &self.inner.metrics;
        match r {
            Ok(v) => {
                m.label_writes.fetch_add(v.len() as u64, Ordering::Relaxed);
                Ok(v)
            }
            Err(e) => {
                if matches!(e, store::StoreError::LabelConflict { .. } | store::StoreError::Conflict(_)) {
                    m.label_conflicts.fetch_add(1, Ordering::Relaxed);
                }
                Err(e.into())
            }
        }
    }
}
