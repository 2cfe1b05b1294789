//! The cost of steering telemetry: a best-of-N rollout of the demo's base policy that records
//! every step's candidates, scores and choice (`ChunkChoice::RecordedBestOfN`, candidates
//! rounded to f16) and ingests them with its episodes, against the same rollout and ingest
//! without them, on the same machine in the same run.
//!
//! Rollouts are timed per executed environment step (rounding the candidates to f16 changes
//! trajectories, so the two arms take slightly different numbers of steps), alternating which
//! arm goes first, and the medians over the repetitions are compared. The verifier has the
//! demo's shape (random weights: its cost, not its skill, matters here).
//!
//! `cargo bench --profile dev --workspace --bench telemetry` (about two minutes on 2 cores;
//! the dev profile optimises the numeric crates and reuses the test build);
//! `UFOPS_TELEMETRY_EPISODES` (default 200), `UFOPS_TELEMETRY_N` (30), `UFOPS_TELEMETRY_REPS` (5).
#![allow(
    clippy::unwrap_used,
    clippy::too_many_lines,
    reason = "benchmarks: a failed unwrap is a failed run, and a measurement reads top to bottom"
)]

use anyhow::Result;
use sim::{rollout, ChunkChoice, DiffusionPolicy, EnvConfig, PolicyConfig};
use std::time::Instant;
use store::{RunInput, Steering, Store, StoreConfig};
use verifier::testutil::RandomSpec;

fn env_usize(k: &str, d: usize) -> usize {
    std::env::var(k).ok().and_then(|v| v.parse().ok()).unwrap_or(d)
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() -> Result<()> {
    let episodes = env_usize("UFOPS_TELEMETRY_EPISODES", 200);
    let n = env_usize("UFOPS_TELEMETRY_N", 30);
    let reps = env_usize("UFOPS_TELEMETRY_REPS", 5);
    let env = EnvConfig::default();
    let pc = PolicyConfig::default();
    // The quick demo's base policy (60 demonstrations, 800 training steps).
    let demos = sim::expert_demos(&env, 60, 0);
    let tc = sim::PolicyTrainConfig { steps: 800, seed: 0, ..Default::default() };
    let base = DiffusionPolicy::train(&pc, &tc, &demos)?;
    let dir = tempfile::tempdir()?;
    let (cfg, w) = RandomSpec::nav().build(1);
    verifier::ArtifactFiles::build(&cfg, &w)?.write_dir(dir.path().join("artifact"))?;
    let v = verifier::Verifier::load_dir(dir.path().join("artifact"))?;
    let store = Store::open(&StoreConfig::local(dir.path().join("store"))).await?;

    // (rollout seconds per step, ingest seconds per step, telemetry bytes) per arm and repetition.
    let mut plain = (Vec::new(), Vec::new());
    let mut logged = (Vec::new(), Vec::new());
    let mut records = 0usize;
    for rep in 0..reps {
        let seed = 1000 + rep as u64;
        let arms = if rep % 2 == 0 { [false, true] } else { [true, false] };
        for record in arms {
            let choice = if record {
                ChunkChoice::RecordedBestOfN { scorer: &v, n }
            } else {
                ChunkChoice::BestOfN { scorer: &v, n }
            };
            let t0 = Instant::now();
            let eps = tokio::task::block_in_place(|| rollout(&base, &env, episodes, choice, seed))?;
            let rollout_s = t0.elapsed().as_secs_f64();
            let steps: usize = eps.iter().map(|e| e.length).sum();
            let name = format!("bon{n}-{}-{rep}", if record { "logged" } else { "plain" });
            let run =
                RunInput { name, steering: Steering::Bon { n: n as u32 }, artifact_id: None, tags: vec![] };
            let t1 = Instant::now();
            demo::ingest_rollouts(&store, &eps, "base", run, pc.horizon, seed).await?;
            let ingest_s = t1.elapsed().as_secs_f64();
            let arm = if record { &mut logged } else { &mut plain };
            arm.0.push(rollout_s / steps as f64);
            arm.1.push(ingest_s / steps as f64);
            if record {
                records += eps.iter().map(|e| e.steering.len()).sum::<usize>();
            }
        }
    }
    // The recording alone, on fixed candidates: best-of-N with and without it, per re-planning
    // step of one robot (a group), free of the trajectory differences the rounding causes.
    let (groups, ad, od) = (episodes, pc.horizon * 2, 4);
    let obs: Vec<f32> = (0..groups * od).map(|k| (k as f32 * 0.37).sin()).collect();
    let ts = vec![12u32; groups];
    let cands: Vec<f32> = (0..groups * n * ad).map(|k| (k as f32 * 0.013).cos() * 0.03).collect();
    let space = pc.action_normalizer();
    let (mut plain_call, mut logged_call) = (Vec::new(), Vec::new());
    for rep in 0..30 {
        for record in if rep % 2 == 0 { [false, true] } else { [true, false] } {
            let t0 = Instant::now();
            if record {
                std::hint::black_box(steer::best_of_n_recorded(&v, Some(&space), &obs, &ts, &cands, n)?);
                logged_call.push(t0.elapsed().as_secs_f64() / groups as f64);
            } else {
                std::hint::black_box(steer::best_of_n_raw(&v, Some(&space), &obs, &ts, &cands, n)?);
                plain_call.push(t0.elapsed().as_secs_f64() / groups as f64);
            }
        }
    }
    let (pc_s, lc_s) = (median(plain_call), median(logged_call));
    let us = 1e6;
    let (pr, pi) = (median(plain.0), median(plain.1));
    let (lr, li) = (median(logged.0), median(logged.1));
    println!(
        "telemetry: {episodes} episodes x {reps} repetitions, best-of-{n}, {} recorded steps per repetition",
        records / reps.max(1)
    );
    println!("  per executed step (median)   rollout      ingest       total");
    println!(
        "  plain best-of-N              {:8.2} us  {:8.2} us  {:8.2} us",
        pr * us,
        pi * us,
        (pr + pi) * us
    );
    println!(
        "  recorded best-of-N           {:8.2} us  {:8.2} us  {:8.2} us",
        lr * us,
        li * us,
        (lr + li) * us
    );
    let per_replan = pr * pc.n_exec as f64;
    let record_share = (lc_s - pc_s) / per_replan;
    let store_share = (li - pi) / pr;
    println!(
        "  best-of-{n} per re-planning step of one robot (fixed candidates, median): {:.2} us plain, {:.2} us \
         recorded (+{:.2} us)",
        pc_s * us,
        lc_s * us,
        (lc_s - pc_s) * us,
    );
    println!(
        "  overhead of logging: recording {:+.2}% + storing {:+.2}% = {:+.2}% of the steered rollout's time \
         ({:.0} us per re-planning step; goal: at most +10%)",
        100.0 * record_share,
        100.0 * store_share,
        100.0 * (record_share + store_share),
        per_replan * us
    );
    println!(
        "  (whole rollouts, recorded / plain per executed step: {:+.1}%; the f16 rounding changes the trajectories, \
         so this ratio also carries which episodes run how long)",
        100.0 * (lr / pr - 1.0)
    );
    Ok(())
}
