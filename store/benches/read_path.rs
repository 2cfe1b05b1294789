//! The store's read path at scale:
//!
//! * 5,000 and 20,000 generated Square-like rollouts (obs 23 floats in 4 keys, action 7, 150-400
//!   steps) written through the store's own writer into a local store under target/;
//! * time to load a training split (every episode, in split order, steps → per-episode float
//!   vectors as the trainer keeps them) with `Store::read_episodes`, next to the time of reading the
//!   store's steps files once sequentially (each file fetched whole and decoded, one after the
//!   other, single-threaded) and of fetching their bytes only, in the same run; medians of 3;
//! * one episode at a time (`read_steps`): bytes and requests per episode;
//! * the old path (`read_steps` per episode as it was: fetch the whole data file, decode the rows)
//!   on the 5,000 store, on a sample of episodes scaled to the split (`READ_PATH_OLD_FULL=1`: all);
//! * the same split loaded from S3 (SeaweedFS started as the tests start it; `READ_PATH_S3=0`
//!   skips): bytes and requests counted in the object-store client against the size of the steps
//!   files the split touches.
//!
//! `cargo bench -p store --bench read_path` (`READ_PATH_SIZES=5000` to run one size,
//! `READ_PATH_OLD=0` to skip the old path, `READ_PATH_DIR` for where the stores are made).
#![allow(
    clippy::unwrap_used,
    clippy::too_many_lines,
    reason = "benchmarks: a failed unwrap is a failed run, and a measurement reads top to bottom"
)]

#[path = "../../tests/common/seaweedfs.rs"]
#[allow(dead_code)]
mod seaweedfs;

use arrow::array::RecordBatch;
use std::time::Instant;
use store::*;

use store::test_support::{square_rollout as rollout, SQUARE_ACTION as ACTION, SQUARE_OBS as OBS};

/// A store of `n` rollouts and a split of all of them (made once, reused across runs).
async fn make_store(config: &StoreConfig, n: u32) -> (Store, SplitRecord) {
    let store = Store::open(config).await.unwrap();
    let ckpt = format!("n{n}");
    if store.checkpoints(Some("square")).await.unwrap().iter().all(|(_, c)| *c != ckpt) {
        let t0 = Instant::now();
        let src = SourceInput {
            path: format!("generated-{n}"),
            sha256: sha256_hex(format!("read_path bench {n}").as_bytes()),
            format: "bench".into(),
            size_bytes: 0,
            metadata: serde_json::json!({}),
        };
        let mut w = store.begin_ingest(src, "square", &ckpt).await.unwrap();
        for i in 0..n {
            w.add_episode(rollout(i)).await.unwrap();
        }
        w.commit("generated").await.unwrap();
        println!("  generated {n} rollouts in {:.1} s", t0.elapsed().as_secs_f64());
    }
    let split = store
        .create_split(&SplitRequest {
            policy: "square".into(),
            checkpoint: ckpt,
            version: None,
            off_policy_from: vec![],
            val_fraction: 0.2,
            seed: 0,
            actor: "bench".into(),
            max_episodes: None,
        })
        .await
        .unwrap();
    (store, split)
}

/// What a trainer keeps of an episode: its float columns.
fn keep(batch: &RecordBatch) -> Vec<Vec<f32>> {
    let mut out: Vec<Vec<f32>> =
        OBS.iter().map(|(k, _)| steps::vector_column(batch, &format!("obs.{k}")).unwrap().1).collect();
    out.push(steps::vector_column(batch, "action").unwrap().1);
    out
}

/// Loads the split as `trainer::load_split` does: locate, one streamed pass, back in split order.
async fn load_split(store: &Store, split: &SplitRecord) -> (usize, usize) {
    let members = store.split_episodes(&split.id).await.unwrap();
    let ids: Vec<String> = members.iter().map(|m| m.episode_id.clone()).collect();
    let locations = store.locate_episodes(&ids, Some(split.version)).await.unwrap();
    let mut kept: Vec<Option<Vec<Vec<f32>>>> = (0..ids.len()).map(|_| None).collect();
    let mut s = store.read_episodes(locations);
    while let Some(item) = s.next().await {
        let item = item.unwrap();
        kept[item.index] = Some(keep(&item.steps));
    }
    let steps: usize = kept.iter().map(|k| k.as_ref().unwrap()[4].len() / ACTION).sum();
    (kept.len(), steps)
}

