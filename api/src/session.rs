//! Browser sessions for the labeling page: an `HttpOnly; SameSite=Strict` cookie holds a random
//! session id; the server keeps `id → token secret` in memory (never sent back to the browser),
//! so a session stops working when its token is revoked (within the token cache's TTL). This
//! module owns the sessions, the cookie and the CSRF rule; the `/ui/session` routes that sign in
//! and out are `session_routes.rs`, and the token middleware (`auth.rs`) reads the cookie here.
//!
//! CSRF: the cookie is `SameSite=Strict`, and every cookie-authenticated request with an unsafe
//! method (and the sign-in itself) must carry `X-Ufops-UI: 1` — a custom header a cross-site form
//! cannot send and cross-site scripts cannot add without a CORS preflight this server never
//! grants — and, when the browser sends `Origin`, it must match the server's public origin
//! (`--public-url`, for a server behind a TLS proxy; the cookie then also gets `Secure`), else
//! `Host`. Each token holds at most [`MAX_SESSIONS_PER_TOKEN`] sessions (its least recently used
//! one is dropped), so one token signing in in a loop cannot push other people's sessions out.

use crate::error::{ApiError, ApiResult};
use crate::AppState;
use axum::extract::Request;
use axum::http::{header, HeaderMap, Method};
use std::collections::HashMap;
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// The session cookie's name.
pub const COOKIE: &str = "ufops_session";
/// The header cookie-authenticated unsafe requests must carry (value `1`).
pub const CSRF_HEADER: &str = "x-ufops-ui";
/// A session ends after this long without a request…
const IDLE: Duration = Duration::from_secs(12 * 3600);
/// …and at the latest this long after sign-in.
pub(crate) const MAX_AGE: Duration = Duration::from_secs(7 * 24 * 3600);
const MAX_SESSIONS: usize = 10_000;
/// Sessions one token may hold (browsers, tabs after cookie loss, a few machines).
pub const MAX_SESSIONS_PER_TOKEN: usize = 32;

struct Session {
    secret: String,
    created: Instant,
    last_seen: Instant,
}

/// The server's sessions (in memory: a restart signs everyone out).
#[derive(Default)]
pub(crate) struct Sessions {
    map: Mutex<HashMap<String, Session>>,
}

impl Sessions {
    pub(crate) fn create(&self, secret: String) -> String {
        // Two v4 UUIDs from the OS random source: 244 random bits.
        let id = format!("{}{}", uuid::Uuid::new_v4().simple(), uuid::Uuid::new_v4().simple());
        let now = Instant::now();
        let mut map = self.map.lock().unwrap_or_else(|e| e.into_inner());
        let mut mine: Vec<(Instant, String)> =
            map.iter().filter(|(_, s)| s.secret == secret).map(|(k, s)| (s.last_seen, k.clone())).collect();
        if mine.len() >= MAX_SESSIONS_PER_TOKEN {
            mine.sort();
            let drop = mine.len() + 1 - MAX_SESSIONS_PER_TOKEN;
            for (_, k) in mine.into_iter().take(drop) {
                map.remove(&k);
            }
        }
        if map.len() >= MAX_SESSIONS {
            map.retain(|_, s| {
                now.duration_since(s.last_seen) < IDLE && now.duration_since(s.created) < MAX_AGE
            });
            if map.len() >= MAX_SESSIONS {
                // Drop the least recently used tenth.
                let mut by_age: Vec<(Instant, String)> =
                    map.iter().map(|(k, s)| (s.last_seen, k.clone())).collect();
                by_age.sort();
                for (_, k) in by_age.into_iter().take(MAX_SESSIONS / 10) {
                    map.remove(&k);
                }
            }
        }
        map.insert(id.clone(), Session { secret, created: now, last_seen: now });
        id
    }

    /// The token secret behind a live session id (and marks it used).
    fn secret(&self, id: &str) -> Option<String> {
        let now = Instant::now();
        let mut map = self.map.lock().unwrap_or_else(|e| e.into_inner());
        let s = map.get_mut(id)?;
        if now.duration_since(s.last_seen) >= IDLE || now.duration_since(s.created) >= MAX_AGE {
            map.remove(id);
            return None;
        }
        s.last_seen = now;
        Some(s.secret.clone())
    }

    pub(crate) fn remove(&self, id: &str) {
        self.map.lock().unwrap_or_else(|e| e.into_inner()).remove(id);
    }
}

/// The value of our cookie in a `Cookie` header, if any.
pub(crate) fn cookie_value(headers: &HeaderMap) -> Option<String> {
    headers
        .get_all(header::COOKIE)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(';'))
        .filter_map(|kv| kv.trim().split_once('='))
        .find(|(k, _)| *k == COOKIE)
        .map(|(_, v)| v.trim().to_string())
        .filter(|v| !v.is_empty() && v.len() <= 128 && v.bytes().all(|b| b.is_ascii_alphanumeric()))
}

fn is_safe(m: &Method) -> bool {
    matches!(*m, Method::GET | Method::HEAD | Method::OPTIONS)
}

