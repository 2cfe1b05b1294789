//! Idempotency keys: a request sent again with the same `Idempotency-Key` gets the first
//! response instead of doing its work twice.
//!
//! A key is claimed (per principal) before the request runs, with a lease its server renews
//! while it runs; the response is stored when it ends and replayed until the key expires. The
//! change the request makes marks the key committed in its own transaction (`events.rs`), so a
//! retry after the serving process died knows whether the work happened: if it did not, the
//! retry runs it; if it did, the retry is told so ([`Claim::CommittedWithoutResponse`]) and is
//! never run a second time. The HTTP side is the API's `idempotency.rs`.

use crate::catalog::{RowExt, Tx};
use crate::{now_ms, Store, StoreError};

/// What a request with a key may do.
#[derive(Debug, Clone, PartialEq)]
pub enum Claim {
    /// The key is this request's now (first use, or a lapsed claim whose work never
    /// committed): run it, then [`Store::complete_idempotent`].
    Run,
    /// Answered before: send this response again.
    Replay(StoredResponse),
    /// The key was used with a different method, path or body.
    Mismatch { method: String, path: String },
    /// Another request with this key is being served now (its lease is live).
    InFlight { lease_left_ms: i64 },
    /// The work committed (as event `seq`) but the server stopped before storing the response.
    CommittedWithoutResponse { seq: i64 },
}

/// A response kept for a key.
#[derive(Debug, Clone, PartialEq)]
pub struct StoredResponse {
    pub status: u16,
    /// The headers worth replaying (content type, ETag, Location), in order.
    pub headers: Vec<(String, String)>,
    pub body: Vec<u8>,
}

/// What identifies a request under its key.
#[derive(Debug, Clone)]
pub struct IdempotentRequest<'a> {
    pub principal: &'a str,
    pub key: &'a str,
    pub method: &'a str,
    pub path: &'a str,
    /// sha256 (hex) of what the request carried (its body, for most routes).
    pub fingerprint: &'a str,
}

/// The longest key accepted (Stripe's limit).
pub const MAX_IDEMPOTENCY_KEY_LEN: usize = 255;

/// Marks the key committed by the change whose last event is `seq` (inside that transaction).
pub(crate) async fn mark_committed(
    tx: &mut Tx,
    principal: &str,
    key: &str,
    seq: i64,
) -> Result<(), StoreError> {
    sqlx::query(
        "UPDATE idempotency_keys SET committed_seq = $1 WHERE principal = $2 AND key = $3 AND committed_seq IS NULL",
    )
    .bind(seq)
    .bind(principal)
    .bind(key)
    .execute(&mut **tx)
    .await?;
    Ok(())
}

