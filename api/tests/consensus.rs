//! Several labelers over real HTTP, on SQLite and Postgres: campaign settings and
//! failure causes (admin only), votes with causes and spans, blind mode, agreement moving the
//! label through the ordinary label events, a dispute settled by an admin, κ and α against an
//! independent computation, hostile input answered with 4xx.

use crate::common;

use common::{Db, TestServer};
use reqwest::Method;
use serde_json::{json, Value};
use store::Role;

async fn send(srv: &TestServer, method: Method, path: &str, role: &str, body: Value) -> (u16, Value) {
    let r = srv.req(method, path, role).json(&body).send().await.unwrap();
    let status = r.status().as_u16();
    let text = r.text().await.unwrap();
    (status, serde_json::from_str(&text).unwrap_or(Value::String(text)))
}

/// Cohen's κ written out for two labelers and two categories, apart from evalstats.
fn kappa_2x2(a: &[&str], b: &[&str]) -> f64 {
    let n = a.len() as f64;
    let po = a.iter().zip(b).filter(|(x, y)| x == y).count() as f64 / n;
    let share = |v: &[&str], c: &str| v.iter().filter(|x| **x == c).count() as f64 / n;
    let pe = share(a, "success") * share(b, "success") + share(a, "failure") * share(b, "failure");
    (po - pe) / (1.0 - pe)
}

