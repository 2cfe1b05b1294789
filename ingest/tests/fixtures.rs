//! Every fixture in the repository's fixtures/ against its expected.json (readers only, no store).

use crate::common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use common::{expected, fixtures};
use ingest::model::Label;
use ingest::options::SuccessFile;
use ingest::sink::CollectSink;
use ingest::{read_path, Format, IngestError, ReadOptions};
use serde_json::Value;

fn read(rel: &str, opts: &ReadOptions) -> Result<CollectSink, IngestError> {
    let mut s = CollectSink::default();
    read_path(&fixtures().join(rel), Format::Auto, opts, &mut s)?;
    Ok(s)
}

fn label_of(v: &Value) -> Label {
    Label::from_bool(v.as_bool())
}

// ---------------------------------------------------------------- robomimic

fn check_robomimic(name: &str) {
    let exp = expected(&format!("robomimic/{name}.expected.json"));
    let sf = SuccessFile::load(&fixtures().join(format!("robomimic/{name}.success.json"))).unwrap();
    let opts = ReadOptions { success_file: Some(sf), ..Default::default() };
    let s = read(&format!("robomimic/{name}.hdf5"), &opts).unwrap();
    let eps = exp["episodes"].as_array().unwrap();
    assert_eq!(s.episodes.len(), eps.len());
    let mut total = 0;
    for (e, x) in s.episodes.iter().zip(eps) {
        assert_eq!(e.source_name, x["name"].as_str().unwrap());
        assert_eq!(e.len() as u64, x["length"].as_u64().unwrap(), "{}", e.source_name);
        assert_eq!(e.label, label_of(&x["success"]), "{}", e.source_name);
        assert_eq!(e.label_source, format!("success-file:{name}.success.json"));
        assert_eq!(e.action.dim as u64, exp["action_dim"].as_u64().unwrap());
        assert_eq!(e.task.as_deref(), Some("Lift"));
        // control_freq 20 → 0.05 s steps
        assert!((e.timestamps[1] - 0.05).abs() < 1e-12);
        // every obs key with its dim/shape
        for (k, v) in exp["obs_keys"].as_object().unwrap() {
            if let Some(d) = v.as_u64() {
                let c = e.observations.iter().find(|o| &o.name == k).unwrap_or_else(|| panic!("no obs {k}"));
                assert_eq!(c.dim as u64, d, "{k}");
                assert_eq!(c.values.len(), e.len() * c.dim);
            } else {
                let shape: Vec<usize> =
                    v.as_array().unwrap().iter().map(|x| x.as_u64().unwrap() as usize).collect();
                let im = e.images.iter().find(|i| &i.name == k).unwrap_or_else(|| panic!("no image {k}"));
                assert_eq!(im.shape.to_vec(), shape);
                assert_eq!(im.frames.len(), e.len());
            }
        }
        // the 38 KB model_file is summarized, not copied
        let mf = &e.metadata["model_file"];
        assert_eq!(mf["sha256"].as_str().unwrap().len(), 64);
        assert!(serde_json::to_string(&e.metadata).unwrap().len() < 2000);
        total += e.len();
    }
    assert_eq!(total as u64, exp["total"].as_u64().unwrap());
    let src = s.source.unwrap();
    assert_eq!(src.format, "robomimic");
    assert_eq!(src.metadata["env_args"]["env_name"], "Lift");
    assert_eq!(src.metadata["total"].as_i64().unwrap() as u64, exp["total"].as_u64().unwrap());

    // --success-from rewards gives the same labels (sparse reward 1.0 on success)
    let opts = ReadOptions { success_from_rewards: Some(1.0), ..Default::default() };
    let s = read(&format!("robomimic/{name}.hdf5"), &opts).unwrap();
    for (e, x) in s.episodes.iter().zip(eps) {
        assert_eq!(e.label, label_of(&x["success"]), "{}", e.source_name);
        assert_eq!(e.label_source, "rewards>=1");
    }
    // no label source: unknown
    let s = read(&format!("robomimic/{name}.hdf5"), &ReadOptions::default()).unwrap();
    assert!(s.episodes.iter().all(|e| e.label == Label::Unknown));
}

#[test]
fn robomimic_lowdim() {
    check_robomimic("lift_rollouts_lowdim");
}

