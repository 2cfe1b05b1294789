//! A short version of the label load test (the full one: `cargo bench -p api --bench label_load`).

use crate::common;

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
    if !store::test_support::require_postgres() {
        return;
    }
    let r = run_label_load(Db::Postgres, 16, 32, Duration::from_millis(2500)).await;
    r.print();
    assert!(r.writes > 50, "too few writes: {r:?}");
    assert_eq!(r.errors, 0);
}

/// Many PUTs racing with the same If-Match on one episode (on SQLite they land in one group
/// commit): exactly one wins; every other gets a 409 naming the winner's label, revision and name,
/// and the audit log holds only the winner's write.
async fn racing_puts_one_winner(db: Db) {
    use serde_json::{json, Value};
    let srv = common::TestServer::start(db, false).await;
    let ids = common::ingest(&srv.store, "race", "c1", 4).await;
    let id = &ids[1];
    let before = srv.store.episode(id, None).await.unwrap().label_revision;
    let mut secrets = Vec::new();
    for i in 0..24 {
        secrets.push((
            format!("racer-{i:02}"),
            srv.store.create_token(&format!("racer-{i:02}"), store::Role::Labeler).await.unwrap().0,
        ));
    }
    let mut tasks = Vec::new();
    for (i, (name, secret)) in secrets.into_iter().enumerate() {
        let (http, url) = (srv.http.clone(), srv.url(&format!("/v1/episodes/{id}/label")));
        let label = ["success", "failure", "unknown"][i % 3];
        tasks.push(tokio::spawn(async move {
            let r = http
                .put(url)
                .bearer_auth(secret)
                .header("If-Match", format!("\"{before}\""))
                .json(&json!({"label": label, "note": name}))
                .send()
                .await
                .unwrap();
            let status = r.status().as_u16();
            (name, label, status, r.json::<Value>().await.unwrap())
        }));
    }
    let mut results = Vec::new();
    for t in tasks {
        results.push(t.await.unwrap());
    }
    let winners: Vec<_> = results.iter().filter(|r| r.2 == 200).collect();
    assert_eq!(winners.len(), 1, "{results:?}");
    let (wname, wlabel, _, wbody) = winners[0];
    assert_eq!(wbody["revision"], before + 1);
    for (name, _, status, body) in &results {
        if name == wname {
            continue;
        }
        assert_eq!(*status, 409, "{name}: {body}");
        assert_eq!(body["current_revision"], before + 1, "{body}");
        assert_eq!(body["expected_revision"], before, "{body}");
        assert_eq!(body["current_label"], *wlabel, "{body}");
        assert_eq!(body["set_by"], wname.as_str(), "{body}");
    }
    let h = srv.store.label_history(id).await.unwrap();
    let last = h.last().unwrap();
    assert_eq!(
        (last.revision, last.actor.as_str(), last.note.as_deref()),
        (before + 1, wname.as_str(), Some(wname.as_str()))
    );
    srv.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn racing_puts_have_one_winner_sqlite() {
    racing_puts_one_winner(Db::Sqlite).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn racing_puts_have_one_winner_postgres() {
    if !store::test_support::require_postgres() {
        return;
    }
    racing_puts_one_winner(Db::Postgres).await;
}
