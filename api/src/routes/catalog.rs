//! Catalog resources: policies, checkpoints, tasks, versions and version diffs.

use super::*;

/// The routes of this resource (behind the token check).
pub(crate) fn router() -> Router<AppState> {
    Router::new()
        .route("/v1/policies", get(list_policies))
        .route("/v1/checkpoints", get(list_checkpoints))
        .route("/v1/tasks", get(list_tasks))
        .route("/v1/versions", get(list_versions))
        .route("/v1/versions/{version}", get(get_version))
        .route("/v1/versions/{from}/diff/{to}", get(diff_versions))
}

/// Policy names.
#[utoipa::path(get, path = "/v1/policies", tag = "catalog",
    responses((status = 200, body = Vec<String>)))]
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
    responses((status = 200, body = Vec<CheckpointRef>)))]
pub async fn list_checkpoints(
    State(s): State<AppState>,
    ApiQuery(q): ApiQuery<CheckpointQuery>,
) -> ApiResult<Json<Vec<CheckpointRef>>> {
    let v = s.store().checkpoints(q.policy.as_deref()).await?;
    Ok(Json(v.into_iter().map(|(policy, checkpoint)| CheckpointRef { policy, checkpoint }).collect()))
}

/// Task names.
#[utoipa::path(get, path = "/v1/tasks", tag = "catalog",
    responses((status = 200, body = Vec<String>)))]
pub async fn list_tasks(State(s): State<AppState>) -> ApiResult<Json<Vec<String>>> {
    Ok(Json(s.store().tasks().await?))
}

/// Every committed version, oldest first.
#[utoipa::path(get, path = "/v1/versions", tag = "versions",
    responses((status = 200, body = Vec<store::VersionInfo>)))]
pub async fn list_versions(State(s): State<AppState>) -> ApiResult<Json<Vec<store::VersionInfo>>> {
    Ok(Json(s.store().versions().await?))
}

/// One version.
#[utoipa::path(get, path = "/v1/versions/{version}", tag = "versions",
    params(("version" = i64, Path)),
    responses((status = 200, body = store::VersionInfo), (status = 404, description = "no such version")))]
pub async fn get_version(
    State(s): State<AppState>,
    ApiPath(v): ApiPath<i64>,
) -> ApiResult<Json<store::VersionInfo>> {
    Ok(Json(s.store().version(v).await?))
}

/// Episodes added/removed and labels changed between two versions.
#[utoipa::path(get, path = "/v1/versions/{from}/diff/{to}", tag = "versions",
    params(("from" = i64, Path), ("to" = i64, Path)),
    responses((status = 200, body = VersionDiffBody), (status = 404, description = "no such version")))]
pub async fn diff_versions(
    State(s): State<AppState>,
    ApiPath((from, to)): ApiPath<(i64, i64)>,
) -> ApiResult<Json<VersionDiffBody>> {
    let d = s.store().diff(from, to).await?;
    Ok(Json(VersionDiffBody {
        from: d.from,
        to: d.to,
        episodes_added: d.episodes_added,
        episodes_removed: d.episodes_removed,
        labels_changed: d
            .labels_changed
            .into_iter()
            .map(|(episode_id, from, to)| LabelDiff { episode_id, from, to })
            .collect(),
    }))
}

/// What changed between two versions.
#[derive(Serialize, ToSchema)]
pub struct VersionDiffBody {
    from: i64,
    to: i64,
    episodes_added: Vec<String>,
    episodes_removed: Vec<String>,
    labels_changed: Vec<LabelDiff>,
}

/// An episode whose label differs between the two versions.
#[derive(Serialize, ToSchema)]
pub struct LabelDiff {
    episode_id: String,
    from: Label,
    to: Label,
}
