//! Round trips: every shared robomimic and LeRobot fixture is ingested,
//! exported (LeRobot v3.0, robomimic HDF5) and the export ingested into a second store; both
//! stores hold the same episodes: the same labels, tasks and lengths, every step column equal
//! bit for bit (floats compared as bits), the same media objects (content-addressed by sha256)
//! and the same extra columns (robomimic `states`, `next_obs`, `model_file`).

use std::path::{Path, PathBuf};

use arrow::array::{Array, RecordBatch};
use ingest::{ingest, IngestOptions};
use store::{select, EpisodeFilter, EpisodeRecord, Selection, Store, StoreConfig};

fn fixtures() -> PathBuf {
    match std::env::var("UFOPS_FIXTURES") {
        Ok(p) => PathBuf::from(p),
        Err(_) => PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../fixtures"),
    }
}

fn opts(success_file: Option<PathBuf>) -> IngestOptions {
    IngestOptions {
        policy: "toy-dp".into(),
        checkpoint: "step-80000".into(),
        success_file,
        ..Default::default()
    }
}

async fn open(dir: &Path) -> Store {
    Store::open(&StoreConfig::local(dir)).await.unwrap()
}

async fn episodes(s: &Store) -> Vec<EpisodeRecord> {
    let mut eps = s.episodes(&EpisodeFilter::default()).await.unwrap();
    eps.sort_by_key(|e| e.source_index);
    eps
}

/// Columns that name the store or the source rather than hold the episode's data.
const PROVENANCE: [&str; 2] = ["episode_id", "label_source"];

/// Every step column of `a` equals `b`'s, floats bit for bit (ArrayData equality compares the
/// value buffers); the schemas (names, types, field metadata) are the same.
fn same_steps(a: &RecordBatch, b: &RecordBatch, what: &str) {
    let names = |x: &RecordBatch| x.schema().fields().iter().map(|f| f.name().clone()).collect::<Vec<_>>();
    assert_eq!(names(a), names(b), "{what}: columns");
    for f in a.schema().fields() {
        if PROVENANCE.contains(&f.name().as_str()) {
            continue;
        }
        let (x, y) = (a.column_by_name(f.name()).unwrap(), b.column_by_name(f.name()).unwrap());
        assert_eq!(x.data_type(), y.data_type(), "{what}: {} type", f.name());
        assert_eq!(
            f.metadata(),
            b.schema().field_with_name(f.name()).unwrap().metadata(),
            "{what}: {} metadata",
            f.name()
        );
        assert!(x.to_data() == y.to_data(), "{what}: column {} differs", f.name());
        // Floats: the same bits (not only equal values).
        if let Some(l) = x.as_any().downcast_ref::<arrow::array::FixedSizeListArray>() {
            if let Some(v) = l.values().as_any().downcast_ref::<arrow::array::Float32Array>() {
                let w = y.as_any().downcast_ref::<arrow::array::FixedSizeListArray>().unwrap().values();
                let w = w.as_any().downcast_ref::<arrow::array::Float32Array>().unwrap();
                let bits = |a: &arrow::array::Float32Array| {
                    a.values().iter().map(|f| f.to_bits()).collect::<Vec<_>>()
                };
                assert_eq!(bits(v), bits(w), "{what}: {} bits", f.name());
            }
        }
    }
}

