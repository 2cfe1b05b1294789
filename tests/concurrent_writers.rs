//! Two writer processes at once: both succeed, version numbers stay dense, nothing is lost.

use crate::common;
use common::*;

fn two_writers(target: Target) {
    target.ok(&["init"]);
    let per_writer = 6;
    let spawn = |w: u32| {
        let target = target.clone();
        std::thread::spawn(move || {
            for k in 0..per_writer {
                let seed = (1000 * (w + 1) + k).to_string();
                let ckpt = format!("w{w}");
                target.ok(&[
                    "dev",
                    "synth",
                    "--seed",
                    &seed,
                    "--episodes",
                    "4",
                    "--steps",
                    "50",
                    "--checkpoint",
                    &ckpt,
                ]);
            }
        })
    };
    let (a, b) = (spawn(0), spawn(1));
    a.join().unwrap();
    b.join().unwrap();
    let versions = target.json(&["versions", "--json"]);
    let nums: Vec<i64> =
        versions.as_array().unwrap().iter().map(|v| v["version"].as_i64().unwrap()).collect();
    assert_eq!(nums, (1..=2 * per_writer as i64).collect::<Vec<_>>(), "dense, no duplicates");
    let sources: std::collections::HashSet<&str> =
        versions.as_array().unwrap().iter().map(|v| v["source_sha256"].as_str().unwrap()).collect();
    assert_eq!(sources.len(), 2 * per_writer as usize, "every write has its own version");
    let eps = target.json(&["episodes", "--json"]);
    assert_eq!(eps.as_array().unwrap().len(), 2 * per_writer as usize * 4, "no lost episodes");
    let last = versions.as_array().unwrap().last().unwrap();
    assert_eq!(last["episode_count"].as_i64(), Some(2 * per_writer as i64 * 4));
    let report = target.json(&["dev", "verify"]);
    assert!(report["problems"].as_array().unwrap().is_empty(), "{report}");
}

#[test]
fn concurrent_writers_sqlite() {
    let dir = tempfile::tempdir().unwrap();
    two_writers(Target::sqlite(dir.path()));
}

#[test]
fn concurrent_writers_postgres() {
    let dir = tempfile::tempdir().unwrap();
    let Some(target) = postgres_target(dir.path()) else { return };
    two_writers(target);
}
