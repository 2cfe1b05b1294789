//! Extractors whose rejections are problem documents, and validation of client-given ids.

use crate::error::ApiError;
use axum::extract::{FromRequest, FromRequestParts, Request};
use axum::http::request::Parts;
use serde::de::DeserializeOwned;

/// `Json<T>` whose rejection is a problem document.
pub struct ApiJson<T>(pub T);

impl<S: Send + Sync, T: DeserializeOwned> FromRequest<S> for ApiJson<T> {
    type Rejection = ApiError;
    async fn from_request(req: Request, state: &S) -> Result<Self, ApiError> {
        match axum::Json::<T>::from_request(req, state).await {
            Ok(axum::Json(v)) => Ok(ApiJson(v)),
            Err(rej) => Err(ApiError::new(rej.status(), "bad-body", rej.body_text())),
        }
    }
}

/// `Query<T>` whose rejection is a problem document.
pub struct ApiQuery<T>(pub T);

impl<S: Send + Sync, T: DeserializeOwned> FromRequestParts<S> for ApiQuery<T> {
    type Rejection = ApiError;
    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, ApiError> {
        match axum::extract::Query::<T>::from_request_parts(parts, state).await {
            Ok(axum::extract::Query(v)) => Ok(ApiQuery(v)),
            Err(rej) => Err(ApiError::new(rej.status(), "bad-query", rej.body_text())),
        }
    }
}

/// `Path<T>` whose rejection is a problem document.
pub struct ApiPath<T>(pub T);

impl<S: Send + Sync, T: DeserializeOwned + Send> FromRequestParts<S> for ApiPath<T> {
    type Rejection = ApiError;
    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, ApiError> {
        match axum::extract::Path::<T>::from_request_parts(parts, state).await {
            Ok(axum::extract::Path(v)) => Ok(ApiPath(v)),
            Err(rej) => Err(ApiError::new(rej.status(), "bad-path", rej.body_text())),
        }
    }
}

/// An id (episode, job, split, artifact, token, alias, media key): 1-128 characters from
/// `[A-Za-z0-9._-]`, not starting with a dot.
pub fn check_id(what: &str, s: &str) -> Result<(), ApiError> {
    let ok = !s.is_empty()
        && s.len() <= 128
        && !s.starts_with('.')
        && s.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'.' || b == b'_' || b == b'-');
    if ok {
        Ok(())
    } else {
        Err(ApiError::bad_request(format!(
            "invalid {what} {s:?}: expected 1-128 characters from A-Z a-z 0-9 . _ - (not starting with '.')"
        )))
    }
}

/// A policy, checkpoint or task name given in a URL: 1-200 printable characters, no '/'.
pub fn check_name(what: &str, s: &str) -> Result<(), ApiError> {
    let ok = !s.is_empty() && s.chars().count() <= 200 && s.trim() == s && !s.chars().any(|c| c.is_control() || c == '/');
    if ok {
        Ok(())
    } else {
        Err(ApiError::bad_request(format!("invalid {what} name {s:?}: 1-200 printable characters, no '/'")))
    }
}