#[test]
fn robomimic_image() {
    check_robomimic("lift_rollouts_image");
    // PNG frames are lossless: decode the first frame of demo_1 and compare with next_obs[0]
    // of... (obs[0] is correct in every demo, see the fixture README)
    let s = read("robomimic/lift_rollouts_image.hdf5", &ReadOptions::default()).unwrap();
    let im = &s.episodes[1].images[0];
    let dec = png::Decoder::new(std::io::Cursor::new(&im.frames.as_encoded().expect("collected")[0]));
    let mut r = dec.read_info().unwrap();
    let mut buf = vec![0; r.output_buffer_size().unwrap()];
    let info = r.next_frame(&mut buf).unwrap();
    assert_eq!((info.width, info.height), (84, 84));
    assert_eq!(info.buffer_size(), 84 * 84 * 3);
    let file = hdf5_pure::File::open(fixtures().join("robomimic/lift_rollouts_image.hdf5")).unwrap();
    let raw = file.dataset("data/demo_1/obs/agentview_image").unwrap().read_u8().unwrap();
    assert_eq!(&buf[..84 * 84 * 3], &raw[..84 * 84 * 3]);
}

#[test]
fn robomimic_truncated_fails_naming_the_file() {
    let exp = expected("robomimic/truncated.expected.json");
    assert!(exp["must_fail"].as_bool().unwrap());
    let err = read("robomimic/truncated.hdf5", &ReadOptions::default()).map(|_| ()).expect_err("must fail");
    let msg = err.to_string();
    assert!(msg.contains("truncated.hdf5"), "{msg}");
}

#[test]
fn success_file_csv_and_bad() {
    let labels = ingest::options::parse_success_text("demo,success\ndemo_0,true\ndemo_1,0\n").unwrap();
    assert!(labels["demo_0"]);
    assert!(!labels["demo_1"]);
    assert!(ingest::options::parse_success_text("demo_0,maybe\ndemo_1,what\n").is_err());
    assert!(ingest::options::parse_success_text("[1,2]").is_err());
}

// ---------------------------------------------------------------- LeRobot

fn check_lerobot(name: &str) {
    let exp = expected(&format!("lerobot/{name}.expected.json"));
    let s = read(&format!("lerobot/{name}"), &ReadOptions::default()).unwrap();
    let eps = exp["episodes"].as_array().unwrap();
    assert_eq!(s.episodes.len() as u64, exp["total_episodes"].as_u64().unwrap());
    let mut frames = 0;
    let (mut ns, mut nf, mut nu) = (0, 0, 0);
    for (e, x) in s.episodes.iter().zip(eps) {
        assert_eq!(e.source_index as u64, x["episode_index"].as_u64().unwrap());
        assert_eq!(e.len() as u64, x["length"].as_u64().unwrap());
        assert_eq!(e.task.as_deref(), x["task"].as_str());
        assert_eq!(e.label, label_of(&x["success"]), "episode {}", e.source_name);
        match e.label {
            Label::Success => ns += 1,
            Label::Failure => nf += 1,
            Label::Unknown => nu += 1,
        }
        if x["success"].is_null() {
            assert_eq!(e.label_source, "");
        } else {
            assert_eq!(e.label_source, "lerobot:next.success");
        }
        if let Some(sr) = x.get("sum_reward").and_then(|v| v.as_f64()) {
            let got: f64 = e.reward.iter().map(|&r| r as f64).sum();
            assert!((got - sr).abs() < 1e-3, "sum_reward {got} vs {sr}");
        }
        assert_eq!(e.action.dim, 6);
        assert_eq!(e.observations.len(), 1);
        assert_eq!(e.observations[0].dim, 6);
        assert!(e.done.last().copied().unwrap());
        for (t0, t1) in e.timestamps.iter().zip(e.timestamps.iter().skip(1)) {
            assert!(t1 > t0);
        }
        assert_eq!(e.media.len(), exp["video_keys"].as_array().unwrap().len());
        assert_eq!(e.images.len(), exp["image_keys"].as_array().unwrap().len());
        for im in &e.images {
            assert_eq!(im.shape, [64, 64, 3]);
            assert_eq!(im.frames.len(), e.len());
        }
        for m in &e.media {
            assert_eq!(m.timestamps.len(), e.len());
            assert!(s.media.iter().any(|f| f.sha256 == m.sha256), "media file emitted");
        }
        frames += e.len();
    }
    assert_eq!(frames as u64, exp["total_frames"].as_u64().unwrap());
    assert_eq!(ns, exp["n_success"].as_u64().unwrap());
    assert_eq!(nf, exp["n_failure"].as_u64().unwrap());
    assert_eq!(nu, exp["n_unlabeled"].as_u64().unwrap());
    let src = s.source.unwrap();
    assert_eq!(src.metadata["fps"].as_f64().unwrap(), exp["fps"].as_f64().unwrap());
    assert_eq!(src.metadata["robot_type"], exp["robot_type"]);
    assert_eq!(src.metadata["codebase_version"], exp["codebase_version"]);
    let tasks: Vec<&str> =
        src.metadata["tasks"].as_array().unwrap().iter().map(|t| t.as_str().unwrap()).collect();
    let mut want: Vec<&str> = exp["tasks"].as_array().unwrap().iter().map(|t| t.as_str().unwrap()).collect();
    let mut got = tasks.clone();
    got.sort();
    want.sort();
    assert_eq!(got, want);
    for k in exp["features"].as_object().unwrap().keys() {
        assert!(src.metadata["features"].get(k).is_some(), "feature {k} in metadata");
    }
    // media files: sha256 matches the file, each emitted once
    let mut seen = std::collections::HashSet::new();
    for m in &s.media {
        assert!(seen.insert(m.sha256.clone()), "media emitted twice");
        assert_eq!(ingest::hashing::hash_file(&m.local_path).unwrap().0, m.sha256);
    }
}

