//! `GET /v1/scoreboard` and `GET /v1/runs` over HTTP on SQLite and Postgres: the JSON equals the
//! store's scoreboard, the CSV carries the same rows, hostile queries are 4xx naming the problem.

use crate::common;
use store_compare::{Compare, CompareRequest, ScoreboardRequest, Scoreboards};

use common::*;
use reqwest::Method;
use store::*;

async fn ingest_run(store: &Store, tag: &str, ckpt: &str, run: RunInput, n: u32, every: u32) {
    let mut w = store.begin_ingest(source(tag), "pol", ckpt).await.unwrap();
    w.set_run(run).unwrap();
    for i in 0..n {
        let label = if i % every == 0 { Label::Failure } else { Label::Success };
        w.add_episode(episode(i, 3, label)).await.unwrap();
    }
    w.commit("scoreboard test").await.unwrap();
}

async fn scoreboard_over_http(db: Db) {
    let srv = TestServer::start(db, false).await;
    ingest_run(&srv.store, "base", "c1", RunInput::new("base", Steering::Base), 40, 2).await;
    let mut bon = RunInput::new("c-bon10", Steering::Bon { n: 10 });
    bon.tags = vec!["on-policy".into(), "a,b \"quoted\"".into()];
    ingest_run(&srv.store, "bon", "c1", bon, 40, 8).await;
    ingest_run(&srv.store, "flow", "c1", RunInput::new("flow-g", Steering::Flow { lambda: 0.5 }), 20, 3)
        .await;

    let want = srv
        .store
        .scoreboard(&ScoreboardRequest { policy: "pol".into(), ..Default::default() })
        .await
        .unwrap();
    let got = srv.get_json("/v1/scoreboard?policy=pol", "viewer").await;
    assert_eq!(got, serde_json::to_value(&want).unwrap());
    assert_eq!(got["rows"].as_array().unwrap().len(), 3);
    let bon_row = got["rows"].as_array().unwrap().iter().find(|r| r["run_name"] == "c-bon10").unwrap();
    assert_eq!(bon_row["baseline"]["separates"], true, "{bon_row}");
    assert_eq!(bon_row["run"]["steering"], serde_json::json!({"method": "bon", "n": 10}));

    let r = srv
        .req(Method::GET, "/v1/scoreboard?policy=pol&format=csv&baseline=c-bon10", "viewer")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    assert!(r.headers()["content-type"].to_str().unwrap().starts_with("text/csv"));
    assert!(r.headers()["content-disposition"].to_str().unwrap().contains("scoreboard-v"));
    let csv = r.text().await.unwrap();
    assert_eq!(csv.lines().count(), 4, "{csv}");
    // Tags are stored sorted; one with a comma and quotes is quoted as CSV quotes it.
    assert!(csv.contains(r#""a,b ""quoted"";on-policy""#), "{csv}");

    let runs = srv.get_json("/v1/runs", "viewer").await;
    assert_eq!(runs.as_array().unwrap().len(), 3);
    let runs = srv.get_json("/v1/runs?name=flow-g", "viewer").await;
    assert_eq!(runs[0]["steering"], serde_json::json!({"method": "flow", "lambda": 0.5}));

    for (path, status, says) in [
        ("/v1/scoreboard", 400, "policy"),
        ("/v1/scoreboard?policy=pol&format=xml", 400, "xml"),
        ("/v1/scoreboard?policy=pol&version=99", 404, "99"),
        ("/v1/scoreboard?policy=pol&version=abc", 400, ""),
        ("/v1/scoreboard?policy=%20bad", 400, "policy"),
        ("/v1/scoreboard?policy=pol&baseline=a%2Fb", 400, "baseline"),
    ] {
        let r = srv.req(Method::GET, path, "viewer").send().await.unwrap();
        assert_eq!(r.status().as_u16(), status, "{path}");
        let body = r.text().await.unwrap();
        assert!(body.contains(says), "{path}: {body}");
    }
    // The anytime-valid comparison: the store's, as JSON; bad arms and settings are 4xx.
    let want = srv
        .store
        .compare(&CompareRequest::new("pol", "c1/base".parse().unwrap(), "c1/c-bon10".parse().unwrap()))
        .await
        .unwrap();
    let got = srv.get_json("/v1/compare?policy=pol&a=c1/base&b=c1/c-bon10", "viewer").await;
    assert_eq!(got, serde_json::to_value(&want).unwrap());
    assert_eq!(got["pooled"]["pairs"], 40);
    for (path, status, says) in [
        ("/v1/compare?policy=pol&a=c1/base", 400, "b"),
        ("/v1/compare?policy=pol&a=c1/base&b=c1/base", 400, "both"),
        ("/v1/compare?policy=pol&a=c1/base&b=c1/nope", 404, "c1/nope"),
        ("/v1/compare?policy=pol&a=c1/base&b=c1/c-bon10&alpha=2", 400, "alpha"),
        ("/v1/compare?policy=pol&a=c1/base&b=c1/c-bon10&margin=-1", 400, "margin"),
        ("/v1/compare?policy=pol&a=%20c1&b=c1/c-bon10", 400, "a"),
    ] {
        let r = srv.req(Method::GET, path, "viewer").send().await.unwrap();
        assert_eq!(r.status().as_u16(), status, "{path}");
        let body = r.text().await.unwrap();
        assert!(body.contains(says), "{path}: {body}");
    }
    // A protected policy alias: set, refused (409) without a decided comparison, the refusal
    // changes nothing; a viewer may not move it.
    let put = |body: serde_json::Value, role: &'static str| {
        srv.req(Method::PUT, "/v1/policies/pol/aliases/prod", role).json(&body).send()
    };
    let r = put(serde_json::json!({"to": "c1/base", "protect": true}), "trainer").await.unwrap();
    assert_eq!(r.status(), 200);
    let set: serde_json::Value = r.json().await.unwrap();
    assert_eq!((&set["target"], &set["protected"]), (&"c1/base".into(), &true.into()), "{set}");
    let r = put(serde_json::json!({"to": "c1/flow-g"}), "trainer").await.unwrap();
    assert_eq!(r.status(), 409);
    assert!(r.text().await.unwrap().contains("undecided"));
    assert_eq!(put(serde_json::json!({"to": "c1/c-bon10"}), "viewer").await.unwrap().status(), 403);
    assert_eq!(put(serde_json::json!({"to": "c1/nope"}), "trainer").await.unwrap().status(), 404);
    assert_eq!(put(serde_json::json!({"to": "c1/base", "extra": 1}), "trainer").await.unwrap().status(), 422);
    assert_eq!(srv.get_json("/v1/policies/pol/aliases", "viewer").await, serde_json::json!([set]));
    let history = srv.get_json("/v1/policies/pol/aliases/prod/history", "viewer").await;
    assert_eq!(history.as_array().unwrap().len(), 1);
    // An ingest upload naming a bad steering or a missing artifact is refused before anything is stored.
    for (q, says) in [
        ("run=r&steering=bon:0", "bon:0"),
        ("run_tags=ok,%20padded", "run tag"),
        ("run=r&run_artifact=art-nope", "art-nope"),
    ] {
        let r = srv
            .req(Method::POST, &format!("/v1/ingest?policy=pol&checkpoint=up&{q}"), "admin")
            .body("{}")
            .send()
            .await
            .unwrap();
        let st = r.status().as_u16();
        let body = r.text().await.unwrap();
        assert!(st == 400 || st == 404, "{q}: {st} {body}");
        assert!(body.contains(says), "{q}: {body}");
    }
    // A run given by its steering (and tags) alone is named after its steering.
    let r = srv
        .req(
            Method::POST,
            "/v1/ingest?policy=pol&checkpoint=up&steering=bon:10&run_tags=nightly,,gpu",
            "admin",
        )
        .body("{}")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 202);
    let job: serde_json::Value = r.json().await.unwrap();
    assert_eq!(
        (&job["spec"]["run"], &job["spec"]["steering"]),
        (&serde_json::json!("bon:10"), &serde_json::json!("bon:10")),
        "{job}"
    );
    assert_eq!(job["spec"]["run_tags"], serde_json::json!(["nightly", "gpu"]));
    srv.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn scoreboard_over_http_sqlite() {
    scoreboard_over_http(Db::Sqlite).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn scoreboard_over_http_postgres() {
    if !store::test_support::require_postgres() {
        return;
    }
    scoreboard_over_http(Db::Postgres).await;
}
