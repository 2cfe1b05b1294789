//! Lists and counts on both catalogs: keyset pages cover every episode exactly once while labels
//! change under them (now and at a past version, through each query shape), and the maintained
//! counts equal a recount of the rows after every kind of write — label writes, bulk and grouped
//! labels, ingests, snapshots, deletions, concurrent writers — now and at every version.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use store::*;

/// A small deterministic generator (xorshift).
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n as u64) as usize
    }
    fn label(&mut self) -> Label {
        [Label::Success, Label::Failure, Label::Unknown][self.below(3)]
    }
}

/// Ingests `n` episodes of `policy/ckpt` with a mix of tasks (one in five has none) and labels.
async fn ingest(store: &Store, tag: &str, policy: &str, ckpt: &str, n: u32) -> Vec<String> {
    let src = SourceInput {
        path: format!("/tmp/{tag}"),
        sha256: sha256_hex(tag.as_bytes()),
        format: "test".into(),
        size_bytes: 1,
        metadata: serde_json::json!({}),
    };
    let mut w = store.begin_ingest(src, policy, ckpt).await.unwrap();
    let mut ids = Vec::new();
    for i in 0..n {
        let task = [Some("reach"), Some("push"), None, Some("reach"), Some("lift")][i as usize % 5];
        let label = [Label::Unknown, Label::Success, Label::Unknown, Label::Failure][i as usize % 4];
        ids.push(w.add_episode(test_support::two_step_episode(i, task, label)).await.unwrap());
    }
    w.commit("lists test").await.unwrap();
    ids
}

fn filters(version: Option<i64>) -> Vec<CountFilter> {
    let f = |p: Option<&str>, c: Option<&str>, t: Option<&str>| CountFilter {
        version,
        policy: p.map(str::to_string),
        checkpoint: c.map(str::to_string),
        task: t.map(str::to_string),
    };
    vec![
        f(None, None, None),
        f(Some("pol"), None, None),
        f(Some("pol"), Some("c1"), None),
        f(Some("pol"), Some("c2"), Some("reach")),
        f(None, None, Some("push")),
        f(Some("other"), Some("c1"), None),
        f(Some("nobody"), None, None),
    ]
}

/// The maintained counts equal a recount of the rows, for several filters, now and at every version.
async fn check_counts(store: &Store, when: &str) {
    let mut versions: Vec<Option<i64>> = vec![None];
    versions.extend(store.versions().await.unwrap().iter().map(|v| Some(v.version)));
    for v in versions {
        for f in filters(v) {
            let kept = store.episode_counts(&f).await.unwrap();
            let recount = store.recount_episodes(&f).await.unwrap();
            assert_eq!(kept, recount, "{when}: counts for {f:?}");
            assert_eq!(kept.total, kept.success + kept.failure + kept.unknown);
        }
    }
    // And the totals match the listing.
    let all = store.episodes(&EpisodeFilter::default()).await.unwrap();
    let c = store.episode_counts(&CountFilter::default()).await.unwrap();
    assert_eq!(c.total as usize, all.len(), "{when}");
    assert_eq!(c.unknown as usize, all.iter().filter(|e| e.label == Label::Unknown).count(), "{when}");
}

fn upd(id: &str, label: Label) -> LabelUpdate {
    LabelUpdate { episode_id: id.to_string(), label, expect_revision: None, note: None }
}

