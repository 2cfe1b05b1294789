//! Versions that cost what they change (spans of labels and counts, delta label files) read back
//! exactly as a recomputation from the whole history would, on both catalogs: a seeded random
//! history of ingests, relabels, snapshots and deletions is replayed into a model kept here, and
//! at every version the episode listings (plain, filtered and by label), the frozen counts, the
//! scoreboard's counts, a split and the labels files equal the model's. A few checkpoints are
//! written part-way, so chains of both kinds are read.

use std::collections::BTreeMap;
use store::*;
use store_compare::{ScoreboardRequest, Scoreboards};

/// xorshift64*: a seeded history without a dependency.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n as u64) as usize
    }
    fn label(&mut self) -> Label {
        [Label::Success, Label::Failure, Label::Unknown][self.below(3)]
    }
}

/// What the test knows of an episode: where it belongs and its current label.
#[derive(Clone, Debug, PartialEq)]
struct Known {
    checkpoint: String,
    steered: bool,
    run: Option<String>,
    label: Label,
}

type Model = BTreeMap<String, Known>;

/// Ingests `n` episodes into `ckpt` as `run` (None: no run) with random labels; returns their ids.
async fn ingest(store: &Store, rng: &mut Rng, tag: &str, ckpt: &str, run: Option<&str>, model: &mut Model) {
    let n = 1 + rng.below(5) as u32;
    let mut w = store.begin_ingest(test_support::source(tag), "pol", ckpt).await.unwrap();
    let steered = run == Some("bon");
    if let Some(r) = run {
        let steering = if steered { Steering::Bon { n: 4 } } else { Steering::Base };
        w.set_run(RunInput::new(r, steering)).unwrap();
    }
    let labels: Vec<Label> = (0..n).map(|_| rng.label()).collect();
    for (i, l) in labels.iter().enumerate() {
        let task = if i % 2 == 0 { Some("reach") } else { Some("push") };
        w.add_episode(test_support::two_step_episode(i as u32, task, *l)).await.unwrap();
    }
    let v = w.commit("history").await.unwrap().version;
    let sha = sha256_hex(tag.as_bytes());
    let added = store.episodes(&EpisodeFilter { version: Some(v), ..Default::default() }).await.unwrap();
    let mut found = 0;
    for e in added.iter().filter(|e| e.source_sha256 == sha) {
        found += 1;
        let known = Known {
            checkpoint: ckpt.into(),
            steered,
            run: run.map(str::to_string),
            label: labels[e.source_index as usize],
        };
        model.insert(e.id.clone(), known);
    }
    assert_eq!(found, n as usize);
}

fn counts_of<'a>(eps: impl Iterator<Item = &'a Known>) -> LabelCounts {
    let mut c = LabelCounts::default();
    for k in eps {
        match k.label {
            Label::Success => c.success += 1,
            Label::Failure => c.failure += 1,
            Label::Unknown => c.unknown += 1,
        }
        c.total += 1;
    }
    c
}

