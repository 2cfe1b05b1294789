//! The API contract: the committed `api/openapi.json` is the document `ufops serve`
//! serves; schemathesis (all checks, every phase including the stateful one) finds no response
//! that breaks it on a server with real data (the robomimic Lift rollouts with a classifier
//! trained on them, a LeRobot evaluation with its videos) but the two kinds the contract accepts;
//! and pydantic models generated from it parse every response of the end-to-end flow.

use crate::common;
use common::*;
use std::path::Path;

const REGENERATE: &str = "cargo run --bin ufops -- openapi --write api/openapi.json";

fn committed() -> serde_json::Value {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("api/openapi.json");
    let text = std::fs::read_to_string(&path)
        .unwrap_or_else(|e| panic!("{}: {e}; regenerate it with `{REGENERATE}`", path.display()));
    serde_json::from_str(&text)
        .unwrap_or_else(|e| panic!("{}: {e}; regenerate it with `{REGENERATE}`", path.display()))
}

/// A store with real data and an admin token: the Lift rollouts, a split and a classifier.
fn store_with_data(dir: &Path) -> (Target, String) {
    let t = Target::sqlite(dir);
    t.ok(&["init"]);
    lift_with_classifier(&t);
    let admin = t.token("contract", "admin");
    (t, admin)
}

#[test]
fn committed_document_is_the_served_one() {
    let dir = tempfile::tempdir().unwrap();
    let t = Target::sqlite(dir.path());
    t.ok(&["init"]);
    let auth = t.bearer("doc", "viewer");
    let server = t.serve(&["--no-worker"]);
    let r = http(&server.url, "GET", "/openapi.json", &[("Authorization", &auth)], None);
    assert_eq!(r.status, 200);
    let printed: serde_json::Value = serde_json::from_str(&t.ok(&["openapi"])).unwrap();
    assert_eq!(printed, r.json(), "`ufops openapi` prints what the server serves");
    assert!(
        r.json() == committed(),
        "api/openapi.json differs from the served /openapi.json: regenerate it with `{REGENERATE}`"
    );
}

/// One failure a schemathesis check reported, as `tests/openapi/contract_hooks.py` logs it.
#[derive(Debug, serde::Deserialize)]
struct Failure {
    operation: String,
    check: String,
    title: String,
    message: String,
    status: Option<u16>,
    problem_type: Option<String>,
    header: Option<String>,
}

/// Why a failure is one the contract accepts, or `None` when it is not.
fn accepted(f: &Failure, doc: &serde_json::Value) -> Option<&'static str> {
    // RFC 6585's status for a missing precondition, which schemathesis's list for a missing
    // required header lacks.
    if f.check == "MissingHeaderNotRejected"
        && f.header.as_deref() == Some("If-Match")
        && f.status == Some(428)
    {
        return Some("428 for a missing If-Match");
    }
    // A negative case keeps the key schemathesis drew, so two of them can share one: the key's
    // 422, which every operation taking the header declares.
    if f.status == Some(422) && f.problem_type.as_deref() == Some("urn:ufops:problem:idempotency-key-reused")
    {
        let (method, path) = f.operation.split_once(' ')?;
        let declared = &doc["paths"][path][method.to_lowercase()]["responses"]["422"];
        if declared["description"].as_str().is_some_and(|d| d.contains("Idempotency-Key was used")) {
            return Some("the declared 422 of a reused Idempotency-Key");
        }
    }
    None
}

