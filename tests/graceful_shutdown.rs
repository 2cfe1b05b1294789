//! SIGTERM (what `docker stop`, systemd and Kubernetes send) stops `ufops worker` and `ufops serve`
//! gracefully: exit status 0, and a job in the middle of running is given back at once (queued
//! again, the attempt not counted) instead of looking "running" until its lease runs out.

use crate::common;
use common::*;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// A child killed when the test ends, also when an assertion fails (a worker left behind would
/// go on training for hours).
struct Killed(Child);
impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn sigterm_and_wait(child: &mut Child, within: Duration) -> std::process::ExitStatus {
    let status = Command::new("kill").args(["-TERM", &child.id().to_string()]).status().unwrap();
    assert!(status.success());
    let t0 = Instant::now();
    loop {
        if let Some(s) = child.try_wait().unwrap() {
            return s;
        }
        assert!(t0.elapsed() < within, "still running {within:?} after SIGTERM");
        std::thread::sleep(Duration::from_millis(50));
    }
}

#[test]
fn sigterm_stops_gracefully_and_releases_the_running_job() {
    let dir = tempfile::tempdir().unwrap();
    let t = Target::sqlite(dir.path());
    t.ok(&["init"]);
    t.ok(&["dev", "synth", "--episodes", "40", "--steps", "30", "--seed", "3"]);
    let split = t.json(&["split", "create", "--policy", "synth", "--checkpoint", "ckpt-0", "--json"]);
    let auth = t.bearer("ops", "trainer");
    let mut server = t.serve(&["--no-worker"]);
    let url = server.url.clone();
    // A job long enough to be running when the worker is stopped.
    let body = serde_json::json!({"split_id": split["id"], "kind": "classifier", "chunk_len": 16, "config": {"epochs": 100000}});
    let r = http(&url, "POST", "/v1/jobs", &[("Authorization", &auth)], Some(&body));
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let id = r.json()["id"].as_str().unwrap().to_string();
    let job = || http(&url, "GET", &format!("/v1/jobs/{id}"), &[("Authorization", &auth)], None).json();

    let mut worker = Killed(
        t.command()
            .args(["worker", "--lease-ms", "3000"])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap(),
    );
    let t0 = Instant::now();
    loop {
        let j = job();
        if j["state"] == "running" && j["progress"]["epoch"].as_u64().unwrap_or(0) >= 1 {
            break;
        }
        assert!(t0.elapsed() < Duration::from_secs(60), "the job never ran: {j}");
        std::thread::sleep(Duration::from_millis(100));
    }
    let status = sigterm_and_wait(&mut worker.0, Duration::from_secs(15));
    assert!(status.success(), "worker exit after SIGTERM: {status:?}");
    // Given back (an expired lease would leave it `running` until another worker claims it),
    // the attempt not counted.
    let j = job();
    assert_eq!(j["state"], "queued", "{j}");
    assert_eq!(j["attempts"], 0, "{j}");
    assert!(j["worker"].is_null(), "{j}");

    // The server stops the same way.
    let r = http(&url, "POST", &format!("/v1/jobs/{id}/cancel"), &[("Authorization", &auth)], None);
    assert_eq!(r.status, 200);
    let status = sigterm_and_wait(server.child_mut(), Duration::from_secs(15));
    assert!(status.success(), "serve exit after SIGTERM: {status:?}");
}
