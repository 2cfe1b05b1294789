//! Steering telemetry through a real store (both catalogs): best-of-N steps recorded by
//! `steer::best_of_n_recorded` on the stored episodes' own verifier inputs, ingested as the
//! steering column, read back and replayed — the same artifact and N reproduce every choice and
//! score; fewer candidates or another artifact change exactly the choices computed here by hand.

use std::collections::HashMap;

use replay::{replay, ReplaySpec};
use store::test_support::{self, open_test_store};
use store::{Backend, Label, RunInput, Steering, Store, VectorColumn};
use store_artifacts::{ArtifactRecord, Artifacts, NewArtifact};
use verifier::steps::{steering_array, steering_log, step_inputs};
use verifier::testutil::RandomSpec;
use verifier::{SteeringStep, Verifier};

const EPISODES: u32 = 12;
const N: usize = 8;
const EVERY: usize = 3;

fn rollout(i: u32) -> store::EpisodeInput {
    let steps = 9 + (i as usize * 5) % 11;
    let phase = i as f32 * 0.41;
    store::EpisodeInput {
        observations: vec![VectorColumn {
            name: "pos".into(),
            dim: 2,
            values: (0..steps * 2).map(|k| ((k / 2) as f32 * 0.3 + phase + (k % 2) as f32).sin()).collect(),
        }],
        ..test_support::episode(i, steps, if i.is_multiple_of(3) { Label::Failure } else { Label::Success })
    }
}

fn artifact(dir: &std::path::Path, seed: u64, chunk_len: usize) -> (std::path::PathBuf, Verifier) {
    let spec = RandomSpec {
        obs_keys: vec![("pos".into(), 2)],
        obs_history: 2,
        chunk_len,
        action_dim: 3,
        ..RandomSpec::nav()
    };
    let (cfg, w) = spec.build(seed);
    let d = dir.join(format!("artifact-{seed}-{chunk_len}"));
    verifier::ArtifactFiles::build(&cfg, &w).unwrap().write_dir(&d).unwrap();
    let v = Verifier::load_dir(&d).unwrap();
    (d, v)
}

/// What the robot logged for episode `ep`: best-of-N every `EVERY` steps on the verifier input the
/// store will build for that step, with candidates drawn from a fixed sequence.
fn steer_episode(v: &Verifier, i: u32) -> Vec<SteeringStep> {
    let ep = rollout(i);
    let meta = store::steps::EpisodeMeta { episode_id: "e", policy: "pol", checkpoint: "c1" };
    let steps = ep.len();
    let batch = store::steps::episode_batch(ep, &meta, &HashMap::new()).unwrap();
    let inputs = step_inputs(v.config(), &batch).unwrap();
    let (od, ad) = (v.obs_dim(), v.act_dim());
    let mut log = Vec::new();
    for t in (0..steps).step_by(EVERY) {
        let cands: Vec<f32> =
            (0..N * ad).map(|k| (k as f32 * 1.37 + t as f32 * 0.71 + i as f32 * 2.3).sin() * 1.7).collect();
        let obs = &inputs.obs[t * od..(t + 1) * od];
        let (best, mut steps) = steer::best_of_n_recorded(v, None, obs, &[t as u32], &cands, N).unwrap();
        assert_eq!(steps.len(), 1);
        assert_eq!(best.index[0], steps[0].chosen as usize);
        log.append(&mut steps);
    }
    log
}

async fn publish(store: &Store, d: &std::path::Path) -> ArtifactRecord {
    let new = NewArtifact {
        dir: d,
        policy: "pol",
        checkpoint: "c1",
        kind: "classifier",
        split_id: None,
        job_id: None,
    };
    store.publish_artifact(new).await.unwrap()
}