/// The steps files the split touches, with their sizes.
async fn split_files(store: &Store, split: &SplitRecord) -> Vec<(String, u64)> {
    let members = store.split_episodes(&split.id).await.unwrap();
    let ids: Vec<String> = members.iter().map(|m| m.episode_id.clone()).collect();
    let mut files: Vec<String> = store
        .locate_episodes(&ids, Some(split.version))
        .await
        .unwrap()
        .into_iter()
        .map(|l| l.data_file)
        .collect();
    files.sort();
    files.dedup();
    let mut out = Vec::new();
    for f in files {
        let size = store.object_size(&f).await.unwrap();
        out.push((f, size));
    }
    out
}

/// The reference: each steps file fetched whole and decoded, one after the other.
async fn sequential_read(store: &Store, files: &[(String, u64)], decode: bool) -> usize {
    let mut rows = 0;
    for (f, _) in files {
        let data = store.get_object(f).await.unwrap();
        if decode {
            let reader = parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder::try_new(data)
                .unwrap()
                .with_batch_size(8192)
                .build()
                .unwrap();
            for b in reader {
                rows += b.unwrap().num_rows();
            }
        } else {
            rows += data.len();
        }
    }
    rows
}

/// The read path before range reads: every episode fetched its whole data file.
async fn old_read_steps(store: &Store, loc: &EpisodeLocation) -> RecordBatch {
    let data = store.get_object(&loc.data_file).await.unwrap();
    steps::read_rows(data, loc.row_group, Some((loc.row_offset, loc.row_count))).unwrap()
}

fn median(mut xs: Vec<f64>) -> f64 {
    xs.sort_by(|a, b| a.partial_cmp(b).unwrap());
    xs[xs.len() / 2]
}

async fn timed<F: std::future::Future>(f: F) -> (f64, F::Output) {
    let t0 = Instant::now();
    let out = f.await;
    (t0.elapsed().as_secs_f64(), out)
}

async fn local(n: u32, root: &std::path::Path) {
    println!("local store, {n} rollouts:");
    let (store, split) = make_store(&StoreConfig::local(root.join(format!("local-{n}"))), n).await;
    let files = split_files(&store, &split).await;
    let bytes: u64 = files.iter().map(|f| f.1).sum();
    println!("  {} steps files, {:.1} MB", files.len(), bytes as f64 / 1e6);
    // Warm the page cache for everyone alike.
    sequential_read(&store, &files, false).await;
    let (mut seq, mut raw, mut load) = (Vec::new(), Vec::new(), Vec::new());
    let mut shape = (0, 0);
    for _ in 0..3 {
        raw.push(timed(sequential_read(&store, &files, false)).await.0);
        seq.push(timed(sequential_read(&store, &files, true)).await.0);
        let (t, s) = timed(load_split(&store, &split)).await;
        load.push(t);
        shape = s;
    }
    let (seq, raw, load) = (median(seq), median(raw), median(load));
    println!("  split: {} episodes, {} steps", shape.0, shape.1);
    println!("  sequential read of the steps files (fetch + decode): {seq:.3} s  [fetch only: {raw:.3} s]");
    println!(
        "  load the split (read_episodes):                      {load:.3} s  = {:.2}x the sequential read (goal <= 2x) [{:.1}x fetch only]",
        load / seq,
        load / raw
    );
    // One episode at a time (the labeling page's steps): bytes fetched per episode, footers cached.
    let members = store.split_episodes(&split.id).await.unwrap();
    let sample: Vec<String> = members.iter().step_by(25).map(|m| m.episode_id.clone()).collect();
    for id in sample.iter().take(3) {
        store.read_steps(id, Some(split.version)).await.unwrap(); // footers into the cache
    }
    let before = store.fetch_counts();
    let (t, rows) = timed(async {
        let mut rows = 0;
        for id in &sample {
            rows += store.read_steps(id, Some(split.version)).await.unwrap().num_rows();
        }
        rows
    })
    .await;
    let got = store.fetch_counts().since(before);
    let share = bytes as f64 / shape.1 as f64 * rows as f64 / sample.len() as f64;
    println!(
        "  one episode (read_steps, {} episodes): {:.2} ms, {:.1} KB and {:.1} requests each; its share of the files {:.1} KB",
        sample.len(),
        t * 1e3 / sample.len() as f64,
        got.bytes_fetched as f64 / 1e3 / sample.len() as f64,
        got.get_requests as f64 / sample.len() as f64,
        share / 1e3
    );
    if n == 5000 && std::env::var("READ_PATH_OLD").map_or(true, |v| v != "0") {
        let members = store.split_episodes(&split.id).await.unwrap();
        let ids: Vec<String> = members.iter().map(|m| m.episode_id.clone()).collect();
        let locs = store.locate_episodes(&ids, Some(split.version)).await.unwrap();
        let full = std::env::var("READ_PATH_OLD_FULL").is_ok_and(|v| v == "1");
        let stride = if full { 1 } else { 25 };
        let sample: Vec<&EpisodeLocation> = locs.iter().step_by(stride).collect();
        let (t, _) = timed(async {
            for l in &sample {
                std::hint::black_box(keep(&old_read_steps(&store, l).await));
            }
        })
        .await;
        let old = t * locs.len() as f64 / sample.len() as f64;
        println!(
            "  old path (read_steps per episode, whole file each): {old:.1} s{} = {:.0}x the sequential read; new/old speed-up {:.0}x",
            if full { "".to_string() } else { format!(" (measured on {} episodes, scaled)", sample.len()) },
            old / seq,
            old / load
        );
    }
}

