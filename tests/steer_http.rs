//! The robot side pulls a verifier from `ufops serve` by alias: the steering client's HTTP loader
//! gets the same artifact, bit for bit, as a download from the store; the robot's scores and
//! gradients (steer, over HTTP) equal what `ufops score` prints from the store and from the API,
//! and the trainer's candle graph (an independent implementation); bad tokens and unknown
//! aliases are clear errors.

use crate::common;
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
    let url = line
        .trim()
        .strip_prefix("listening on ")
        .unwrap_or_else(|| panic!("unexpected: {line:?}"))
        .to_string();
    (server, url)
}

#[test]
fn verifier_loads_over_http_like_from_the_store() {
    let dir = tempfile::tempdir().unwrap();
    let t = Target::sqlite(dir.path());
    t.ok(&["init"]);
    t.ok(&["dev", "synth", "--episodes", "40", "--steps", "30", "--seed", "3"]);
    t.train("synth", "ckpt-0", "classifier", r#"{"epochs": 2}"#, &["--chunk-len", "16"]);
    let local = dir.path().join("local");
    t.ok(&["artifacts", "download", "synth/ckpt-0/classifier@latest", local.to_str().unwrap()]);
    let token = t.token("robot-7", "viewer");

    let (_server, url) = start_server(&t);
    let src = steer::http::ApiSource::new(&url, &token);
    let fetched = steer::http::fetch_artifact(&src, "synth/ckpt-0/classifier@latest").unwrap();
    for (name, bytes) in &fetched.files {
        assert_eq!(bytes, &std::fs::read(local.join(name)).unwrap(), "{name} differs from the store's copy");
    }
    let remote = steer::http::load_verifier(&src, "synth/ckpt-0/classifier@latest").unwrap();
    let from_dir = steer::Verifier::load_dir(&local).unwrap();
    assert_eq!(remote.id(), from_dir.id());
    // By id as well.
    let by_id = steer::http::load_verifier(&src, remote.id().unwrap()).unwrap();
    assert_eq!(by_id.id(), remote.id());

    // The robot's scores and gradients (steer's Scorer, loaded over HTTP)...
    let (od, ad) = (remote.obs_dim(), remote.act_dim());
    let n = 5;
    let obs: Vec<f32> = (0..n * od).map(|k| (k as f32 * 0.37).sin()).collect();
    let act: Vec<f32> = (0..n * ad).map(|k| (k as f32 * 0.21).cos()).collect();
    let steps: Vec<u32> = (0..n as u32).map(|i| i * 4).collect();
    let robot = steer::Scorer::score_batch(&remote, &obs, &steps, &act, 1).unwrap();
    let robot_grad = steer::Scorer::grad_batch(&remote, &obs, &steps, &act).unwrap();
    let rows: Vec<trainer::ScoreRow> = (0..n)
        .map(|i| trainer::ScoreRow {
            obs: obs[i * od..(i + 1) * od].to_vec(),
            action: act[i * ad..(i + 1) * ad].to_vec(),
            t: steps[i] as f64,
            extras: Default::default(),
        })
        .collect();
    let input = dir.path().join("rows.json");
    std::fs::write(&input, serde_json::json!({ "rows": rows }).to_string()).unwrap();
    let input_s = input.to_str().unwrap();
    // ...equal `ufops score` on the store and through the API...
    let a = t.json(&["score", "--artifact", "synth/ckpt-0/classifier@latest", "--input", input_s, "--grad"]);
    let b = t.json(&[
        "score",
        "--artifact",
        "synth/ckpt-0/classifier@latest",
        "--input",
        input_s,
        "--grad",
        "--api",
        &url,
        "--token",
        &token,
    ]);
    // ...and the trainer's candle graph with autograd (an independent implementation).
    let (candle, candle_grad) =
        trainer::load_artifact(&local).unwrap().candle_scores_and_grads(&rows).unwrap();
    let floats = |v: &serde_json::Value| -> Vec<f32> {
        v.as_array().unwrap().iter().map(|x| x.as_f64().unwrap() as f32).collect()
    };
    for (name, scores, grads) in [
        (
            "ufops score",
            floats(&a["scores"]),
            a["grads"].as_array().unwrap().iter().flat_map(&floats).collect::<Vec<_>>(),
        ),
        (
            "ufops score --api",
            floats(&b["scores"]),
            b["grads"].as_array().unwrap().iter().flat_map(floats).collect(),
        ),
        ("candle", candle.clone(), candle_grad.iter().flatten().copied().collect()),
    ] {
        assert_eq!(scores.len(), n, "{name}");
        for (x, y) in scores.iter().zip(&robot) {
            assert!((x - y).abs() <= 1e-5, "{name}: score {x} vs robot {y}");
        }
        assert_eq!(grads.len(), n * ad, "{name}");
        for (x, y) in grads.iter().zip(&robot_grad) {
            assert!((x - y).abs() <= 1e-5 * y.abs().max(1.0), "{name}: gradient {x} vs robot {y}");
        }
    }
    assert!(robot_grad.iter().any(|g| g.abs() > 1e-4), "the gradient is trivially zero");
    assert_eq!(a["artifact"], remote.id().unwrap());

    // A wrong token and an unknown alias: clear errors, nothing loaded.
    let bad = steer::http::ApiSource::new(&url, "not-a-token");
    let err = steer::http::load_verifier(&bad, "synth/ckpt-0/classifier@latest").err().unwrap().to_string();
    assert!(err.contains("401"), "{err}");
    let err = steer::http::load_verifier(&src, "synth/ckpt-0/classifier@nope").err().unwrap().to_string();
    assert!(err.contains("404") && err.contains("nope"), "{err}");
    let out = t.run(&[
        "score",
        "--artifact",
        "synth/ckpt-0/q@latest",
        "--input",
        input_s,
        "--api",
        &url,
        "--token",
        &token,
    ]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("404"), "{}", String::from_utf8_lossy(&out.stderr));
}
