//! The webhook receiver api/README.md documents (ten lines of Python's standard library) is run
//! as written against `ufops serve`: it accepts the server's signed deliveries, prints each
//! with its delivery id, and refuses a delivery whose signature is forged. Also `ufops events`
//! prints the same events from the store and from the server.

use crate::common;
use common::*;
use std::io::BufRead;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// The Python block after the `<!-- webhook-receiver -->` marker.
fn receiver_source() -> String {
    let readme =
        std::fs::read_to_string(std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("api/README.md"))
            .unwrap();
    let at = readme.find("<!-- webhook-receiver -->").expect("the receiver's marker in api/README.md");
    let block = &readme[at..];
    let start = block.find("```python\n").unwrap() + "```python\n".len();
    let end = block[start..].find("```").unwrap();
    block[start..start + end].to_string()
}

#[test]
fn documented_receiver_verifies_deliveries_and_events_follow() {
    let source = receiver_source();
    assert!(source.lines().count() <= 11, "the example grew: {} lines", source.lines().count());
    let dir = tempfile::tempdir().unwrap();
    let t = Target::sqlite(dir.path());
    t.ok(&["init"]);
    t.ok(&["dev", "synth", "--episodes", "4", "--steps", "10", "--seed", "2"]);
    let admin = t.bearer("ops", "admin");
    let server = t.serve(&["--no-worker"]);
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let hook_url = format!("http://127.0.0.1:{port}/");
    let body = serde_json::json!({"url": hook_url, "kinds": ["label.set"]});
    let r = http(&server.url, "POST", "/v1/webhooks", &[("Authorization", &admin)], Some(&body));
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let created = r.json();
    let secret = created["secret"].as_str().unwrap();
    let script = dir.path().join("receiver.py");
    std::fs::write(&script, &source).unwrap();
    let mut receiver = Command::new("python3")
        .arg(&script)
        .env("UFOPS_WEBHOOK_SECRET", secret)
        .env("PORT", port.to_string())
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("python3");
    let wait_port = Instant::now();
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(wait_port.elapsed() < Duration::from_secs(20), "the receiver never listened");
        std::thread::sleep(Duration::from_millis(50));
    }
    // A forged delivery is refused.
    let forged = http_bytes(
        &hook_url,
        "POST",
        "",
        &[("Ufops-Signature", "t=1700000000,v1=00"), ("Ufops-Delivery", "x-1")],
        b"{}",
        Some("application/json"),
    );
    assert_eq!(forged.status, 401);

    // A label change is delivered, signed, and the receiver prints it.
    let episodes = t.json(&["episodes", "--json"]);
    let id = episodes[0]["id"].as_str().unwrap();
    t.ok(&["label", id, "failure"]);
    let stdout = receiver.stdout.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in std::io::BufReader::new(stdout).lines().map_while(Result::ok) {
            let _ = tx.send(line);
        }
    });
    let line = rx.recv_timeout(Duration::from_secs(30)).expect("the receiver printed no delivery");
    let _ = receiver.kill();
    let _ = receiver.wait();
    let (delivery, event) = line.split_once(' ').unwrap();
    let event: serde_json::Value = serde_json::from_str(event).unwrap();
    assert_eq!(event["kind"], "label.set");
    assert_eq!(event["subject"], id);
    assert_eq!(delivery, format!("{}-{}", created["webhook"]["id"].as_str().unwrap(), event["seq"]));

    // `ufops events`, from the store and from the server, prints that event.
    let from_store = t.ok(&["events", "--kind", "label.set", "--json"]);
    let lines: Vec<serde_json::Value> =
        from_store.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(lines, vec![event.clone()]);
    let token = admin.strip_prefix("Bearer ").unwrap();
    let from_api = t.ok(&["events", "--kind", "label.set", "--json", "--api", &server.url, "--token", token]);
    assert_eq!(
        from_api.lines().next().map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap()),
        Some(event.clone())
    );
    // --follow waits for the next one: started, then a change, then it prints it.
    let mut follow = t
        .command()
        .args(["events", "--follow", "--kind", "label.set", "--limit", "1"])
        .args(["--after", &event["seq"].to_string()])
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_millis(500));
    t.ok(&["label", id, "success"]);
    let out = std::io::BufReader::new(follow.stdout.take().unwrap()).lines().next().unwrap().unwrap();
    assert!(out.contains("label.set") && out.contains(id), "{out}");
    assert!(follow.wait().unwrap().success());
}