async fn s3(n: u32, root: &std::path::Path) {
    println!("S3 store (SeaweedFS), {n} rollouts:");
    let dir = root.join(format!("s3-{n}-{}", std::process::id()));
    let config = StoreConfig {
        data_dir: dir.clone(),
        database_url: None,
        object_store_url: Some(format!("s3://{}/bench{n}", seaweedfs::BUCKET)),
    };
    let (store, split) = make_store(&config, n).await;
    let files = split_files(&store, &split).await;
    let bytes: u64 = files.iter().map(|f| f.1).sum();
    // A fresh handle: nothing cached, counters at zero.
    let store = Store::open(&config).await.unwrap();
    let before = store.fetch_counts();
    let (t, shape) = timed(load_split(&store, &split)).await;
    let got = store.fetch_counts().since(before);
    println!(
        "  split: {} episodes, {} steps, {} steps files of {:.1} MB",
        shape.0,
        shape.1,
        files.len(),
        bytes as f64 / 1e6
    );
    println!(
        "  load from S3: {t:.2} s, {} GET + {} HEAD requests, {:.1} MB fetched = {:.3}x the steps files (goal <= 1.2x)",
        got.get_requests,
        got.head_requests,
        got.bytes_fetched as f64 / 1e6,
        got.bytes_fetched as f64 / bytes as f64
    );
    let _ = std::fs::remove_dir_all(dir);
}

fn main() {
    let sizes: Vec<u32> = std::env::var("READ_PATH_SIZES")
        .unwrap_or_else(|_| "5000,20000".into())
        .split(',')
        .map(|s| s.trim().parse().expect("READ_PATH_SIZES: numbers"))
        .collect();
    let root = std::env::var("READ_PATH_DIR")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|_| std::path::PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("read_path"));
    let with_s3 = std::env::var("READ_PATH_S3").map_or(true, |v| v != "0");
    // The S3 client is configured from the environment: set it before any other thread runs.
    let server = with_s3.then(seaweedfs::SeaweedFs::start);
    for (k, v) in server.as_ref().map(|s| s.env()).unwrap_or_default() {
        std::env::set_var(k, v);
    }
    let rt = tokio::runtime::Builder::new_multi_thread().enable_all().build().unwrap();
    if server.is_some() {
        rt.block_on(s3(sizes[0], &root));
    }
    drop(server);
    for n in sizes {
        rt.block_on(local(n, &root));
    }
}
