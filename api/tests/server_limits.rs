//! The server survives its clients: metrics labels come from a fixed set whatever methods a
//! client invents, and server-side failures are logged in full but answered without paths,
//! bucket names or SQL (an incident id instead).

use crate::common;
use common::*;
use reqwest::Method;

fn files_with_ext(dir: &std::path::Path, ext: &str, out: &mut Vec<std::path::PathBuf>) {
    for e in std::fs::read_dir(dir).unwrap().flatten() {
        let p = e.path();
        if p.is_dir() {
            files_with_ext(&p, ext, out);
        } else if p.extension().is_some_and(|x| x == ext) {
            out.push(p);
        }
    }
}

#[tokio::test]
async fn invented_methods_do_not_grow_the_metrics() {
    let srv = TestServer::start(Db::Sqlite, false).await;
    for i in 0..40 {
        let m = Method::from_bytes(format!("BREW{i}").as_bytes()).unwrap();
        let r = srv.req(m, "/v1/policies", "viewer").send().await.unwrap();
        assert!(r.status().is_client_error(), "{}", r.status());
    }
    let text = srv.req(Method::GET, "/metrics", "viewer").send().await.unwrap().text().await.unwrap();
    assert!(!text.contains("BREW"), "a client-chosen method became a label:\n{text}");
    let series = text.lines().filter(|l| l.starts_with("ufops_http_requests_total{")).count();
    assert!(series <= 4, "{series} series:\n{text}");
    assert!(text.contains("method=\"other\""), "{text}");
    srv.stop().await;
}

#[tokio::test]
async fn internal_errors_are_answered_without_paths() {
    let srv = TestServer::start(Db::Sqlite, false).await;
    let ids = common::ingest(&srv.store, "a", "c1", 4).await;
    // Break the stored steps file behind the server's back (a disk error, a bad copy).
    let mut parquet = Vec::new();
    files_with_ext(srv.dir.path(), "parquet", &mut parquet);
    let steps: Vec<_> = parquet.iter().filter(|p| !p.to_string_lossy().contains("label")).collect();
    assert!(!steps.is_empty(), "{parquet:?}");
    for p in &steps {
        let n = std::fs::metadata(p).unwrap().len() as usize;
        std::fs::write(p, vec![7u8; n]).unwrap();
    }
    let r = srv.req(Method::GET, &format!("/v1/episodes/{}/steps", ids[0]), "viewer").send().await.unwrap();
    let status = r.status().as_u16();
    let body = r.text().await.unwrap();
    assert_eq!(status, 500, "{body}");
    let dir = srv.dir.path().to_string_lossy().into_owned();
    for leak in [dir.as_str(), ".parquet", "objects", "data/", "SELECT", "sqlite"] {
        assert!(!body.contains(leak), "the answer names {leak:?}: {body}");
    }
    let problem: serde_json::Value = serde_json::from_str(&body).unwrap();
    assert!(problem["incident"].as_str().is_some_and(|s| s.len() == 12), "{body}");
    // A missing object is a 404 that does not name it either.
    for p in &steps {
        std::fs::remove_file(p).unwrap();
    }
    let r = srv.req(Method::GET, &format!("/v1/episodes/{}/steps", ids[1]), "viewer").send().await.unwrap();
    let status = r.status().as_u16();
    let body = r.text().await.unwrap();
    assert!(status == 404 || status == 500, "{status} {body}");
    assert!(!body.contains(dir.as_str()) && !body.contains(".parquet"), "{body}");
    srv.stop().await;
}

/// A token's requests in flight are bounded: two stalled uploads of a label (headers sent, body
/// never finished) hold that token's two slots, so its next request gets 429 with Retry-After
/// while other tokens are served; when the stalled connections go, the token works again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stalled_client_cannot_take_more_than_its_tokens_share() {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let srv = TestServer::start_with(Db::Sqlite, false, |c| c.max_in_flight_per_token = 2).await;
    let ids = common::ingest(&srv.store, "a", "c1", 2).await;
    let addr = srv.base.trim_start_matches("http://").to_string();
    let token = srv.tokens["labeler"].clone();
    let stall = || {
        let (addr, token, id) = (addr.clone(), token.clone(), ids[0].clone());
        async move {
            let mut s = tokio::net::TcpStream::connect(&addr).await.unwrap();
            let head = format!(
                "PUT /v1/episodes/{id}/label HTTP/1.1\r\nHost: {addr}\r\nAuthorization: Bearer {token}\r\nIf-Match: \"1\"\r\n\
                 Content-Type: application/json\r\nContent-Length: 100\r\n\r\n{{\"label\":"
            );
            s.write_all(head.as_bytes()).await.unwrap();
            s
        }
    };
    let mut stalled = vec![stall().await, stall().await];
    tokio::time::sleep(std::time::Duration::from_millis(300)).await;
    let t0 = std::time::Instant::now();
    let r = loop {
        let r = srv.req(Method::GET, "/v1/policies", "labeler").send().await.unwrap();
        if r.status() == 429 {
            break r;
        }
        assert!(
            t0.elapsed() < std::time::Duration::from_secs(10),
            "the stalled requests never held the token's slots"
        );
        // A stall that arrived while a probe held a slot was itself refused: stall again.
        for s in stalled.iter_mut() {
            let mut buf = [0u8; 64];
            if let Ok(Ok(_)) =
                tokio::time::timeout(std::time::Duration::from_millis(50), s.read(&mut buf)).await
            {
                *s = stall().await;
            }
        }
        tokio::time::sleep(std::time::Duration::from_millis(200)).await;
    };
    assert_eq!(r.status(), 429);
    assert_eq!(r.headers()["retry-after"], "1");
    assert!(r.text().await.unwrap().contains("requests in flight"));
    let r = srv.req(Method::GET, "/v1/policies", "viewer").send().await.unwrap();
    assert_eq!(r.status(), 200, "another token is served");
    drop(stalled);
    let t0 = std::time::Instant::now();
    loop {
        let r = srv.req(Method::GET, "/v1/policies", "labeler").send().await.unwrap();
        if r.status() == 200 {
            break;
        }
        assert!(
            t0.elapsed() < std::time::Duration::from_secs(5),
            "the token's slots were not given back: {}",
            r.status()
        );
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    srv.stop().await;
}
