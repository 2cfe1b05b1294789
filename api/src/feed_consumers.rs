//! The loop the servers' consumers of the change feed share (webhook delivery, automations):
//! work when this server commits (after a moment, so one pass takes a burst of commits) and at
//! least every `poll` (other servers' commits, retries due); and when no consumer exists at all,
//! do not wake on commits, looking again for one every `poll` by the clock (under a steady stream
//! of commits a poll timeout never comes).

use std::future::Future;
use std::time::{Duration, Instant};
use store::Store;

/// After a commit wakes the loop, how long it waits for more before working.
const COALESCE: Duration = Duration::from_millis(50);

/// One kind of feed consumer, as [`run`] drives it.
pub(crate) trait FeedConsumers: Send {
    /// Whether any consumer of this kind exists.
    fn any(&self, store: &Store) -> impl Future<Output = bool> + Send;
    /// Claims the consumers that are due and works through what the feed holds for them.
    fn work(&mut self, store: &Store) -> impl Future<Output = ()> + Send;
}

/// Drives `consumers` until `stop` says so.
pub(crate) async fn run(
    store: Store,
    poll: Duration,
    mut stop: tokio::sync::watch::Receiver<bool>,
    mut consumers: impl FeedConsumers,
) {
    let mut commits = store.feed_watch();
    let mut any = consumers.any(&store).await;
    let mut looked = Instant::now();
    while !*stop.borrow() {
        commits.mark_unchanged();
        if any {
            consumers.work(&store).await;
        }
        let by_commit = tokio::select! {
            r = commits.changed(), if any => r.is_ok(),
            _ = tokio::time::sleep(poll) => false,
            _ = stop.changed() => false,
        };
        if by_commit {
            tokio::time::sleep(COALESCE).await;
        }
        if looked.elapsed() >= poll {
            any = consumers.any(&store).await;
            looked = Instant::now();
        }
    }
}
