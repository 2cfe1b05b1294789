//! The labeling page's cookie session over real HTTP: sign-in with a token sets an HttpOnly,
//! SameSite=Strict cookie; a cookie-authenticated write needs `X-Ufops-UI: 1` and, when the
//! browser sends `Origin`, our own origin (CSRF); sign-out and token revocation end the session.

use crate::common;

use common::{Db, TestServer};
use reqwest::{Method, StatusCode};
use serde_json::{json, Value};

const CSRF: &str = "x-ufops-ui";

/// Signs in with `token` (as the page does: JSON body and the CSRF header); returns the cookie
/// pair to send back (`ufops_session=<id>`), the Set-Cookie header, and the body.
async fn sign_in(srv: &TestServer, token: &str) -> (String, String, Value) {
    let r = srv
        .http
        .post(srv.url("/ui/session"))
        .header(CSRF, "1")
        .json(&json!({"token": token}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    let set_cookie =
        r.headers().get(reqwest::header::SET_COOKIE).expect("a Set-Cookie").to_str().unwrap().to_string();
    let pair = set_cookie.split(';').next().unwrap().trim().to_string();
    (pair, set_cookie, r.json().await.unwrap())
}

/// A request authenticated by the cookie only (no Authorization header).
fn with_cookie(srv: &TestServer, method: Method, path: &str, cookie: &str) -> reqwest::RequestBuilder {
    srv.http.request(method, srv.url(path)).header(reqwest::header::COOKIE, cookie)
}

/// `(label, revision)` of an episode, read with a bearer token (not through the session).
async fn label_of(srv: &TestServer, id: &str) -> (String, i64) {
    let e = &srv.get_json(&format!("/v1/episodes/{id}"), "viewer").await["episode"];
    (e["label"].as_str().unwrap().to_string(), e["label_revision"].as_i64().unwrap())
}

/// A cookie-authenticated label write: `csrf` adds `X-Ufops-UI: 1`, `origin` an Origin header.
async fn put_label(
    srv: &TestServer,
    cookie: &str,
    id: &str,
    label: &str,
    csrf: bool,
    origin: Option<&str>,
) -> (StatusCode, String) {
    let (_, rev) = label_of(srv, id).await;
    let mut req = with_cookie(srv, Method::PUT, &format!("/v1/episodes/{id}/label"), cookie)
        .header(reqwest::header::IF_MATCH, rev.to_string())
        .json(&json!({"label": label}));
    if csrf {
        req = req.header(CSRF, "1");
    }
    if let Some(o) = origin {
        req = req.header(reqwest::header::ORIGIN, o);
    }
    let r = req.send().await.unwrap();
    (r.status(), r.text().await.unwrap())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cookie_session_with_csrf_rule_sign_out_and_revocation() {
    let srv = TestServer::start(Db::Sqlite, false).await;
    let ids = common::ingest(&srv.store, "s", "c1", 2).await;
    let ep = &ids[0];
    let own_origin = srv.base.clone();

    // Sign-in itself needs the CSRF header, and a valid token.
    let r = srv
        .http
        .post(srv.url("/ui/session"))
        .json(&json!({"token": srv.tokens["labeler"]}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::FORBIDDEN);
    assert!(r.headers().get(reqwest::header::SET_COOKIE).is_none(), "no cookie without the CSRF header");
    let r = srv
        .http
        .post(srv.url("/ui/session"))
        .header(CSRF, "1")
        .json(&json!({"token": "ufops_not_a_token"}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::UNAUTHORIZED);
    assert!(r.headers().get(reqwest::header::SET_COOKIE).is_none());

    // A token gives an HttpOnly, SameSite=Strict cookie for the whole site, and who signed in.
    let (cookie, set_cookie, who) = sign_in(&srv, &srv.tokens["labeler"]).await;
    let attrs: Vec<String> = set_cookie.split(';').map(|a| a.trim().to_ascii_lowercase()).collect();
    assert!(
        cookie.starts_with("ufops_session=") && cookie.len() > "ufops_session=".len() + 32,
        "{set_cookie}"
    );
    assert!(
        !set_cookie.contains(&srv.tokens["labeler"]),
        "the token never goes into the cookie: {set_cookie}"
    );
    for want in ["httponly", "samesite=strict", "path=/"] {
        assert!(attrs.iter().any(|a| a == want), "{want} missing: {set_cookie}");
    }
    assert_eq!((who["name"].as_str(), who["role"].as_str()), (Some("labeler-user"), Some("labeler")));

    // Reads need nothing but the cookie.
    let r = with_cookie(&srv, Method::GET, "/ui/session", &cookie).send().await.unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    assert_eq!(r.json::<Value>().await.unwrap()["name"], "labeler-user");
    let r = with_cookie(&srv, Method::GET, &format!("/v1/episodes/{ep}"), &cookie).send().await.unwrap();
    assert_eq!(r.status(), StatusCode::OK);

    // Writes: without X-Ufops-UI, 403; with it but from a foreign Origin, 403; nothing changes.
    let before = label_of(&srv, ep).await;
    assert_eq!(before.0, "success");
    let (st, body) = put_label(&srv, &cookie, ep, "failure", false, None).await;
    assert_eq!(st, StatusCode::FORBIDDEN, "{body}");
    assert!(body.contains("x-ufops-ui"), "{body}");
    let (st, body) = put_label(&srv, &cookie, ep, "failure", false, Some(&own_origin)).await;
    assert_eq!(st, StatusCode::FORBIDDEN, "own origin but no header: {body}");
    let (st, body) = put_label(&srv, &cookie, ep, "failure", true, Some("http://evil.example")).await;
    assert_eq!(st, StatusCode::FORBIDDEN, "{body}");
    assert!(body.contains("evil.example"), "{body}");
    let (st, body) = put_label(&srv, &cookie, ep, "failure", true, Some("http://127.0.0.1:1")).await;
    assert_eq!(st, StatusCode::FORBIDDEN, "same host, another port: {body}");
    assert_eq!(label_of(&srv, ep).await, before, "a refused write changed the label");

    // With both right: 200, the label changes and is recorded as the signed-in token's.
    let (st, body) = put_label(&srv, &cookie, ep, "failure", true, Some(&own_origin)).await;
    assert_eq!(st, StatusCode::OK, "{body}");
    assert_eq!(label_of(&srv, ep).await, ("failure".to_string(), before.1 + 1));
    let history = srv.store.label_history(ep).await.unwrap();
    assert_eq!(history.last().unwrap().actor, "labeler-user");
    // No Origin at all (older browsers, same-origin GET-then-PUT): the header alone suffices.
    let (st, body) = put_label(&srv, &cookie, ep, "success", true, None).await;
    assert_eq!(st, StatusCode::OK, "{body}");

    // Sign-out needs the header too, clears the cookie and ends the session on the server.
    let r = with_cookie(&srv, Method::DELETE, "/ui/session", &cookie).send().await.unwrap();
    assert_eq!(r.status(), StatusCode::FORBIDDEN);
    let r = with_cookie(&srv, Method::DELETE, "/ui/session", &cookie).header(CSRF, "1").send().await.unwrap();
    assert_eq!(r.status(), StatusCode::NO_CONTENT);
    let cleared =
        r.headers().get(reqwest::header::SET_COOKIE).unwrap().to_str().unwrap().to_ascii_lowercase();
    assert!(cleared.starts_with("ufops_session=;") && cleared.contains("max-age=0"), "{cleared}");
    let r = with_cookie(&srv, Method::GET, "/ui/session", &cookie).send().await.unwrap();
    assert_eq!(r.status(), StatusCode::UNAUTHORIZED, "the old cookie still works after sign-out");
    let (st, _) = put_label(&srv, &cookie, ep, "failure", true, Some(&own_origin)).await;
    assert_eq!(st, StatusCode::UNAUTHORIZED);

    // Revoking the token behind a live session ends that session at once.
    let (secret, _) = srv.store.create_token("short-lived", store::Role::Labeler).await.unwrap();
    let (cookie2, _, who2) = sign_in(&srv, &secret).await;
    let (st, body) = put_label(&srv, &cookie2, ep, "failure", true, Some(&own_origin)).await;
    assert_eq!(st, StatusCode::OK, "{body}");
    let token_id = who2["token_id"].as_str().unwrap();
    let r = srv.req(Method::DELETE, &format!("/v1/tokens/{token_id}"), "admin").send().await.unwrap();
    assert_eq!(r.status(), StatusCode::NO_CONTENT);
    let r = with_cookie(&srv, Method::GET, "/ui/session", &cookie2).send().await.unwrap();
    assert_eq!(r.status(), StatusCode::UNAUTHORIZED, "a revoked token's session still reads");
    let (st, body) = put_label(&srv, &cookie2, ep, "success", true, Some(&own_origin)).await;
    assert_eq!(st, StatusCode::UNAUTHORIZED, "a revoked token's session still writes: {body}");
    assert_eq!(label_of(&srv, ep).await.0, "failure");
    srv.stop().await;
}
