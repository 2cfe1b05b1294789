//! Episode pages and counts over HTTP: `next_cursor` pages cover every matching episode once
//! while labels change between pages, and `GET /v1/episodes/counts` equals a recount of the rows
//! after label writes, now and at a past version.

use crate::common;

use common::{Db, TestServer};
use reqwest::Method;
use serde_json::{json, Value};
use std::collections::BTreeSet;
use store::CountFilter;

async fn counts_equal_recount(srv: &TestServer, query: &str, f: CountFilter) {
    let got = srv.get_json(&format!("/v1/episodes/counts{query}"), "viewer").await;
    let want = srv.store.recount_episodes(&f).await.unwrap();
    assert_eq!(
        (got["total"].as_i64(), got["success"].as_i64(), got["failure"].as_i64(), got["unknown"].as_i64()),
        (Some(want.total), Some(want.success), Some(want.failure), Some(want.unknown)),
        "counts{query}: {got}"
    );
}

async fn pages_and_counts(db: Db) {
    let srv = TestServer::start(db, false).await;
    let mut ids = common::ingest(&srv.store, "lists-a", "c1", 23).await;
    ids.extend(common::ingest(&srv.store, "lists-b", "c2", 17).await);
    counts_equal_recount(&srv, "", CountFilter::default()).await;
    counts_equal_recount(
        &srv,
        "?policy=pol&checkpoint=c2",
        CountFilter { policy: Some("pol".into()), checkpoint: Some("c2".into()), ..Default::default() },
    )
    .await;

    // Walk label=success 4 at a time while a labeler flips episodes between pages.
    let mut seen = BTreeSet::new();
    let mut after: Option<String> = None;
    let mut k = 0;
    loop {
        let path = match &after {
            Some(a) => format!("/v1/episodes?label=success&limit=4&after={a}"),
            None => "/v1/episodes?label=success&limit=4".to_string(),
        };
        let page: Value = srv.get_json(&path, "viewer").await;
        for e in page["episodes"].as_array().unwrap() {
            assert_eq!(e["label"], "success");
            assert!(seen.insert(e["id"].as_str().unwrap().to_string()), "{} twice", e["id"]);
        }
        let updates: Vec<Value> = (0..3)
            .map(|j| {
                let id = &ids[(k * 7 + j * 13) % ids.len()];
                let label = ["success", "failure", "unknown"][(k + j) % 3];
                json!({"episode_id": id, "label": label})
            })
            .collect();
        let r = srv
            .req(Method::POST, "/v1/labels/bulk", "labeler")
            .json(&json!({"updates": updates}))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 200);
        k += 1;
        match page["next_cursor"].as_str() {
            Some(c) => after = Some(c.to_string()),
            None => break,
        }
    }
    assert!(k >= 3, "several pages ({k})");
    counts_equal_recount(&srv, "", CountFilter::default()).await;
    counts_equal_recount(
        &srv,
        "?task=reach",
        CountFilter { task: Some("reach".into()), ..Default::default() },
    )
    .await;

    // A version's counts stay as frozen; an unknown version is a 404.
    let v = srv.store.head_version().await.unwrap();
    let bulk = json!({"updates": ids[..5].iter().map(|id| json!({"episode_id": id, "label": "failure"})).collect::<Vec<_>>()});
    let r = srv.req(Method::POST, "/v1/labels/bulk", "labeler").json(&bulk).send().await.unwrap();
    assert_eq!(r.status(), 200);
    counts_equal_recount(
        &srv,
        &format!("?version={v}"),
        CountFilter { version: Some(v), ..Default::default() },
    )
    .await;
    counts_equal_recount(&srv, "", CountFilter::default()).await;
    let r = srv.req(Method::GET, "/v1/episodes/counts?version=999", "viewer").send().await.unwrap();
    assert_eq!(r.status(), 404);
    let r = srv.req(Method::GET, "/v1/episodes/counts?version=x", "viewer").send().await.unwrap();
    assert_eq!(r.status(), 400);
    srv.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn pages_and_counts_sqlite() {
    pages_and_counts(Db::Sqlite).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn pages_and_counts_postgres() {
    pages_and_counts(Db::Postgres).await;
}
