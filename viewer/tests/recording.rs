//! Writes recordings from a temp store with synthetic success/failure episodes and reads the
//! `.rrd` back with re_log_encoding's decoder: entities, timelines, rows per episode, blueprint.
//! `check_rrd_with_official_rerun_sdk` also runs `viewer/scripts/check_rrd.sh` (PyPI rerun-sdk).
#![allow(
    clippy::unwrap_used,
    clippy::too_many_lines,
    reason = "tests: a failed unwrap is a failed test, and a scenario reads top to bottom"
)]

use arrow::array::RecordBatch;
use re_sdk::log::{Chunk, LogMsg};
use re_sdk::StoreKind;
use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;
use store::*;
use viewer::*;

/// A 2x2 RGB PNG.
const PNG: [u8; 74] = [
    137, 80, 78, 71, 13, 10, 26, 10, 0, 0, 0, 13, 73, 72, 68, 82, 0, 0, 0, 2, 0, 0, 0, 2, 8, 2, 0, 0, 0, 253,
    212, 154, 115, 0, 0, 0, 17, 73, 68, 65, 84, 120, 156, 99, 248, 207, 192, 0, 68, 96, 226, 63, 3, 0, 29,
    240, 3, 253, 160, 51, 9, 137, 0, 0, 0, 0, 73, 69, 78, 68, 174, 66, 96, 130,
];

struct Opts {
    images: bool,
    video: Option<String>,
}

/// Success episodes go right (x grows), failures go up and stall; positions are 2-D `pos`
/// plus a 3-D `eef` and a wide `features` observation that must not be plotted.
fn episode(i: u32, steps: usize, label: Label, o: &Opts) -> EpisodeInput {
    let mut pos = Vec::new();
    let mut eef = Vec::new();
    for t in 0..steps {
        let s = t as f32 / steps as f32;
        match label {
            Label::Success => pos.extend([s, 0.1 * i as f32]),
            _ => pos.extend([0.1 * i as f32, s.min(0.5)]),
        }
        eef.extend([s, s * 2.0, i as f32]);
    }
    EpisodeInput {
        source_name: format!("ep_{i}"),
        task: Some("nav".into()),
        tags: vec![],
        metadata: serde_json::json!({}),
        timestamps: (0..steps).map(|t| t as f64 * 0.05).collect(),
        observations: vec![
            VectorColumn { name: "pos".into(), dim: 2, values: pos },
            VectorColumn { name: "eef".into(), dim: 3, values: eef },
            VectorColumn { name: "features".into(), dim: 80, values: vec![0.0; steps * 80] },
        ],
        action: VectorColumn {
            name: "action".into(),
            dim: 2,
            values: (0..steps * 2).map(|k| k as f32).collect(),
        },
        reward: (0..steps)
            .map(|t| if label == Label::Success && t + 1 == steps { 1.0 } else { 0.0 })
            .collect(),
        images: if o.images {
            vec![ImageColumn {
                name: "top".into(),
                shape: [2, 2, 3],
                frames: vec![PNG.to_vec(); steps].into(),
            }]
        } else {
            vec![]
        },
        media: match &o.video {
            Some(sha) => vec![MediaColumn {
                name: "observation.images.front".into(),
                sha256: sha.clone(),
                timestamps: (0..steps).map(|t| 10.0 + t as f64 * 0.05).collect(),
            }],
            None => vec![],
        },
        ..test_support::episode(i, steps, label)
    }
}

/// Labels of the synthetic episodes, by index: 3 successes, 2 failures, 1 unknown.
const LABELS: [Label; 6] =
    [Label::Success, Label::Failure, Label::Success, Label::Failure, Label::Success, Label::Unknown];

fn steps_of(i: usize) -> usize {
    8 + 3 * i
}

