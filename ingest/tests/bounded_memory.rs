//! Ingest memory is bounded by the work, not by the source: a source twice as large must not
//! need more memory. A counting global allocator records the heap's high-water mark (every
//! thread's: reader, hashing, writer) while each source is ingested into a fresh store with small
//! buffer budgets, so the plateau is reached within a few MB of output.
//!
//! A reader that loads the source whole (robomimic did, up to 2 GiB files), a writer that keeps
//! encoded row groups until the end, or a channel without a byte bound all make the larger
//! source's peak grow with it, and fail here.
#![allow(
    clippy::unwrap_used,
    clippy::too_many_lines,
    reason = "tests: a failed unwrap is a failed test, and a scenario reads top to bottom"
)]

mod common;

use std::path::Path;
use std::sync::Arc;

use arrow::array::{
    ArrayRef, BinaryArray, FixedSizeListArray, Float32Array, Int64Array, RecordBatch, StringArray,
    StructArray,
};
use arrow::datatypes::{DataType, Field};
use hdf5_pure::{AttrValue, FileBuilder};
use ingest::{Format, IngestOptions, MemoryBudget};

#[global_allocator]
static ALLOC: store::test_support::CountingAlloc = store::test_support::CountingAlloc;

/// The counters see every thread: tests of this binary run one at a time.
static SERIAL: std::sync::Mutex<()> = std::sync::Mutex::new(());

const STEPS: usize = 120;
const IMG: usize = 24; // 24 x 24 x 3 camera frames

/// Bytes that look like camera frames to no compressor (an LCG), so file and output sizes
/// follow the number of demos.
fn noise(seed: u64, n: usize) -> Vec<u8> {
    let mut s = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
    (0..n)
        .map(|_| {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (s >> 56) as u8
        })
        .collect()
}

/// A robomimic-layout file: `data/demo_i/{obs/{pos, agentview_image}, actions, rewards, dones}`,
/// the image gzip-compressed in chunks (as robomimic's `--compress` writes it), the rest
/// contiguous.
fn write_robomimic(path: &Path, demos: usize) {
    let mut b = FileBuilder::new();
    let mut data = b.create_group("data");
    for i in 0..demos {
        let mut g = data.create_group(&format!("demo_{i}"));
        let mut obs = g.create_group("obs");
        let pos: Vec<f64> = (0..STEPS * 3).map(|k| (k + i) as f64 * 0.01).collect();
        obs.create_dataset("pos").with_f64_data(&pos).with_shape(&[STEPS as u64, 3]);
        obs.create_dataset("agentview_image")
            .with_u8_data(&noise(i as u64, STEPS * IMG * IMG * 3))
            .with_shape(&[STEPS as u64, IMG as u64, IMG as u64, 3])
            .with_chunks(&[16, IMG as u64, IMG as u64, 3])
            .with_deflate(1);
        g.add_group(obs.finish());
        let act: Vec<f64> = (0..STEPS * 7).map(|k| ((k * 7 + i) % 13) as f64 / 13.0).collect();
        g.create_dataset("actions").with_f64_data(&act).with_shape(&[STEPS as u64, 7]);
        let mut rewards = vec![0.0; STEPS];
        rewards[STEPS - 1] = (i % 2) as f64;
        g.create_dataset("rewards").with_f64_data(&rewards);
        let dones: Vec<i64> = (0..STEPS).map(|t| (t + 1 == STEPS) as i64).collect();
        g.create_dataset("dones").with_i64_data(&dones);
        g.set_attr("num_samples", AttrValue::I64(STEPS as i64));
        data.add_group(g.finish());
    }
    data.set_attr("total", AttrValue::I64((demos * STEPS) as i64));
    data.set_attr(
        "env_args",
        AttrValue::String(r#"{"env_name": "Lift", "env_kwargs": {"control_freq": 20}}"#.into()),
    );
    b.add_group(data.finish());
    b.write(path).unwrap();
}

fn parquet(path: &Path, batch: RecordBatch) {
    parquet_with(path, batch, None)
}

fn parquet_with(path: &Path, batch: RecordBatch, props: Option<parquet::file::properties::WriterProperties>) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    let f = std::fs::File::create(path).unwrap();
    let mut w = parquet::arrow::ArrowWriter::try_new(f, batch.schema(), props).unwrap();
    w.write(&batch).unwrap();
    w.close().unwrap();
}

