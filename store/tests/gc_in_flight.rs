//! gc never deletes what a writer in flight will reference, whatever its grace period: gc with
//! grace 0 while an ingest has uploaded steps files and a video (one re-used from an earlier,
//! aborted ingest) leaves every one of them, and the ingest then commits a version that reads
//! back whole. What an aborted writer left is collected.

use store::test_support::two_step_episode;
use store::{Label, MediaColumn, MediaFile, SourceInput, Store, StoreConfig};

fn source(tag: &str) -> SourceInput {
    SourceInput {
        path: format!("/tmp/{tag}"),
        sha256: store::sha256_hex(tag.as_bytes()),
        format: "test".into(),
        size_bytes: 1,
        metadata: serde_json::json!({}),
    }
}

fn video(dir: &std::path::Path) -> MediaFile {
    let bytes: Vec<u8> = (0..50_000u32).map(|i| (i.wrapping_mul(2654435761) >> 11) as u8).collect();
    let local_path = dir.join("front.mp4");
    std::fs::write(&local_path, &bytes).unwrap();
    MediaFile {
        sha256: store::sha256_hex(&bytes),
        local_path,
        content_type: "video/mp4".into(),
        size_bytes: bytes.len() as u64,
    }
}

#[tokio::test]
async fn gc_with_grace_zero_during_an_ingest_keeps_the_writers_objects() {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open(&StoreConfig::local(dir.path().join("store"))).await.unwrap();
    let media = video(dir.path());

    // An earlier ingest uploaded the video, then gave up: its objects are garbage now...
    let mut failed = store.begin_ingest(source("failed"), "pol", "c1").await.unwrap();
    failed.add_media(&media).await.unwrap();
    for i in 0..3 {
        failed.add_episode(two_step_episode(i, Some("t"), Label::Success)).await.unwrap();
    }
    failed.abort().await.unwrap();

    // ...until a new ingest re-uses the video (content-addressed) while gc runs with grace 0.
    let mut w = store.begin_ingest(source("live"), "pol", "c1").await.unwrap().with_max_file_bytes(1);
    w.add_media(&media).await.unwrap();
    for i in 0..6 {
        let mut ep = two_step_episode(i, Some("t"), if i % 2 == 0 { Label::Success } else { Label::Failure });
        ep.media = vec![MediaColumn {
            name: "front".into(),
            sha256: media.sha256.clone(),
            timestamps: ep.timestamps.clone(),
        }];
        w.add_episode(ep).await.unwrap();
    }
    let report = store.gc(0, false).await.unwrap();
    assert!(report.kept_pending >= 2, "the live writer's steps files and video are pending: {report:?}");
    assert!(
        report.deleted.iter().all(|p| !p.starts_with("media/")),
        "the re-used video was deleted: {report:?}"
    );
    let c = w.commit("live").await.unwrap();
    assert_eq!(c.episodes, 6);

    // Everything the version references is there and reads back.
    let eps = store.episodes(&store::EpisodeFilter::default()).await.unwrap();
    assert_eq!(eps.len(), 6);
    for e in &eps {
        let steps = store.read_steps(&e.id, None).await.unwrap();
        assert_eq!(steps.num_rows(), 2, "{}", e.id);
        let m = store.episode_media(&e.id, "front").await.unwrap();
        assert_eq!(store.object_size(&m.path).await.unwrap(), media.size_bytes);
    }
    // Committed: nothing pending any more; another gc deletes nothing referenced.
    let again = store.gc(0, false).await.unwrap();
    assert_eq!(again.kept_pending, 0, "{again:?}");
    for e in &eps {
        store.read_steps(&e.id, None).await.unwrap();
    }

    // A writer that gave up no longer protects what it uploaded.
    let mut gone = store.begin_ingest(source("gone"), "pol", "c2").await.unwrap().with_max_file_bytes(1);
    gone.add_episode(two_step_episode(0, Some("t"), Label::Success)).await.unwrap();
    gone.add_episode(two_step_episode(1, Some("t"), Label::Success)).await.unwrap();
    assert!(store.gc(0, true).await.unwrap().kept_pending >= 1);
    gone.abort().await.unwrap();
    let last = store.gc(0, false).await.unwrap();
    assert_eq!(last.kept_pending, 0, "{last:?}");
    assert!(!last.deleted.is_empty(), "the aborted writer's steps files are collected: {last:?}");
    for e in &eps {
        store.read_steps(&e.id, None).await.unwrap();
    }
}
