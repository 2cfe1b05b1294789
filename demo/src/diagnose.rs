//! Guidance diagnostics: what verifier guidance does to the Tweedie estimate x̂0 at every
//! denoising step, and what the guided policy then does in the environment. The demo records
//! them for every guided row so that a collapse (or a gain) can be explained from the report.

use serde::Serialize;
use sim::{Episode, Outcome};
use std::sync::Mutex;
use steer::{ActionAffine, Scorer, SteerError};

#[derive(Debug, Default, Clone, Copy)]
struct Acc {
    rows: u64,
    grad_norm: f64,
    push_norm: f64,
    /// entries of x̂0 + λ∇ outside the policy's sample range [-1, 1]
    out_of_range: u64,
    entries: u64,
}

/// One denoising step's averages over every guided sample of a run (step 0 is the noisiest).
#[derive(Debug, Clone, Serialize)]
pub struct StepStat {
    pub step: usize,
    /// mean L2 norm of the guidance gradient per chunk
    pub grad_norm: f64,
    /// mean L2 norm of λ∇ (the change of x̂0) per chunk
    pub push_norm: f64,
    /// fraction of the perturbed x̂0's entries outside [-1, 1]
    pub out_of_range: f64,
}

/// A scorer that forwards to another one and records, per denoising step, the gradient norms it
/// returns. Guided samplers call `grad_batch` once per step in order (K, K−1, …, 1) and the
/// rollouts are sequential, so the call count modulo `steps` is the denoising step.
pub struct TracingScorer<'a> {
    inner: &'a dyn Scorer,
    steps: usize,
    lambda: f32,
    state: Mutex<(usize, Vec<Acc>)>,
}

impl<'a> TracingScorer<'a> {
    pub fn new(inner: &'a dyn Scorer, guided_steps_per_sample: usize, lambda: f32) -> Self {
        let steps = guided_steps_per_sample.max(1);
        TracingScorer { inner, steps, lambda, state: Mutex::new((0, vec![Acc::default(); steps])) }
    }

    pub fn steps(&self) -> Vec<StepStat> {
        let st = self.state.lock().unwrap_or_else(|e| e.into_inner());
        st.1.iter()
            .enumerate()
            .map(|(step, a)| {
                let r = a.rows.max(1) as f64;
                StepStat {
                    step,
                    grad_norm: a.grad_norm / r,
                    push_norm: a.push_norm / r,
                    out_of_range: a.out_of_range as f64 / a.entries.max(1) as f64,
                }
            })
            .collect()
    }
}

impl Scorer for TracingScorer<'_> {
    fn obs_dim(&self) -> usize {
        self.inner.obs_dim()
    }
    fn act_dim(&self) -> usize {
        self.inner.act_dim()
    }
    fn takes_policy_space(&self) -> bool {
        self.inner.takes_policy_space()
    }
    fn artifact_id(&self) -> Option<String> {
        self.inner.artifact_id()
    }
    fn steering_warning(&self) -> Option<String> {
        self.inner.steering_warning()
    }
    fn score_batch(&self, obs: &[f32], t: &[u32], candidates: &[f32], n: usize) -> steer::Result<Vec<f32>> {
        self.inner.score_batch(obs, t, candidates, n)
    }
    fn pick_batch(
        &self,
        obs: &[f32],
        t: &[u32],
        candidates: &[f32],
        n: usize,
    ) -> steer::Result<steer::Picks> {
        self.inner.pick_batch(obs, t, candidates, n)
    }
    fn grad_batch(&self, obs: &[f32], t: &[u32], chunks: &[f32]) -> steer::Result<Vec<f32>> {
        let g = self.inner.grad_batch(obs, t, chunks)?;
        let ad = self.act_dim();
        if ad == 0 || g.len() != chunks.len() {
            return Err(SteerError::Model(format!(
                "{} gradient values for {} chunk values",
                g.len(),
                chunks.len()
            )));
        }
        let mut st = self.state.lock().unwrap_or_else(|e| e.into_inner());
        let step = st.0 % self.steps;
        st.0 += 1;
        let acc = &mut st.1[step];
        for (gr, x) in g.chunks(ad).zip(chunks.chunks(ad)) {
            let n2: f64 = gr.iter().map(|v| f64::from(*v) * f64::from(*v)).sum();
            acc.rows += 1;
            acc.grad_norm += n2.sqrt();
            acc.push_norm += f64::from(self.lambda.abs()) * n2.sqrt();
            acc.out_of_range +=
                x.iter().zip(gr).filter(|(x, g)| (**x + self.lambda * **g).abs() > 1.0).count() as u64;
            acc.entries += ad as u64;
        }
        Ok(g)
    }
}

