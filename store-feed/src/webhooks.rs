//! Webhook subscriptions: a URL, a secret, an event filter and a cursor into the change feed
//! (`events.rs`), with the state of the delivery in progress and the dead letters. The delivering
//! loop is the API's (`api/src/webhooks.rs`); every step it takes is a row update here, fenced by
//! the subscription's lease, so a restart or a second server loses or doubles nothing.

use serde::Serialize;
use std::future::Future;
use store::sql::RowExt;
use store::sql::{now_ms, now_rfc3339};
use store::{EventFilter, EventKind};
use store::{Store, StoreError};

/// A subscription, without its secret.
#[derive(Debug, Clone, Serialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct WebhookRecord {
    pub id: String,
    pub url: String,
    /// Event kinds delivered (empty: all).
    pub kinds: Vec<EventKind>,
    pub policy: Option<String>,
    /// Failed attempts at one event before it goes to the dead letters.
    pub max_attempts: i64,
    /// The last event delivered or given up on.
    pub cursor_seq: i64,
    /// Failed attempts at the next event so far.
    pub attempts: i64,
    pub last_error: Option<String>,
    /// Events delivered so far.
    pub delivered: i64,
    pub created_by: String,
    pub created_at: String,
}

impl WebhookRecord {
    pub fn filter(&self) -> EventFilter {
        EventFilter { kinds: self.kinds.clone(), policy: self.policy.clone() }
    }
}

/// An event a subscription gave up on.
#[derive(Debug, Clone, Serialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct DeadLetter {
    pub webhook_id: String,
    pub seq: i64,
    pub delivery_id: String,
    pub attempts: i64,
    pub last_error: String,
    pub created_at: String,
}

/// A subscription a delivering server holds, with what it needs to sign.
#[derive(Debug, Clone)]
pub struct HeldWebhook {
    pub record: WebhookRecord,
    pub secret: String,
}

/// The largest `max_attempts` a subscription may set.
pub const MAX_WEBHOOK_ATTEMPTS: i64 = 100;

/// The id of the delivery of event `seq` to subscription `webhook_id`: the same on every
/// attempt, so a receiver drops repeats by it.
pub fn delivery_id(webhook_id: &str, seq: i64) -> String {
    format!("{webhook_id}-{seq}")
}

const COLS: &str =
    "id, url, secret, kinds, policy, max_attempts, cursor_seq, attempts, last_error, delivered, \
    created_by, created_at";

fn from_row(r: &sqlx::any::AnyRow) -> Result<HeldWebhook, StoreError> {
    let kinds: Vec<String> = serde_json::from_str(&r.s("kinds")?)
        .map_err(|e| StoreError::Corrupt(format!("webhook kinds: {e}")))?;
    Ok(HeldWebhook {
        record: WebhookRecord {
            id: r.s("id")?,
            url: r.s("url")?,
            kinds: kinds.iter().map(|k| k.parse()).collect::<Result<_, _>>()?,
            policy: r.os("policy")?,
            max_attempts: r.i("max_attempts")?,
            cursor_seq: r.i("cursor_seq")?,
            attempts: r.i("attempts")?,
            last_error: r.os("last_error")?,
            delivered: r.i("delivered")?,
            created_by: r.s("created_by")?,
            created_at: r.s("created_at")?,
        },
        secret: r.s("secret")?,
    })
}

/// Webhook subscriptions on a [`Store`]: registered, listed, claimed by one deliverer at a
/// time, their attempts and dead letters recorded.
pub trait Webhooks {
    /// Subscribes `url` to the events after the feed's head now; returns the subscription and
    /// its signing secret (shown once).
    fn create_webhook(
        &self,
        url: &str,
        filter: &EventFilter,
        max_attempts: i64,
        actor: &str,
    ) -> impl Future<Output = Result<(WebhookRecord, String), StoreError>> + Send;

    fn webhook(&self, id: &str) -> impl Future<Output = Result<WebhookRecord, StoreError>> + Send;

    fn webhooks(&self) -> impl Future<Output = Result<Vec<WebhookRecord>, StoreError>> + Send;

    /// Whether any subscription exists.
    fn has_webhooks(&self) -> impl Future<Output = Result<bool, StoreError>> + Send;

    /// Deletes a subscription and its dead letters.
    fn delete_webhook(&self, id: &str) -> impl Future<Output = Result<(), StoreError>> + Send;

    fn dead_letters(
        &self,
        webhook_id: &str,
    ) -> impl Future<Output = Result<Vec<DeadLetter>, StoreError>> + Send;

