//! `ufops compare` and `ufops alias` end to end on real-format rollouts: two robomimic files of the
//! same task ingested as two runs pair by their demo names (`--pair-key source_name`), the
//! comparison of so few rollouts is undecided (exit 2) and says how many more it needs, a
//! protected alias refuses to move on it (exit 1, the alias unchanged), and bad arguments fail
//! with a message naming the problem.

use crate::common;
use common::*;

#[test]
fn compare_and_alias_through_the_cli() {
    let dir = tempfile::tempdir().unwrap();
    let t = Target::sqlite(dir.path());
    let f = fixtures().join("robomimic");
    for (file, run) in [("lift_rollouts_lowdim", "base"), ("lift_rollouts_image", "cam")] {
        let success = f.join(format!("{file}.success.json"));
        t.ok(&[
            "ingest",
            f.join(format!("{file}.hdf5")).to_str().unwrap(),
            "--policy",
            "lift",
            "--checkpoint",
            "c1",
            "--run",
            run,
            "--success-file",
            success.to_str().unwrap(),
        ]);
    }
    let run = |args: &[&str]| {
        let mut a = vec!["compare", "--policy", "lift", "--a", "c1/base", "--b", "c1/cam"];
        a.extend_from_slice(args);
        t.run(&a)
    };
    // Paired by demo name: the two files share demo_0 … demo_3.
    let out = run(&["--pair-key", "source_name", "--format", "json"]);
    assert_eq!(out.status.code(), Some(2), "undecided: {}", String::from_utf8_lossy(&out.stderr));
    let c: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(c["pairing"], "key:source_name");
    assert_eq!(c["pooled"]["decision"], "undecided");
    let lowdim =
        std::fs::read_to_string(f.join("lift_rollouts_lowdim.success.json")).unwrap().matches(':').count();
    let image =
        std::fs::read_to_string(f.join("lift_rollouts_image.success.json")).unwrap().matches(':').count();
    assert_eq!(c["pooled"]["pairs"].as_u64().unwrap() as usize, lowdim.min(image));
    let t2 = &c["pooled"]["pair_table"];
    let n: u64 = ["both", "only_a", "only_b", "neither"].iter().map(|k| t2[*k].as_u64().unwrap()).sum();
    assert_eq!(n, c["pooled"]["pairs"].as_u64().unwrap());
    // Unpaired: arrival order, and the table says what it could not compare.
    let out = run(&["--pair-key", ""]);
    let table = String::from_utf8_lossy(&out.stdout).to_string();
    assert_eq!(out.status.code(), Some(2));
    assert!(table.contains("paired in arrival order") && table.contains("| pooled | undecided |"), "{table}");
    assert!(table.contains("without a partner"), "{table}");
    assert!(table.contains("gate: undecided (exit 2)"), "{table}");
    // Bad arguments: a message naming the problem.
    for (args, says) in [
        (vec!["--alpha", "0"], "alpha"),
        (vec!["--margin", "2"], "margin"),
        (vec!["--format", "xml"], "xml"),
        (vec!["--plan-effect=-0.1"], "plan"),
    ] {
        let out = run(&args);
        assert!(!out.status.success(), "{args:?}");
        assert!(
            String::from_utf8_lossy(&out.stderr).contains(says),
            "{args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    let out = t.run(&["compare", "--policy", "lift", "--a", "c1/base", "--b", "c9"]);
    assert!(!out.status.success() && String::from_utf8_lossy(&out.stderr).contains("c9"));

    // A protected alias does not move on an undecided comparison.
    t.ok(&["alias", "move", "--policy", "lift", "--alias", "prod", "--to", "c1/base", "--protect"]);
    let before = t.json(&["alias", "list", "--policy", "lift", "--json"]);
    let out = t.run(&[
        "alias",
        "move",
        "--policy",
        "lift",
        "--alias",
        "prod",
        "--to",
        "c1/cam",
        "--pair-key",
        "source_name",
    ]);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("protected") && err.contains("undecided"), "{err}");
    assert_eq!(t.json(&["alias", "list", "--policy", "lift", "--json"]), before);
    let history = t.ok(&["alias", "history", "--policy", "lift", "--alias", "prod"]);
    assert_eq!(history.lines().count(), 1, "{history}");
    // `ufops artifacts --policy` lists the policy's aliases too.
    let arts = t.ok(&["artifacts", "--policy", "lift"]);
    assert!(arts.contains("lift@prod -> c1/base (protected)"), "{arts}");
}
