//! `lerobot-eval` output folders (`fixtures/lerobot_eval/`, written by lerobot 0.4.4 and 0.3.3's own
//! `lerobot-eval`) against their `expected.json` (figures read with Python's json and PyAV): every
//! episode's label, seed, pair key, rewards and frames; seeds from `--start-seed` or the file;
//! several tasks; what is refused. Into a store: all or nothing, and the videos stored once.

use crate::common;

use std::path::{Path, PathBuf};

use common::{expected, fixtures};
use ingest::model::Label;
use ingest::sink::CollectSink;
use ingest::{read_path_report, Format, IngestOptions, ReadOptions};
use serde_json::{json, Value};

fn read(path: &Path, opts: &ReadOptions) -> Result<(CollectSink, Vec<String>), ingest::IngestError> {
    let mut s = CollectSink::default();
    let r = read_path_report(path, Format::Auto, opts, &mut s)?;
    assert_eq!(r.format, Format::LerobotEval);
    Ok((s, r.notes))
}

fn seeded(start: i64) -> ReadOptions {
    ReadOptions { start_seed: Some(start), ..Default::default() }
}

/// Every episode of `layout`'s run `name` as the expected file lists it.
fn check_run(layout: &str, name: &str, opts: &ReadOptions) -> CollectSink {
    let exp = expected(&format!("lerobot_eval/{layout}.expected.json"));
    let run = &exp["runs"][name];
    let (s, _) = read(&fixtures().join(format!("lerobot_eval/{layout}/{name}")), opts).unwrap();
    let eps = run["episodes"].as_array().unwrap();
    assert_eq!(s.episodes.len(), eps.len());
    assert_eq!(s.media.len() as u64, run["videos"].as_u64().unwrap(), "one media file per video");
    let task = exp["task_group"].as_str().map(|g| format!("{g}_{}", exp["task_id"]));
    for (e, x) in s.episodes.iter().zip(eps) {
        let i = x["index"].as_u64().unwrap();
        let ctx = format!("{layout}/{name} episode {i}");
        assert_eq!(e.source_index as u64, i, "{ctx}");
        assert_eq!(e.source_name, format!("episode_{i}"), "{ctx}");
        assert_eq!(e.label, Label::from_bool(x["success"].as_bool()), "{ctx}");
        assert_eq!(e.label_source, "lerobot-eval:success", "{ctx}");
        assert_eq!(e.task, None, "one task: no task name, {ctx}");
        let md = &e.metadata;
        assert_eq!(md["episode_index"], x["index"], "{ctx}");
        assert_eq!(md["seed"], x["seed"], "{ctx}");
        let seed = x["seed"].as_i64().unwrap();
        let key = match &task {
            Some(t) => format!("{t}/seed:{seed}"),
            None => format!("seed:{seed}"),
        };
        assert_eq!(md["pair_key"], json!(key), "{ctx}");
        assert_eq!(md["sum_reward"], x["sum_reward"], "{ctx}");
        assert_eq!(md["max_reward"], x["max_reward"], "{ctx}");
        assert_eq!(md["success"], x["success"], "{ctx}");
        assert_eq!(e.action.dim, 0, "{ctx}");
        assert!(e.observations.is_empty() && e.images.is_empty(), "{ctx}");
        assert_eq!(e.reward, vec![0.0; e.len()], "{ctx}");
        assert_eq!(e.done.iter().filter(|d| **d).count(), 1, "{ctx}");
        assert!(*e.done.last().unwrap(), "{ctx}");
        match x["video"].as_str() {
            Some(video) => {
                let frames = x["frames"].as_u64().unwrap() as usize;
                let fps = x["fps"].as_f64().unwrap();
                assert_eq!(e.len(), frames, "one step per frame, {ctx}");
                assert_eq!(e.media.len(), 1, "{ctx}");
                let m = &e.media[0];
                assert_eq!(m.name, "render");
                for (t, (a, b)) in m.timestamps.iter().zip(&e.timestamps).enumerate() {
                    assert!((a - t as f64 / fps).abs() < 1e-9 && a == b, "{ctx}: frame {t} at {a}");
                }
                let file = s.media.iter().find(|f| f.sha256 == m.sha256).expect("its media file");
                assert!(file.local_path.ends_with(video), "{ctx}: {}", file.local_path.display());
                assert_eq!(ingest::hashing::hash_file(&file.local_path).unwrap().0, m.sha256);
                assert_eq!(md["video"]["file"], json!(video), "{ctx}");
                assert_eq!(md["video"]["frames"], json!(frames), "{ctx}");
                assert_eq!(md["video"]["fps"], json!(fps), "{ctx}");
                assert_eq!(md["video"]["codec"], "H.264", "{ctx}");
                assert!(md.get("outcome_only").is_none(), "{ctx}");
            }
            None => {
                assert_eq!((e.len(), e.timestamps[0]), (1, 0.0), "outcome only: one step, {ctx}");
                assert!(e.media.is_empty(), "{ctx}");
                assert_eq!(md["video"], Value::Null, "{ctx}");
                assert_eq!(md["outcome_only"], json!(true), "{ctx}");
            }
        }
    }
    let labels = |l: Label| s.episodes.iter().filter(|e| e.label == l).count() as u64;
    assert_eq!(labels(Label::Success), run["n_success"].as_u64().unwrap());
    assert_eq!(labels(Label::Failure), run["n_failure"].as_u64().unwrap());
    s
}

