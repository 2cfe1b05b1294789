//! Ingest into a real temporary store (SQLite + local objects): episodes listed, re-ingest is a
//! no-op, broken inputs leave the store exactly as before with an error naming the file; ALOHA
//! episodes are stored exactly (`aloha/`).

use crate::common;

use std::path::{Path, PathBuf};

use common::{expected, fixtures};
use ingest::model::Label;
use ingest::{ingest, Format, IngestOptions};
use store::{EpisodeFilter, Store, StoreConfig};

fn opts(success_file: Option<PathBuf>) -> IngestOptions {
    IngestOptions {
        policy: "toy-dp".into(),
        checkpoint: "step-80000".into(),
        success_file,
        ..Default::default()
    }
}

async fn open(dir: &Path) -> Store {
    Store::open(&StoreConfig::local(dir)).await.expect("open store")
}

/// Everything that identifies the store's visible state.
async fn snapshot(s: &Store) -> (i64, usize, Vec<String>) {
    let head = s.head_version().await.unwrap();
    let eps = s.episodes(&EpisodeFilter::default()).await.unwrap();
    let mut ids: Vec<String> = eps.iter().map(|e| e.id.clone()).collect();
    ids.sort();
    (head, s.versions().await.unwrap().len(), ids)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn robomimic_ingest_reingest_and_broken() {
    let tmp = tempfile::tempdir().unwrap();
    let store = open(tmp.path()).await;
    let f = fixtures();
    let path = f.join("robomimic/lift_rollouts_lowdim.hdf5");
    let exp = expected("robomimic/lift_rollouts_lowdim.expected.json");

    let rep = ingest(&store, &path, &opts(Some(f.join("robomimic/lift_rollouts_lowdim.success.json"))))
        .await
        .unwrap();
    assert!(!rep.already_ingested);
    assert_eq!(rep.episodes, 12);
    assert_eq!(rep.labels.success, 7);
    assert_eq!(rep.labels.failure, 5);
    assert_eq!(rep.steps, 1014);
    assert_eq!(rep.format, "robomimic");

    let eps =
        store.episodes(&EpisodeFilter { version: Some(rep.version), ..Default::default() }).await.unwrap();
    assert_eq!(eps.len(), 12);
    for x in exp["episodes"].as_array().unwrap() {
        let e = eps.iter().find(|e| e.source_name == x["name"].as_str().unwrap()).expect("episode listed");
        assert_eq!(e.length as u64, x["length"].as_u64().unwrap());
        assert_eq!(e.label, Label::from_bool(x["success"].as_bool()));
        assert_eq!(e.label_source, "success-file:lift_rollouts_lowdim.success.json");
        assert_eq!(e.policy, "toy-dp");
        assert_eq!(e.checkpoint, "step-80000");
        assert_eq!(e.task.as_deref(), Some("Lift"));
    }
    let before = snapshot(&store).await;

    // same content again: a no-op naming the version
    let again = ingest(&store, &path, &opts(None)).await.unwrap();
    assert!(again.already_ingested);
    assert_eq!(again.version, rep.version);
    assert!(again.to_string().contains(&format!("version {}", rep.version)));
    assert_eq!(snapshot(&store).await, before);

    // broken inputs: clear error naming the file, store unchanged
    let work = tempfile::tempdir().unwrap();
    let bytes = std::fs::read(&path).unwrap();
    let mut cases: Vec<(String, Vec<u8>)> = vec![
        ("truncated_at_1k.hdf5".into(), bytes[..1024].to_vec()),
        ("truncated_at_90pct.hdf5".into(), bytes[..bytes.len() * 9 / 10].to_vec()),
        ("wrong_magic.hdf5".into(), {
            let mut b = bytes.clone();
            b[1] = b'X';
            b
        }),
        ("empty.hdf5".into(), Vec::new()),
    ];
    cases.push(("truncated.hdf5".into(), std::fs::read(f.join("robomimic/truncated.hdf5")).unwrap()));
    for (name, data) in cases {
        let p = work.path().join(&name);
        std::fs::write(&p, data).unwrap();
        let err = ingest(&store, &p, &opts(None)).await.expect_err(&name);
        assert!(err.to_string().contains(&name), "{name}: {err}");
        assert_eq!(snapshot(&store).await, before, "{name} changed the store");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn lerobot_and_mcap_into_one_store() {
    let tmp = tempfile::tempdir().unwrap();
    let store = open(tmp.path()).await;
    let f = fixtures();
    let mut last = 0;
    for (rel, n, media) in [
        ("lerobot/v30_eval_video", 8, 1),
        ("lerobot/v21_eval_video", 6, 6),
        ("lerobot/v30_unlabeled", 6, 0),
        ("mcap/ros2_jointstate_eval.mcap", 5, 0),
        ("mcap/protobuf_eval.mcap", 3, 0),
        ("mcap/json_eval.mcap", 3, 0),
    ] {
        let rep = ingest(&store, &f.join(rel), &opts(None)).await.unwrap_or_else(|e| panic!("{rel}: {e}"));
        assert_eq!(rep.episodes, n, "{rel}");
        assert_eq!(rep.media_files, media, "{rel}");
        assert!(rep.version > last);
        last = rep.version;
        let eps = store
            .episodes(&EpisodeFilter { version: Some(rep.version), ..Default::default() })
            .await
            .unwrap();
        let mine: Vec<_> = eps.iter().filter(|e| e.source_sha256 == rep.sha256).collect();
        assert_eq!(mine.len(), n, "{rel}");
    }
    // labels with provenance
    let eps = store.episodes(&EpisodeFilter::default()).await.unwrap();
    assert!(eps.iter().any(|e| e.label_source == "lerobot:next.success"));
    assert!(eps.iter().any(|e| e.label_source == "mcap:metadata:episode"));
    assert!(eps.iter().any(|e| e.label_source == "mcap:topic:/episode_event"));
    let before = snapshot(&store).await;

    // truncated MCAP: refused (store unchanged), then --recover ingests episodes 0..=2
    let t = f.join("mcap/truncated.mcap");
    let err = ingest(&store, &t, &opts(None)).await.unwrap_err();
    assert!(err.to_string().contains("truncated.mcap") && err.to_string().contains("--recover"), "{err}");
    assert_eq!(snapshot(&store).await, before);
    let rep = ingest(&store, &t, &IngestOptions { recover: true, ..opts(None) }).await.unwrap();
    assert_eq!(rep.episodes, 3);
    assert!(rep.notes.iter().any(|n| n.contains("truncated")), "{:?}", rep.notes);

    // a LeRobot folder without info.json / with a corrupt data file: refused, store unchanged
    let before = snapshot(&store).await;
    let work = tempfile::tempdir().unwrap();
    let ds = work.path().join("ds");
    copy_dir(&f.join("lerobot/v21_eval_video"), &ds);
    std::fs::remove_file(ds.join("meta/info.json")).unwrap();
    let err = ingest(&store, &ds, &opts(None)).await.unwrap_err();
    assert!(err.to_string().contains("info.json"), "{err}");
    let ds2 = work.path().join("ds2");
    copy_dir(&f.join("lerobot/v21_eval_video"), &ds2);
    let victim = ds2.join("data/chunk-000/episode_000003.parquet");
    let b = std::fs::read(&victim).unwrap();
    std::fs::write(&victim, &b[..b.len() / 2]).unwrap();
    let err =
        ingest(&store, &ds2, &IngestOptions { format: Format::Lerobot, ..opts(None) }).await.unwrap_err();
    assert!(err.to_string().contains("episode_000003.parquet"), "{err}");
    assert_eq!(snapshot(&store).await, before);
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let p = e.path();
        let q = to.join(e.file_name());
        if p.is_dir() {
            copy_dir(&p, &q);
        } else {
            std::fs::copy(&p, &q).unwrap();
            let mut perm = std::fs::metadata(&q).unwrap().permissions();
            #[allow(clippy::permissions_set_readonly_false)]
            perm.set_readonly(false);
            std::fs::set_permissions(&q, perm).unwrap();
        }
    }
}
