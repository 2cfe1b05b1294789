//! Steering telemetry in the store and where people look at episodes. `ufops ingest` keeps a
//! source's sidecar of best-of-N records with its episodes and refuses a bad one. A steered run whose best-of-N steps were
//! logged (`steer::best_of_n_recorded` on the stored episodes' own verifier inputs, stored with
//! `push_episode_steered`) is served by `ufops serve`. The steps JSON gives each logged step's
//! record without its candidates; the labeling page draws the candidates' score spread and the
//! chosen score at exactly the logged steps (`tests/web/steering_e2e.mjs`, headless Chromium,
//! screenshot `steering_timeline.png`); the rerun recording logs the same series.

use crate::common::{self, browser, Target};
use serde_json::{json, Value};
use std::collections::HashMap;
use store::{Label, RunInput, Steering, StoreConfig, VectorColumn};
use store_artifacts::{Artifacts, NewArtifact};
use verifier::steps::{steering_array, step_inputs};
use verifier::testutil::RandomSpec;
use verifier::SteeringStep;

const N: usize = 8;

fn rollout(i: u32, steps: usize) -> store::EpisodeInput {
    store::EpisodeInput {
        observations: vec![VectorColumn {
            name: "pos".into(),
            dim: 2,
            values: (0..steps * 2)
                .map(|k| ((k / 2) as f32 * 0.25 + i as f32 + (k % 2) as f32).sin())
                .collect(),
        }],
        ..store::test_support::episode(i, steps, if i == 1 { Label::Failure } else { Label::Success })
    }
}

/// Episodes 0 and 1 steered (best-of-8 every 4 steps), episode 2 not; returns the episodes' ids
/// and logs in source order.
fn steered_store(t: &Target) -> (Vec<String>, Vec<Vec<SteeringStep>>) {
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let store = store::Store::open(&StoreConfig::local(&t.data_dir)).await.unwrap();
        let spec = RandomSpec {
            obs_keys: vec![("pos".into(), 2)],
            obs_history: 2,
            chunk_len: 4,
            action_dim: 3,
            ..RandomSpec::nav()
        };
        let (cfg, w) = spec.build(9);
        let dir = t.data_dir.join("artifact-src");
        verifier::ArtifactFiles::build(&cfg, &w).unwrap().write_dir(&dir).unwrap();
        let v = verifier::Verifier::load_dir(&dir).unwrap();
        let new = NewArtifact {
            dir: &dir,
            policy: "pol",
            checkpoint: "c1",
            kind: "classifier",
            split_id: None,
            job_id: None,
        };
        let rec = store.publish_artifact(new).await.unwrap();
        let mut w =
            store.begin_ingest(store::test_support::source("steered-page"), "pol", "c1").await.unwrap();
        w.set_run(RunInput {
            name: "bon8".into(),
            steering: Steering::Bon { n: N as u32 },
            artifact_id: Some(rec.id),
            tags: vec![],
        })
        .unwrap();
        let (mut ids, mut logs) = (Vec::new(), Vec::new());
        for i in 0..3u32 {
            let ep = rollout(i, 24 + 6 * i as usize);
            if i == 2 {
                ids.push(w.add_episode(ep).await.unwrap());
                logs.push(Vec::new());
                continue;
            }
            let meta = store::steps::EpisodeMeta { episode_id: "e", policy: "pol", checkpoint: "c1" };
            let batch =
                store::steps::episode_batch(rollout(i, 24 + 6 * i as usize), &meta, &HashMap::new()).unwrap();
            let inputs = step_inputs(v.config(), &batch).unwrap();
            let (od, ad) = (v.obs_dim(), v.act_dim());
            let mut log = Vec::new();
            for t in (0..ep.len()).step_by(4) {
                let cands: Vec<f32> =
                    (0..N * ad).map(|k| (k as f32 * 0.9 + t as f32 + i as f32 * 5.0).cos()).collect();
                let (_, mut s) = steer::best_of_n_recorded(
                    &v,
                    None,
                    &inputs.obs[t * od..(t + 1) * od],
                    &[t as u32],
                    &cands,
                    N,
                )
                .unwrap();
                log.append(&mut s);
            }
            let col = steering_array(&log, ep.len()).unwrap();
            ids.push(w.add_episode_steered(ep, col).await.unwrap());
            logs.push(log);
        }
        w.commit("steered page").await.unwrap();

        // The rerun recording logs each steered episode's series; the unsteered one has none.
        let out = t.data_dir.join("steered.rrd");
        let opts = viewer::ViewOptions::new("pol", "c1");
        let report = viewer::write_recording(&store, &opts, None, &out).await.unwrap();
        assert_eq!(report.steered_episodes, 2, "{report:?}");
        let steering: Vec<&String> = report.entities.iter().filter(|e| e.ends_with("/steering")).collect();
        assert_eq!(steering.len(), 2, "{:?}", report.entities);
        (ids, logs)
    })
}