    /// Takes the lease of every subscription due for a delivery attempt that no live lease
    /// holds and that the feed has gone past, for `owner` (an idle subscription costs no write).
    fn claim_webhooks(
        &self,
        owner: &str,
        lease_ms: i64,
    ) -> impl Future<Output = Result<Vec<HeldWebhook>, StoreError>> + Send;

    /// Records the outcome of delivering event `seq` (the one after the cursor) while `owner`
    /// holds the lease: `Ok` moves the cursor past it; `Err` counts a failed attempt and
    /// schedules the next after `retry_after_ms`, or, at the subscription's `max_attempts`,
    /// records a dead letter and moves past it. `None` moves the cursor to `seq` with nothing
    /// delivered (no matching event up to it). Returns `false` when the lease was lost.
    fn record_webhook_attempt(
        &self,
        id: &str,
        owner: &str,
        seq: i64,
        outcome: Option<Result<(), String>>,
        retry_after_ms: i64,
    ) -> impl Future<Output = Result<bool, StoreError>> + Send;

    /// Gives a held subscription's lease back (its next delivery may go to any server).
    fn release_webhook(&self, id: &str, owner: &str) -> impl Future<Output = Result<(), StoreError>> + Send;
}

impl Webhooks for Store {
    async fn create_webhook(
        &self,
        url: &str,
        filter: &EventFilter,
        max_attempts: i64,
        actor: &str,
    ) -> Result<(WebhookRecord, String), StoreError> {
        store::model::check_name("actor", actor)?;
        let lower = url.to_ascii_lowercase();
        if !(lower.starts_with("http://") || lower.starts_with("https://")) || url.len() > 2000 {
            return Err(StoreError::invalid(format!(
                "webhook URL {url:?}: expected http(s)://HOST[:PORT]/PATH"
            )));
        }
        if !(1..=MAX_WEBHOOK_ATTEMPTS).contains(&max_attempts) {
            return Err(StoreError::invalid(format!("max_attempts must be 1 to {MAX_WEBHOOK_ATTEMPTS}")));
        }
        let id = format!("wh_{}", &uuid::Uuid::new_v4().simple().to_string()[..12]);
        let secret = format!("whsec_{}", uuid::Uuid::new_v4().simple());
        let kinds: Vec<&str> = filter.kinds.iter().map(|k| k.as_str()).collect();
        let (head, _) = self.event_head().await?;
        sqlx::query(&format!(
            "INSERT INTO webhooks ({COLS}, next_attempt_ms, lease_owner, lease_until_ms) \
             VALUES ($1, $2, $3, $4, $5, $6, $7, 0, NULL, 0, $8, $9, 0, NULL, 0)"
        ))
        .bind(&id)
        .bind(url)
        .bind(&secret)
        .bind(serde_json::to_string(&kinds)?)
        .bind(filter.policy.clone())
        .bind(max_attempts)
        .bind(head)
        .bind(actor)
        .bind(now_rfc3339())
        .execute(&self.catalog().pool)
        .await?;
        Ok((self.webhook(&id).await?, secret))
    }

    async fn webhook(&self, id: &str) -> Result<WebhookRecord, StoreError> {
        let row = sqlx::query(&format!("SELECT {COLS} FROM webhooks WHERE id = $1"))
            .bind(id)
            .fetch_optional(&self.catalog().pool)
            .await?
            .ok_or_else(|| StoreError::not_found("webhook", id))?;
        Ok(from_row(&row)?.record)
    }

    async fn webhooks(&self) -> Result<Vec<WebhookRecord>, StoreError> {
        let rows = sqlx::query(&format!("SELECT {COLS} FROM webhooks ORDER BY created_at, id"))
            .fetch_all(&self.catalog().pool)
            .await?;
        rows.iter().map(|r| Ok(from_row(r)?.record)).collect()
    }

    async fn has_webhooks(&self) -> Result<bool, StoreError> {
        let row = sqlx::query("SELECT id FROM webhooks LIMIT 1").fetch_optional(&self.catalog().pool).await?;
        Ok(row.is_some())
    }

    async fn delete_webhook(&self, id: &str) -> Result<(), StoreError> {
        let mut tx = self.catalog().begin_write().await?;
        sqlx::query("DELETE FROM webhook_dead_letters WHERE webhook_id = $1")
            .bind(id)
            .execute(&mut *tx)
            .await?;
        let r = sqlx::query("DELETE FROM webhooks WHERE id = $1").bind(id).execute(&mut *tx).await?;
        if r.rows_affected() == 0 {
            return Err(StoreError::not_found("webhook", id));
        }
        tx.commit().await?;
        Ok(())
    }