#[test]
fn lerobot_v30_eval_video() {
    check_lerobot("v30_eval_video");
    let s = read("lerobot/v30_eval_video", &ReadOptions::default()).unwrap();
    // one shared mp4 for all 8 episodes: stored once; frame times continue across episodes
    assert_eq!(s.media.len(), 1);
    let e1 = &s.episodes[1];
    assert!((e1.media[0].timestamps[0] - 7.8).abs() < 1e-6, "{}", e1.media[0].timestamps[0]);
    assert!(e1.timestamps[0].abs() < 1e-9);
}

#[test]
fn lerobot_v21_eval_video() {
    check_lerobot("v21_eval_video");
    let s = read("lerobot/v21_eval_video", &ReadOptions::default()).unwrap();
    assert_eq!(s.media.len(), 6);
}

#[test]
fn lerobot_v30_unlabeled() {
    check_lerobot("v30_unlabeled");
}

// ---------------------------------------------------------------- MCAP

fn counts(v: &Value) -> BTreeMap<String, u64> {
    v.as_object().unwrap().iter().map(|(k, v)| (k.clone(), v.as_u64().unwrap())).collect()
}

fn check_mcap_episodes(s: &CollectSink, eps: &[Value]) {
    assert_eq!(s.episodes.len(), eps.len());
    for (e, x) in s.episodes.iter().zip(eps) {
        assert_eq!(e.source_index as u64, x["index"].as_u64().unwrap());
        assert_eq!(e.metadata["start_ns"].as_u64(), x["start_ns"].as_u64());
        assert_eq!(e.metadata["end_ns"].as_u64(), x["end_ns"].as_u64());
        assert_eq!(e.label, label_of(&x["success"]));
        let got: BTreeMap<String, u64> = counts(&e.metadata["message_counts"]);
        assert_eq!(got, counts(&x["message_counts"]), "episode {}", e.source_name);
        // one step per action message
        assert_eq!(e.len() as u64, x["message_counts"]["/action"].as_u64().unwrap());
        assert_eq!(e.action.dim, 7);
        let jp = e.observations.iter().find(|o| o.name == "joint_pos").expect("joint_pos");
        assert_eq!(jp.dim, 7);
        for k in ["policy", "checkpoint"] {
            if let Some(p) = x.get(k) {
                assert_eq!(&e.metadata[k], p);
            }
        }
    }
}

fn check_mcap(name: &str) {
    let exp = expected(&format!("mcap/{name}.expected.json"));
    let path = fixtures().join(format!("mcap/{name}.mcap"));
    let mut s = CollectSink::default();
    let rep = ingest::mcapfmt::read_file(&path, &ReadOptions::default(), &mut s).unwrap();
    assert_eq!(rep.summary.message_count, exp["message_count"].as_u64().unwrap());
    assert_eq!(rep.summary.message_counts, counts(&exp["message_counts"]));
    assert_eq!(rep.summary.first_log_time, exp["message_start_time_ns"].as_u64());
    assert_eq!(rep.summary.last_log_time, exp["message_end_time_ns"].as_u64());
    assert_eq!(rep.summary.profile, exp["profile"].as_str().unwrap());
    assert!(rep.summary.truncated.is_none());
    check_mcap_episodes(&s, exp["episodes"].as_array().unwrap());
    let n_s = s.episodes.iter().filter(|e| e.label == Label::Success).count();
    assert_eq!(n_s as u64, exp["n_success"].as_u64().unwrap());
    let n_f = s.episodes.iter().filter(|e| e.label == Label::Failure).count();
    assert_eq!(n_f as u64, exp["n_failure"].as_u64().unwrap());
    let src = s.source.unwrap();
    for m in exp["other_metadata"].as_array().unwrap() {
        assert!(src.metadata["metadata"].get(m.as_str().unwrap()).is_some());
    }
    // joint names reach the decoded messages: checked through the topic schema names
    for (t, x) in exp["topics"].as_object().unwrap() {
        assert_eq!(src.metadata["topics"][t]["schema"], x["schema"]);
    }
}

#[test]
fn mcap_ros2_jointstate() {
    check_mcap("ros2_jointstate_eval");
}

#[test]
fn mcap_protobuf() {
    check_mcap("protobuf_eval");
}