fn f32_list(values: Vec<f32>, dim: i32) -> ArrayRef {
    let item = Arc::new(Field::new("item", DataType::Float32, true));
    Arc::new(FixedSizeListArray::try_new(item, dim, Arc::new(Float32Array::from(values)), None).unwrap())
}

/// A LeRobot v3.0 dataset: every episode in one data file (`data/chunk-000/file-000.parquet`),
/// with a 6-D state, a 6-D action and a PNG `image` feature stored in the Parquet.
/// A LeRobot `info.json`'s features: a 6-D state and action, the bookkeeping columns, and
/// image features `cameras` of `shape`.
fn features(cameras: &[&str], shape: [usize; 3]) -> serde_json::Value {
    let mut f = serde_json::json!({
        "observation.state": {"dtype": "float32", "shape": [6]},
        "action": {"dtype": "float32", "shape": [6]},
        "timestamp": {"dtype": "float32", "shape": [1]},
        "frame_index": {"dtype": "int64", "shape": [1]},
        "episode_index": {"dtype": "int64", "shape": [1]},
        "index": {"dtype": "int64", "shape": [1]},
        "task_index": {"dtype": "int64", "shape": [1]}
    });
    for camera in cameras {
        f[*camera] = serde_json::json!({"dtype": "image", "shape": shape});
    }
    f
}

fn write_lerobot_v3(root: &Path, episodes: usize) {
    let info = serde_json::json!({
        "codebase_version": "v3.0", "fps": 10, "robot_type": "toy", "total_episodes": episodes,
        "features": features(&["observation.images.front"], [IMG, IMG, 3]),
    });
    std::fs::create_dir_all(root.join("meta")).unwrap();
    std::fs::write(root.join("meta/info.json"), info.to_string()).unwrap();
    let n = episodes * STEPS;
    let ep: Vec<i64> = (0..episodes as i64).collect();
    let cols: Vec<(&str, ArrayRef)> = vec![
        ("episode_index", Arc::new(Int64Array::from(ep.clone()))),
        ("length", Arc::new(Int64Array::from(vec![STEPS as i64; episodes]))),
        ("dataset_from_index", Arc::new(Int64Array::from_iter_values(ep.iter().map(|e| e * STEPS as i64)))),
        (
            "dataset_to_index",
            Arc::new(Int64Array::from_iter_values(ep.iter().map(|e| (e + 1) * STEPS as i64))),
        ),
    ];
    parquet(
        &root.join("meta/episodes/chunk-000/file-000.parquet"),
        RecordBatch::try_from_iter(cols).unwrap(),
    );
    let image = png_column(&(0..n).map(|r| noise(r as u64, IMG * IMG * 3)).collect::<Vec<_>>(), IMG, IMG);
    let cols: Vec<(&str, ArrayRef)> = vec![
        ("observation.state", f32_list((0..n * 6).map(|k| k as f32 * 1e-3).collect(), 6)),
        ("observation.images.front", image),
        ("action", f32_list((0..n * 6).map(|k| (k % 11) as f32).collect(), 6)),
        ("timestamp", Arc::new(Float32Array::from_iter_values((0..n).map(|r| (r % STEPS) as f32 / 10.0)))),
        ("frame_index", Arc::new(Int64Array::from_iter_values((0..n).map(|r| (r % STEPS) as i64)))),
        ("episode_index", Arc::new(Int64Array::from_iter_values((0..n).map(|r| (r / STEPS) as i64)))),
        ("index", Arc::new(Int64Array::from_iter_values(0..n as i64))),
        ("task_index", Arc::new(Int64Array::from(vec![0i64; n]))),
    ];
    parquet(&root.join("data/chunk-000/file-000.parquet"), RecordBatch::try_from_iter(cols).unwrap());
}