/// Everything a version is read through, against the model of that version.
async fn check_version(store: &Store, v: i64, want: &Model) {
    let ids_labels = |eps: Vec<EpisodeRecord>| -> BTreeMap<String, Label> {
        eps.into_iter().map(|e| (e.id, e.label)).collect()
    };
    let all: BTreeMap<String, Label> = want.iter().map(|(id, k)| (id.clone(), k.label)).collect();
    let f = EpisodeFilter { version: Some(v), ..Default::default() };
    assert_eq!(ids_labels(store.episodes(&f).await.unwrap()), all, "version {v}: listing");
    // Paged by keyset: the same episodes.
    let mut paged = BTreeMap::new();
    let mut after = None;
    loop {
        let page =
            EpisodeFilter { version: Some(v), after: after.clone(), limit: Some(3), ..Default::default() };
        let eps = store.episodes(&page).await.unwrap();
        if eps.is_empty() {
            break;
        }
        after = eps.last().map(|e| e.id.clone());
        paged.extend(ids_labels(eps));
    }
    assert_eq!(paged, all, "version {v}: pages");
    for ckpt in ["c1", "c2"] {
        let of: Model =
            want.iter().filter(|(_, k)| k.checkpoint == ckpt).map(|(i, k)| (i.clone(), k.clone())).collect();
        let f = EpisodeFilter {
            version: Some(v),
            policy: Some("pol".into()),
            checkpoint: Some(ckpt.into()),
            ..Default::default()
        };
        let got = ids_labels(store.episodes(&f).await.unwrap());
        assert_eq!(got, of.iter().map(|(i, k)| (i.clone(), k.label)).collect(), "version {v}: {ckpt}");
        let cf = CountFilter { version: Some(v), checkpoint: Some(ckpt.into()), ..Default::default() };
        assert_eq!(
            store.episode_counts(&cf).await.unwrap(),
            counts_of(of.values()),
            "version {v}: counts {ckpt}"
        );
        assert_eq!(store.recount_episodes(&cf).await.unwrap(), counts_of(of.values()));
    }
    for label in [Label::Success, Label::Failure, Label::Unknown] {
        let f = EpisodeFilter { version: Some(v), label: Some(label), ..Default::default() };
        let got: Vec<String> = store.episodes(&f).await.unwrap().into_iter().map(|e| e.id).collect();
        let exp: Vec<String> =
            want.iter().filter(|(_, k)| k.label == label).map(|(i, _)| i.clone()).collect();
        assert_eq!(got, exp, "version {v}: label {label:?}");
    }
    let cf = CountFilter { version: Some(v), ..Default::default() };
    assert_eq!(store.episode_counts(&cf).await.unwrap(), counts_of(want.values()), "version {v}: counts");

    // The scoreboard's frozen counts equal a GROUP BY, and the model's per checkpoint and run.
    let req = ScoreboardRequest { policy: "pol".into(), version: Some(v), ..Default::default() };
    let frozen = store.scoreboard_counts(&req, v).await.unwrap();
    assert_eq!(frozen, store.recount_scoreboard(&req, v).await.unwrap(), "version {v}: scoreboard counts");
    if !want.is_empty() {
        let sb = store.scoreboard(&req).await.unwrap();
        let mut by_row: BTreeMap<(String, String), [u64; 2]> = BTreeMap::new();
        for r in &sb.rows {
            let c = by_row.entry((r.checkpoint.clone(), r.run_name.clone())).or_default();
            c[0] += r.successes;
            c[1] += r.failures;
        }
        let mut exp: BTreeMap<(String, String), [u64; 2]> = BTreeMap::new();
        for k in want.values() {
            let c = exp.entry((k.checkpoint.clone(), k.run.clone().unwrap_or("-".into()))).or_default();
            match k.label {
                Label::Success => c[0] += 1,
                Label::Failure => c[1] += 1,
                Label::Unknown => {}
            }
        }
        assert_eq!(by_row, exp, "version {v}: scoreboard");
    }

    // A split pinned to the version takes its labeled on-policy episodes of c1.
    let members: Vec<(String, Label)> = want
        .iter()
        .filter(|(_, k)| k.checkpoint == "c1" && !k.steered && k.label != Label::Unknown)
        .map(|(i, k)| (i.clone(), k.label))
        .collect();
    let req = SplitRequest {
        policy: "pol".into(),
        checkpoint: "c1".into(),
        version: Some(v),
        off_policy_from: vec![],
        val_fraction: 0.25,
        seed: 3,
        actor: "test".into(),
        max_episodes: None,
    };
    match store.create_split(&req).await {
        Ok(split) => {
            let got: Vec<(String, Label)> = store
                .split_episodes(&split.id)
                .await
                .unwrap()
                .into_iter()
                .map(|m| (m.episode_id, m.label))
                .collect();
            let mut got = got;
            got.sort_by(|a, b| a.0.cmp(&b.0));
            assert_eq!(got, members, "version {v}: split");
        }
        Err(StoreError::Conflict(_)) => assert!(members.is_empty(), "version {v}: no split of {members:?}"),
        Err(e) => panic!("version {v}: {e}"),
    }

    // The labels files alone give the same labels.
    let files: BTreeMap<String, Label> =
        store.read_labels_files(v).await.unwrap().into_iter().map(|r| (r.episode_id, r.label)).collect();
    assert_eq!(files, all, "version {v}: labels files");
}