/// The settings of the schemathesis run: the committed ones, and the store's own names for the
/// operations nothing in the document links to (else they would only ever see 404s).
fn schemathesis_config(dir: &Path, server: &str, auth: &str) -> std::path::PathBuf {
    let settings = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/openapi/schemathesis.toml");
    let page = http(server, "GET", "/v1/episodes?policy=bc&limit=1", &[("Authorization", auth)], None).json();
    let episode = page["episodes"][0]["id"].as_str().unwrap().to_string();
    let mut text = std::fs::read_to_string(&settings).unwrap();
    for (path, params) in [
        ("/v1/episodes/{id}/scores", format!(r#""path.id" = "{episode}""#)),
        ("/v1/episodes/{id}/media/{key}", format!(r#""path.id" = "{episode}""#)),
        ("/v1/review/artifacts/{policy}", r#""path.policy" = "bc""#.to_string()),
        (
            "/v1/policies/{policy}/checkpoints/{checkpoint}/verifiers/{kind_at_alias}",
            r#""path.policy" = "bc", "path.checkpoint" = "e600", "path.kind_at_alias" = "classifier@latest""#
                .to_string(),
        ),
    ] {
        text.push_str(&format!("\n[[operations]]\ninclude-path = \"{path}\"\nparameters = {{ {params} }}\n"));
    }
    let config = dir.join("schemathesis.toml");
    std::fs::write(&config, text).unwrap();
    config
}

/// schemathesis (`--checks all`, every phase, 30 examples an operation) against a server holding
/// the robomimic Lift rollouts with a classifier and a LeRobot v3.0 evaluation with its videos
/// finds no failure but the two the contract accepts ([`accepted`]): every rule the server
/// enforces on a request is in the document.
#[test]
fn schemathesis_finds_no_failures() {
    if !store::test_support::require_python(&["schemathesis"]) {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let (t, admin) = store_with_data(dir.path());
    t.ok(&[
        "ingest",
        fixtures().join("lerobot/v30_eval_video").to_str().unwrap(),
        "--policy",
        "arm",
        "--checkpoint",
        "c1",
    ]);
    // No worker: generated ingests and training jobs stay queued, so the run stays bounded.
    let server = t.serve(&["--no-worker"]);
    let auth = format!("Bearer {admin}");
    let config = schemathesis_config(dir.path(), &server.url, &auth);
    let report = dir.path().join("schemathesis.json");
    let failures = dir.path().join("failures.ndjson");
    let out = std::process::Command::new("python3")
        .args(["-m", "schemathesis.cli", "--config-file", config.to_str().unwrap(), "run", &format!("{}/openapi.json", server.url)])
        .args(["--checks", "all", "--phases", "examples,coverage,fuzzing,stateful"])
        .args(["--max-examples", "30", "--seed", "18", "--workers", "1", "--no-shrink"])
        .args(["--header", &format!("Authorization: {auth}")])
        .args(["--report", "json", "--report-json-path", report.to_str().unwrap()])
        .env("NO_COLOR", "1")
        // A fresh Idempotency-Key per call, as clients send them, and the failure log.
        .env("SCHEMATHESIS_HOOKS", "contract_hooks")
        .env("UFOPS_SCHEMATHESIS_FAILURES", &failures)
        .env("PYTHONPATH", Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/openapi"))
        // Its example cache goes to the temp dir, not the checkout.
        .current_dir(dir.path())
        .output()
        .expect("run schemathesis");
    let stdout = String::from_utf8_lossy(&out.stdout);
    eprintln!("{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    let summary: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(&report).unwrap_or_else(|e| panic!("no report from schemathesis ({e})")),
    )
    .unwrap();
    assert_eq!(summary["complete"], true, "schemathesis did not finish: {summary:#}");
    assert_eq!(summary["errors"], serde_json::json!([]), "schemathesis errors: {summary:#}");
    assert!(
        summary["operations"]["tested"].as_u64().unwrap_or(0) >= 60
            && summary["test_cases"]["generated"].as_u64().unwrap_or(0) >= 1000,
        "schemathesis tested too little: {summary:#}"
    );
    let doc = committed();
    let logged: Vec<Failure> = std::fs::read_to_string(&failures)
        .unwrap_or_default()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("{e}: {l}")))
        .collect();
    let mut kinds = std::collections::BTreeMap::<&str, usize>::new();
    let mut refused = Vec::new();
    for f in &logged {
        match accepted(f, &doc) {
            Some(kind) => *kinds.entry(kind).or_default() += 1,
            None => refused.push(f),
        }
    }
    eprintln!("schemathesis: {} failures logged, accepted by kind {kinds:?}", logged.len());
    // Every failure of the run's summary went through the log.
    let grouped: u64 =
        summary["failures"].as_array().unwrap().iter().map(|g| g["count"].as_u64().unwrap()).sum();
    assert!(
        grouped as usize <= logged.len(),
        "the summary counts {grouped} failures, the log {}",
        logged.len()
    );
    assert!(
        refused.is_empty(),
        "schemathesis found failures the contract does not accept:\n{}",
        refused
            .iter()
            .map(|f| format!(
                "{} {} ({}): {:?} {:?}\n  {}",
                f.operation, f.check, f.title, f.status, f.problem_type, f.message
            ))
            .collect::<Vec<_>>()
            .join("\n")
    );
}

#[test]
fn generated_client_parses_the_api_flow() {
    if !store::test_support::require_python(&["datamodel_code_generator", "pydantic"]) {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let (t, admin) = store_with_data(dir.path());
    let server = t.serve(&["--no-worker"]);
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let out = std::process::Command::new("python3")
        .arg(root.join("tests/python/openapi_client_flow.py"))
        .arg(root.join("api/openapi.json"))
        .args([server.url.as_str(), admin.as_str(), dir.path().to_str().unwrap()])
        .output()
        .expect("run python3");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    let report: serde_json::Value = serde_json::from_str(stdout.lines().last().unwrap_or("")).unwrap();
    eprintln!("{report:#}");
    assert!(report["parsed"].as_array().unwrap().len() >= 40, "{report}");
}
