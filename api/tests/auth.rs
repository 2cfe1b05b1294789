//! Authorization matrix: every route × {no token, wrong token, each role} → 401 / 403 / allowed.
//! "Allowed" means any status other than 401 and 403 (a 404 for a made-up id is fine).

use crate::common;

use common::{Db, TestServer};
use reqwest::Method;
use serde_json::json;

#[derive(Clone, Copy, PartialEq, PartialOrd, Debug)]
enum Need {
    Viewer = 0,
    Labeler = 1,
    Trainer = 2,
    Admin = 3,
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn authorization_matrix() {
    let srv = TestServer::start(Db::Sqlite, false).await;
    let ids = common::ingest(&srv.store, "a", "c1", 4).await;
    let ep = ids[0].clone();
    let body = |v: serde_json::Value| Some(v.to_string());
    // (method, path, JSON body, needed role)
    let routes: Vec<(Method, String, Option<String>, Need)> = vec![
        (Method::GET, "/metrics".into(), None, Need::Viewer),
        (Method::GET, "/openapi.json".into(), None, Need::Viewer),
        (Method::GET, "/v1/policies".into(), None, Need::Viewer),
        (Method::GET, "/v1/checkpoints".into(), None, Need::Viewer),
        (Method::GET, "/v1/tasks".into(), None, Need::Viewer),
        (Method::GET, "/v1/versions".into(), None, Need::Viewer),
        (Method::GET, "/v1/versions/1".into(), None, Need::Viewer),
        (Method::GET, "/v1/versions/1/diff/1".into(), None, Need::Viewer),
        (Method::GET, "/v1/episodes".into(), None, Need::Viewer),
        (Method::GET, "/v1/episodes/counts".into(), None, Need::Viewer),
        (Method::GET, format!("/v1/episodes/{ep}"), None, Need::Viewer),
        (Method::GET, format!("/v1/episodes/{ep}/steps"), None, Need::Viewer),
        (Method::GET, format!("/v1/episodes/{ep}/media/front"), None, Need::Viewer),
        (Method::GET, format!("/v1/episodes/{ep}/frames/front/0"), None, Need::Viewer),
        (Method::PUT, format!("/v1/episodes/{ep}/label"), body(json!({"label": "success"})), Need::Labeler),
        (Method::POST, "/v1/labels/bulk".into(), body(json!({"updates": []})), Need::Labeler),
        (Method::POST, "/v1/label-snapshots".into(), body(json!({})), Need::Labeler),
        (Method::GET, "/v1/campaigns/pol".into(), None, Need::Viewer),
        (Method::PUT, "/v1/campaigns/pol".into(), body(json!({"labels_needed": 1})), Need::Admin),
        (Method::GET, "/v1/tasks/reach/failure-causes".into(), None, Need::Viewer),
        (
            Method::PUT,
            "/v1/tasks/reach/failure-causes".into(),
            body(json!({"causes": ["collision"]})),
            Need::Admin,
        ),
        (Method::GET, format!("/v1/episodes/{ep}/votes"), None, Need::Viewer),
        (Method::POST, format!("/v1/episodes/{ep}/votes"), body(json!({"label": "failure"})), Need::Labeler),
        (
            Method::POST,
            format!("/v1/episodes/{ep}/adjudication"),
            body(json!({"label": "failure"})),
            Need::Admin,
        ),
        (Method::GET, "/v1/adjudication".into(), None, Need::Admin),
        (Method::GET, "/v1/agreement?policy=pol".into(), None, Need::Viewer),
        (Method::GET, format!("/v1/episodes/{ep}/scores"), None, Need::Viewer),
        (Method::GET, "/v1/review/artifacts/pol".into(), None, Need::Viewer),
        (
            Method::PUT,
            "/v1/review/artifacts/pol".into(),
            body(json!({"artifact": "0123456789abcdef"})),
            Need::Trainer,
        ),
        (Method::DELETE, "/v1/review/artifacts/pol".into(), None, Need::Trainer),
        (
            Method::POST,
            "/v1/review/score".into(),
            body(json!({"policy": "pol", "checkpoint": "c1"})),
            Need::Trainer,
        ),
        (Method::GET, "/v1/layers".into(), None, Need::Viewer),
        (
            Method::GET,
            format!("/v1/layers/features.x/episodes?producer_hash={}", "a".repeat(64)),
            None,
            Need::Viewer,
        ),
        (Method::GET, format!("/v1/episodes/{ep}/layers"), None, Need::Viewer),
        (Method::POST, "/v1/layers/features.x".into(), Some("not arrow".into()), Need::Trainer),
        (Method::GET, "/v1/splits".into(), None, Need::Viewer),
        (
            Method::POST,
            "/v1/splits".into(),
            body(json!({"policy": "pol", "checkpoint": "c1"})),
            Need::Trainer,
        ),
        (Method::GET, "/v1/splits/split-nope".into(), None, Need::Viewer),
        (Method::GET, "/v1/jobs".into(), None, Need::Viewer),
        (
            Method::POST,
            "/v1/jobs".into(),
            body(json!({"split_id": "split-nope", "kind": "classifier"})),
            Need::Trainer,
        ),
        (Method::GET, "/v1/jobs/job-nope".into(), None, Need::Viewer),
        (Method::POST, "/v1/jobs/job-nope/cancel".into(), None, Need::Trainer),
        (Method::GET, "/v1/scoreboard?policy=pol".into(), None, Need::Viewer),
        (Method::GET, "/v1/runs".into(), None, Need::Viewer),
        (Method::GET, "/v1/compare?policy=pol&a=c1&b=c2".into(), None, Need::Viewer),
        (Method::GET, "/v1/policies/pol/aliases".into(), None, Need::Viewer),
        (Method::PUT, "/v1/policies/pol/aliases/prod".into(), body(json!({"to": "c1"})), Need::Trainer),
        (Method::GET, "/v1/policies/pol/aliases/prod/history".into(), None, Need::Viewer),
        (Method::GET, "/v1/artifacts".into(), None, Need::Viewer),
        (Method::GET, "/v1/artifacts/0123456789abcdef".into(), None, Need::Viewer),
        (Method::GET, "/v1/artifacts/0123456789abcdef/files/config.json".into(), None, Need::Viewer),
        (Method::PUT, "/v1/artifacts/0123456789abcdef/aliases/prod".into(), None, Need::Trainer),
        (Method::GET, "/v1/monitors".into(), None, Need::Viewer),
        (Method::GET, "/v1/monitors/0123456789abcdef".into(), None, Need::Viewer),
        (Method::GET, "/v1/policies/pol/checkpoints/c1/monitors/latest".into(), None, Need::Viewer),
        (
            Method::GET,
            "/v1/policies/pol/checkpoints/c1/verifiers/classifier@latest".into(),
            None,
            Need::Viewer,
        ),
        (
            Method::GET,
            "/v1/policies/pol/checkpoints/c1/verifiers/classifier@latest/files/config.json".into(),
            None,
            Need::Viewer,
        ),
        (
            Method::POST,
            "/v1/ingest?policy=pol&checkpoint=up".into(),
            Some("{\"episodes\": []}".into()),
            Need::Admin,
        ),
        (Method::POST, "/v1/gc".into(), body(json!({"dry_run": true})), Need::Admin),
        (Method::GET, "/v1/exports".into(), None, Need::Viewer),
        (
            Method::POST,
            "/v1/exports".into(),
            body(json!({"format": "lerobot", "policy": "nobody"})),
            Need::Trainer,
        ),
        (Method::GET, "/v1/exports/job-nope".into(), None, Need::Viewer),
        (Method::GET, "/v1/exports/job-nope/files/meta/info.json".into(), None, Need::Viewer),
        (Method::DELETE, "/v1/exports/job-nope".into(), None, Need::Trainer),
        (Method::GET, "/v1/tokens".into(), None, Need::Admin),
        (
            Method::POST,
            "/v1/tokens".into(),
            body(json!({"name": "new-token", "role": "viewer"})),
            Need::Admin,
        ),
        (Method::DELETE, "/v1/tokens/tok_nope".into(), None, Need::Admin),
        (Method::GET, "/v1/events?after=0".into(), None, Need::Viewer),
        (Method::GET, "/v1/webhooks".into(), None, Need::Admin),
        (Method::POST, "/v1/webhooks".into(), body(json!({"url": "http://127.0.0.1:9/hook"})), Need::Admin),
        (Method::GET, "/v1/webhooks/wh_nope".into(), None, Need::Admin),
        (Method::GET, "/v1/webhooks/wh_nope/dead-letters".into(), None, Need::Admin),
        (Method::DELETE, "/v1/webhooks/wh_nope".into(), None, Need::Admin),
        (Method::GET, "/v1/automations".into(), None, Need::Viewer),
        (
            Method::POST,
            "/v1/automations".into(),
            body(json!({"policy": "pol", "rule": "score_on_publish"})),
            Need::Trainer,
        ),
        (Method::GET, "/v1/automations/auto_nope".into(), None, Need::Viewer),
        (Method::DELETE, "/v1/automations/auto_nope".into(), None, Need::Trainer),
    ];
    // Every route of the OpenAPI document is in the matrix (and vice versa).
    let doc = api::openapi();
    let mut documented: Vec<String> = Vec::new();
    for (path, item) in doc.paths.paths.iter() {
        let v = serde_json::to_value(item).unwrap();
        for m in ["get", "put", "post", "delete"] {
            if v.get(m).is_some() && path != "/healthz" {
                documented.push(format!("{} {path}", m.to_uppercase()));
            }
        }
    }
    documented.sort();
    let mut tested: Vec<String> = routes
        .iter()
        .map(|(m, p, _, _)| {
            let p = p.split('?').next().unwrap();
            format!("{m} {}", templatize(p))
        })
        .collect();
    tested.sort();
    tested.dedup();
    assert_eq!(tested, documented, "the matrix covers exactly the documented routes");

    let roles = [
        ("viewer", Need::Viewer),
        ("labeler", Need::Labeler),
        ("trainer", Need::Trainer),
        ("admin", Need::Admin),
    ];
    let mut failures = Vec::new();
    for (method, path, body, need) in &routes {
        let build = |token: Option<&str>| {
            let mut b = srv.http.request(method.clone(), srv.url(path));
            if let Some(t) = token {
                b = b.bearer_auth(t);
            }
            if path.ends_with("/label") {
                b = b.header("If-Match", "1");
            }
            if let Some(body) = body {
                b = b.header("content-type", "application/json").body(body.clone());
            }
            b
        };
        let r = build(None).send().await.unwrap();
        if r.status() != 401 {
            failures.push(format!("{method} {path} without a token: {}", r.status()));
        } else {
            assert_eq!(r.headers()["content-type"], "application/problem+json");
            assert!(r.headers().contains_key("www-authenticate"));
        }
        let r = build(Some("ufops_not_a_real_token")).send().await.unwrap();
        if r.status() != 401 {
            failures.push(format!("{method} {path} with a wrong token: {}", r.status()));
        }
        for (role, level) in roles {
            let r = build(Some(&srv.tokens[role])).send().await.unwrap();
            let s = r.status().as_u16();
            let ok = if level >= *need { s != 401 && s != 403 } else { s == 403 };
            if !ok {
                failures
                    .push(format!("{method} {path} as {role}: {s} {}", r.text().await.unwrap_or_default()));
            }
        }
    }
    // /healthz is open.
    assert_eq!(reqwest::get(srv.url("/healthz")).await.unwrap().status(), 200);
    // A revoked token stops working at once on this server.
    let (secret, rec) = srv.store.create_token("short-lived", store::Role::Viewer).await.unwrap();
    let r = srv.http.get(srv.url("/v1/policies")).bearer_auth(&secret).send().await.unwrap();
    assert_eq!(r.status(), 200);
    let r = srv.req(Method::DELETE, &format!("/v1/tokens/{}", rec.id), "admin").send().await.unwrap();
    assert_eq!(r.status(), 204);
    let r = srv.http.get(srv.url("/v1/policies")).bearer_auth(&secret).send().await.unwrap();
    assert_eq!(r.status(), 401);
    assert!(failures.is_empty(), "authorization matrix failures:\n{}", failures.join("\n"));
    srv.stop().await;
}

/// Turns a concrete path back into its route template.
fn templatize(p: &str) -> String {
    let segs: Vec<&str> = p.split('/').collect();
    let mut out = Vec::new();
    for (i, s) in segs.iter().enumerate() {
        let prev = if i > 0 { segs[i - 1] } else { "" };
        let t = match prev {
            // /v1/review/artifacts/{policy}: a policy after "artifacts", not an artifact id.
            "artifacts" if i >= 2 && segs[i - 2] == "review" => "{policy}",
            "episodes" if *s != "counts" => "{id}",
            "versions" => "{version}",
            "diff" => "{to}",
            "splits" | "jobs" | "artifacts" | "tokens" | "exports" | "webhooks" | "automations"
                if !s.is_empty() =>
            {
                "{id}"
            }
            // /v1/monitors/{id}, and a checkpoint's /monitors/{alias}
            "monitors" if segs[i - 2] == "v1" => "{id}",
            "monitors" => "{alias}",
            "media" => "{key}",
            "frames" => "{camera}",
            _ if i >= 2 && segs[i - 2] == "frames" => "{t}",
            "layers" if !s.is_empty() => "{name}",
            "files" => "{name}",
            "aliases" => "{alias}",
            "policies" | "campaigns" if !s.is_empty() => "{policy}",
            "tasks" if !s.is_empty() => "{task}",
            "checkpoints" if !s.is_empty() => "{checkpoint}",
            "verifiers" => "{kind_at_alias}",
            _ => s,
        };
        out.push(t.to_string());
    }
    let mut s = out.join("/");
    s = s.replace("/v1/versions/{version}/diff/{to}", "/v1/versions/{from}/diff/{to}");
    if let Some(at) = s.find("/files/").filter(|_| s.starts_with("/v1/exports/")) {
        s = format!("{}/files/{{path}}", &s[..at]); // a path of any depth
    }
    s
}