/// Ingests `source`, exports it with `export`, ingests the export; compares the two stores.
async fn round_trip(source: &Path, success_file: Option<PathBuf>, format: &str) {
    let tmp = tempfile::tempdir().unwrap();
    let a = open(&tmp.path().join("a")).await;
    let b = open(&tmp.path().join("b")).await;
    ingest(&a, source, &opts(success_file)).await.unwrap();
    let sel = select(&a, &Selection::default()).await.unwrap();
    let out = tmp.path().join(if format == "lerobot" { "export" } else { "export.hdf5" });
    let rep = match format {
        "lerobot" => export::lerobot::export(&a, &sel, &out, None).await.unwrap(),
        _ => export::robomimic::export(&a, &sel, &out, None).await.unwrap(),
    };
    assert_eq!(rep.episodes, sel.episodes.len());
    // Nothing staged is left beside the export.
    let left: Vec<_> = std::fs::read_dir(tmp.path())
        .unwrap()
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().contains(".tmp-"))
        .collect();
    assert!(left.is_empty(), "{left:?}");
    let back = ingest(&b, &out, &opts(None)).await.unwrap();
    assert!(back.notes.is_empty(), "{}: {:?}", source.display(), back.notes);

    let (ea, eb) = (episodes(&a).await, episodes(&b).await);
    assert_eq!(ea.len(), eb.len(), "{}", source.display());
    for (x, y) in ea.iter().zip(&eb) {
        let what = format!("{} -> {format}: {} / {}", source.display(), x.source_name, y.source_name);
        assert_eq!(x.label, y.label, "{what}");
        assert_eq!(x.task, y.task, "{what}");
        assert_eq!(x.length, y.length, "{what}");
        assert_eq!(x.tags, y.tags, "{what}");
        let (sa, sb) = (a.read_steps(&x.id, None).await.unwrap(), b.read_steps(&y.id, None).await.unwrap());
        same_steps(&sa, &sb, &what);
    }
    // The same media objects, by content.
    let media = |s: &Store| {
        let mut v: Vec<String> = std::fs::read_dir(s.data_dir().join("objects/media"))
            .map(|rd| rd.flatten().map(|e| e.file_name().to_string_lossy().into_owned()).collect())
            .unwrap_or_default();
        v.sort();
        v
    };
    assert_eq!(media(&a), media(&b), "{}: media objects", source.display());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn lerobot_fixtures_round_trip_through_lerobot_v30() {
    for name in ["v30_eval_video", "v30_unlabeled", "v21_eval_video"] {
        round_trip(&fixtures().join("lerobot").join(name), None, "lerobot").await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn robomimic_fixtures_round_trip_through_robomimic_hdf5() {
    for name in ["lift_rollouts_lowdim", "lift_rollouts_image"] {
        let dir = fixtures().join("robomimic");
        round_trip(
            &dir.join(format!("{name}.hdf5")),
            Some(dir.join(format!("{name}.success.json"))),
            "robomimic",
        )
        .await;
    }
}

/// The export writes the version's frozen labels and records where it came from.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn exports_frozen_labels_with_provenance() {
    let tmp = tempfile::tempdir().unwrap();
    let a = open(&tmp.path().join("a")).await;
    let src = fixtures().join("lerobot/v30_eval_video");
    let v = ingest(&a, &src, &opts(None)).await.unwrap().version;
    let eps = episodes(&a).await;
    // A label edit after the version: not in the version's frozen labels.
    let flipped = eps.iter().find(|e| e.label == store::Label::Success).unwrap();
    a.set_label(
        store::LabelUpdate {
            episode_id: flipped.id.clone(),
            label: store::Label::Failure,
            expect_revision: None,
            note: None,
        },
        "t",
        "test",
    )
    .await
    .unwrap();
    let sel =
        select(&a, &Selection { version: Some(v), label: Some(store::Label::Success), ..Default::default() })
            .await
            .unwrap();
    assert_eq!(sel.episodes.len(), eps.iter().filter(|e| e.label == store::Label::Success).count());
    let out = tmp.path().join("succ");
    export::lerobot::export(&a, &sel, &out, None).await.unwrap();
    let info: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("meta/info.json")).unwrap()).unwrap();
    assert_eq!(info["codebase_version"], "v3.0");
    assert_eq!(info["ufops"]["store_version"], v);
    assert_eq!(info["ufops"]["selection"]["label"], "success");
    let files = info["ufops"]["label_files"].as_array().unwrap();
    assert!(
        !files.is_empty() && files.iter().all(|f| f.as_str().unwrap().starts_with("labels/")),
        "{files:?}"
    );
    assert_eq!(info["total_episodes"], sel.episodes.len());
    // An existing output is refused, untouched.
    let err = export::lerobot::export(&a, &sel, &out, None).await.unwrap_err();
    assert!(err.to_string().contains("already exists"), "{err}");
}