async fn labelers_agree_or_get_adjudicated(db: Db) {
    let mut srv = TestServer::start(db, false).await;
    let (second, _) = srv.store.create_token("labeler2-user", Role::Labeler).await.unwrap();
    srv.tokens.insert("labeler2", second);
    let ids = common::ingest(&srv.store, "consensus", "c1", 6).await;

    // Defaults: one labeler, not blind; a vote is a label write (with If-Match semantics).
    let c = srv.get_json("/v1/campaigns/pol", "viewer").await;
    assert_eq!((c["labels_needed"].as_i64(), c["blind"].as_bool()), (Some(1), Some(false)));
    let (st, out) = send(
        &srv,
        Method::POST,
        &format!("/v1/episodes/{}/votes", ids[0]),
        "labeler",
        json!({"label": "failure", "expect_revision": 1}),
    )
    .await;
    assert_eq!(st, 200, "{out}");
    assert_eq!(
        (out["state"].as_str(), out["label"].as_str(), out["revision"].as_i64()),
        (Some("agreed"), Some("failure"), Some(2)),
        "{out}"
    );
    assert_eq!(out["change"]["old_label"], "success");
    let (st, out) = send(
        &srv,
        Method::POST,
        &format!("/v1/episodes/{}/votes", ids[1]),
        "labeler",
        json!({"label": "success", "expect_revision": 1}),
    )
    .await;
    assert_eq!(
        (st, out["label"].as_str(), out["revision"].as_i64()),
        (200, Some("success"), Some(2)),
        "{out}"
    );
    let (st, out) = send(
        &srv,
        Method::POST,
        &format!("/v1/episodes/{}/votes", ids[1]),
        "labeler",
        json!({"label": "failure", "expect_revision": 1}),
    )
    .await;
    assert_eq!((st, out["current_revision"].as_i64()), (409, Some(2)), "a stale revision: {out}");

    // Failure causes: admin only, at most 9, a duplicate counts once; a cause must be in the taxonomy.
    let causes = json!({"causes": ["missed grasp", "collision", "timeout"]});
    let (st, _) = send(&srv, Method::PUT, "/v1/tasks/reach/failure-causes", "labeler", causes.clone()).await;
    assert_eq!(st, 403);
    let (st, out) = send(
        &srv,
        Method::PUT,
        "/v1/tasks/reach/failure-causes",
        "admin",
        json!({"causes": ["a", "b", "a"]}),
    )
    .await;
    assert_eq!((st, &out), (200, &json!({"causes": ["a", "b"]})));
    let ten: Vec<String> = (0..10).map(|i| format!("c{i}")).collect();
    let (st, _) =
        send(&srv, Method::PUT, "/v1/tasks/reach/failure-causes", "admin", json!({"causes": ten})).await;
    assert_eq!(st, 400);
    let (st, out) = send(&srv, Method::PUT, "/v1/tasks/reach/failure-causes", "admin", causes.clone()).await;
    assert_eq!((st, &out), (200, &causes));
    assert_eq!(srv.get_json("/v1/tasks/reach/failure-causes", "viewer").await, causes);
    assert_eq!(srv.get_json("/v1/tasks/other/failure-causes", "viewer").await, json!({"causes": []}));

    // Campaign: two labelers, blind (admin only; 1-10).
    let (st, _) =
        send(&srv, Method::PUT, "/v1/campaigns/pol", "labeler", json!({"labels_needed": 2, "blind": true}))
            .await;
    assert_eq!(st, 403);
    let (st, _) = send(&srv, Method::PUT, "/v1/campaigns/pol", "admin", json!({"labels_needed": 0})).await;
    assert_eq!(st, 400);
    let (st, c) =
        send(&srv, Method::PUT, "/v1/campaigns/pol", "admin", json!({"labels_needed": 2, "blind": true}))
            .await;
    assert_eq!(
        (st, c["labels_needed"].as_i64(), c["blind"].as_bool(), c["updated_by"].as_str()),
        (200, Some(2), Some(true), Some("admin-user"))
    );

    // A labeler can no longer set a label directly (that would bypass the votes); an admin can.
    let r = srv
        .req(Method::PUT, &format!("/v1/episodes/{}/label", ids[5]), "labeler")
        .header("If-Match", "\"1\"")
        .json(&json!({"label": "success"}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 409);
    assert_eq!(r.json::<Value>().await.unwrap()["type"], "urn:ufops:problem:votes-required");
    let (st, _) = send(
        &srv,
        Method::POST,
        "/v1/labels/bulk",
        "labeler",
        json!({"updates": [{"episode_id": ids[5], "label": "success"}]}),
    )
    .await;
    assert_eq!(st, 409);

    // Hostile votes: 4xx with a message, nothing recorded.
    let ep2 = format!("/v1/episodes/{}/votes", ids[2]);
    for body in [
        json!({"label": "maybe"}),
        json!({"label": "failure", "failure_cause": "gremlins"}),
        json!({"label": "failure", "spans": [{"start_step": -1, "end_step": 1}]}),
        json!({"label": "failure", "spans": [{"start_step": 0, "end_step": 1000}]}),
        json!({"label": "failure", "extra": 1}),
    ] {
        let (st, out) = send(&srv, Method::POST, &ep2, "labeler", body.clone()).await;
        assert!((400..500).contains(&st), "{body}: {st} {out}");
    }
    let (st, _) = send(
        &srv,
        Method::POST,
        "/v1/episodes/no-such-episode/votes",
        "labeler",
        json!({"label": "failure"}),
    )
    .await;
    assert_eq!(st, 404);
    let (st, _) = send(&srv, Method::POST, &ep2, "viewer", json!({"label": "failure"})).await;
    assert_eq!(st, 403);
    assert_eq!(srv.get_json(&ep2, "admin").await["voters"], 0);

    // Two labelers on episodes 2-5; they disagree on episode 4.
    let a = ["success", "failure", "success", "failure"];
    let b = ["success", "failure", "failure", "failure"];
    for (k, id) in ids[2..6].iter().enumerate() {
        let mut body = json!({"label": a[k]});
        if a[k] == "failure" {
            body["failure_cause"] = json!("collision");
            // Marked end first: the same stretch, stored in order.
            body["spans"] = json!([{"start_step": 3, "end_step": 1}]);
        } else {
            // A cause on a success verdict is ignored.
            body["failure_cause"] = json!("collision");
        }
        let (st, out) = send(&srv, Method::POST, &format!("/v1/episodes/{id}/votes"), "labeler", body).await;
        assert_eq!(
            (st, out["state"].as_str(), out["voters"].as_i64()),
            (200, Some("pending"), Some(1)),
            "{out}"
        );
        assert!(out["change"].is_null());
        // Blind: the second labeler sees that someone voted, not what.
        let v = srv.get_json(&format!("/v1/episodes/{id}/votes"), "labeler2").await;
        assert_eq!(
            (v["hidden"].as_bool(), v["voters"].as_i64(), v["votes"].as_array().unwrap().len()),
            (Some(true), Some(1), 0),
            "{v}"
        );
        let v = srv.get_json(&format!("/v1/episodes/{id}/votes"), "labeler").await;
        assert_eq!((v["hidden"].as_bool(), v["votes"][0]["label"].as_str()), (Some(false), Some(a[k])));
    }
    for (k, id) in ids[2..6].iter().enumerate() {
        let mut body = json!({"label": b[k]});
        if b[k] == "failure" {
            body["failure_cause"] = json!("collision");
        }
        let (st, out) = send(&srv, Method::POST, &format!("/v1/episodes/{id}/votes"), "labeler2", body).await;
        assert_eq!(st, 200, "{out}");
        let expect = if a[k] == b[k] { "agreed" } else { "disputed" };
        assert_eq!(out["state"].as_str(), Some(expect), "{out}");
        let v = srv.get_json(&format!("/v1/episodes/{id}/votes"), "labeler2").await;
        assert_eq!(v["votes"].as_array().unwrap().len(), 2, "after voting the others' votes show: {v}");
    }
    // The agreed verdict is the label, through an ordinary label event with the votes as data.
    let ep = srv.get_json(&format!("/v1/episodes/{}", ids[3]), "viewer").await;
    assert_eq!(ep["episode"]["label"], "failure");
    let last = ep["history"].as_array().unwrap().last().unwrap().clone();
    assert_eq!((last["source"].as_str(), last["actor"].as_str()), (Some("consensus"), Some("labeler2-user")));
    assert_eq!(last["data"]["failure_cause"], "collision");
    assert_eq!(last["data"]["spans"], json!([{"start_step": 1, "end_step": 3, "actor": "labeler-user"}]));
    assert_eq!(last["data"]["votes"].as_array().unwrap().len(), 2);
    // The disputed episode kept its label and waits for an admin.
    let (st, _) = send(&srv, Method::GET, "/v1/adjudication?policy=pol", "labeler", Value::Null).await;
    assert_eq!(st, 403);
    let q = srv.get_json("/v1/adjudication?policy=pol", "admin").await;
    let q = q.as_array().unwrap();
    assert_eq!(q.len(), 1, "{q:?}");
    assert_eq!(q[0]["episode_id"].as_str(), Some(ids[4].as_str()));
    assert_eq!(q[0]["votes"].as_array().unwrap().len(), 2);

    // Agreement: per-labeler counts, κ and α against an independent computation.
    let ag = srv.get_json("/v1/agreement?policy=pol", "viewer").await;
    // labeler-user also voted alone on episodes 0 and 1 under the one-labeler settings.
    assert_eq!(
        (ag["agreed"].as_u64(), ag["disputed"].as_u64(), ag["pending"].as_u64()),
        (Some(3), Some(1), Some(2)),
        "{ag}"
    );
    let counts: Vec<(String, u64)> = ag["labelers"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| (l["actor"].as_str().unwrap().to_string(), l["votes"].as_u64().unwrap()))
        .collect();
    assert_eq!(counts, [("labeler-user".to_string(), 6), ("labeler2-user".to_string(), 4)]);
    let pair = &ag["pairs"][0];
    assert_eq!(
        (pair["a"].as_str(), pair["b"].as_str(), pair["episodes"].as_u64()),
        (Some("labeler-user"), Some("labeler2-user"), Some(4))
    );
    let kappa = kappa_2x2(&a, &b);
    assert!((pair["kappa"].as_f64().unwrap() - kappa).abs() < 1e-12, "{pair} vs {kappa}");
    assert!((kappa - 0.5).abs() < 1e-12);
    // α (nominal), 8 pairable values (3 success, 5 failure), one disagreeing unit:
    // 1 − (n − 1)·2 / (n² − Σ n_c²) = 1 − 7·2 / (64 − 9 − 25).
    let alpha = 1.0 - 7.0 * 2.0 / 30.0;
    assert!((ag["krippendorff_alpha"].as_f64().unwrap() - alpha).abs() < 1e-12, "{ag}");

    // An admin settles the dispute; it leaves the queue and the label is the adjudicated one.
    let (st, _) = send(
        &srv,
        Method::POST,
        &format!("/v1/episodes/{}/adjudication", ids[4]),
        "labeler",
        json!({"label": "failure"}),
    )
    .await;
    assert_eq!(st, 403);
    let (st, ch) = send(
        &srv,
        Method::POST,
        &format!("/v1/episodes/{}/adjudication", ids[4]),
        "admin",
        json!({"label": "failure", "failure_cause": "timeout", "note": "slipped at the end"}),
    )
    .await;
    assert_eq!(
        (st, ch["label"].as_str(), ch["actor"].as_str()),
        (200, Some("failure"), Some("admin-user")),
        "{ch}"
    );
    assert!(srv.get_json("/v1/adjudication?policy=pol", "admin").await.as_array().unwrap().is_empty());
    let v = srv.get_json(&format!("/v1/episodes/{}/votes", ids[4]), "viewer").await;
    assert_eq!(v["state"], "settled");
    let ep = srv.get_json(&format!("/v1/episodes/{}", ids[4]), "viewer").await;
    let last = ep["history"].as_array().unwrap().last().unwrap().clone();
    assert_eq!(
        (last["source"].as_str(), last["data"]["failure_cause"].as_str()),
        (Some("adjudication"), Some("timeout"))
    );
    let ag = srv.get_json("/v1/agreement?policy=pol", "viewer").await;
    assert_eq!((ag["disputed"].as_u64(), ag["settled"].as_u64()), (Some(0), Some(1)));

    // Label counts follow the consensus writes; a snapshot freezes them as any label.
    let counts = srv.get_json("/v1/episodes/counts?policy=pol", "viewer").await;
    let labels: Vec<String> = srv.get_json("/v1/episodes?policy=pol", "viewer").await["episodes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| e["label"].as_str().unwrap().to_string())
        .collect();
    assert_eq!(
        counts["failure"].as_u64().unwrap() as usize,
        labels.iter().filter(|l| *l == "failure").count(),
        "{counts}"
    );
    let (st, snap) = send(&srv, Method::POST, "/v1/label-snapshots", "labeler", json!({})).await;
    assert_eq!(st, 201, "{snap}");

    // The OpenAPI document lists the new routes with typed bodies.
    let doc = srv.get_json("/openapi.json", "viewer").await;
    for p in [
        "/v1/campaigns/{policy}",
        "/v1/episodes/{id}/votes",
        "/v1/adjudication",
        "/v1/agreement",
        "/v1/tasks/{task}/failure-causes",
    ] {
        assert!(doc["paths"][p].is_object(), "{p}");
    }
    assert!(doc["components"]["schemas"]["Agreement"].is_object());
    srv.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn consensus_sqlite() {
    labelers_agree_or_get_adjudicated(Db::Sqlite).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn consensus_postgres() {
    if !store::test_support::require_postgres() {
        return;
    }
    labelers_agree_or_get_adjudicated(Db::Postgres).await;
}

/// Two labelers voting on the same episodes at the same moment: every episode ends agreed with
/// exactly one consensus event (the vote that completes the agreement sees the other one: the
/// episode row is locked on Postgres, the write is serialized on SQLite).
async fn concurrent_votes_agree_once(db: Db) {
    let mut srv = TestServer::start(db, false).await;
    let (second, _) = srv.store.create_token("labeler2-user", Role::Labeler).await.unwrap();
    srv.tokens.insert("labeler2", second);
    let ids = common::ingest(&srv.store, "concurrent", "c1", 24).await;
    let (st, _) = send(&srv, Method::PUT, "/v1/campaigns/pol", "admin", json!({"labels_needed": 2})).await;
    assert_eq!(st, 200);
    let srv = std::sync::Arc::new(srv);
    let mut tasks = Vec::new();
    for who in ["labeler", "labeler2"] {
        for id in ids.clone() {
            let srv = srv.clone();
            tasks.push(tokio::spawn(async move {
                let (st, out) = send(
                    &srv,
                    Method::POST,
                    &format!("/v1/episodes/{id}/votes"),
                    who,
                    json!({"label": "unknown"}),
                )
                .await;
                assert_eq!(st, 200, "{out}");
            }));
        }
    }
    for t in tasks {
        t.await.unwrap();
    }
    for id in &ids {
        let ep = srv.get_json(&format!("/v1/episodes/{id}"), "viewer").await;
        assert_eq!(ep["episode"]["label"], "unknown", "{ep}");
        let consensus =
            ep["history"].as_array().unwrap().iter().filter(|h| h["source"] == "consensus").count();
        assert_eq!(consensus, 1, "{ep}");
    }
    let ag = srv.get_json("/v1/agreement?policy=pol", "viewer").await;
    assert_eq!((ag["agreed"].as_u64(), ag["pending"].as_u64()), (Some(24), Some(0)), "{ag}");
    // One label throughout: κ is undefined (null), not a number made up.
    assert!(ag["pairs"][0]["kappa"].is_null() && ag["krippendorff_alpha"].is_null(), "{ag}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn concurrent_votes_sqlite() {
    concurrent_votes_agree_once(Db::Sqlite).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn concurrent_votes_postgres() {
    if !store::test_support::require_postgres() {
        return;
    }
    concurrent_votes_agree_once(Db::Postgres).await;
}