impl Store {
    /// Claims `req.key` for `lease_ms`, or says why not; a key unused for `ttl_ms` is free again.
    pub async fn claim_idempotent(
        &self,
        req: &IdempotentRequest<'_>,
        lease_ms: i64,
        ttl_ms: i64,
    ) -> Result<Claim, StoreError> {
        if req.key.is_empty()
            || req.key.len() > MAX_IDEMPOTENCY_KEY_LEN
            || !req.key.bytes().all(|b| b.is_ascii_graphic())
        {
            return Err(StoreError::invalid(format!(
                "Idempotency-Key must be 1 to {MAX_IDEMPOTENCY_KEY_LEN} visible ASCII characters"
            )));
        }
        let now = now_ms();
        let mut tx = self.catalog().begin_write().await?;
        let lock = if self.backend() == crate::Backend::Postgres { " FOR UPDATE" } else { "" };
        let row = sqlx::query(&format!(
            "SELECT method, path, request_sha256, lease_until_ms, committed_seq, status, headers, body, \
             expires_ms FROM idempotency_keys WHERE principal = $1 AND key = $2{lock}"
        ))
        .bind(req.principal)
        .bind(req.key)
        .fetch_optional(&mut *tx)
        .await?;
        let claim = match row {
            Some(r) if r.i("expires_ms")? >= now => {
                if r.s("method")? != req.method
                    || r.s("path")? != req.path
                    || r.s("request_sha256")? != req.fingerprint
                {
                    Claim::Mismatch { method: r.s("method")?, path: r.s("path")? }
                } else if let Some(status) = r.oi("status")? {
                    let body: Option<Vec<u8>> = sqlx::Row::try_get(&r, "body")?;
                    let headers = match r.os("headers")? {
                        Some(t) => serde_json::from_str(&t)
                            .map_err(|e| StoreError::Corrupt(format!("stored response headers: {e}")))?,
                        None => Vec::new(),
                    };
                    Claim::Replay(StoredResponse {
                        status: u16::try_from(status)
                            .map_err(|_| StoreError::Corrupt("stored status".into()))?,
                        headers,
                        body: body.unwrap_or_default(),
                    })
                } else if r.i("lease_until_ms")? > now {
                    Claim::InFlight { lease_left_ms: r.i("lease_until_ms")? - now }
                } else if let Some(seq) = r.oi("committed_seq")? {
                    Claim::CommittedWithoutResponse { seq }
                } else {
                    // Its server died before the work committed: the work is ours to do.
                    sqlx::query(
                        "UPDATE idempotency_keys SET lease_until_ms = $1 WHERE principal = $2 AND key = $3",
                    )
                    .bind(now + lease_ms)
                    .bind(req.principal)
                    .bind(req.key)
                    .execute(&mut *tx)
                    .await?;
                    Claim::Run
                }
            }
            stale => {
                if stale.is_some() {
                    sqlx::query("DELETE FROM idempotency_keys WHERE principal = $1 AND key = $2")
                        .bind(req.principal)
                        .bind(req.key)
                        .execute(&mut *tx)
                        .await?;
                }
                // Two first uses at once on Postgres: the loser's insert fails on the key and
                // its retry finds the winner's claim.
                let inserted = sqlx::query(
                    "INSERT INTO idempotency_keys (principal, key, method, path, request_sha256, lease_until_ms, \
                     created_ms, expires_ms) VALUES ($1, $2, $3, $4, $5, $6, $7, $8) ON CONFLICT DO NOTHING",
                )
                .bind(req.principal)
                .bind(req.key)
                .bind(req.method)
                .bind(req.path)
                .bind(req.fingerprint)
                .bind(now + lease_ms)
                .bind(now)
                .bind(now + ttl_ms)
                .execute(&mut *tx)
                .await?;
                if inserted.rows_affected() == 1 {
                    Claim::Run
                } else {
                    Claim::InFlight { lease_left_ms: lease_ms }
                }
            }
        };
        tx.commit().await?;
        Ok(claim)
    }

    /// Extends the lease of a claim being served; `false` if it is no longer held.
    pub async fn renew_idempotent(
        &self,
        principal: &str,
        key: &str,
        lease_ms: i64,
    ) -> Result<bool, StoreError> {
        let r = sqlx::query(
            "UPDATE idempotency_keys SET lease_until_ms = $1 WHERE principal = $2 AND key = $3 AND status IS NULL",
        )
        .bind(now_ms() + lease_ms)
        .bind(principal)
        .bind(key)
        .execute(&self.catalog().pool)
        .await?;
        Ok(r.rows_affected() == 1)
    }

    /// Stores the response of a claimed request (replayed to retries), or, with `None`, gives
    /// the key up (a failure that changed nothing: a retry runs again) unless its work committed.
    pub async fn complete_idempotent(
        &self,
        principal: &str,
        key: &str,
        response: Option<&StoredResponse>,
    ) -> Result<(), StoreError> {
        match response {
            Some(resp) => {
                sqlx::query(
                    "UPDATE idempotency_keys SET status = $1, headers = $2, body = $3, lease_until_ms = 0 \
                     WHERE principal = $4 AND key = $5",
                )
                .bind(resp.status as i64)
                .bind(serde_json::to_string(&resp.headers)?)
                .bind(resp.body.clone())
                .bind(principal)
                .bind(key)
                .execute(&self.catalog().pool)
                .await?;
            }
            None => {
                sqlx::query(
                    "DELETE FROM idempotency_keys WHERE principal = $1 AND key = $2 AND committed_seq IS NULL \
                     AND status IS NULL",
                )
                .bind(principal)
                .bind(key)
                .execute(&self.catalog().pool)
                .await?;
            }
        }
        Ok(())
    }

    /// Whether the claimed request's work has committed (its change marked the key).
    pub async fn idempotent_committed(&self, principal: &str, key: &str) -> Result<bool, StoreError> {
        let r = sqlx::query("SELECT committed_seq FROM idempotency_keys WHERE principal = $1 AND key = $2")
            .bind(principal)
            .bind(key)
            .fetch_optional(&self.catalog().pool)
            .await?;
        Ok(match r {
            Some(r) => r.oi("committed_seq")?.is_some(),
            None => false,
        })
    }

    /// Deletes keys past their expiry; returns how many.
    pub async fn prune_idempotency_keys(&self) -> Result<u64, StoreError> {
        let r = sqlx::query("DELETE FROM idempotency_keys WHERE expires_ms < $1")
            .bind(now_ms())
            .execute(&self.catalog().pool)
            .await?;
        Ok(r.rows_affected())
    }
}
