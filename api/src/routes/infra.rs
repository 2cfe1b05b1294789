//! Infrastructure routes: liveness, Prometheus metrics, the 404 fallback.

use super::*;
use store_jobs::JobQueue;

/// The routes of this resource (behind the token check).
pub(crate) fn router() -> Router<AppState> {
    Router::new().route("/metrics", get(metrics))
}

/// Liveness (no token needed).
#[utoipa::path(get, path = "/healthz", tag = "infra", security(()),
    responses((status = 200, body = Health)))]
pub async fn healthz() -> Json<Health> {
    Json(Health { status: "ok".into() })
}

/// Liveness: `{"status": "ok"}`.
#[derive(Serialize, ToSchema)]
pub struct Health {
    status: String,
}

/// Prometheus metrics (text format).
#[utoipa::path(get, path = "/metrics", tag = "infra",
    responses((status = 200, description = "Prometheus text", content_type = "text/plain", body = String)))]
pub async fn metrics(State(s): State<AppState>) -> ApiResult<Response> {
    let mut by_state = std::collections::BTreeMap::new();
    for st in ["queued", "running", "succeeded", "failed", "cancelled"] {
        by_state.insert(st.to_string(), 0u64);
    }
    for j in s.store().jobs(None).await? {
        *by_state.entry(j.state.as_str().to_string()).or_insert(0) += 1;
    }
    let text = s.inner.metrics.render(&by_state, s.store().fetch_counts());
    Ok(([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], text).into_response())
}

pub async fn not_found() -> ApiError {
    ApiError::not_found("no such route")
}