async fn counts_follow_every_write(db: Backend) {
    let dir = tempfile::tempdir().unwrap();
    let store = test_support::open_test_store(db, dir.path(), "lists").await;
    let c = store.episode_counts(&CountFilter::default()).await.unwrap();
    assert_eq!(c, LabelCounts::default(), "an empty store counts nothing");
    let a = ingest(&store, "lists-a", "pol", "c1", 40).await;
    let b = ingest(&store, "lists-b", "pol", "c2", 30).await;
    let o = ingest(&store, "lists-o", "other", "c1", 10).await;
    check_counts(&store, "after three ingests").await;
    let head = store.episode_counts(&CountFilter::default()).await.unwrap();
    assert_eq!((head.total, head.unknown, head.success, head.failure), (80, 40, 21, 19));

    // Single writes, including one to the label it already has (no change) and a stale one.
    store.set_label(upd(&a[0], Label::Success), "alice", "human").await.unwrap();
    store.set_label(upd(&a[1], Label::Success), "alice", "human").await.unwrap();
    let stale = LabelUpdate { expect_revision: Some(7), ..upd(&a[2], Label::Failure) };
    assert!(matches!(store.set_label(stale, "alice", "human").await, Err(StoreError::LabelConflict { .. })));
    check_counts(&store, "after single writes").await;

    // Bulk: all or nothing.
    let bulk: Vec<_> = b[..10].iter().map(|id| upd(id, Label::Failure)).collect();
    store.set_labels(bulk, "bob", "human").await.unwrap();
    let mut refused: Vec<_> = b[10..20].iter().map(|id| upd(id, Label::Success)).collect();
    refused.push(upd("no-such-episode", Label::Success));
    assert!(store.set_labels(refused, "bob", "human").await.is_err());
    check_counts(&store, "after bulk labels (one refused)").await;

    // Group commit: per-item outcomes, the same episode twice, across checkpoints and policies.
    let items = vec![
        (upd(&a[3], Label::Unknown), "carol".to_string()),
        (upd(&a[3], Label::Success), "carol".to_string()),
        (LabelUpdate { expect_revision: Some(9), ..upd(&b[25], Label::Success) }, "carol".to_string()),
        (upd(&o[4], Label::Failure), "dave".to_string()),
        (upd("missing", Label::Failure), "dave".to_string()),
    ];
    let out = store.set_labels_each(items, "human").await.unwrap();
    assert_eq!(out.iter().filter(|r| r.is_ok()).count(), 3);
    check_counts(&store, "after a group commit").await;

    // A snapshot freezes the counts; later writes change the head only.
    let snap = store.snapshot_labels("alice", "freeze").await.unwrap();
    let frozen = CountFilter { version: Some(snap.version), ..Default::default() };
    let at_snap = store.episode_counts(&frozen).await.unwrap();
    assert_eq!(at_snap, store.episode_counts(&CountFilter::default()).await.unwrap());
    store
        .set_labels(a[4..14].iter().map(|id| upd(id, Label::Failure)).collect(), "erin", "human")
        .await
        .unwrap();
    assert_eq!(store.episode_counts(&frozen).await.unwrap(), at_snap, "a version's counts never change");
    check_counts(&store, "after a snapshot and more writes").await;

    // Deletions (with their current labels) and an ingest into an existing checkpoint.
    store.delete_episodes(&[a[0].clone(), a[5].clone(), o[4].clone()], "alice", "bad runs").await.unwrap();
    check_counts(&store, "after a deletion").await;
    assert!(
        store.set_label(upd(&a[0], Label::Unknown), "alice", "human").await.is_err(),
        "deleted: not writable"
    );
    ingest(&store, "lists-a2", "pol", "c1", 12).await;
    check_counts(&store, "after another ingest").await;

    // A rebuild from the rows changes nothing when the counts were right.
    let before = store.episode_counts(&CountFilter::default()).await.unwrap();
    store.rebuild_episode_counts().await.unwrap();
    assert_eq!(store.episode_counts(&CountFilter::default()).await.unwrap(), before);
    check_counts(&store, "after a rebuild").await;

    // An unknown version is an error, not zeros.
    let bad = CountFilter { version: Some(999), ..Default::default() };
    assert!(matches!(store.episode_counts(&bad).await, Err(StoreError::NotFound { .. })));
}

/// Concurrent writers (single and grouped) on the same few episodes: no deadlock on the counter
/// rows, and the counts still equal a recount.
async fn counts_under_concurrent_writers(db: Backend) {
    let dir = tempfile::tempdir().unwrap();
    let store = test_support::open_test_store(db, dir.path(), "lists").await;
    let mut ids = ingest(&store, "conc-a", "pol", "c1", 12).await;
    ids.extend(ingest(&store, "conc-b", "pol", "c2", 12).await);
    let mut tasks = Vec::new();
    for t in 0..8u64 {
        let store = store.clone();
        let ids = ids.clone();
        tasks.push(tokio::spawn(async move {
            let mut rng = Rng(0x9E37_79B9_7F4A_7C15 ^ (t + 1));
            for k in 0..15 {
                if k % 3 == 0 {
                    // Several episodes in one transaction, in an order of their own.
                    let items: Vec<_> = (0..4)
                        .map(|_| (upd(&ids[rng.below(ids.len())], rng.label()), format!("w{t}")))
                        .collect();
                    store.set_labels_each(items, "human").await.unwrap();
                } else {
                    let id = &ids[rng.below(ids.len())];
                    store.set_label(upd(id, rng.label()), &format!("w{t}"), "human").await.unwrap();
                }
            }
        }));
    }
    for t in tasks {
        t.await.unwrap();
    }
    check_counts(&store, "after concurrent writers").await;
}