/// A LeRobot `image` column (`struct<bytes, path>`) of `frames` (`h x w x 3` each) as PNGs.
fn png_column(frames: &[Vec<u8>], h: usize, w: usize) -> ArrayRef {
    let pngs: Vec<Vec<u8>> = frames.iter().map(|f| ingest::png::encode_png(f, h, w, 3).unwrap()).collect();
    Arc::new(StructArray::from(vec![
        (
            Arc::new(Field::new("bytes", DataType::Binary, true)),
            Arc::new(BinaryArray::from_iter_values(pngs.iter())) as ArrayRef,
        ),
        (
            Arc::new(Field::new("path", DataType::Utf8, true)),
            Arc::new(StringArray::from(vec![Some(""); frames.len()])) as ArrayRef,
        ),
    ]))
}

/// Peak heap growth (bytes above what was live before) while `path` is ingested into a fresh
/// store, and the number of episodes ingested.
fn peak_while_ingesting(
    rt: &tokio::runtime::Runtime,
    path: &Path,
    format: Format,
    store_dir: &Path,
) -> (usize, usize) {
    let store = rt.block_on(store::Store::open(&store::StoreConfig::local(store_dir))).unwrap();
    let opts = IngestOptions {
        policy: "p".into(),
        checkpoint: "c".into(),
        format,
        // Small budgets so that a few MB of output reach the plateau (the defaults are 64-96 MB).
        memory: MemoryBudget {
            in_flight_bytes: 256 << 10,
            unhashed_bytes: 1 << 20,
            row_group_bytes: 256 << 10,
            file_bytes: 1 << 20,
        },
        ..Default::default()
    };
    let (peak, report) =
        store::test_support::peak_heap_while(|| rt.block_on(ingest::ingest(&store, path, &opts)).unwrap());
    assert!(!report.already_ingested);
    (peak, report.episodes)
}

fn source_bytes(path: &Path) -> u64 {
    ingest::hashing::hash_path(path).unwrap().1
}

/// Ingests a source of `n` and one of `2n` episodes (made by `write`) and checks that the larger
/// one's peak heap is no larger (within 25%) and far below its size.
fn check_bounded(what: &str, format: Format, n: usize, write: impl Fn(&Path, usize), file_name: &str) {
    let dir = tempfile::tempdir().unwrap();
    let small = dir.path().join(format!("small_{file_name}"));
    let large = dir.path().join(format!("large_{file_name}"));
    write(&small, n);
    write(&large, 2 * n);
    let (small_size, large_size) = (source_bytes(&small), source_bytes(&large));
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    let (peak_small, eps_small) = peak_while_ingesting(&rt, &small, format, &dir.path().join("store_small"));
    let (peak_large, eps_large) = peak_while_ingesting(&rt, &large, format, &dir.path().join("store_large"));
    assert_eq!((eps_small, eps_large), (n, 2 * n));
    let mb = |b: u64| b as f64 / 1e6;
    eprintln!(
        "{what}: {n} episodes ({:.1} MB) peak heap {:.1} MB; {} episodes ({:.1} MB) peak heap {:.1} MB",
        mb(small_size),
        mb(peak_small as u64),
        2 * n,
        mb(large_size),
        mb(peak_large as u64)
    );
    assert!(
        (peak_large as f64) < peak_small as f64 * 1.25,
        "{what}: peak heap grew with the source: {peak_small} bytes for {small_size}, {peak_large} for {large_size}"
    );
    assert!(
        (peak_large as u64) < large_size / 3,
        "{what}: peak heap {peak_large} bytes is not far below the source's {large_size} bytes"
    );
}

