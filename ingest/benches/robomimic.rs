//! `cargo bench -p ingest`: the whole ingest of a 200+ MB robomimic-layout file (hashing,
//! decoding, Parquet encoding and the store commit included) into a fresh temporary store, side by
//! side with the Python reference (h5py + pyarrow, zstd) run in the same process tree, plus the
//! machine's limit (reading the file + zstd-compressing the output columns, nothing else).
//!
//! The input is generated once with `bench/reference/gen_robomimic.py OUT --demos 1000` into the
//! target directory (never into git). Env: `UFOPS_BENCH_RUNS` (default 3), `UFOPS_BENCH_FILE`,
//! `UFOPS_BENCH_INGEST_ONLY` (time the whole ingest only, e.g. under `perf record`).
#![allow(
    clippy::unwrap_used,
    clippy::too_many_lines,
    reason = "benchmarks: a failed unwrap is a failed run, and a measurement reads top to bottom"
)]

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use ingest::sink::{CollectSink, CountSink};
use ingest::{Format, IngestOptions, ReadOptions};

/// The Python reference scripts (bench/reference/README.md).
fn reference_script(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../bench/reference").join(name)
}

fn target_dir() -> PathBuf {
    std::env::var_os("CARGO_TARGET_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../target"))
}

fn median(mut v: Vec<Duration>) -> Duration {
    v.sort();
    v[v.len() / 2]
}

fn input() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("UFOPS_BENCH_FILE") {
        return Some(PathBuf::from(p));
    }
    let dir = target_dir().join("bench");
    let p = dir.join("robomimic_1000.hdf5");
    if p.exists() {
        return Some(p);
    }
    std::fs::create_dir_all(&dir).ok()?;
    eprintln!("generating {} (python3 gen_robomimic.py --demos 1000) ...", p.display());
    let st = Command::new("python3")
        .arg(reference_script("gen_robomimic.py"))
        .arg(&p)
        .args(["--demos", "1000"])
        .status()
        .ok()?;
    if !st.success() {
        let _ = std::fs::remove_file(&p);
        return None;
    }
    Some(p)
}

fn python_reference(inp: &Path, out: &Path) -> Option<Duration> {
    let t = Instant::now();
    let st = Command::new("python3")
        .arg(reference_script("py_convert_robomimic.py"))
        .arg(inp)
        .arg(out)
        .stdout(std::process::Stdio::null())
        .status()
        .ok()?;
    st.success().then(|| t.elapsed())
}

/// This process's user and system (kernel) CPU seconds so far, all threads (`/proc/self/stat`,
/// in clock ticks of 10 ms); zeros where that file is missing.
fn cpu_times() -> (f64, f64) {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    // fields after the command name (which may hold spaces): state is field 3, utime 14, stime 15
    let rest = stat.rsplit_once(')').map_or("", |(_, r)| r);
    let f: Vec<f64> = rest.split_whitespace().map(|x| x.parse().unwrap_or(0.0)).collect();
    let tick = |i: usize| f.get(i).copied().unwrap_or(0.0) / 100.0;
    (tick(11), tick(12))
}

/// `/proc/loadavg`'s 1, 5 and 15 minute figures (figures are noisy on a shared machine).
fn loadavg() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_else(|_| "unknown".into())
}

