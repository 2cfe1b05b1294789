//! The robot side pulls a verifier from `ufops serve` by alias: the steering client's HTTP loader
//! gets the same artifact, bit for bit, as a download from the store, and `ufops score --api`
//! scores exactly like `ufops score` on the store; bad tokens and unknown aliases are clear errors.

mod common;
use common::*;
use std::io::{BufRead, BufReader};
use std::process::{Child, Stdio};

struct Server(Child);
impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn start_server(t: &Target) -> (Server, String) {
    let mut child = t
        .command()
        .args(["serve", "--addr", "127.0.0.1:0", "--no-worker"])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let stdout = child.stdout.take().unwrap();
    let server = Server(child);
    let mut line = String::new();
    BufReader::new(stdout).read_line(&mut line).unwrap();
    let url = line.trim().strip_prefix("listening on ").unwrap_or_else(|| panic!("unexpected: {line:?}")).to_string();
    (server, url)
}

#[test]
fn verifier_loads_over_http_like_from_the_store() {
    let dir = tempfile::tempdir().unwrap();
    let t = Target::sqlite(dir.path());
    t.ok(&["init"]);
    t.ok(&["dev", "synth", "--episodes", "40", "--steps", "30", "--seed", "3"]);
    let split = t.json(&["split", "create", "--policy", "synth", "--checkpoint", "ckpt-0", "--json"]);
    let cfg = dir.path().join("train.json");
    std::fs::write(&cfg, r#"{"epochs": 2}"#).unwrap();
    t.ok(&["train", "--split", split["id"].as_str().unwrap(), "--kind", "classifier", "--config", cfg.to_str().unwrap()]);
    let local = dir.path().join("local");
    t.ok(&["artifacts", "download", "synth/ckpt-0/classifier@latest", local.to_str().unwrap()]);
    let token = t.json(&["token", "create", "--name", "robot-7", "--role", "viewer", "--json"]);
    let token = token["token"].as_str().unwrap_or_else(|| panic!("no token in {token}")).to_string();

    let (_server, url) = start_server(&t);
    let src = steer::http::ApiSource::new(&url, &token);
    let fetched = steer::http::fetch_artifact(&src, "synth/ckpt-0/classifier@latest").unwrap();
    for (name, bytes) in &fetched.files {
        assert_eq!(bytes, &std::fs::read(local.join(name)).unwrap(), "{name} differs from the store's copy");
    }
    let remote = steer::Verifier::load_http(&src, "synth/ckpt-0/classifier@latest").unwrap();
    let from_dir = steer::Verifier::load_dir(&local).unwrap();
    assert_eq!(remote.id(), from_dir.id());
    // By id as well.
    let by_id = steer::Verifier::load_http(&src, remote.id().unwrap()).unwrap();
    assert_eq!(by_id.id(), remote.id());

    // Same scores through the CLI, local and remote.
    let c = remote.config();
    let rows: Vec<_> = (0..5)
        .map(|i| {
            let obs: Vec<f32> = (0..c.obs_dim()).map(|k| ((i * 7 + k) as f32 * 0.37).sin()).collect();
            let action: Vec<f32> = (0..c.act_dim()).map(|k| ((i * 3 + k) as f32 * 0.21).cos()).collect();
            serde_json::json!({"obs": obs, "action": action, "t": i * 4})
        })
        .collect();
    let input = dir.path().join("rows.json");
    std::fs::write(&input, serde_json::json!({ "rows": rows }).to_string()).unwrap();
    let input_s = input.to_str().unwrap();
    let a = t.json(&["score", "--artifact", "synth/ckpt-0/classifier@latest", "--input", input_s]);
    let b = t.json(&["score", "--artifact", "synth/ckpt-0/classifier@latest", "--input", input_s, "--api", &url, "--token", &token]);
    assert_eq!(a, b);
    assert_eq!(a["scores"].as_array().unwrap().len(), 5);

    // A wrong token and an unknown alias: clear errors, nothing loaded.
    let bad = steer::http::ApiSource::new(&url, "not-a-token");
    let err = steer::Verifier::load_http(&bad, "synth/ckpt-0/classifier@latest").err().unwrap().to_string();
    assert!(err.contains("401"), "{err}");
    let err = steer::Verifier::load_http(&src, "synth/ckpt-0/classifier@nope").err().unwrap().to_string();
    assert!(err.contains("404") && err.contains("nope"), "{err}");
    let out = t.run(&["score", "--artifact", "synth/ckpt-0/q@latest", "--input", input_s, "--api", &url, "--token", &token]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("404"), "{}", String::from_utf8_lossy(&out.stderr));
}
