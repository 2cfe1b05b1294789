//! Running automations: each server runs [`automation_loop`], which takes the lease of the
//! automations the feed has gone past (`store::Store::claim_automations`) and advances each
//! through the events after its cursor (`store::Store::advance_automation`: what a rule decides,
//! and the transaction that queues its jobs and moves its cursor, are the store's). The jobs run
//! on the job queue like any other, under the workers' leases and fencing.

use std::time::Duration;
use store::Store;

/// How long a server holds an automation per claim.
const LEASE: Duration = Duration::from_secs(30);
/// Pages of events one automation may take per claim before the others get their turn.
const PAGES_PER_CLAIM: usize = 20;
/// After a commit wakes the loop, how long it waits for more before claiming.
const COALESCE: Duration = Duration::from_millis(50);

/// Advances the automations until `stop` says so; wakes on this server's commits and at least
/// every `poll` (for other servers' commits).
pub(crate) async fn automation_loop(
    store: Store,
    owner: String,
    poll: Duration,
    mut stop: tokio::sync::watch::Receiver<bool>,
) {
    let mut commits = store.feed_watch();
    // Whether any automation existed when last looked: without one, commits do not wake the loop.
    let mut any = store.has_automations().await.unwrap_or(true);
    let mut looked = std::time::Instant::now();
    while !*stop.borrow() {
        commits.mark_unchanged();
        if any {
            match store.claim_automations(&owner, LEASE.as_millis() as i64).await {
                Ok(held) => {
                    for mut a in held {
                        for _ in 0..PAGES_PER_CLAIM {
                            match store.advance_automation(&a, &owner).await {
                                Ok(Some(cursor)) if cursor > a.cursor_seq => a.cursor_seq = cursor,
                                Ok(_) => break,
                                Err(e) => {
                                    tracing::warn!("automation {}: {e}", a.id);
                                    break;
                                }
                            }
                        }
                        let _ = store.release_automation(&a.id, &owner).await;
                    }
                }
                Err(e) => tracing::warn!("cannot claim automations: {e}"),
            }
        }
        let by_commit = tokio::select! {
            r = commits.changed(), if any => r.is_ok(),
            _ = tokio::time::sleep(poll) => false,
            _ = stop.changed() => false,
        };
        if by_commit {
            // Commits come in bursts: one claim for those of the next moment too.
            tokio::time::sleep(COALESCE).await;
        }
        // Under a steady stream of commits the poll never times out: look again by the clock.
        if looked.elapsed() >= poll {
            any = store.has_automations().await.unwrap_or(true);
            looked = std::time::Instant::now();
        }
    }
}
