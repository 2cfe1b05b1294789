//! Human takeovers, end to end through the binary: a LeRobot
//! v3.0 dataset laid out as `lerobot-rollout --strategy dagger` records one (the bool feature
//! `intervention`, shape [1], true on the frames a human drove; generated here, in a temp dir) is
//! ingested; the flags survive ingest → export → ingest → export frame for frame; the catalog,
//! the API's episode detail and steps carry them; an on-policy split reports the steps before the
//! first takeover per checkpoint, and the trainer's samples stop at each takeover (counted). The
//! page's takeover strip is checked in headless Chromium by `takeover_strip_in_the_labeling_page`.

use crate::common::{self, Target};
use arrow::array::{
    Array, ArrayRef, AsArray, BooleanArray, FixedSizeListArray, Float32Array, Int64Array, ListBuilder,
    RecordBatch, StringArray, StringBuilder,
};
use arrow::datatypes::{DataType, Field};
use serde_json::{json, Value};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

const STEPS: usize = 30;

/// Per episode, the steps a human drove (inclusive runs). Episode 1 hands back to the policy
/// (the HG-DAgger loop), 2 is taken over twice, 3 from its first step, 0 never.
const TAKEOVERS: [&[(usize, usize)]; 5] = [&[], &[(10, 19)], &[(5, 7), (15, 29)], &[(0, 4)], &[(25, 29)]];

fn intervention_of(e: usize) -> Vec<bool> {
    (0..STEPS).map(|t| TAKEOVERS[e].iter().any(|&(a, b)| (a..=b).contains(&t))).collect()
}

fn first_takeover(e: usize) -> Option<usize> {
    TAKEOVERS[e].first().map(|r| r.0)
}

fn parquet(path: &Path, batch: RecordBatch) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    let f = std::fs::File::create(path).unwrap();
    let mut w = parquet::arrow::ArrowWriter::try_new(f, batch.schema(), None).unwrap();
    w.write(&batch).unwrap();
    w.close().unwrap();
}

fn f32_list(values: Vec<f32>, dim: i32) -> ArrayRef {
    let item = Arc::new(Field::new("item", DataType::Float32, true));
    Arc::new(FixedSizeListArray::try_new(item, dim, Arc::new(Float32Array::from(values)), None).unwrap())
}

