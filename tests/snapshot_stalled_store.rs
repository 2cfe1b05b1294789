//! A label snapshot writes its labels file before it takes the version lock: on
//! SQLite that lock stops every label write, so an object store that stalls (S3 under load, a
//! network hiccup) must not stop labeling. Here SeaweedFS is frozen (SIGSTOP) while a snapshot
//! uploads: label writes go on; once it resumes, the snapshot commits with the labels as of its
//! lock, the label written meanwhile included.

use crate::common;
use common::*;
use std::sync::mpsc;
use std::time::Duration;

fn signal(pid: u32, sig: &str) {
    let ok = std::process::Command::new("kill").args([sig, &pid.to_string()]).status().unwrap().success();
    assert!(ok, "kill {sig} {pid}");
}

/// Sets an episode's label through the API (If-Match from its current ETag).
fn put_label(url: &str, auth: &str, id: &str, label: &str) -> u16 {
    let ep = http(url, "GET", &format!("/v1/episodes/{id}"), &[("Authorization", auth)], None);
    let etag = ep.header("etag").expect("ETag").to_string();
    let body = serde_json::json!({ "label": label });
    http(
        url,
        "PUT",
        &format!("/v1/episodes/{id}/label"),
        &[("Authorization", auth), ("If-Match", &etag)],
        Some(&body),
    )
    .status
}

#[test]
fn labeling_goes_on_while_a_snapshot_uploads_to_a_stalled_object_store() {
    let dir = tempfile::tempdir().unwrap();
    let Some(s3) = seaweedfs::SeaweedFs::start_if_available() else { return };
    let mut t = Target::sqlite(dir.path());
    t.object_store = Some(format!("s3://{}/snapshot-ahead", seaweedfs::BUCKET));
    t.env = s3.env();
    t.ok(&["init"]);
    let fixture = fixtures().join("robomimic/lift_rollouts_lowdim.hdf5");
    t.ok(&["ingest", fixture.to_str().unwrap(), "--policy", "arm", "--checkpoint", "c1"]);
    let auth = t.bearer("ops", "admin");
    let server = t.serve(&[]);
    let url = server.url.clone();
    let listed = http(&url, "GET", "/v1/episodes?limit=2", &[("Authorization", &auth)], None);
    assert_eq!(listed.status, 200, "{}", String::from_utf8_lossy(&listed.body));
    let page = listed.json();
    let ids: Vec<String> =
        page["episodes"].as_array().unwrap().iter().map(|e| e["id"].as_str().unwrap().to_string()).collect();
    assert_eq!(ids.len(), 2, "{page}");
    let label_of = |e: &serde_json::Value| e["label"].as_str().unwrap().to_string();
    let flip = |l: &str| if l == "success" { "failure" } else { "success" };
    let first =
        http(&url, "GET", &format!("/v1/episodes/{}", ids[0]), &[("Authorization", &auth)], None).json();
    let second =
        http(&url, "GET", &format!("/v1/episodes/{}", ids[1]), &[("Authorization", &auth)], None).json();
    let (want0, want1) =
        (flip(&label_of(&first["episode"])).to_string(), flip(&label_of(&second["episode"])).to_string());
    assert_eq!(put_label(&url, &auth, &ids[0], &want0), 200);

    // Freeze the object store, then ask for a snapshot: its upload hangs.
    signal(s3.pid(), "-STOP");
    let (snap_tx, snap_rx) = mpsc::channel();
    {
        let (url, auth) = (url.clone(), auth.clone());
        std::thread::spawn(move || {
            let body = serde_json::json!({ "message": "while the store stalls" });
            let _ = snap_tx.send(http(
                &url,
                "POST",
                "/v1/label-snapshots",
                &[("Authorization", &auth)],
                Some(&body),
            ));
        });
    }
    std::thread::sleep(Duration::from_secs(2));
    // A label write meanwhile: answered while the store is still frozen.
    let (put_tx, put_rx) = mpsc::channel();
    {
        let (url, auth, id, want) = (url.clone(), auth.clone(), ids[1].clone(), want1.clone());
        std::thread::spawn(move || {
            let _ = put_tx.send(put_label(&url, &auth, &id, &want));
        });
    }
    let put = put_rx.recv_timeout(Duration::from_secs(20));
    assert!(snap_rx.try_recv().is_err(), "the snapshot finished while the object store was frozen");
    signal(s3.pid(), "-CONT");
    assert_eq!(put.expect("a label write waited 20 s on a snapshot's upload to a stalled object store"), 200);

    // The snapshot commits once the store answers, with both labels.
    let snap = snap_rx.recv_timeout(Duration::from_secs(120)).expect("the snapshot never finished");
    assert_eq!(snap.status, 201, "{}", String::from_utf8_lossy(&snap.body));
    let version = snap.json()["version"].as_i64().unwrap();
    let frozen = http(
        &url,
        "GET",
        &format!("/v1/episodes?limit=500&version={version}"),
        &[("Authorization", &auth)],
        None,
    )
    .json();
    let label_at = |id: &str| {
        frozen["episodes"]
            .as_array()
            .unwrap()
            .iter()
            .find(|e| e["id"] == id)
            .map(label_of)
            .unwrap_or_default()
    };
    assert_eq!(
        (label_at(&ids[0]), label_at(&ids[1])),
        (want0.clone(), want1.clone()),
        "labels frozen in version {version}"
    );
    // And a second snapshot with nothing changed is the same version (no new file, no new version).
    let again =
        http(&url, "POST", "/v1/label-snapshots", &[("Authorization", &auth)], Some(&serde_json::json!({})));
    assert_eq!((again.status, again.json()["version"].as_i64()), (200, Some(version)));
    drop(server);
}
