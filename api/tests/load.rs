//! A short version of the label load test (the full one: `cargo bench -p api --bench label_load`).

mod common;

use common::load::run_label_load;
use common::Db;
use std::time::Duration;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_labelers_lose_no_updates_sqlite() {
    let r = run_label_load(Db::Sqlite, 16, 32, Duration::from_millis(2500)).await;
    r.print();
    assert!(r.writes > 100, "too few writes: {r:?}");
    assert!(r.conflicts > 0, "the episodes overlap, so some writes must conflict");
    assert_eq!(r.errors, 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_labelers_lose_no_updates_postgres() {
    let r = run_label_load(Db::Postgres, 16, 32, Duration::from_millis(2500)).await;
    r.print();
    assert!(r.writes > 50, "too few writes: {r:?}");
    assert_eq!(r.errors, 0);
}
