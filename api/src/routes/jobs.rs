//! Jobs: training (and ingest) jobs queued for workers, their state, cancellation.

use super::*;
use store_jobs::JobQueue;

/// The routes of this resource (behind the token check).
pub(crate) fn router() -> Router<AppState> {
    Router::new()
        .route("/v1/jobs", get(list_jobs).post(create_job.layer(need!(Role::Trainer))))
        .route("/v1/jobs/{id}", get(get_job))
        .route("/v1/jobs/{id}/cancel", post(cancel_job.layer(need!(Role::Trainer))))
}

/// The verifier kinds a training job can train.
#[derive(ToSchema)]
#[schema(rename_all = "lowercase")]
#[allow(dead_code)]
pub enum VerifierKind {
    Classifier,
    Q,
}

#[derive(Deserialize, ToSchema)]
pub struct JobCreate {
    split_id: String,
    /// Verifier kind.
    #[schema(value_type = VerifierKind)]
    kind: String,
    /// Training recipe (hyper-parameters; missing ones take the paper's), passed to the trainer. It
    /// may also carry the input spec below, as a `--config` file does; the fields below win.
    #[serde(default)]
    #[schema(value_type = Object)]
    config: Value,
    /// Observation keys in order: observation columns and layers (default: every observation
    /// column of the split's first episode, in the source's order).
    #[serde(default)]
    obs_keys: Option<Vec<String>>,
    /// Observation history `T_o` (default 2).
    #[serde(default)]
    #[schema(minimum = 1)]
    obs_history: Option<u32>,
    /// The policy's action chunk length `H`: required unless the episodes store action chunks.
    #[serde(default)]
    #[schema(minimum = 1)]
    chunk_len: Option<u32>,
    /// Train on steps `t % step_stride == 0` (default 1).
    #[serde(default)]
    #[schema(minimum = 1)]
    step_stride: Option<u32>,
}

/// Queues a training job; the job's spec is `{split_id, kind, config, obs_keys, obs_history,
/// chunk_len, step_stride, policy, checkpoint}` (the input spec fields only when given).
#[utoipa::path(post, path = "/v1/jobs", tag = "jobs", request_body = JobCreate,
    responses((status = 201, description = "the queued job", body = store_jobs::JobRecord),
              (status = 403, description = "the token's role is below trainer"), (status = 404, description = "no such split")))]
pub async fn create_job(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiJson(b): ApiJson<JobCreate>,
) -> ApiResult<(StatusCode, Json<store_jobs::JobRecord>)> {
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
    let mut spec = json!({
        "split_id": split.id, "kind": b.kind, "config": config,
        "policy": split.policy, "checkpoint": split.checkpoint,
    });
    let input = [
        ("obs_keys", b.obs_keys.map(|k| json!(k))),
        ("obs_history", b.obs_history.map(|n| json!(n))),
        ("chunk_len", b.chunk_len.map(|n| json!(n))),
        ("step_stride", b.step_stride.map(|n| json!(n))),
    ];
    for (key, value) in input {
        if let Some(v) = value {
            spec[key] = v;
        }
    }
    let job = s.store().create_job(store_jobs::JobKind::Train, &spec, &caller.name).await?;
    Ok((StatusCode::CREATED, Json(job)))
}

#[derive(Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct JobQuery {
    #[param(value_type = Option<store_jobs::JobState>)]
    state: Option<String>,
}

fn parse_state(s: &str) -> ApiResult<store_jobs::JobState> {
    use store_jobs::JobState::*;
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
    responses((status = 200, body = Vec<store_jobs::JobRecord>)))]
pub async fn list_jobs(
    State(s): State<AppState>,
    ApiQuery(q): ApiQuery<JobQuery>,
) -> ApiResult<Json<Vec<store_jobs::JobRecord>>> {
    let state = q.state.as_deref().map(parse_state).transpose()?;
    Ok(Json(s.store().jobs(state).await?))
}

/// A job: state, progress (epoch, losses), result (metrics, artifact), error.
#[utoipa::path(get, path = "/v1/jobs/{id}", tag = "jobs", params(("id" = String, Path)),
    responses((status = 200, body = store_jobs::JobRecord), (status = 404, description = "no such job")))]
pub async fn get_job(
    State(s): State<AppState>,
    ApiPath(id): ApiPath<String>,
) -> ApiResult<Json<store_jobs::JobRecord>> {
    check_id("job id", &id)?;
    Ok(Json(s.store().job(&id).await?))
}

/// Cancels a job: at once when queued, at its next heartbeat when running.
#[utoipa::path(post, path = "/v1/jobs/{id}/cancel", tag = "jobs", params(("id" = String, Path)),
    responses((status = 200, body = store_jobs::JobRecord), (status = 404, description = "no such job"),
              (status = 403, description = "the token's role is below trainer")))]
pub async fn cancel_job(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiPath(id): ApiPath<String>,
) -> ApiResult<Json<store_jobs::JobRecord>> {
    caller.require(Role::Trainer)?;
    check_id("job id", &id)?;
    Ok(Json(s.store().cancel_job(&id).await?))
}