/// A LeRobot v3.0 DAgger rollout dataset, as lerobot 0.6's `LeRobotDataset` writes one for
/// `lerobot-rollout --strategy dagger`: the features of the robot (a 4-D state and action), the
/// bookkeeping columns, and `intervention` (bool, shape [1]: a scalar bool column), with one
/// task. `lerobot-rollout` records no success: labels come from a side file.
fn write_dagger_dataset(root: &Path) {
    let episodes = TAKEOVERS.len();
    let info = json!({
        "codebase_version": "v3.0", "robot_type": "so101_follower", "fps": 30,
        "total_episodes": episodes, "total_frames": episodes * STEPS, "total_tasks": 1,
        "chunks_size": 1000, "data_files_size_in_mb": 100, "video_files_size_in_mb": 200,
        "data_path": "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet",
        "video_path": null,
        "features": {
            "action": {"dtype": "float32", "shape": [4], "names": ["j0.pos", "j1.pos", "j2.pos", "gripper.pos"]},
            "observation.state": {"dtype": "float32", "shape": [4], "names": ["j0.pos", "j1.pos", "j2.pos", "gripper.pos"]},
            "intervention": {"dtype": "bool", "shape": [1], "names": null},
            "timestamp": {"dtype": "float32", "shape": [1], "names": null},
            "frame_index": {"dtype": "int64", "shape": [1], "names": null},
            "episode_index": {"dtype": "int64", "shape": [1], "names": null},
            "index": {"dtype": "int64", "shape": [1], "names": null},
            "task_index": {"dtype": "int64", "shape": [1], "names": null}
        }
    });
    std::fs::create_dir_all(root.join("meta")).unwrap();
    std::fs::write(root.join("meta/info.json"), serde_json::to_vec_pretty(&info).unwrap()).unwrap();
    let tasks: Vec<(&str, ArrayRef)> = vec![
        ("task_index", Arc::new(Int64Array::from(vec![0i64]))),
        ("task", Arc::new(StringArray::from(vec!["put the cube in the bowl"]))),
    ];
    parquet(&root.join("meta/tasks.parquet"), RecordBatch::try_from_iter(tasks).unwrap());
    let ep: Vec<i64> = (0..episodes as i64).collect();
    let mut task_lists = ListBuilder::new(StringBuilder::new());
    for _ in 0..episodes {
        task_lists.values().append_value("put the cube in the bowl");
        task_lists.append(true);
    }
    let meta: Vec<(&str, ArrayRef)> = vec![
        ("episode_index", Arc::new(Int64Array::from(ep.clone()))),
        ("tasks", Arc::new(task_lists.finish())),
        ("length", Arc::new(Int64Array::from(vec![STEPS as i64; episodes]))),
        ("data/chunk_index", Arc::new(Int64Array::from(vec![0i64; episodes]))),
        ("data/file_index", Arc::new(Int64Array::from(vec![0i64; episodes]))),
        ("dataset_from_index", Arc::new(Int64Array::from_iter_values(ep.iter().map(|e| e * STEPS as i64)))),
        (
            "dataset_to_index",
            Arc::new(Int64Array::from_iter_values(ep.iter().map(|e| (e + 1) * STEPS as i64))),
        ),
    ];
    parquet(
        &root.join("meta/episodes/chunk-000/file-000.parquet"),
        RecordBatch::try_from_iter(meta).unwrap(),
    );
    let n = episodes * STEPS;
    let flags: Vec<bool> = (0..episodes).flat_map(intervention_of).collect();
    let data: Vec<(&str, ArrayRef)> = vec![
        ("action", f32_list((0..n * 4).map(|k| (k as f32 * 0.01).sin()).collect(), 4)),
        ("observation.state", f32_list((0..n * 4).map(|k| (k as f32 * 0.01).cos()).collect(), 4)),
        ("intervention", Arc::new(BooleanArray::from(flags))),
        ("timestamp", Arc::new(Float32Array::from_iter_values((0..n).map(|r| (r % STEPS) as f32 / 30.0)))),
        ("frame_index", Arc::new(Int64Array::from_iter_values((0..n).map(|r| (r % STEPS) as i64)))),
        ("episode_index", Arc::new(Int64Array::from_iter_values((0..n).map(|r| (r / STEPS) as i64)))),
        ("index", Arc::new(Int64Array::from_iter_values(0..n as i64))),
        ("task_index", Arc::new(Int64Array::from(vec![0i64; n]))),
    ];
    parquet(&root.join("data/chunk-000/file-000.parquet"), RecordBatch::try_from_iter(data).unwrap());
}

/// The dataset and its labels (a success file: episodes 0, 1 and 3 succeeded).
fn dagger_source(dir: &Path) -> (PathBuf, PathBuf) {
    let ds = dir.join("rollout_dagger");
    write_dagger_dataset(&ds);
    let labels = dir.join("labels.json");
    let l: BTreeMap<String, bool> =
        (0..TAKEOVERS.len()).map(|e| (format!("episode_{e:06}"), [0, 1, 3].contains(&e))).collect();
    std::fs::write(&labels, serde_json::to_vec(&l).unwrap()).unwrap();
    (ds, labels)
}

/// `episode_index` → the `intervention` frames of a LeRobot v3.0 dataset's data files, and its
/// info.json's `intervention` feature.
fn exported_flags(root: &Path) -> (BTreeMap<i64, Vec<bool>>, Value) {
    let info: Value = serde_json::from_slice(&std::fs::read(root.join("meta/info.json")).unwrap()).unwrap();
    let mut out: BTreeMap<i64, Vec<bool>> = BTreeMap::new();
    let mut files: Vec<PathBuf> = walk(&root.join("data"));
    files.sort();
    for f in files {
        let r = parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder::try_new(
            std::fs::File::open(&f).unwrap(),
        )
        .unwrap()
        .build()
        .unwrap();
        for b in r {
            let b = b.unwrap();
            let ep = b.column_by_name("episode_index").unwrap().as_primitive::<arrow::datatypes::Int64Type>();
            let flag = b.column_by_name("intervention").expect("an intervention column").as_boolean().clone();
            assert_eq!(flag.null_count(), 0);
            for r in 0..b.num_rows() {
                out.entry(ep.value(r)).or_default().push(flag.value(r));
            }
        }
    }
    (out, info["features"]["intervention"].clone())
}

