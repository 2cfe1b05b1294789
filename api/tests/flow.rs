//! The full flow over real HTTP, on SQLite and Postgres: ingest (directly and by upload) → list →
//! label (409 on a stale revision, 428 without If-Match) → snapshot → split → training job →
//! artifact download by alias with a matching sha256; plus steps (JSON and Arrow), media ranges,
//! metrics and the OpenAPI document.

use crate::common;

use common::{Db, TestServer};
use reqwest::Method;
use serde_json::{json, Value};
use store::sha256_hex;

async fn full_flow(db: Db) {
    let srv = TestServer::start(db, true).await;
    let (video_ids, video) = common::ingest_with_video(&srv.store, srv.dir.path(), "vid", "c1", 3).await;
    let plain_ids = common::ingest(&srv.store, "plain", "c1", 4).await;

    // Upload a rollout file: streamed to disk, then an ingest job run by the worker.
    let upload = serde_json::to_vec(&json!({"episodes": [
        {"label": "success", "steps": 5}, {"label": "failure", "steps": 7}, {"label": "unknown", "steps": 4}]}))
    .unwrap();
    let r = srv
        .req(Method::POST, "/v1/ingest?policy=pol&checkpoint=c2&filename=../../etc/rollouts.json", "admin")
        .body(upload.clone())
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 202);
    let job: Value = r.json().await.unwrap();
    assert_eq!(job["kind"], "ingest");
    let path = job["spec"]["path"].as_str().unwrap();
    assert!(path.starts_with(srv.dir.path().join("uploads").to_str().unwrap()), "{path}");
    assert!(path.ends_with("/rollouts.json"), "client path parts are dropped: {path}");
    assert_eq!(job["spec"]["sha256"], sha256_hex(&upload));
    let done = srv.wait_job(job["id"].as_str().unwrap()).await;
    assert_eq!(done["state"], "succeeded", "{done}");
    assert_eq!(done["result"]["episodes"], 3);
    // The labeler cannot upload.
    let r = srv
        .req(Method::POST, "/v1/ingest?policy=pol&checkpoint=c3", "labeler")
        .body("x")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 403);

    // Catalog lists.
    assert_eq!(srv.get_json("/v1/policies", "viewer").await, json!(["pol"]));
    assert_eq!(srv.get_json("/v1/checkpoints?policy=pol", "viewer").await.as_array().unwrap().len(), 2);
    assert_eq!(srv.get_json("/v1/tasks", "viewer").await, json!(["reach"]));

    // Episodes: filters and cursor pagination.
    let all = srv.get_json("/v1/episodes?checkpoint=c1", "viewer").await;
    assert_eq!(all["episodes"].as_array().unwrap().len(), 7);
    assert!(all["next_cursor"].is_null());
    let p1 = srv.get_json("/v1/episodes?checkpoint=c1&limit=4", "viewer").await;
    assert_eq!(p1["episodes"].as_array().unwrap().len(), 4);
    let cursor = p1["next_cursor"].as_str().unwrap();
    let p2 = srv.get_json(&format!("/v1/episodes?checkpoint=c1&limit=4&after={cursor}"), "viewer").await;
    assert_eq!(p2["episodes"].as_array().unwrap().len(), 3);
    assert!(p2["next_cursor"].is_null());
    let mut seen: Vec<String> = p1["episodes"]
        .as_array()
        .unwrap()
        .iter()
        .chain(p2["episodes"].as_array().unwrap())
        .map(|e| e["id"].as_str().unwrap().to_string())
        .collect();
    seen.dedup();
    assert_eq!(seen.len(), 7);
    let succ = srv.get_json("/v1/episodes?label=success&checkpoint=c2", "viewer").await;
    assert_eq!(succ["episodes"].as_array().unwrap().len(), 1);
    assert_eq!(
        srv.get_json("/v1/episodes?tag=eval&label_source=test&task=reach&policy=pol", "viewer").await
            ["episodes"]
            .as_array()
            .unwrap()
            .len(),
        10
    );
    let r = srv.req(Method::GET, "/v1/episodes?label=maybe", "viewer").send().await.unwrap();
    assert_eq!(r.status(), 400);
    assert_eq!(r.headers()["content-type"], "application/problem+json");
    let r = srv.req(Method::GET, "/v1/episodes?sort=-length", "viewer").send().await.unwrap();
    assert_eq!(r.status(), 400);

    // One episode: metadata, label, history; its revision is the ETag.
    let id = &plain_ids[1];
    let r = srv.req(Method::GET, &format!("/v1/episodes/{id}"), "viewer").send().await.unwrap();
    assert_eq!(r.headers()["etag"], "\"1\"");
    let ep: Value = r.json().await.unwrap();
    assert_eq!(ep["episode"]["label"], "failure");
    assert_eq!(ep["history"].as_array().unwrap().len(), 1);

    // Label with If-Match; a stale revision → 409 with who set the label; none → 428.
    let put = |role: &'static str, rev: Option<&'static str>, label: &'static str| {
        let mut b = srv
            .req(Method::PUT, &format!("/v1/episodes/{id}/label"), role)
            .json(&json!({"label": label, "note": "looked again"}));
        if let Some(r) = rev {
            b = b.header("If-Match", r);
        }
        b.send()
    };
    let r = put("labeler", Some("\"1\""), "success").await.unwrap();
    assert_eq!(r.status(), 200);
    assert_eq!(r.headers()["etag"], "\"2\"");
    let ch: Value = r.json().await.unwrap();
    assert_eq!(
        (ch["old_label"].as_str(), ch["label"].as_str(), ch["revision"].as_i64()),
        (Some("failure"), Some("success"), Some(2))
    );
    assert_eq!(ch["actor"], "labeler-user");
    let r = put("admin", Some("1"), "failure").await.unwrap();
    assert_eq!(r.status(), 409);
    assert_eq!(r.headers()["content-type"], "application/problem+json");
    let p: Value = r.json().await.unwrap();
    assert_eq!(p["status"], 409);
    assert_eq!(p["type"], "urn:ufops:problem:label-conflict");
    assert_eq!(p["current_label"], "success");
    assert_eq!(p["current_revision"], 2);
    assert_eq!(p["set_by"], "labeler-user");
    assert!(p["set_at"].as_str().unwrap().len() >= 20);
    assert!(p["detail"].as_str().unwrap().contains("revision 2"));
    let r = put("labeler", None, "failure").await.unwrap();
    assert_eq!(r.status(), 428);
    let r = put("viewer", Some("2"), "failure").await.unwrap();
    assert_eq!(r.status(), 403);
    let r = put("labeler", Some("2"), "sometimes").await.unwrap();
    assert_eq!(r.status(), 400);
    let r = srv
        .req(Method::PUT, "/v1/episodes/bad%20id/label", "labeler")
        .header("If-Match", "1")
        .json(&json!({"label": "success"}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 400);
    let ep = srv.get_json(&format!("/v1/episodes/{id}"), "viewer").await;
    let hist = ep["history"].as_array().unwrap();
    assert_eq!(hist.len(), 2);
    assert_eq!(hist[1]["actor"], "labeler-user");
    assert_eq!(hist[1]["note"], "looked again");
    assert_eq!(hist[1]["old_label"], "failure");

    // Bulk labels: one transaction (a stale revision anywhere changes nothing).
    let bad = srv
        .req(Method::POST, "/v1/labels/bulk", "labeler")
        .json(&json!({"updates": [
        {"episode_id": plain_ids[0], "label": "failure"},
        {"episode_id": plain_ids[1], "label": "failure", "expect_revision": 1}]}))
        .send()
        .await
        .unwrap();
    assert_eq!(bad.status(), 409);
    assert_eq!(
        srv.get_json(&format!("/v1/episodes/{}", plain_ids[0]), "viewer").await["episode"]["label"],
        "success"
    );
    let ok = srv
        .req(Method::POST, "/v1/labels/bulk", "labeler")
        .json(&json!({"updates": [
        {"episode_id": plain_ids[2], "label": "failure"},
        {"episode_id": plain_ids[3], "label": "success", "expect_revision": 1}]}))
        .send()
        .await
        .unwrap();
    assert_eq!(ok.status(), 200);
    assert_eq!(ok.json::<Value>().await.unwrap().as_array().unwrap().len(), 2);

    // Steps as JSON and as Arrow IPC.
    let steps = srv.get_json(&format!("/v1/episodes/{}/steps", video_ids[0]), "viewer").await;
    assert_eq!(steps["num_rows"], 6);
    assert_eq!(steps["columns"]["obs.pos"][1], json!([2.0, 3.0]));
    assert_eq!(steps["columns"]["media.front.path"].as_array().unwrap().len(), 6);
    let r = srv
        .req(Method::GET, &format!("/v1/episodes/{}/steps", video_ids[0]), "viewer")
        .header("Accept", "application/vnd.apache.arrow.stream")
        .send()
        .await
        .unwrap();
    assert_eq!(r.headers()["content-type"], "application/vnd.apache.arrow.stream");
    let bytes = r.bytes().await.unwrap();
    let reader =
        arrow::ipc::reader::StreamReader::try_new(std::io::Cursor::new(bytes.to_vec()), None).unwrap();
    let batches: Vec<_> = reader.collect::<Result<_, _>>().unwrap();
    assert_eq!(batches.iter().map(|b| b.num_rows()).sum::<usize>(), 6);
    assert!(batches[0].schema().field_with_name("obs.pos").is_ok());

    // Media with range requests.
    let media = format!("/v1/episodes/{}/media/front", video_ids[1]);
    let r = srv.req(Method::GET, &media, "viewer").header("Range", "bytes=1000-1999").send().await.unwrap();
    assert_eq!(r.status(), 206);
    assert_eq!(r.headers()["content-range"], format!("bytes 1000-1999/{}", video.len()));
    assert_eq!(r.headers()["content-type"], "video/mp4");
    assert_eq!(r.bytes().await.unwrap().as_ref(), &video[1000..2000]);
    let r = srv.req(Method::GET, &media, "viewer").header("Range", "bytes=-10").send().await.unwrap();
    assert_eq!(r.status(), 206);
    assert_eq!(r.bytes().await.unwrap().as_ref(), &video[video.len() - 10..]);
    let r = srv.req(Method::GET, &media, "viewer").send().await.unwrap();
    assert_eq!(r.status(), 200);
    assert_eq!(r.headers()["accept-ranges"], "bytes");
    assert_eq!(r.bytes().await.unwrap().as_ref(), &video[..]);
    let r = srv.req(Method::GET, &media, "viewer").header("Range", "bytes=999999-").send().await.unwrap();
    assert_eq!(r.status(), 416);
    assert_eq!(r.headers()["content-range"], format!("bytes */{}", video.len()));
    let r = srv
        .req(Method::GET, &format!("/v1/episodes/{}/media/back", video_ids[1]), "viewer")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 404);
    let r = srv
        .req(Method::GET, &format!("/v1/episodes/{}/media/..%2F..%2Fcatalog.sqlite", video_ids[1]), "viewer")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 400);
    let r = srv
        .req(Method::GET, &format!("/v1/episodes/{}/media/front", plain_ids[0]), "viewer")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 404, "an episode without video");

    // Snapshot, versions, diff.
    let r = srv
        .req(Method::POST, "/v1/label-snapshots", "labeler")
        .json(&json!({"message": "relabel"}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    let snap: Value = r.json().await.unwrap();
    assert_eq!(snap["version"], 4);
    // Again with nothing changed: the head is the snapshot, no new version.
    for _ in 0..3 {
        let r =
            srv.req(Method::POST, "/v1/label-snapshots", "labeler").json(&json!({})).send().await.unwrap();
        assert_eq!(r.status(), 200);
        assert_eq!(r.json::<Value>().await.unwrap()["version"], 4);
    }
    let versions = srv.get_json("/v1/versions", "viewer").await;
    assert_eq!(versions.as_array().unwrap().len(), 4);
    assert_eq!(srv.get_json("/v1/versions/4", "viewer").await["kind"], "label_snapshot");
    let diff = srv.get_json("/v1/versions/2/diff/4", "viewer").await;
    assert_eq!(diff["episodes_added"].as_array().unwrap().len(), 3);
    assert_eq!(diff["labels_changed"].as_array().unwrap().len(), 3);
    let old = srv.get_json(&format!("/v1/episodes/{id}?version=2"), "viewer").await;
    assert_eq!(old["episode"]["label"], "failure", "time travel");

    // Split → training job → artifact → alias → download with a matching sha256.
    let r = srv
        .req(Method::POST, "/v1/splits", "trainer")
        .json(&json!({"policy": "pol", "checkpoint": "c1", "val_fraction": 0.3, "seed": 7}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    let split: Value = r.json().await.unwrap();
    assert_eq!(split["train_episodes"].as_i64().unwrap() + split["val_episodes"].as_i64().unwrap(), 7);
    let split_id = split["id"].as_str().unwrap();
    let sp = srv.get_json(&format!("/v1/splits/{split_id}"), "viewer").await;
    assert_eq!(sp["episodes"].as_array().unwrap().len(), 7);
    assert_eq!(srv.get_json("/v1/splits", "viewer").await.as_array().unwrap().len(), 1);
    let r = srv
        .req(Method::POST, "/v1/jobs", "trainer")
        .json(&json!({"split_id": split_id, "kind": "classifier", "config": {"epochs": 2}}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    let job: Value = r.json().await.unwrap();
    assert_eq!(job["state"], "queued");
    assert_eq!(job["spec"]["policy"], "pol");
    assert_eq!(job["created_by"], "trainer-user");
    let done = srv.wait_job(job["id"].as_str().unwrap()).await;
    assert_eq!(done["state"], "succeeded", "{done}");
    let art_id = done["result"]["artifact_id"].as_str().unwrap().to_string();
    let jobs = srv.get_json("/v1/jobs?state=succeeded", "viewer").await;
    assert_eq!(jobs.as_array().unwrap().len(), 2);
    let r = srv
        .req(Method::POST, "/v1/jobs", "trainer")
        .json(&json!({"split_id": "split-nope", "kind": "classifier"}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 404);
    let r = srv
        .req(Method::POST, "/v1/jobs", "trainer")
        .json(&json!({"split_id": split_id, "kind": "oracle"}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 400);

    let latest = srv.get_json("/v1/policies/pol/checkpoints/c1/verifiers/classifier@latest", "viewer").await;
    assert_eq!(latest["id"], art_id);
    assert_eq!(latest["job_id"], job["id"]);
    let r = srv
        .req(Method::PUT, &format!("/v1/artifacts/{art_id}/aliases/prod"), "labeler")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 403);
    let r = srv
        .req(Method::PUT, &format!("/v1/artifacts/{art_id}/aliases/prod"), "trainer")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let r = srv
        .req(Method::PUT, &format!("/v1/artifacts/{art_id}/aliases/pr@d"), "trainer")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 400);
    let art = srv.get_json(&format!("/v1/artifacts/{art_id}"), "viewer").await;
    assert_eq!(art["aliases"], json!(["latest", "prod"]));
    assert_eq!(
        srv.get_json("/v1/artifacts?policy=pol&kind=classifier", "viewer").await.as_array().unwrap().len(),
        1
    );
    let manifest: Value = serde_json::from_slice(
        &srv.req(
            Method::GET,
            "/v1/policies/pol/checkpoints/c1/verifiers/classifier@prod/files/manifest.json",
            "viewer",
        )
        .send()
        .await
        .unwrap()
        .bytes()
        .await
        .unwrap(),
    )
    .unwrap();
    for name in ["model.safetensors", "config.json"] {
        let r = srv
            .req(
                Method::GET,
                &format!("/v1/policies/pol/checkpoints/c1/verifiers/classifier@prod/files/{name}"),
                "viewer",
            )
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 200);
        let sum = r.headers()["x-checksum-sha256"].to_str().unwrap().to_string();
        assert_eq!(r.headers()["etag"].to_str().unwrap(), format!("\"{sum}\""));
        assert_eq!(r.headers()["x-artifact-id"].to_str().unwrap(), art_id);
        let body = r.bytes().await.unwrap();
        assert_eq!(sha256_hex(&body), sum);
        assert_eq!(manifest["files"][name], sum, "{name} matches the manifest");
    }
    let r = srv
        .req(Method::GET, &format!("/v1/artifacts/{art_id}/files/model.safetensors"), "viewer")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let r = srv
        .req(Method::GET, &format!("/v1/artifacts/{art_id}/files/secret.txt"), "viewer")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 404);
    let r = srv
        .req(Method::GET, "/v1/policies/pol/checkpoints/c1/verifiers/classifier@nope", "viewer")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 404);

    // Cancel: a queued job is cancelled at once.
    let r = srv
        .req(Method::POST, "/v1/jobs", "trainer")
        .json(&json!({"split_id": split_id, "kind": "q"}))
        .send()
        .await
        .unwrap();
    let j: Value = r.json().await.unwrap();
    let r = srv
        .req(Method::POST, &format!("/v1/jobs/{}/cancel", j["id"].as_str().unwrap()), "trainer")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let st = srv.wait_job(j["id"].as_str().unwrap()).await;
    assert_eq!(st["state"], "cancelled", "{st}");

    // gc (admin), metrics, OpenAPI, health.
    let r = srv
        .req(Method::POST, "/v1/gc", "admin")
        .json(&json!({"grace_seconds": 0, "dry_run": true}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let m = srv.req(Method::GET, "/metrics", "viewer").send().await.unwrap().text().await.unwrap();
    assert!(m.contains("ufops_label_writes_total 3"), "{m}");
    assert!(m.contains("ufops_label_conflicts_total 2"), "{m}");
    assert!(
        m.contains(
            r#"ufops_http_requests_total{method="PUT",route="/v1/episodes/{id}/label",status="409"} 1"#
        ),
        "{m}"
    );
    assert!(m.contains(r#"ufops_jobs{state="succeeded"} 2"#), "{m}");
    let doc = srv.get_json("/openapi.json", "viewer").await;
    assert!(doc["openapi"].as_str().unwrap().starts_with("3."));
    assert!(doc["paths"]["/v1/episodes/{id}/label"]["put"].is_object());
    assert!(doc["components"]["securitySchemes"]["bearer"].is_object());
    let h = reqwest::get(srv.url("/healthz")).await.unwrap();
    assert_eq!(h.status(), 200);
    srv.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn full_flow_sqlite() {
    full_flow(Db::Sqlite).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn full_flow_postgres() {
    if !store::test_support::require_postgres() {
        return;
    }
    full_flow(Db::Postgres).await;
}

#[tokio::test]
async fn oversized_json_body_is_refused() {
    let srv = TestServer::start(Db::Sqlite, false).await;
    let big = "x".repeat(2 << 20);
    let r = srv
        .req(Method::POST, "/v1/labels/bulk", "labeler")
        .header("content-type", "application/json")
        .body(format!("{{\"updates\": [], \"pad\": \"{big}\"}}"))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 413);
    srv.stop().await;
}

/// Image cameras: an episode's detail lists its cameras (image columns and videos), and
/// `/v1/episodes/{id}/frames/{camera}/{t}` serves one step's PNG with a strong ETag and
/// immutable caching; a missing episode, camera, step or version is a 404 naming it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn image_camera_frames() {
    let srv = TestServer::start(Db::Sqlite, false).await;
    let frame = |cam: &str, i: u32, t: usize| format!("\u{89}PNG {cam} {i} {t}").into_bytes();
    let mut w = srv.store.begin_ingest(common::source("img"), "pol", "c1").await.unwrap();
    let mut ids = Vec::new();
    for i in 0..2u32 {
        let mut ep = common::episode(i, 7, store::Label::Success);
        for cam in ["agentview_image", "robot0_eye_in_hand_image"] {
            ep.images.push(store::ImageColumn {
                name: cam.into(),
                shape: [8, 8, 3],
                frames: store::Frames::Encoded((0..7).map(|t| frame(cam, i, t)).collect()),
            });
        }
        ids.push(w.add_episode(ep).await.unwrap());
    }
    let v = w.commit("images").await.unwrap().version;
    let (video_ids, _) = common::ingest_with_video(&srv.store, srv.dir.path(), "vid", "c1", 1).await;

    let d = srv.get_json(&format!("/v1/episodes/{}", ids[1]), "viewer").await;
    assert_eq!(
        d["cameras"],
        json!([
            {"name": "agentview_image", "kind": "image", "shape": [8, 8, 3], "encoding": "png"},
            {"name": "robot0_eye_in_hand_image", "kind": "image", "shape": [8, 8, 3], "encoding": "png"}
        ])
    );
    let d = srv.get_json(&format!("/v1/episodes/{}", video_ids[0]), "viewer").await;
    assert_eq!(d["cameras"], json!([{"name": "front", "kind": "video", "shape": null, "encoding": null}]));

    let url = format!("/v1/episodes/{}/frames/robot0_eye_in_hand_image/5", ids[1]);
    let r = srv.req(Method::GET, &url, "viewer").send().await.unwrap();
    assert_eq!(r.status(), 200);
    assert_eq!(r.headers()["content-type"], "image/png");
    assert_eq!(r.headers()["cache-control"], "private, max-age=31536000, immutable");
    let etag = r.headers()["etag"].to_str().unwrap().to_string();
    assert!(etag.starts_with('"') && etag.ends_with('"'), "a strong ETag: {etag}");
    assert_eq!(r.bytes().await.unwrap().as_ref(), frame("robot0_eye_in_hand_image", 1, 5).as_slice());
    let r = srv.req(Method::GET, &url, "viewer").header("If-None-Match", &etag).send().await.unwrap();
    assert_eq!(r.status(), 304);
    assert_eq!(r.headers()["etag"], etag.as_str());
    // Another step is another ETag; the version the episode came in serves the same bytes.
    let r = srv
        .req(Method::GET, &format!("/v1/episodes/{}/frames/agentview_image/0?version={v}", ids[1]), "viewer")
        .header("If-None-Match", &etag)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    assert_eq!(r.bytes().await.unwrap().as_ref(), frame("agentview_image", 1, 0).as_slice());

    // A video camera's frame is decoded on request; these videos are not decodable H.264, which
    // is the file's fault: 400 with the reason, never a 5xx.
    let path = format!("/v1/episodes/{}/frames/front/0", video_ids[0]);
    let r = srv.req(Method::GET, &path, "viewer").send().await.unwrap();
    assert_eq!(r.status(), 400, "{path}");
    let p: Value = r.json().await.unwrap();
    assert!(p["detail"].as_str().unwrap().contains("video"), "{path}: {p}");

    for (path, names) in [
        ("/v1/episodes/nope-1/frames/agentview_image/0".to_string(), "episode"),
        (format!("/v1/episodes/{}/frames/wrist/0", ids[0]), "camera"),
        (format!("/v1/episodes/{}/frames/agentview_image/7", ids[0]), "step"),
        (format!("/v1/episodes/{}/frames/agentview_image/99999999999999999999999", ids[0]), "step"),
        (format!("/v1/episodes/{}/frames/agentview_image/0?version=999", ids[0]), "version"),
    ] {
        let r = srv.req(Method::GET, &path, "viewer").send().await.unwrap();
        assert_eq!(r.status(), 404, "{path}");
        let p: Value = r.json().await.unwrap();
        assert!(p["detail"].as_str().unwrap().contains(names), "{path}: {p}");
    }
    let r = srv
        .req(Method::GET, &format!("/v1/episodes/{}/frames/agentview_image/-1", ids[0]), "viewer")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 400);
    srv.stop().await;
}
