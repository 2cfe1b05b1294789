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
    /// Boxed: every handler's `Result` carries an `ApiError`, which stays one pointer wide.
    pub problem: Box<Problem>,
    pub headers: Vec<(header::HeaderName, HeaderValue)>,
}

impl ApiError {
    pub fn new(status: StatusCode, kind: &str, detail: impl Into<String>) -> Self {
        ApiError {
            status,
            problem: Box::new(Problem {
                kind: format!("urn:ufops:problem:{kind}"),
                title: status.canonical_reason().unwrap_or("error").to_string(),
                status: status.as_u16(),
                detail: detail.into(),
                extra: Default::default(),
            }),
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
    /// A server-side failure: the detail (which may name files, buckets or SQL) goes to the log
    /// with an incident id; the client gets only the id.
    pub fn internal(detail: impl Into<String>) -> Self {
        let incident = &uuid::Uuid::new_v4().simple().to_string()[..12];
        tracing::error!(incident, "internal error: {}", detail.into());
        Self::new(
            StatusCode::INTERNAL_SERVER_ERROR,
            "internal",
            format!("internal error (incident {incident}); the server's log has the details"),
        )
        .with("incident", incident.to_string())
    }
    /// A server-side failure whose message is safe to show as it is.
    pub fn internal_public(detail: impl Into<String>) -> Self {
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
            // A stored object the catalog names is gone: a server-side fault, its key logged only.
            StoreError::NotFound { what: "object", .. } => {
                tracing::warn!("{detail}");
                ApiError::not_found("a stored object is missing (the server's log names it)")
            }
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
            StoreError::Gone(_) => ApiError::new(StatusCode::GONE, "gone", detail),
            StoreError::Db(sqlx_err) => {
                if matches!(sqlx_err, sqlx::Error::PoolTimedOut) {
                    ApiError::new(StatusCode::SERVICE_UNAVAILABLE, "busy", "the catalog is busy; retry")
                } else {
                    ApiError::internal(format!("catalog error: {sqlx_err}"))
                }
            }
            // The object store's message names the bucket or the local path: logged, not sent.
            StoreError::Object(object_store::Error::NotFound { .. }) => {
                tracing::warn!("{detail}");
                ApiError::not_found("a stored object is missing (the server's log names it)")
            }
            _ => ApiError::internal(detail),
        }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let body = serde_json::to_vec(&self.problem).unwrap_or_default();
        let mut resp = (self.status, body).into_response();
        resp.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static("application/problem+json"));
        for (k, v) in self.headers {
            resp.headers_mut().insert(k, v);
        }
        resp
    }
}

pub type ApiResult<T> = Result<T, ApiError>;