/// Every page of a keyset walk, with labels changed between pages (behind and ahead of the cursor).
async fn walk(
    store: &Store,
    base: &EpisodeFilter,
    page: i64,
    mut between: impl FnMut(usize) -> Vec<LabelUpdate>,
) -> Vec<EpisodeRecord> {
    let mut out = Vec::new();
    let mut after: Option<String> = None;
    for n in 0.. {
        let f = EpisodeFilter { after: after.clone(), limit: Some(page), ..base.clone() };
        let got = store.episodes(&f).await.unwrap();
        assert!(got.len() as i64 <= page);
        for w in got.windows(2) {
            assert!(w[0].id < w[1].id, "pages are in id order");
        }
        if let (Some(a), Some(first)) = (&after, got.first()) {
            assert!(&first.id > a, "a page starts after its cursor");
        }
        let updates = between(n);
        if !updates.is_empty() {
            store.set_labels(updates, "walker", "human").await.unwrap();
        }
        after = got.last().map(|e| e.id.clone());
        let last = (got.len() as i64) < page;
        out.extend(got);
        if last {
            break;
        }
    }
    out
}

async fn pages_cover_every_episode_once(db: Backend) {
    let dir = tempfile::tempdir().unwrap();
    let store = test_support::open_test_store(db, dir.path(), "lists").await;
    let mut ids = ingest(&store, "pages-a", "pol", "c1", 45).await;
    ids.extend(ingest(&store, "pages-b", "pol", "c2", 38).await);
    ids.extend(ingest(&store, "pages-o", "other", "c1", 20).await);
    ids.sort();
    let mut rng = Rng(42);

    // No label filter: every visible episode exactly once, whatever happens to labels meanwhile.
    let all = walk(&store, &EpisodeFilter::default(), 7, |_| {
        (0..5).map(|_| upd(&ids[rng.below(ids.len())], rng.label())).collect()
    })
    .await;
    let got: Vec<&str> = all.iter().map(|e| e.id.as_str()).collect();
    assert_eq!(
        got,
        ids.iter().map(String::as_str).collect::<Vec<_>>(),
        "every episode exactly once, in id order"
    );

    // label=unknown, while episodes are labeled and unlabeled between pages: never one twice,
    // every returned one was unknown when read, and every episode that stayed unknown throughout
    // is there.
    for base in [
        EpisodeFilter { label: Some(Label::Unknown), ..Default::default() },
        EpisodeFilter {
            label: Some(Label::Unknown),
            policy: Some("pol".into()),
            checkpoint: Some("c1".into()),
            ..Default::default()
        },
        EpisodeFilter { label: Some(Label::Unknown), task: Some("reach".into()), ..Default::default() },
    ] {
        let scope: Vec<String> = store
            .episodes(&EpisodeFilter { label: None, ..base.clone() })
            .await
            .unwrap()
            .into_iter()
            .map(|e| e.id)
            .collect();
        let unknown_at_start: BTreeSet<String> =
            store.episodes(&base).await.unwrap().into_iter().map(|e| e.id).collect();
        let mut touched: BTreeSet<String> = BTreeSet::new();
        let pages = walk(&store, &base, 4, |_| {
            let ups: Vec<_> = (0..3).map(|_| upd(&scope[rng.below(scope.len())], rng.label())).collect();
            touched.extend(ups.iter().map(|u| u.episode_id.clone()));
            ups
        })
        .await;
        let mut seen = BTreeSet::new();
        for e in &pages {
            assert!(seen.insert(e.id.clone()), "{} twice for {base:?}", e.id);
            assert_eq!(e.label, Label::Unknown);
            assert!(scope.contains(&e.id), "{} is outside the filter {base:?}", e.id);
        }
        for id in unknown_at_start.difference(&touched) {
            assert!(seen.contains(id), "{id} stayed unknown but was skipped ({base:?})");
        }
    }

    // At a past version, through both query shapes: the frozen labels, every episode once,
    // labels changing meanwhile (they do not show).
    let v = store.snapshot_labels("alice", "freeze").await.unwrap().version;
    let frozen: HashMap<String, Label> = store
        .episodes(&EpisodeFilter { version: Some(v), ..Default::default() })
        .await
        .unwrap()
        .into_iter()
        .map(|e| (e.id, e.label))
        .collect();
    assert_eq!(frozen.len(), ids.len());
    let shapes = [
        EpisodeFilter { version: Some(v), ..Default::default() },
        EpisodeFilter { version: Some(v), label: Some(Label::Unknown), ..Default::default() },
        EpisodeFilter { version: Some(v), policy: Some("pol".into()), ..Default::default() },
        EpisodeFilter {
            version: Some(v),
            policy: Some("pol".into()),
            checkpoint: Some("c2".into()),
            label: Some(Label::Failure),
            ..Default::default()
        },
        EpisodeFilter { version: Some(v), label_source: Some("human".into()), ..Default::default() },
    ];
    for base in shapes {
        let expect: Vec<String> = {
            let mut v: Vec<String> = store.episodes(&base).await.unwrap().into_iter().map(|e| e.id).collect();
            v.sort();
            v
        };
        let pages = walk(&store, &base, 6, |_| {
            (0..4).map(|_| upd(&ids[rng.below(ids.len())], rng.label())).collect()
        })
        .await;
        let got: Vec<String> = pages.iter().map(|e| e.id.clone()).collect();
        assert_eq!(got, expect, "pages at version {v} for {base:?}");
        for e in &pages {
            assert_eq!(Some(&e.label), frozen.get(&e.id), "{} at version {v}", e.id);
            if let Some(l) = base.label {
                assert_eq!(e.label, l);
            }
            if let Some(p) = &base.policy {
                assert_eq!(&e.policy, p);
            }
        }
        if base.label.is_none() && base.policy.is_none() && base.label_source.is_none() {
            assert_eq!(got.len(), ids.len());
        }
    }
    check_counts(&store, "after the walks").await;

    // The frozen label's actor and time come from its audit event.
    let some = &ids[3];
    let at_v = store.episode(some, Some(v)).await.unwrap();
    let hist = store.label_history(some).await.unwrap();
    let ev = hist.iter().find(|h| h.revision == at_v.label_revision).unwrap();
    assert_eq!((&at_v.label_actor, &at_v.label_updated_at), (&ev.actor, &ev.created_at));
    let by_label: BTreeMap<&str, usize> = frozen.values().fold(BTreeMap::new(), |mut m, l| {
        *m.entry(l.as_str()).or_default() += 1;
        m
    });
    let c = store.episode_counts(&CountFilter { version: Some(v), ..Default::default() }).await.unwrap();
    assert_eq!(c.unknown as usize, by_label.get("unknown").copied().unwrap_or(0));
}

