//! The LeRobot v3.0 export loads in PyPI's `lerobot` itself
//! (`LeRobotDataset`, local root, no Hub), and every frame it returns equals the export's data
//! (tests/python/check_lerobot_package.py). Sources: robomimic low-dim rollouts, a LeRobot
//! dataset with PNG image features, and the LeRobot v3.0 fixture with an mp4 camera: lerobot
//! decodes the export's video frames with its `pyav` backend (PyPI `av`
//! ships the FFmpeg libraries) and each equals the same mp4 decoded independently with PyAV.

use std::path::PathBuf;

use ingest::{ingest, IngestOptions};
use store::{select, Selection, Store, StoreConfig};

fn fixtures() -> PathBuf {
    match std::env::var("UFOPS_FIXTURES") {
        Ok(p) => PathBuf::from(p),
        Err(_) => PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../fixtures"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn lerobot_loads_the_export_frame_for_frame() {
    if !store::test_support::require_python(&["lerobot", "PIL", "av"]) {
        return;
    }
    let sources = [
        ("robomimic/lift_rollouts_lowdim.hdf5", Some("robomimic/lift_rollouts_lowdim.success.json")),
        ("lerobot/v30_unlabeled", None),
        ("lerobot/v30_eval_video", None),
    ];
    for (name, success) in sources {
        let tmp = tempfile::tempdir().unwrap();
        let store = Store::open(&StoreConfig::local(tmp.path().join("store"))).await.unwrap();
        let opts = IngestOptions {
            policy: "p".into(),
            checkpoint: "c".into(),
            success_file: success.map(|s| fixtures().join(s)),
            ..Default::default()
        };
        ingest(&store, &fixtures().join(name), &opts).await.unwrap();
        let sel = select(&store, &Selection::default()).await.unwrap();
        let out = tmp.path().join("export");
        let report = export::lerobot::export(&store, &sel, &out, None).await.unwrap();
        let script =
            PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/python/check_lerobot_package.py");
        let res = std::process::Command::new("python3")
            .arg(script)
            .arg(&out)
            .env("HF_HUB_OFFLINE", "1")
            .output()
            .unwrap();
        assert!(
            res.status.success(),
            "{name}: lerobot could not load the export:\n{}\n{}",
            String::from_utf8_lossy(&res.stdout),
            String::from_utf8_lossy(&res.stderr)
        );
        let summary: serde_json::Value = serde_json::from_slice(&res.stdout).unwrap();
        assert_eq!(summary["frames"].as_u64(), Some(report.frames), "{name}: {summary}");
        assert_eq!(summary["episodes"].as_u64().unwrap() as usize, report.episodes, "{name}: {summary}");
        assert!(summary["features"].as_array().unwrap().iter().any(|f| f == "action"), "{name}: {summary}");
        if name.ends_with("video") {
            // One camera: every frame lerobot returned carried a decoded video frame, checked.
            assert_eq!(summary["video_frames"].as_u64(), Some(report.frames), "{name}: {summary}");
        }
        eprintln!("{name}: {summary}");
    }
}
