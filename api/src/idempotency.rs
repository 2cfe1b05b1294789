//! `Idempotency-Key` on every mutating route: a retried request gets the first response, and
//! its work is done once.
//!
//! Behind the token check, a `POST`, `PUT`, `PATCH` or `DELETE` carrying the header claims the
//! key for its caller (the token) in the catalog before it runs (`store::Store::claim_idempotent`),
//! with a lease this server renews while the handler runs; the handler runs under
//! `store::with_request`, so the catalog write it makes marks the key committed in its own
//! transaction; the response (status, a few headers, body) is stored and replayed, with
//! `Idempotent-Replayed: true`, to every retry for [`crate::ServeConfig::idempotency_ttl`].
//!
//! * same key, different method, path or body: 422 `idempotency-key-reused`;
//! * same key while the first request is still being served: 409 `idempotency-key-in-use`
//!   with `Retry-After` (retry later; the first one's answer will be replayed);
//! * the server that served the first request died after its change committed but before the
//!   response was stored: 409 `idempotent-response-lost`, naming the change's event in the
//!   feed. The work is not done again.
//! * a 5xx whose request changed nothing is not kept: a retry runs again.
//!
//! The request's fingerprint is its body's sha256; a streamed upload (no `Content-Length`, or
//! one over the JSON body limit) is fingerprinted by its length and type instead of being read
//! twice (an ingest is also refused a second time by its source's sha256).

use crate::auth::Caller;
use crate::error::ApiError;
use crate::AppState;
use axum::body::Body;
use axum::extract::{MatchedPath, Request, State};
use axum::http::{header, HeaderName, HeaderValue, Method, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use std::time::Duration;
use store::{Claim, IdempotentRequest, RequestContext, StoredResponse};

/// The request header.
pub const IDEMPOTENCY_KEY: &str = "idempotency-key";
/// Set on every response to a request with a key: `true` when it is a stored one.
pub const REPLAYED: &str = "idempotent-replayed";
/// The largest response body kept for replay; a larger one is replaced by a problem saying so.
const MAX_STORED_BODY: usize = 1 << 20;
/// Response headers a replay carries besides the body.
const KEPT_HEADERS: [HeaderName; 3] = [header::CONTENT_TYPE, header::ETAG, header::LOCATION];

#[allow(
    clippy::too_many_lines,
    reason = "the idempotency protocol's states in order: claim, replay, conflict, store"
)]
pub(crate) async fn guard(
    State(state): State<AppState>,
    req: Request,
    next: Next,
) -> Result<Response, ApiError> {
    if !matches!(*req.method(), Method::POST | Method::PUT | Method::PATCH | Method::DELETE) {
        return Ok(next.run(req).await);
    }
    let Some(key) = req.headers().get(IDEMPOTENCY_KEY) else {
        return Ok(next.run(req).await);
    };
    // A method the route does not have is a 405 from the router, key or not.
    if !is_operation(req.method(), req.extensions().get::<MatchedPath>()) {
        return Ok(next.run(req).await);
    }
    let key = key
        .to_str()
        .ok()
        .filter(|k| !k.is_empty() && k.len() <= store::MAX_IDEMPOTENCY_KEY_LEN)
        .ok_or_else(|| {
            ApiError::bad_request(format!(
                "Idempotency-Key must be 1 to {} visible ASCII characters",
                store::MAX_IDEMPOTENCY_KEY_LEN
            ))
        })?
        .to_string();
    let principal = req
        .extensions()
        .get::<Caller>()
        .map(|c| c.token_id.clone())
        .ok_or_else(|| ApiError::internal("idempotency check ran before the token check"))?;
    let method = req.method().as_str().to_string();
    let path = req.uri().path_and_query().map_or_else(|| req.uri().path().to_string(), |p| p.to_string());
    let (req, fingerprint) = fingerprint(req, state.inner.cfg.body_limit_bytes).await?;
    let cfg = &state.inner.cfg;
    let (lease_ms, ttl_ms) =
        (cfg.idempotency_lease.as_millis() as i64, cfg.idempotency_ttl.as_millis() as i64);
    let ask = IdempotentRequest {
        principal: &principal,
        key: &key,
        method: &method,
        path: &path,
        fingerprint: &fingerprint,
    };
    match state.store().claim_idempotent(&ask, lease_ms, ttl_ms).await? {
        Claim::Run => {}
        Claim::Replay(stored) => return Ok(replay(stored)),
        Claim::Mismatch { method, path } => {
            return Err(ApiError::new(
                StatusCode::UNPROCESSABLE_ENTITY,
                "idempotency-key-reused",
                format!(
                    "Idempotency-Key {key:?} was used for another request ({method} {path} or another body)"
                ),
            ))
        }
        Claim::InFlight { lease_left_ms } => {
            let mut e = ApiError::new(
                StatusCode::CONFLICT,
                "idempotency-key-in-use",
                format!("a request with Idempotency-Key {key:?} is being served; retry to get its response"),
            );
            let secs = (lease_left_ms as u64).div_ceil(1000).clamp(1, 30);
            e.headers.push((header::RETRY_AFTER, HeaderValue::from(secs)));
            return Err(e);
        }
        Claim::CommittedWithoutResponse { seq } => {
            let detail = format!(
                "the request with Idempotency-Key {key:?} was done (its change is event {seq} of the feed, \
                 GET /v1/events?after={}) but its server stopped before answering; it is not done again",
                seq - 1
            );
            let lost = ApiError::new(StatusCode::CONFLICT, "idempotent-response-lost", detail);
            return Err(lost.with("event_seq", seq));
        }
    }
    // Renew the claim while the handler runs, so a slow request is not taken over.
    let renew = {
        let (store, principal, key) = (state.store().clone(), principal.clone(), key.clone());
        let every = Duration::from_millis((lease_ms / 3).max(50) as u64);
        tokio::spawn(async move {
            loop {
                tokio::time::sleep(every).await;
                if !matches!(store.renew_idempotent(&principal, &key, lease_ms).await, Ok(true)) {
                    break;
                }
            }
        })
    };
    let ctx = RequestContext { idempotency: Some((principal.clone(), key.clone())) };
    let response = store::with_request(ctx, next.run(req)).await;
    renew.abort();
    let (mut parts, body) = response.into_parts();
    let bytes = axum::body::to_bytes(body, MAX_STORED_BODY).await.ok();
    let store = state.store();
    let keep = !parts.status.is_server_error() || store.idempotent_committed(&principal, &key).await?;
    if keep {
        let stored = match &bytes {
            Some(b) => StoredResponse {
                status: parts.status.as_u16(),
                headers: KEPT_HEADERS
                    .iter()
                    .filter_map(|h| {
                        Some((h.as_str().to_string(), parts.headers.get(h)?.to_str().ok()?.to_string()))
                    })
                    .collect(),
                body: b.to_vec(),
            },
            None => too_large(parts.status),
        };
        store.complete_idempotent(&principal, &key, Some(&stored)).await?;
    } else {
        store.complete_idempotent(&principal, &key, None).await?;
    }
    parts.headers.insert(HeaderName::from_static(REPLAYED), HeaderValue::from_static("false"));
    Ok(match bytes {
        Some(b) => Response::from_parts(parts, Body::from(b)),
        None => replay(too_large(parts.status)),
    })
}

