//! `POST /v1/exports` end to end through `ufops serve` and its worker, on the embedded store and on
//! the scale-out one (Postgres + S3): a Demo-SCORE-curated LeRobot export keeps exactly what the
//! scorer (`ufops rank`) keeps, its files are listed and served from the store (ranges too),
//! survive gc while the job stands, and are deleted on request; bad requests are 4xx and queue
//! nothing.

use crate::common;
use common::*;
use std::time::{Duration, Instant};

fn wait_for(url: &str, auth: &str, id: &str) -> serde_json::Value {
    let t0 = Instant::now();
    loop {
        let r = http(url, "GET", &format!("/v1/exports/{id}"), &[("Authorization", auth)], None);
        assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
        let v = r.json();
        match v["job"]["state"].as_str().unwrap() {
            "succeeded" => return v,
            "failed" | "cancelled" => panic!("export {id} did not succeed: {v}"),
            _ => {}
        }
        assert!(t0.elapsed() < Duration::from_secs(180), "export {id} still not done: {v}");
        std::thread::sleep(Duration::from_millis(200));
    }
}

fn exports_end_to_end(t: &Target) {
    t.ok(&["init"]);
    let (artifact, n) = lift_with_classifier(t);
    let split = t.json(&["split", "create", "--policy", "bc", "--checkpoint", "e600", "--json"]);
    let split_id = split["id"].as_str().unwrap().to_string();
    let ranked = t.json(&["rank", "--artifact", artifact, "--policy", "bc", "--json"]);
    let mut want: Vec<String> = ranked["episodes"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|r| r["score"].as_f64().unwrap() >= 0.5)
        .map(|r| r["episode_id"].as_str().unwrap().to_string())
        .collect();
    want.sort();
    assert!(!want.is_empty() && want.len() < n, "{ranked}");
    let trainer = t.bearer("curator", "trainer");
    let viewer = t.bearer("robot", "viewer");
    let server = t.serve(&[]);
    let url = server.url.as_str();

    // Refused before anything is queued.
    for (body, status, want_text) in [
        (serde_json::json!({"format": "csv"}), 400, "expected lerobot or robomimic"),
        (serde_json::json!({"format": "lerobot", "score": {"min": 0.5}}), 422, "artifact"),
        (
            serde_json::json!({"format": "lerobot", "score": {"artifact": "bc/e600/classifier@nope"}}),
            404,
            "nope",
        ),
        (
            serde_json::json!({"format": "lerobot", "score": {"artifact": artifact, "min": 0.9, "max": 0.1}}),
            400,
            "min must not exceed max",
        ),
        (serde_json::json!({"format": "lerobot", "split": "no-such-split"}), 404, "no-such-split"),
        (serde_json::json!({"format": "lerobot", "colour": "red"}), 422, "colour"),
    ] {
        let r = http(url, "POST", "/v1/exports", &[("Authorization", &trainer)], Some(&body));
        let text = String::from_utf8_lossy(&r.body).into_owned();
        assert_eq!(r.status, status, "{body}: {text}");
        assert!(text.contains(want_text), "{body}: {text}");
    }
    let r = http(
        url,
        "POST",
        "/v1/exports",
        &[("Authorization", &viewer)],
        Some(&serde_json::json!({"format": "lerobot"})),
    );
    assert_eq!(r.status, 403);
    let r = http(url, "GET", "/v1/exports", &[("Authorization", &viewer)], None);
    assert_eq!(r.json().as_array().unwrap().len(), 0, "nothing was queued");

    // The curated LeRobot export.
    let body =
        serde_json::json!({"format": "lerobot", "policy": "bc", "score": {"artifact": artifact, "min": 0.5}});
    let r = http(url, "POST", "/v1/exports", &[("Authorization", &trainer)], Some(&body));
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let id = r.json()["id"].as_str().unwrap().to_string();
    let done = wait_for(url, &viewer, &id);
    let result = &done["job"]["result"];
    assert_eq!(result["report"]["episodes"].as_u64().unwrap() as usize, want.len(), "{done}");
    assert_eq!(result["episodes_scored"].as_u64().unwrap() as usize, n, "{done}");
    let files: Vec<(String, u64)> = done["files"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| (f["path"].as_str().unwrap().to_string(), f["bytes"].as_u64().unwrap()))
        .collect();
    for p in [
        "meta/info.json",
        "meta/stats.json",
        "meta/episodes/chunk-000/file-000.parquet",
        "data/chunk-000/file-000.parquet",
    ] {
        assert!(files.iter().any(|(f, _)| f == p), "{p} not in {files:?}");
    }
    // Files come back whole and by range, and are the dataset the job wrote.
    let info = http(
        url,
        "GET",
        &format!("/v1/exports/{id}/files/meta/info.json"),
        &[("Authorization", &viewer)],
        None,
    );
    assert_eq!(info.status, 200);
    assert_eq!(info.header("content-type"), Some("application/json"));
    let info = info.json();
    assert_eq!(info["total_episodes"].as_u64().unwrap() as usize, want.len(), "{info}");
    assert_eq!(info["ufops"]["selection"]["score"]["min"], 0.5, "{info}");
    let (data, size) = files.iter().find(|(f, _)| f == "meta/episodes/chunk-000/file-000.parquet").unwrap();
    let whole =
        http(url, "GET", &format!("/v1/exports/{id}/files/{data}"), &[("Authorization", &viewer)], None);
    assert_eq!((whole.status, whole.body.len() as u64), (200, *size));
    let part = http(
        url,
        "GET",
        &format!("/v1/exports/{id}/files/{data}"),
        &[("Authorization", &viewer), ("Range", "bytes=0-3")],
        None,
    );
    assert_eq!(part.status, 206);
    assert_eq!(part.body, b"PAR1");
    // The episode table names exactly the episodes the scorer put at or above 0.5.
    let local = t.data_dir.join("episodes.parquet");
    std::fs::write(&local, &whole.body).unwrap();
    let reader = parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder::try_new(
        std::fs::File::open(&local).unwrap(),
    )
    .unwrap()
    .build()
    .unwrap();
    let mut got: Vec<String> = Vec::new();
    for b in reader {
        let b = b.unwrap();
        let ids = b.column_by_name("ufops/episode_id").unwrap();
        let ids = ids.as_any().downcast_ref::<arrow::array::StringArray>().unwrap();
        got.extend(ids.iter().map(|s| s.unwrap().to_string()));
    }
    got.sort();
    assert_eq!(got, want);
    for bad in ["../../catalog.db", "meta/..%2F..%2Fx", "nope.json"] {
        let r =
            http(url, "GET", &format!("/v1/exports/{id}/files/{bad}"), &[("Authorization", &viewer)], None);
        assert!(r.status == 400 || r.status == 404, "{bad}: {}", r.status);
    }

    // A robomimic export of the split, kept by gc while its job stands.
    let body = serde_json::json!({"format": "robomimic", "split": split_id});
    let r = http(url, "POST", "/v1/exports", &[("Authorization", &trainer)], Some(&body));
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let id2 = r.json()["id"].as_str().unwrap().to_string();
    let done2 = wait_for(url, &viewer, &id2);
    assert_eq!(done2["files"][0]["path"], "rollouts.hdf5", "{done2}");
    let h5 = http(
        url,
        "GET",
        &format!("/v1/exports/{id2}/files/rollouts.hdf5"),
        &[("Authorization", &viewer), ("Range", "bytes=0-7")],
        None,
    );
    assert_eq!(h5.body, b"\x89HDF\r\n\x1a\n");
    let gc = t.json(&["gc", "--grace-seconds", "0", "--json"]);
    assert!(
        gc["deleted"].as_array().unwrap().iter().all(|p| !p.as_str().unwrap().starts_with("exports/")),
        "{gc}"
    );
    assert_eq!(wait_for(url, &viewer, &id)["files"].as_array().unwrap().len(), files.len());

    // Deleted on request (trainers only); the job record stays.
    let r = http(url, "DELETE", &format!("/v1/exports/{id}"), &[("Authorization", &viewer)], None);
    assert_eq!(r.status, 403);
    let r = http(url, "DELETE", &format!("/v1/exports/{id}"), &[("Authorization", &trainer)], None);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.json()["files_deleted"].as_u64().unwrap() as usize, files.len());
    let after = wait_for(url, &viewer, &id);
    assert!(after["files"].as_array().unwrap().is_empty(), "{after}");
    let r = http(
        url,
        "GET",
        &format!("/v1/exports/{id}/files/meta/info.json"),
        &[("Authorization", &viewer)],
        None,
    );
    assert_eq!(r.status, 404);
    // A job of another kind is not an export.
    let jobs = http(url, "GET", "/v1/jobs", &[("Authorization", &viewer)], None).json();
    let train = jobs.as_array().unwrap().iter().find(|j| j["kind"] == "train").expect("the training job");
    let r = http(
        url,
        "GET",
        &format!("/v1/exports/{}", train["id"].as_str().unwrap()),
        &[("Authorization", &viewer)],
        None,
    );
    assert_eq!(r.status, 404);
}

#[test]
fn exports_on_the_embedded_store() {
    let dir = tempfile::tempdir().unwrap();
    exports_end_to_end(&Target::sqlite(dir.path()));
}

#[test]
fn exports_on_postgres_and_s3() {
    let dir = tempfile::tempdir().unwrap();
    let Some(s3) = seaweedfs::SeaweedFs::start_if_available() else { return };
    let Some(mut t) = postgres_target(dir.path()) else { return };
    t.object_store = Some(format!("s3://{}/exports-test", seaweedfs::BUCKET));
    t.env = s3.env();
    exports_end_to_end(&t);
}