#[test]
fn lerobot_04_output_with_its_start_seed() {
    for name in ["ckpt-a", "ckpt-b"] {
        let s = check_run("v04", name, &seeded(1000));
        let src = s.source.unwrap();
        assert_eq!(src.format, "lerobot-eval");
        assert_eq!(src.metadata["layout"], "per_task (lerobot >= 0.4)");
        assert_eq!(src.metadata["seeds"], "--start-seed");
        assert_eq!(src.metadata["start_seed"], 1000);
        assert_eq!(
            src.metadata["tasks"],
            json!([{"task_group": "pusht", "task_id": 0, "episodes": 8, "videos": 5}])
        );
        assert_eq!(src.metadata["overall"]["n_episodes"], 8);
        assert!(src.metadata["overall"].get("video_paths").is_none(), "video lists are not copied");
        for e in &s.episodes {
            assert_eq!((&e.metadata["task_group"], &e.metadata["task_id"]), (&json!("pusht"), &json!(0)));
        }
    }
}

#[test]
fn lerobot_04_output_without_a_start_seed_has_no_seeds_and_says_so() {
    let (s, notes) = read(&fixtures().join("lerobot_eval/v04/ckpt-a"), &ReadOptions::default()).unwrap();
    assert!(s.episodes.iter().all(|e| e.metadata["seed"].is_null() && e.metadata["pair_key"].is_null()));
    assert_eq!(s.source.unwrap().metadata["seeds"], "unknown");
    assert_eq!(notes.len(), 1, "{notes:?}");
    assert!(notes[0].contains("does not record seeds") && notes[0].contains("--start-seed"), "{notes:?}");
}

#[test]
fn lerobot_03_output_records_its_seeds() {
    for name in ["ckpt-a", "ckpt-b"] {
        let s = check_run("v03", name, &ReadOptions::default());
        let src = s.source.unwrap();
        assert_eq!(src.metadata["layout"], "per_episode (lerobot <= 0.3)");
        assert_eq!(src.metadata["seeds"], "eval_info.json");
        assert!(src.metadata["aggregated"]["pc_success"].as_f64().is_some());
        assert!(s.episodes.iter().all(|e| e.metadata.get("task_group").is_none()));
    }
    // The seed the file records agrees with --start-seed, or the ingest is refused.
    check_run("v03", "ckpt-a", &seeded(1000));
    let err = read(&fixtures().join("lerobot_eval/v03/ckpt-a"), &seeded(7)).unwrap_err().to_string();
    assert!(err.contains("--start-seed 7") && err.contains("starting at 1000"), "{err}");
}