/// Whether `method` on the matched route is an operation of the API (the OpenAPI document lists
/// every one).
fn is_operation(method: &Method, path: Option<&MatchedPath>) -> bool {
    static OPERATIONS: std::sync::OnceLock<std::collections::HashSet<(String, String)>> =
        std::sync::OnceLock::new();
    let ops = OPERATIONS.get_or_init(|| {
        let doc = crate::openapi();
        let mut set = std::collections::HashSet::new();
        for (path, item) in &doc.paths.paths {
            for (m, op) in
                [("PUT", &item.put), ("POST", &item.post), ("DELETE", &item.delete), ("PATCH", &item.patch)]
            {
                if op.is_some() {
                    set.insert((m.to_string(), path.clone()));
                }
            }
        }
        set
    });
    path.is_some_and(|p| ops.contains(&(method.as_str().to_string(), p.as_str().to_string())))
}

/// The request, with its body read back in when it was buffered, and its fingerprint.
async fn fingerprint(req: Request, limit: usize) -> Result<(Request, String), ApiError> {
    let length = req
        .headers()
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok());
    let content_type =
        req.headers().get(header::CONTENT_TYPE).and_then(|v| v.to_str().ok()).unwrap_or("").to_string();
    match length {
        Some(n) if n <= limit as u64 => {
            let (parts, body) = req.into_parts();
            let bytes = axum::body::to_bytes(body, limit)
                .await
                .map_err(|e| ApiError::bad_request(format!("cannot read the request body: {e}")))?;
            let digest = store::sha256_hex(&bytes);
            Ok((Request::from_parts(parts, Body::from(bytes)), digest))
        }
        _ => {
            let text = format!("streamed\n{}\n{content_type}", length.map_or("-".into(), |n| n.to_string()));
            Ok((req, store::sha256_hex(text.as_bytes())))
        }
    }
}

fn too_large(status: StatusCode) -> StoredResponse {
    let e = ApiError::new(
        status,
        "idempotent-response-too-large",
        format!("the first response ({status}) was larger than {MAX_STORED_BODY} bytes and was not kept"),
    );
    StoredResponse {
        status: status.as_u16(),
        headers: vec![("content-type".into(), "application/problem+json".into())],
        body: serde_json::to_vec(&e.problem).unwrap_or_default(),
    }
}

fn replay(stored: StoredResponse) -> Response {
    let status = StatusCode::from_u16(stored.status).unwrap_or(StatusCode::INTERNAL_SERVER_ERROR);
    let mut resp = (status, stored.body).into_response();
    for (name, value) in stored.headers {
        if let (Ok(n), Ok(v)) = (HeaderName::try_from(name), HeaderValue::try_from(value)) {
            resp.headers_mut().insert(n, v);
        }
    }
    resp.headers_mut().insert(HeaderName::from_static(REPLAYED), HeaderValue::from_static("true"));
    resp
}
