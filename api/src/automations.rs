//! Running automations: each server runs [`Automations`] in the feed consumers' loop, which takes the lease of the
//! automations the feed has gone past (`store::Store::claim_automations`) and advances each
//! through the events after its cursor (`store_feed::Automations::advance_automation`: what a rule decides,
//! and the transaction that queues its jobs and moves its cursor, are the store's). The jobs run
//! on the job queue like any other, under the workers' leases and fencing.

use std::time::Duration;
use store::Store;
use store_feed::Automations as _;

/// How long a server holds an automation per claim.
const LEASE: Duration = Duration::from_secs(30);
/// Pages of events one automation may take per claim before the others get their turn.
const PAGES_PER_CLAIM: usize = 20;
/// The automations this server advances, as [`crate::feed_consumers::run`] drives them.
pub(crate) struct Automations {
    /// Whose lease it takes.
    pub owner: String,
}

impl crate::feed_consumers::FeedConsumers for Automations {
    async fn any(&self, store: &Store) -> bool {
        store.has_automations().await.unwrap_or(true)
    }

    async fn work(&mut self, store: &Store) {
        let owner = &self.owner;
        let held = match store.claim_automations(owner, LEASE.as_millis() as i64).await {
            Ok(held) => held,
            Err(e) => return tracing::warn!("cannot claim automations: {e}"),
        };
        for mut a in held {
            for _ in 0..PAGES_PER_CLAIM {
                match store.advance_automation(&a, owner).await {
                    Ok(Some(cursor)) if cursor > a.cursor_seq => a.cursor_seq = cursor,
                    Ok(_) => break,
                    Err(e) => {
                        tracing::warn!("automation {}: {e}", a.id);
                        break;
                    }
                }
            }
            let _ = store.release_automation(&a.id, owner).await;
        }
    }
}
