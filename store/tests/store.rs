//! The store's behaviour on both catalogs: versions and time travel, labels with optimistic
//! concurrency and audit, snapshots, splits, artifacts, jobs, tokens and gc.

use store::test_support::{episode, source};
use store::*;
use store_artifacts::{Artifacts, NewArtifact};

async fn ingest(store: &Store, tag: &str, ckpt: &str, n: u32) -> CommitInfo {
    let mut w = store.begin_ingest(source(tag), "pol", ckpt).await.unwrap();
    for i in 0..n {
        let label = if i % 2 == 0 { Label::Success } else { Label::Failure };
        w.add_episode(episode(i, 5 + i as usize, label)).await.unwrap();
    }
    w.commit("test ingest").await.unwrap()
}

async fn open_sqlite(dir: &std::path::Path) -> Store {
    Store::open(&StoreConfig::local(dir)).await.unwrap()
}

async fn open_postgres(dir: &std::path::Path) -> Store {
    let url =
        create_test_schema("store").await.expect("the Postgres tests need a server (UFOPS_TEST_POSTGRES)");
    Store::open(&StoreConfig { data_dir: dir.into(), database_url: Some(url), object_store_url: None })
        .await
        .unwrap()
}

async fn versions_labels_time_travel(store: Store) {
    assert_eq!(store.head_version().await.unwrap(), 0);
    let c1 = ingest(&store, "a", "c1", 4).await;
    assert_eq!((c1.version, c1.episodes), (1, 4));
    let eps = store.episodes(&EpisodeFilter::default()).await.unwrap();
    assert_eq!(eps.len(), 4);
    assert_eq!(eps.iter().filter(|e| e.label == Label::Success).count(), 2);
    let id = eps[1].id.clone();
    assert_eq!(eps[1].label, Label::Failure);
    assert_eq!(eps[1].label_revision, 1);

    // Steps round-trip through Parquet.
    let batch = store.read_steps(&eps[1].id, None).await.unwrap();
    assert_eq!(batch.num_rows() as i64, eps[1].length);
    let (dim, pos) = steps::vector_column(&batch, "obs.pos").unwrap();
    assert_eq!(dim, 2);
    assert_eq!(pos[..4], [1000.0, 1001.0, 1002.0, 1003.0]);

    // Re-ingesting the same content is refused with the version that holds it.
    match store.begin_ingest(source("a"), "pol", "c1").await {
        Err(StoreError::AlreadyIngested { version, .. }) => assert_eq!(version, 1),
        other => panic!("expected AlreadyIngested, got {:?}", other.map(|_| ())),
    }

    // Labels: optimistic concurrency and an audit log.
    let ch = store
        .set_label(
            LabelUpdate {
                episode_id: id.clone(),
                label: Label::Success,
                expect_revision: Some(1),
                note: Some("looked again".into()),
            },
            "alice",
            "human",
        )
        .await
        .unwrap();
    assert_eq!((ch.old_label, ch.label, ch.revision), (Label::Failure, Label::Success, 2));
    let stale = store
        .set_label(
            LabelUpdate {
                episode_id: id.clone(),
                label: Label::Failure,
                expect_revision: Some(1),
                note: None,
            },
            "bob",
            "human",
        )
        .await;
    match stale {
        Err(StoreError::LabelConflict { revision, label, actor, .. }) => {
            assert_eq!((revision, label, actor.as_str()), (2, Label::Success, "alice"))
        }
        other => panic!("expected a conflict, got {other:?}"),
    }
    let hist = store.label_history(&id).await.unwrap();
    assert_eq!(hist.len(), 2);
    assert_eq!(hist[1].actor, "alice");
    assert_eq!(hist[1].old_label, Some(Label::Failure));

    // The change is live now but version 1 still shows the old label (time travel).
    assert_eq!(store.episode(&id, None).await.unwrap().label, Label::Success);
    assert_eq!(store.episode(&id, Some(1)).await.unwrap().label, Label::Failure);
    assert!(store.labels_changed_since_head().await.unwrap());
    let snap = store.snapshot_labels("alice", "relabel").await.unwrap();
    assert_eq!(snap.version, 2);
    assert!(!store.labels_changed_since_head().await.unwrap());
    assert_eq!(store.episode(&id, Some(2)).await.unwrap().label, Label::Success);
    let v2 = store.version(2).await.unwrap();
    assert_eq!((v2.kind.as_str(), v2.labels_changed, v2.episode_count), ("label_snapshot", 1, 4));

    // A bulk change is one transaction: one bad id and nothing changes.
    let bad = store
        .set_labels(
            vec![
                LabelUpdate {
                    episode_id: eps[0].id.clone(),
                    label: Label::Failure,
                    expect_revision: None,
                    note: None,
                },
                LabelUpdate {
                    episode_id: "nope".into(),
                    label: Label::Failure,
                    expect_revision: None,
                    note: None,
                },
            ],
            "bob",
            "human",
        )
        .await;
    assert!(matches!(bad, Err(StoreError::NotFound { .. })));
    assert_eq!(store.episode(&eps[0].id, None).await.unwrap().label, Label::Success);

    // A second ingest, a diff, and a deletion version.
    let c3 = ingest(&store, "b", "c2", 2).await;
    assert_eq!(c3.version, 3);
    let d = store.diff(1, 3).await.unwrap();
    assert_eq!(d.episodes_added.len(), 2);
    assert_eq!(d.labels_changed, vec![(id.clone(), Label::Failure, Label::Success)]);
    let del = store.delete_episodes(&[eps[3].id.clone()], "alice", "bad episode").await.unwrap();
    assert_eq!((del.version, del.episodes), (4, 5));
    assert!(store.read_steps(&eps[3].id, None).await.is_err());
    assert_eq!(store.read_steps(&eps[3].id, Some(3)).await.unwrap().num_rows(), 8);
    let at1 = store.episodes(&EpisodeFilter { version: Some(1), ..Default::default() }).await.unwrap();
    assert_eq!(at1.len(), 4);
    let filtered = store
        .episodes(&EpisodeFilter {
            checkpoint: Some("c2".into()),
            label: Some(Label::Success),
            ..Default::default()
        })
        .await
        .unwrap();
    assert_eq!(filtered.len(), 1);
    let versions = store.versions().await.unwrap();
    assert_eq!(versions.iter().map(|v| v.version).collect::<Vec<_>>(), vec![1, 2, 3, 4]);
    assert_eq!(store.checkpoints(Some("pol")).await.unwrap().len(), 2);

    // Splits are by episode, seeded, pinned to a version.
    let req = SplitRequest {
        policy: "pol".into(),
        checkpoint: "c1".into(),
        version: None,
        off_policy_from: vec![],
        val_fraction: 0.5,
        seed: 3,
        actor: "alice".into(),
        max_episodes: None,
    };
    let s1 = store.create_split(&req).await.unwrap();
    let s2 = store.create_split(&req).await.unwrap();
    assert_eq!(s1.version, 4);
    assert_eq!(s1.train_episodes + s1.val_episodes, 3);
    assert_eq!(store.split_episodes(&s1.id).await.unwrap(), store.split_episodes(&s2.id).await.unwrap());
    let off = store
        .create_split(&SplitRequest { off_policy_from: vec![("pol".into(), "c2".into())], ..req.clone() })
        .await
        .unwrap();
    assert_eq!((off.mode.as_str(), off.train_episodes + off.val_episodes), ("off_policy", 2));

    // Artifacts: content-addressed, checked against the manifest, aliased.
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("config.json"), b"{\"kind\":\"classifier\"}").unwrap();
    std::fs::write(dir.path().join("model.safetensors"), b"weights").unwrap();
    let manifest = serde_json::json!({"schema_version": 1, "files": {
        "config.json": sha256_hex(b"{\"kind\":\"classifier\"}"), "model.safetensors": sha256_hex(b"weights")}});
    std::fs::write(dir.path().join("manifest.json"), serde_json::to_vec(&manifest).unwrap()).unwrap();
    let new = || NewArtifact {
        dir: dir.path(),
        policy: "pol",
        checkpoint: "c1",
        kind: "classifier",
        split_id: Some(&s1.id),
        job_id: None,
    };
    let a = store.publish_artifact(new()).await.unwrap();
    assert_eq!(a.aliases, vec!["latest".to_string()]);
    assert_eq!(store.resolve_artifact("pol/c1/classifier@latest").await.unwrap().id, a.id);
    // A verifier trained off-policy (on c2's rollouts) is published without taking c1's `latest`.
    let off_dir = tempfile::tempdir().unwrap();
    let off_cfg = b"{\"kind\":\"classifier\",\"mode\":\"off_policy\"}";
    std::fs::write(off_dir.path().join("config.json"), off_cfg).unwrap();
    std::fs::write(off_dir.path().join("model.safetensors"), b"other weights").unwrap();
    let off_manifest = serde_json::json!({"schema_version": 1, "files": {
        "config.json": sha256_hex(off_cfg), "model.safetensors": sha256_hex(b"other weights")}});
    std::fs::write(off_dir.path().join("manifest.json"), serde_json::to_vec(&off_manifest).unwrap()).unwrap();
    let off_art = store
        .publish_artifact(NewArtifact {
            dir: off_dir.path(),
            policy: "pol",
            checkpoint: "c1",
            kind: "classifier",
            split_id: Some(&off.id),
            job_id: None,
        })
        .await
        .unwrap();
    assert!(off_art.aliases.is_empty(), "{:?}", off_art.aliases);
    assert_eq!(store.resolve_artifact("pol/c1/classifier@latest").await.unwrap().id, a.id);
    store.set_alias("prod", &a.id).await.unwrap();
    assert_eq!(store.resolve_artifact("pol/c1/classifier@prod").await.unwrap().id, a.id);
    let out = tempfile::tempdir().unwrap();
    store.download_artifact(&a.id, out.path()).await.unwrap();
    assert_eq!(std::fs::read(out.path().join("model.safetensors")).unwrap(), b"weights");
    std::fs::write(dir.path().join("model.safetensors"), b"tampered").unwrap();
    assert!(store.publish_artifact(new()).await.is_err());

    // Tokens are stored hashed and can be revoked.
    let (secret, tok) = store.create_token("ci", Role::Labeler).await.unwrap();
    assert_eq!(store.verify_token(&secret).await.unwrap().unwrap().role, Role::Labeler);
    assert!(store.verify_token("ufops_wrong").await.unwrap().is_none());
    store.revoke_token(&tok.id).await.unwrap();
    assert!(store.verify_token(&secret).await.unwrap().is_none());

    // gc keeps everything referenced.
    let r = store.gc(0, false).await.unwrap();
    assert!(r.deleted.is_empty(), "{:?}", r.deleted);
}