async fn round_trip(store: Store) {
    let dir = tempfile::tempdir().unwrap();
    let (d, v) = artifact(dir.path(), 5, 4);
    let (d2, other) = artifact(dir.path(), 6, 4);
    let (d3, wrong_chunk) = artifact(dir.path(), 7, 2);
    let rec = publish(&store, &d).await;
    let other_rec = publish(&store, &d2).await;
    publish(&store, &d3).await;

    // The steered run: every episode but the last logged its best-of-N steps.
    let mut logs = Vec::new();
    let mut w = store.begin_ingest(test_support::source("steered"), "pol", "c1").await.unwrap();
    w.set_run(RunInput {
        name: "bon8".into(),
        steering: Steering::Bon { n: N as u32 },
        artifact_id: Some(rec.id.clone()),
        tags: vec![],
    })
    .unwrap();
    for i in 0..EPISODES {
        let ep = rollout(i);
        if i + 1 == EPISODES {
            w.add_episode(ep).await.unwrap();
            continue;
        }
        let log = steer_episode(&v, i);
        let col = steering_array(&log, ep.len()).unwrap();
        w.add_episode_steered(ep, col).await.unwrap();
        logs.push(log);
    }
    w.commit("steered").await.unwrap();
    let logged_steps: usize = logs.iter().map(Vec::len).sum();

    // The store gives every record back as it was logged (candidates on the f16 grid).
    let eps = store
        .episodes(&store::EpisodeFilter { policy: Some("pol".into()), ..Default::default() })
        .await
        .unwrap();
    let mut eps = eps;
    eps.sort_by_key(|e| e.source_index);
    for (e, log) in eps.iter().zip(&logs) {
        let steps = store.read_steps(&e.id, None).await.unwrap();
        assert_eq!(&steering_log(&steps).unwrap(), log, "episode {}", e.source_index);
    }
    let last = store.read_steps(&eps[EPISODES as usize - 1].id, None).await.unwrap();
    assert!(steering_log(&last).unwrap().is_empty());

    // The same artifact and N: every choice and every score, bit for bit.
    let spec = ReplaySpec { run: "bon8".into(), ..Default::default() };
    let same = replay(&store, &v, &rec.id, &spec).await.unwrap();
    assert_eq!(same.steps as usize, logged_steps);
    assert_eq!((same.changed, same.max_score_difference), (0, Some(0.0)));
    assert_eq!((same.episodes, same.episodes_without_telemetry), (EPISODES as usize, 1));
    assert_eq!(same.logged_n, vec![N]);
    assert_eq!(same.logged_artifacts, vec![rec.id.clone()]);
    assert_eq!(same.mean_margin, 0.0);
    // At the version the run was written in, the same (the run filter on a version's labels).
    let head = store.head_version().await.unwrap();
    let at_version =
        replay(&store, &v, &rec.id, &ReplaySpec { version: Some(head), ..spec.clone() }).await.unwrap();
    assert_eq!(at_version, same);

    // The first 3 of 8 candidates: changed exactly where the logged pick is not the best of them.
    let k = 3;
    let expect =
        logs.iter().flatten().filter(|s| steer::select_best(&s.scores[..k]) != s.chosen as usize).count();
    let fewer = replay(&store, &v, &rec.id, &ReplaySpec { n: Some(k), ..spec.clone() }).await.unwrap();
    assert!(expect > 0 && expect < logged_steps, "the fixture exercises both outcomes ({expect})");
    assert_eq!(fewer.changed as usize, expect);
    assert_eq!(fewer.max_score_difference, None);
    // Same artifact, fewer candidates: its pick never scores above the logged one.
    assert!(fewer.mean_margin < 0.0 && fewer.median_margin <= 0.0, "{fewer:?}");

    // Another artifact: its own argmax over the logged candidates, at the stored observations.
    let mut expect_other = 0;
    for (e, log) in eps.iter().zip(&logs) {
        let steps = store.read_steps(&e.id, None).await.unwrap();
        let inputs = step_inputs(other.config(), &steps).unwrap();
        let od = other.obs_dim();
        for s in log {
            let t = s.t as usize;
            let scores = other.score(&inputs.obs[t * od..(t + 1) * od], &[s.t], &s.candidates, N).unwrap();
            expect_other += usize::from(steer::select_best(&scores) != s.chosen as usize);
        }
    }
    let by_other = replay(&store, &other, &other_rec.id, &spec).await.unwrap();
    assert_eq!(by_other.changed as usize, expect_other);
    assert!(by_other.changed > 0 && by_other.mean_margin > 0.0);
    assert!(by_other.mean_logged_regret.unwrap() >= 0.0, "the logging verifier preferred its own picks");

    // Bad input: an artifact of another chunk length, n = 0, a run without telemetry.
    let e = replay(&store, &wrong_chunk, "x", &spec).await.unwrap_err().to_string();
    assert!(e.contains("logged chunks of 12 values") && e.contains("takes 6"), "{e}");
    assert!(replay(&store, &v, &rec.id, &ReplaySpec { n: Some(0), ..spec.clone() }).await.is_err());
    let mut w = store.begin_ingest(test_support::source("unsteered"), "pol", "c1").await.unwrap();
    w.set_run(RunInput { name: "plain".into(), steering: Steering::Base, artifact_id: None, tags: vec![] })
        .unwrap();
    w.add_episode(rollout(100)).await.unwrap();
    w.commit("plain").await.unwrap();
    let e = replay(&store, &v, &rec.id, &ReplaySpec { run: "plain".into(), ..Default::default() })
        .await
        .unwrap_err()
        .to_string();
    assert!(e.contains("holds no steering telemetry"), "{e}");
    let e = replay(&store, &v, &rec.id, &ReplaySpec { run: "nope".into(), ..Default::default() })
        .await
        .unwrap_err()
        .to_string();
    assert!(e.contains("no run is named"), "{e}");

    // A steering column of the wrong length is refused and the store stays as it was.
    let head = store.head_version().await.unwrap();
    let mut w = store.begin_ingest(test_support::source("bad-steering"), "pol", "c1").await.unwrap();
    let ep = rollout(200);
    let col = steering_array(&logs[0], ep.len() + 1).unwrap();
    let e = w.add_episode_steered(ep, col).await.unwrap_err().to_string();
    assert!(e.contains("the steering column has"), "{e}");
    w.abort().await.unwrap();
    assert_eq!(store.head_version().await.unwrap(), head);
}

#[test]
fn steering_array_refuses_inconsistent_logs() {
    let s = SteeringStep {
        t: 2,
        artifact_id: "a".into(),
        candidates: vec![0.5; 8],
        scores: vec![0.1, 0.9],
        chosen: 1,
        latency_us: 3,
    };
    assert!(steering_array(std::slice::from_ref(&s), 3).is_ok());
    let e = steering_array(std::slice::from_ref(&s), 2).unwrap_err().to_string();
    assert!(e.contains("outside the episode's 2 steps"), "{e}");
    let e = steering_array(&[s.clone(), s.clone()], 5).unwrap_err().to_string();
    assert!(e.contains("two steering steps at t=2"), "{e}");
    let e = steering_array(&[SteeringStep { chosen: 2, ..s }], 5).unwrap_err().to_string();
    assert!(e.contains("chosen index 2 of 2"), "{e}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sqlite_telemetry_round_trip_and_replay() {
    let dir = tempfile::tempdir().unwrap();
    round_trip(open_test_store(Backend::Sqlite, dir.path(), "replay").await).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn postgres_telemetry_round_trip_and_replay() {
    if !test_support::require_postgres() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    round_trip(open_test_store(Backend::Postgres, dir.path(), "replay").await).await;
}