#[tokio::test]
async fn counts_follow_every_write_sqlite() {
    counts_follow_every_write(Backend::Sqlite).await;
}
#[tokio::test]
async fn counts_follow_every_write_postgres() {
    counts_follow_every_write(Backend::Postgres).await;
}
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn counts_under_concurrent_writers_sqlite() {
    counts_under_concurrent_writers(Backend::Sqlite).await;
}
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn counts_under_concurrent_writers_postgres() {
    counts_under_concurrent_writers(Backend::Postgres).await;
}
#[tokio::test]
async fn pages_cover_every_episode_once_sqlite() {
    pages_cover_every_episode_once(Backend::Sqlite).await;
}
#[tokio::test]
async fn pages_cover_every_episode_once_postgres() {
    pages_cover_every_episode_once(Backend::Postgres).await;
}

/// `tag=` matches whole tags, through the tag index: not a tag that merely contains it, nor JSON
/// punctuation; an episode with a tag twice is listed once; pages and versions filter alike.
async fn tag_filter_matches_whole_tags(db: Backend) {
    let dir = tempfile::tempdir().unwrap();
    let store = test_support::open_test_store(db, dir.path(), "lists").await;
    let tag_sets: [&[&str]; 6] =
        [&["eval"], &["eval", "night"], &["evaluation"], &[], &["a\"b", "100%"], &["eval", "eval"]];
    let mut w = store.begin_ingest(test_support::source("tags"), "pol", "c1").await.unwrap();
    let mut ids = Vec::new();
    for (i, tags) in tag_sets.iter().enumerate() {
        let mut ep = test_support::two_step_episode(i as u32, Some("reach"), Label::Success);
        ep.tags = tags.iter().map(|t| t.to_string()).collect();
        ids.push(w.add_episode(ep).await.unwrap());
    }
    w.commit("tagged").await.unwrap();
    let listed = |tag: &str, version: Option<i64>, limit: Option<i64>| {
        let store = store.clone();
        let f = EpisodeFilter { tag: Some(tag.to_string()), version, limit, ..Default::default() };
        async move { store.episodes(&f).await.unwrap().into_iter().map(|e| e.id).collect::<BTreeSet<_>>() }
    };
    let want = |ix: &[usize]| ix.iter().map(|&i| ids[i].clone()).collect::<BTreeSet<_>>();
    assert_eq!(listed("eval", None, None).await, want(&[0, 1, 5]));
    assert_eq!(listed("eval", Some(1), None).await, want(&[0, 1, 5]));
    assert_eq!(listed("night", None, None).await, want(&[1]));
    assert_eq!(listed("a\"b", None, None).await, want(&[4]));
    assert_eq!(listed("100%", None, None).await, want(&[4]));
    for none in ["eva", "val", "%", "\"", ","] {
        assert!(listed(none, None, None).await.is_empty(), "{none:?}");
    }
    assert_eq!(listed("eval", None, Some(2)).await.len(), 2);
}

#[tokio::test]
async fn tag_filter_matches_whole_tags_sqlite() {
    tag_filter_matches_whole_tags(Backend::Sqlite).await;
}
#[tokio::test]
async fn tag_filter_matches_whole_tags_postgres() {
    tag_filter_matches_whole_tags(Backend::Postgres).await;
}
