//! One job, one runner: heartbeats and the outcome are fenced by the attempt, so a stale runner
//! of a worker that re-claimed its own job cannot extend or finish the new attempt; a cancelled
//! job whose worker died is finished as cancelled, not left running forever.

use std::time::Duration;
use store::{Store, StoreConfig};
use store_jobs::{JobKind, JobQueue, JobState};

async fn open() -> (tempfile::TempDir, Store) {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open(&StoreConfig {
        data_dir: dir.path().to_path_buf(),
        database_url: None,
        object_store_url: None,
    })
    .await
    .unwrap();
    (dir, store)
}

#[tokio::test]
async fn a_stale_attempt_cannot_heartbeat_or_finish_the_new_one() {
    let (_d, store) = open().await;
    let j = store.create_job(JobKind::Train, &serde_json::json!({}), "alice").await.unwrap();
    let first = store.claim_job("w1", 20).await.unwrap().unwrap();
    assert_eq!(first.attempts, 1);
    tokio::time::sleep(Duration::from_millis(40)).await;
    // The same worker (same name) claims it again after its lease ran out: attempt 2.
    let second = store.claim_job("w1", 60_000).await.unwrap().unwrap();
    assert_eq!((second.id.as_str(), second.attempts), (j.id.as_str(), 2));
    // The first attempt's runner is still going: it is fenced off.
    assert!(!store.heartbeat_job(&j.id, "w1", 1, 60_000, &serde_json::json!({"stale": true})).await.unwrap());
    assert!(!store.finish_job(&j.id, "w1", 1, Err("stale runner failed".into())).await.unwrap());
    let now = store.job(&j.id).await.unwrap();
    assert_eq!((now.state, now.error.as_deref()), (JobState::Running, None));
    // The current attempt carries on and finishes.
    assert!(store.heartbeat_job(&j.id, "w1", 2, 60_000, &serde_json::json!({"epoch": 1})).await.unwrap());
    assert!(store.finish_job(&j.id, "w1", 2, Ok(serde_json::json!({"ok": true}))).await.unwrap());
    assert_eq!(store.job(&j.id).await.unwrap().state, JobState::Succeeded);
}

#[tokio::test]
async fn a_cancelled_job_whose_worker_died_is_cancelled_not_left_running() {
    let (_d, store) = open().await;
    // Cancel requested while running; the worker dies before its next heartbeat.
    let a = store.create_job(JobKind::Train, &serde_json::json!({}), "alice").await.unwrap();
    // A lease long enough for the two reads below on a loaded machine (20 ms was not).
    store.claim_job("dead-worker", 1_000).await.unwrap().unwrap();
    assert!(store.cancel_job(&a.id).await.unwrap().cancel_requested);
    assert_eq!(store.job(&a.id).await.unwrap().state, JobState::Running, "the lease still runs");
    tokio::time::sleep(Duration::from_millis(1_100)).await;
    // The next worker looking for work finishes it; there is nothing else to claim.
    assert!(store.claim_job("w2", 60_000).await.unwrap().is_none());
    let a = store.job(&a.id).await.unwrap();
    assert_eq!(a.state, JobState::Cancelled);
    assert!(a.error.unwrap().contains("worker stopped"));
    // Cancelling a job whose worker is already gone finishes it at once.
    let b = store.create_job(JobKind::Train, &serde_json::json!({}), "alice").await.unwrap();
    store.claim_job("dead-worker", 20).await.unwrap().unwrap();
    tokio::time::sleep(Duration::from_millis(40)).await;
    assert_eq!(store.cancel_job(&b.id).await.unwrap().state, JobState::Cancelled);
    // A cancel of a live job is still only a request (its worker winds it down).
    let c = store.create_job(JobKind::Train, &serde_json::json!({}), "alice").await.unwrap();
    store.claim_job("w3", 60_000).await.unwrap().unwrap();
    let c = store.cancel_job(&c.id).await.unwrap();
    assert_eq!((c.state, c.cancel_requested), (JobState::Running, true));
}

#[tokio::test]
async fn a_released_job_is_queued_again_without_losing_an_attempt() {
    let (_d, store) = open().await;
    let j = store.create_job(JobKind::Train, &serde_json::json!({}), "alice").await.unwrap();
    store.claim_job("w1", 60_000).await.unwrap().unwrap();
    assert!(!store.release_job(&j.id, "w2", 1).await.unwrap(), "only the holder releases");
    assert!(store.release_job(&j.id, "w1", 1).await.unwrap());
    let r = store.job(&j.id).await.unwrap();
    assert_eq!((r.state, r.attempts, r.worker), (JobState::Queued, 0, None));
    let again = store.claim_job("w2", 60_000).await.unwrap().unwrap();
    assert_eq!(again.attempts, 1);
    // With a cancel pending, a release ends it.
    store.cancel_job(&j.id).await.unwrap();
    assert!(store.release_job(&j.id, "w2", 1).await.unwrap());
    assert_eq!(store.job(&j.id).await.unwrap().state, JobState::Cancelled);
}

#[tokio::test]
async fn a_job_is_claimed_once_its_lease_expires_and_it_cancels() {
    let (_d, store) = open().await;
    let j =
        store.create_job(JobKind::Train, &serde_json::json!({"split": "split-1"}), "alice").await.unwrap();
    let claimed = store.claim_job("w1", 60_000).await.unwrap().unwrap();
    assert_eq!((claimed.id.as_str(), claimed.state, claimed.attempts), (j.id.as_str(), JobState::Running, 1));
    assert!(store.claim_job("w2", 60_000).await.unwrap().is_none());
    assert!(store.heartbeat_job(&j.id, "w1", 1, 1, &serde_json::json!({"epoch": 1})).await.unwrap());
    tokio::time::sleep(Duration::from_millis(20)).await;
    let again = store.claim_job("w2", 60_000).await.unwrap().unwrap();
    assert_eq!((again.id.as_str(), again.attempts), (j.id.as_str(), 2));
    assert!(!store.heartbeat_job(&j.id, "w1", 1, 60_000, &serde_json::json!({})).await.unwrap());
    assert!(store.finish_job(&j.id, "w2", 2, Ok(serde_json::json!({"artifact": "a-1"}))).await.unwrap());
    assert_eq!(store.job(&j.id).await.unwrap().state, JobState::Succeeded);
    let j2 = store.create_job(JobKind::Train, &serde_json::json!({}), "alice").await.unwrap();
    assert_eq!(store.cancel_job(&j2.id).await.unwrap().state, JobState::Cancelled);
}