async fn make_store(dir: &Path, o: &Opts) -> Store {
    let store = Store::open(&StoreConfig::local(dir.join("data"))).await.unwrap();
    let src = SourceInput {
        path: "/tmp/synthetic".into(),
        sha256: sha256_hex(b"viewer-test"),
        format: "test".into(),
        size_bytes: 1,
        metadata: serde_json::json!({}),
    };
    let mut w = store.begin_ingest(src, "nav", "ckpt1").await.unwrap();
    if let Some(sha) = &o.video {
        let path = dir.join("front.mp4");
        std::fs::write(&path, fake_mp4()).unwrap();
        w.add_media(&MediaFile {
            sha256: sha.clone(),
            local_path: path,
            content_type: "video/mp4".into(),
            size_bytes: 64,
        })
        .await
        .unwrap();
    }
    for (i, l) in LABELS.iter().enumerate() {
        w.add_episode(episode(i as u32, steps_of(i), *l, o)).await.unwrap();
    }
    w.commit("synthetic").await.unwrap();
    store
}

/// Not a decodable video; enough for references and for the file's structure.
fn fake_mp4() -> Vec<u8> {
    let mut v = vec![0, 0, 0, 24];
    v.extend(b"ftypisom\0\0\x02\0isomiso2");
    v.resize(64, 0);
    v
}

/// Rises to 1 along successes, stays at 0.2 on failures, 0.5 elsewhere.
struct FakeVerifier;
impl StepScorer for FakeVerifier {
    fn score_steps(&self, batch: &RecordBatch) -> verifier::Result<Vec<f32>> {
        let n = batch.num_rows();
        let success = batch
            .column_by_name("success")
            .and_then(|c| c.as_any().downcast_ref::<arrow::array::BooleanArray>())
            .map(|a| if arrow::array::Array::is_valid(a, 0) { Some(a.value(0)) } else { None })
            .ok_or_else(|| verifier::VerifierError::Input("no success column".into()))?;
        Ok((0..n)
            .map(|t| match success {
                Some(true) => t as f32 / (n - 1) as f32,
                Some(false) => 0.2,
                None => 0.5,
            })
            .collect())
    }
}

/// What a decoded `.rrd` holds.
#[derive(Default, Debug)]
struct Decoded {
    /// entity → temporal rows (summed over chunks)
    rows: BTreeMap<String, usize>,
    /// entity → static rows
    statics: BTreeMap<String, usize>,
    /// entity → component names
    components: BTreeMap<String, BTreeSet<String>>,
    /// entity → timelines
    timelines: BTreeMap<String, BTreeSet<String>>,
    blueprint_chunks: usize,
    recordings: BTreeSet<String>,
    /// entity → the media types its rows carry (EncodedImage / AssetVideo)
    media_types: BTreeMap<String, BTreeSet<String>>,
    /// entity → every video timestamp it references, in seconds (VideoFrameReference)
    video_times: BTreeMap<String, Vec<f64>>,
}

fn decode(bytes: &[u8]) -> Decoded {
    let mut d = Decoded::default();
    let it =
        re_log_encoding::DecoderApp::decode_eager(std::io::BufReader::new(bytes)).expect("an rrd stream");
    for msg in it {
        let msg = msg.expect("decodes");
        let LogMsg::ArrowMsg(store_id, arrow_msg) = &msg else { continue };
        let chunk = Chunk::from_arrow_msg(arrow_msg).expect("a chunk");
        if store_id.kind() == StoreKind::Blueprint {
            d.blueprint_chunks += 1;
            continue;
        }
        d.recordings.insert(format!("{store_id:?}"));
        let path = chunk.entity_path().to_string();
        let path = path.trim_start_matches('/').to_string();
        if chunk.is_static() {
            *d.statics.entry(path.clone()).or_default() += chunk.num_rows();
        } else {
            *d.rows.entry(path.clone()).or_default() += chunk.num_rows();
            let tl = d.timelines.entry(path.clone()).or_default();
            for name in chunk.timelines().keys() {
                tl.insert(name.to_string());
            }
        }
        for desc in chunk.component_descriptors() {
            let name = desc.display_name().to_string();
            let values = chunk.raw_component_array(desc.component);
            if name.ends_with("media_type") {
                let v = values.and_then(|a| a.as_any().downcast_ref::<arrow::array::StringArray>()).unwrap();
                let set = d.media_types.entry(path.clone()).or_default();
                set.extend(v.iter().flatten().map(str::to_string));
            } else if name.ends_with("VideoFrameReference:timestamp") {
                let v = values.and_then(|a| a.as_any().downcast_ref::<arrow::array::Int64Array>()).unwrap();
                d.video_times
                    .entry(path.clone())
                    .or_default()
                    .extend(v.values().iter().map(|&ns| ns as f64 * 1e-9));
            }
            d.components.entry(path.clone()).or_default().insert(name);
        }
    }
    d
}