fn walk(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            out.extend(walk(&p));
        } else if p.extension().is_some_and(|x| x == "parquet") {
            out.push(p);
        }
    }
    out
}

/// `source_name` → `(first_intervention, intervention_steps)` of the store's episodes.
fn catalog_takeovers(t: &Target, policy: &str) -> BTreeMap<String, (Value, Value)> {
    let eps = t.json(&["episodes", "--policy", policy, "--json"]);
    eps.as_array()
        .unwrap()
        .iter()
        .map(|e| {
            let name = e["source_name"].as_str().unwrap().to_string();
            (name, (e["first_intervention"].clone(), e["intervention_steps"].clone()))
        })
        .collect()
}

fn expected_catalog() -> BTreeMap<String, (Value, Value)> {
    (0..TAKEOVERS.len())
        .map(|e| {
            let steps = intervention_of(e).iter().filter(|&&b| b).count();
            (format!("episode_{e:06}"), (json!(first_takeover(e)), json!(steps)))
        })
        .collect()
}

#[test]
fn takeovers_survive_ingest_export_ingest_and_bound_on_policy_samples() {
    let dir = tempfile::tempdir().unwrap();
    let (ds, labels) = dagger_source(dir.path());
    let expected_flags: BTreeMap<i64, Vec<bool>> =
        (0..TAKEOVERS.len()).map(|e| (e as i64, intervention_of(e))).collect();
    // The generator wrote what it meant to (read back as lerobot's Parquet).
    assert_eq!(exported_flags(&ds).0, expected_flags);

    let a = Target::sqlite(&dir.path().join("a"));
    ingest_dagger(&a, &ds, &labels);
    assert_eq!(catalog_takeovers(&a, "so101"), expected_catalog());

    // Export, ingest the export into a second store, export again: the same flags each time.
    let out1 = dir.path().join("export1");
    a.json(&["export", out1.to_str().unwrap(), "--format", "lerobot", "--json"]);
    let (flags1, feature) = exported_flags(&out1);
    assert_eq!(flags1, expected_flags);
    assert_eq!(
        feature,
        json!({"dtype": "bool", "shape": [1], "names": null}),
        "as lerobot-rollout declares it"
    );
    let b = Target::sqlite(&dir.path().join("b"));
    b.json(&["ingest", out1.to_str().unwrap(), "--policy", "so101", "--checkpoint", "c1", "--json"]);
    assert_eq!(catalog_takeovers(&b, "so101"), expected_catalog());
    let out2 = dir.path().join("export2");
    b.json(&["export", out2.to_str().unwrap(), "--format", "lerobot", "--json"]);
    assert_eq!(exported_flags(&out2).0, expected_flags);

    // A flag under another name: --intervention-key; a name the dataset lacks is refused.
    let renamed = dir.path().join("renamed");
    write_dagger_dataset(&renamed);
    rename_feature(&renamed, "intervention", "human_correction");
    let c = Target::sqlite(&dir.path().join("c"));
    let r = c.run(&[
        "ingest",
        renamed.to_str().unwrap(),
        "--policy",
        "p",
        "--checkpoint",
        "c",
        "--intervention-key",
        "nope",
    ]);
    let err = String::from_utf8_lossy(&r.stderr);
    assert!(
        !r.status.success()
            && err.contains("--intervention-key \"nope\"")
            && err.contains("human_correction"),
        "{err}"
    );
    let l = labels.to_str().unwrap();
    c.json(&[
        "ingest",
        renamed.to_str().unwrap(),
        "--policy",
        "p",
        "--checkpoint",
        "c",
        "--intervention-key",
        "human_correction",
        "--success-file",
        l,
        "--json",
    ]);
    assert_eq!(catalog_takeovers(&c, "p"), expected_catalog());

    // The API: the episode detail and its steps carry the takeovers.
    let admin = a.token("admin", "admin");
    let srv = a.serve(&["--no-worker"]);
    let (_, page) = api(&srv.url, "/v1/episodes?policy=so101", &admin);
    let listed = page["episodes"].as_array().unwrap();
    assert_eq!(listed.len(), TAKEOVERS.len());
    for e in listed {
        let idx: usize = e["source_name"].as_str().unwrap()["episode_".len()..].parse().unwrap();
        let id = e["id"].as_str().unwrap();
        let (st, d) = api(&srv.url, &format!("/v1/episodes/{id}"), &admin);
        assert_eq!(st, 200, "{d}");
        assert_eq!(d["episode"]["first_intervention"], json!(first_takeover(idx)), "{d}");
        let (st, s) = api(&srv.url, &format!("/v1/episodes/{id}/steps"), &admin);
        assert_eq!(st, 200, "{s}");
        assert_eq!(s["columns"]["intervention"], json!(intervention_of(idx)), "episode {idx}");
    }
    drop(srv);

    // The split: every checkpoint's share of steps before a takeover, in its summary.
    let split = a.json(&[
        "split",
        "create",
        "--policy",
        "so101",
        "--checkpoint",
        "c1",
        "--val-fraction",
        "0",
        "--json",
    ]);
    let on_policy: usize = (0..TAKEOVERS.len()).map(|e| first_takeover(e).unwrap_or(STEPS)).sum();
    let total = TAKEOVERS.len() * STEPS;
    let c1 = &split["checkpoint_steps"][0];
    assert_eq!(split["checkpoint_steps"].as_array().unwrap().len(), 1, "{split}");
    assert_eq!((c1["policy"].as_str(), c1["checkpoint"].as_str()), (Some("so101"), Some("c1")));
    assert_eq!(c1["episodes"], json!(TAKEOVERS.len()));
    assert_eq!(c1["episodes_taken_over"], json!(4));
    assert_eq!(c1["steps"], json!(total));
    assert_eq!(c1["on_policy_steps"], json!(on_policy));
    assert!((c1["on_policy_fraction"].as_f64().unwrap() - on_policy as f64 / total as f64).abs() < 1e-12);
    let split_id = split["id"].as_str().unwrap();
    let shown = a.ok(&["split", "show", split_id]);
    assert!(
        shown.contains(&format!("so101/c1: on-policy 46.7% of steps ({on_policy} of {total}; 4 of 5")),
        "{shown}"
    );

    // The trainer's samples: one per step before each episode's first takeover, none after.
    let rt = tokio::runtime::Runtime::new().unwrap();
    let store = rt.block_on(store::Store::open(&store::StoreConfig::local(&a.data_dir))).unwrap();
    let spec = trainer::TrainJobSpec {
        split_id: split_id.to_string(),
        kind: trainer::Kind::Classifier,
        config: None,
        obs_keys: None,
        obs_history: Some(2),
        chunk_len: Some(4),
        step_stride: None,
        ensemble: None,
    };
    let data = rt.block_on(trainer::load_split(&store, &spec)).unwrap();
    assert_eq!(data.train.len(), TAKEOVERS.len());
    let samples = trainer::build_samples(&data.train, &data.input, 0.99).unwrap();
    assert_eq!(samples.len(), on_policy, "one sample per on-policy step (of {total} steps)");
    for (i, ep) in data.train.iter().enumerate() {
        let idx = listed
            .iter()
            .find(|e| e["id"] == json!(ep.id))
            .map(|e| e["source_name"].as_str().unwrap()["episode_".len()..].parse::<usize>().unwrap())
            .unwrap();
        let ts: Vec<u32> = samples
            .episode
            .iter()
            .zip(&samples.t)
            .filter(|(e, _)| **e as usize == i)
            .map(|(_, t)| *t)
            .collect();
        let want = first_takeover(idx).unwrap_or(STEPS);
        assert_eq!(ts, (0..want as u32).collect::<Vec<_>>(), "episode {idx}: samples stop at the takeover");
        // The chunk of the last step before a takeover repeats that step's action, never the
        // human's that follow it (chunk of 4 actions of dimension 4).
        if let (Some(last), Some(_)) = (ts.last(), first_takeover(idx)) {
            let k = samples
                .t
                .iter()
                .zip(&samples.episode)
                .position(|(t, e)| t == last && *e as usize == i)
                .unwrap();
            let act = &samples.act[k * 16..(k + 1) * 16];
            let own = &ep.actions[*last as usize * 4..(*last as usize + 1) * 4];
            for j in 0..4 {
                assert_eq!(&act[j * 4..(j + 1) * 4], own, "episode {idx}: chunk step {j}");
            }
        }
    }
}

