//! Bearer-token authentication (tokens live hashed in the store) and role checks.

use crate::error::ApiError;
use crate::AppState;
use axum::extract::{Request, State};
use axum::http::header;
use axum::middleware::Next;
use axum::response::Response;
use std::collections::HashMap;
use std::sync::Arc;
use std::sync::Mutex;
use std::time::{Duration, Instant};
use store::Role;

/// Who is calling: the token's name (recorded as the actor of every write) and its role.
#[derive(Debug, Clone)]
pub struct Caller {
    pub token_id: String,
    pub name: String,
    pub role: Role,
}

impl Caller {
    /// Fails with 403 unless the caller's role is at least `role`.
    pub fn require(&self, role: Role) -> Result<(), ApiError> {
        if self.role >= role {
            Ok(())
        } else {
            Err(ApiError::forbidden(format!(
                "token {:?} has role {}, this needs {} or above",
                self.name,
                self.role.as_str(),
                role.as_str()
            )))
        }
    }
}

/// A short-lived cache of verified tokens (keyed by the secret's sha256), so that a busy client
/// does not cost a catalog read per request. A revoked token stops working within the TTL.
pub(crate) struct TokenCache {
    ttl: Duration,
    map: Mutex<HashMap<String, (Caller, Instant)>>,
}

impl TokenCache {
    pub fn new(ttl: Duration) -> Self {
        TokenCache { ttl, map: Mutex::new(HashMap::new()) }
    }
    fn get(&self, key: &str) -> Option<Caller> {
        let map = self.map.lock().expect("token cache lock");
        map.get(key).filter(|(_, t)| t.elapsed() < self.ttl).map(|(c, _)| c.clone())
    }
    /// Whether this token was valid when last checked, however long ago (while the cache
    /// holds it): its re-check is not a guess, so the per-address limit does not apply.
    fn seen_valid(&self, key: &str) -> bool {
        self.map.lock().expect("token cache lock").contains_key(key)
    }
    fn put(&self, key: String, caller: Caller) {
        let mut map = self.map.lock().expect("token cache lock");
        if map.len() > 10_000 {
            map.clear();
        }
        map.insert(key, (caller, Instant::now()));
    }
}

/// Middleware: every route behind it needs `Authorization: Bearer <token>` (or the web page's
/// session cookie, see `session.rs`); puts the [`Caller`] into the request's extensions.
pub(crate) async fn require_token(
    State(state): State<AppState>,
    req: Request,
    next: Next,
) -> Result<Response, ApiError> {
    // No Authorization header: the web page's session cookie (with its CSRF rule), if any.
    let Some(value) = req.headers().get(header::AUTHORIZATION) else {
        let secret = crate::session::secret_from_cookie(&state, &req)?;
        return authenticate(&state, &secret, req, next).await;
    };
    let value = value.to_str().map_err(|_| ApiError::unauthorized("malformed Authorization header"))?;
    let secret = value
        .strip_prefix("Bearer ")
        .or_else(|| value.strip_prefix("bearer "))
        .map(str::trim)
        .filter(|s| !s.is_empty() && s.len() <= 256)
        .ok_or_else(|| ApiError::unauthorized("expected Authorization: Bearer <token>"))?
        .to_string();
    authenticate(&state, &secret, req, next).await
}

