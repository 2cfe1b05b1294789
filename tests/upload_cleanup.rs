//! Uploads do not pile up on the server's disk: `POST /v1/ingest` leaves no folder behind once its
//! job has finished, whether the ingest succeeded or failed, and the server sweeps at start the
//! folders nobody will ingest (no job names them and they are old), keeping a young one.

use crate::common;
use common::*;
use std::process::Command;
use std::time::{Duration, Instant};

fn wait_job(url: &str, auth: &str, id: &str) -> serde_json::Value {
    let t0 = Instant::now();
    loop {
        let j = http(url, "GET", &format!("/v1/jobs/{id}"), &[("Authorization", auth)], None).json();
        if j["state"] != "queued" && j["state"] != "running" {
            return j;
        }
        assert!(t0.elapsed() < Duration::from_secs(60), "job {id} stuck: {j}");
        std::thread::sleep(Duration::from_millis(100));
    }
}

fn folders(dir: &std::path::Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .map(|rd| rd.flatten().map(|e| e.file_name().to_string_lossy().into_owned()).collect())
        .unwrap_or_default();
    v.sort();
    v
}

#[test]
fn finished_uploads_are_deleted_and_stale_ones_swept() {
    let dir = tempfile::tempdir().unwrap();
    let t = Target::sqlite(dir.path());
    t.ok(&["init"]);
    let uploads = dir.path().join("uploads");
    // Left by an earlier server: one old folder no job names, one young one (an upload whose job
    // is about to be queued).
    let old = uploads.join("0123456789abcdef0123456789abcdef");
    let young = uploads.join("fedcba9876543210fedcba9876543210");
    for d in [&old, &young] {
        std::fs::create_dir_all(d).unwrap();
        std::fs::write(d.join("x.hdf5"), b"x").unwrap();
    }
    assert!(Command::new("touch").args(["-d", "3 hours ago"]).arg(&old).status().unwrap().success());
    let auth = t.bearer("ops", "admin");
    let server = t.serve(&[]);
    let url = server.url.as_str();
    let t0 = Instant::now();
    while old.exists() {
        assert!(t0.elapsed() < Duration::from_secs(10), "the stale upload was not swept");
        std::thread::sleep(Duration::from_millis(100));
    }
    assert!(young.exists(), "a young upload folder is kept");

    // A good file and a broken one: both jobs end, neither folder stays.
    let good = std::fs::read(fixtures().join("robomimic/lift_rollouts_lowdim.hdf5")).unwrap();
    let mut broken = good.clone();
    broken.truncate(4096);
    for (body, want) in [(&good, "succeeded"), (&broken, "failed")] {
        let r = http_bytes(
            url,
            "POST",
            "/v1/ingest?policy=bc&checkpoint=e600&filename=lift.hdf5",
            &[("Authorization", &auth)],
            body,
            Some("application/octet-stream"),
        );
        assert_eq!(r.status, 202, "{}", String::from_utf8_lossy(&r.body));
        let job = r.json();
        let done = wait_job(url, &auth, job["id"].as_str().unwrap());
        assert_eq!(done["state"], want, "{done}");
        let t0 = Instant::now();
        while folders(&uploads) != vec!["fedcba9876543210fedcba9876543210".to_string()] {
            assert!(t0.elapsed() < Duration::from_secs(5), "upload left behind: {:?}", folders(&uploads));
            std::thread::sleep(Duration::from_millis(50));
        }
    }
    let eps = t.json(&["episodes", "--json"]);
    assert_eq!(eps.as_array().unwrap().len(), 12);

    // An upload the disk cannot take (a petabyte declared) is refused before a byte is written.
    use std::io::{Read, Write};
    let addr = url.trim_start_matches("http://");
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    write!(s, "POST /v1/ingest?policy=bc&checkpoint=big HTTP/1.1\r\nHost: {addr}\r\nAuthorization: {auth}\r\n\
        Content-Type: application/octet-stream\r\nContent-Length: 1000000000000000\r\nConnection: close\r\n\r\n").unwrap();
    s.write_all(&[0u8; 1024]).unwrap();
    let mut raw = Vec::new();
    let _ = s.read_to_end(&mut raw);
    let text = String::from_utf8_lossy(&raw);
    assert!(text.starts_with("HTTP/1.1 507"), "{text}");
    assert!(text.contains("free for uploads"), "{text}");
    assert_eq!(folders(&uploads), vec!["fedcba9876543210fedcba9876543210".to_string()]);
}