#[test]
fn peak_memory_does_not_grow_with_the_source() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    // robomimic: about 30 MB and 60 MB files (120 steps of a 24x24 camera and 10 low-dim values).
    check_bounded("robomimic", Format::Robomimic, 140, write_robomimic, "rollouts.hdf5");
    // LeRobot v3.0: one data file holding every episode, PNG frames inside the Parquet.
    check_bounded("lerobot v3.0", Format::Lerobot, 120, write_lerobot_v3, "dataset");
}

/// The smallest budgets change where row groups and files end, never what is stored: the reader
/// waits for the hash after every episode, every episode is its own row group and file, and each
/// one reads back exactly as with the default budgets (robomimic with images, LeRobot with videos).
#[test]
fn tiny_budgets_store_the_same_steps() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let f = common::fixtures();
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    for source in ["robomimic/lift_rollouts_image.hdf5", "lerobot/v30_eval_video"] {
        let dir = tempfile::tempdir().unwrap();
        let tiny = MemoryBudget { in_flight_bytes: 1, unhashed_bytes: 1, row_group_bytes: 1, file_bytes: 1 };
        let mut ids = Vec::new();
        let mut stores = Vec::new();
        for (name, memory) in [("default", MemoryBudget::default()), ("tiny", tiny)] {
            let store =
                rt.block_on(store::Store::open(&store::StoreConfig::local(dir.path().join(name)))).unwrap();
            let opts =
                IngestOptions { policy: "p".into(), checkpoint: "c".into(), memory, ..Default::default() };
            let report = rt.block_on(ingest::ingest(&store, &f.join(source), &opts)).unwrap();
            let eps = rt.block_on(store.episodes(&store::EpisodeFilter::default())).unwrap();
            assert_eq!(eps.len(), report.episodes, "{source}");
            let files: std::collections::HashSet<_> = eps.iter().map(|e| e.data_file.clone()).collect();
            if name == "tiny" {
                assert_eq!(
                    files.len(),
                    eps.len(),
                    "{source}: one steps file per episode with a 1-byte file budget"
                );
            }
            let mut e: Vec<String> = eps.into_iter().map(|e| e.id).collect();
            e.sort();
            ids.push(e);
            stores.push(store);
        }
        assert_eq!(ids[0], ids[1], "{source}");
        for id in &ids[0] {
            let a = rt.block_on(stores[0].read_steps(id, None)).unwrap();
            let b = rt.block_on(stores[1].read_steps(id, None)).unwrap();
            assert_eq!(a, b, "{source}: episode {id}");
        }
    }
}

/// An ALOHA episode file with raw cameras: `/observations/{qpos, qvel, images/cam_*}` and
/// `/action`, three `(steps, 96, 128, 3)` uint8 cameras chunked a frame per chunk (as ALOHA's
/// recorders write them), frames of noise so their PNGs are as large as the raw frames.
fn write_aloha_raw(path: &Path, steps: usize) {
    const H: usize = 96;
    const W: usize = 128;
    let t = steps as u64;
    let mut b = FileBuilder::new();
    let vec: Vec<f32> = (0..steps * 14).map(|k| k as f32 * 0.01).collect();
    let mut obs = b.create_group("observations");
    obs.create_dataset("qpos").with_f32_data(&vec).with_shape(&[t, 14]);
    obs.create_dataset("qvel").with_f32_data(&vec).with_shape(&[t, 14]);
    let mut images = obs.create_group("images");
    for (k, cam) in ["cam_high", "cam_left_wrist", "cam_right_wrist"].iter().enumerate() {
        images
            .create_dataset(cam)
            .with_u8_data(&noise(k as u64 * 1000 + steps as u64, steps * H * W * 3))
            .with_shape(&[t, H as u64, W as u64, 3])
            .with_chunks(&[1, H as u64, W as u64, 3]);
    }
    obs.add_group(images.finish());
    b.add_group(obs.finish());
    b.create_dataset("action").with_f32_data(&vec).with_shape(&[t, 14]);
    b.set_attr("sim", AttrValue::I8(0));
    b.write(path).unwrap();
}

