//! `ufops ingest --run … --steering …` end to end, on SQLite and Postgres: a robomimic fixture
//! ingested as a steered run (named after its steering by default) carries it on every episode and shows as a scoreboard row against
//! the base run; hostile run options fail with a message naming the problem and leave the store
//! unchanged.

use crate::common;
use common::*;

fn runs_through_the_cli(t: &Target) {
    let f = fixtures().join("robomimic");
    let lowdim = f.join("lift_rollouts_lowdim.hdf5");
    let image = f.join("lift_rollouts_image.hdf5");
    let success = |name: &str| f.join(format!("{name}.success.json")).to_str().unwrap().to_string();
    t.ok(&[
        "ingest",
        lowdim.to_str().unwrap(),
        "--policy",
        "lift",
        "--checkpoint",
        "c1",
        "--run",
        "base",
        "--success-file",
        &success("lift_rollouts_lowdim"),
    ]);
    let versions = || t.json(&["versions", "--json"]).as_array().unwrap().len();
    let before = versions();
    // Hostile run options: nothing is written.
    for (args, says) in [
        (vec!["--steering", "bon:4", "--run-tag", " padded"], "run tag"),
        (vec!["--run", "c-bon", "--steering", "bon:0"], "bon:0"),
        (vec!["--run", "c-bon", "--steering", "ddim:3"], "ddim:3"),
        (vec!["--run", " padded"], "run"),
        (vec!["--run", "c-bon", "--steering", "bon:4", "--run-artifact", "art-missing"], "art-missing"),
    ] {
        let mut a = vec!["ingest", image.to_str().unwrap(), "--policy", "lift", "--checkpoint", "c1"];
        a.extend(args.iter().copied());
        let out = t.run(&a);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?} should fail");
        assert!(err.contains(says), "{args:?}: {err}");
        assert_eq!(versions(), before, "{args:?} left the store unchanged");
    }
    t.ok(&[
        "ingest",
        image.to_str().unwrap(),
        "--policy",
        "lift",
        "--checkpoint",
        "c1",
        "--steering",
        "bon:4",
        "--run-tag",
        "on-policy",
        "--run-tag",
        "lab-a",
        "--success-file",
        &success("lift_rollouts_image"),
    ]);
    let eps = t.json(&["episodes", "--policy", "lift", "--json"]);
    let sb = t.json(&["scoreboard", "--policy", "lift", "--format", "json"]);
    let rows = sb["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 2, "{sb}");
    // Without --run, the run is named after its steering.
    let bon = rows.iter().find(|r| r["run_name"] == "bon:4").unwrap();
    assert_eq!(bon["run"]["steering"], serde_json::json!({"method": "bon", "n": 4}));
    assert_eq!(bon["run"]["tags"], serde_json::json!(["lab-a", "on-policy"]));
    assert_eq!(bon["baseline"]["run_name"], "base");
    let bon_id = bon["run"]["id"].as_str().unwrap();
    let of_bon = eps.as_array().unwrap().iter().filter(|e| e["run_id"] == bon_id).count() as u64;
    assert_eq!(of_bon, bon["episodes"].as_u64().unwrap());
    let total: u64 = rows.iter().map(|r| r["episodes"].as_u64().unwrap()).sum();
    assert_eq!(total as usize, eps.as_array().unwrap().len());
}

#[test]
fn ingest_runs_sqlite() {
    let dir = tempfile::tempdir().unwrap();
    runs_through_the_cli(&Target::sqlite(dir.path()));
}

#[test]
fn ingest_runs_postgres() {
    let dir = tempfile::tempdir().unwrap();
    if let Some(t) = postgres_target(dir.path()) {
        runs_through_the_cli(&t);
    }
}
