//! The scale-out store for real: a Postgres catalog and objects in S3 (SeaweedFS started here),
//! through the `ufops` binary: ingest with videos, dedup, read back, train, download an artifact
//! with checked sha256s, gc.

use crate::common;
use common::*;

fn s3_target(dir: &std::path::Path, s3: &seaweedfs::SeaweedFs, prefix: &str) -> Option<Target> {
    let mut t = postgres_target(dir)?;
    t.object_store = Some(format!("s3://{}/{prefix}", seaweedfs::BUCKET));
    t.env = s3.env();
    Some(t)
}

#[test]
fn postgres_and_s3_store_end_to_end() {
    let dir = tempfile::tempdir().unwrap();
    let Some(s3) = seaweedfs::SeaweedFs::start_if_available() else { return };
    let Some(t) = s3_target(dir.path(), &s3, "e2e") else { return };
    t.ok(&["init"]);

    let fixture = fixtures().join("lerobot/v30_eval_video");
    let expected: serde_json::Value = serde_json::from_slice(
        &std::fs::read(fixtures().join("lerobot/v30_eval_video.expected.json")).unwrap(),
    )
    .unwrap();
    let fixture_s = fixture.to_str().unwrap();
    t.ok(&["ingest", fixture_s, "--policy", "arm", "--checkpoint", "c1"]);

    // The episodes, their lengths and labels, as the fixture's expected output lists them.
    let episodes = t.json(&["episodes", "--json"]);
    let episodes = episodes.as_array().unwrap();
    let want = expected["episodes"].as_array().unwrap();
    assert_eq!(episodes.len(), want.len());
    let mut got: Vec<(u64, String)> = episodes
        .iter()
        .map(|e| (e["length"].as_u64().unwrap(), e["label"].as_str().unwrap().to_string()))
        .collect();
    let mut exp: Vec<(u64, String)> = want
        .iter()
        .map(|e| {
            let label = if e["success"].as_bool().unwrap() { "success" } else { "failure" };
            (e["length"].as_u64().unwrap(), label.to_string())
        })
        .collect();
    got.sort();
    exp.sort();
    assert_eq!(got, exp);

    // Same content again: a no-op, no second version.
    let again = t.ok(&["ingest", fixture_s, "--policy", "arm", "--checkpoint", "c1"]);
    assert!(again.contains("already"), "re-ingest should say which version holds it: {again}");
    assert_eq!(t.json(&["versions", "--json"]).as_array().unwrap().len(), 1);

    // Every step and label snapshot reads back from S3; the video is there once.
    let report = t.json(&["dev", "verify"]);
    assert!(report["problems"].as_array().unwrap().is_empty(), "{report}");
    assert!(report["referenced_objects"].as_u64().unwrap() >= 3, "{report}");

    // Train a verifier from S3 data and publish it to S3; download it back with checked sha256s.
    let split = t.json(&["split", "create", "--policy", "arm", "--checkpoint", "c1", "--json"]);
    let split_id = split["id"].as_str().unwrap();
    let cfg = dir.path().join("train.json");
    std::fs::write(&cfg, r#"{"epochs": 2, "batch_size": 64, "chunk_len": 16}"#).unwrap();
    let job = t.json(&[
        "train",
        "--split",
        split_id,
        "--kind",
        "classifier",
        "--config",
        cfg.to_str().unwrap(),
        "--json",
    ]);
    let artifact_id = job["id"].as_str().unwrap_or_else(|| panic!("train printed no artifact id: {job}"));
    let out = dir.path().join("downloaded");
    t.ok(&["artifacts", "download", "arm/c1/classifier@latest", out.to_str().unwrap()]);
    // The artifact id is the sha256 prefix of its manifest; every listed file came back intact.
    let manifest = std::fs::read(out.join("manifest.json")).unwrap();
    assert_eq!(&store::sha256_hex(&manifest)[..16], artifact_id);
    for f in job["files"].as_array().unwrap() {
        let bytes = std::fs::read(out.join(f["name"].as_str().unwrap())).unwrap();
        assert_eq!(store::sha256_hex(&bytes), f["sha256"].as_str().unwrap());
    }

    // Nothing is orphaned, nothing went to the local directory.
    let gc = t.json(&["gc", "--grace-seconds", "0", "--dry-run", "--json"]);
    assert!(gc["deleted"].as_array().unwrap().is_empty(), "{gc}");
    assert_eq!(gc["objects_scanned"], gc["referenced"], "{gc}");
    assert!(object_files(dir.path()).is_empty());

    // A second store prefix in the same bucket is a separate store: it sees none of these objects.
    let other =
        s3_target(tempfile::tempdir().unwrap().path(), &s3, "other").expect("Postgres answered above");
    other.ok(&["init"]);
    let gc = other.json(&["gc", "--grace-seconds", "0", "--dry-run", "--json"]);
    assert_eq!(gc["objects_scanned"].as_u64(), Some(0), "{gc}");
}

/// A wrong secret is refused with a message naming the object store, and the catalog stays as before.
#[test]
fn bad_s3_credentials_fail_cleanly() {
    let dir = tempfile::tempdir().unwrap();
    let Some(s3) = seaweedfs::SeaweedFs::start_if_available() else { return };
    let Some(mut t) = s3_target(dir.path(), &s3, "bad") else { return };
    t.ok(&["init"]);
    for (k, v) in t.env.iter_mut() {
        if *k == "AWS_SECRET_ACCESS_KEY" {
            *v = "wrong".into();
        }
    }
    let out = t.run(&["dev", "synth", "--episodes", "2", "--steps", "10"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.to_lowercase().contains("s3") || err.contains("object"), "unclear error: {err}");
    assert!(!err.contains("panicked"), "{err}");
    assert!(t.json(&["versions", "--json"]).as_array().unwrap().is_empty());
}

/// One HTTP/1.1 GET (`Connection: close`): the status line, the headers (lower-case names) and the body.
fn http_get(url: &str, path: &str, headers: &[(&str, &str)]) -> (String, Vec<(String, String)>, Vec<u8>) {
    use std::io::{Read, Write};
    let addr = url.trim_start_matches("http://").trim_end_matches('/');
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    let mut req = format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n");
    for (k, v) in headers {
        req.push_str(&format!("{k}: {v}\r\n"));
    }
    req.push_str("\r\n");
    s.write_all(req.as_bytes()).unwrap();
    let mut raw = Vec::new();
    s.read_to_end(&mut raw).unwrap();
    let end = raw.windows(4).position(|w| w == b"\r\n\r\n").expect("a complete response");
    let head = String::from_utf8_lossy(&raw[..end]).into_owned();
    let mut lines = head.lines();
    let status = lines.next().unwrap_or_default().to_string();
    let hdrs = lines
        .filter_map(|l| l.split_once(':').map(|(k, v)| (k.trim().to_ascii_lowercase(), v.trim().to_string())))
        .collect();
    (status, hdrs, raw[end + 4..].to_vec())
}

/// `ufops_object_store_*` counters of a running server: (GET requests, HEAD requests, bytes).
fn object_reads(url: &str, token: &str) -> (u64, u64, u64) {
    let auth = format!("Bearer {token}");
    let (status, _, body) = http_get(url, "/metrics", &[("Authorization", &auth)]);
    assert!(status.contains(" 200"), "{status}");
    let text = String::from_utf8(body).unwrap();
    let value = |name: &str| -> u64 {
        let line =
            text.lines().find(|l| l.starts_with(name)).unwrap_or_else(|| panic!("no {name} in /metrics"));
        line.rsplit(' ').next().unwrap().parse().unwrap()
    };
    (
        value("ufops_object_store_requests_total{method=\"GET\"}"),
        value("ufops_object_store_requests_total{method=\"HEAD\"}"),
        value("ufops_object_store_fetched_bytes_total"),
    )
}

/// The labeling page's video requests: a Range request is answered from exactly that range of
/// the video object in S3 (one GET, the range's bytes, no HEAD, no steps file), and the bytes are
/// the video's own.
#[test]
fn video_range_request_fetches_only_its_range() {
    use std::io::{BufRead, BufReader};
    let dir = tempfile::tempdir().unwrap();
    let Some(s3) = seaweedfs::SeaweedFs::start_if_available() else { return };
    let Some(t) = s3_target(dir.path(), &s3, "media") else { return };
    t.ok(&["init"]);
    let fixture = fixtures().join("lerobot/v30_eval_video");
    t.ok(&["ingest", fixture.to_str().unwrap(), "--policy", "arm", "--checkpoint", "c1"]);
    let episodes = t.json(&["episodes", "--json"]);
    let id = episodes[3]["id"].as_str().unwrap().to_string();
    let token = t.token("labeler", "labeler");
    let mut child = t
        .command()
        .args(["serve", "--addr", "127.0.0.1:0", "--no-worker"])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
    struct Kill(std::process::Child);
    impl Drop for Kill {
        fn drop(&mut self) {
            let _ = self.0.kill();
            let _ = self.0.wait();
        }
    }
    let _server = Kill(child);
    let url = line
        .trim()
        .strip_prefix("listening on ")
        .unwrap_or_else(|| panic!("unexpected: {line:?}"))
        .to_string();
    let auth = format!("Bearer {token}");
    // LeRobot keys lose their `observation.` prefix in the store.
    let media = format!("/v1/episodes/{id}/media/images.front");

    let before = object_reads(&url, &token);
    let (status, headers, body) =
        http_get(&url, &media, &[("Authorization", &auth), ("Range", "bytes=100-1099")]);
    let after = object_reads(&url, &token);
    assert!(status.contains(" 206"), "{status}: {}", String::from_utf8_lossy(&body));
    let range = headers.iter().find(|(k, _)| k == "content-range").map(|(_, v)| v.clone()).unwrap();
    assert!(range.starts_with("bytes 100-1099/"), "{range}");
    assert_eq!(body.len(), 1000);
    let (gets, heads, bytes) = (after.0 - before.0, after.1 - before.1, after.2 - before.2);
    assert_eq!(
        (gets, heads, bytes),
        (1, 0, 1000),
        "GETs, HEADs and bytes fetched from S3 for a 1000-byte range"
    );

    // The same bytes as the video file itself.
    let size: u64 = range.rsplit('/').next().unwrap().parse().unwrap();
    let candidates: Vec<Vec<u8>> = walk(&fixture.join("videos"))
        .into_iter()
        .filter(|p| std::fs::metadata(p).unwrap().len() == size)
        .map(|p| std::fs::read(p).unwrap())
        .collect();
    assert!(!candidates.is_empty(), "no video of {size} bytes in the fixture");
    assert!(candidates.iter().any(|v| v[100..1100] == body[..]), "the range is the video's bytes 100-1099");
}

fn walk(p: &std::path::Path) -> Vec<std::path::PathBuf> {
    if p.is_dir() {
        std::fs::read_dir(p).unwrap().flat_map(|e| walk(&e.unwrap().path())).collect()
    } else {
        vec![p.to_path_buf()]
    }
}

/// An Arrow IPC stream of layer values: `dim` floats per step, step t of episode k holding
/// `k * 100 + t + d / 10`.
fn layer_stream(eps: &[(String, usize)], dim: usize) -> Vec<u8> {
    use arrow::array::{ArrayRef, FixedSizeListArray, Float32Array, RecordBatch, StringArray};
    use arrow::datatypes::{DataType, Field, Schema};
    use std::sync::Arc;
    let item = Arc::new(Field::new("item", DataType::Float32, false));
    let schema = Arc::new(Schema::new(vec![
        Field::new("episode_id", DataType::Utf8, false),
        Field::new("value", DataType::FixedSizeList(item.clone(), dim as i32), false),
    ]));
    let mut buf = Vec::new();
    let mut w = arrow::ipc::writer::StreamWriter::try_new(&mut buf, &schema).unwrap();
    for (k, (id, steps)) in eps.iter().enumerate() {
        let ids: ArrayRef = Arc::new(StringArray::from(vec![id.as_str(); *steps]));
        let v: Vec<f32> =
            (0..*steps).flat_map(|t| (0..dim).map(move |d| (k * 100 + t) as f32 + d as f32 / 10.0)).collect();
        let vals: ArrayRef = Arc::new(
            FixedSizeListArray::try_new(item.clone(), dim as i32, Arc::new(Float32Array::from(v)), None)
                .unwrap(),
        );
        w.write(&RecordBatch::try_new(schema.clone(), vec![ids, vals]).unwrap()).unwrap();
    }
    w.finish().unwrap();
    drop(w);
    buf
}

/// Layers over the API on the scale-out store (Postgres + S3): a trainer writes a layer as an
/// Arrow IPC stream (a version; the same again writes nothing), every client reads the steps
/// with it joined, the version before has none, bad streams are 400s that change nothing, a
/// viewer may not write, and a verifier trains on the layer from S3.
#[test]
fn layers_over_the_api_on_postgres_and_s3() {
    let dir = tempfile::tempdir().unwrap();
    let Some(s3) = seaweedfs::SeaweedFs::start_if_available() else { return };
    let Some(t) = s3_target(dir.path(), &s3, "layers") else { return };
    t.ok(&["init"]);
    t.ok(&[
        "ingest",
        fixtures().join("lerobot/v30_eval_video").to_str().unwrap(),
        "--policy",
        "arm",
        "--checkpoint",
        "c1",
    ]);
    let before = t.json(&["versions", "--json"]).as_array().unwrap().len() as i64;
    let eps: Vec<(String, usize)> = t
        .json(&["episodes", "--json"])
        .as_array()
        .unwrap()
        .iter()
        .map(|e| (e["id"].as_str().unwrap().to_string(), e["length"].as_u64().unwrap() as usize))
        .collect();
    let trainer = t.token("enc", "trainer");
    let viewer = t.token("v", "viewer");
    let server = t.serve(&["--no-worker"]);
    let (ta, va) = (format!("Bearer {trainer}"), format!("Bearer {viewer}"));
    let producer = r#"{"encoder":"cnn","policy":"arm","checkpoint":"c1","content_hash":"abc"}"#;
    let q: String = producer
        .bytes()
        .map(|b| if b.is_ascii_alphanumeric() { (b as char).to_string() } else { format!("%{b:02X}") })
        .collect();
    let path = format!("/v1/layers/features.cnn?producer={q}");
    let ct = Some("application/vnd.apache.arrow.stream");

    // Refused: a viewer, a stream that is not Arrow, a wrong row count; the store is unchanged.
    let body = layer_stream(&eps[..3], 4);
    assert_eq!(http_bytes(&server.url, "POST", &path, &[("Authorization", &va)], &body, ct).status, 403);
    let r = http_bytes(&server.url, "POST", &path, &[("Authorization", &ta)], b"not arrow", ct);
    assert_eq!(r.status, 400, "{}", String::from_utf8_lossy(&r.body));
    let mut short = eps[..1].to_vec();
    short[0].1 -= 1;
    let r = http_bytes(&server.url, "POST", &path, &[("Authorization", &ta)], &layer_stream(&short, 4), ct);
    assert_eq!(r.status, 400, "{}", String::from_utf8_lossy(&r.body));
    assert!(String::from_utf8_lossy(&r.body).contains("steps"));
    assert_eq!(t.json(&["versions", "--json"]).as_array().unwrap().len() as i64, before);

    // Three episodes, then all (the first three skipped), then all again (nothing).
    let r = http_bytes(&server.url, "POST", &path, &[("Authorization", &ta)], &body, ct);
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.json()["episodes_written"], 3);
    let all = layer_stream(&eps, 4);
    let r = http_bytes(&server.url, "POST", &path, &[("Authorization", &ta)], &all, ct);
    assert_eq!(
        (r.status, r.json()["episodes_written"].as_u64(), r.json()["episodes_skipped"].as_u64()),
        (201, Some(eps.len() as u64 - 3), Some(3))
    );
    let r = http_bytes(&server.url, "POST", &path, &[("Authorization", &ta)], &all, ct);
    assert_eq!((r.status, r.json()["version"].is_null()), (200, true));
    let listed = http(&server.url, "GET", "/v1/layers", &[("Authorization", &va)], None).json();
    assert_eq!(listed[0]["episodes"].as_u64(), Some(eps.len() as u64), "{listed}");
    let hash = listed[0]["producer_hash"].as_str().unwrap();
    let held = http(
        &server.url,
        "GET",
        &format!("/v1/layers/features.cnn/episodes?producer_hash={hash}"),
        &[("Authorization", &va)],
        None,
    )
    .json();
    assert_eq!(held.as_array().unwrap().len(), eps.len());

    // Read back joined, as JSON columns; not there in the version before.
    let (id, steps) = &eps[5];
    let r = http(
        &server.url,
        "GET",
        &format!("/v1/episodes/{id}/steps?layers=features.cnn"),
        &[("Authorization", &va)],
        None,
    );
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let col = r.json()["columns"]["obs.features.cnn"].clone();
    let rows = col.as_array().unwrap_or_else(|| {
        panic!(
            "no obs.features.cnn in {}",
            r.json()["columns"].as_object().unwrap().keys().cloned().collect::<Vec<_>>().join(",")
        )
    });
    assert_eq!(rows.len(), *steps);
    assert_eq!(rows[2][1].as_f64().unwrap() as f32, 502.0 + 0.1);
    let r = http(
        &server.url,
        "GET",
        &format!("/v1/episodes/{id}/steps?layers=features.cnn&version={before}"),
        &[("Authorization", &va)],
        None,
    );
    assert_eq!(r.status, 404, "{}", String::from_utf8_lossy(&r.body));
    let held = http(
        &server.url,
        "GET",
        &format!("/v1/episodes/{id}/layers?version={before}"),
        &[("Authorization", &va)],
        None,
    )
    .json();
    assert_eq!(held, serde_json::json!([]));
    drop(server);

    // A verifier trained on the layer, from S3, records the producer.
    let split = t.json(&["split", "create", "--policy", "arm", "--checkpoint", "c1", "--json"]);
    let cfg = dir.path().join("train.json");
    std::fs::write(&cfg, r#"{"epochs": 2, "batch_size": 64, "chunk_len": 4}"#).unwrap();
    let art = t.json(&[
        "train",
        "--split",
        split["id"].as_str().unwrap(),
        "--kind",
        "classifier",
        "--config",
        cfg.to_str().unwrap(),
        "--obs-keys",
        "features.cnn",
        "--json",
    ]);
    let keys = &art["config"]["input"]["obs_keys"];
    assert_eq!(keys[0]["key"], "features.cnn", "{keys}");
    assert_eq!(keys[0]["producer"].as_str(), Some(hash));
    assert_eq!(art["config"]["input"]["chunk_len"], 4, "the recipe file's chunk_len");
}

/// A signed request to SeaweedFS's S3 API with curl (`--aws-sigv4`): the independent view of
/// the bucket that the multipart test checks ufops against.
fn s3_api(s3: &seaweedfs::SeaweedFs, path_and_query: &str) -> String {
    let out = std::process::Command::new("curl")
        .args(["-sS", "--fail-with-body", "--aws-sigv4", "aws:amz:us-east-1:s3"])
        .arg("--user")
        .arg(format!("{}:{}", seaweedfs::ACCESS_KEY, seaweedfs::SECRET_KEY))
        .args(["-H", "x-amz-content-sha256: UNSIGNED-PAYLOAD"])
        .arg(format!("{}/{}{path_and_query}", s3.s3_endpoint, seaweedfs::BUCKET))
        .output()
        .unwrap_or_else(|e| panic!("this test lists the bucket with curl, which did not run: {e}"));
    let body = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(out.status.success(), "curl {path_and_query}: {body} {}", String::from_utf8_lossy(&out.stderr));
    body
}

/// The texts of every `<tag>` element of an XML answer.
fn xml_values(xml: &str, tag: &str) -> Vec<String> {
    let (open, close) = (format!("<{tag}>"), format!("</{tag}>"));
    xml.split(&open).skip(1).filter_map(|s| s.split_once(&close).map(|(v, _)| v.to_string())).collect()
}

/// Incomplete multipart uploads in the bucket, by S3's own ListMultipartUploads.
fn incomplete_uploads(s3: &seaweedfs::SeaweedFs) -> Vec<String> {
    xml_values(&s3_api(s3, "?uploads="), "UploadId")
}

/// Starts `dev synth` writing one steps file of about 100 MB (parts of 8 MB) and stops it
/// (SIGSTOP) as soon as its multipart upload is recorded under `<prefix>/_uploads/`, where
/// `recorded` records were before.
fn writer_stopped_mid_upload(
    t: &Target,
    s3: &seaweedfs::SeaweedFs,
    prefix: &str,
    seed: &str,
    lease_seconds: &str,
    recorded: usize,
) -> std::process::Child {
    let child = t
        .command()
        .env("UFOPS_WRITER_LEASE_SECONDS", lease_seconds)
        .args(["dev", "synth", "--seed", seed, "--episodes", "10", "--steps", "300000"])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let records =
        || xml_values(&s3_api(s3, &format!("?list-type=2&prefix={prefix}%2F_uploads%2F")), "Key").len();
    let t0 = std::time::Instant::now();
    while records() <= recorded {
        assert!(t0.elapsed() < std::time::Duration::from_secs(180), "no multipart upload started");
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
    signal(&child, "-STOP");
    child
}

fn signal(child: &std::process::Child, sig: &str) {
    let ok = std::process::Command::new("kill").arg(sig).arg(child.id().to_string()).status().unwrap();
    assert!(ok.success(), "kill {sig}");
}

/// gc aborts the multipart upload of a writer killed mid-upload (S3 lists the upload before and
/// not after) and leaves alone the upload of a writer in flight, which then completes.
#[test]
fn gc_aborts_a_killed_writers_multipart_upload_and_spares_one_in_flight() {
    let dir = tempfile::tempdir().unwrap();
    let Some(s3) = seaweedfs::SeaweedFs::start_if_available() else { return };
    let mut t = Target::sqlite(dir.path());
    t.object_store = Some(format!("s3://{}/mp", seaweedfs::BUCKET));
    t.env = s3.env();
    t.ok(&["init"]);
    assert!(incomplete_uploads(&s3).is_empty());

    // Writer A renews its records every third of a 1 s lease: killed, they lapse at once.
    let mut a = writer_stopped_mid_upload(&t, &s3, "mp", "1", "1", 0);
    let killed = incomplete_uploads(&s3);
    assert_eq!(killed.len(), 1, "the killed writer's upload is listed by S3");
    a.kill().unwrap();
    a.wait().unwrap();
    // Writer B (the default 60 s lease) is stopped mid-upload, alive.
    let mut b = writer_stopped_mid_upload(&t, &s3, "mp", "2", "60", 1);
    assert_eq!(incomplete_uploads(&s3).len(), 2);
    std::thread::sleep(std::time::Duration::from_millis(1500)); // A's lease lapses

    let dry = t.json(&["gc", "--grace-seconds", "0", "--dry-run", "--json"]);
    assert_eq!(dry["uploads_aborted"].as_array().unwrap().len(), 1, "{dry}");
    assert_eq!(incomplete_uploads(&s3).len(), 2, "a dry run aborts nothing");
    let gc = t.json(&["gc", "--grace-seconds", "0", "--json"]);
    let aborted = gc["uploads_aborted"].as_array().unwrap();
    assert_eq!(aborted.len(), 1, "{gc}");
    assert!(aborted[0].as_str().unwrap().contains(&killed[0]), "{gc}");
    assert_eq!(gc["uploads_in_flight"].as_u64(), Some(1), "{gc}");
    let left = incomplete_uploads(&s3);
    assert_eq!(left.len(), 1, "{left:?}");
    assert_ne!(left[0], killed[0], "the killed writer's upload is gone, the live one's is not");

    // B goes on: its upload completes and its version commits.
    signal(&b, "-CONT");
    assert!(b.wait().unwrap().success());
    assert!(incomplete_uploads(&s3).is_empty());
    let report = t.json(&["dev", "verify"]);
    assert!(report["problems"].as_array().unwrap().is_empty(), "{report}");
    assert_eq!(report["versions"].as_u64(), Some(1), "{report}");
    let after = t.json(&["gc", "--grace-seconds", "0", "--dry-run", "--json"]);
    assert!(after["uploads_aborted"].as_array().unwrap().is_empty(), "{after}");
    assert_eq!(after["uploads_in_flight"].as_u64(), Some(0), "{after}");
}
