//! The review queue: the verifier orders the labeling queue from scores a `score` job
//! stored; per-step scores for the episode view's timeline; the artifact scoring each policy's
//! queue (a campaign here is a policy).

use super::*;
use store_jobs::JobQueue;

/// The routes of this resource (behind the token check).
pub(crate) fn router() -> Router<AppState> {
    Router::new()
        .route("/v1/episodes/{id}/scores", get(get_episode_scores))
        .route(
            "/v1/review/artifacts/{policy}",
            get(get_review_artifact)
                .put(put_review_artifact.layer(need!(Role::Trainer)))
                .delete(delete_review_artifact.layer(need!(Role::Trainer))),
        )
        .route("/v1/review/score", post(create_score_job.layer(need!(Role::Trainer))))
}

/// An episode's place in a review order: the artifact that scores it and its stored score.
#[derive(Serialize, ToSchema)]
pub struct ReviewScoreRef {
    pub episode_id: String,
    /// The policy's review artifact (absent when neither a setting nor the checkpoint's
    /// `classifier@latest` alias names one).
    pub artifact_id: Option<String>,
    /// The mean of the episode's step scores; absent until a score job stored it.
    pub score: Option<f64>,
}

/// `GET /v1/episodes?order=…` other than `id` (see [`EpisodeQuery`]).
pub(crate) async fn list_review_queue(s: &AppState, order: &str, q: EpisodeQuery) -> ApiResult<EpisodePage> {
    let order: store_labeling::ReviewOrder = order.parse()?;
    if q.sort.as_deref().is_some_and(|s| s != "id") {
        return Err(ApiError::bad_request("give order or sort, not both"));
    }
    let limit = q.page_limit()?;
    if let Some(a) = &q.after {
        if a.chars().count() > 400 || a.chars().any(char::is_control) {
            return Err(ApiError::bad_request("cursor: not one of this order's cursors"));
        }
    }
    let filter = EpisodeFilter { version: q.version, ..q.filters()? };
    let mut entries = s.store().review_queue(&filter, order, q.after.as_deref(), limit + 1).await?;
    let next_cursor = if entries.len() as i64 > limit {
        entries.truncate(limit as usize);
        entries.last().map(|e| e.cursor.clone())
    } else {
        None
    };
    let review = entries
        .iter()
        .map(|e| ReviewScoreRef {
            episode_id: e.episode.id.clone(),
            artifact_id: e.artifact_id.clone(),
            score: e.score,
        })
        .collect();
    Ok(EpisodePage {
        episodes: entries.into_iter().map(|e| e.episode).collect(),
        next_cursor,
        review: Some(review),
    })
}

#[derive(Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct ScoresQuery {
    /// The artifact whose scores to read; default: the episode's review artifact.
    artifact: Option<String>,
}

/// The per-step verifier scores of an episode (for the timeline), as a score job stored them.
#[utoipa::path(get, path = "/v1/episodes/{id}/scores", tag = "review", params(("id" = String, Path), ScoresQuery),
    responses((status = 200, body = store::EpisodeScore),
              (status = 400, body = Problem, content_type = "application/problem+json"),
              (status = 401, body = Problem, content_type = "application/problem+json"),
              (status = 404, description = "no such episode, no review artifact, or not scored yet", body = Problem,
               content_type = "application/problem+json")))]
pub async fn get_episode_scores(
    State(s): State<AppState>,
    ApiPath(id): ApiPath<String>,
    ApiQuery(q): ApiQuery<ScoresQuery>,
) -> ApiResult<Json<store::EpisodeScore>> {
    check_id("episode id", &id)?;
    if let Some(a) = &q.artifact {
        check_id("artifact id", a)?;
    }
    Ok(Json(s.store().episode_score(&id, q.artifact.as_deref()).await?))
}

/// The artifact that scores a policy's review queue.
#[derive(Serialize, ToSchema)]
pub struct ReviewArtifactSetting {
    pub policy: String,
    pub artifact_id: String,
    /// `setting` (set with PUT) or `default` (the checkpoint's `classifier@latest`; only with `checkpoint`).
    pub source: String,
    pub updated_by: Option<String>,
    pub updated_at: Option<String>,
}

impl ReviewArtifactSetting {
    /// A policy's stored setting.
    fn from_setting(a: store_labeling::ReviewArtifact) -> Self {
        ReviewArtifactSetting {
            policy: a.policy,
            artifact_id: a.artifact_id,
            source: "setting".into(),
            updated_by: Some(a.updated_by),
            updated_at: Some(a.updated_at),
        }
    }
}

#[derive(Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct ReviewArtifactQuery {
    /// Without a setting, report this checkpoint's default (`classifier@latest`).
    checkpoint: Option<String>,
}

/// The artifact scoring a policy's queue: its setting, else (with `checkpoint`) the default alias.
#[utoipa::path(get, path = "/v1/review/artifacts/{policy}", tag = "review",
    params(("policy" = String, Path), ReviewArtifactQuery),
    responses((status = 200, body = ReviewArtifactSetting),
              (status = 400, body = Problem, content_type = "application/problem+json"),
              (status = 401, body = Problem, content_type = "application/problem+json"),
              (status = 404, description = "no setting and no default", body = Problem, content_type = "application/problem+json")))]
pub async fn get_review_artifact(
    State(s): State<AppState>,
    ApiPath(policy): ApiPath<String>,
    ApiQuery(q): ApiQuery<ReviewArtifactQuery>,
) -> ApiResult<Json<ReviewArtifactSetting>> {
    check_name("policy", &policy)?;
    if let Some(a) = s.store().review_artifact(&policy).await? {
        return Ok(Json(ReviewArtifactSetting::from_setting(a)));
    }
    let Some(c) = q.checkpoint else {
        return Err(ApiError::not_found(format!("policy {policy:?} has no review artifact setting")));
    };
    check_name("checkpoint", &c)?;
    let a =
        s.store().resolve_alias(&policy, &c, store::DEFAULT_REVIEW_KIND, store::DEFAULT_REVIEW_ALIAS).await?;
    Ok(Json(ReviewArtifactSetting {
        policy,
        artifact_id: a.id,
        source: "default".into(),
        updated_by: None,
        updated_at: None,
    }))
}

