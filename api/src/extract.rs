//! Extractors whose rejections are problem documents, and validation of client-given ids.

use crate::error::ApiError;
use axum::extract::{FromRequest, FromRequestParts, Request};
use axum::http::request::Parts;
use serde::de::DeserializeOwned;

/// `Json<T>` whose rejection is a problem document. The body must be a JSON object (every
/// request record is one), and a number with no fractional part (`646.0`) is an integer, as JSON
/// Schema (the OpenAPI document) says.
pub struct ApiJson<T>(pub T);

impl<S: Send + Sync, T: DeserializeOwned> FromRequest<S> for ApiJson<T> {
    type Rejection = ApiError;
    async fn from_request(req: Request, state: &S) -> Result<Self, ApiError> {
        let mut v = match axum::Json::<serde_json::Value>::from_request(req, state).await {
            Ok(axum::Json(v)) => v,
            Err(rej) => return Err(ApiError::new(rej.status(), "bad-body", rej.body_text())),
        };
        let unprocessable =
            |detail: String| ApiError::new(axum::http::StatusCode::UNPROCESSABLE_ENTITY, "bad-body", detail);
        if !v.is_object() {
            return Err(unprocessable("the body must be a JSON object".into()));
        }
        integral_floats_to_integers(&mut v);
        serde_json::from_value(v).map(ApiJson).map_err(|e| {
            unprocessable(format!("Failed to deserialize the JSON body into the target type: {e}"))
        })
    }
}

/// `646.0` → `646` (within i64/u64), everywhere in `v`.
fn integral_floats_to_integers(v: &mut serde_json::Value) {
    use serde_json::Value;
    match v {
        Value::Number(n) if n.is_f64() => {
            let f = n.as_f64().unwrap_or(f64::NAN);
            if f.fract() == 0.0 && f >= i64::MIN as f64 && f < i64::MAX as f64 {
                *v = Value::from(f as i64);
            } else if f.fract() == 0.0 && f >= 0.0 && f < u64::MAX as f64 {
                *v = Value::from(f as u64);
            }
        }
        Value::Array(a) => a.iter_mut().for_each(integral_floats_to_integers),
        Value::Object(o) => o.values_mut().for_each(integral_floats_to_integers),
        _ => {}
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

/// A policy, checkpoint or task name given in a URL: the store's rule for policy and checkpoint
/// names (`store::model::check_ref_name`: 1-200 printable characters, no '/').
pub fn check_name(what: &str, s: &str) -> Result<(), ApiError> {
    store::model::check_ref_name(what, s).map_err(|e| ApiError::bad_request(e.to_string()))
}
