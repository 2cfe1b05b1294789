//! Helpers for the end-to-end tests: run the real `ufops` binary against a store.
#![allow(dead_code)]

pub mod browser;
pub mod seaweedfs;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

pub fn bin() -> PathBuf {
    PathBuf::from(env!("CARGO_BIN_EXE_ufops"))
}

/// A store location: a data dir and optionally a Postgres catalog.
#[derive(Clone)]
pub struct Target {
    pub data_dir: PathBuf,
    pub database_url: Option<String>,
    /// `s3://bucket/prefix` (with `env` holding the endpoint and keys); None: the local directory.
    pub object_store: Option<String>,
    pub env: Vec<(&'static str, String)>,
}

impl Target {
    pub fn sqlite(dir: &Path) -> Target {
        Target { data_dir: dir.to_path_buf(), database_url: None, object_store: None, env: Vec::new() }
    }

    pub fn command(&self) -> Command {
        let mut c = Command::new(bin());
        c.arg("--data-dir").arg(&self.data_dir);
        if let Some(u) = &self.database_url {
            c.arg("--database-url").arg(u);
        }
        c.env_remove("UFOPS_DATABASE_URL").env_remove("UFOPS_OBJECT_STORE").env("CI", "true");
        if let Some(o) = &self.object_store {
            c.arg("--object-store").arg(o);
        }
        c.envs(self.env.iter().map(|(k, v)| (*k, v.as_str())));
        c
    }

    pub fn run(&self, args: &[&str]) -> Output {
        self.command().args(args).output().expect("run ufops")
    }

    /// Runs a command that must succeed and returns its stdout parsed as JSON.
    pub fn json(&self, args: &[&str]) -> serde_json::Value {
        let out = self.run(args);
        assert!(
            out.status.success(),
            "ufops {args:?} failed: {}\n{}",
            String::from_utf8_lossy(&out.stderr),
            String::from_utf8_lossy(&out.stdout)
        );
        serde_json::from_slice(&out.stdout).unwrap_or_else(|e| {
            panic!("ufops {args:?} printed no JSON ({e}): {}", String::from_utf8_lossy(&out.stdout))
        })
    }

    pub fn ok(&self, args: &[&str]) -> String {
        let out = self.run(args);
        assert!(out.status.success(), "ufops {args:?} failed: {}", String::from_utf8_lossy(&out.stderr));
        String::from_utf8_lossy(&out.stdout).into_owned()
    }

    /// The secret of a new token for user `name` with `role`.
    pub fn token(&self, name: &str, role: &str) -> String {
        let v = self.json(&["token", "create", "--name", name, "--role", role, "--json"]);
        v["token"].as_str().unwrap_or_else(|| panic!("no token in {v}")).to_string()
    }

    /// [`Target::token`] as an `Authorization` header's value.
    pub fn bearer(&self, name: &str, role: &str) -> String {
        format!("Bearer {}", self.token(name, role))
    }

