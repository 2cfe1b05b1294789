//! `ufops demo --quick` runs the whole loop (sim → store → trainer → steer) and its report shows
//! best-of-N steering improving on the base policy.

mod common;
use common::*;

#[test]
fn quick_demo_improves_on_base() {
    let dir = tempfile::tempdir().unwrap();
    let t = Target::sqlite(dir.path());
    let out = t.ok(&["demo", "--quick"]);
    assert!(out.contains("| base (DDPM)"), "{out}");
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("demo/report.json")).unwrap()).unwrap();
    let rows = report["rows"].as_array().unwrap();
    let rate = |m: &str, v: &str| {
        rows.iter()
            .find(|r| r["method"] == m && r["verifier"].as_str().unwrap().starts_with(v))
            .unwrap_or_else(|| panic!("no row {m}/{v}"))["rate"]
            .as_f64()
            .unwrap()
    };
    let base = rate("base (DDPM)", "-");
    let bon = rate("C x BoN (N=10)", "on-policy");
    assert!(bon > base + 0.05, "best-of-N {bon} vs base {base}");
    assert!(dir.path().join("demo/trajectories.png").exists());
    // The rollouts are in the store as checkpoint nav-dp/base with the simulator's labels.
    let eps = t.json(&["episodes", "--policy", "nav-dp", "--checkpoint", "base", "--json"]);
    assert_eq!(eps.as_array().unwrap().len(), 200);
    assert!(eps.as_array().unwrap().iter().all(|e| e["label_source"] == "sim"));
    let arts = t.json(&["artifacts", "--policy", "nav-dp", "--json"]);
    assert_eq!(arts.as_array().unwrap().len(), 3, "classifier, q and the off-policy classifier");
}
