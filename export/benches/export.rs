//! Export of 5,000 rollouts: `export::lerobot::export` and
//! `export::robomimic::export` against the Python path a user would write with pyarrow / h5py
//! (`bench/reference/py_export_store.py`), in the same run, each in its own process (wall time
//! and peak RSS), medians of `EXPORT_BENCH_RUNS` (default 3). The ufops child runs with the
//! allocator settings the `ufops` binary sets for itself.
//!
//! The store: 5,000 generated Square-like rollouts (obs 23 floats in 4 keys, action 7, 150-400
//! steps, 1.38 M steps), made once under the target dir and reused.
//! `cargo bench -p export --bench export` (`EXPORT_BENCH_N` for another count).
#![allow(
    clippy::unwrap_used,
    clippy::too_many_lines,
    reason = "benchmarks: a failed unwrap is a failed run, and a measurement reads top to bottom"
)]

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use store::*;

use store::test_support::square_rollout as rollout;

async fn make_store(dir: &Path, n: u32) -> Store {
    let store = Store::open(&StoreConfig::local(dir)).await.unwrap();
    if store.head_version().await.unwrap() == 0 {
        let t0 = Instant::now();
        let src = SourceInput {
            path: "bench".into(),
            sha256: sha256_hex(format!("export bench {n}").as_bytes()),
            format: "bench".into(),
            size_bytes: 1,
            metadata: serde_json::json!({"fps": 20}),
        };
        let mut w = store.begin_ingest(src, "square", "bench").await.unwrap();
        for i in 0..n {
            w.add_episode(rollout(i)).await.unwrap();
        }
        w.commit("bench").await.unwrap();
        eprintln!("made a store of {n} rollouts in {:.1} s", t0.elapsed().as_secs_f64());
    }
    store
}

fn peak_rss_mb() -> f64 {
    let s = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    s.lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        .map_or(f64::NAN, |kb| kb / 1024.0)
}

/// The child process: one export, then `{"rows", "seconds", "peak_rss_mb"}` on stdout.
async fn child(format: &str, store_dir: &Path, out: &Path) {
    let t0 = Instant::now();
    let store = Store::open(&StoreConfig::local(store_dir)).await.unwrap();
    let sel = store::select(&store, &store::Selection::default()).await.unwrap();
    let rep = match format {
        "lerobot" => export::lerobot::export(&store, &sel, out, None).await.unwrap(),
        _ => export::robomimic::export(&store, &sel, out, None).await.unwrap(),
    };
    let secs = t0.elapsed().as_secs_f64();
    println!("{}", serde_json::json!({"rows": rep.frames, "seconds": secs, "peak_rss_mb": peak_rss_mb()}));
}

fn run(cmd: &mut Command) -> serde_json::Value {
    let out = cmd.output().expect("runs");
    assert!(out.status.success(), "{:?} failed:\n{}", cmd, String::from_utf8_lossy(&out.stderr));
    let stdout = String::from_utf8_lossy(&out.stdout);
    serde_json::from_str(stdout.lines().last().expect("a result line")).expect("JSON result")
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

#[tokio::main]
async fn main() {
    let base = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("export_bench");
    let n: u32 = std::env::var("EXPORT_BENCH_N").ok().and_then(|v| v.parse().ok()).unwrap_or(5000);
    let store_dir = base.join(format!("store-{n}"));
    if let Ok(format) = std::env::var("EXPORT_BENCH_CHILD") {
        let out = PathBuf::from(std::env::var("EXPORT_BENCH_OUT").expect("EXPORT_BENCH_OUT"));
        child(&format, &store_dir, &out).await;
        return;
    }
    let store = make_store(&store_dir, n).await;
    let head = store.head_version().await.unwrap();
    let labels = store.full_labels_file(head).await.unwrap();
    let runs: usize = std::env::var("EXPORT_BENCH_RUNS").ok().and_then(|v| v.parse().ok()).unwrap_or(3);
    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../bench/reference/py_export_store.py");
    let exe = std::env::current_exe().unwrap();
    println!("export of {n} rollouts, medians of {runs} (each in its own process; same run):");
    println!("| format | ufops s | python s | python / ufops | ufops peak RSS MB | python peak RSS MB |");
    println!("|---|---|---|---|---|---|");
    for format in ["lerobot", "robomimic"] {
        let (mut us, mut py) = (Vec::new(), Vec::new());
        for r in 0..runs {
            let ext = if format == "lerobot" { "" } else { ".hdf5" };
            let a = base.join(format!("out-ufops-{format}-{r}{ext}"));
            let b = base.join(format!("out-py-{format}-{r}{ext}"));
            for p in [&a, &b] {
                let _ = std::fs::remove_dir_all(p);
                let _ = std::fs::remove_file(p);
            }
            // The allocator settings the `ufops` binary gives itself (src/main.rs,
            // `keep_freed_memory_from_piling_up`), so the peak is the one users see.
            let cores = std::thread::available_parallelism().map_or(2, |n| n.get()).max(2);
            let u = run(Command::new(&exe)
                .env("MALLOC_ARENA_MAX", cores.to_string())
                .env("MALLOC_MMAP_THRESHOLD_", (1 << 20).to_string())
                .env("EXPORT_BENCH_CHILD", format)
                .env("EXPORT_BENCH_OUT", &a)
                .env("EXPORT_BENCH_N", n.to_string()));
            let p = run(Command::new("python3")
                .arg(&script)
                .arg(store_dir.join("objects"))
                .arg(&labels)
                .arg(format)
                .arg(&b));
            assert_eq!(u["rows"], p["rows"], "both export every step");
            us.push(u);
            py.push(p);
            for p in [&a, &b] {
                let _ = std::fs::remove_dir_all(p);
                let _ = std::fs::remove_file(p);
            }
        }
        let m = |v: &[serde_json::Value], k: &str| median(v.iter().map(|x| x[k].as_f64().unwrap()).collect());
        let (ut, pt) = (m(&us, "seconds"), m(&py, "seconds"));
        println!(
            "| {format} | {ut:.2} | {pt:.2} | {:.2}x | {:.0} | {:.0} |",
            pt / ut,
            m(&us, "peak_rss_mb"),
            m(&py, "peak_rss_mb")
        );
    }
}
