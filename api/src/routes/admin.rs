//! Administration: garbage collection and API tokens.

use super::*;

/// The routes of this resource (behind the token check).
pub(crate) fn router() -> Router<AppState> {
    Router::new()
        .route("/v1/gc", post(gc.layer(need!(Role::Admin))))
        .route("/v1/tokens", get(list_tokens.layer(need!(Role::Admin))).post(create_token.layer(need!(Role::Admin))))
        .route("/v1/tokens/{id}", axum::routing::delete(revoke_token.layer(need!(Role::Admin))))
}

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
