//! Errors as RFC 9457 `application/problem+json`: `type`, `title`, `status`, `detail`, plus
//! extension members (for a label conflict: the current label, revision, who set it and when).

use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use serde::Serialize;
use store::StoreError;
use utoipa::ToSchema;

/// The body of every error response.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct Problem {
    /// A URI reference naming the problem type, e.g. `urn:ufops:problem:label-conflict`.
    #[serde(rename = "type")]
    pub kind: String,
    pub title: String,
    pub status: u16,
    pub detail: String,
    /// Extension members (label conflicts: `episode_id`, `expected_revision`, `current_revision`,
    /// `current_label`, `set_by`, `set_at`).
    #[serde(flatten)]
    #[schema(value_type = Object)]
    pub extra: serde_json::Map<String, serde_json::Value>,
}

/// An error a handler returns; rendered as a problem document.
#[derive(Debug)]
pub struct ApiError {
    pub status: StatusCode,
    pub problem: Problem,
    pub headers: Vec<(header::HeaderName, HeaderValue)>,
}

impl ApiError {
    pub fn new(status: StatusCode, kind: &str, detail: impl Into<String>) -> Self {
        ApiError {
            status,
            problem: Problem {
                kind: format!("urn:ufops:problem:{kind}"),
                title: status.canonical_reason().unwrap_or("error").to_string(),
                status: status.as_u16(),
                detail: detail.into(),
                extra: Default::default(),
            },
            headers: Vec::new(),
        }
    }
    pub fn bad_request(detail: impl Into<String>) -> Self {
        Self::new(StatusCode::BAD_REQUEST, "bad-request", detail)
    }
    pub fn not_found(detail: impl Into<String>) -> Self {
        Self::new(StatusCode::NOT_FOUND, "not-found", detail)
    }
    pub fn unauthorized(detail: impl Into<String>) -> Self {
        let mut e = Self::new(StatusCode::UNAUTHORIZED, "unauthorized", detail);
        e.headers.push((header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer realm=\"ufops\"")));
        e
    }
    pub fn forbidden(detail: impl Into<String>) -> Self {
        Self::new(StatusCode::FORBIDDEN, "forbidden", detail)
    }
    pub fn internal(detail: impl Into<String>) -> Self {
        Self::new(StatusCode::INTERNAL_SERVER_ERROR, "internal", detail)
    }
    pub fn with(mut self, key: &str, value: impl Into<serde_json::Value>) -> Self {
        self.problem.extra.insert(key.to_string(), value.into());
        self
    }
}

impl From<StoreError> for ApiError {
    fn from(e: StoreError) -> Self {
        let detail = e.to_string();
        match e {
            StoreError::Invalid(_) => ApiError::new(StatusCode::BAD_REQUEST, "invalid", detail),
            StoreError::NotFound { .. } => ApiError::not_found(detail),
            StoreError::AlreadyIngested { version, sha256 } => {
                ApiError::new(StatusCode::CONFLICT, "already-ingested", detail)
                    .with("version", version)
                    .with("sha256", sha256)
            }
            StoreError::LabelConflict { episode_id, expected, revision, label, actor, at } => {
                let mut err = ApiError::new(StatusCode::CONFLICT, "label-conflict", detail)
                    .with("episode_id", episode_id)
                    .with("expected_revision", expected)
                    .with("current_revision", revision)
                    .with("current_label", label.as_str())
                    .with("set_by", actor)
                    .with("set_at", at);
                if let Ok(v) = HeaderValue::from_str(&format!("\"{revision}\"")) {
                    err.headers.push((header::ETAG, v));
                }
                err
            }
            StoreError::Conflict(_) => ApiError::new(StatusCode::CONFLICT, "conflict", detail),
            StoreError::Db(sqlx_err) => {
                tracing::error!("catalog error: {sqlx_err}");
                if matches!(sqlx_err, sqlx::Error::PoolTimedOut) {
                    ApiError::new(StatusCode::SERVICE_UNAVAILABLE, "busy", "the catalog is busy; retry")
                } else {
                    ApiError::internal(format!("catalog error: {sqlx_err}"))
                }
            }
            StoreError::Object(object_store::Error::NotFound { .. }) => ApiError::not_found(detail),
            other => {
                tracing::error!("{other}");
                ApiError::internal(other.to_string())
            }
        }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let body = serde_json::to_vec(&self.problem).unwrap_or_default();
        let mut resp = (self.status, body).into_response();
        resp.headers_mut()
            .insert(header::CONTENT_TYPE, HeaderValue::from_static("application/problem+json"));
        for (k, v) in self.headers {
            resp.headers_mut().insert(k, v);
        }
        resp
    }
}

pub type ApiResult<T> = Result<T, ApiError>;