/// Renames a data column and its feature (a dataset whose takeover flag has another name).
fn rename_feature(root: &Path, from: &str, to: &str) {
    let p = root.join("meta/info.json");
    let mut info: Value = serde_json::from_slice(&std::fs::read(&p).unwrap()).unwrap();
    let f = info["features"].as_object_mut().unwrap().remove(from).unwrap();
    info["features"][to] = f;
    std::fs::write(&p, serde_json::to_vec(&info).unwrap()).unwrap();
    let data = root.join("data/chunk-000/file-000.parquet");
    let r = parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder::try_new(
        std::fs::File::open(&data).unwrap(),
    )
    .unwrap()
    .build()
    .unwrap();
    let batches: Vec<RecordBatch> = r.map(|b| b.unwrap()).collect();
    let b = arrow::compute::concat_batches(&batches[0].schema(), &batches).unwrap();
    let cols: Vec<(String, ArrayRef)> = b
        .schema()
        .fields()
        .iter()
        .zip(b.columns())
        .map(|(f, c)| (if f.name() == from { to.to_string() } else { f.name().clone() }, c.clone()))
        .collect();
    parquet(&data, RecordBatch::try_from_iter(cols).unwrap());
}

/// The DAgger dataset and its labels ingested as `so101/c1`.
fn ingest_dagger(t: &Target, ds: &Path, labels: &Path) {
    let (ds, labels) = (ds.to_str().unwrap(), labels.to_str().unwrap());
    t.json(&["ingest", ds, "--policy", "so101", "--checkpoint", "c1", "--success-file", labels, "--json"]);
}

