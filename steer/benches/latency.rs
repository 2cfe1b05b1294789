//! Latency at the paper's Square dimensions (obs 46, chunk 16 x 10, lowdim: encoders 64, t-emb 64,
//! trunk 128 -> 64), random weights, one thread: BoN(10) scoring (+ argmax) and one CG gradient
//! through the `Scorer` trait (the verifier core's kernels: AVX2/FMA and the portable fallback),
//! and the PyTorch eager peer (bench/reference/torch_bon_latency.py) measured in the same run
//! when `python3 -c "import torch"` works. Run with `cargo bench -p steer`.
#![allow(
    clippy::unwrap_used,
    clippy::too_many_lines,
    reason = "benchmarks: a failed unwrap is a failed run, and a measurement reads top to bottom"
)]
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::time::Instant;
use steer::verifier::kernels::Isa;
use steer::verifier::testutil::RandomSpec;
use steer::{select_best, Scorer, Verifier};

fn measure(iters: usize, mut f: impl FnMut()) -> (f64, f64) {
    for _ in 0..iters / 10 + 50 {
        f();
    }
    let mut ts: Vec<u64> = (0..iters)
        .map(|_| {
            let t0 = Instant::now();
            f();
            t0.elapsed().as_nanos() as u64
        })
        .collect();
    ts.sort_unstable();
    (ts[ts.len() / 2] as f64 / 1e3, ts[ts.len() * 99 / 100] as f64 / 1e3)
}

fn torch_peer() -> Option<(f64, f64, f64, f64)> {
    let script =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../bench/reference/torch_bon_latency.py");
    if !script.exists() {
        return None;
    }
    let out = std::process::Command::new("python3").arg(script).output().ok()?;
    if !out.status.success() {
        eprintln!("torch peer failed: {}", String::from_utf8_lossy(&out.stderr).lines().last().unwrap_or(""));
        return None;
    }
    let s = String::from_utf8_lossy(&out.stdout);
    // lines: "BoN(10) score: p50 X us, p99 Y us" / "CG gradient: p50 X us, p99 Y us"
    let v: Vec<f64> = s
        .lines()
        .flat_map(|l| {
            l.split_whitespace()
                .collect::<Vec<_>>()
                .windows(2)
                .filter(|w| w[0] == "p50" || w[0] == "p99")
                .filter_map(|w| w[1].parse::<f64>().ok())
                .collect::<Vec<_>>()
        })
        .collect();
    (v.len() == 4).then(|| (v[0], v[1], v[2], v[3]))
}

fn main() {
    let quick = std::env::args().any(|a| a == "--quick");
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let (cfg, w) = RandomSpec::square().build(0);
    let fast = Verifier::new(cfg.clone(), &w).unwrap();
    let reference = Verifier::with_isa(cfg, &w, Isa::Portable).unwrap();
    let obs: Vec<f32> = (0..46).map(|_| rng.gen_range(-1.0..1.0)).collect();
    let cands: Vec<f32> = (0..1600).map(|_| rng.gen_range(-1.0..1.0)).collect();
    let chunk = cands[..160].to_vec();
    let (nf, nr) = if quick { (2000, 300) } else { (20000, 5000) };

    println!("steer latency, Square dims (obs 46, chunk 160, enc 64, t-emb 64, trunk 128/64), 1 thread");
    println!("kernels: {} (fallback: {})", fast.backend_name(), reference.backend_name());
    let (fast, reference): (&dyn Scorer, &dyn Scorer) = (&fast, &reference);
    let mut sink = 0usize;
    let bon_fast = measure(nf, || sink += select_best(&fast.score(&obs, &cands, 7).unwrap()));
    let cg_fast = measure(nf, || sink += fast.grad(&obs, &chunk, 7).unwrap().len());
    let bon_ref = measure(nr, || sink += select_best(&reference.score(&obs, &cands, 7).unwrap()));
    let cg_ref = measure(nr, || sink += reference.grad(&obs, &chunk, 7).unwrap().len());
    // The failure monitor: one chunk's score plus the statistic's step, against the score alone.
    let record = steer::verifier::MonitorRecord {
        schema_version: steer::verifier::monitor::MONITOR_SCHEMA_VERSION,
        artifact_id: "bench".into(),
        policy: "p".into(),
        checkpoint: "c".into(),
        method: steer::verifier::monitor::SPLIT_CONFORMAL_PEAK.into(),
        statistic: steer::verifier::monitor::Statistic::RiskEma { smoothing: 0.8 },
        alpha: 0.1,
        threshold: 0.7,
        version: 1,
        seed: 0,
        calibration_episodes: vec![],
        confidence: None,
    };
    let mut monitor = steer::Monitor::new(fast, Some("bench"), record).unwrap();
    let mut fired = 0usize;
    let score_one = measure(nf, || sink += fast.score(&obs, &chunk, 7).unwrap().len());
    let monitor_one = measure(nf, || fired += monitor.update(&obs, &chunk, 7).unwrap().alarm as usize);
    let step_only = measure(nf, || fired += monitor.update_score(0.4).alarm as usize);
    std::hint::black_box((sink, fired));
    let row =
        |name: &str, (p50, p99): (f64, f64)| println!("  {name:<28} p50 {p50:>9.1} us   p99 {p99:>9.1} us");
    row("BoN(10) score, fast", bon_fast);
    row("BoN(10) score, portable", bon_ref);
    row("CG gradient, fast", cg_fast);
    row("CG gradient, portable", cg_ref);
    row("score of 1 chunk", score_one);
    row("monitor update (score + step)", monitor_one);
    println!(
        "  {:<28} p50 {:>9.0} ns   p99 {:>9.0} ns (with the clock's own cost)",
        "monitor step, score given",
        step_only.0 * 1e3,
        step_only.1 * 1e3
    );
    println!(
        "  monitor over the score (p50): {:.2} us (goal <= 1 us: {})",
        monitor_one.0 - score_one.0,
        if monitor_one.0 - score_one.0 <= 1.0 { "met" } else { "MISSED" }
    );
    println!(
        "  goals: BoN(10) <= 30 us: {}; CG gradient <= 20 us: {}",
        if bon_fast.0 <= 30.0 { "met" } else { "MISSED" },
        if cg_fast.0 <= 20.0 { "met" } else { "MISSED" }
    );
    println!("  portable / fast (p50): BoN {:.1}x, CG {:.1}x", bon_ref.0 / bon_fast.0, cg_ref.0 / cg_fast.0);
    if std::env::var_os("STEER_BENCH_NO_TORCH").is_some() {
        return;
    }
    match torch_peer() {
        Some((b50, b99, g50, g99)) => {
            row("BoN(10) score, torch eager", (b50, b99));
            row("CG gradient, torch eager", (g50, g99));
            println!("  torch / fast (p50): BoN {:.1}x, CG {:.1}x", b50 / bon_fast.0, g50 / cg_fast.0);
        }
        None => println!("  (PyTorch peer not run: python3 with torch unavailable)"),
    }
}
