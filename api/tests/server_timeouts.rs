//! What one client can hold: a request
//! whose headers trickle in, an idle keep-alive connection, a body that stops arriving and a
//! download nobody reads are all cut off; a token's requests per second and the checks of
//! unknown tokens per peer address are bounded (429 with Retry-After), without touching others.
//!
//! The limits are set to a second here so that the tests are short; each assertion waits far
//! longer than the limit (a connection still open after 15 s is held forever on a server without
//! the limit).

use crate::common;
use common::*;
use reqwest::Method;
use std::time::Duration;
use store::{Label, MediaColumn, MediaFile};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

fn short_limits(cfg: &mut api::ServeConfig) {
    cfg.header_read_timeout = Duration::from_secs(1);
    cfg.body_idle_timeout = Duration::from_secs(1);
    cfg.write_stall_timeout = Duration::from_secs(1);
}

/// Reads until the server closes the connection (Ok(bytes read)) or `wait` passes (Err).
async fn read_until_closed(s: &mut TcpStream, wait: Duration) -> Result<Vec<u8>, Vec<u8>> {
    let mut got = Vec::new();
    let mut buf = vec![0u8; 64 * 1024];
    let deadline = tokio::time::Instant::now() + wait;
    loop {
        match tokio::time::timeout_at(deadline, s.read(&mut buf)).await {
            Err(_) => return Err(got),
            Ok(Ok(0)) | Ok(Err(_)) => return Ok(got),
            Ok(Ok(n)) => got.extend_from_slice(&buf[..n]),
        }
    }
}