#[test]
fn steering_telemetry_in_steps_json_and_the_labeling_page() {
    let dir = tempfile::tempdir().unwrap();
    let t = Target::sqlite(dir.path());
    let (ids, logs) = steered_store(&t);
    let admin = t.token("admin", "admin");
    let srv = t.serve(&["--no-worker"]);
    let auth = format!("Bearer {admin}");
    let steps = |id: &str| {
        let r = common::http(
            &srv.url,
            "GET",
            &format!("/v1/episodes/{id}/steps"),
            &[("Authorization", &auth)],
            None,
        );
        assert_eq!(r.status, 200);
        r.json()
    };
    for (id, log) in ids.iter().zip(&logs) {
        let s = steps(id);
        assert!(!s["omitted"].as_array().unwrap().iter().any(|c| c == "steering"), "{}", s["omitted"]);
        let col = &s["columns"]["steering"];
        if log.is_empty() {
            assert!(col.is_null(), "an unsteered episode has no steering column: {col}");
            continue;
        }
        let rows = col.as_array().unwrap();
        assert_eq!(rows.len(), s["num_rows"].as_u64().unwrap() as usize);
        let logged: Vec<usize> = log.iter().map(|r| r.t as usize).collect();
        for (t, row) in rows.iter().enumerate() {
            match log.iter().find(|r| r.t as usize == t) {
                None => assert!(row.is_null(), "step {t}: {row}"),
                Some(r) => {
                    // Each score read back as the float32 it was (JSON parsing may differ from the
                    // widened f64 in its last bit).
                    let scores: Vec<f32> = row["scores"]
                        .as_array()
                        .unwrap()
                        .iter()
                        .map(|x| x.as_f64().unwrap() as f32)
                        .collect();
                    assert_eq!(scores, r.scores, "step {t}");
                    assert_eq!(row["chosen"], json!(r.chosen));
                    assert_eq!(row["artifact_id"], json!(r.artifact_id));
                    assert!(row.get("candidates").is_none(), "the JSON leaves the candidates out: {row}");
                }
            }
        }
        assert!(logged.len() >= 6, "{logged:?}");
    }
    drop(srv);

    if !browser::available() {
        return;
    }
    let labeler = t.token("alice", "labeler");
    let expect: serde_json::Map<String, Value> = ids
        .iter()
        .zip(&logs)
        .map(|(id, log)| (id.clone(), json!(log.iter().map(|r| r.t).collect::<Vec<_>>())))
        .collect();
    let srv = t.serve(&["--no-worker"]);
    browser::forget_screenshot("steering_timeline.png");
    let result = browser::run_script(
        "steering_e2e.mjs",
        &srv.url,
        &[
            ("UFOPS_TOKEN_A", labeler),
            ("UFOPS_EXPECT", Value::Object(expect).to_string()),
            ("UFOPS_SHOT", ids[0].clone()),
        ],
    );
    assert_eq!(result[&ids[0]]["steps"], json!(logs[0].len()), "{result}");
    assert_eq!(result[&ids[2]]["shown"], json!(false), "{result}");
    let last = logs[0].last().unwrap().t;
    assert!(result[&ids[0]]["seeked"].as_u64().unwrap().abs_diff(u64::from(last)) <= 1, "{result}");
    browser::assert_screenshot("steering_timeline.png");
}

/// The sidecar's records for the lowdim Lift fixture: best-of-4 every 8 steps of demo_2 (37
/// steps) and demo_3 (41 steps), chunks of 2 actions of 7 (values on the f16 grid already).
fn lift_records() -> Vec<(u64, SteeringStep)> {
    let mut out = Vec::new();
    for (demo, len) in [(2u64, 37u32), (3, 41)] {
        for t in (0..len).step_by(8) {
            let candidates: Vec<f32> = (0..4 * 14)
                .map(|k| ((k as f32 * 0.37 + t as f32 + demo as f32).sin() * 64.0).round() / 64.0)
                .collect();
            let scores: Vec<f32> = (0..4).map(|k| ((k + t as usize) % 5) as f32 / 5.0).collect();
            let chosen = steer::select_best(&scores) as u32;
            out.push((
                demo,
                SteeringStep {
                    t,
                    artifact_id: "a1b2c3".into(),
                    candidates,
                    scores,
                    chosen,
                    latency_us: 40 + t,
                },
            ));
        }
    }
    out
}