fn api(url: &str, path: &str, token: &str) -> (u16, Value) {
    let auth = format!("Bearer {token}");
    let r = common::http(url, "GET", path, &[("Authorization", &auth), ("Accept", "application/json")], None);
    (r.status, r.json())
}

/// The page: the takeover strip of each episode (its spans, seeking by a click, the metadata row)
/// in headless Chromium (`tests/web/takeovers_e2e.mjs`); screenshot `takeovers_timeline.png`.
#[test]
fn takeover_strip_in_the_labeling_page() {
    use crate::common::browser;
    if !browser::available() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let (ds, labels) = dagger_source(dir.path());
    let t = Target::sqlite(&dir.path().join("store"));
    ingest_dagger(&t, &ds, &labels);
    let labeler = t.token("alice", "labeler");
    let eps = t.json(&["episodes", "--policy", "so101", "--json"]);
    let id_of = |e: usize| {
        eps.as_array().unwrap().iter().find(|x| x["source_name"] == json!(format!("episode_{e:06}"))).unwrap()
            ["id"]
            .as_str()
            .unwrap()
            .to_string()
    };
    // No takeover, two takeovers, one from the first step.
    let expect: serde_json::Map<String, Value> =
        [0, 2, 3].iter().map(|&e| (id_of(e), json!(TAKEOVERS[e]))).collect();
    let srv = t.serve(&["--no-worker"]);
    browser::forget_screenshot("takeovers_timeline.png");
    let result = browser::run_script(
        "takeovers_e2e.mjs",
        &srv.url,
        &[
            ("UFOPS_TOKEN_A", labeler),
            ("UFOPS_EXPECT", Value::Object(expect).to_string()),
            ("UFOPS_SHOT", id_of(2)),
        ],
    );
    assert_eq!(
        result[id_of(2)]["seeked"],
        json!(15),
        "the click on the second takeover seeks to step 15: {result}"
    );
    assert_eq!(result[id_of(0)]["spans"], json!([]), "{result}");
    browser::assert_screenshot("takeovers_timeline.png");
}

