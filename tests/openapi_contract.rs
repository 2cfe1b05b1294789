//! The API contract: the committed `api/openapi.json` is the document `ufops serve`
//! serves; schemathesis (all checks, every phase including the stateful one) finds no response
//! that breaks it on a server with real data (the Lift rollouts and a classifier trained on
//! them); and pydantic models generated from it parse every response of the end-to-end flow.

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

#[test]
fn schemathesis_finds_no_failures() {
    if !store::test_support::require_python(&["schemathesis"]) {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let (t, admin) = store_with_data(dir.path());
    // No worker: generated ingests and training jobs stay queued, so the run stays bounded.
    let server = t.serve(&["--no-worker"]);
    let report = dir.path().join("schemathesis.json");
    // The committed settings, and the store's own names for the operations nothing in the
    // document links to (else they would only ever see 404s).
    let settings = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/openapi/schemathesis.toml");
    let auth = format!("Bearer {admin}");
    let page =
        http(&server.url, "GET", "/v1/episodes?policy=bc&limit=1", &[("Authorization", &auth)], None).json();
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
    let config = dir.path().join("schemathesis.toml");
    std::fs::write(&config, text).unwrap();
    // No failure is accepted (no baseline). Rules of the store's state answer 409, which
    // schemathesis's check of valid data accepts by default.
    let out = std::process::Command::new("python3")
        .args(["-m", "schemathesis.cli", "--config-file", config.to_str().unwrap(), "run", &format!("{}/openapi.json", server.url)])
        .args(["--checks", "all", "--phases", "examples,coverage,fuzzing,stateful"])
        .args(["--max-examples", "25", "--seed", "18", "--workers", "1", "--no-shrink"])
        .args(["--header", &format!("Authorization: Bearer {admin}")])
        .args(["--report", "json", "--report-json-path", report.to_str().unwrap()])
        .env("NO_COLOR", "1")
        // A fresh Idempotency-Key per call, as clients send them (the hook module says why).
        .env("SCHEMATHESIS_HOOKS", "idempotency_hooks")
        .env("PYTHONPATH", Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/openapi"))
        // Its example cache goes to the temp dir, not the checkout.
        .current_dir(dir.path())
        .output()
        .expect("run schemathesis");
    let stdout = String::from_utf8_lossy(&out.stdout);
    eprintln!("{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "schemathesis found failures (its output is above)");
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
