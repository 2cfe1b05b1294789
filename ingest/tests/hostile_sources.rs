//! The readers refuse every source of the hostile corpus (`hostile-corpus`) with the
//! expected error, and no single allocation comes near what the sources declare (a counting global
//! allocator records the largest request). The same corpus through the `ufops` binary, with the
//! child's peak RSS and the store checked, is `tests/hostile_corpus.rs` at the workspace root.
#![allow(
    clippy::unwrap_used,
    clippy::too_many_lines,
    reason = "tests: a failed unwrap is a failed test, and a scenario reads top to bottom"
)]

mod largest_alloc;
use largest_alloc::LARGEST;
use std::sync::atomic::Ordering;

use ingest::sink::CountSink;
use ingest::{Format, ReadOptions};

/// Largest single allocation allowed while a hostile source is read (the 24 MB JSON event is
/// decompressed before its size is refused; everything else is refused before any big buffer).
const MAX_ALLOCATION: usize = 64 << 20;

#[test]
fn readers_refuse_every_hostile_source_without_a_huge_allocation() {
    let dir = tempfile::tempdir().unwrap();
    let cases = hostile_corpus::write_corpus(dir.path()).unwrap();
    assert!(cases.len() >= 12, "{} cases", cases.len());
    let mut failures = Vec::new();
    for c in &cases {
        LARGEST.store(0, Ordering::Relaxed);
        let mut sink = CountSink::default();
        let r = ingest::read_path(&c.path, Format::Auto, &ReadOptions::default(), &mut sink);
        let largest = LARGEST.load(Ordering::Relaxed);
        let msg = match &r {
            Ok(_) => "accepted".to_string(),
            Err(e) => e.to_string(),
        };
        eprintln!("{:<32} largest allocation {:>8.1} MB  {msg}", c.name, largest as f64 / 1e6);
        if r.is_ok() || !msg.contains(c.expect) || msg.contains("decoder failed") {
            failures.push(format!("{}: expected an error saying {:?}, got: {msg}", c.name, c.expect));
        }
        if largest > MAX_ALLOCATION {
            failures.push(format!("{}: an allocation of {largest} bytes", c.name));
        }
        if sink.media > 0 {
            failures.push(format!("{}: {} media files were passed on", c.name, sink.media));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// A Parquet page whose header declares 2 GB for 64 bytes: refused before the decompression
/// buffer is sized (snappy zero-fills it), in the fuzz body as in a dataset.
#[test]
fn a_page_declaring_gigabytes_is_refused() {
    let data = hostile_corpus::parquet_page_bomb(i32::MAX);
    let err = ingest::lerobot::fuzz_entry(b"", &data).unwrap_err().to_string();
    assert!(err.contains("declares 2147483647 uncompressed bytes from 64 compressed bytes"), "{err}");
    assert!(err.contains("column episode_index"), "{err}");
}
