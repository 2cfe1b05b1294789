//! The command line behaves in a pipeline: a listing whose reader has gone (`ufops episodes | head`)
//! ends quietly instead of panicking on the broken pipe.

mod common;
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