#[tokio::test]
async fn sqlite_store_behaviour() {
    let dir = tempfile::tempdir().unwrap();
    versions_labels_time_travel(open_sqlite(dir.path()).await).await;
}

#[tokio::test]
async fn postgres_store_behaviour() {
    if !store::test_support::require_postgres() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    versions_labels_time_travel(open_postgres(dir.path()).await).await;
}

/// Every file under the local object directory, relative to it (`steps/…`, `media/…`).
fn object_files(data_dir: &std::path::Path) -> std::collections::BTreeSet<String> {
    fn walk(root: &std::path::Path, dir: &std::path::Path, out: &mut std::collections::BTreeSet<String>) {
        for e in std::fs::read_dir(dir).unwrap().flatten() {
            let p = e.path();
            if p.is_dir() {
                walk(root, &p, out);
            } else {
                out.insert(p.strip_prefix(root).unwrap().to_string_lossy().into_owned());
            }
        }
    }
    let mut out = std::collections::BTreeSet::new();
    let root = data_dir.join("objects");
    if root.exists() {
        walk(&root, &root, &mut out);
    }
    out
}

#[tokio::test]
async fn aborted_ingest_is_invisible_and_collected() {
    let dir = tempfile::tempdir().unwrap();
    let store = open_sqlite(dir.path()).await;
    // A video file for an ingest, and its media file record.
    let video = |seed: u32| {
        let bytes: Vec<u8> =
            (0..50_000u32).map(|i| (i.wrapping_mul(2654435761).wrapping_add(seed) >> 11) as u8).collect();
        let path = dir.path().join(format!("front-{seed}.mp4"));
        std::fs::write(&path, &bytes).unwrap();
        MediaFile {
            sha256: sha256_hex(&bytes),
            local_path: path,
            content_type: "video/mp4".into(),
            size_bytes: bytes.len() as u64,
        }
    };
    // An episode of 4 steps that shows `media`.
    let with_video = |i: u32, label: Label, media: &MediaFile| {
        let mut ep = episode(i, 4, label);
        ep.media = vec![MediaColumn {
            name: "front".into(),
            sha256: media.sha256.clone(),
            timestamps: ep.timestamps.clone(),
        }];
        ep
    };
    // A committed ingest with its own video: gc must keep all of it.
    let kept_video = video(1);
    let mut w = store.begin_ingest(source("keep"), "pol", "c").await.unwrap();
    w.add_media(&kept_video).await.unwrap();
    for i in 0..2 {
        w.add_episode(with_video(i, Label::Success, &kept_video)).await.unwrap();
    }
    w.commit("kept").await.unwrap();
    let kept_ids: Vec<String> =
        store.episodes(&EpisodeFilter::default()).await.unwrap().into_iter().map(|e| e.id).collect();
    let committed = object_files(dir.path());
    assert!(committed.contains(&format!("media/{}.mp4", kept_video.sha256)), "{committed:?}");

    // An ingest that writes data files (one per episode: a 1-byte roll-over) and another video
    // before it gives up.
    let dropped_video = video(2);
    let mut w = store.begin_ingest(source("drop"), "pol", "c").await.unwrap().with_max_file_bytes(1);
    w.add_media(&dropped_video).await.unwrap();
    let mut dropped_ids = Vec::new();
    for i in 0..3 {
        dropped_ids.push(w.add_episode(with_video(i, Label::Unknown, &dropped_video)).await.unwrap());
    }
    let video_sha = dropped_video.sha256.clone();
    let orphans: std::collections::BTreeSet<String> =
        object_files(dir.path()).difference(&committed).cloned().collect();
    let video_object = format!("media/{video_sha}.mp4");
    assert!(orphans.contains(&video_object), "the video was written: {orphans:?}");
    let data_files = orphans.iter().filter(|p| p.starts_with("steps/") && p.ends_with(".parquet")).count();
    assert_eq!(data_files, 3, "one data file per episode was written before the abort: {orphans:?}");
    assert_eq!(orphans.len(), 4, "{orphans:?}");
    w.abort().await.unwrap();

    // Invisible: no new version, none of its episodes, its source not recorded.
    assert_eq!(store.head_version().await.unwrap(), 1);
    let ids: Vec<String> =
        store.episodes(&EpisodeFilter::default()).await.unwrap().into_iter().map(|e| e.id).collect();
    assert_eq!(ids, kept_ids);
    for id in &dropped_ids {
        assert!(store.episode(id, None).await.is_err(), "{id} is visible");
        assert!(store.read_steps(id, None).await.is_err(), "{id}'s steps are readable");
    }
    assert_eq!(store.source_version(&sha256_hex(b"drop")).await.unwrap(), None);
    let referenced = store.referenced_objects().await.unwrap();
    assert!(orphans.iter().all(|o| !referenced.contains(o)), "an aborted object is referenced");

    // Bad input is refused with a message and changes nothing.
    let mut w = store.begin_ingest(source("bad"), "pol", "c").await.unwrap();
    let mut ep = episode(0, 4, Label::Success);
    ep.reward.pop();
    let err = w.add_episode(ep).await.unwrap_err().to_string();
    assert!(err.contains("reward"), "{err}");
    assert_eq!(store.head_version().await.unwrap(), 1);

    // Within the grace period (a writer may still be in flight) gc keeps everything.
    let r = store.gc(3600, false).await.unwrap();
    assert!(r.deleted.is_empty(), "young orphans are kept: {:?}", r.deleted);
    assert_eq!(r.kept_recent, orphans.len());
    assert_eq!(object_files(dir.path()), committed.union(&orphans).cloned().collect());
    // A grace period too large to compute with is refused and deletes nothing (it used to wrap
    // around into "everything unreferenced is old enough").
    for huge in [u64::MAX, 1 << 62, store::MAX_GRACE_SECONDS + 1] {
        let e = store.gc(huge, false).await.unwrap_err().to_string();
        assert!(e.contains("grace period"), "{e}");
    }
    assert_eq!(object_files(dir.path()), committed.union(&orphans).cloned().collect());

    // After it, gc removes exactly the aborted ingest's objects (a dry run first lists them).
    tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    let dry = store.gc(0, true).await.unwrap();
    assert_eq!(dry.deleted.iter().cloned().collect::<std::collections::BTreeSet<_>>(), orphans);
    assert_eq!(
        object_files(dir.path()),
        committed.union(&orphans).cloned().collect(),
        "a dry run deletes nothing"
    );
    let r = store.gc(0, false).await.unwrap();
    assert_eq!(r.deleted.iter().cloned().collect::<std::collections::BTreeSet<_>>(), orphans);
    assert_eq!(r.deleted.len(), orphans.len());
    assert_eq!(object_files(dir.path()), committed, "only the aborted ingest's objects went");
    for id in &kept_ids {
        assert!(store.read_steps(id, None).await.unwrap().num_rows() > 0);
    }
    assert!(store.gc(0, false).await.unwrap().deleted.is_empty());
}