/// The CSRF rule for cookie-authenticated unsafe requests (see the module docs); `public_origin`
/// is `scheme://host[:port]` of `--public-url`.
pub(crate) fn check_csrf(headers: &HeaderMap, public_origin: Option<&str>) -> ApiResult<()> {
    let marked = headers.get(CSRF_HEADER).and_then(|v| v.to_str().ok()).is_some_and(|v| v.trim() == "1");
    if !marked {
        return Err(ApiError::forbidden(format!(
            "a request authenticated by the session cookie that changes data must carry the header {CSRF_HEADER}: 1"
        )));
    }
    if let Some(origin) = headers.get(header::ORIGIN) {
        let origin = origin.to_str().unwrap_or("");
        let same = match public_origin {
            // Behind a proxy the Host header may be the proxy's upstream; the public origin decides.
            Some(public) => origin.eq_ignore_ascii_case(public),
            None => {
                let host = headers.get(header::HOST).and_then(|v| v.to_str().ok()).unwrap_or("");
                let origin_host = origin.split_once("://").map(|(_, h)| h).unwrap_or("");
                !host.is_empty() && origin_host == host
            }
        };
        if !same {
            return Err(ApiError::forbidden(format!("cross-origin request from {origin:?} refused")));
        }
    }
    Ok(())
}

/// For [`crate::auth::require_token`] when the request has no `Authorization` header: the token
/// secret of the request's session cookie, after the CSRF check for unsafe methods.
pub(crate) fn secret_from_cookie(state: &AppState, req: &Request) -> ApiResult<String> {
    let id = cookie_value(req.headers()).ok_or_else(|| {
        ApiError::unauthorized("missing Authorization: Bearer <token> header (or a signed-in session cookie)")
    })?;
    let secret = state
        .inner
        .sessions
        .secret(&id)
        .ok_or_else(|| ApiError::unauthorized("the session has ended; sign in again"))?;
    if !is_safe(req.method()) {
        check_csrf(req.headers(), state.public_origin())?;
    }
    Ok(secret)
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::http::HeaderValue;

    #[test]
    fn cookie_parsing() {
        let mut h = HeaderMap::new();
        h.insert(header::COOKIE, HeaderValue::from_static("a=b; ufops_session=abc123 ; c=d"));
        assert_eq!(cookie_value(&h).as_deref(), Some("abc123"));
        h.insert(header::COOKIE, HeaderValue::from_static("ufops_session=../x"));
        assert_eq!(cookie_value(&h), None);
        h.remove(header::COOKIE);
        assert_eq!(cookie_value(&h), None);
    }

    #[test]
    fn csrf_rule() {
        let mut h = HeaderMap::new();
        assert!(check_csrf(&h, None).is_err());
        h.insert(CSRF_HEADER, HeaderValue::from_static("1"));
        assert!(check_csrf(&h, None).is_ok());
        h.insert(header::HOST, HeaderValue::from_static("127.0.0.1:8080"));
        h.insert(header::ORIGIN, HeaderValue::from_static("http://127.0.0.1:8080"));
        assert!(check_csrf(&h, None).is_ok());
        h.insert(header::ORIGIN, HeaderValue::from_static("http://evil.example"));
        assert!(check_csrf(&h, None).is_err());
        // Behind a TLS proxy: the public origin decides, whatever Host the proxy forwards.
        let public = Some("https://label.example.com");
        h.insert(header::ORIGIN, HeaderValue::from_static("https://label.example.com"));
        assert!(check_csrf(&h, public).is_ok());
        h.insert(header::ORIGIN, HeaderValue::from_static("http://127.0.0.1:8080"));
        assert!(check_csrf(&h, public).is_err(), "the proxy's upstream is not the public origin");
        h.insert(header::ORIGIN, HeaderValue::from_static("http://label.example.com"));
        assert!(check_csrf(&h, public).is_err(), "plain http is another origin");
    }

    #[test]
    fn one_token_cannot_hold_more_than_its_share_of_sessions() {
        let s = Sessions::default();
        let other = s.create("other".into());
        let first = s.create("loop".into());
        let mut last = String::new();
        for _ in 0..(MAX_SESSIONS_PER_TOKEN * 3) {
            last = s.create("loop".into());
        }
        let held = s.map.lock().unwrap().values().filter(|x| x.secret == "loop").count();
        assert_eq!(held, MAX_SESSIONS_PER_TOKEN);
        assert_eq!(s.secret(&first), None, "its least recently used session went");
        assert_eq!(s.secret(&last).as_deref(), Some("loop"));
        assert_eq!(s.secret(&other).as_deref(), Some("other"), "another token's session is untouched");
    }

    #[test]
    fn sessions_expire_and_sign_out() {
        let s = Sessions::default();
        let id = s.create("secret".into());
        assert_eq!(id.len(), 64);
        assert_eq!(s.secret(&id).as_deref(), Some("secret"));
        s.remove(&id);
        assert_eq!(s.secret(&id), None);
    }
}
