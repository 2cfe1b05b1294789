//! Jobs: training (and ingest) jobs queued for workers, their state, cancellation.

use super::*;

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
    /// Training configuration (hyper-parameters), passed to the trainer.
    #[serde(default)]
    #[schema(value_type = Object)]
    config: Value,
}

/// Queues a training job; the job's spec is `{split_id, kind, config, policy, checkpoint}`.
#[utoipa::path(post, path = "/v1/jobs", tag = "jobs", request_body = JobCreate,
    responses((status = 201, description = "the queued job", body = store::JobRecord),
              (status = 403, description = "the token's role is below trainer"), (status = 404, description = "no such split")))]
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
    #[param(value_type = Option<store::JobState>)]
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
    responses((status = 200, body = Vec<store::JobRecord>)))]
pub async fn list_jobs(
    State(s): State<AppState>,
    ApiQuery(q): ApiQuery<JobQuery>,
) -> ApiResult<Json<Vec<store::JobRecord>>> {
    let state = q.state.as_deref().map(parse_state).transpose()?;
    Ok(Json(s.store().jobs(state).await?))
}

/// A job: state, progress (epoch, losses), result (metrics, artifact), error.
#[utoipa::path(get, path = "/v1/jobs/{id}", tag = "jobs", params(("id" = String, Path)),
    responses((status = 200, body = store::JobRecord), (status = 404, description = "no such job")))]
pub async fn get_job(
    State(s): State<AppState>,
    ApiPath(id): ApiPath<String>,
) -> ApiResult<Json<store::JobRecord>> {
    check_id("job id", &id)?;
    Ok(Json(s.store().job(&id).await?))
}

/// Cancels a job: at once when queued, at its next heartbeat when running.
#[utoipa::path(post, path = "/v1/jobs/{id}/cancel", tag = "jobs", params(("id" = String, Path)),
    responses((status = 200, body = store::JobRecord), (status = 404, description = "no such job"),
              (status = 403, description = "the token's role is below trainer")))]
pub async fn cancel_job(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiPath(id): ApiPath<String>,
) -> ApiResult<Json<store::JobRecord>> {
    caller.require(Role::Trainer)?;
    check_id("job id", &id)?;
    Ok(Json(s.store().cancel_job(&id).await?))
}