fn addr(srv: &TestServer) -> String {
    srv.base.trim_start_matches("http://").to_string()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn trickled_headers_and_idle_connections_are_closed() {
    let srv = TestServer::start_with(Db::Sqlite, false, short_limits).await;
    // A slowloris client: half a request, then nothing.
    let mut s = TcpStream::connect(addr(&srv)).await.unwrap();
    s.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n").await.unwrap();
    let got = read_until_closed(&mut s, Duration::from_secs(15)).await;
    assert!(got.is_ok(), "a request whose headers never finish held its connection for 15 s");
    // One byte every 300 ms keeps the socket busy but the headers never finish in time.
    let mut s = TcpStream::connect(addr(&srv)).await.unwrap();
    let mut closed = false;
    for b in
        b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-Slow: aaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaa"
            .iter()
    {
        if s.write_all(&[*b]).await.is_err() {
            closed = true;
            break;
        }
        tokio::time::sleep(Duration::from_millis(300)).await;
    }
    assert!(
        closed || read_until_closed(&mut s, Duration::from_millis(100)).await.is_ok(),
        "trickled headers were accepted for 20 s"
    );
    // A finished request, then an idle keep-alive connection: answered, then closed.
    let mut s = TcpStream::connect(addr(&srv)).await.unwrap();
    s.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n").await.unwrap();
    let got = read_until_closed(&mut s, Duration::from_secs(15))
        .await
        .expect("an idle keep-alive connection stayed open 15 s");
    assert!(String::from_utf8_lossy(&got).starts_with("HTTP/1.1 200"), "{}", String::from_utf8_lossy(&got));
    srv.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_body_that_stops_arriving_fails() {
    let srv = TestServer::start_with(Db::Sqlite, false, short_limits).await;
    let ids = common::ingest(&srv.store, "a", "c1", 1).await;
    let mut s = TcpStream::connect(addr(&srv)).await.unwrap();
    let head = format!(
        "PUT /v1/episodes/{}/label HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {}\r\nContent-Type: application/json\r\nContent-Length: 400\r\n\r\n{{\"label\":",
        ids[0], srv.tokens["labeler"]
    );
    s.write_all(head.as_bytes()).await.unwrap();
    let got = read_until_closed(&mut s, Duration::from_secs(15))
        .await
        .expect("a stalled body held its request for 15 s");
    let text = String::from_utf8_lossy(&got);
    assert!(text.is_empty() || text.starts_with("HTTP/1.1 4"), "{text}");
    // The label did not change, and the server goes on serving.
    let ep = srv.get_json(&format!("/v1/episodes/{}", ids[0]), "viewer").await;
    assert_eq!(ep["episode"]["label_revision"].as_i64(), Some(1), "{ep}");
    assert_eq!(ep["history"].as_array().map(Vec::len), Some(1), "{ep}");
    srv.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_download_nobody_reads_is_cut_off() {
    let srv = TestServer::start_with(Db::Sqlite, false, short_limits).await;
    // 32 MiB of video: more than the socket buffers on both sides can hold.
    let video: Vec<u8> = (0..32u32 << 20).map(|i| (i.wrapping_mul(2654435761) >> 13) as u8).collect();
    let vpath = srv.dir.path().join("big.mp4");
    std::fs::write(&vpath, &video).unwrap();
    let sha = store::sha256_hex(&video);
    let mut w = srv.store.begin_ingest(common::source("big"), "pol", "c1").await.unwrap();
    w.add_media(&MediaFile {
        sha256: sha.clone(),
        local_path: vpath,
        content_type: "video/mp4".into(),
        size_bytes: video.len() as u64,
    })
    .await
    .unwrap();
    let mut ep = common::episode(0, 6, Label::Success);
    ep.media = vec![MediaColumn { name: "front".into(), sha256: sha, timestamps: ep.timestamps.clone() }];
    let id = w.add_episode(ep).await.unwrap();
    w.commit("big video").await.unwrap();

    let mut s = TcpStream::connect(addr(&srv)).await.unwrap();
    let req = format!(
        "GET /v1/episodes/{id}/media/front HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {}\r\n\r\n",
        srv.tokens["viewer"]
    );
    s.write_all(req.as_bytes()).await.unwrap();
    // Read nothing for long enough that the server's writes stall past the limit, then drain.
    tokio::time::sleep(Duration::from_secs(5)).await;
    let got = read_until_closed(&mut s, Duration::from_secs(30))
        .await
        .expect("the server never closed the stalled download");
    assert!(
        got.len() < video.len(),
        "the whole body arrived ({} bytes): the stalled write was not cut off",
        got.len()
    );
    // The server goes on serving that file to a client that reads.
    let r = srv.req(Method::GET, &format!("/v1/episodes/{id}/media/front"), "viewer").send().await.unwrap();
    assert_eq!(r.status(), 200);
    assert_eq!(r.bytes().await.unwrap().len(), video.len());
    srv.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_tokens_request_rate_is_bounded_without_touching_other_tokens() {
    let srv = TestServer::start_with(Db::Sqlite, false, |c| c.rate_limit_per_token = 5).await;
    let mut statuses = Vec::new();
    for _ in 0..40 {
        let r = srv.req(Method::GET, "/v1/policies", "viewer").send().await.unwrap();
        if r.status() == 429 {
            assert_eq!(r.headers().get("retry-after").and_then(|v| v.to_str().ok()), Some("1"));
            let p: serde_json::Value = r.json().await.unwrap();
            assert!(p["detail"].as_str().unwrap().contains("per second"), "{p}");
            statuses.push(429);
        } else {
            statuses.push(r.status().as_u16());
        }
    }
    let limited = statuses.iter().filter(|s| **s == 429).count();
    // A burst of 10 (twice the rate) passes; at most a few more refill while the loop runs.
    assert!(limited >= 20, "{limited} of 40 requests refused: {statuses:?}");
    assert!(statuses[..10].iter().all(|s| *s == 200), "{statuses:?}");
    // Another token is not affected.
    let r = srv.req(Method::GET, "/v1/policies", "labeler").send().await.unwrap();
    assert_eq!(r.status(), 200);
    srv.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn guessing_tokens_is_bounded_per_address_but_known_tokens_go_on() {
    let srv = TestServer::start_with(Db::Sqlite, false, |c| {
        c.unverified_checks_per_peer = 2;
        // Every request re-checks its token: known tokens must not be caught by the guess limit.
        c.token_cache_ttl = Duration::ZERO;
    })
    .await;
    // The viewer's token is seen valid once.
    assert_eq!(srv.req(Method::GET, "/v1/policies", "viewer").send().await.unwrap().status(), 200);
    let mut statuses = Vec::new();
    for n in 0..60 {
        let r = srv
            .http
            .get(srv.url("/v1/policies"))
            .bearer_auth(format!("ufops_{n:032x}"))
            .send()
            .await
            .unwrap();
        statuses.push(r.status().as_u16());
    }
    assert!(statuses.iter().all(|s| *s == 401 || *s == 429), "{statuses:?}");
    let limited = statuses.iter().filter(|s| **s == 429).count();
    assert!(limited >= 30, "{limited} of 60 guesses refused: {statuses:?}");
    // Not behind a trusted proxy: a claimed client address changes nothing.
    let r = srv
        .http
        .get(srv.url("/v1/policies"))
        .bearer_auth("ufops_guess")
        .header("X-Forwarded-For", "198.51.100.9")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 429);
    // Sign-in attempts count against the same budget.
    let r = srv
        .http
        .post(srv.url("/ui/session"))
        .header("Origin", &srv.base)
        .header("x-ufops-ui", "1")
        .json(&serde_json::json!({"token": "ufops_guess"}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 429);
    // The known token goes on working from the same address.
    for _ in 0..5 {
        assert_eq!(srv.req(Method::GET, "/v1/policies", "viewer").send().await.unwrap().status(), 200);
    }
    srv.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn behind_a_trusted_proxy_each_client_has_its_own_guess_budget() {
    let srv = TestServer::start_with(Db::Sqlite, false, |c| {
        c.unverified_checks_per_peer = 2;
        c.trusted_proxies = vec!["127.0.0.1".parse().unwrap()];
    })
    .await;
    let guess = |client: Option<&'static str>, n: usize| {
        let mut r = srv.http.get(srv.url("/v1/policies")).bearer_auth(format!("ufops_{n:032x}"));
        if let Some(c) = client {
            // A forged entry on the left, the proxy's view of the client on the right.
            r = r.header("X-Forwarded-For", format!("192.0.2.1, {c}"));
        }
        r.send()
    };
    let mut statuses = Vec::new();
    for n in 0..40 {
        statuses.push(guess(Some("198.51.100.1"), n).await.unwrap().status().as_u16());
    }
    assert!(statuses.iter().filter(|s| **s == 429).count() >= 20, "{statuses:?}");
    // Another client behind the same proxy, and the proxy itself, still get answers.
    assert_eq!(guess(Some("198.51.100.2"), 100).await.unwrap().status(), 401);
    assert_eq!(guess(None, 101).await.unwrap().status(), 401);
    srv.stop().await;
}