fn has(d: &Decoded, entity: &str, component_part: &str) -> bool {
    d.components.get(entity).is_some_and(|c| c.iter().any(|n| n.contains(component_part)))
}

#[tokio::test]
async fn recording_has_episodes_timelines_scores_and_blueprint() {
    let dir = tempfile::tempdir().unwrap();
    let o = Opts { images: true, video: Some(sha256_hex(&fake_mp4())) };
    let store = make_store(dir.path(), &o).await;
    let eps = store.episodes(&EpisodeFilter::default()).await.unwrap();
    assert_eq!(eps.len(), 6);

    let out = dir.path().join("out/view.rrd");
    let mut opts = ViewOptions::new("nav", "ckpt1");
    opts.image_stride = 2;
    let report = write_recording(&store, &opts, Some(&FakeVerifier), &out).await.unwrap();
    assert_eq!((report.episodes, report.success, report.failure, report.unknown), (6, 3, 2, 1));
    assert_eq!(report.position_dims, vec!["pos[0]", "pos[1]"], "first 2/3-dim observation key");
    assert_eq!(report.steps, (0..6).map(steps_of).sum::<usize>());
    assert_eq!(report.videos, 1, "one video object, embedded once");
    assert_eq!(report.video_frames, report.steps);
    assert!(report.mean_score_success.unwrap() > report.mean_score_failure.unwrap());
    // The fake verifier separates late: the gap is largest late in the episodes.
    let (step, gap) = report.max_separation.unwrap();
    assert!(step >= steps_of(0) as i64 - 1 && gap > 0.5, "{step} {gap}");
    assert!(report.separates_from_step.unwrap() > 0);

    let bytes = std::fs::read(&out).unwrap();
    let d = decode(&bytes);
    assert_eq!(d.recordings.len(), 1, "one recording store: {:?}", d.recordings);
    assert!(d.blueprint_chunks > 0, "a blueprint is stored in the file");

    for (i, ep) in eps.iter().enumerate() {
        let label = LABELS[ep.source_index as usize];
        assert_eq!(ep.label, label);
        let base = episode_path(label, &ep.id);
        let n = steps_of(ep.source_index as usize);
        assert_eq!(ep.length as usize, n);
        for e in [
            "position",
            "action",
            "state/pos",
            "state/eef",
            "reward",
            "score",
            "camera/observation.images.front",
        ] {
            let path = format!("{base}/{e}");
            assert_eq!(d.rows.get(&path).copied(), Some(n), "rows of {path} (episode {i})");
            let tl: Vec<&str> = d.timelines[&path].iter().map(String::as_str).collect();
            assert_eq!(tl, ["step", "time"], "timelines of {path}");
        }
        // Images sampled every 2nd step.
        assert_eq!(d.rows.get(&format!("{base}/image/top")).copied(), Some(n.div_ceil(2)));
        assert!(
            has(&d, &format!("{base}/image/top"), "blob"),
            "{:?}",
            d.components.get(&format!("{base}/image/top"))
        );
        assert_eq!(d.statics.get(&format!("{base}/trajectory")).copied(), Some(1), "one static strip");
        assert!(
            has(&d, &format!("{base}/trajectory"), "strips"),
            "{:?}",
            d.components.get(&format!("{base}/trajectory"))
        );
        assert!(has(&d, &format!("{base}/action"), "scalars"));
        assert!(has(&d, &format!("{base}/camera/observation.images.front"), "timestamp"));
        assert!(!d.rows.contains_key(&format!("{base}/state/features")), "80-dim key is not plotted");
    }
    assert!(
        d.statics.keys().any(|k| k.starts_with("media/observation.images.front/")),
        "{:?}",
        d.statics.keys()
    );
    // Summary: mean score of successes vs failures per step; failures are shorter than the
    // longest success, so the success curve is longer.
    let longest = |l: Label| (0..6).filter(|&i| LABELS[i] == l).map(steps_of).max().unwrap();
    assert_eq!(d.rows.get("summary/score/success").copied(), Some(longest(Label::Success)));
    assert_eq!(d.rows.get("summary/score/failure").copied(), Some(longest(Label::Failure)));
    assert_eq!(
        d.rows.get("summary/score/gap").copied(),
        Some(longest(Label::Success).min(longest(Label::Failure)))
    );
    assert_eq!(d.timelines["summary/score/gap"].iter().collect::<Vec<_>>(), ["step"]);
    assert!(d.statics.contains_key("summary/info"));
    // Per-episode data is sent as whole columns: one chunk per entity and episode, not per row.
    let path = format!("{}/action", episode_path(eps[0].label, &eps[0].id));
    assert_eq!(report.entities.iter().filter(|e| **e == path).count(), 1);

    // The in-memory writer produces the same content.
    let (mem, report2) = recording_bytes(&store, &opts, Some(&FakeVerifier)).await.unwrap();
    assert_eq!(report2, report);
    let d2 = decode(&mem);
    assert_eq!(d2.rows, d.rows);
    assert_eq!(d2.statics, d.statics);
}

