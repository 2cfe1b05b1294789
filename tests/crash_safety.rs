//! A writer killed with SIGKILL at random points never leaves a visible partial version, and
//! `gc` then removes exactly the orphans it left.

use crate::common;
use common::*;
use rand::{Rng, SeedableRng};
use std::time::{Duration, Instant};

fn crash_trials(mut target: Target, trials: u32) {
    // A killed writer's uploads stay protected for its lease (gc never takes what a live writer
    // will commit); shortened here so its leftovers are collectable right after the trials.
    target.env.push(("UFOPS_WRITER_LEASE_SECONDS", "1".into()));
    target.ok(&["init"]);
    target.ok(&["dev", "synth", "--seed", "0", "--episodes", "3", "--steps", "20"]);
    // Calibrate: how long does an uninterrupted write take?
    let t0 = Instant::now();
    target.ok(&[
        "dev",
        "synth",
        "--seed",
        "1",
        "--episodes",
        "40",
        "--steps",
        "3000",
        "--max-file-bytes",
        "300000",
    ]);
    let full = t0.elapsed();
    let mut rng = rand::rngs::StdRng::seed_from_u64(42);
    let (mut committed, mut killed_before) = (0, 0);
    for trial in 0..trials {
        let before = target.json(&["versions", "--json"]).as_array().unwrap().len();
        let seed = (100 + trial).to_string();
        let mut child = target
            .command()
            .args([
                "dev",
                "synth",
                "--seed",
                &seed,
                "--episodes",
                "40",
                "--steps",
                "3000",
                "--max-file-bytes",
                "300000",
            ])
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap();
        let wait = full.mul_f64(rng.gen_range(0.05..1.1));
        std::thread::sleep(wait);
        let _ = child.kill(); // SIGKILL
        let _ = child.wait();
        let report = target.json(&["dev", "verify"]);
        assert!(report["problems"].as_array().unwrap().is_empty(), "trial {trial}: {report}");
        let after = report["versions"].as_u64().unwrap() as usize;
        if after > before {
            committed += 1;
        } else {
            killed_before += 1;
        }
    }
    eprintln!("{trials} trials: {committed} committed before the kill, {killed_before} killed before commit");
    assert!(killed_before > 0, "no trial interrupted a write: the test exercised nothing");
    std::thread::sleep(Duration::from_millis(1500)); // the last killed writer's lease lapses
    let gc = target.json(&["gc", "--grace-seconds", "0", "--json"]);
    let deleted = gc["deleted"].as_array().unwrap().len();
    assert!(deleted > 0, "killed writers left orphans that gc should remove: {gc}");
    let report = target.json(&["dev", "verify"]);
    assert!(report["problems"].as_array().unwrap().is_empty(), "{report}");
    let referenced = report["referenced_objects"].as_u64().unwrap();
    // After gc every object in storage is referenced by the catalog.
    let listing = target.json(&["gc", "--grace-seconds", "0", "--dry-run", "--json"]);
    assert!(listing["deleted"].as_array().unwrap().is_empty(), "{listing}");
    assert_eq!(listing["objects_scanned"].as_u64(), Some(referenced), "{listing}");
    if target.object_store.is_none() {
        // The local directory also holds staging files that listings hide: none may remain.
        let files = object_files(&target.data_dir);
        assert_eq!(files.len() as u64, referenced, "{files:?}");
    }
}

#[test]
fn sigkill_mid_commit_sqlite() {
    let dir = tempfile::tempdir().unwrap();
    crash_trials(Target::sqlite(dir.path()), 24);
}

#[test]
fn sigkill_mid_commit_postgres() {
    let dir = tempfile::tempdir().unwrap();
    let Some(target) = postgres_target(dir.path()) else { return };
    crash_trials(target, 20);
}

/// The scale-out layout: Postgres catalog, objects in S3 (a real SeaweedFS server).
#[test]
fn sigkill_mid_commit_postgres_s3() {
    let dir = tempfile::tempdir().unwrap();
    let Some(s3) = seaweedfs::SeaweedFs::start_if_available() else { return };
    let Some(mut target) = postgres_target(dir.path()) else { return };
    target.object_store = Some(format!("s3://{}/crash", seaweedfs::BUCKET));
    target.env = s3.env();
    crash_trials(target, 12);
    // Nothing went to the local directory.
    assert!(object_files(dir.path()).is_empty());
}

#[test]
fn grace_period_protects_young_orphans() {
    let dir = tempfile::tempdir().unwrap();
    let t = Target::sqlite(dir.path());
    t.ok(&["init"]);
    std::fs::create_dir_all(dir.path().join("objects/steps")).unwrap();
    std::fs::write(dir.path().join("objects/steps/orphan.parquet"), b"x").unwrap();
    let gc = t.json(&["gc", "--json"]);
    assert_eq!(gc["kept_recent"].as_u64(), Some(1));
    assert!(dir.path().join("objects/steps/orphan.parquet").exists());
    std::thread::sleep(Duration::from_millis(1100));
    let gc = t.json(&["gc", "--grace-seconds", "1", "--json"]);
    assert_eq!(gc["deleted"].as_array().unwrap().len(), 1);
}
