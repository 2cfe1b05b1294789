//! Webhooks (admin): subscriptions to the change feed, their state and dead letters. Delivery is
//! `webhooks.rs` at the crate root.

use super::*;
use store_feed::Webhooks;

/// The routes of this resource (behind the token check).
pub(crate) fn router() -> Router<AppState> {
    Router::new()
        .route(
            "/v1/webhooks",
            get(list_webhooks.layer(need!(Role::Admin))).post(create_webhook.layer(need!(Role::Admin))),
        )
        .route(
            "/v1/webhooks/{id}",
            get(get_webhook.layer(need!(Role::Admin))).delete(delete_webhook.layer(need!(Role::Admin))),
        )
        .route("/v1/webhooks/{id}/dead-letters", get(list_dead_letters.layer(need!(Role::Admin))))
}

#[derive(Deserialize, ToSchema)]
pub struct WebhookCreate {
    /// Where deliveries are POSTed (`http://` or `https://`).
    url: String,
    /// Only these event kinds (default: all).
    #[serde(default)]
    #[schema(value_type = Vec<store::EventKind>)]
    kinds: Vec<String>,
    /// Only events of this policy.
    policy: Option<String>,
    /// Failed attempts at one event before it goes to the dead letters (default 8).
    #[schema(minimum = 1, maximum = 100)]
    max_attempts: Option<i64>,
}

/// A new subscription and the secret its deliveries are signed with (shown only here).
#[derive(Serialize, ToSchema)]
pub struct WebhookCreated {
    webhook: store_feed::WebhookRecord,
    secret: String,
}

/// Subscribes a URL to the change feed from now on (admin). Each event is POSTed with
/// `Ufops-Delivery`, `Ufops-Event` and `Ufops-Signature: t=T,v1=HEX(HMAC-SHA256(secret, "T." + body))`
/// headers, at least once, in feed order; see api/README.md.
#[utoipa::path(post, path = "/v1/webhooks", tag = "webhooks", request_body = WebhookCreate,
    responses((status = 201, body = WebhookCreated), (status = 403, description = "the token's role is below admin")))]
pub async fn create_webhook(
    State(s): State<AppState>,
    Extension(caller): Extension<Caller>,
    ApiJson(b): ApiJson<WebhookCreate>,
) -> ApiResult<(StatusCode, Json<WebhookCreated>)> {
    caller.require(Role::Admin)?;
    let mut filter = store::EventFilter::default();
    for k in &b.kinds {
        filter.kinds.push(k.parse()?);
    }
    if let Some(p) = &b.policy {
        check_name("policy", p)?;
        filter.policy = Some(p.clone());
    }
    let (webhook, secret) =
        s.store().create_webhook(&b.url, &filter, b.max_attempts.unwrap_or(8), &caller.name).await?;
    Ok((StatusCode::CREATED, Json(WebhookCreated { webhook, secret })))
}

/// Every subscription with its delivery state (admin).
#[utoipa::path(get, path = "/v1/webhooks", tag = "webhooks",
    responses((status = 200, body = Vec<store_feed::WebhookRecord>), (status = 403, description = "the token's role is below admin")))]
pub async fn list_webhooks(State(s): State<AppState>) -> ApiResult<Json<Vec<store_feed::WebhookRecord>>> {
    Ok(Json(s.store().webhooks().await?))
}

/// One subscription (admin).
#[utoipa::path(get, path = "/v1/webhooks/{id}", tag = "webhooks", params(("id" = String, Path,)),
    responses((status = 200, body = store_feed::WebhookRecord), (status = 403, description = "the token's role is below admin")))]
pub async fn get_webhook(
    State(s): State<AppState>,
    ApiPath(id): ApiPath<String>,
) -> ApiResult<Json<store_feed::WebhookRecord>> {
    check_id("webhook id", &id)?;
    Ok(Json(s.store().webhook(&id).await?))
}

/// Ends a subscription (admin).
#[utoipa::path(delete, path = "/v1/webhooks/{id}", tag = "webhooks", params(("id" = String, Path,)),
    responses((status = 204, description = "deleted"), (status = 403, description = "the token's role is below admin")))]
pub async fn delete_webhook(
    State(s): State<AppState>,
    ApiPath(id): ApiPath<String>,
) -> ApiResult<StatusCode> {
    check_id("webhook id", &id)?;
    s.store().delete_webhook(&id).await?;
    Ok(StatusCode::NO_CONTENT)
}

/// The events a subscription gave up on after `max_attempts` failed deliveries (admin); read
/// them again from `GET /v1/events?after=SEQ-1`.
#[utoipa::path(get, path = "/v1/webhooks/{id}/dead-letters", tag = "webhooks", params(("id" = String, Path,)),
    responses((status = 200, body = Vec<store_feed::DeadLetter>), (status = 403, description = "the token's role is below admin")))]
pub async fn list_dead_letters(
    State(s): State<AppState>,
    ApiPath(id): ApiPath<String>,
) -> ApiResult<Json<Vec<store_feed::DeadLetter>>> {
    check_id("webhook id", &id)?;
    Ok(Json(s.store().dead_letters(&id).await?))
}
