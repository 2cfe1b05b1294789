//! Steering telemetry on the robot: best-of-N that records, per group, the candidates it scored,
//! their scores, the chosen index, the artifact and the scoring latency
//! ([`verifier::telemetry::SteeringStep`]), for the store's steering column and `ufops replay`.

use std::time::Instant;

use crate::sample::{best_of_n_raw, BestOfN};
use crate::{ActionAffine, Result, Scorer, SteerError};
use verifier::telemetry::{round_to_f16, SteeringStep};

/// [`best_of_n_raw`] that records each group's step. The raw candidates are first rounded to
/// the half-float grid the store keeps them on ([`round_to_f16`]), so what is scored, executed
/// and stored is the same chunk and a replay with the same artifact makes the same choice; then
/// they are scored and picked exactly as [`best_of_n_raw`] does. Group `g`'s record is for step
/// `t[g]`; its latency is the scoring call's wall time divided among the groups it scored.
/// Refuses a scorer without an artifact id (the record must name what scored).
pub fn best_of_n_recorded(
    scorer: &dyn Scorer,
    affine: Option<&ActionAffine>,
    obs: &[f32],
    t: &[u32],
    raw_candidates: &[f32],
    n: usize,
) -> Result<(BestOfN, Vec<SteeringStep>)> {
    let artifact_id = scorer.artifact_id().ok_or_else(|| {
        SteerError::Input("steering telemetry needs a scorer loaded from an artifact (it has no id)".into())
    })?;
    let mut cands = raw_candidates.to_vec();
    round_to_f16(&mut cands);
    let started = Instant::now();
    let best = best_of_n_raw(scorer, affine, obs, t, &cands, n)?;
    let per_group = started.elapsed().as_micros() / t.len().max(1) as u128;
    let latency_us = u32::try_from(per_group).unwrap_or(u32::MAX);
    let group = n * scorer.act_dim();
    let log = t
        .iter()
        .enumerate()
        .map(|(g, &step)| SteeringStep {
            t: step,
            artifact_id: artifact_id.clone(),
            candidates: cands[g * group..(g + 1) * group].to_vec(),
            scores: best.scores[g * n..(g + 1) * n].to_vec(),
            chosen: best.index[g] as u32,
            latency_us,
        })
        .collect();
    Ok((best, log))
}
