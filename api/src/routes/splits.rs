//! Splits: on-policy / off-policy episode sets pinned to a store version.

use super::*;

/// The routes of this resource (behind the token check).
pub(crate) fn router() -> Router<AppState> {
    Router::new()
        .route("/v1/splits", get(list_splits).post(create_split.layer(need!(Role::Trainer))))
        .route("/v1/splits/{id}", get(get_split))
}

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
    #[schema(minimum = 0.0, maximum = 0.99)]
    val_fraction: Option<f64>,
    /// Default 0.
    seed: Option<u64>,
    /// Keep at most this many labeled episodes, a seeded sample (nested across sizes).
    #[schema(minimum = 1)]
    max_episodes: Option<u64>,
}

#[derive(Deserialize, ToSchema)]
pub struct CheckpointRefIn {
    policy: String,
    checkpoint: String,
}

/// Creates a split (on-policy for a checkpoint, or off-policy from other checkpoints).
#[utoipa::path(post, path = "/v1/splits", tag = "splits", request_body = SplitCreate,
    responses((status = 201, body = store::SplitRecord), (status = 403, description = "the token's role is below trainer"),
              (status = 404, description = "no such version"),
              (status = 409, description = "no labeled episodes to split")))]
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
        max_episodes: b.max_episodes,
    };
    let rec = {
        let _gate = s.write_gate().await;
        s.store().create_split(&req).await?
    };
    Ok((StatusCode::CREATED, Json(rec)))
}

/// All splits.
#[utoipa::path(get, path = "/v1/splits", tag = "splits",
    responses((status = 200, body = Vec<store::SplitRecord>)))]
pub async fn list_splits(State(s): State<AppState>) -> ApiResult<Json<Vec<store::SplitRecord>>> {
    Ok(Json(s.store().splits().await?))
}

/// A split and its episodes (train/val, label).
#[utoipa::path(get, path = "/v1/splits/{id}", tag = "splits", params(("id" = String, Path)),
    responses((status = 200, body = SplitDetail), (status = 404, description = "no such split")))]
pub async fn get_split(
    State(s): State<AppState>,
    ApiPath(id): ApiPath<String>,
) -> ApiResult<Json<SplitDetail>> {
    check_id("split id", &id)?;
    let split = s.store().split(&id).await?;
    let episodes = s.store().split_episodes(&id).await?;
    Ok(Json(SplitDetail { split, episodes }))
}

/// A split and its episodes.
#[derive(Serialize, ToSchema)]
pub struct SplitDetail {
    split: store::SplitRecord,
    episodes: Vec<store::SplitEpisode>,
}