#[test]
fn migration_histories_are_in_step() {
    let (sqlite, pg) = store::migration_names();
    assert_eq!(sqlite, pg);
    let names = |dir: &str| {
        let mut v: Vec<String> =
            std::fs::read_dir(format!("{}/../migrations/{dir}", env!("CARGO_MANIFEST_DIR")))
                .unwrap()
                .map(|e| e.unwrap().file_name().into_string().unwrap())
                .collect();
        v.sort();
        v
    };
    assert_eq!(names("sqlite"), names("postgres"));
    assert_eq!(names("sqlite").len(), sqlite.len(), "every migration file is embedded");
}

/// One episode's values of a test layer: step t of episode `i` holds `[i, t, producer_seed, …]`.
fn layer_values(id: &str, i: u32, steps: usize, dim: usize, seed: f32) -> LayerValues {
    let values = (0..steps)
        .flat_map(|t| (0..dim).map(move |d| i as f32 * 1000.0 + t as f32 + d as f32 * 0.01 + seed))
        .collect();
    LayerValues { episode_id: id.to_string(), dim, values }
}

/// Layers: a new version per write that never rewrites the steps; joined by the read path as
/// `obs.<layer>`; visible in time travel from their version on; re-writing the same producer's
/// values is idempotent (and a partial write resumes); a new producer replaces the old values
/// from its version on; gc keeps every layer file; bad input is refused and changes nothing.
async fn layers_behaviour(store: Store, data_dir: &std::path::Path) {
    let before = ingest(&store, "layers", "c1", 4).await.version;
    let eps = store.episodes(&EpisodeFilter::default()).await.unwrap();
    let steps_files: Vec<String> =
        object_files(data_dir).into_iter().filter(|p| p.starts_with("steps/")).collect();
    let name = "features.cnn";
    let producer =
        serde_json::json!({"encoder": "cnn", "policy": "pol", "checkpoint": "c1", "content_hash": "aa"});
    let dim = 3;
    let values = |idx: &[usize], seed: f32| -> Vec<LayerValues> {
        idx.iter()
            .map(|&k| layer_values(&eps[k].id, eps[k].source_index as u32, eps[k].length as usize, dim, seed))
            .collect()
    };

    // A partial computation: two episodes, then all four (the first two skipped).
    let first = store.write_layer(name, &producer, values(&[0, 1], 0.0), "test").await.unwrap();
    assert_eq!((first.episodes_written, first.episodes_skipped), (2, 0));
    let v1 = first.version.expect("a version");
    assert_eq!(v1, before + 1);
    let rest = store.write_layer(name, &producer, values(&[0, 1, 2, 3], 0.0), "test").await.unwrap();
    assert_eq!((rest.episodes_written, rest.episodes_skipped), (2, 2));
    let v2 = rest.version.unwrap();
    assert_eq!(rest.producer_hash, first.producer_hash);
    // Again: nothing written, no version.
    let again = store.write_layer(name, &producer, values(&[0, 1, 2, 3], 0.0), "test").await.unwrap();
    assert_eq!((again.version, again.episodes_written, again.episodes_skipped), (None, 0, 4));
    assert_eq!(store.head_version().await.unwrap(), v2);
    let after_steps: Vec<String> =
        object_files(data_dir).into_iter().filter(|p| p.starts_with("steps/")).collect();
    assert_eq!(after_steps, steps_files, "no steps file rewritten or added");
    assert_eq!(store.versions().await.unwrap().last().unwrap().kind, "layer");

    // Joined reads, now and in time travel.
    let ids: Vec<String> = eps.iter().map(|e| e.id.clone()).collect();
    let layers = vec![name.to_string()];
    let b = store.read_steps_with_layers(&ids[3], None, &layers).await.unwrap();
    let (d, got) = steps::vector_column(&b, &format!("obs.{name}")).unwrap();
    assert_eq!(d, dim);
    assert_eq!(got, values(&[3], 0.0)[0].values);
    let field = b.schema().field_with_name(&format!("obs.{name}")).unwrap().clone();
    assert_eq!(field.metadata().get(PRODUCER_META_KEY), Some(&first.producer_hash));
    assert_eq!(
        steps::vector_column(&b, "obs.pos").unwrap().1,
        steps::vector_column(&store.read_steps(&ids[3], None).await.unwrap(), "obs.pos").unwrap().1
    );
    let err = store.read_steps_with_layers(&ids[3], Some(v1), &layers).await.unwrap_err().to_string();
    assert!(err.contains("layer not found") && err.contains(&format!("version {v1}")), "{err}");
    assert!(store.read_steps_with_layers(&ids[0], Some(v1), &layers).await.is_ok());
    assert!(
        store.read_steps_with_layers(&ids[0], Some(before), &layers).await.is_err(),
        "the version before has no layer"
    );
    assert_eq!(store.episode_layers(&ids[0], Some(before)).await.unwrap(), vec![]);
    assert_eq!(store.episode_layers(&ids[3], None).await.unwrap().len(), 1);
    // Many episodes at once, in any order, each with its own values.
    let locs = store.locate_episodes(&ids, None).await.unwrap();
    let layer_locs = store.locate_layers(&ids, &layers, None).await.unwrap();
    let mut stream = store.read_episodes_with_layers(locs, layers.clone(), layer_locs);
    let mut seen = 0;
    while let Some(item) = stream.next().await {
        let item = item.unwrap();
        let (_, got) = steps::vector_column(&item.steps, &format!("obs.{name}")).unwrap();
        assert_eq!(got, values(&[item.index], 0.0)[0].values);
        seen += 1;
    }
    assert_eq!(seen, 4);

    // Another producer (new weights) replaces the values from its version on.
    let producer2 =
        serde_json::json!({"encoder": "cnn", "policy": "pol", "checkpoint": "c1", "content_hash": "bb"});
    let w3 = store.write_layer(name, &producer2, values(&[0], 7.0), "test").await.unwrap();
    let v3 = w3.version.unwrap();
    let now = store.read_steps_with_layers(&ids[0], None, &layers).await.unwrap();
    assert_eq!(steps::vector_column(&now, &format!("obs.{name}")).unwrap().1, values(&[0], 7.0)[0].values);
    let then = store.read_steps_with_layers(&ids[0], Some(v2), &layers).await.unwrap();
    assert_eq!(steps::vector_column(&then, &format!("obs.{name}")).unwrap().1, values(&[0], 0.0)[0].values);
    let listed = store.layers().await.unwrap();
    assert_eq!(listed.len(), 2);
    let count = |h: &str| listed.iter().find(|l| l.producer_hash == h).unwrap().episodes;
    assert_eq!((count(&first.producer_hash), count(&w3.producer_hash)), (3, 1));
    assert_eq!(store.layer_episodes(name, &w3.producer_hash).await.unwrap(), vec![ids[0].clone()]);

    // Bad input: refused with a message, and the store stays as it was.
    let head = store.head_version().await.unwrap();
    let mut short = values(&[1], 1.0);
    short[0].values.truncate(dim * 2);
    let bad_cases: Vec<(&str, serde_json::Value, Vec<LayerValues>, &str)> = vec![
        (
            name,
            producer.clone(),
            vec![LayerValues { episode_id: "nope".into(), dim, values: vec![0.0; 3] }],
            "not found",
        ),
        (name, serde_json::json!({"content_hash": "cc"}), short, "steps"),
        ("bad name", producer.clone(), values(&[1], 1.0), "invalid layer name"),
        ("pos", serde_json::json!({"content_hash": "dd"}), values(&[1], 1.0), "observation key"),
        (name, serde_json::json!("cnn"), values(&[1], 1.0), "JSON object"),
        (
            name,
            serde_json::json!({"content_hash": "ee"}),
            vec![LayerValues {
                episode_id: ids[1].clone(),
                dim,
                values: vec![f32::NAN; eps[1].length as usize * dim],
            }],
            "non-finite",
        ),
        (
            name,
            producer.clone(),
            vec![LayerValues {
                episode_id: ids[1].clone(),
                dim: 2,
                values: vec![0.0; eps[1].length as usize * 2],
            }],
            "dim",
        ),
    ];
    for (n, p, vals, want) in bad_cases {
        let err = store.write_layer(n, &p, vals, "test").await.unwrap_err().to_string();
        assert!(err.contains(want), "{n} {p}: {err} (wanted {want:?})");
    }
    assert_eq!(store.head_version().await.unwrap(), head);

    // gc keeps every layer file (the replaced values are still in time travel).
    let layer_files: Vec<String> =
        object_files(data_dir).into_iter().filter(|p| p.starts_with("layers/")).collect();
    assert_eq!(layer_files.len(), 3);
    let report = store.gc(0, false).await.unwrap();
    assert!(report.deleted.iter().all(|p| !p.starts_with("layers/")), "{:?}", report.deleted);
    let kept: Vec<String> = object_files(data_dir).into_iter().filter(|p| p.starts_with("layers/")).collect();
    assert_eq!(kept, layer_files);
    assert!(store.read_steps_with_layers(&ids[2], Some(v3), &layers).await.is_ok());
}