    async fn dead_letters(&self, webhook_id: &str) -> Result<Vec<DeadLetter>, StoreError> {
        self.webhook(webhook_id).await?;
        let rows = sqlx::query(
            "SELECT webhook_id, seq, delivery_id, attempts, last_error, created_at FROM webhook_dead_letters \
             WHERE webhook_id = $1 ORDER BY seq",
        )
        .bind(webhook_id)
        .fetch_all(&self.catalog().pool)
        .await?;
        rows.iter()
            .map(|r| {
                Ok(DeadLetter {
                    webhook_id: r.s("webhook_id")?,
                    seq: r.i("seq")?,
                    delivery_id: r.s("delivery_id")?,
                    attempts: r.i("attempts")?,
                    last_error: r.s("last_error")?,
                    created_at: r.s("created_at")?,
                })
            })
            .collect()
    }

    async fn claim_webhooks(&self, owner: &str, lease_ms: i64) -> Result<Vec<HeldWebhook>, StoreError> {
        let now = now_ms();
        let rows = sqlx::query(&format!(
            "UPDATE webhooks SET lease_owner = $1, lease_until_ms = $2 \
             WHERE lease_until_ms < $3 AND next_attempt_ms <= $3 \
             AND cursor_seq < (SELECT seq FROM event_head WHERE id = 1) RETURNING {COLS}"
        ))
        .bind(owner)
        .bind(now + lease_ms)
        .bind(now)
        .fetch_all(&self.catalog().pool)
        .await?;
        rows.iter().map(from_row).collect()
    }

    async fn record_webhook_attempt(
        &self,
        id: &str,
        owner: &str,
        seq: i64,
        outcome: Option<Result<(), String>>,
        retry_after_ms: i64,
    ) -> Result<bool, StoreError> {
        let now = now_ms();
        let mut tx = self.catalog().begin_write().await?;
        let row = sqlx::query(
            "SELECT attempts, max_attempts, cursor_seq FROM webhooks WHERE id = $1 AND lease_owner = $2 AND lease_until_ms >= $3",
        )
        .bind(id)
        .bind(owner)
        .bind(now)
        .fetch_optional(&mut *tx)
        .await?;
        let Some(row) = row else {
            return Ok(false);
        };
        if row.i("cursor_seq")? >= seq {
            return Ok(false);
        }
        match outcome {
            None => {
                sqlx::query("UPDATE webhooks SET cursor_seq = $1 WHERE id = $2")
                    .bind(seq)
                    .bind(id)
                    .execute(&mut *tx)
                    .await?;
            }
            Some(Ok(())) => {
                sqlx::query(
                    "UPDATE webhooks SET cursor_seq = $1, attempts = 0, last_error = NULL, delivered = delivered + 1 \
                     WHERE id = $2",
                )
                .bind(seq)
                .bind(id)
                .execute(&mut *tx)
                .await?;
            }
            Some(Err(error)) => {
                let attempts = row.i("attempts")? + 1;
                if attempts >= row.i("max_attempts")? {
                    sqlx::query(
                        "INSERT INTO webhook_dead_letters (webhook_id, seq, delivery_id, attempts, last_error, created_at) \
                         VALUES ($1, $2, $3, $4, $5, $6) ON CONFLICT DO NOTHING",
                    )
                    .bind(id)
                    .bind(seq)
                    .bind(delivery_id(id, seq))
                    .bind(attempts)
                    .bind(&error)
                    .bind(now_rfc3339())
                    .execute(&mut *tx)
                    .await?;
                    sqlx::query(
                        "UPDATE webhooks SET cursor_seq = $1, attempts = 0, last_error = $2 WHERE id = $3",
                    )
                    .bind(seq)
                    .bind(&error)
                    .bind(id)
                    .execute(&mut *tx)
                    .await?;
                } else {
                    sqlx::query(
                        "UPDATE webhooks SET attempts = $1, last_error = $2, next_attempt_ms = $3 WHERE id = $4",
                    )
                    .bind(attempts)
                    .bind(&error)
                    .bind(now + retry_after_ms)
                    .bind(id)
                    .execute(&mut *tx)
                    .await?;
                }
            }
        }
        tx.commit().await?;
        Ok(true)
    }

    async fn release_webhook(&self, id: &str, owner: &str) -> Result<(), StoreError> {
        sqlx::query(
            "UPDATE webhooks SET lease_owner = NULL, lease_until_ms = 0 WHERE id = $1 AND lease_owner = $2",
        )
        .bind(id)
        .bind(owner)
        .execute(&self.catalog().pool)
        .await?;
        Ok(())
    }
}