#[test]
fn mcap_json_event_topic() {
    check_mcap("json_eval");
}

#[test]
fn mcap_truncated_refused_then_recovered() {
    let exp = expected("mcap/truncated.expected.json");
    let rec = &exp["streaming_recovery"];
    let path = fixtures().join("mcap/truncated.mcap");
    let mut s = CollectSink::default();
    let err = ingest::mcapfmt::read_file(&path, &ReadOptions::default(), &mut s).unwrap_err();
    let msg = err.to_string();
    assert!(matches!(err, IngestError::Truncated { recoverable: 3, .. }), "{msg}");
    assert!(msg.contains("truncated.mcap"), "{msg}");
    assert!(msg.contains("Recovered 928 messages"), "{msg}");
    assert!(msg.contains("complete episodes: 0, 1, 2"), "{msg}");
    assert!(msg.contains("160 message(s)"), "{msg}");
    assert!(msg.contains("--recover"), "{msg}");

    let opts = ReadOptions { recover: true, ..Default::default() };
    let mut s = CollectSink::default();
    let rep = ingest::mcapfmt::read_file(&path, &opts, &mut s).unwrap();
    assert_eq!(rep.summary.message_counts, counts(&rec["message_counts"]));
    assert_eq!(rep.summary.last_log_time, rec["last_recovered_log_time_ns"].as_u64());
    let complete: Vec<i64> =
        rec["episodes_fully_recovered"].as_array().unwrap().iter().map(|x| x.as_i64().unwrap()).collect();
    assert_eq!(rep.episodes, complete);
    let full = exp["full_file_episodes"].as_array().unwrap();
    let want: Vec<Value> =
        full.iter().filter(|e| complete.contains(&e["index"].as_i64().unwrap())).cloned().collect();
    check_mcap_episodes(&s, &want);
    let names: Vec<&str> = rep.summary.metadata.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(
        names.iter().filter(|n| **n == "episode").count(),
        rec["episode_metadata_indices"].as_array().unwrap().len()
    );
}

#[test]
fn mcap_conformance_all_read() {
    let dir = fixtures().join("mcap/conformance");
    let mut n = 0;
    for ent in std::fs::read_dir(&dir).unwrap() {
        let p: PathBuf = ent.unwrap().path();
        if p.extension().and_then(|e| e.to_str()) != Some("mcap") {
            continue;
        }
        n += 1;
        let exp: Value =
            serde_json::from_str(&std::fs::read_to_string(p.with_extension("json")).unwrap()).unwrap();
        let recs = exp["records"].as_array().unwrap();
        let count = |t: &str| recs.iter().filter(|r| r["type"] == t).count();
        let f = std::fs::File::open(&p).unwrap();
        let size = f.metadata().unwrap().len();
        let sum = ingest::mcapfmt::scan(&p, &mut std::io::BufReader::new(f), size)
            .unwrap_or_else(|e| panic!("{}: {e}", p.display()));
        assert_eq!(sum.message_count as usize, count("Message"), "{}", p.display());
        assert_eq!(sum.metadata.len(), count("Metadata"), "{}", p.display());
        assert_eq!(sum.attachments, count("Attachment"), "{}", p.display());
        assert!(sum.truncated.is_none(), "{}: {:?}", p.display(), sum.truncated);
        // the ingest reader reads them too: it refuses (no episodes/no action topic), never panics
        let mut s = CollectSink::default();
        let r = ingest::mcapfmt::read_file(&p, &ReadOptions::default(), &mut s);
        let e = r.expect_err("conformance files hold no episodes");
        assert!(e.to_string().contains(p.file_name().unwrap().to_str().unwrap()));
        // with a mapping that takes their `example` topic as the action... they hold raw bytes
        // in encoding "a", which is reported as unsupported, by name
        let m = ingest::mapping::Mapping::parse("action = { topic = \"example\" }").unwrap();
        let opts = ReadOptions { mapping: Some(m), ..Default::default() };
        if let Err(e) = ingest::mcapfmt::read_file(&p, &opts, &mut CollectSink::default()) {
            assert!(e.to_string().contains(".mcap"), "{e}");
        }
    }
    assert_eq!(n, 23);
}

#[test]
fn detect_formats() {
    let f = fixtures();
    assert_eq!(ingest::detect(&f.join("robomimic/lift_rollouts_lowdim.hdf5")).unwrap(), Format::Robomimic);
    assert_eq!(ingest::detect(&f.join("lerobot/v21_eval_video")).unwrap(), Format::Lerobot);
    assert_eq!(ingest::detect(&f.join("mcap/json_eval.mcap")).unwrap(), Format::Mcap);
    let e = ingest::detect(&f.join("robomimic")).unwrap_err().to_string();
    assert!(e.contains("info.json"), "{e}");
    let _ = Path::new("");
}
