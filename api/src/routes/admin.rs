//! Administration: garbage collection and API tokens.

use super::*;

/// The routes of this resource (behind the token check).
pub(crate) fn router() -> Router<AppState> {
    Router::new()
        .route("/v1/gc", post(gc.layer(need!(Role::Admin))))
        .route(
            "/v1/tokens",
            get(list_tokens.layer(need!(Role::Admin))).post(create_token.layer(need!(Role::Admin))),
        )
        .route("/v1/tokens/{id}", axum::routing::delete(revoke_token.layer(need!(Role::Admin))))
}

#[derive(Deserialize, ToSchema)]
pub struct GcRequest {
    /// Keep unreferenced objects younger than this (default 3600; at most ten years,
    /// store::gc::MAX_GRACE_SECONDS).
    #[schema(maximum = 315_360_000)]
    grace_seconds: Option<u64>,
    /// Only report (default false).
    dry_run: Option<bool>,
}

/// Deletes objects no committed version references (admin).
#[utoipa::path(post, path = "/v1/gc", tag = "admin", request_body = GcRequest,
    responses((status = 200, body = store::GcReport), (status = 403, description = "the token's role is below admin")))]
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
    #[schema(value_type = store::Role)]
    role: String,
}

/// Creates a token; the secret is in the response only (admin).
#[utoipa::path(post, path = "/v1/tokens", tag = "admin", request_body = TokenCreate,
    responses((status = 201, body = TokenCreated), (status = 403, description = "the token's role is below admin")))]
pub async fn create_token(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiJson(b): ApiJson<TokenCreate>,
) -> ApiResult<(StatusCode, Json<TokenCreated>)> {
    caller.require(Role::Admin)?;
    let role: Role = b.role.parse()?;
    let (token, record) = s.store().create_token(&b.name, role).await?;
    Ok((StatusCode::CREATED, Json(TokenCreated { token, record })))
}

/// A new token: its secret (shown this once) and its record.
#[derive(Serialize, ToSchema)]
pub struct TokenCreated {
    token: String,
    record: store::TokenRecord,
}

/// Tokens (never their secrets) (admin).
#[utoipa::path(get, path = "/v1/tokens", tag = "admin",
    responses((status = 200, body = Vec<store::TokenRecord>), (status = 403, description = "the token's role is below admin")))]
pub async fn list_tokens(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
) -> ApiResult<Json<Vec<store::TokenRecord>>> {
    caller.require(Role::Admin)?;
    Ok(Json(s.store().tokens().await?))
}

/// Revokes a token (admin). A caller cannot revoke the token it is using (409): an admin cannot
/// lock itself out by mistake, and a fuzzer holding an admin token cannot end its own run.
#[utoipa::path(delete, path = "/v1/tokens/{id}", tag = "admin", params(("id" = String, Path)),
    responses((status = 204, description = "revoked"), (status = 404, description = "no such token"),
              (status = 409, description = "the token making the request"), (status = 403, description = "the token's role is below admin")))]
pub async fn revoke_token(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiPath(id): ApiPath<String>,
) -> ApiResult<StatusCode> {
    caller.require(Role::Admin)?;
    check_id("token id", &id)?;
    if id == caller.token_id {
        return Err(ApiError::new(
            StatusCode::CONFLICT,
            "conflict",
            "a token cannot revoke itself: use another admin token or `ufops token revoke`",
        ));
    }
    s.store().revoke_token(&id).await?;
    s.inner.tokens.clear();
    Ok(StatusCode::NO_CONTENT)
}