/// Ingests one episode of 200 and one of [`LONG`] steps (written by `write`, `frame_bytes` of raw
/// frames a step), checks each with `check(steps batch, steps)`, and holds the longer episode's
/// peak heap to about the shorter one's (within 50%), not eight times it, and far below its
/// frames. A reader that collects an episode's frames, or a writer that keeps an episode's
/// encoded row group in memory, fails here.
/// The long episode's steps: 8× the short one's, so that a peak that does not depend on the length
/// sits far below a third of its frames (the peak moves by ~8 MB between runs of one source).
const LONG: usize = 1600;

fn check_episode_length_bounded(
    what: &str,
    format: Format,
    file_name: &str,
    frame_bytes: usize,
    write: impl Fn(&Path, usize),
    check: impl Fn(&arrow::array::RecordBatch, usize),
) {
    let dir = tempfile::tempdir().unwrap();
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    let mut peaks = Vec::new();
    for steps in [200, LONG] {
        let source = dir.path().join(format!("{steps}_{file_name}"));
        write(&source, steps);
        let store_dir = dir.path().join(format!("store_{steps}"));
        let (peak, episodes) = peak_while_ingesting(&rt, &source, format, &store_dir);
        assert_eq!(episodes, 1);
        let frames = steps * frame_bytes;
        eprintln!(
            "{what}: one episode of {steps} steps ({:.1} MB of frames) peak heap {:.1} MB",
            frames as f64 / 1e6,
            peak as f64 / 1e6
        );
        let store = rt.block_on(store::Store::open(&store::StoreConfig::local(&store_dir))).unwrap();
        let eps = rt.block_on(store.episodes(&store::EpisodeFilter::default())).unwrap();
        let steps_batch = rt.block_on(store.read_steps(&eps[0].id, None)).unwrap();
        assert_eq!(steps_batch.num_rows(), steps);
        check(&steps_batch, steps);
        peaks.push((peak, frames));
    }
    let ((short, _), (long, long_frames)) = (peaks[0], peaks[1]);
    assert!(
        (long as f64) < short as f64 * 1.5,
        "{what}: peak heap grew with the episode: {short} bytes for 200 steps, {long} for {LONG}"
    );
    assert!(
        long < long_frames / 3,
        "{what}: peak heap {long} bytes is not far below the episode's {long_frames} bytes of frames"
    );
}

/// The PNG of frame `t` of column `name` decodes to `expected`.
fn assert_png_frame(batch: &arrow::array::RecordBatch, name: &str, t: usize, expected: &[u8]) {
    let cam = batch.column_by_name(name).unwrap();
    let cam = cam.as_any().downcast_ref::<BinaryArray>().unwrap();
    let mut r = png::Decoder::new(std::io::Cursor::new(cam.value(t))).read_info().unwrap();
    let mut buf = vec![0; r.output_buffer_size().unwrap()];
    r.next_frame(&mut buf).unwrap();
    assert_eq!(buf, expected, "{name}: frame {t}");
}

/// One ALOHA episode of 200 and one of 1,600 steps (three raw cameras, 22 and 177 MB of frames):
/// the cameras stream to the store a page at a time.
#[test]
fn peak_memory_does_not_grow_with_an_episodes_length() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    const FRAME: usize = 96 * 128 * 3;
    let write = write_aloha_raw;
    check_episode_length_bounded(
        "aloha",
        Format::Aloha,
        "episode_0.hdf5",
        3 * FRAME,
        write,
        |batch, steps| {
            // Every frame is there, in order, as PNG.
            let raw = noise(1000 + steps as u64, steps * FRAME);
            for t in [0, steps / 2, steps - 1] {
                assert_png_frame(batch, "image.cam_left_wrist", t, &raw[t * FRAME..(t + 1) * FRAME]);
            }
        },
    );
}

