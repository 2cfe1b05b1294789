//! Webhook delivery: each server runs [`Deliveries`] in the feed consumers' loop, which takes the lease of the
//! subscriptions that are due (`store::Store::claim_webhooks`) and posts each one's next events,
//! in feed order, one at a time.
//!
//! A delivery is `POST <url>` with the event as its JSON body and the headers
//! * `Ufops-Delivery`: the delivery id, `<webhook id>-<event seq>`, the same on every attempt
//!   (a receiver that has seen it drops the repeat: delivery is at least once);
//! * `Ufops-Event`: the event's kind;
//! * `Ufops-Signature: t=<unix seconds>,v1=<hex HMAC-SHA256 of "<t>." + body>` keyed by the
//!   subscription's secret (a receiver also refuses an old `t`, against replays).
//!
//! A 2xx answer moves the subscription past the event; anything else (or no answer within
//! [`DELIVERY_TIMEOUT`]) is a failed attempt, retried after a back-off that doubles from
//! `ServeConfig::webhook_backoff` (at most an hour), until `max_attempts`, when the event goes to
//! the subscription's dead letters and delivery goes on with the next. An event is never
//! delivered before the one before it was delivered or given up on.

use hmac::{Hmac, Mac};
use std::time::Duration;
use store::Store;
use store_feed::{HeldWebhook, Webhooks};

/// How long a receiver may take to answer.
pub const DELIVERY_TIMEOUT: Duration = Duration::from_secs(10);
/// Events delivered per subscription per lease.
const BATCH: i64 = 100;

/// The `Ufops-Signature` header of `body` sent at `unix_seconds`.
pub fn signature(secret: &str, unix_seconds: i64, body: &[u8]) -> String {
    let mut mac =
        Hmac::<sha2::Sha256>::new_from_slice(secret.as_bytes()).expect("HMAC takes a key of any length");
    mac.update(format!("{unix_seconds}.").as_bytes());
    mac.update(body);
    format!("t={unix_seconds},v1={}", hex::encode(mac.finalize().into_bytes()))
}

/// The subscriptions this server delivers, as [`crate::feed_consumers::run`] drives them.
pub(crate) struct Deliveries {
    agent: ureq::Agent,
    /// Whose lease it takes.
    owner: String,
    backoff: Duration,
}

impl Deliveries {
    pub(crate) fn new(owner: String, backoff: Duration) -> Self {
        let agent: ureq::Agent = ureq::Agent::config_builder()
            .timeout_global(Some(DELIVERY_TIMEOUT))
            .http_status_as_error(false)
            .build()
            .into();
        Deliveries { agent, owner, backoff }
    }
}

impl crate::feed_consumers::FeedConsumers for Deliveries {
    async fn any(&self, store: &Store) -> bool {
        store.has_webhooks().await.unwrap_or(true)
    }

    async fn work(&mut self, store: &Store) {
        let lease_ms = (DELIVERY_TIMEOUT.as_millis() as i64) * 3;
        let held = match store.claim_webhooks(&self.owner, lease_ms).await {
            Ok(held) => held,
            Err(e) => return tracing::warn!("cannot claim webhooks: {e}"),
        };
        for hook in held {
            if let Err(e) = deliver_some(store, &self.agent, &self.owner, &hook, self.backoff).await {
                tracing::warn!("webhook {}: {e}", hook.record.id);
            }
            let _ = store.release_webhook(&hook.record.id, &self.owner).await;
        }
    }
}

/// Delivers the events after the subscription's cursor, in order, until one fails or the batch
/// ends.
async fn deliver_some(
    store: &Store,
    agent: &ureq::Agent,
    owner: &str,
    hook: &HeldWebhook,
    backoff: Duration,
) -> Result<(), store::StoreError> {
    let w = &hook.record;
    let page = match store.events_after(w.cursor_seq, BATCH, &w.filter()).await {
        // Retention deleted events it had not delivered (a receiver down for longer than the
        // retention): they are gone, so delivery goes on from the oldest left.
        Err(store::StoreError::Gone(_)) => {
            let (_, pruned_through) = store.event_head().await?;
            tracing::warn!("webhook {}: events up to {pruned_through} are gone; delivering from there", w.id);
            store.record_webhook_attempt(&w.id, owner, pruned_through, None, 0).await?;
            return Ok(());
        }
        r => r?,
    };
    if page.events.is_empty() {
        if page.next > w.cursor_seq {
            store.record_webhook_attempt(&w.id, owner, page.next, None, 0).await?;
        }
        return Ok(());
    }
    let mut attempts = w.attempts;
    for event in page.events {
        let body = serde_json::to_vec(&event)?;
        let delivery = store_feed::delivery_id(&w.id, event.seq);
        let sig = signature(&hook.secret, chrono::Utc::now().timestamp(), &body);
        let (agent, url, kind) = (agent.clone(), w.url.clone(), event.kind.as_str());
        let outcome = tokio::task::spawn_blocking(move || -> Result<(), String> {
            let resp = agent
                .post(&url)
                .header("Content-Type", "application/json")
                .header("Ufops-Delivery", &delivery)
                .header("Ufops-Event", kind)
                .header("Ufops-Signature", &sig)
                .send(&body[..])
                .map_err(|e| e.to_string())?;
            let status = resp.status().as_u16();
            if (200..300).contains(&status) {
                Ok(())
            } else {
                Err(format!("the receiver answered {status}"))
            }
        })
        .await
        .unwrap_or_else(|e| Err(format!("delivery task failed: {e}")));
        let failed = outcome.is_err();
        // Doubling back-off from the configured base, at most an hour.
        let wait = backoff.as_millis() as i64 * (1i64 << attempts.clamp(0, 20));
        if !store.record_webhook_attempt(&w.id, owner, event.seq, Some(outcome), wait.min(3_600_000)).await? {
            return Ok(()); // lease lost: another server delivers it now
        }
        if failed {
            attempts += 1;
            if attempts < w.max_attempts {
                return Ok(()); // retried after the back-off, before anything later
            }
            attempts = 0;
        } else {
            attempts = 0;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    #[test]
    fn signature_is_hmac_sha256_of_timestamp_and_body() {
        // Computed independently: printf '1700000000.{"a":1}' | openssl dgst -sha256 -hmac whsec_test
        assert_eq!(
            super::signature("whsec_test", 1_700_000_000, br#"{"a":1}"#),
            "t=1700000000,v1=38877139021993b830af32feea6e18a8da83eb2f6e49ee50bd9e4cf4ca4d3789"
        );
    }
}