#[tokio::test]
async fn split_limit_and_3d_positions() {
    let dir = tempfile::tempdir().unwrap();
    let store = make_store(dir.path(), &Opts { images: false, video: None }).await;
    let split = store
        .create_split(&SplitRequest {
            policy: "nav".into(),
            checkpoint: "ckpt1".into(),
            version: None,
            off_policy_from: vec![],
            val_fraction: 0.3,
            seed: 1,
            actor: "test".into(),
            max_episodes: None,
        })
        .await
        .unwrap();
    // Unknown-label episodes are not in splits: 5 labelled episodes.
    let in_split = store.split_episodes(&split.id).await.unwrap();
    assert_eq!(in_split.len(), 5);

    let mut opts = ViewOptions::new("nav", "ckpt1");
    opts.split_id = Some(split.id.clone());
    opts.position_keys = vec!["eef".into()];
    opts.max_episodes = Some(3);
    let (bytes, report) = recording_bytes(&store, &opts, None).await.unwrap();
    assert_eq!(report.episodes, 3);
    assert_eq!((report.success, report.failure), (2, 1), "round-robin over labels: S, F, S");
    assert_eq!(report.position_dims, vec!["eef[0]", "eef[1]", "eef[2]"]);
    assert!(!report.scored && report.max_separation.is_none());
    let d = decode(&bytes);
    let trajectories: Vec<&String> = d.statics.keys().filter(|k| k.ends_with("/trajectory")).collect();
    assert_eq!(trajectories.len(), 3);
    for t in trajectories {
        assert!(has(&d, t, "LineStrips3D"), "{:?}", d.components.get(t));
    }
    assert!(!d.rows.keys().any(|k| k.ends_with("/score") || k.starts_with("summary/score")));

    // Picked dims of a wider key, and errors that say what is wrong.
    opts.position_keys = vec!["eef[0,2]".into()];
    let (_, r) = recording_bytes(&store, &opts, None).await.unwrap();
    assert_eq!(r.position_dims, vec!["eef[0]", "eef[2]"]);
    let err_of = |r: Result<(Vec<u8>, ViewReport), ViewError>| match r {
        Ok((_, rep)) => panic!("expected an error, got {rep:?}"),
        Err(e) => e.to_string(),
    };
    opts.position_keys = vec!["pos".into(), "eef".into()];
    let err = err_of(recording_bytes(&store, &opts, None).await);
    assert!(err.contains("expected 2 or 3"), "{err}");
    opts.position_keys = vec!["nope".into()];
    let err = err_of(recording_bytes(&store, &opts, None).await);
    assert!(err.contains("nope"), "{err}");
    let err = err_of(recording_bytes(&store, &ViewOptions::new("", ""), None).await);
    assert!(err.contains("policy and a checkpoint"), "{err}");
}

