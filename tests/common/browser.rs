//! The browser tests' one harness: Debian's `chromium` driven by playwright-core from
//! `tests/web` (`node tests/web/<script>.mjs`). A script prints one `E2E_RESULT <json>` line with
//! what it saw and writes its screenshots to the artifacts directory
//! (`<target dir>/web-artifacts/`); the Rust test checks that result against the API.
//!
//! `scripts/test.sh` installs the prerequisites (`ensure_browser`) and sets
//! `UFOPS_REQUIRE_BROWSER=1`, which turns a missing one into a failure instead of a skip.

use std::path::PathBuf;
use std::process::{Command, Stdio};

use serde_json::Value;

use super::Server;

/// The repository's root (the root package's manifest directory).
pub fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// `$CHROMIUM`, else Debian's chromium.
pub fn chromium() -> Option<PathBuf> {
    if let Ok(p) = std::env::var("CHROMIUM") {
        return Some(PathBuf::from(p)).filter(|p| p.is_file());
    }
    ["/usr/bin/chromium", "/usr/bin/chromium-browser"].iter().map(PathBuf::from).find(|p| p.is_file())
}

/// What is missing to run a browser test, if anything.
fn missing_prerequisites() -> Vec<String> {
    let mut missing = Vec::new();
    if chromium().is_none() {
        missing.push(
            "chromium (apt-get install -y --no-install-recommends chromium, or set CHROMIUM)".to_string(),
        );
    }
    if Command::new("node").arg("--version").output().map(|o| !o.status.success()).unwrap_or(true) {
        missing.push("node (Node.js >= 20)".to_string());
    }
    if !repo().join("tests/web/node_modules/playwright-core/package.json").is_file() {
        missing.push("tests/web/node_modules (run `npm ci --no-audit --no-fund` in tests/web)".to_string());
    }
    missing
}

/// Whether the browser test may run: false (a skip) when something is missing, unless
/// `UFOPS_REQUIRE_BROWSER=1`, where a missing prerequisite fails the test.
pub fn available() -> bool {
    let missing = missing_prerequisites();
    let probe = if missing.is_empty() { Ok(()) } else { Err(missing.join("; ")) };
    store::test_support::require(store::test_support::Tool::Browser, probe)
}

/// Where the scripts write their screenshots: `<target dir>/web-artifacts/` (created).
pub fn artifacts_dir() -> PathBuf {
    // <target>/debug/deps/tests-HASH → <target>
    let target = std::env::var("CARGO_TARGET_DIR").map(PathBuf::from).unwrap_or_else(|_| {
        std::env::current_exe()
            .ok()
            .and_then(|p| p.ancestors().nth(3).map(PathBuf::from))
            .unwrap_or_else(|| repo().join("target"))
    });
    let dir = target.join("web-artifacts");
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Removes a screenshot a script is about to write, so [`assert_screenshot`] sees this run's.
pub fn forget_screenshot(name: &str) {
    let _ = std::fs::remove_file(artifacts_dir().join(name));
}

/// The screenshot `name` was written and holds a picture (not a blank page's few bytes).
pub fn assert_screenshot(name: &str) {
    let shot = artifacts_dir().join(name);
    assert!(std::fs::metadata(&shot).map(|m| m.len() > 10_000).unwrap_or(false), "{}", shot.display());
}

/// Runs `tests/web/<script>` against the server at `url` with `env` (besides `UFOPS_URL`,
/// `UFOPS_ARTIFACTS` and `CHROMIUM`), fails the test if the script fails, and returns its
/// `E2E_RESULT`.
pub fn run_script(script: &str, url: &str, env: &[(&str, String)]) -> Value {
    // One Chromium at a time: on two cores, two of them beside the other tests starve each
    // other's video playback, which the labeling test waits for.
    static ONE_BROWSER: std::sync::Mutex<()> = std::sync::Mutex::new(());
    let _turn = ONE_BROWSER.lock().unwrap_or_else(|e| e.into_inner());
    let out = Command::new("node")
        .arg(repo().join("tests/web").join(script))
        .current_dir(repo().join("tests/web"))
        .env("UFOPS_URL", url)
        .env("UFOPS_ARTIFACTS", artifacts_dir())
        .env("CHROMIUM", chromium().expect("chromium"))
        .envs(env.iter().map(|(k, v)| (*k, v.as_str())))
        .stderr(Stdio::inherit())
        .output()
        .unwrap_or_else(|e| panic!("run node tests/web/{script}: {e}"));
    let stdout = String::from_utf8_lossy(&out.stdout);
    println!("{stdout}");
    assert!(
        out.status.success(),
        "the browser test {script} failed (screenshots in {})",
        artifacts_dir().display()
    );
    let line = stdout
        .lines()
        .find_map(|l| l.strip_prefix("E2E_RESULT "))
        .unwrap_or_else(|| panic!("{script} printed no E2E_RESULT line"));
    serde_json::from_str(line).unwrap_or_else(|e| panic!("{script}'s E2E_RESULT is not JSON ({e}): {line}"))
}

/// One JSON request as `token` (empty: none): the status and the body (a JSON value, or the text
/// as a JSON string when it is not JSON).
pub fn api(srv: &Server, method: &str, path: &str, token: &str, body: Option<&str>) -> (u16, Value) {
    let auth = format!("Bearer {token}");
    let mut headers = vec![("Accept", "application/json")];
    if !token.is_empty() {
        headers.push(("Authorization", auth.as_str()));
    }
    let body = body.unwrap_or("").as_bytes();
    let ctype = (!body.is_empty()).then_some("application/json");
    let r = super::http_bytes(&srv.url, method, path, &headers, body, ctype);
    let value = serde_json::from_slice(&r.body)
        .unwrap_or_else(|_| Value::String(String::from_utf8_lossy(&r.body).into_owned()));
    (r.status, value)
}

/// The names and kinds (`image`, `video`) of an episode detail's cameras.
pub fn cameras(detail: &Value) -> Vec<(String, String)> {
    detail["cameras"]
        .as_array()
        .unwrap_or_else(|| panic!("no cameras in {detail}"))
        .iter()
        .map(|c| (c["name"].as_str().unwrap().to_string(), c["kind"].as_str().unwrap().to_string()))
        .collect()
}
