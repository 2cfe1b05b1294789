//! Regression test for the fuzz finding "a corrupt Parquet footer makes the parquet crate reserve
//! ~9 GB": `data/corrupt_footer_huge_list.parquet` (36 bytes) is a footer whose row-group list
//! claims 10^8 elements. The LeRobot reader must refuse it with an error, and no single allocation
//! may come anywhere near that size (a counting global allocator records the largest request).
#![allow(
    clippy::unwrap_used,
    clippy::too_many_lines,
    reason = "tests: a failed unwrap is a failed test, and a scenario reads top to bottom"
)]

mod largest_alloc;
use largest_alloc::LARGEST;
use std::sync::atomic::Ordering;

#[test]
fn corrupt_footer_list_count_is_refused_without_a_huge_allocation() {
    let data =
        std::fs::read(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/corrupt_footer_huge_list.parquet"))
            .unwrap();
    LARGEST.store(0, Ordering::Relaxed);
    let err = ingest::lerobot::fuzz_entry(b"", &data).unwrap_err().to_string();
    let largest = LARGEST.load(Ordering::Relaxed);
    assert!(largest < 64 << 20, "largest allocation while reading: {largest} bytes ({err})");
    assert!(err.contains("Parquet"), "{err}");
    assert!(err.contains("list of 100000000 elements"), "{err}");
    // The fuzz target body as a whole (info.json part empty, then the file) stays bounded too.
    ingest::fuzzing::lerobot_bytes(&[&b"{}\0"[..], &data].concat());
    let largest = LARGEST.load(Ordering::Relaxed);
    assert!(largest < 64 << 20, "largest allocation in the fuzz body: {largest} bytes");
}
