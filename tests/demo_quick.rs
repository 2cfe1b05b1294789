//! `ufops demo --quick` runs the whole loop (sim → store → trainer → steer) on 200 rollouts per
//! row. Every row whose effect is large at that scale (|Δ| ≥ 15 pp in the full demo) must go the
//! way the method says: on-policy best-of-N and classifier guidance lift the base policy, the
//! flow twin's best-of-N too, a verifier trained on fewer rollouts still helps, and best-of-N with
//! an off-policy classifier hurts. "Goes that way" is the Newcombe 95% interval of Δ excluding 0.
//! Every row's rollouts are in the store as a run, and `ufops scoreboard` gives the table back.

use crate::common;
use common::*;

#[test]
fn quick_demo_rows_go_the_way_the_method_says() {
    let dir = tempfile::tempdir().unwrap();
    let t = Target::sqlite(dir.path());
    let out = t.ok(&["demo", "--quick"]);
    assert!(out.contains("| base (DDPM)"), "{out}");
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("demo/report.json")).unwrap()).unwrap();
    let rows = report["rows"].as_array().unwrap();
    let row = |m: &str, v: &str| {
        rows.iter()
            .find(|r| r["method"] == m && r["verifier"] == v)
            .unwrap_or_else(|| panic!("no row {m} / {v} in {out}"))
    };
    let interval = |m: &str, v: &str| {
        let ci = &row(m, v)["newcombe_95"];
        (ci[0].as_f64().unwrap(), ci[1].as_f64().unwrap())
    };
    for (m, v) in [
        ("C x BoN (N=10)", "on-policy"),
        ("Q x BoN (N=10)", "on-policy"),
        ("C x CG (lambda=3)", "on-policy"),
        ("flow twin, C x BoN (N=10)", "on-policy (DDPM rollouts)"),
        ("C x BoN (N=10)", "on-policy, 50 rollouts"),
    ] {
        let (lo, _) = interval(m, v);
        assert!(lo > 0.0, "{m} / {v} should lift the base policy: Δ interval starts at {lo}\n{out}");
    }
    let (_, hi) = interval("C x BoN (N=10)", "off-policy (alt rollouts)");
    assert!(hi < 0.0, "best-of-N with the off-policy classifier should hurt: Δ interval ends at {hi}\n{out}");
    // Rows without a large effect in the full demo exist, with the diagnostics of every guided row.
    for (m, v) in [
        ("Q x CG (lambda=3)", "on-policy"),
        ("flow twin, unsteered", "-"),
        ("C x CG (lambda=3)", "off-policy (alt rollouts)"),
    ] {
        row(m, v);
    }
    let diag = report["diagnostics"].as_array().unwrap();
    let guided =
        diag.iter().find(|d| d["method"] == "Q x CG (lambda=3)").expect("diagnostics of the Q x CG row");
    assert_eq!(guided["per_step"].as_array().unwrap().len(), 20, "one entry per denoising step");
    assert!(guided["total_push"].as_f64().unwrap() > 0.0);
    assert!(dir.path().join("demo/trajectories.png").exists());

    // Every row's rollouts are in the store as a run of nav-dp/base (the flow twin's of
    // nav-dp/flow-twin) with the simulator's labels: 200 of the base run, 200 per steered row,
    // and 200 fresh base rollouts the failure monitor is measured on (run `base-fresh`).
    let eps = t.json(&["episodes", "--policy", "nav-dp", "--checkpoint", "base", "--json"]);
    let eps = eps.as_array().unwrap();
    let base_rows = rows.iter().filter(|r| r["checkpoint"] == "base").count();
    assert_eq!(eps.len(), 200 * (base_rows + 1));
    assert!(eps.iter().all(|e| e["label_source"] == "sim" && e["run_id"].is_string()));

    // The scoreboard gives the demo's table back from the store alone: every row's counts, rate,
    // Wilson interval, and its Newcombe interval against the base policy (the DDPM base run).
    let sb =
        t.json(&["scoreboard", "--policy", "nav-dp", "--baseline-checkpoint", "base", "--format", "json"]);
    assert_eq!(
        report["meta"]["scoreboard_version"], sb["version"],
        "the demo checked its table against this scoreboard"
    );
    let sb_rows = sb["rows"].as_array().unwrap();
    assert_eq!(
        sb_rows.len(),
        rows.len() + 2,
        "one scoreboard row per report row, the alt checkpoint's base run and the monitor's fresh base run"
    );
    for r in rows {
        let s = sb_rows
            .iter()
            .find(|s| s["checkpoint"] == r["checkpoint"] && s["run_name"] == r["run"])
            .unwrap_or_else(|| panic!("no scoreboard row for {r}"));
        assert_eq!(s["task"], "two-gap-navigation");
        assert_eq!(s["successes"], r["successes"], "{r} vs {s}");
        assert_eq!(
            s["successes"].as_u64().unwrap() + s["failures"].as_u64().unwrap(),
            r["episodes"].as_u64().unwrap()
        );
        assert_eq!(s["unlabeled"], 0);
        assert_eq!(s["rate"], r["rate"], "{r} vs {s}");
        assert_eq!(s["wilson_95"], r["wilson_95"], "{r} vs {s}");
        if r["run"] == "base" && r["checkpoint"] == "base" {
            assert_eq!(s["is_baseline"], true);
            assert!(s["baseline"].is_null());
        } else {
            assert_eq!(s["baseline"]["newcombe_95"], r["newcombe_95"], "{r} vs {s}");
            assert_eq!(s["baseline"]["diff"], r["diff_to_base"], "{r} vs {s}");
            let lo = r["newcombe_95"][0].as_f64().unwrap();
            let hi = r["newcombe_95"][1].as_f64().unwrap();
            assert_eq!(s["baseline"]["separates"], lo > 0.0 || hi < 0.0);
        }
    }
    // The steering and artifact of each run are recorded: the on-policy C x BoN row's run was
    // steered by the main classifier.
    let bon = sb_rows.iter().find(|s| s["checkpoint"] == "base" && s["run_name"] == "c-bon10").unwrap();
    assert_eq!(bon["run"]["steering"], serde_json::json!({"method": "bon", "n": 10}));
    assert_eq!(bon["run"]["artifact_id"], report["meta"]["artifacts"]["classifier"]);
    // ... and its verifier's quality on the split's held-out samples, from the artifact.
    let q = &bon["verifier_quality"];
    assert_eq!(q["auroc"], report["meta"]["verifier_metrics"]["classifier"]["val_auc"]);
    for k in ["accuracy", "brier", "ece"] {
        let v = q[k].as_f64().unwrap_or_else(|| panic!("{k} in {q}"));
        assert!((0.0..=1.0).contains(&v), "{k} = {v}");
    }
    assert_eq!(q["reliability"].as_array().unwrap().len(), 10);
    // Next to the AUROC, how much the chunk matters: the verifier's AUROC among held-out samples
    // its observation-only twin scores alike, and the twin's own, as the artifact records them.
    let sensitivity = &report["meta"]["verifier_metrics"]["classifier"]["action_sensitivity"];
    assert_eq!(q["action_auroc"], sensitivity["action_auc"], "{q}");
    assert_eq!(q["obs_only_auroc"], sensitivity["obs_only_auc"], "{q}");
    let gain = q["auroc"].as_f64().unwrap() - q["obs_only_auroc"].as_f64().unwrap();
    assert!((sensitivity["auc_gain"].as_f64().unwrap() - gain).abs() < 1e-12);
    // The report ranks every best-of-N row of the base policy (C and Q at N = 10, the off-policy
    // classifier, the 50-rollout one) by each figure against the gain its steering achieved.
    let sq = &report["steering_quality"];
    let sq_rows = sq["rows"].as_array().unwrap();
    let runs: Vec<&str> = sq_rows.iter().map(|r| r["run"].as_str().unwrap()).collect();
    assert_eq!(runs, ["c-bon10", "q-bon10", "off-c-bon10", "c-bon10-n50"], "{sq}");
    for r in sq_rows {
        let row = rows.iter().find(|x| x["run"] == r["run"] && x["checkpoint"] == "base").unwrap();
        assert_eq!(r["gain"], row["diff_to_base"]);
        assert!(r["action_auroc"].is_number() && r["auroc"].is_number(), "{r}");
    }
    for k in ["spearman_auroc", "spearman_action_auroc"] {
        let rho = sq[k].as_f64().unwrap_or_else(|| panic!("{k} in {sq}"));
        assert!((-1.0..=1.0).contains(&rho), "{k} = {rho}");
    }
    assert!(out.contains("Rank correlation with the gain over these 4 rows (Spearman)"), "{out}");
    // The failure alarm calibrated from the same classifier, stored and shown with its quality.
    let monitor = &report["monitor"];
    assert_eq!(monitor["artifact_id"], report["meta"]["artifacts"]["classifier"]);
    assert_eq!(q["monitor"]["id"], monitor["id"]);
    assert_eq!(q["monitor"]["alpha"], 0.1);
    let e = &monitor["evaluation"];
    assert!(e["successes"].as_u64().unwrap() >= 50 && e["failures"].as_u64().unwrap() > 0, "{e}");
    let listed = t.json(&["monitor", "list", "--policy", "nav-dp", "--json"]);
    assert_eq!(listed[0]["id"], monitor["id"]);
    assert_eq!(&listed[0]["evaluation"], e, "the store keeps what the calibration measured");
    assert!(out.contains("Failure alarm (monitor "), "{out}");
    // One calibration's false-alarm rate can be far above α; the training-conditional threshold
    // (`--confidence` = 1 − δ) keeps it at most α in at least 1 − δ of calibration draws. 200
    // calibration draws on the demo's pool at α = δ = 0.1, both ways: `monitor draws`.
    let classifier = report["meta"]["artifacts"]["classifier"].as_str().unwrap();
    let draws = t.json(&[
        "monitor",
        "draws",
        "--artifact",
        classifier,
        "--alpha",
        "0.1",
        "--confidence",
        "0.9",
        "--draws",
        "200",
        "--json",
    ]);
    assert_eq!(draws["draws"].as_array().unwrap().len(), 200);
    assert_eq!(draws["calibration"], monitor["calibration_episodes"], "{}", draws["calibration"]);
    let (m, c, r) = (&draws["marginal"], &draws["conditional"], &draws["resampled"]);
    let f = |s: &serde_json::Value, k: &str| s[k].as_f64().unwrap_or(f64::NAN);
    eprintln!(
        "monitor draws on the quick demo's pool ({} successes, {} calibrate, {} held out, {} failures), alpha 0.1, \
         confidence 0.9. Held-out false-alarm rate > alpha in: split conformal (rank {}) {:.3} of draws (exact {:.3}), \
         training-conditional (rank {}) {:.3} (exact {:.3}); median held-out false-alarm rate {:.3} vs {:.3}; median \
         detection {:.3} vs {:.3}; median threshold {:.4} vs {:.4}. Resampled, the pool as the population: rate > \
         alpha in {:.3} (theory {:.3}) vs {:.3} (theory {:.3}) of calibrations",
        draws["successes"],
        draws["calibration"],
        draws["held_out"],
        draws["failures"],
        m["rank"],
        f(m, "above_alpha"),
        f(m, "above_alpha_expected"),
        c["rank"],
        f(c, "above_alpha"),
        f(c, "above_alpha_expected"),
        f(m, "false_alarm_rate_median"),
        f(c, "false_alarm_rate_median"),
        f(m, "detection_rate_median"),
        f(c, "detection_rate_median"),
        f(m, "threshold_median"),
        f(c, "threshold_median"),
        f(r, "marginal_above_alpha"),
        f(r, "marginal_expected"),
        f(r, "conditional_above_alpha"),
        f(r, "conditional_expected"),
    );
    // The guarantee is about the false-alarm rate on fresh successes. With the pool's successes as
    // the population (calibrations resampled from it, each one's rate on all of it), at most δ of
    // the calibrations exceed α with the training-conditional threshold; the split-conformal
    // threshold's share is several times that (the test can fail either way).
    assert!(
        f(r, "conditional_above_alpha") <= 0.1,
        "training-conditional threshold over alpha too often: {r}"
    );
    assert!(f(r, "marginal_above_alpha") >= 0.2, "the split-conformal share should be well above delta: {r}");
    // On a draw's held-out half the rate is measured on finitely many episodes, so it exceeds α in
    // a share of draws fixed by the sizes and the threshold's rank (exact with distinct peaks:
    // 16.3% for rank 66 of 69 against 69 held out, 50% for the split-conformal rank 63): the draws
    // follow it within their sampling error (three standard errors of 200 draws), and the
    // training-conditional threshold exceeds in far fewer draws than the split-conformal one.
    for s in [m, c] {
        let (p, got) = (f(s, "above_alpha_expected"), f(s, "above_alpha"));
        let se = (p * (1.0 - p) / 200.0).sqrt();
        assert!((got - p).abs() <= 3.0 * se, "held-out share {got} vs exact {p} (±{se:.3}): {s}");
    }
    assert!(f(m, "above_alpha") >= f(c, "above_alpha") + 0.2, "{m} vs {c}");
    assert!(c["rank"].as_u64().unwrap() > m["rank"].as_u64().unwrap(), "{m} vs {c}");
    assert!(f(c, "threshold_median") >= f(m, "threshold_median"), "{c} vs {m}");
    let text = t.ok(&["monitor", "draws", "--artifact", classifier, "--draws", "20"]);
    assert!(
        text.contains("training-conditional (0.9)") && text.contains("split conformal (marginal)"),
        "{text}"
    );
    // The default table and CSV.
    let table = t.ok(&["scoreboard", "--policy", "nav-dp"]);
    assert!(table.contains("| base | two-gap-navigation | c-bon10 (on-policy) | bon:10 |"), "{table}");
    let n = |v: &serde_json::Value| format!("{:.3}", v.as_f64().unwrap());
    let cell = format!(
        "| bon:10 | {} (AUROC {}, action {}, obs-only {}",
        bon["run"]["artifact_id"].as_str().unwrap(),
        n(&q["auroc"]),
        n(&q["action_auroc"]),
        n(&q["obs_only_auroc"])
    );
    assert!(table.contains(&cell), "the verifier column shows its figures: {cell}\n{table}");
    let csv = t.ok(&["scoreboard", "--policy", "nav-dp", "--format", "csv"]);
    assert_eq!(csv.lines().count(), sb_rows.len() + 1, "{csv}");
    // `ufops compare` on the stored runs: the rows share initial conditions (`pair_key`), best-of-N
    // is decided better than the base run within the 200 rollouts, the off-policy one worse, and
    // the exit status says so.
    let compare = |b: &str| {
        let out = t.run(&["compare", "--policy", "nav-dp", "--a", "base/base", "--b", b, "--format", "json"]);
        let c: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        assert_eq!(out.status.code(), Some(c["exit_code"].as_i64().unwrap() as i32), "{c}");
        c
    };
    let better = compare("base/c-bon10");
    assert_eq!(better["pairing"], "key:pair_key");
    assert_eq!(
        (&better["pooled"]["decision"], &better["exit_code"]),
        (&"better".into(), &0.into()),
        "{better}"
    );
    assert_eq!(better["pooled"]["pairs"], 200);
    assert!(better["pooled"]["decided_at_pairs"].as_u64().unwrap() < 200, "{better}");
    let worse = compare("base/off-c-bon10");
    assert_eq!((&worse["pooled"]["decision"], &worse["exit_code"]), (&"worse".into(), &1.into()), "{worse}");
    // The split of a later `split create` holds the unsteered runs' rollouts (`base` and the
    // monitor's `base-fresh`), not the steered ones.
    let split = t.json(&["split", "create", "--policy", "nav-dp", "--checkpoint", "base", "--json"]);
    assert_eq!(split["train_episodes"].as_i64().unwrap() + split["val_episodes"].as_i64().unwrap(), 400);
    let arts = t.json(&["artifacts", "--policy", "nav-dp", "--json"]);
    assert_eq!(
        arts.as_array().unwrap().len(),
        4,
        "classifier, q, the off-policy classifier, the 50-rollout classifier"
    );
    // `latest` of the base checkpoint's classifier is the on-policy one trained on every rollout
    // (neither the off-policy one nor a learning-curve one published after it).
    let latest: Vec<&serde_json::Value> = arts
        .as_array()
        .unwrap()
        .iter()
        .filter(|a| {
            a["kind"] == "classifier" && a["aliases"].as_array().unwrap().iter().any(|x| x == "latest")
        })
        .collect();
    assert_eq!(latest.len(), 1, "{arts}");
    assert_eq!(latest[0]["id"], report["meta"]["artifacts"]["classifier"]);
    // The learning-curve split holds 50 of the on-policy rollouts.
    let splits = t.json(&["split", "list", "--json"]);
    let sizes: Vec<i64> = splits
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["train_episodes"].as_i64().unwrap() + s["val_episodes"].as_i64().unwrap())
        .collect();
    assert!(sizes.contains(&50), "{sizes:?}");

    // Steering telemetry: the recorded best-of-N runs kept every step's candidates, and
    // `ufops replay` with the run's own verifier and N reproduces every logged choice and score.
    let replays = report["replays"].as_array().unwrap();
    assert_eq!(replays.len(), 3, "exact, by Q, off-policy by the on-policy C: {replays:?}");
    let exact = &replays[0]["report"];
    assert!(exact["steps"].as_u64().unwrap() > 200 * 5, "{exact}");
    assert_eq!((&exact["changed"], &exact["max_score_difference"]), (&0.into(), &0.0.into()), "{exact}");
    let same = t.json(&["replay", "--run", "c-bon10", "--checkpoint", "base", "--json"]);
    assert_eq!(same["artifact_id"], report["meta"]["artifacts"]["classifier"]);
    assert_eq!((&same["steps"], &same["changed"]), (&exact["steps"], &0.into()), "{same}");
    assert_eq!(same["max_score_difference"], 0.0);
    assert_eq!(same["episodes_without_telemetry"], 0);
    // Fewer candidates: the changed share is measured, with its interval.
    let fewer = t.json(&["replay", "--run", "c-bon10", "--checkpoint", "base", "--n", "3", "--json"]);
    let f = fewer["changed_fraction"].as_f64().unwrap();
    assert!(f > 0.0 && f < 1.0, "{fewer}");
    assert!(fewer["max_score_difference"].is_null());
    // Another artifact: Q on the classifier's logged steps.
    let q_id = report["meta"]["artifacts"]["q"].as_str().unwrap();
    let by_q = t.json(&["replay", "--run", "c-bon10", "--checkpoint", "base", "--artifact", q_id, "--json"]);
    assert_eq!(by_q, replays[1]["report"], "the CLI and the demo's report replay the same way");
    let text = t.ok(&["replay", "--run", "c-bon10", "--checkpoint", "base", "--n", "3"]);
    assert!(text.contains("choice changed: ") && text.contains("the first 3 of N = 10 candidates"), "{text}");
    // The base run logged nothing: a clear message, not an empty report.
    let err = t.run(&["replay", "--run", "base", "--checkpoint", "base", "--artifact", q_id]);
    let msg = String::from_utf8_lossy(&err.stderr);
    assert!(!err.status.success() && msg.contains("holds no steering telemetry"), "{msg}");
    let md = std::fs::read_to_string(dir.path().join("demo/report.md")).unwrap();
    assert!(
        md.contains("## Replaying the logged steps") && md.contains("| would Q have picked differently? |"),
        "{md}"
    );

    // A training-conditional monitor (last: it becomes the checkpoint's `latest`): the CLI states
    // its guarantee and prints the split-conformal threshold of the same episodes beside it, and
    // its record names the method and the confidence.
    let text = t.ok(&["monitor", "calibrate", "--artifact", classifier, "--confidence", "0.9"]);
    assert!(
        text.contains("guarantee: training-conditional")
            && text.contains("the split-conformal threshold of the same"),
        "{text}"
    );
    let record = t.json(&["monitor", "show", "nav-dp/base@latest"]);
    assert_eq!(record["method"], "split_conformal_peak_training_conditional", "{record}");
    assert_eq!(record["confidence"], 0.9);
    assert!(record["threshold"].as_f64().unwrap() >= monitor["threshold"].as_f64().unwrap(), "{record}");
    // Too few calibration successes for the asked confidence: refused with the count it needs.
    let refused = t.run(&["monitor", "calibrate", "--artifact", classifier, "--confidence", "0.999999"]);
    let msg = String::from_utf8_lossy(&refused.stderr);
    assert!(!refused.status.success() && msg.contains("needs at least 132 successful episodes"), "{msg}");
}