/// A robomimic file of one image demo: `data/demo_0/{obs, next_obs}/{pos, agentview_image,
/// robot0_eye_in_hand_image}`, each camera `(steps, 96, 128, 3)` uint8 chunked 16 frames a
/// chunk, `next_obs` the next step's `obs` but for the last step (as robomimic writes it),
/// frames of noise (camera `k`'s from seed `2000 * (k + 1) + steps`, its last `next_obs` frame
/// from seed `3000 * (k + 1) + steps`).
fn write_robomimic_image_demo(path: &Path, steps: usize) {
    const SHAPE: [u64; 3] = [96, 128, 3];
    let frame = (SHAPE[0] * SHAPE[1] * SHAPE[2]) as usize;
    let t = steps as u64;
    let pos: Vec<f64> = (0..steps * 3).map(|k| k as f64 * 0.01).collect();
    let mut next_pos = pos[3..].to_vec();
    next_pos.extend([9.0, 9.0, 9.0]);
    let mut b = FileBuilder::new();
    let mut data = b.create_group("data");
    let mut g = data.create_group("demo_0");
    let (mut obs, mut next_obs) = (g.create_group("obs"), g.create_group("next_obs"));
    obs.create_dataset("pos").with_f64_data(&pos).with_shape(&[t, 3]);
    next_obs.create_dataset("pos").with_f64_data(&next_pos).with_shape(&[t, 3]);
    for (k, camera) in ["agentview_image", "robot0_eye_in_hand_image"].iter().enumerate() {
        let seed = (k as u64 + 1, steps as u64);
        let frames = noise(2000 * seed.0 + seed.1, steps * frame);
        let mut next = frames[frame..].to_vec();
        next.extend(noise(3000 * seed.0 + seed.1, frame));
        for (group, values) in [(&mut obs, &frames), (&mut next_obs, &next)] {
            group
                .create_dataset(camera)
                .with_u8_data(values)
                .with_shape(&[t, SHAPE[0], SHAPE[1], SHAPE[2]])
                .with_chunks(&[16, SHAPE[0], SHAPE[1], SHAPE[2]]);
        }
    }
    g.add_group(obs.finish());
    g.add_group(next_obs.finish());
    let act: Vec<f64> = (0..steps * 7).map(|k| (k % 13) as f64 / 13.0).collect();
    g.create_dataset("actions").with_f64_data(&act).with_shape(&[t, 7]);
    g.create_dataset("rewards").with_f64_data(&vec![0.0; steps]);
    g.set_attr("num_samples", AttrValue::I64(steps as i64));
    data.add_group(g.finish());
    data.set_attr("total", AttrValue::I64(steps as i64));
    data.set_attr("env_args", AttrValue::String(r#"{"env_name": "Lift"}"#.into()));
    b.add_group(data.finish());
    b.write(path).unwrap();
}

/// One robomimic image demo of 200 and one of 1,600 steps (two 96x128 cameras and their
/// `next_obs`, 29.5 and 236 MB of frames): the cameras stream to the store, `next_obs` is
/// compared with the shifted `obs` a window at a time and written a page at a time.
#[test]
fn robomimic_peak_memory_does_not_grow_with_a_demos_length() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    const FRAME: usize = 96 * 128 * 3;
    let write = write_robomimic_image_demo;
    let format = Format::Robomimic;
    check_episode_length_bounded("robomimic", format, "image.hdf5", 4 * FRAME, write, |batch, steps| {
        use arrow::array::{Array, AsArray};
        let raw = noise(2000 + steps as u64, steps * FRAME);
        for t in [0, steps / 2, steps - 1] {
            assert_png_frame(batch, "image.agentview_image", t, &raw[t * FRAME..(t + 1) * FRAME]);
        }
        // next_obs: null (the next step's obs) but for the last step, kept exactly.
        let next = batch.column_by_name("extra.next_obs/agentview_image").unwrap().as_fixed_size_list();
        assert_eq!(next.null_count(), steps - 1);
        let last = next.value(steps - 1);
        let last = last.as_primitive::<arrow::datatypes::UInt8Type>().values();
        assert_eq!(&last[..], &noise(3000 + steps as u64, FRAME)[..]);
    });
}

/// A LeRobot v2.1 dataset of one episode (`data/chunk-000/episode_000000.parquet`) with a 6-D
/// state and action and two PNG `image` features of 128x192 frames of noise (camera `k`'s frame
/// `t` from seed `4000 * (k + 1) + t`), pages of 16 rows.
fn write_lerobot_v21_images(root: &Path, steps: usize) {
    const CAMERAS: [&str; 2] = ["observation.images.front", "observation.images.wrist"];
    let info = serde_json::json!({
        "codebase_version": "v2.1", "fps": 10, "robot_type": "toy", "total_episodes": 1,
        "data_path": "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet",
        "features": features(&CAMERAS, [128, 192, 3]),
    });
    std::fs::create_dir_all(root.join("meta")).unwrap();
    std::fs::write(root.join("meta/info.json"), info.to_string()).unwrap();
    let episode = serde_json::json!({"episode_index": 0, "tasks": ["reach"], "length": steps});
    std::fs::write(root.join("meta/episodes.jsonl"), format!("{episode}\n")).unwrap();
    std::fs::write(root.join("meta/tasks.jsonl"), "{\"task_index\": 0, \"task\": \"reach\"}\n").unwrap();
    let mut cols: Vec<(&str, ArrayRef)> =
        vec![("observation.state", f32_list((0..steps * 6).map(|k| k as f32 * 1e-3).collect(), 6))];
    for (k, camera) in CAMERAS.iter().enumerate() {
        let frames: Vec<Vec<u8>> =
            (0..steps).map(|t| noise(4000 * (k as u64 + 1) + t as u64, 128 * 192 * 3)).collect();
        cols.push((camera, png_column(&frames, 128, 192)));
    }
    cols.extend([
        ("action", f32_list((0..steps * 6).map(|k| (k % 11) as f32).collect(), 6)),
        (
            "timestamp",
            Arc::new(Float32Array::from_iter_values((0..steps).map(|t| t as f32 / 10.0))) as ArrayRef,
        ),
        ("frame_index", Arc::new(Int64Array::from_iter_values(0..steps as i64))),
        ("episode_index", Arc::new(Int64Array::from(vec![0i64; steps]))),
        ("index", Arc::new(Int64Array::from_iter_values(0..steps as i64))),
        ("task_index", Arc::new(Int64Array::from(vec![0i64; steps]))),
    ]);
    // Pages of 16 rows (1.2 MB of PNGs): a reader holds a page at a time, not the column.
    let props = parquet::file::properties::WriterProperties::builder()
        .set_write_batch_size(16)
        .set_data_page_row_count_limit(16)
        .build();
    let batch = RecordBatch::try_from_iter(cols).unwrap();
    parquet_with(&root.join("data/chunk-000/episode_000000.parquet"), batch, Some(props));
}

/// One LeRobot v2.1 episode of 200 and one of 1,600 steps (two 128x192 PNG image columns, 29.5
/// and 236 MB of frames): the frames are read from the Parquet file a batch at a time as the
/// store's writer pulls them.
#[test]
fn lerobot_v21_peak_memory_does_not_grow_with_an_episodes_length() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    const FRAME: usize = 128 * 192 * 3;
    let write = write_lerobot_v21_images;
    check_episode_length_bounded(
        "lerobot v2.1",
        Format::Lerobot,
        "dataset",
        2 * FRAME,
        write,
        |batch, steps| {
            // Every frame is there, in order, the PNG as written.
            for t in [0, steps / 2, steps - 1] {
                assert_png_frame(batch, "image.images.wrist", t, &noise(8000 + t as u64, FRAME));
            }
        },
    );
}
