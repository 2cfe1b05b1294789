//! Calibrating and evaluating a monitor on a real store (both catalogs), and the robot's monitor
//! (`steer::Monitor`) stepping the stored episodes' verifier inputs to the same alarms.

use std::collections::HashMap;

use monitor::{calibrate, calibration_draws, evaluate, CalibrateSpec};
use store::test_support::{self, open_test_store};
use store::{Backend, EpisodeRecord, Label, Store, VectorColumn};
use store_artifacts::{ArtifactRecord, Artifacts, Monitors, NewArtifact, NewMonitor};
use store_labeling::{Consensus, NewVote, Span, VerdictData};
use verifier::monitor::{
    conformal_threshold, peak, training_conditional_threshold, MonitorRecord, Statistic,
    SPLIT_CONFORMAL_PEAK, SPLIT_CONFORMAL_PEAK_PAC,
};
use verifier::testutil::RandomSpec;
use verifier::{StepScorer, Verifier};

const EPISODES: u32 = 90;

/// Episode i: 10–25 steps of a smooth 2-D position; one in three fails.
fn rollout(i: u32) -> store::EpisodeInput {
    let steps = 10 + (i as usize * 7) % 16;
    let label = if i.is_multiple_of(3) { Label::Failure } else { Label::Success };
    let phase = i as f32 * 0.37;
    store::EpisodeInput {
        observations: vec![VectorColumn {
            name: "pos".into(),
            dim: 2,
            values: (0..steps * 2).map(|k| ((k / 2) as f32 * 0.2 + phase + (k % 2) as f32).sin()).collect(),
        }],
        action: VectorColumn {
            name: "action".into(),
            dim: 3,
            values: (0..steps * 3).map(|k| (k as f32 * 0.3 + phase).cos()).collect(),
        },
        ..test_support::episode(i, steps, label)
    }
}

async fn seeded_store(store: &Store, dir: &std::path::Path) -> (ArtifactRecord, Verifier, Verifier) {
    let mut w = store.begin_ingest(test_support::source("monitor"), "pol", "c1").await.unwrap();
    for i in 0..EPISODES {
        w.add_episode(rollout(i)).await.unwrap();
    }
    w.commit("monitor test").await.unwrap();
    let spec = RandomSpec {
        obs_keys: vec![("pos".into(), 2)],
        obs_history: 2,
        chunk_len: 4,
        action_dim: 3,
        ..RandomSpec::nav()
    };
    let load = |seed: u64| {
        let (cfg, w) = spec.build(seed);
        let d = dir.join(format!("artifact-{seed}"));
        verifier::ArtifactFiles::build(&cfg, &w).unwrap().write_dir(&d).unwrap();
        (d.clone(), Verifier::load_dir(&d).unwrap())
    };
    let (d, v) = load(3);
    let (d2, other) = load(4);
    let mut published = Vec::new();
    for d in [&d, &d2] {
        let new = NewArtifact {
            dir: d,
            policy: "pol",
            checkpoint: "c1",
            kind: "classifier",
            split_id: None,
            job_id: None,
        };
        published.push(store.publish_artifact(new).await.unwrap());
    }
    let rec = published.swap_remove(0);
    assert_eq!(v.id(), Some(rec.id.as_str()));
    (rec, v, other)
}

async fn episodes(store: &Store) -> Vec<EpisodeRecord> {
    let sel = store::Selection { policy: Some("pol".into()), ..Default::default() };
    store::select(store, &sel).await.unwrap().episodes
}