/// `viewer/scripts/check_rrd.sh` installs rerun-sdk==0.36.3 from PyPI (once, into a cached venv)
/// and runs `rerun rrd verify` and `rerun rrd print` on a written recording.
#[tokio::test]
async fn check_rrd_with_official_rerun_sdk() {
    let dir = tempfile::tempdir().unwrap();
    let o = Opts { images: true, video: Some(sha256_hex(&fake_mp4())) };
    let store = make_store(dir.path(), &o).await;
    let out = dir.path().join("view.rrd");
    let opts = ViewOptions::new("nav", "ckpt1");
    write_recording(&store, &opts, Some(&FakeVerifier), &out).await.unwrap();

    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/check_rrd.sh");
    let res = std::process::Command::new("bash").arg(&script).arg(&out).output().expect("runs bash");
    let stdout = String::from_utf8_lossy(&res.stdout);
    let stderr = String::from_utf8_lossy(&res.stderr);
    if res.status.code() == Some(3) {
        // No python3 venv, or PyPI unreachable: a failure under UFOPS_REQUIRE_PYTHON, else a skip.
        let missing =
            format!("rerun-sdk=={RERUN_SDK_VERSION} from PyPI in a python3 venv (check_rrd.sh:\n{stderr})");
        if !store::test_support::require(store::test_support::Tool::Python, Err(missing)) {
            return;
        }
    }
    assert!(
        res.status.success(),
        "check_rrd.sh failed ({:?}):\nstdout:\n{stdout}\nstderr:\n{stderr}",
        res.status
    );
    assert!(
        stdout.contains(&format!("rerun-cli {RERUN_SDK_VERSION}")) || stdout.contains(RERUN_SDK_VERSION),
        "{stdout}"
    );
    assert!(stdout.contains("episodes/success"), "rrd print lists the episodes:\n{stdout}");
    assert!(stderr.contains("verified without error"), "rrd verify:\n{stderr}");
    assert!(stdout.contains("summary/score/gap") && stdout.contains("Blueprint"), "{stdout}");
    if let Ok(keep) = std::env::var("VIEWER_KEEP_CHECK_OUTPUT") {
        std::fs::write(keep, format!("{stdout}\n--- stderr\n{stderr}")).unwrap();
    }
}

/// A JPEG's start-of-image and end-of-image markers: enough for the store to record the column
/// as `jpeg` (the viewer passes the bytes through, it never decodes them).
const JPEG: [u8; 6] = [0xFF, 0xD8, 0xFF, 0xE0, 0xFF, 0xD9];

/// Every camera is logged by default: a robomimic-like store with two image cameras (one PNG,
/// one JPEG as ALOHA's compressed cameras are stored) gives each episode two EncodedImage
/// entities, one row per step on `step` and `time`, with the stored encoding's media type, and
/// a camera view per episode and camera in the blueprint.
#[tokio::test]
async fn two_image_cameras_every_step_with_their_media_type() {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open(&StoreConfig::local(dir.path().join("data"))).await.unwrap();
    let src = SourceInput {
        path: "/tmp/two_cameras.hdf5".into(),
        sha256: sha256_hex(b"two-cameras"),
        format: "test".into(),
        size_bytes: 1,
        metadata: serde_json::json!({}),
    };
    let mut w = store.begin_ingest(src, "lift", "ckpt").await.unwrap();
    let o = Opts { images: false, video: None };
    for (i, label) in [Label::Success, Label::Failure, Label::Success].into_iter().enumerate() {
        let mut ep = episode(i as u32, steps_of(i), label, &o);
        let n = steps_of(i);
        ep.images = vec![
            ImageColumn {
                name: "agentview_image".into(),
                shape: [2, 2, 3],
                frames: vec![PNG.to_vec(); n].into(),
            },
            ImageColumn { name: "cam_high".into(), shape: [2, 2, 3], frames: vec![JPEG.to_vec(); n].into() },
        ];
        w.add_episode(ep).await.unwrap();
    }
    w.commit("two cameras").await.unwrap();
    let eps = store.episodes(&EpisodeFilter::default()).await.unwrap();

    let out = dir.path().join("cams.rrd");
    let report = write_recording(&store, &ViewOptions::new("lift", "ckpt"), None, &out).await.unwrap();
    assert_eq!(report.cameras, ["agentview_image", "cam_high"]);
    assert_eq!(report.images, 2 * report.steps, "every step of both cameras");
    assert_eq!((report.videos, report.video_frames), (0, 0));
    let d = decode(&std::fs::read(&out).unwrap());
    for ep in &eps {
        let base = episode_path(ep.label, &ep.id);
        for (cam, media) in [("agentview_image", "image/png"), ("cam_high", "image/jpeg")] {
            let path = format!("{base}/image/{cam}");
            assert_eq!(d.rows.get(&path).copied(), Some(ep.length as usize), "{path}");
            assert_eq!(d.timelines[&path].iter().collect::<Vec<_>>(), ["step", "time"]);
            assert!(has(&d, &path, "EncodedImage:blob"), "{:?}", d.components.get(&path));
            assert_eq!(d.media_types[&path].iter().collect::<Vec<_>>(), [media], "{path}");
        }
    }

    // `no_images` leaves them out; `image_stride` samples them.
    let mut opts = ViewOptions::new("lift", "ckpt");
    opts.no_images = true;
    let (bytes, r) = recording_bytes(&store, &opts, None).await.unwrap();
    assert!(r.cameras.is_empty() && r.images == 0);
    assert!(!decode(&bytes).rows.keys().any(|k| k.contains("/image/")));
    opts.no_images = false;
    opts.image_stride = 3;
    let (_, r) = recording_bytes(&store, &opts, None).await.unwrap();
    assert_eq!(r.images, 2 * eps.iter().map(|e| (e.length as usize).div_ceil(3)).sum::<usize>());
}

