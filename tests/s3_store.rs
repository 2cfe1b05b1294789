//! The scale-out store for real: a Postgres catalog and objects in S3 (SeaweedFS started here),
//! through the `ufops` binary: ingest with videos, dedup, read back, train, download an artifact
//! with checked sha256s, gc.

mod common;
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
    let expected: serde_json::Value =
        serde_json::from_slice(&std::fs::read(fixtures().join("lerobot/v30_eval_video.expected.json")).unwrap())
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
    std::fs::write(&cfg, r#"{"epochs": 2, "batch_size": 64}"#).unwrap();
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
    let other = s3_target(tempfile::tempdir().unwrap().path(), &s3, "other").expect("Postgres answered above");
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
