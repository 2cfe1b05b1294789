//! The LeRobot v3.0 export read with pyarrow along the v3.0 layout and compared with the source
//! dataset frame by frame, episode by episode, video file by video file
//! (tests/python/check_lerobot_export.py). PyPI's `lerobot` itself is not used: it pulls torch,
//! torchvision, diffusers and wandb (several GB), too much for the test suite.

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
async fn pyarrow_reads_the_lerobot_export_as_the_source() {
    if !store::test_support::require_python(&["pyarrow"]) {
        return;
    }
    for name in ["v30_eval_video", "v30_unlabeled", "v21_eval_video"] {
        let tmp = tempfile::tempdir().unwrap();
        let store = Store::open(&StoreConfig::local(tmp.path().join("store"))).await.unwrap();
        let src = fixtures().join("lerobot").join(name);
        let opts = IngestOptions { policy: "act".into(), checkpoint: "last".into(), ..Default::default() };
        ingest(&store, &src, &opts).await.unwrap();
        let sel = select(&store, &Selection::default()).await.unwrap();
        let out = tmp.path().join("export");
        export::lerobot::export(&store, &sel, &out, None).await.unwrap();
        let script =
            PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/python/check_lerobot_export.py");
        let res = std::process::Command::new("python3").arg(script).arg(&out).arg(&src).output().unwrap();
        assert!(
            res.status.success(),
            "{name}: pyarrow check failed:\n{}\n{}",
            String::from_utf8_lossy(&res.stdout),
            String::from_utf8_lossy(&res.stderr)
        );
        eprintln!("{name}: {}", String::from_utf8_lossy(&res.stdout));
    }
}