#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ReviewArtifactUpdate {
    /// An artifact id or `POLICY/CHECKPOINT/KIND@ALIAS` (resolved now).
    artifact: String,
}

/// Sets the artifact that scores a policy's review queue (instead of each checkpoint's
/// `classifier@latest`). Run a score job with it (`POST /v1/review/score`) to fill the queue.
#[utoipa::path(put, path = "/v1/review/artifacts/{policy}", tag = "review", params(("policy" = String, Path)),
    request_body = ReviewArtifactUpdate,
    responses((status = 200, body = ReviewArtifactSetting),
              (status = 400, body = Problem, content_type = "application/problem+json"),
              (status = 401, body = Problem, content_type = "application/problem+json"),
              (status = 403, body = Problem, content_type = "application/problem+json"),
              (status = 404, description = "no such artifact", body = Problem, content_type = "application/problem+json")))]
pub async fn put_review_artifact(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiPath(policy): ApiPath<String>,
    ApiJson(b): ApiJson<ReviewArtifactUpdate>,
) -> ApiResult<Json<ReviewArtifactSetting>> {
    caller.require(Role::Trainer)?;
    check_name("policy", &policy)?;
    if b.artifact.is_empty() || b.artifact.len() > 600 {
        return Err(ApiError::bad_request("artifact: an id or POLICY/CHECKPOINT/KIND@ALIAS"));
    }
    let a = s.store().set_review_artifact(&policy, &b.artifact, &caller.name).await?;
    Ok(Json(ReviewArtifactSetting::from_setting(a)))
}

/// Removes a policy's setting: its checkpoints' `classifier@latest` score the queue again.
#[utoipa::path(delete, path = "/v1/review/artifacts/{policy}", tag = "review", params(("policy" = String, Path)),
    responses((status = 204, description = "removed"),
              (status = 401, body = Problem, content_type = "application/problem+json"),
              (status = 403, body = Problem, content_type = "application/problem+json"),
              (status = 404, description = "no setting", body = Problem, content_type = "application/problem+json")))]
pub async fn delete_review_artifact(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiPath(policy): ApiPath<String>,
) -> ApiResult<StatusCode> {
    caller.require(Role::Trainer)?;
    check_name("policy", &policy)?;
    if s.store().clear_review_artifact(&policy).await? {
        Ok(StatusCode::NO_CONTENT)
    } else {
        Err(ApiError::not_found(format!("policy {policy:?} has no review artifact setting")))
    }
}

#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ScoreJobCreate {
    policy: String,
    /// Only this checkpoint's episodes (default: all the policy's).
    checkpoint: Option<String>,
    /// An artifact id or `POLICY/CHECKPOINT/KIND@ALIAS`; default: the policy's review artifact
    /// (its setting, else `checkpoint`'s `classifier@latest`, which then needs `checkpoint`).
    artifact: Option<String>,
}

/// Queues a `score` job: a worker scores the episodes with the artifact and stores each one's
/// mean and per-step scores, which `GET /v1/episodes?order=…` and `/v1/episodes/{id}/scores` read.
#[utoipa::path(post, path = "/v1/review/score", tag = "review", request_body = ScoreJobCreate,
    responses((status = 201, description = "the queued job (kind `score`, spec {artifact_id, policy, checkpoint})", body = store_jobs::JobRecord),
              (status = 400, body = Problem, content_type = "application/problem+json"),
              (status = 401, body = Problem, content_type = "application/problem+json"),
              (status = 403, body = Problem, content_type = "application/problem+json"),
              (status = 404, description = "no such artifact", body = Problem, content_type = "application/problem+json"),
              (status = 409, description = "neither artifact nor checkpoint, and the policy has no review artifact setting", body = Problem, content_type = "application/problem+json")))]
pub async fn create_score_job(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiJson(b): ApiJson<ScoreJobCreate>,
) -> ApiResult<(StatusCode, Json<store_jobs::JobRecord>)> {
    caller.require(Role::Trainer)?;
    check_name("policy", &b.policy)?;
    if let Some(c) = &b.checkpoint {
        check_name("checkpoint", c)?;
    }
    if b.artifact.as_ref().is_some_and(|r| r.is_empty() || r.len() > 600) {
        return Err(ApiError::bad_request("artifact: an id or POLICY/CHECKPOINT/KIND@ALIAS"));
    }
    let found =
        s.store().artifact_to_score(&b.policy, b.checkpoint.as_deref(), b.artifact.as_deref()).await?;
    let artifact_id = match (found, &b.checkpoint) {
        (Some(a), _) => a,
        (None, Some(c)) => {
            return Err(ApiError::not_found(format!(
                "no review artifact for {}/{c}: set one or alias classifier@latest",
                b.policy
            )))
        }
        // The policy's setting is state: without one, this request conflicts with it.
        (None, None) => {
            return Err(ApiError::new(
                StatusCode::CONFLICT,
                "no-review-artifact",
                "give artifact or checkpoint (the policy has no review artifact setting)",
            ))
        }
    };
    let spec = json!({"artifact_id": artifact_id, "policy": b.policy, "checkpoint": b.checkpoint});
    let job = s.store().create_job(store_jobs::JobKind::Score, &spec, &caller.name).await?;
    Ok((StatusCode::CREATED, Json(job)))
}