async fn random_history(store: Store, seed: u64) {
    let mut rng = Rng(seed);
    let mut model = Model::new();
    let mut history: Vec<(i64, Model)> = Vec::new();
    let mut n_sources = 0;
    for step in 0..40 {
        let head_before = store.head_version().await.unwrap();
        match rng.below(10) {
            0..=2 => {
                n_sources += 1;
                let ckpt = if rng.below(2) == 0 { "c1" } else { "c2" };
                let run = [None, Some("base"), Some("bon")][rng.below(3)];
                ingest(&store, &mut rng, &format!("h{seed}-{n_sources}"), ckpt, run, &mut model).await;
            }
            3..=6 if !model.is_empty() => {
                // Relabel a few (sometimes to the same label: a new revision, the same label).
                let ids: Vec<String> = model.keys().cloned().collect();
                let mut updates = Vec::new();
                for _ in 0..1 + rng.below(4) {
                    let id = ids[rng.below(ids.len())].clone();
                    if updates.iter().any(|u: &LabelUpdate| u.episode_id == id) {
                        continue;
                    }
                    let label = rng.label();
                    model.get_mut(&id).unwrap().label = label;
                    updates.push(LabelUpdate { episode_id: id, label, expect_revision: None, note: None });
                }
                store.set_labels(updates, "tester", "human").await.unwrap();
                if rng.below(2) == 0 {
                    store.snapshot_labels_if_changed("tester", &format!("step {step}")).await.unwrap();
                }
            }
            7 if model.len() > 2 => {
                let ids: Vec<String> = model.keys().cloned().collect();
                let gone = ids[rng.below(ids.len())].clone();
                model.remove(&gone);
                store.delete_episodes(&[gone], "tester", "bad rollout").await.unwrap();
            }
            8 if head_before > 2 => {
                // A checkpoint of some past version: later reads start from it.
                let v = 1 + rng.below(head_before as usize) as i64;
                let path = store.full_labels_file(v).await.unwrap();
                assert_eq!(store.labels_files(v).await.unwrap(), vec![path]);
            }
            _ => {
                store.snapshot_labels_if_changed("tester", "snapshot").await.unwrap();
            }
        }
        let head = store.head_version().await.unwrap();
        if head != head_before {
            assert_eq!(head, head_before + 1);
            // A version freezes every label written before it: the model as it stands now.
            history.push((head, model.clone()));
        }
    }
    assert!(history.len() >= 10, "a history of {} versions", history.len());
    for (v, want) in &history {
        check_version(&store, *v, want).await;
    }
    let last = store.head_version().await.unwrap();
    let versions = store.versions().await.unwrap();
    let deltas = versions.iter().filter(|v| v.labels_kind == "delta").count();
    assert!(deltas > versions.len() / 2, "{deltas} delta files of {}", versions.len());
    assert_eq!(versions.last().unwrap().version, last);
}

#[tokio::test]
async fn random_histories_read_back_as_recomputed_sqlite() {
    for seed in [1, 2, 3] {
        let dir = tempfile::tempdir().unwrap();
        random_history(test_support::open_test_store(Backend::Sqlite, dir.path(), "history").await, seed)
            .await;
    }
}

#[tokio::test]
async fn random_histories_read_back_as_recomputed_postgres() {
    if !test_support::require_postgres() {
        return;
    }
    for seed in [1, 2] {
        let dir = tempfile::tempdir().unwrap();
        random_history(test_support::open_test_store(Backend::Postgres, dir.path(), "history").await, seed)
            .await;
    }
}