    /// A split of `policy`/`checkpoint` and a `kind` verifier trained on it with `recipe` (the
    /// JSON of a `--config` file) and the `extra` flags; returns the artifact `train --json`
    /// prints.
    pub fn train(
        &self,
        policy: &str,
        checkpoint: &str,
        kind: &str,
        recipe: &str,
        extra: &[&str],
    ) -> serde_json::Value {
        let split = self.json(&["split", "create", "--policy", policy, "--checkpoint", checkpoint, "--json"]);
        let cfg = self.data_dir.join(format!("recipe-{}.json", &store::sha256_hex(recipe.as_bytes())[..12]));
        std::fs::write(&cfg, recipe).unwrap();
        let split = split["id"].as_str().expect("a split id");
        let mut args =
            vec!["train", "--split", split, "--kind", kind, "--config", cfg.to_str().unwrap(), "--json"];
        args.extend_from_slice(extra);
        self.json(&args)
    }
}

/// A store with a Postgres catalog on a fresh schema; None (after a skip notice) when the test
/// Postgres is unreachable and `UFOPS_REQUIRE_POSTGRES` is not set (set: the test fails).
pub fn postgres_target(dir: &Path) -> Option<Target> {
    if !store::test_support::require_postgres() {
        return None;
    }
    let rt = tokio::runtime::Runtime::new().unwrap();
    let url = rt
        .block_on(store::create_test_schema("e2e"))
        .expect("the Postgres tests need the server at 127.0.0.1:5432 (UFOPS_TEST_POSTGRES)");
    Some(Target { data_dir: dir.to_path_buf(), database_url: Some(url), object_store: None, env: Vec::new() })
}

/// Every file under the local object directory, relative to it.
pub fn object_files(data_dir: &Path) -> Vec<String> {
    fn walk(root: &Path, dir: &Path, out: &mut Vec<String>) {
        for e in std::fs::read_dir(dir).unwrap().flatten() {
            let p = e.path();
            if p.is_dir() {
                walk(root, &p, out);
            } else {
                out.push(p.strip_prefix(root).unwrap().to_string_lossy().into_owned());
            }
        }
    }
    let root = data_dir.join("objects");
    let mut out = Vec::new();
    if root.exists() {
        walk(&root, &root, &mut out);
    }
    out.sort();
    out
}

/// The fixtures: `$UFOPS_FIXTURES`, else the repository's own `fixtures/` (see its README).
pub fn fixtures() -> PathBuf {
    std::env::var("UFOPS_FIXTURES")
        .map(PathBuf::from)
        .unwrap_or_else(|_| Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures"))
}

/// A running `ufops serve` (killed when dropped) and its base URL.
pub struct Server {
    child: std::process::Child,
    pub url: String,
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Server {
    pub fn child_mut(&mut self) -> &mut std::process::Child {
        &mut self.child
    }
}

impl Target {
    /// Starts `ufops serve` on a free port (with its in-process worker unless `extra` says
    /// otherwise) and waits for its "listening on" line.
    pub fn serve(&self, extra: &[&str]) -> Server {
        use std::io::BufRead;
        let mut child = self
            .command()
            .args(["serve", "--addr", "127.0.0.1:0"])
            .args(extra)
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::null())
            .spawn()
            .expect("start ufops serve");
        let stdout = child.stdout.take().unwrap();
        let mut line = String::new();
        std::io::BufReader::new(stdout).read_line(&mut line).unwrap();
        let url = line
            .trim()
            .strip_prefix("listening on ")
            .unwrap_or_else(|| panic!("unexpected: {line:?}"))
            .to_string();
        Server { child, url }
    }
}

/// A response of [`http`]: status code, headers (lower-case names), body.
pub struct HttpResponse {
    pub status: u16,
    pub headers: Vec<(String, String)>,
    pub body: Vec<u8>,
}

impl HttpResponse {
    pub fn json(&self) -> serde_json::Value {
        serde_json::from_slice(&self.body)
            .unwrap_or_else(|e| panic!("not JSON ({e}): {}", String::from_utf8_lossy(&self.body)))
    }
    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers.iter().find(|(k, _)| k == name).map(|(_, v)| v.as_str())
    }
}

/// One request to a server of [`Target::serve`], with a JSON body if any.
pub fn http(
    url: &str,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: Option<&serde_json::Value>,
) -> HttpResponse {
    let body = body.map(|b| b.to_string()).unwrap_or_default();
    let ctype = (!body.is_empty()).then_some("application/json");
    http_bytes(url, method, path, headers, body.as_bytes(), ctype)
}

/// [`http`] with a raw body. The tests' one HTTP client is reqwest's (the API crate's tests use
/// its async side): redirects are not followed, nothing times out, and no connection is reused
/// (each request is the server's only work from that socket, as a load test wants).
pub fn http_bytes(
    url: &str,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: &[u8],
    content_type: Option<&str>,
) -> HttpResponse {
    static CLIENT: std::sync::OnceLock<reqwest::blocking::Client> = std::sync::OnceLock::new();
    let client = CLIENT.get_or_init(|| {
        reqwest::blocking::Client::builder()
            .redirect(reqwest::redirect::Policy::none())
            .timeout(None)
            .pool_max_idle_per_host(0)
            .build()
            .expect("an HTTP client")
    });
    let method = reqwest::Method::from_bytes(method.as_bytes()).expect("an HTTP method");
    let mut req = client.request(method, format!("{}{path}", url.trim_end_matches('/'))).body(body.to_vec());
    if let Some(ct) = content_type {
        req = req.header("Content-Type", ct);
    }
    for (k, v) in headers {
        req = req.header(*k, *v);
    }
    match req.send() {
        Ok(r) => {
            let status = r.status().as_u16();
            let headers = r
                .headers()
                .iter()
                .map(|(k, v)| (k.as_str().to_string(), String::from_utf8_lossy(v.as_bytes()).into_owned()))
                .collect();
            // A body cut short still says what the server answered.
            let body = r.bytes().map(|b| b.to_vec()).unwrap_or_default();
            HttpResponse { status, headers, body }
        }
        // No response at all (status 0): the connection was closed on us (a server refusing a
        // body it will not read may close before the request is sent).
        Err(e) => {
            HttpResponse { status: 0, headers: Vec::new(), body: format!("no response: {e}").into_bytes() }
        }
    }
}

/// `ufops rank`'s score of each of the `bc` episodes by `artifact` (the scores the review
/// queue must store: one scoring definition).
#[allow(dead_code)]
pub fn rank_scores(t: &Target, artifact: &str) -> std::collections::HashMap<String, f64> {
    let ranked = t.json(&["rank", "--artifact", artifact, "--policy", "bc", "--json"]);
    ranked["episodes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| (r["episode_id"].as_str().unwrap().to_string(), r["score"].as_f64().unwrap()))
        .collect()
}

/// The robomimic low-dim Lift rollouts (12, 7 successes) ingested as `bc/e600` with their
/// success labels, and a classifier trained on them; returns the artifact's alias reference.
/// Real rollouts give a classifier that separates successes from failures (random synthetic
/// episodes do not), so score thresholds such as 0.5 split them.
pub fn lift_with_classifier(t: &Target) -> (&'static str, usize) {
    let f = fixtures().join("robomimic");
    t.ok(&[
        "ingest",
        f.join("lift_rollouts_lowdim.hdf5").to_str().unwrap(),
        "--policy",
        "bc",
        "--checkpoint",
        "e600",
        "--success-file",
        f.join("lift_rollouts_lowdim.success.json").to_str().unwrap(),
    ]);
    t.train("bc", "e600", "classifier", r#"{"epochs": 60, "batch_size": 256}"#, &["--chunk-len", "16"]);
    ("bc/e600/classifier@latest", 12)
}
