//! A split capped at `max_episodes` is a seeded sample of the labeled episodes: the right size,
//! nested across sizes for one seed (so a learning curve adds data instead of swapping it), with
//! about the requested validation fraction, and a cap of zero is refused.

use std::collections::HashSet;
use store::{sha256_hex, test_support, Label, SourceInput, SplitRequest, Store, StoreConfig};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn capped_splits_are_nested_seeded_samples() {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open(&StoreConfig::local(dir.path())).await.unwrap();
    let src = SourceInput {
        path: "/tmp/sample".into(),
        sha256: sha256_hex(b"sample"),
        format: "test".into(),
        size_bytes: 1,
        metadata: serde_json::json!({}),
    };
    let mut w = store.begin_ingest(src, "pol", "c1").await.unwrap();
    for i in 0..400u32 {
        // One in four unlabeled: never in a split.
        let label = [Label::Success, Label::Failure, Label::Success, Label::Unknown][i as usize % 4];
        w.add_episode(test_support::two_step_episode(i, Some("reach"), label)).await.unwrap();
    }
    w.commit("sample test").await.unwrap();

    let req = |cap: Option<u64>, seed: u64| SplitRequest {
        policy: "pol".into(),
        checkpoint: "c1".into(),
        version: None,
        off_policy_from: vec![],
        val_fraction: 0.2,
        seed,
        actor: "test".into(),
        max_episodes: cap,
    };
    let members = |id: String| {
        let store = &store;
        async move { store.split_episodes(&id).await.unwrap() }
    };
    let all = store.create_split(&req(None, 1)).await.unwrap();
    assert_eq!(all.train_episodes + all.val_episodes, 300);
    let mut previous: HashSet<String> = HashSet::new();
    for cap in [50u64, 120, 250] {
        let s = store.create_split(&req(Some(cap), 1)).await.unwrap();
        assert_eq!((s.train_episodes + s.val_episodes) as u64, cap);
        let eps = members(s.id.clone()).await;
        let ids: HashSet<String> = eps.iter().map(|e| e.episode_id.clone()).collect();
        assert!(previous.is_subset(&ids), "the sample of {cap} contains the smaller ones");
        assert!(eps.iter().all(|e| e.label != Label::Unknown));
        let val = s.val_episodes as f64 / cap as f64;
        assert!((0.08..0.35).contains(&val), "val fraction {val} of {cap}");
        previous = ids;
    }
    // Another seed draws another sample; a cap above the count keeps everything.
    let other = members(store.create_split(&req(Some(50), 2)).await.unwrap().id).await;
    let first = members(store.create_split(&req(Some(50), 1)).await.unwrap().id).await;
    assert_ne!(other, first);
    let over = store.create_split(&req(Some(10_000), 1)).await.unwrap();
    assert_eq!(over.train_episodes + over.val_episodes, 300);
    let err = store.create_split(&req(Some(0), 1)).await.unwrap_err();
    assert!(err.to_string().contains("max episodes"), "{err}");
}