/// The LeRobot v3.0 fixture keeps its 8 episodes in one shared mp4: the recording embeds it once
/// (a static AssetVideo) and each episode's camera entity has one VideoFrameReference per step,
/// at the episode's own frame times inside the file (the second episode's start at 7.8 s).
#[tokio::test]
async fn lerobot_v30_shared_video_embedded_once_and_referenced_per_step() {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open(&StoreConfig::local(dir.path().join("data"))).await.unwrap();
    let fixture = Path::new(env!("CARGO_MANIFEST_DIR")).join("../fixtures/lerobot/v30_eval_video");
    let opts = ingest::IngestOptions { policy: "p".into(), checkpoint: "c".into(), ..Default::default() };
    ingest::ingest(&store, &fixture, &opts).await.unwrap();
    let eps = store.episodes(&EpisodeFilter::default()).await.unwrap();
    assert_eq!(eps.len(), 8);

    let (bytes, report) = recording_bytes(&store, &ViewOptions::new("p", "c"), None).await.unwrap();
    assert_eq!(report.cameras, ["images.front"], "the key ingest stores");
    assert_eq!(report.videos, 1, "one shared mp4, embedded once");
    assert_eq!(report.video_frames, report.steps);
    assert_eq!(report.steps, 519);
    let d = decode(&bytes);
    let videos: Vec<&String> = d.statics.keys().filter(|k| k.starts_with("media/")).collect();
    assert_eq!(videos.len(), 1, "{videos:?}");
    assert!(has(&d, videos[0], "AssetVideo:blob"), "{:?}", d.components.get(videos[0]));
    assert_eq!(d.media_types[videos[0]].iter().collect::<Vec<_>>(), ["video/mp4"]);
    let mut firsts = Vec::new();
    for ep in &eps {
        let path = format!("{}/camera/images.front", episode_path(ep.label, &ep.id));
        assert_eq!(d.rows.get(&path).copied(), Some(ep.length as usize), "{path}");
        assert_eq!(d.timelines[&path].iter().collect::<Vec<_>>(), ["step", "time"]);
        let times = &d.video_times[&path];
        assert_eq!(times.len(), ep.length as usize);
        assert!(times.windows(2).all(|w| w[1] > w[0]), "frame times grow within an episode");
        firsts.push((ep.source_index, times[0], *times.last().unwrap()));
    }
    firsts.sort_by_key(|f| f.0);
    assert!(firsts[0].1.abs() < 1e-6, "{firsts:?}");
    assert!((firsts[1].1 - 7.8).abs() < 1e-6, "{firsts:?}");
    // Episodes follow one another in the shared file, without overlap.
    assert!(firsts.windows(2).all(|w| w[1].1 > w[0].2), "{firsts:?}");
}
