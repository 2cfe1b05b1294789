//! The labeling page's sign-in routes, outside the bearer-token API and its OpenAPI document:
//! `POST /ui/session {token}` checks an API token and sets the session cookie, `GET /ui/session`
//! says who is signed in, `DELETE /ui/session` signs out (forgets the id, clears the cookie).
//! The sessions, the cookie and the CSRF rule are `session.rs`.

use crate::auth::Caller;
use crate::error::{ApiError, ApiResult};
use crate::extract::ApiJson;
use crate::session::{check_csrf, cookie_value, COOKIE, MAX_AGE};
use crate::AppState;
use axum::extract::State;
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::post;
use axum::{Json, Router};
use serde::Deserialize;
use serde_json::json;

fn set_cookie(value: &str, max_age: u64, secure: bool) -> HeaderValue {
    let secure = if secure { "; Secure" } else { "" };
    HeaderValue::from_str(&format!(
        "{COOKIE}={value}; Path=/; HttpOnly; SameSite=Strict; Max-Age={max_age}{secure}"
    ))
    .unwrap_or_else(|_| {
        HeaderValue::from_static("ufops_session=; Path=/; HttpOnly; SameSite=Strict; Max-Age=0")
    })
}

fn who(c: &Caller) -> serde_json::Value {
    json!({"name": c.name, "role": c.role.as_str(), "token_id": c.token_id})
}

#[derive(Deserialize)]
pub(crate) struct SignIn {
    token: String,
}

/// `POST /ui/session {token}` → 200 `{name, role, token_id}` + the cookie; 401 for a bad token.
async fn sign_in(
    State(s): State<AppState>,
    peer: Option<axum::Extension<axum::extract::ConnectInfo<std::net::SocketAddr>>>,
    headers: HeaderMap,
    ApiJson(body): ApiJson<SignIn>,
) -> ApiResult<Response> {
    check_csrf(&headers, s.public_origin())?;
    let secret = body.token.trim().to_string();
    if secret.is_empty() || secret.len() > 256 {
        return Err(ApiError::unauthorized("unknown or revoked token"));
    }
    // Guessing tokens through the sign-in form is bounded like guessing them in a header.
    crate::auth::check_unverified(&s, &store::sha256_hex(secret.as_bytes()), peer.map(|p| p.0 .0.ip()))?;
    let rec = s
        .store()
        .verify_token(&secret)
        .await?
        .ok_or_else(|| ApiError::unauthorized("unknown or revoked token"))?;
    let caller = Caller { token_id: rec.id, name: rec.name, role: rec.role };
    let id = s.inner.sessions.create(secret);
    let mut resp = Json(who(&caller)).into_response();
    resp.headers_mut().insert(header::SET_COOKIE, set_cookie(&id, MAX_AGE.as_secs(), s.secure_cookies()));
    resp.headers_mut().insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    Ok(resp)
}

/// `GET /ui/session` → who is signed in (through the cookie or a bearer token), 401 otherwise.
async fn whoami(axum::Extension(caller): axum::Extension<Caller>) -> Response {
    let mut resp = Json(who(&caller)).into_response();
    resp.headers_mut().insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    resp
}

/// `DELETE /ui/session` → 204, the session forgotten and the cookie cleared (also when there
/// was none).
async fn sign_out(State(s): State<AppState>, headers: HeaderMap) -> ApiResult<Response> {
    check_csrf(&headers, s.public_origin())?;
    if let Some(id) = cookie_value(&headers) {
        s.inner.sessions.remove(&id);
    }
    let mut resp = StatusCode::NO_CONTENT.into_response();
    resp.headers_mut().insert(header::SET_COOKIE, set_cookie("", 0, s.secure_cookies()));
    Ok(resp)
}

/// The session routes: sign-in and sign-out are open (they check the token / CSRF themselves);
/// `GET /ui/session` sits behind the token middleware.
pub(crate) fn routes(state: AppState) -> Router<AppState> {
    use axum::handler::Handler;
    let authed_whoami = whoami.layer(axum::middleware::from_fn_with_state(state, crate::auth::require_token));
    Router::new().route("/ui/session", post(sign_in).delete(sign_out).get(authed_whoami))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cookies_are_secure_behind_tls() {
        assert!(set_cookie("abc", 10, true).to_str().unwrap().ends_with("; Secure"));
        assert!(!set_cookie("abc", 10, false).to_str().unwrap().contains("Secure"));
    }
}
