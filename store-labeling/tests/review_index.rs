//! The review orders walk an index of each episode's stored review score (migration 0014), kept
//! by the writes that change it. Property-style, on both catalogs: after every step of a random
//! history (scores stored for several artifacts, the `latest` classifier moving by publish and by
//! alias, the policy's setting set and cleared, labels changing), every page of both orders, with
//! and without further filters, equals the order recomputed from the public reads (each
//! episode's review artifact, its score by it, its label).

use std::collections::HashMap;
use store::*;
use store_artifacts::{Artifacts, NewArtifact};
use store_labeling::{ReviewOrder, ReviewQueue};

struct Rng(evalstats::splitmix::SplitMix64);
impl Rng {
    fn below(&mut self, n: usize) -> usize {
        (self.0.next_u64() % n as u64) as usize
    }
    /// Scores with ties and the exact midpoint, so the tie-break by id is exercised.
    fn score(&mut self) -> f64 {
        [0.5, 0.25, 0.75, 0.9, 0.1, 0.5, 0.625][self.below(7)]
    }
}

/// Publishes a classifier for `policy/checkpoint` (distinct bytes per `n`: a new artifact).
async fn publish(store: &Store, policy: &str, checkpoint: &str, n: usize) -> String {
    let dir = tempfile::tempdir().unwrap();
    let config = format!("{{\"kind\":\"classifier\",\"n\":{n}}}");
    std::fs::write(dir.path().join("config.json"), &config).unwrap();
    std::fs::write(dir.path().join("model.safetensors"), format!("weights {n}")).unwrap();
    let manifest = serde_json::json!({"schema_version": 1, "files": {
        "config.json": sha256_hex(config.as_bytes()),
        "model.safetensors": sha256_hex(format!("weights {n}").as_bytes())}});
    std::fs::write(dir.path().join("manifest.json"), serde_json::to_vec(&manifest).unwrap()).unwrap();
    let new =
        NewArtifact { dir: dir.path(), policy, checkpoint, kind: "classifier", split_id: None, job_id: None };
    store.publish_artifact(new).await.unwrap().id
}

/// The order's key, as `review.rs` documents it (lower first).
fn key(order: ReviewOrder, score: Option<f64>, label: Label) -> f64 {
    match (order, score) {
        (_, None) => 9.0,
        (ReviewOrder::Uncertain, Some(s)) => (s - 0.5).abs(),
        (ReviewOrder::Disagreement, Some(s)) => match label {
            Label::Success => s - 1.0,
            Label::Failure => 0.0 - s,
            Label::Unknown => 8.0,
        },
        (ReviewOrder::Source, _) => unreachable!(),
    }
}

/// Every page (of 7) of the queue.
async fn walk(store: &Store, filter: &EpisodeFilter, order: ReviewOrder) -> Vec<(String, Option<f64>)> {
    let (mut out, mut cursor) = (Vec::new(), None::<String>);
    loop {
        let page = store.review_queue(filter, order, cursor.as_deref(), 7).await.unwrap();
        let Some(last) = page.last() else { break };
        cursor = Some(last.cursor.clone());
        out.extend(page.iter().map(|e| (e.episode.id.clone(), e.score)));
        assert!(out.len() <= 1000, "the walk does not end");
    }
    out
}

async fn check(store: &Store, step: &str) {
    let all =
        store.episodes(&EpisodeFilter { policy: Some("pol".into()), ..Default::default() }).await.unwrap();
    let mut artifact: HashMap<String, Option<String>> = HashMap::new();
    for e in &all {
        if !artifact.contains_key(&e.checkpoint) {
            artifact
                .insert(e.checkpoint.clone(), store.review_artifact_for("pol", &e.checkpoint).await.unwrap());
        }
    }
    let mut truth = Vec::new();
    for e in &all {
        let score = match &artifact[&e.checkpoint] {
            Some(a) => match store.episode_score(&e.id, Some(a)).await {
                Ok(s) => Some(s.score),
                Err(StoreError::NotFound { .. }) => None,
                Err(err) => panic!("{err}"),
            },
            None => None,
        };
        truth.push((e.id.clone(), e.checkpoint.clone(), e.label, score));
    }
    for order in [ReviewOrder::Uncertain, ReviewOrder::Disagreement] {
        let filters = [
            EpisodeFilter { policy: Some("pol".into()), ..Default::default() },
            EpisodeFilter { policy: Some("pol".into()), checkpoint: Some("c2".into()), ..Default::default() },
            EpisodeFilter { policy: Some("pol".into()), label: Some(Label::Unknown), ..Default::default() },
        ];
        for f in filters {
            let mut want: Vec<(f64, String, Option<f64>)> = truth
                .iter()
                .filter(|(_, c, l, _)| {
                    f.checkpoint.as_ref().is_none_or(|x| x == c) && f.label.is_none_or(|x| x == *l)
                })
                .map(|(id, _, l, s)| (key(order, *s, *l), id.clone(), *s))
                .collect();
            want.sort_by(|a, b| a.0.total_cmp(&b.0).then_with(|| a.1.cmp(&b.1)));
            let want: Vec<(String, Option<f64>)> = want.into_iter().map(|(_, id, s)| (id, s)).collect();
            assert_eq!(walk(store, &f, order).await, want, "{step}: {order:?} {f:?}");
        }
    }
}