/// The 0.4 output of ckpt-a copied to `dir`, its eval_info.json rewritten by `edit`.
fn edited_copy(dir: &Path, edit: impl FnOnce(&mut Value, &Path)) -> PathBuf {
    let src = fixtures().join("lerobot_eval/v04/ckpt-a");
    let root = dir.join("eval");
    for f in walk(&src) {
        let to = root.join(f.strip_prefix(&src).unwrap());
        std::fs::create_dir_all(to.parent().unwrap()).unwrap();
        std::fs::copy(&f, &to).unwrap();
    }
    let mut info: Value =
        serde_json::from_slice(&std::fs::read(root.join("eval_info.json")).unwrap()).unwrap();
    edit(&mut info, &root);
    std::fs::write(root.join("eval_info.json"), serde_json::to_vec_pretty(&info).unwrap()).unwrap();
    root
}

fn walk(d: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(d).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            out.extend(walk(&p));
        } else {
            out.push(p);
        }
    }
    out
}

/// A suite of two tasks (as LIBERO's are evaluated): each task restarts at the start seed, so
/// the pair key names the task; episode names and tasks are `<task_group>_<task_id>`. Video
/// paths written under an absolute output dir are found in the folder all the same.
#[test]
fn several_tasks_are_named_and_keyed_by_task() {
    let tmp = tempfile::tempdir().unwrap();
    let root = edited_copy(tmp.path(), |info, root| {
        let mut second = info["per_task"][0].clone();
        second["task_id"] = json!(1);
        let videos: Vec<Value> = (0..2)
            .map(|i| json!(format!("/home/someone/outputs/eval/run/videos/pusht_1/eval_episode_{i}.mp4")))
            .collect();
        second["metrics"]["video_paths"] = Value::Array(videos);
        std::fs::create_dir_all(root.join("videos/pusht_1")).unwrap();
        for i in 0..2 {
            let v = format!("eval_episode_{i}.mp4");
            std::fs::copy(root.join("videos/pusht_0").join(&v), root.join("videos/pusht_1").join(&v))
                .unwrap();
        }
        info["per_task"].as_array_mut().unwrap().push(second);
    });
    let (s, _) = read(&root, &seeded(1000)).unwrap();
    assert_eq!(s.episodes.len(), 16);
    assert_eq!(s.media.len(), 5, "task 1's 2 videos are copies of task 0's: passed on once");
    let e = &s.episodes[9];
    assert_eq!(
        (e.source_index, e.source_name.as_str(), e.task.as_deref()),
        (9, "pusht_1/episode_1", Some("pusht_1"))
    );
    assert_eq!((&e.metadata["seed"], &e.metadata["pair_key"]), (&json!(1001), &json!("pusht_1/seed:1001")));
    assert_eq!(e.media.len(), 1);
    assert_eq!(s.episodes[1].metadata["pair_key"], "pusht_0/seed:1001");
    assert_eq!(s.episodes[1].task.as_deref(), Some("pusht_0"));
    assert!(s.episodes[10].media.is_empty(), "task 1 rendered 2 episodes");
    // --task names every episode's task.
    let opts = ReadOptions { task: Some("push-t".into()), ..seeded(1000) };
    let (s, _) = read(&root, &opts).unwrap();
    assert!(s.episodes.iter().all(|e| e.task.as_deref() == Some("push-t")));
}

/// lerobot-eval renders whole batches: with 5 episodes in batches of 2, episode 5 of the last
/// batch is rendered too, past the episodes the file keeps. That video is left out.
#[test]
fn videos_past_the_episodes_are_left_out_with_a_note() {
    let tmp = tempfile::tempdir().unwrap();
    let root = edited_copy(tmp.path(), |info, _| {
        let m = &mut info["per_task"][0]["metrics"];
        for k in ["sum_rewards", "max_rewards", "successes"] {
            m[k].as_array_mut().unwrap().truncate(4);
        }
    });
    let (s, notes) = read(&root, &seeded(1000)).unwrap();
    assert_eq!((s.episodes.len(), s.media.len()), (4, 4));
    assert!(notes.iter().any(|n| n.contains("1 videos listed past the 4 episodes")), "{notes:?}");
}

