//! Training throughput on synthetic Square-sized data (302,400 samples, obs 46, action chunk 160,
//! the paper's low-dim contrastive classifier, batch 1024), and the PyTorch peer measured in the
//! same run (`bench/reference/torch_verifier_epoch.py`, or `UFOPS_TORCH_EPOCH_SCRIPT`; skipped
//! when torch is not importable). Run: `cargo bench -p trainer`.
//! Env: `UFOPS_BENCH_SAMPLES` (default 302400), `UFOPS_BENCH_EPOCHS` (default 2),
//! `UFOPS_BENCH_BACKENDS` (default "fast", comma list of fast,candle), `UFOPS_BENCH_THREADS`
//! (default "1,2"), `UFOPS_BENCH_NO_TORCH` (skip the peer).
#![allow(
    clippy::unwrap_used,
    clippy::too_many_lines,
    reason = "benchmarks: a failed unwrap is a failed run, and a measurement reads top to bottom"
)]

use std::time::Instant;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use trainer::{InputSpec, Kind, ObsKey, Samples, TrainBackend, TrainConfig};

fn env<T: std::str::FromStr>(k: &str, d: T) -> T {
    std::env::var(k).ok().and_then(|v| v.parse().ok()).unwrap_or(d)
}

/// Process CPU time (user + system, all threads) in seconds, from /proc/self/stat (Linux).
fn cpu_seconds() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/stat").ok()?;
    let rest = &s[s.rfind(')')? + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks: f64 = f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?;
    Some(ticks / 100.0)
}

/// Samples/s of the PyTorch peer (one thread) at its median epoch time, taken like ours (sorted
/// epoch times, index len/2), parsed from its "N samples/s" lines.
fn torch_peer(n: usize, epochs: usize) -> Option<f64> {
    let script = std::env::var("UFOPS_TORCH_EPOCH_SCRIPT").unwrap_or_else(|_| {
        concat!(env!("CARGO_MANIFEST_DIR"), "/../bench/reference/torch_verifier_epoch.py").into()
    });
    if !std::path::Path::new(&script).exists() {
        return None;
    }
    let out = std::process::Command::new("python3")
        .arg(&script)
        .args(["--threads", "1", "--samples", &n.to_string(), "--epochs", &epochs.max(2).to_string()])
        .output()
        .ok()?;
    if !out.status.success() {
        eprintln!("torch peer failed: {}", String::from_utf8_lossy(&out.stderr).lines().last().unwrap_or(""));
        return None;
    }
    let mut times: Vec<f64> = String::from_utf8_lossy(&out.stdout)
        .lines()
        .filter_map(|l| l.split(", ").nth(1)?.split_whitespace().next()?.parse::<f64>().ok())
        .map(|rate| n as f64 / rate)
        .collect();
    times.sort_by(|a, b| a.total_cmp(b));
    times.get(times.len() / 2).map(|t| n as f64 / t)
}

fn main() {
    let n: usize = env("UFOPS_BENCH_SAMPLES", 302_400);
    let epochs: usize = env("UFOPS_BENCH_EPOCHS", 2);
    let backends: String = env("UFOPS_BENCH_BACKENDS", "fast".to_string());
    let threads: String = env("UFOPS_BENCH_THREADS", "1,2".to_string());
    let (od, ad) = (46usize, 160usize);
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let mut s = Samples { obs_dim: od, act_dim: ad, ..Default::default() };
    s.obs = (0..n * od).map(|_| rng.sample::<f32, _>(StandardNormal)).collect();
    s.act = (0..n * ad).map(|_| rng.sample::<f32, _>(StandardNormal)).collect();
    s.t = (0..n).map(|_| rng.gen_range(0..50)).collect();
    s.label = (0..n).map(|_| if rng.gen::<f32>() < 0.6 { 1.0 } else { 0.0 }).collect();
    s.q_target = s.label.clone();
    s.discount = vec![1.0; n];
    s.episode = vec![0; n];
    let input = InputSpec {
        obs_keys: vec![ObsKey::new("state", od)],
        obs_history: 1,
        chunk_len: 16,
        action_dim: 10,
        t_embed_dim: 64,
        extra_inputs: vec![],
    };
    println!("synthetic Square-sized data: {n} samples, obs {od}, act {ad}, batch 1024, {epochs} epochs");
    let mut fast_1thread = None;
    for b in backends.split(',') {
        for th in threads.split(',') {
            let th: usize = th.trim().parse().unwrap();
            let backend = match b.trim() {
                "candle" => TrainBackend::Candle,
                _ => TrainBackend::Fast,
            };
            if backend == TrainBackend::Candle {
                // candle's CPU matmul reads RAYON_NUM_THREADS on every call.
                std::env::set_var("RAYON_NUM_THREADS", th.to_string());
            }
            let cfg =
                TrainConfig { kind: Kind::Classifier, epochs, threads: th, backend, ..Default::default() };
            let mut times = Vec::new();
            let mut cpu = Vec::new();
            let mut last_cpu = cpu_seconds();
            let t0 = Instant::now();
            let r = trainer::train_samples(
                s.clone(),
                Samples { obs_dim: od, act_dim: ad, ..Default::default() },
                &input,
                &cfg,
                &mut |e| {
                    times.push(e.seconds);
                    let c = cpu_seconds();
                    if let (Some(a), Some(b)) = (last_cpu, c) {
                        if e.epoch > 1 {
                            cpu.push(b - a); // epoch 1 also holds the setup
                        }
                    }
                    last_cpu = c;
                },
                None,
            )
            .expect("training failed");
            let _ = t0;
            times.sort_by(|a, b| a.total_cmp(b));
            let best = times[0];
            let med = times[times.len() / 2];
            cpu.sort_by(|a, b| a.total_cmp(b));
            let cpu_txt = match cpu.get(cpu.len() / 2) {
                Some(c) => {
                    format!(", CPU time {:.3} s/epoch ({:.0} samples per CPU-second)", c, n as f64 / c)
                }
                None => String::new(),
            };
            if backend == TrainBackend::Fast && th == 1 {
                fast_1thread = Some(n as f64 / med);
            }
            println!(
                "backend={:<6} threads={th}: best {:.3} s/epoch ({:.0} samples/s), median {:.3} s/epoch ({:.0} samples/s), final train loss {:.4}{cpu_txt}",
                b.trim(),
                best,
                n as f64 / best,
                med,
                n as f64 / med,
                r.metrics.final_train_loss
            );
        }
    }
    if std::env::var_os("UFOPS_BENCH_NO_TORCH").is_some() {
        return;
    }
    match torch_peer(n, epochs) {
        Some(torch) => {
            println!("torch eager threads=1: median {torch:.0} samples/s");
            if let Some(fast) = fast_1thread {
                println!("fast / torch (1 thread, medians, same run): {:.2}x", fast / torch);
            }
        }
        None => println!("(PyTorch peer not run: python3 with torch or the script unavailable)"),
    }
}
