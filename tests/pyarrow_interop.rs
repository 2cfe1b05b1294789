//! A version written by ufops reads back in pyarrow (and duckdb/polars when installed) with the
//! same rows and labels, using nothing but the files.

use crate::common;
use common::*;

#[test]
fn pyarrow_reads_a_version() {
    if !store::test_support::require_python(&["pyarrow", "duckdb"]) {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let t = Target::sqlite(dir.path());
    t.ok(&["dev", "synth", "--seed", "7", "--episodes", "12", "--steps", "33"]);
    t.ok(&["dev", "synth", "--seed", "8", "--episodes", "5", "--steps", "17", "--checkpoint", "c2"]);
    let eps = t.json(&["episodes", "--json"]);
    let first = eps[0]["id"].as_str().unwrap().to_string();
    let new_label = if eps[0]["label"] == "success" { "failure" } else { "success" };
    t.ok(&["label", &first, new_label, "--note", "checked the video"]);
    t.ok(&["snapshot", "--message", "after review"]);
    let versions = t.json(&["versions", "--json"]);
    let last = versions.as_array().unwrap().last().unwrap().clone();
    let v = last["version"].as_i64().unwrap().to_string();
    let expected = serde_json::json!({
        "version": last["version"],
        "versions": versions,
        "episodes": t.json(&["episodes", "--version", &v, "--json"]),
    });
    assert_eq!(expected["episodes"][0]["label"], new_label);
    let path = dir.path().join("expected.json");
    std::fs::write(&path, serde_json::to_vec(&expected).unwrap()).unwrap();
    let script = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/check_store.py");
    let out = std::process::Command::new("python3")
        .arg(script)
        .arg(dir.path())
        .arg(&path)
        .output()
        .expect("python3 is needed for the interop test");
    assert!(
        out.status.success(),
        "pyarrow check failed (pip install pyarrow):\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    let stdout = String::from_utf8_lossy(&out.stdout);
    // duckdb is importable (checked above), so its reading must have run
    assert!(stdout.contains("duckdb: "), "{stdout}");
    eprintln!("{stdout}");
}

#[test]
fn bad_input_gets_one_clear_line_and_nonzero_exit() {
    let dir = tempfile::tempdir().unwrap();
    let t = Target::sqlite(dir.path());
    t.ok(&["init"]);
    let out = t.run(&["label", "no-such-episode", "success"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.starts_with("error: episode not found: no-such-episode"), "{err}");
    assert_eq!(err.lines().count(), 1, "{err}");
    let out = t.run(&["episodes", "--label", "maybe"]);
    assert!(String::from_utf8_lossy(&out.stderr).contains("unknown label"));
    let out = t.run(&["--database-url", "mysql://x", "versions"]);
    assert!(String::from_utf8_lossy(&out.stderr).contains("unsupported database URL"));
    // A stale revision is refused and names who changed the label.
    t.ok(&["dev", "synth", "--episodes", "1", "--steps", "3"]);
    let id = t.json(&["episodes", "--json"])[0]["id"].as_str().unwrap().to_string();
    t.ok(&["label", &id, "unknown", "--expect-revision", "1", "--actor", "alice"]);
    let out = t.run(&["label", &id, "success", "--expect-revision", "1"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("label conflict") && err.contains("alice") && err.contains("revision 2"), "{err}");
}
