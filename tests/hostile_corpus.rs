//! The hostile-input corpus: every source written by
//! `hostile_corpus::write_corpus` is given to the real `ufops ingest` as a child process, which
//! must refuse it with the expected error and a non-zero exit, without a panic, with its peak
//! resident memory under [`MAX_RSS_BYTES`], and leave the store as it was (same versions, same
//! object files).
//!
//! Peak memory is the child's `ru_maxrss` from `wait4`. Linux carries into it the resident set of
//! the test process the child was spawned from (the high-water mark of the address space it had
//! before `exec`), so the test resets its own high-water mark first (`/proc/self/clear_refs`):
//! the figure is then max(the test's resident set at spawn, the child's peak), an upper bound of
//! the child's peak.
//!
//! `paths_named_by_a_dataset_stay_inside_it` covers the sources that try to make ingest read
//! outside them (LeRobot templates, feature keys, symlinks); `declared_sizes_never_drive_memory`
//! those whose declared sizes would (HDF5 shapes, MCAP chunks and messages, Parquet pages, huge
//! metadata). On the main branch before this corpus, the first copied a file from outside the
//! dataset into the store and the second used 1-2 GB per file.

use crate::common;
use common::*;

use std::os::unix::process::ExitStatusExt;
use std::path::Path;
use std::process::Stdio;

use hostile_corpus::{write_corpus, Attack, Case};

/// Generous: a refused source should cost a few tens of MB; the attacks cost GBs.
const MAX_RSS_BYTES: u64 = 512 << 20;

struct Run {
    status: std::process::ExitStatus,
    stderr: String,
    max_rss: u64,
    /// This process's resident set when the child was spawned (a floor of `max_rss`).
    parent_rss: u64,
}

/// `VmRSS` of this process, in bytes.
fn own_rss() -> u64 {
    let s = std::fs::read_to_string("/proc/self/status").unwrap();
    let kb = s
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok());
    kb.expect("VmRSS in /proc/self/status") * 1024
}

/// Runs `ufops ingest` on `source` and measures the child's peak RSS.
#[allow(unsafe_code, reason = "wait4(2) for the child's peak RSS: std has no safe wrapper")]
fn ingest(t: &Target, source: &Path) -> Run {
    let stderr_path = t.data_dir.with_extension(format!("stderr-{}", std::process::id()));
    let stderr_file = std::fs::File::create(&stderr_path).unwrap();
    // Reset this process's peak RSS to its current RSS (see the module doc).
    std::fs::write("/proc/self/clear_refs", "5").expect("reset the peak RSS through /proc/self/clear_refs");
    let parent_rss = own_rss();
    let child = command(t)
        .args(["ingest", source.to_str().unwrap(), "--policy", "hostile", "--checkpoint", "c1"])
        .stdout(Stdio::null())
        .stderr(stderr_file)
        .spawn()
        .expect("run ufops");
    let pid = child.id() as libc::pid_t;
    let mut status: libc::c_int = 0;
    // SAFETY: rusage is plain integers, for which all zeroes is a valid value.
    let mut ru: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: plain FFI; `ru` is a valid out-parameter and `pid` is our own child (std's
    // `Child` is never waited on afterwards).
    let r = unsafe { libc::wait4(pid, &mut status, 0, &mut ru) };
    assert_eq!(r, pid, "wait4: {}", std::io::Error::last_os_error());
    drop(child);
    let stderr = std::fs::read_to_string(&stderr_path).unwrap_or_default();
    let _ = std::fs::remove_file(&stderr_path);
    Run {
        status: std::process::ExitStatus::from_raw(status),
        stderr,
        max_rss: ru.ru_maxrss as u64 * 1024,
        parent_rss,
    }
}

/// `ufops` against the store; `UFOPS_HOSTILE_BIN` runs another build instead (e.g. one of an
/// earlier commit, to see which sources it lets through).
fn command(t: &Target) -> std::process::Command {
    let c = t.command();
    let Ok(other) = std::env::var("UFOPS_HOSTILE_BIN") else { return c };
    let mut d = std::process::Command::new(other);
    d.args(c.get_args());
    for (k, v) in c.get_envs() {
        match v {
            Some(v) => d.env(k, v),
            None => d.env_remove(k),
        };
    }
    d
}

/// What must not change: the versions (as JSON) and the object files.
fn store_state(t: &Target) -> (String, Vec<String>) {
    (t.ok(&["versions", "--json"]), object_files(&t.data_dir))
}

fn run_corpus(attack: Attack) {
    let dir = tempfile::tempdir().unwrap();
    let cases: Vec<Case> = write_corpus(&dir.path().join("corpus"))
        .unwrap()
        .into_iter()
        .filter(|c| c.attack == attack)
        .collect();
    assert!(cases.len() >= 5, "{attack:?}: {} cases", cases.len());
    // A store holding one version already, so "unchanged" means something.
    let t = Target::sqlite(&dir.path().join("store"));
    let good = fixtures().join("robomimic/lift_rollouts_lowdim.hdf5");
    let ok = ingest(&t, &good);
    assert!(ok.status.success(), "the fixture ingests: {}", ok.stderr);
    eprintln!(
        "{:<32} peak RSS {:>6.1} MB (test process at spawn {:.1} MB)",
        "(fixture lowdim, accepted)",
        ok.max_rss as f64 / 1e6,
        ok.parent_rss as f64 / 1e6
    );
    let before = store_state(&t);
    assert!(!before.1.is_empty());
    let mut failures = Vec::new();
    for c in &cases {
        let r = ingest(&t, &c.path);
        let err = r.stderr.trim();
        eprintln!(
            "{:<32} exit {:?} peak RSS {:>6.1} MB (test process at spawn {:.1} MB)  {}",
            c.name,
            r.status.code(),
            r.max_rss as f64 / 1e6,
            r.parent_rss as f64 / 1e6,
            err.lines().last().unwrap_or("")
        );
        let mut why = Vec::new();
        if r.status.success() {
            why.push("was accepted".to_string());
        }
        if r.status.signal().is_some() {
            why.push(format!("killed by signal {:?}", r.status.signal()));
        }
        if err.contains("panicked") {
            why.push("panicked".into());
        }
        if !err.contains(c.expect) {
            why.push(format!("the error does not say {:?}", c.expect));
        }
        if r.max_rss > MAX_RSS_BYTES {
            why.push(format!("peak RSS {} MB > {} MB", r.max_rss >> 20, MAX_RSS_BYTES >> 20));
        }
        if store_state(&t) != before {
            why.push("the store changed".into());
        }
        if !why.is_empty() {
            failures.push(format!("{}: {} (stderr: {err})", c.name, why.join("; ")));
        }
    }
    assert!(
        failures.is_empty(),
        "{} of {} hostile sources:\n{}",
        failures.len(),
        cases.len(),
        failures.join("\n")
    );
}

#[test]
fn paths_named_by_a_dataset_stay_inside_it() {
    run_corpus(Attack::Path);
}

#[test]
fn declared_sizes_never_drive_memory() {
    run_corpus(Attack::Size);
}