/// What a steered run did, in terms that explain its success rate.
#[derive(Debug, Clone, Serialize)]
pub struct RunDiagnostics {
    pub method: String,
    /// per denoising step (guided rows only)
    pub per_step: Vec<StepStat>,
    /// sum over the denoising steps of the mean ‖λ∇‖: how far guidance moves x̂0 in all
    pub total_push: f64,
    /// executed actions at the speed limit (‖a‖ ≥ 0.999 · max_speed): the env clips the rest away
    pub saturated_actions: f64,
    /// the verifier's mean score of the chunks the run executed (at its re-planning steps)
    pub verifier_score_executed: f64,
    pub collisions: u64,
    pub timeouts: u64,
    pub wide_gap: u64,
    pub narrow_gap: u64,
}

/// Diagnostics of a run's episodes under `scorer` (the verifier that steered it, or the one to
/// compare with). `space` is the policy's map from its sample space to raw actions (chunks go to
/// a policy-space scorer through its inverse); `max_speed` is the environment's speed limit;
/// `trace` is the tracing scorer of a guided run.
pub fn run_diagnostics(
    method: &str,
    eps: &[Episode],
    scorer: &dyn Scorer,
    space: &ActionAffine,
    max_speed: f32,
    trace: Option<&TracingScorer>,
) -> steer::Result<RunDiagnostics> {
    let per_step = trace.map(|t| t.steps()).unwrap_or_default();
    let total_push = per_step.iter().map(|s| s.push_norm).sum();
    let (mut sat, mut acts) = (0u64, 0u64);
    for e in eps {
        for a in &e.actions {
            acts += 1;
            if (a[0] * a[0] + a[1] * a[1]).sqrt() >= 0.999 * max_speed {
                sat += 1;
            }
        }
    }
    // Score every executed chunk at its re-planning step, batched over the whole run.
    let t_o = scorer.obs_dim() / 2;
    let (mut obs, mut ts, mut chunks) = (Vec::new(), Vec::new(), Vec::new());
    for e in eps {
        for (t, (&off, chunk)) in e.chunk_offset.iter().zip(&e.action_chunks).enumerate() {
            if off != 0 {
                continue;
            }
            sim::rollout::obs_history(&e.positions[..=t], t_o, &mut obs);
            ts.push(t as u32);
            chunks.extend_from_slice(chunk);
        }
    }
    if scorer.takes_policy_space() {
        space.invert(&mut chunks)?;
    }
    let scores = if ts.is_empty() { vec![] } else { scorer.score_batch(&obs, &ts, &chunks, 1)? };
    let count = |f: &dyn Fn(&Episode) -> bool| eps.iter().filter(|e| f(e)).count() as u64;
    Ok(RunDiagnostics {
        method: method.to_string(),
        per_step,
        total_push,
        saturated_actions: sat as f64 / acts.max(1) as f64,
        verifier_score_executed: scores.iter().map(|s| f64::from(*s)).sum::<f64>()
            / scores.len().max(1) as f64,
        collisions: count(&|e| e.outcome == Outcome::Collision),
        timeouts: count(&|e| e.outcome == Outcome::Timeout),
        wide_gap: count(&|e| e.gap == Some(sim::env::Gap::Wide)),
        narrow_gap: count(&|e| e.gap == Some(sim::env::Gap::Narrow)),
    })
}

/// The diagnostics as a Markdown table.
pub fn markdown(rows: &[RunDiagnostics]) -> String {
    let mut s = String::from(
        "| run | ‖λ∇‖ first / mid / last step | total push | x̂0 outside [-1,1] | actions at speed limit | verifier score of executed chunks | wide / narrow gap | collisions / timeouts |\n|---|---|---|---|---|---|---|---|\n",
    );
    for r in rows {
        let steps = if r.per_step.is_empty() {
            "-".to_string()
        } else {
            let p = &r.per_step;
            format!(
                "{:.3} / {:.3} / {:.3}",
                p[0].push_norm,
                p[p.len() / 2].push_norm,
                p[p.len() - 1].push_norm
            )
        };
        let oor = if r.per_step.is_empty() {
            "-".to_string()
        } else {
            format!(
                "{:.1}%",
                100.0 * r.per_step.iter().map(|p| p.out_of_range).sum::<f64>() / r.per_step.len() as f64
            )
        };
        let push = if r.per_step.is_empty() { "-".to_string() } else { format!("{:.2}", r.total_push) };
        s.push_str(&format!(
            "| {} | {} | {} | {} | {:.1}% | {:.3} | {} / {} | {} / {} |\n",
            r.method,
            steps,
            push,
            oor,
            100.0 * r.saturated_actions,
            r.verifier_score_executed,
            r.wide_gap,
            r.narrow_gap,
            r.collisions,
            r.timeouts
        ));
    }
    s
}