async fn review_orders_follow_every_write(db: Backend) {
    let dir = tempfile::tempdir().unwrap();
    let store = test_support::open_test_store(db, dir.path(), "review").await;
    let mut ids = Vec::new();
    for (n, (policy, ckpt)) in [("pol", "c1"), ("pol", "c2"), ("other", "c1")].into_iter().enumerate() {
        let mut w = store.begin_ingest(test_support::source(&format!("src{n}")), policy, ckpt).await.unwrap();
        for i in 0..12 {
            let label = [Label::Unknown, Label::Success, Label::Failure][i as usize % 3];
            let id = w.add_episode(test_support::two_step_episode(i, Some("t"), label)).await.unwrap();
            if policy == "pol" {
                ids.push(id);
            }
        }
        w.commit("episodes").await.unwrap();
    }
    let mut rng = Rng(evalstats::splitmix::SplitMix64(0x9e37_79b9_7f4a_7c15));
    let mut artifacts = vec![publish(&store, "pol", "c1", 0).await];
    check(&store, "no scores").await;
    let mut published = 1;
    for step in 0..36 {
        let what = match rng.below(6) {
            0 | 1 => {
                let a = artifacts[rng.below(artifacts.len())].clone();
                // One row per episode (a batch with an episode twice is not a score job's).
                let rows: Vec<(String, f64, Vec<f32>)> = (0..1 + rng.below(10))
                    .map(|_| (ids[rng.below(ids.len())].clone(), rng.score()))
                    .collect::<HashMap<_, _>>()
                    .into_iter()
                    .map(|(id, s)| (id, s, vec![0.5]))
                    .collect();
                store.put_episode_scores(&a, None, rows).await.unwrap();
                format!("scores by {a}")
            }
            2 => {
                let ckpt = ["c1", "c2"][rng.below(2)];
                artifacts.push(publish(&store, "pol", ckpt, published).await);
                published += 1;
                format!("published for {ckpt}")
            }
            3 => {
                let a = artifacts[rng.below(artifacts.len())].clone();
                store.set_alias("latest", &a).await.unwrap();
                format!("latest moved to {a}")
            }
            4 => {
                if rng.below(2) == 0 {
                    let a = artifacts[rng.below(artifacts.len())].clone();
                    store.set_review_artifact("pol", &a, "admin").await.unwrap();
                    format!("setting {a}")
                } else {
                    store.clear_review_artifact("pol").await.unwrap();
                    "setting cleared".into()
                }
            }
            _ => {
                let updates = (0..1 + rng.below(6))
                    .map(|_| LabelUpdate {
                        episode_id: ids[rng.below(ids.len())].clone(),
                        label: [Label::Unknown, Label::Success, Label::Failure][rng.below(3)],
                        expect_revision: None,
                        note: None,
                    })
                    .collect();
                store.set_labels(updates, "labeler", "human").await.unwrap();
                "labels".into()
            }
        };
        check(&store, &format!("step {step} ({what})")).await;
    }
}

#[tokio::test]
async fn review_orders_follow_every_write_sqlite() {
    review_orders_follow_every_write(Backend::Sqlite).await;
}
#[tokio::test]
async fn review_orders_follow_every_write_postgres() {
    review_orders_follow_every_write(Backend::Postgres).await;
}
