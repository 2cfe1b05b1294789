//! The robomimic export read by h5py along robomimic's documented layout: demos, states, obs,
//! next_obs, actions, rewards, dones, attributes and the split's masks compared with the source file (tests/python/check_robomimic_export.py).

use std::path::PathBuf;

use ingest::{ingest, IngestOptions};
use store::{select, Selection, SplitRequest, Store, StoreConfig};

fn fixtures() -> PathBuf {
    match std::env::var("UFOPS_FIXTURES") {
        Ok(p) => PathBuf::from(p),
        Err(_) => PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../fixtures"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn h5py_reads_the_robomimic_export_of_a_split() {
    if !store::test_support::require_python(&["h5py", "numpy"]) {
        return;
    }
    for name in ["lift_rollouts_lowdim", "lift_rollouts_image"] {
        let tmp = tempfile::tempdir().unwrap();
        let store = Store::open(&StoreConfig::local(tmp.path().join("store"))).await.unwrap();
        let src = fixtures().join(format!("robomimic/{name}.hdf5"));
        let opts = IngestOptions {
            policy: "bc".into(),
            checkpoint: "epoch-600".into(),
            success_file: Some(fixtures().join(format!("robomimic/{name}.success.json"))),
            ..Default::default()
        };
        ingest(&store, &src, &opts).await.unwrap();
        let req = SplitRequest {
            policy: "bc".into(),
            checkpoint: "epoch-600".into(),
            version: None,
            off_policy_from: vec![],
            val_fraction: 0.25,
            seed: 3,
            actor: "test".into(),
            max_episodes: None,
        };
        let split = store.create_split(&req).await.unwrap();
        let sel =
            select(&store, &Selection { split: Some(split.id.clone()), ..Default::default() }).await.unwrap();
        let out = tmp.path().join("export.hdf5");
        let rep = export::robomimic::export(&store, &sel, &out, None).await.unwrap();
        assert_eq!(rep.episodes, sel.episodes.len());
        // The exported demos are in source order, so demo_i is the source's demo_i.
        let mut labels = serde_json::Map::new();
        let mut masks: std::collections::BTreeMap<&str, Vec<String>> = Default::default();
        for (i, e) in sel.episodes.iter().enumerate() {
            assert_eq!(e.source_name, format!("demo_{i}"));
            labels.insert(e.source_name.clone(), serde_json::json!(e.label.as_bool()));
            let part = if sel.parts[&e.id] == "val" { "valid" } else { "train" };
            masks.entry(part).or_default().push(e.source_name.clone());
        }
        let expected = tmp.path().join("expected.json");
        std::fs::write(&expected, serde_json::json!({"labels": labels, "masks": masks}).to_string()).unwrap();
        let script =
            PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/python/check_robomimic_export.py");
        let out = std::process::Command::new("python3")
            .arg(script)
            .arg(&out)
            .arg(&src)
            .arg(&expected)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{name}: h5py check failed:\n{}\n{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
        eprintln!("{name}: {}", String::from_utf8_lossy(&out.stdout));
    }
}