/// The flags in the HDF5 layouts: the DAgger dataset exported as robomimic and as ALOHA keeps
/// its takeovers (an `intervention` dataset per demo / file) through another ingest. (ALOHA's
/// reader needs `/observations/qpos`: the ALOHA copy names its state so.)
#[test]
fn takeovers_round_trip_through_robomimic_and_aloha() {
    let dir = tempfile::tempdir().unwrap();
    let (ds, labels) = dagger_source(dir.path());
    for format in ["robomimic", "aloha"] {
        let src = if format == "aloha" {
            let d = dir.path().join("dagger-qpos");
            write_dagger_dataset(&d);
            rename_feature(&d, "observation.state", "observation.qpos");
            d
        } else {
            ds.clone()
        };
        let a = Target::sqlite(&dir.path().join(format!("a-{format}")));
        ingest_dagger(&a, &src, &labels);
        let out = dir.path().join(format!("out-{format}"));
        let out = if format == "robomimic" { out.with_extension("hdf5") } else { out };
        a.json(&["export", out.to_str().unwrap(), "--format", format, "--json"]);
        let b = Target::sqlite(&dir.path().join(format!("b-{format}")));
        b.json(&["ingest", out.to_str().unwrap(), "--policy", "so101", "--checkpoint", "c1", "--json"]);
        // Source names differ by layout (demo_<i>, episode_<i>); the flags follow the order.
        let want: Vec<(Value, Value)> = expected_catalog().into_values().collect();
        assert_eq!(catalog_by_index(&b), want, "{format}");
    }
}

/// `(first_intervention, intervention_steps)` of a store's episodes in source order.
fn catalog_by_index(t: &Target) -> Vec<(Value, Value)> {
    let eps = t.json(&["episodes", "--json"]);
    let mut v: Vec<(i64, (Value, Value))> = eps
        .as_array()
        .unwrap()
        .iter()
        .map(|e| {
            (
                e["source_index"].as_i64().unwrap(),
                (e["first_intervention"].clone(), e["intervention_steps"].clone()),
            )
        })
        .collect();
    v.sort_by_key(|(i, _)| *i);
    v.into_iter().map(|(_, x)| x).collect()
}

/// GR00T's validity (`annotation.human.validity`, an index into the tasks `valid` / `invalid`)
/// is kept as the steps' `validity` and written back as the same feature, indexes into the same
/// task names; an index that names another task keeps no validity and says why.
#[test]
fn gr00t_validity_round_trips_as_task_indexes() {
    let dir = tempfile::tempdir().unwrap();
    let ds = dir.path().join("gr00t");
    write_dagger_dataset(&ds);
    // Tasks: 0 the instruction, 1 "valid", 2 "invalid"; episode e's steps t >= 20 - 3e invalid
    // (episode 4: from step 8), and the flag under GR00T's name.
    let p = ds.join("meta/info.json");
    let mut info: Value = serde_json::from_slice(&std::fs::read(&p).unwrap()).unwrap();
    info["features"]["annotation.human.validity"] = json!({"dtype": "int64", "shape": [1], "names": null});
    info["total_tasks"] = json!(3);
    std::fs::write(&p, serde_json::to_vec(&info).unwrap()).unwrap();
    let tasks: Vec<(&str, ArrayRef)> = vec![
        ("task_index", Arc::new(Int64Array::from(vec![0i64, 1, 2]))),
        ("task", Arc::new(StringArray::from(vec!["put the cube in the bowl", "valid", "invalid"]))),
    ];
    parquet(&ds.join("meta/tasks.parquet"), RecordBatch::try_from_iter(tasks).unwrap());
    let valid = |e: usize, t: usize| t + 3 * e < 20;
    add_column(&ds, "annotation.human.validity", |e, t| if valid(e, t) { 1 } else { 2 });

    let a = Target::sqlite(&dir.path().join("a"));
    a.json(&["ingest", ds.to_str().unwrap(), "--policy", "g", "--checkpoint", "c", "--json"]);
    let out = dir.path().join("export");
    a.json(&["export", out.to_str().unwrap(), "--format", "lerobot", "--json"]);
    let info: Value = serde_json::from_slice(&std::fs::read(out.join("meta/info.json")).unwrap()).unwrap();
    assert_eq!(info["features"]["annotation.human.validity"]["dtype"], "int64", "{info}");
    let names = task_names(&out);
    let got = column_by_episode(&out, "annotation.human.validity");
    for (e, rows) in &got {
        let want: Vec<&str> =
            (0..STEPS).map(|t| if valid(*e as usize, t) { "valid" } else { "invalid" }).collect();
        let have: Vec<&str> = rows.iter().map(|i| names[i].as_str()).collect();
        assert_eq!(have, want, "episode {e}");
    }
    // Through a second ingest the same again.
    let b = Target::sqlite(&dir.path().join("b"));
    b.json(&["ingest", out.to_str().unwrap(), "--policy", "g", "--checkpoint", "c", "--json"]);
    let out2 = dir.path().join("export2");
    b.json(&["export", out2.to_str().unwrap(), "--format", "lerobot", "--json"]);
    let names2 = task_names(&out2);
    let again: BTreeMap<i64, Vec<String>> = column_by_episode(&out2, "annotation.human.validity")
        .into_iter()
        .map(|(e, v)| (e, v.iter().map(|i| names2[i].clone()).collect()))
        .collect();
    let first: BTreeMap<i64, Vec<String>> =
        got.into_iter().map(|(e, v)| (e, v.iter().map(|i| names[i].clone()).collect())).collect();
    assert_eq!(again, first);

    // An index naming the instruction: no validity kept, and the episode's metadata says why.
    let odd = dir.path().join("odd");
    write_dagger_dataset(&odd);
    let p = odd.join("meta/info.json");
    let mut info: Value = serde_json::from_slice(&std::fs::read(&p).unwrap()).unwrap();
    info["features"]["annotation.human.validity"] = json!({"dtype": "int64", "shape": [1], "names": null});
    std::fs::write(&p, serde_json::to_vec(&info).unwrap()).unwrap();
    add_column(&odd, "annotation.human.validity", |_, _| 0);
    let c = Target::sqlite(&dir.path().join("c"));
    c.json(&["ingest", odd.to_str().unwrap(), "--policy", "g", "--checkpoint", "c", "--json"]);
    let eps = c.json(&["episodes", "--json"]);
    let why = eps[0]["metadata"]["validity_not_kept"].as_str().unwrap_or_default().to_string();
    assert!(why.contains("names the task \"put the cube in the bowl\""), "{eps}");
}