fn write_sidecar(path: &std::path::Path, records: &[(u64, SteeringStep)]) {
    let batch = verifier::steps::steering_sidecar_batch(records).unwrap();
    let f = std::fs::File::create(path).unwrap();
    let mut w = parquet::arrow::ArrowWriter::try_new(f, batch.schema(), None).unwrap();
    w.write(&batch).unwrap();
    w.close().unwrap();
}

/// `ufops ingest` picks up `<source>.steering.parquet` (or `--steering-log FILE`) and keeps each
/// record with its episode; a sidecar naming an episode the source lacks, a step outside its
/// episode, or bytes that are not Parquet fail the ingest with a message and leave the store as
/// it was.
#[test]
fn ingest_keeps_a_steering_sidecar_and_refuses_a_bad_one() {
    let dir = tempfile::tempdir().unwrap();
    let fixture = common::fixtures().join("robomimic/lift_rollouts_lowdim.hdf5");
    let src = dir.path().join("lift.hdf5");
    std::fs::copy(&fixture, &src).unwrap();
    let success = common::fixtures().join("robomimic/lift_rollouts_lowdim.success.json");
    let records = lift_records();
    let sidecar = ingest::steering::sidecar_for(&src);
    assert_eq!(sidecar, dir.path().join("lift.hdf5.steering.parquet"));
    write_sidecar(&sidecar, &records);
    let ingest_args = |t: &Target, extra: &[&str]| {
        let mut a = vec!["ingest", src.to_str().unwrap(), "--policy", "lift", "--checkpoint", "c1"];
        a.extend_from_slice(&["--success-file", success.to_str().unwrap()]);
        a.extend_from_slice(extra);
        t.run(&a)
    };

    let t = Target::sqlite(&dir.path().join("store"));
    let out = ingest_args(&t, &["--json"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let rep: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(rep["notes"].to_string().contains(&format!("{} steering records", records.len())), "{rep}");
    let rt = tokio::runtime::Runtime::new().unwrap();
    let store = rt.block_on(store::Store::open(&StoreConfig::local(&t.data_dir))).unwrap();
    let eps = rt.block_on(store.episodes(&store::EpisodeFilter::default())).unwrap();
    assert_eq!(eps.len(), 12);
    for e in &eps {
        let steps = rt.block_on(store.read_steps(&e.id, None)).unwrap();
        let log = verifier::steps::steering_log(&steps).unwrap();
        let want: Vec<SteeringStep> =
            records.iter().filter(|(d, _)| *d == e.source_index as u64).map(|(_, s)| s.clone()).collect();
        assert_eq!(log, want, "episode {}", e.source_name);
    }

    // Refused: each leaves the store without a version.
    let refused = |records: Option<&[(u64, SteeringStep)]>, bytes: Option<&[u8]>, want: &str| {
        let bad = dir.path().join("bad.steering.parquet");
        match (records, bytes) {
            (Some(r), _) => write_sidecar(&bad, r),
            (_, Some(b)) => std::fs::write(&bad, b).unwrap(),
            _ => unreachable!(),
        }
        let t = Target::sqlite(&dir.path().join(format!("refused-{}", want.len())));
        let out = ingest_args(&t, &["--steering-log", bad.to_str().unwrap()]);
        let err = String::from_utf8_lossy(&out.stderr).to_string();
        assert!(!out.status.success() && err.contains(want), "want {want:?}: {err}");
        // No version: the store was not created, or holds nothing.
        let v = t.run(&["versions", "--json"]);
        if v.status.success() {
            let versions: Value = serde_json::from_slice(&v.stdout).unwrap();
            assert_eq!(versions.as_array().map(Vec::len), Some(0), "{versions}");
        }
    };
    let mut stray = records.clone();
    stray[0].0 = 99;
    refused(Some(&stray), None, "records for episode index 99");
    let mut late = records.clone();
    late[0].1.t = 37;
    refused(Some(&late), None, "outside the episode's 37 steps");
    refused(None, Some(b"not parquet at all, just bytes"), "not a readable Parquet file");
}
