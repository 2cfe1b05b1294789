//! The robomimic export's memory is one demo, not the file: a store eight times larger must not
//! raise the export's peak heap (a counting global allocator, every thread's). Writing the file
//! with `hdf5-pure`'s `FileBuilder`, which holds the file until it writes it, failed here.
//!
//! Its own test binary: the allocator counts the whole process.
#![allow(
    clippy::unwrap_used,
    clippy::too_many_lines,
    reason = "tests: a failed unwrap is a failed test, and a scenario reads top to bottom"
)]

use std::path::Path;

use store::test_support::{peak_heap_while, square_rollout, CountingAlloc};
use store::*;

#[global_allocator]
static ALLOC: CountingAlloc = CountingAlloc;

/// A store of `n` Square-like rollouts (obs 23 floats, action 7, 150-400 steps).
async fn store_of(dir: &Path, n: u32) -> Store {
    let store = Store::open(&StoreConfig::local(dir)).await.unwrap();
    let src = SourceInput {
        path: "bounded".into(),
        sha256: sha256_hex(format!("bounded {n}").as_bytes()),
        format: "bench".into(),
        size_bytes: 1,
        metadata: serde_json::json!({}),
    };
    let mut w = store.begin_ingest(src, "square", "bench").await.unwrap();
    for i in 0..n {
        w.add_episode(square_rollout(i)).await.unwrap();
    }
    w.commit("test").await.unwrap();
    store
}

#[test]
fn robomimic_export_peak_does_not_grow_with_the_store() {
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let mut peaks = Vec::new();
    for n in [100u32, 800] {
        let store = rt.block_on(store_of(&tmp.path().join(format!("store-{n}")), n));
        let sel = rt.block_on(select(&store, &Selection::default())).unwrap();
        let out = tmp.path().join(format!("out-{n}.hdf5"));
        let (peak, report) =
            peak_heap_while(|| rt.block_on(export::robomimic::export(&store, &sel, &out, None)).unwrap());
        assert_eq!(report.episodes, n as usize);
        let size = std::fs::metadata(&out).unwrap().len() as usize;
        eprintln!(
            "{n} rollouts: file {:.1} MB, export peak heap {:.1} MB",
            size as f64 / 1e6,
            peak as f64 / 1e6
        );
        peaks.push((peak, size));
    }
    let ((small, small_size), (large, large_size)) = (peaks[0], peaks[1]);
    assert!(large_size > 6 * small_size, "the larger file is {large_size} bytes, the smaller {small_size}");
    // The demos' names and links grow with the store (tens of bytes each); the rest must not.
    assert!(
        large <= small + small / 2 + (4 << 20),
        "the export's peak heap grew with the store: {small} bytes for {small_size}-byte file, {large} for {large_size}"
    );
    assert!(large < large_size / 2, "peak heap {large} bytes is not far below the file's {large_size}");
}