async fn calibrate_evaluate_and_step(store: Store) {
    let dir = tempfile::tempdir().unwrap();
    let (artifact, v, other) = seeded_store(&store, dir.path()).await;
    // A labeler marks where failure 3 went wrong: its onset is the span's start.
    store
        .cast_vote(
            NewVote {
                episode_id: episodes(&store).await.iter().find(|e| e.source_index == 3).unwrap().id.clone(),
                label: Label::Failure,
                data: VerdictData { failure_cause: None, spans: vec![Span { start_step: 6, end_step: 9 }] },
                note: None,
                expect_revision: None,
            },
            "ann",
        )
        .await
        .unwrap();
    store.snapshot_labels("ann", "spans").await.unwrap();

    let spec = CalibrateSpec {
        alpha: 0.2,
        confidence: None,
        statistic: Statistic::RiskEma { smoothing: 0.5 },
        seed: 11,
        calibration_fraction: 0.5,
        version: None,
    };
    let cal = calibrate(&store, &v, &artifact, &spec).await.unwrap();
    let eps = episodes(&store).await;
    let by_id: HashMap<&str, &EpisodeRecord> = eps.iter().map(|e| (e.id.as_str(), e)).collect();
    let successes = eps.iter().filter(|e| e.label == Label::Success).count();
    assert_eq!(cal.record.calibration_episodes.len(), (successes as f64 * 0.5).round() as usize);
    assert_eq!(cal.evaluation.successes as usize + cal.record.calibration_episodes.len(), successes);
    assert_eq!(cal.evaluation.failures as usize, eps.len() - successes);
    assert_eq!(cal.evaluation.failures_with_spans, 1);

    // The threshold is the conformal order statistic of the calibration episodes' peaks, scored
    // here through the core's StepScorer, not the crate's pool.
    let cal_eps: Vec<EpisodeRecord> =
        cal.record.calibration_episodes.iter().map(|id| (*by_id[id.as_str()]).clone()).collect();
    let mut peaks = Vec::new();
    store::for_each_episode(&store, &cal_eps, |_, _, steps| {
        peaks.push(peak(spec.statistic, &v.score_steps(&steps).unwrap()));
        Ok::<_, store::StoreError>(())
    })
    .await
    .unwrap();
    assert_eq!(cal.record.threshold, conformal_threshold(&peaks, 0.2).unwrap());
    assert_eq!((cal.record.method.as_str(), cal.record.confidence), (SPLIT_CONFORMAL_PEAK, None));
    assert!(cal.marginal.is_none());

    // With a confidence: the training-conditional order statistic of the same peaks, its method
    // and confidence in the record, and the split-conformal one alongside for comparison.
    let pac =
        calibrate(&store, &v, &artifact, &CalibrateSpec { confidence: Some(0.9), ..spec }).await.unwrap();
    assert_eq!(pac.record.threshold, training_conditional_threshold(&peaks, 0.2, 0.1).unwrap());
    assert_eq!(pac.record.method, SPLIT_CONFORMAL_PEAK_PAC);
    assert_eq!(pac.record.confidence, Some(0.9));
    assert_eq!(pac.record.calibration_episodes, cal.record.calibration_episodes);
    assert!(pac.record.threshold >= cal.record.threshold);
    let (tau, marginal) = pac.marginal.clone().expect("the marginal threshold for comparison");
    assert_eq!((tau, &marginal), (cal.record.threshold, &cal.evaluation));
    assert!(pac.evaluation.false_alarms <= cal.evaluation.false_alarms);
    assert!(pac.evaluation.detected <= cal.evaluation.detected);

    // Calibration draws: seed s partitions the pool as `calibrate` with seed s does, and each
    // threshold's figures are what calibrating with it measures.
    let draws = calibration_draws(&store, &v, &artifact, &CalibrateSpec { confidence: Some(0.9), ..spec }, 4)
        .await
        .unwrap();
    assert_eq!(draws.draws.len(), 4);
    assert_eq!((draws.successes, draws.calibration, draws.failures), (successes, 30, eps.len() - successes));
    for seed in [0, 3] {
        let d = draws.draws[seed as usize];
        for (confidence, fig) in [(None, d.marginal), (Some(0.9), d.conditional)] {
            let c =
                calibrate(&store, &v, &artifact, &CalibrateSpec { seed, confidence, ..spec }).await.unwrap();
            assert_eq!(fig.threshold, c.record.threshold, "seed {seed} confidence {confidence:?}");
            assert_eq!(Some(fig.false_alarm_rate), c.evaluation.false_alarm_rate, "seed {seed}");
            assert_eq!(fig.detection_rate, c.evaluation.detection_rate, "seed {seed}");
        }
    }
    let above = draws.draws.iter().filter(|d| d.conditional.false_alarm_rate > 0.2).count();
    assert_eq!(draws.conditional.above_alpha, above as f64 / 4.0);
    assert!(calibration_draws(&store, &v, &artifact, &spec, 4).await.is_err(), "draws need a confidence");

    // Stored and read back, the record reproduces the evaluation exactly.
    let json = serde_json::to_vec(&cal.record).unwrap();
    let entry = store
        .put_monitor(NewMonitor {
            record_json: &json,
            policy: "pol",
            checkpoint: "c1",
            artifact_id: &artifact.id,
            alpha: cal.record.alpha,
            threshold: cal.record.threshold,
            evaluation: Some(&serde_json::to_value(&cal.evaluation).unwrap()),
            created_by: "test",
        })
        .await
        .unwrap();
    assert_eq!(entry.aliases, vec!["latest".to_string()]);
    let resolved = store.resolve_monitor("pol/c1@latest").await.unwrap();
    assert_eq!(resolved.id, entry.id);
    let record = MonitorRecord::from_json(resolved.record.to_string().as_bytes()).unwrap();
    assert_eq!(record, cal.record);
    let (again, traces) = evaluate(&store, &v, &artifact, &record, None).await.unwrap();
    assert_eq!(again, cal.evaluation);
    let stored: monitor::Evaluation = serde_json::from_value(resolved.evaluation.clone().unwrap()).unwrap();
    assert_eq!(stored, cal.evaluation);

    // The robot's monitor, fed each stored step's verifier inputs one at a time, raises the same
    // alarms with the same statistics as the offline evaluation.
    let traced: Vec<EpisodeRecord> = traces.iter().map(|t| (*by_id[t.episode_id.as_str()]).clone()).collect();
    let mut robot = steer::Monitor::for_verifier(&v, record.clone()).unwrap();
    let (od, ad) = (v.obs_dim(), v.act_dim());
    let mut checked = 0;
    store::for_each_episode(&store, &traced, |i, _, steps| {
        let inputs = verifier::steps::step_inputs(v.config(), &steps).unwrap();
        robot.reset();
        for (k, want) in traces[i].steps.iter().enumerate() {
            let got = robot
                .update(&inputs.obs[k * od..(k + 1) * od], &inputs.act[k * ad..(k + 1) * ad], inputs.t[k])
                .unwrap();
            assert!(
                (got.statistic - want.statistic).abs() < 1e-5,
                "episode {i} step {k}: {got:?} vs {want:?}"
            );
            assert_eq!(got.alarm, want.alarm, "episode {i} step {k}");
            checked += 1;
        }
        Ok::<_, store::StoreError>(())
    })
    .await
    .unwrap();
    assert!(checked > 500, "{checked} steps");

    // Bad input: the record on another artifact is refused, by the robot and offline.
    let e = steer::Monitor::for_verifier(&other, record.clone()).err().expect("refused").to_string();
    assert!(e.contains(&format!("calibrated for verifier artifact {}", artifact.id)), "{e}");
    let other_rec = store.artifact(other.id().unwrap()).await.unwrap();
    assert!(matches!(
        evaluate(&store, &other, &other_rec, &record, None).await,
        Err(verifier::stored::StoredEpisodesError::Verifier(_))
    ));
    assert!(evaluate(&store, &v, &other_rec, &record, None).await.is_err());
    let refused = store
        .put_monitor(NewMonitor {
            record_json: &json,
            policy: "pol",
            checkpoint: "c1",
            artifact_id: &other_rec.id,
            alpha: 0.2,
            threshold: record.threshold,
            evaluation: None,
            created_by: "test",
        })
        .await;
    assert!(refused.unwrap_err().to_string().contains("artifact_id"));

    // Too few successes for the asked α: a message naming the count, nothing stored.
    let strict = CalibrateSpec { alpha: 0.01, ..spec };
    let e = calibrate(&store, &v, &artifact, &strict).await.unwrap_err().to_string();
    assert!(e.contains("needs at least 99 successful episodes"), "{e}");
    // The training-conditional threshold at α = 0.2 and 1 − δ = 0.999 needs ⌈ln 0.001 / ln 0.8⌉ = 31
    // calibration successes; the pool gives 30.
    let sure = CalibrateSpec { confidence: Some(0.999), ..spec };
    let e = calibrate(&store, &v, &artifact, &sure).await.unwrap_err().to_string();
    assert!(e.contains("needs at least 31 successful episodes") && e.contains("got 30"), "{e}");
    let e = calibrate(&store, &v, &artifact, &CalibrateSpec { confidence: Some(1.0), ..spec })
        .await
        .unwrap_err()
        .to_string();
    assert!(e.contains("must be in (0, 1)"), "{e}");
    assert_eq!(store.monitors(Some("pol"), None, None).await.unwrap().len(), 1);
}

#[tokio::test]
async fn sqlite_calibrate_evaluate_and_step() {
    let dir = tempfile::tempdir().unwrap();
    calibrate_evaluate_and_step(open_test_store(Backend::Sqlite, dir.path(), "monitor").await).await;
}

#[tokio::test]
async fn postgres_calibrate_evaluate_and_step() {
    if !test_support::require_postgres() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    calibrate_evaluate_and_step(open_test_store(Backend::Postgres, dir.path(), "monitor").await).await;
}