#[test]
fn refused_options_and_broken_outputs() {
    let eval = fixtures().join("lerobot_eval/v04/ckpt-a");
    let refused = |opts: ReadOptions, want: &str| {
        let err = read(&eval, &opts).expect_err("refused").to_string();
        assert!(err.contains(want), "{err}");
    };
    refused(ReadOptions { success_from_rewards: Some(1.0), ..Default::default() }, "no per-step rewards");
    refused(ReadOptions { intervention_key: Some("x".into()), ..Default::default() }, "no takeover flags");
    // --start-seed is lerobot-eval's only.
    let mut s = CollectSink::default();
    let err = read_path_report(&fixtures().join("lerobot/v30_eval_video"), Format::Auto, &seeded(1), &mut s)
        .unwrap_err()
        .to_string();
    assert!(err.contains("--start-seed 1: only lerobot-eval output"), "{err}");
    // The file itself: ingest its folder.
    let err = ingest::detect(&eval.join("eval_info.json")).unwrap_err().to_string();
    assert!(err.contains("ingest the folder that holds it"), "{err}");

    let tmp = tempfile::tempdir().unwrap();
    let missing = edited_copy(&tmp.path().join("a"), |_, root| {
        std::fs::remove_file(root.join("videos/pusht_0/eval_episode_2.mp4")).unwrap();
    });
    let err = read(&missing, &seeded(1000)).unwrap_err().to_string();
    assert!(err.contains("eval_episode_2.mp4: missing: the video of episode 2"), "{err}");
    let short = edited_copy(&tmp.path().join("b"), |info, _| {
        info["per_task"][0]["metrics"]["max_rewards"].as_array_mut().unwrap().pop();
    });
    let err = read(&short, &seeded(1000)).unwrap_err().to_string();
    assert!(err.contains("task pusht_0: 8 successes but 7 max_rewards"), "{err}");
    let not_video = edited_copy(&tmp.path().join("c"), |_, root| {
        std::fs::write(root.join("videos/pusht_0/eval_episode_0.mp4"), b"not a video").unwrap();
    });
    let err = read(&not_video, &seeded(1000)).unwrap_err().to_string();
    assert!(err.contains("eval_episode_0.mp4: not a readable MP4 video"), "{err}");
}

/// Into a store: two runs, the videos stored once each; a broken output leaves the store as it
/// was; the same output again is a no-op.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn into_a_store_all_or_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let store = store::Store::open(&store::StoreConfig::local(tmp.path().join("store"))).await.unwrap();
    let opts = |ckpt: &str| IngestOptions {
        policy: "diffusion-pusht".into(),
        checkpoint: ckpt.into(),
        start_seed: Some(1000),
        ..Default::default()
    };
    let exp = expected("lerobot_eval/v04.expected.json");
    for name in ["ckpt-a", "ckpt-b"] {
        let path = fixtures().join(format!("lerobot_eval/v04/{name}"));
        let rep = ingest::ingest(&store, &path, &opts(name)).await.unwrap();
        let run = &exp["runs"][name];
        let steps: u64 =
            run["episodes"].as_array().unwrap().iter().map(|e| e["frames"].as_u64().unwrap().max(1)).sum();
        assert_eq!((rep.format.as_str(), rep.episodes, rep.steps), ("lerobot-eval", 8, steps));
        assert_eq!(rep.labels.success as u64, run["n_success"].as_u64().unwrap());
        assert_eq!(rep.media_files as u64, run["videos"].as_u64().unwrap());
        let again = ingest::ingest(&store, &path, &opts(name)).await.unwrap();
        assert!(again.already_ingested);
    }
    let head = store.head_version().await.unwrap();
    let broken = edited_copy(tmp.path(), |_, root| {
        std::fs::write(root.join("videos/pusht_0/eval_episode_4.mp4"), b"\0\0\0\x08moov").unwrap();
    });
    let err = ingest::ingest(&store, &broken, &opts("ckpt-c")).await.unwrap_err().to_string();
    assert!(err.contains("eval_episode_4.mp4"), "{err}");
    assert_eq!(store.head_version().await.unwrap(), head, "the store is as it was");
}
