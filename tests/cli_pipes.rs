//! The command line behaves in a pipeline: a listing whose reader has gone (`ufops episodes | head`)
//! ends quietly instead of panicking on the broken pipe. And a newcomer's first mistakes get one
//! clear line each: no store where a read command looks, a missing file, an empty store.

use crate::common;
use common::*;
use std::os::unix::process::ExitStatusExt;
use std::process::Stdio;

#[test]
fn listing_into_a_closed_pipe_ends_quietly() {
    let dir = tempfile::tempdir().unwrap();
    let t = Target::sqlite(dir.path());
    let fixture = fixtures().join("robomimic/lift_rollouts_lowdim.hdf5");
    t.ok(&["ingest", fixture.to_str().unwrap(), "--policy", "arm", "--checkpoint", "c1"]);
    assert!(!t.ok(&["episodes"]).trim().is_empty(), "the listing prints rows");
    // Close the reading end before the process writes: its first write meets a broken pipe.
    let mut child =
        t.command().arg("episodes").stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap();
    drop(child.stdout.take());
    let out = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert!(
        out.status.success() || out.status.signal() == Some(SIGPIPE),
        "status {:?}, stderr {stderr}",
        out.status
    );
}

/// SIGPIPE's number on Linux.
const SIGPIPE: i32 = 13;

fn failure(t: &Target, args: &[&str]) -> String {
    let out = t.run(args);
    assert!(!out.status.success(), "ufops {args:?} should fail");
    String::from_utf8_lossy(&out.stderr).into_owned()
}

#[test]
fn a_read_command_without_a_store_says_how_to_make_one_and_creates_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let t = Target::sqlite(&dir.path().join("ufops-data"));
    for args in [&["episodes"][..], &["versions"], &["scoreboard", "--policy", "p"], &["layers"]] {
        let err = failure(&t, args);
        assert!(err.contains("no store at") && err.contains("ufops init"), "{args:?}: {err}");
    }
    assert!(!t.data_dir.exists(), "a read command created {}", t.data_dir.display());
    t.ok(&["init"]);
    assert!(t.ok(&["episodes", "--json"]).trim().starts_with('['));
    // One name for the label filter across commands (`export --label`); the older one still works.
    t.ok(&["dev", "synth", "--episodes", "6", "--steps", "3", "--seed", "1"]);
    let all = t.json(&["episodes", "--json"]);
    let successes = t.json(&["episodes", "--label", "success", "--json"]);
    let n = all.as_array().unwrap().iter().filter(|e| e["label"] == "success").count();
    assert_eq!(successes.as_array().unwrap().len(), n);
    assert_eq!(t.json(&["episodes", "--success", "success", "--json"]), successes);
}

#[test]
fn a_missing_file_is_named_once() {
    let dir = tempfile::tempdir().unwrap();
    let t = Target::sqlite(dir.path());
    t.ok(&["init"]);
    let missing = dir.path().join("nope.hdf5");
    let err = failure(&t, &["ingest", missing.to_str().unwrap(), "--policy", "p", "--checkpoint", "c"]);
    assert!(err.contains("nope.hdf5"), "{err}");
    assert_eq!(err.matches("os error 2").count(), 1, "the OS error is said once: {err}");
    assert_eq!(err.lines().count(), 1, "{err}");
}

#[test]
fn a_split_of_an_empty_store_says_what_is_missing() {
    let dir = tempfile::tempdir().unwrap();
    let t = Target::sqlite(dir.path());
    t.ok(&["init"]);
    let err = failure(&t, &["split", "create", "--policy", "nope", "--checkpoint", "c1"]);
    assert!(err.contains("the store is empty") && err.contains("ufops ingest"), "{err}");
    assert!(!err.contains("version not found"), "{err}");
}