// One function past 100 lines: the benchmark's measurements in the order the report prints them.
fn main() {
    // `cargo bench` passes --bench; `cargo test --benches` passes nothing useful: run only on bench
    if std::env::args().any(|a| a == "--list") {
        return;
    }
    let Some(inp) = input() else {
        eprintln!("skipping: cannot generate the input (needs python3 with h5py and numpy)");
        return;
    };
    let runs: usize = std::env::var("UFOPS_BENCH_RUNS").ok().and_then(|s| s.parse().ok()).unwrap_or(3).max(1);
    let size = std::fs::metadata(&inp).unwrap().len();
    let mb = size as f64 / 1e6;
    println!("input: {} ({mb:.1} MB), {runs} runs each, medians", inp.display());
    println!("load average at start: {}", loadavg());

    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    let tmp = tempfile::tempdir().unwrap();

    // warm the page cache
    let _ = std::fs::read(&inp).unwrap();

    // 1. the whole ingest into a fresh store each time
    let mut t_ingest = Vec::new();
    let mut cpu_ingest = Vec::new();
    let mut episodes = 0;
    let mut steps = 0;
    for i in 0..runs {
        let dir = tmp.path().join(format!("store{i}"));
        let opts = IngestOptions {
            policy: "bench".into(),
            checkpoint: "c1".into(),
            format: Format::Robomimic,
            success_from_rewards: Some(1.0),
            ..Default::default()
        };
        let (d, rep) = rt.block_on(async {
            let store = store::Store::open(&store::StoreConfig::local(&dir)).await.unwrap();
            let (u0, s0) = cpu_times();
            let t = Instant::now();
            let rep = ingest::ingest(&store, &inp, &opts).await.unwrap();
            let d = t.elapsed();
            let (u1, s1) = cpu_times();
            cpu_ingest.push((d, u1 - u0, s1 - s0));
            (d, rep)
        });
        episodes = rep.episodes;
        steps = rep.steps;
        t_ingest.push(d);
        let _ = std::fs::remove_dir_all(&dir);
    }

    if std::env::var_os("UFOPS_BENCH_INGEST_ONLY").is_some() {
        // for profiling (perf record ...): the whole ingest only
        for (d, u, s) in &cpu_ingest {
            println!("ufops ingest run: wall {:.3} s, user {u:.2} s, sys {s:.2} s", d.as_secs_f64());
        }
        println!("ufops ingest: {:.3} s median of {runs}", median(t_ingest).as_secs_f64());
        return;
    }

    // 2. the Python reference
    let ref_out = tmp.path().join("ref.parquet");
    let mut t_py = Vec::new();
    for _ in 0..runs {
        match python_reference(&inp, &ref_out) {
            Some(d) => t_py.push(d),
            None => break,
        }
    }

    // 3. parts: reader alone, hashing alone
    let mut t_read = Vec::new();
    for _ in 0..runs {
        let t = Instant::now();
        let mut s = CountSink::default();
        ingest::read_path(&inp, Format::Robomimic, &ReadOptions::default(), &mut s).unwrap();
        t_read.push(t.elapsed());
    }
    let mut t_hash = Vec::new();
    for _ in 0..runs {
        let t = Instant::now();
        ingest::hashing::hash_file(&inp).unwrap();
        t_hash.push(t.elapsed());
    }

    // 4. the machine's limit: read the file + zstd(1)-compress the output columns
    let mut t_fs = Vec::new();
    for _ in 0..runs {
        let t = Instant::now();
        let b = std::fs::read(&inp).unwrap();
        std::hint::black_box(&b);
        t_fs.push(t.elapsed());
    }
    let mut collected = CollectSink::default();
    ingest::read_path(&inp, Format::Robomimic, &ReadOptions::default(), &mut collected).unwrap();
    // the store's part alone: add_episode (Arrow + Parquet encoding) and commit (catalog)
    let (t_add, t_commit) = rt.block_on(async {
        let dir = tmp.path().join("store_only");
        let store = store::Store::open(&store::StoreConfig::local(&dir)).await.unwrap();
        let src = store::SourceInput {
            path: "bench".into(),
            sha256: "0".repeat(64),
            format: "robomimic".into(),
            size_bytes: size,
            metadata: collected.source.clone().map(|s| s.metadata).unwrap_or_default(),
        };
        let mut w = store.begin_ingest(src, "bench", "c1").await.unwrap();
        let t = Instant::now();
        // A second read: episodes are not Clone (their cameras may stream).
        let mut again = CollectSink::default();
        ingest::read_path(&inp, Format::Robomimic, &ReadOptions::default(), &mut again).unwrap();
        for e in again.episodes {
            w.add_episode(e).await.unwrap();
        }
        let t_add = t.elapsed();
        let t = Instant::now();
        w.commit("bench").await.unwrap();
        (t_add, t.elapsed())
    });
    let mut cols: Vec<Vec<u8>> = Vec::new();
    for e in &collected.episodes {
        let mut v: Vec<u8> = Vec::new();
        for o in &e.observations {
            v.extend(o.values.iter().flat_map(|x| x.to_le_bytes()));
        }
        v.extend(e.action.values.iter().flat_map(|x| x.to_le_bytes()));
        v.extend(e.reward.iter().flat_map(|x| x.to_le_bytes()));
        v.extend(e.timestamps.iter().flat_map(|x| x.to_le_bytes()));
        cols.push(v);
    }
    drop(collected);
    let raw_out: usize = cols.iter().map(|c| c.len()).sum();
    let mut t_z = Vec::new();
    let mut z_out = 0;
    for _ in 0..runs {
        let t = Instant::now();
        z_out = cols.iter().map(|c| zstd::bulk::compress(c, 1).unwrap().len()).sum::<usize>();
        t_z.push(t.elapsed());
    }

    let s = |d: Duration| d.as_secs_f64();
    let ing = s(median(t_ingest));
    println!();
    println!("{:<46} {:>8} {:>10} {:>12}", "", "seconds", "MB/s", "episodes/s");
    let row =
        |name: &str, t: f64| println!("{name:<46} {t:>8.3} {:>10.1} {:>12.0}", mb / t, episodes as f64 / t);
    row("ufops ingest (hash+decode+parquet+commit)", ing);
    let py = if t_py.is_empty() {
        println!("python reference: unavailable (needs python3 with h5py, pyarrow)");
        None
    } else {
        let p = s(median(t_py));
        row("python reference (h5py+pyarrow, zstd)", p);
        Some(p)
    };
    row("  part: reader alone (decode, no store)", s(median(t_read)));
    row("  part: sha256 of the file alone", s(median(t_hash)));
    row("  part: store add_episode x N alone", s(t_add));
    row("  part: store commit alone", s(t_commit));
    let fs = s(median(t_fs));
    let z = s(median(t_z));
    row("limit: read file + zstd(1) output, 1 core", fs + z);
    row("limit: read file + zstd(1) output, 2 cores", fs + z / 2.0);
    println!();
    println!(
        "{episodes} episodes, {steps} steps; output columns {:.1} MB raw -> {:.1} MB zstd(1)",
        raw_out as f64 / 1e6,
        z_out as f64 / 1e6
    );
    println!("  read file alone {fs:.3} s, zstd(1) alone {z:.3} s (1 core)");
    if let Some(p) = py {
        println!("ratio: ufops ingest is {:.2}x the Python reference's throughput (goal >= 3x)", p / ing);
    }
    println!("load average at end: {}", loadavg());
    println!(
        "distance to the machine's limit: {:.2}x slower than read+zstd on 1 core, {:.2}x on 2 cores",
        ing / (fs + z),
        ing / (fs + z / 2.0)
    );
}