#[tokio::test]
async fn sqlite_layers() {
    let dir = tempfile::tempdir().unwrap();
    layers_behaviour(open_sqlite(dir.path()).await, dir.path()).await;
}

#[tokio::test]
async fn postgres_layers() {
    if !store::test_support::require_postgres() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    layers_behaviour(open_postgres(dir.path()).await, dir.path()).await;
}

/// Two (here eight) writers of one producer's layer at once, each over every episode, as two
/// runs of a computation started together: each episode is written once in all (the later
/// commits skip, under the version write lock, what an earlier one wrote), and the versions
/// made hold exactly the episodes.
async fn concurrent_layer_writers(store: Store) {
    let before = ingest(&store, "layers-race", "c1", 6).await.version;
    let eps = store.episodes(&EpisodeFilter::default()).await.unwrap();
    let producer =
        serde_json::json!({"encoder": "cnn", "policy": "pol", "checkpoint": "c1", "content_hash": "race"});
    let all: Vec<LayerValues> =
        eps.iter().map(|e| layer_values(&e.id, e.source_index as u32, e.length as usize, 4, 0.5)).collect();
    let writers: Vec<_> = (0..8)
        .map(|k| {
            let (store, producer) = (store.clone(), producer.clone());
            // Each writer its own order: the groups overlap in every way.
            let mut mine = all.clone();
            mine.rotate_left(k % all.len());
            tokio::spawn(async move { store.write_layer("features.race", &producer, mine, "test").await })
        })
        .collect();
    let mut written = 0;
    let mut versions = Vec::new();
    for w in writers {
        let done = w.await.unwrap().unwrap();
        assert_eq!(done.episodes_written + done.episodes_skipped, all.len());
        written += done.episodes_written;
        versions.extend(done.version);
    }
    assert_eq!(written, all.len(), "every episode written once in all");
    versions.sort();
    assert_eq!(store.head_version().await.unwrap(), before + versions.len() as i64);
    let hash = producer_hash(&producer).unwrap();
    let mut held = store.layer_episodes("features.race", &hash).await.unwrap();
    held.sort();
    let mut ids: Vec<String> = eps.iter().map(|e| e.id.clone()).collect();
    ids.sort();
    assert_eq!(held, ids);
    // No value was ended by a second write of the same producer: each episode's layer rows
    // are the one it got in its version.
    for e in &eps {
        let got = store.episode_layers(&e.id, None).await.unwrap();
        assert_eq!(got.len(), 1);
        assert!(versions.contains(&got[0].version_added));
        for v in &versions {
            let at = store.episode_layers(&e.id, Some(*v)).await.unwrap();
            assert!(at.is_empty() || at[0].version_added == got[0].version_added, "{} at {v}: {at:?}", e.id);
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn sqlite_concurrent_layer_writers() {
    let dir = tempfile::tempdir().unwrap();
    concurrent_layer_writers(open_sqlite(dir.path()).await).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn postgres_concurrent_layer_writers() {
    if !store::test_support::require_postgres() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    concurrent_layer_writers(open_postgres(dir.path()).await).await;
}