async fn authenticate(
    state: &AppState,
    secret: &str,
    mut req: Request,
    next: Next,
) -> Result<Response, ApiError> {
    let key = store::sha256_hex(secret.as_bytes());
    let caller = match state.inner.tokens.get(&key) {
        Some(c) => c,
        None => {
            check_unverified(state, &key, peer(&req))?;
            // A burst of new clients waits its turn briefly; a flood of made-up tokens gets 429.
            let _check = tokio::time::timeout(Duration::from_secs(2), state.inner.token_checks.acquire())
                .await
                .ok()
                .and_then(Result::ok)
                .ok_or_else(|| too_many("too many token checks at once"))?;
            let rec = state
                .inner
                .store
                .verify_token(secret)
                .await?
                .ok_or_else(|| ApiError::unauthorized("unknown or revoked token"))?;
            let c = Caller { token_id: rec.id, name: rec.name, role: rec.role };
            state.inner.tokens.put(key, c.clone());
            c
        }
    };
    if let Some(limiter) = &state.inner.token_rate {
        if limiter.check_key(&caller.token_id).is_err() {
            return Err(too_many(&format!(
                "token {} made more than {} requests per second, the limit",
                caller.name, state.inner.cfg.rate_limit_per_token
            )));
        }
    }
    // One token's requests in flight are bounded (held until the handler has answered).
    let permits = {
        let mut map = state.inner.in_flight.lock().unwrap_or_else(|e| e.into_inner());
        map.entry(caller.token_id.clone())
            .or_insert_with(|| {
                Arc::new(tokio::sync::Semaphore::new(state.inner.cfg.max_in_flight_per_token.max(1)))
            })
            .clone()
    };
    let _permit = permits.try_acquire_owned().map_err(|_| {
        too_many(&format!(
            "token {} has {} requests in flight, the limit",
            caller.name, state.inner.cfg.max_in_flight_per_token
        ))
    })?;
    req.extensions_mut().insert(caller);
    Ok(next.run(req).await)
}

/// A rate limiter per key (GCRA, the `governor` crate): `per_second` on average, bursts of
/// `burst_factor` seconds' worth.
pub(crate) type KeyedLimiter<K> = governor::DefaultKeyedRateLimiter<K>;

/// None when `per_second` is 0 (no limit).
pub(crate) fn keyed_limiter<K: std::hash::Hash + Eq + Clone>(
    per_second: u32,
    burst_factor: u32,
) -> Option<KeyedLimiter<K>> {
    let rate = std::num::NonZeroU32::new(per_second)?;
    let burst = std::num::NonZeroU32::new(per_second.saturating_mul(burst_factor.max(1))).unwrap_or(rate);
    Some(governor::RateLimiter::keyed(governor::Quota::per_second(rate).allow_burst(burst)))
}

/// A secret never seen valid costs a catalog read: such checks are bounded per peer address
/// (`cfg.unverified_checks_per_peer`), before the catalog is asked. `key` is the secret's hash.
pub(crate) fn check_unverified(
    state: &AppState,
    key: &str,
    peer: Option<std::net::IpAddr>,
) -> Result<(), ApiError> {
    if let (Some(limiter), Some(peer)) = (&state.inner.unverified_checks, peer) {
        if !state.inner.tokens.seen_valid(key) && limiter.check_key(&peer).is_err() {
            return Err(too_many(&format!("too many checks of unknown tokens from {peer}")));
        }
    }
    Ok(())
}

/// The peer's address (set by the accept loop, `conn.rs`; absent when the router is called
/// directly, as in some tests).
pub(crate) fn peer(req: &Request) -> Option<std::net::IpAddr> {
    req.extensions().get::<axum::extract::ConnectInfo<std::net::SocketAddr>>().map(|c| c.0.ip())
}

/// 429 with `Retry-After: 1`.
fn too_many(why: &str) -> ApiError {
    let mut e = ApiError::new(
        axum::http::StatusCode::TOO_MANY_REQUESTS,
        "too-many-requests",
        format!("{why}; retry shortly"),
    );
    e.headers.push((header::RETRY_AFTER, axum::http::HeaderValue::from_static("1")));
    e
}

/// Route-level middleware: 403 unless the caller (set by [`require_token`]) has at least this
/// role. Runs before the body is read, so a low-privilege caller learns nothing from validation.
pub(crate) async fn require_role(
    State(min): State<Role>,
    req: Request,
    next: Next,
) -> Result<Response, ApiError> {
    let caller = req.extensions().get::<Caller>().ok_or_else(|| ApiError::unauthorized("missing token"))?;
    caller.require(min)?;
    Ok(next.run(req).await)
}

impl TokenCache {
    pub fn clear(&self) {
        self.map.lock().expect("token cache lock").clear();
    }
}