/// Adds an int64 column `name` (value of episode e, step t) to the dataset's data file.
fn add_column(root: &Path, name: &str, value: impl Fn(usize, usize) -> i64) {
    let data = root.join("data/chunk-000/file-000.parquet");
    let r = parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder::try_new(
        std::fs::File::open(&data).unwrap(),
    )
    .unwrap()
    .build()
    .unwrap();
    let batches: Vec<RecordBatch> = r.map(|b| b.unwrap()).collect();
    let b = arrow::compute::concat_batches(&batches[0].schema(), &batches).unwrap();
    let mut cols: Vec<(String, ArrayRef)> =
        b.schema().fields().iter().zip(b.columns()).map(|(f, c)| (f.name().clone(), c.clone())).collect();
    let n = b.num_rows();
    cols.push((
        name.to_string(),
        Arc::new(Int64Array::from_iter_values((0..n).map(|r| value(r / STEPS, r % STEPS)))),
    ));
    parquet(&data, RecordBatch::try_from_iter(cols).unwrap());
}

/// `task_index` → task of a LeRobot v3.0 dataset.
fn task_names(root: &Path) -> BTreeMap<i64, String> {
    let r = parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder::try_new(
        std::fs::File::open(root.join("meta/tasks.parquet")).unwrap(),
    )
    .unwrap()
    .build()
    .unwrap();
    let mut out = BTreeMap::new();
    for b in r {
        let b = b.unwrap();
        let i = b.column_by_name("task_index").unwrap().as_primitive::<arrow::datatypes::Int64Type>().clone();
        let t = b.column_by_name("task").unwrap().as_string::<i32>().clone();
        for r in 0..b.num_rows() {
            out.insert(i.value(r), t.value(r).to_string());
        }
    }
    out
}

/// `episode_index` → the int64 column `name` of a LeRobot v3.0 dataset's data files.
fn column_by_episode(root: &Path, name: &str) -> BTreeMap<i64, Vec<i64>> {
    let mut out: BTreeMap<i64, Vec<i64>> = BTreeMap::new();
    for f in walk(&root.join("data")) {
        let r = parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder::try_new(
            std::fs::File::open(&f).unwrap(),
        )
        .unwrap()
        .build()
        .unwrap();
        for b in r {
            let b = b.unwrap();
            let ep = b
                .column_by_name("episode_index")
                .unwrap()
                .as_primitive::<arrow::datatypes::Int64Type>()
                .clone();
            let v = b
                .column_by_name(name)
                .expect("the column")
                .as_primitive::<arrow::datatypes::Int64Type>()
                .clone();
            for r in 0..b.num_rows() {
                out.entry(ep.value(r)).or_default().push(v.value(r));
            }
        }
    }
    out
}
