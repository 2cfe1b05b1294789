//! [`Verifier`]: the runnable verifier — one network, or an ensemble's members behind the same
//! interface — and the ensemble's rules, once (trainer/ARTIFACT.md, "Ensembles"):
//!
//! * the score of a chunk is the members' mean, its *spread* their population standard
//!   deviation ([`Verifier::score_spread_into`]);
//! * best-of-N ranks candidates by the pessimistic `mean − κ · spread` and keeps the policy's
//!   own first candidate unless enough members score the pick above it ([`Verifier::pick`]);
//! * guidance pushes along the members' mean gradient, scaled by how much their gradients
//!   agree, down to zero where they do not ([`Verifier::grad`]).
//!
//! For one network each rule reduces to the plain one (the score, the argmax, the gradient),
//! so every client calls the same methods whatever the artifact holds.

use crate::error::{Result, VerifierError};
use crate::format::{member_prefix, ArtifactConfig, EnsembleSpec, Kind};
use crate::kernels::Isa;
use crate::net::Net;
use crate::weights::Weights;

/// A loaded verifier (success classifier or time-to-success Q; one network or an ensemble).
/// Immutable after loading, so it is `Send + Sync` and one instance serves any number of
/// threads.
#[derive(Clone, Debug)]
pub struct Verifier {
    config: ArtifactConfig,
    id: Option<String>,
    isa: Isa,
    members: Vec<Net>,
}

const _: () = {
    const fn send_sync<T: Send + Sync>() {}
    send_sync::<Verifier>();
};

/// What best-of-N chose for each of `B` groups of `n` candidates ([`Verifier::pick`]).
#[derive(Clone, Debug, PartialEq)]
pub struct Picks {
    /// The chosen candidate of each group.
    pub index: Vec<usize>,
    /// Every candidate's score (`B * n`): the members' mean.
    pub scores: Vec<f32>,
    /// Every candidate's spread over the members (`B * n`; 0 for one network).
    pub spread: Vec<f32>,
    /// Per group: the pessimistic pick was overruled for the policy's first candidate.
    pub fell_back: Vec<bool>,
    /// Per group: the share of members that score the pessimistic pick above the first
    /// candidate (1 when the pick is the first candidate, and for one network).
    pub agreement: Vec<f32>,
}

/// Index of the largest value (first one on ties; NaN counts as −∞).
pub fn argmax(values: &[f32]) -> usize {
    let mut best = 0;
    let mut bv = f32::NEG_INFINITY;
    for (i, &v) in values.iter().enumerate() {
        let v = if v.is_nan() { f32::NEG_INFINITY } else { v };
        if v > bv {
            best = i;
            bv = v;
        }
    }
    best
}

/// The members' mean and population standard deviation of one value, `member_values[k]` for
/// member `k`, summed in member order in f32.
pub fn mean_spread(member_values: impl Iterator<Item = f32> + Clone) -> (f32, f32) {
    let (mut sum, mut k) = (0f32, 0usize);
    for v in member_values.clone() {
        sum += v;
        k += 1;
    }
    if k == 0 {
        return (f32::NAN, f32::NAN);
    }
    let mean = sum / k as f32;
    let var = member_values.map(|v| (v - mean) * (v - mean)).sum::<f32>() / k as f32;
    (mean, var.sqrt())
}

/// Best-of-N's rule for one group: `member_scores[k * n + i]` is member `k`'s score of
/// candidate `i`. Returns `(pick, fell_back, agreement)`: the argmax of `mean − κ · spread`,
/// replaced by candidate 0 when the share of members scoring it above candidate 0 is below
/// `min_agreement`.
pub fn pick_group(member_scores: &[f32], n: usize, spec: &EnsembleSpec) -> (usize, bool, f32) {
    let k = member_scores.len().checked_div(n).unwrap_or(0);
    if n == 0 || k == 0 {
        return (0, false, 1.0);
    }
    let kappa = spec.pessimism as f32;
    let lcb: Vec<f32> = (0..n)
        .map(|i| {
            let (m, s) = mean_spread((0..k).map(|j| member_scores[j * n + i]));
            m - kappa * s
        })
        .collect();
    let best = argmax(&lcb);
    if best == 0 {
        return (0, false, 1.0);
    }
    let above = (0..k).filter(|&j| member_scores[j * n + best] > member_scores[j * n]).count();
    let agreement = above as f32 / k as f32;
    if (agreement as f64) < spec.min_agreement {
        (0, true, agreement)
    } else {
        (best, false, agreement)
    }
}

/// Guidance's rule for one chunk: `member_grads[k * d + j]` is member `k`'s gradient. Writes
/// the members' mean gradient scaled by `clamp((R − r0) / (1 − r0), 0, 1)` into `out` (`d`)
/// and returns `R`, the mean resultant length `|mean g_k| / mean |g_k|` (1 when every member
/// pushes the same way, near `1/√K` when their directions are unrelated, 0 with no push).
pub fn agree_gradients(member_grads: &[f32], d: usize, spec: &EnsembleSpec, out: &mut [f32]) -> f32 {
    let k = member_grads.len().checked_div(d).unwrap_or(0);
    out.iter_mut().for_each(|v| *v = 0.0);
    if d == 0 || k == 0 {
        return 0.0;
    }
    let mut norms = 0f32;
    for g in member_grads.chunks_exact(d) {
        norms += g.iter().map(|v| v * v).sum::<f32>().sqrt();
        for (o, v) in out.iter_mut().zip(g) {
            *o += v;
        }
    }
    out.iter_mut().for_each(|v| *v /= k as f32);
    let mean_norm = norms / k as f32;
    let resultant = out.iter().map(|v| v * v).sum::<f32>().sqrt();
    let r = if mean_norm > 0.0 && mean_norm.is_finite() { (resultant / mean_norm).min(1.0) } else { 0.0 };
    let r0 = spec.min_gradient_agreement as f32;
    let scale = ((r - r0) / (1.0 - r0)).clamp(0.0, 1.0);
    out.iter_mut().for_each(|v| *v *= scale);
    r
}

impl Verifier {
    /// Load and check an artifact directory (see [`crate::Artifact::load_dir`]).
    pub fn load_dir(dir: impl AsRef<std::path::Path>) -> Result<Self> {
        crate::Artifact::load_dir(dir)?.verifier()
    }

    /// Load through a getter, every file checked (see [`crate::Artifact::load_with`]).
    pub fn load_with(manifest: &[u8], get: impl FnMut(&str) -> Result<Vec<u8>>) -> Result<Self> {
        crate::Artifact::load_with(manifest, get)?.verifier()
    }

    /// From `config.json` and `model.safetensors` bytes the caller has already checked.
    pub fn from_bytes(config_json: &[u8], safetensors: &[u8]) -> Result<Self> {
        crate::Artifact::from_checked_bytes(config_json, safetensors)?.verifier()
    }

    /// From a configuration and its weights (validated here), with the best kernels the CPU has.
    pub fn new(config: ArtifactConfig, weights: &Weights) -> Result<Self> {
        Self::with_isa(config, weights, Isa::detect())
    }

    /// Same, with the given kernels (`Isa::Portable` tests the fallback; a request for AVX2 on
    /// a CPU without it gets the portable kernels).
    pub fn with_isa(config: ArtifactConfig, weights: &Weights, isa: Isa) -> Result<Self> {
        config.validate()?;
        weights.validate(&config)?;
        let members = match &config.ensemble {
            None => vec![Net::build(&config, weights, "", isa)?],
            Some(e) => (0..e.members)
                .map(|k| Net::build(&config, weights, &member_prefix(k), isa))
                .collect::<Result<_>>()?,
        };
        Ok(Verifier { isa: isa.checked(), id: None, members, config })
    }

    pub(crate) fn set_id(&mut self, id: Option<String>) {
        self.id = id;
    }

    /// The artifact id (when loaded through a manifest).
    pub fn id(&self) -> Option<&str> {
        self.id.as_deref()
    }
    pub fn config(&self) -> &ArtifactConfig {
        &self.config
    }
    /// Refuses to score features from another producer than the one this verifier was trained
    /// on: `provided` names the producer (sha256) of each layer observation key about to be
    /// scored (see [`crate::InputLayout::check_producers`]). Call it once when the robot's
    /// encoder is set up, before the first score.
    pub fn check_producers<'a>(
        &self,
        provided: impl IntoIterator<Item = (&'a str, &'a str)>,
    ) -> crate::Result<()> {
        self.config.input.layout.check_producers(provided)
    }
    pub fn kind(&self) -> Kind {
        self.config.kind
    }
    /// Length of one observation-history row.
    pub fn obs_dim(&self) -> usize {
        self.config.input.obs_dim
    }
    /// Length of one flattened action chunk (`H * A`).
    pub fn act_dim(&self) -> usize {
        self.config.input.act_dim
    }
    /// `(name, dim)` of each extra input, in the order `*_ext` calls take them.
    pub fn extra_inputs(&self) -> Vec<(&str, usize)> {
        self.config.architecture.extra_inputs.iter().map(|e| (e.name.as_str(), e.dim)).collect()
    }
    /// Whether chunks are taken in the policy's normalised space (the paper's choice) rather
    /// than as raw actions standardised with train-set statistics (older artifacts).
    pub fn takes_policy_space(&self) -> bool {
        self.config.input.action_space.is_policy()
    }
    /// The kernels in use: `"avx2-fma"` or `"portable"`.
    pub fn backend_name(&self) -> &'static str {
        self.isa.name()
    }
    /// Networks behind the scores: 1, or the ensemble's members.
    pub fn members(&self) -> usize {
        self.members.len()
    }
    /// The ensemble's members and steering rules (`None` for one network).
    pub fn ensemble(&self) -> Option<&EnsembleSpec> {
        self.config.ensemble.as_ref()
    }

    /// Scores of `n` candidates for each of `B = t.len()` observations: `obs` is `B * obs_dim`,
    /// `candidates` is `B * n * act_dim` (group-major); returns `B * n` scores (classifier:
    /// sigmoid(logit), q: the value; an ensemble's members' mean).
    pub fn score(&self, obs: &[f32], t: &[u32], candidates: &[f32], n: usize) -> Result<Vec<f32>> {
        self.score_ext(obs, &[], t, candidates, n)
    }

    /// [`Self::score`] with extra inputs: `extras[i]` is `B * dim_i`, in [`Self::extra_inputs`] order.
    pub fn score_ext(
        &self,
        obs: &[f32],
        extras: &[&[f32]],
        t: &[u32],
        candidates: &[f32],
        n: usize,
    ) -> Result<Vec<f32>> {
        let mut out = vec![0f32; batch(t.len(), n)?];
        self.score_into(obs, extras, t, candidates, n, &mut out)?;
        Ok(out)
    }

    /// [`Self::score_ext`] into a caller's buffer of `B * n` (no allocation for the result with
    /// one network).
    pub fn score_into(
        &self,
        obs: &[f32],
        extras: &[&[f32]],
        t: &[u32],
        candidates: &[f32],
        n: usize,
        out: &mut [f32],
    ) -> Result<()> {
        if let [one] = self.members.as_slice() {
            return one.score_into(obs, extras, t, candidates, n, out);
        }
        let mut spread = vec![0f32; out.len()];
        self.score_spread_into(obs, extras, t, candidates, n, out, &mut spread)
    }

    /// Every member's scores, member-major: `out` is `members * B * n`, member `k`'s scores at
    /// `k * B * n`.
    pub fn score_members_into(
        &self,
        obs: &[f32],
        extras: &[&[f32]],
        t: &[u32],
        candidates: &[f32],
        n: usize,
        out: &mut [f32],
    ) -> Result<()> {
        let m = batch(t.len(), n)?;
        if Some(out.len()) != m.checked_mul(self.members.len()) {
            return Err(VerifierError::Input(format!(
                "member scores buffer has length {}, expected members {} * batch {} * n {n}",
                out.len(),
                self.members.len(),
                t.len()
            )));
        }
        for (net, o) in self.members.iter().zip(out.chunks_exact_mut(m.max(1))) {
            net.score_into(obs, extras, t, candidates, n, o)?;
        }
        Ok(())
    }

    /// The score (members' mean) and spread (their population standard deviation) of every
    /// candidate, each `B * n`.
    #[allow(clippy::too_many_arguments)] // the score's operands and its two outputs
    pub fn score_spread_into(
        &self,
        obs: &[f32],
        extras: &[&[f32]],
        t: &[u32],
        candidates: &[f32],
        n: usize,
        mean: &mut [f32],
        spread: &mut [f32],
    ) -> Result<()> {
        let m = batch(t.len(), n)?;
        if mean.len() != m || spread.len() != m {
            return Err(VerifierError::Input(format!(
                "score and spread buffers have lengths {} and {}, expected batch {} * n {n}",
                mean.len(),
                spread.len(),
                t.len()
            )));
        }
        let k = self.members.len();
        let mut all = vec![0f32; m * k];
        self.score_members_into(obs, extras, t, candidates, n, &mut all)?;
        for i in 0..m {
            let (mu, sd) = mean_spread((0..k).map(|j| all[j * m + i]));
            mean[i] = mu;
            spread[i] = sd;
        }
        Ok(())
    }

    /// Best-of-N's choice in each of `B` groups of `n` candidates: the argmax of the score for
    /// one network; for an ensemble the argmax of `mean − κ · spread`, kept only when at least
    /// `min_agreement` of the members score it above the group's first candidate (the policy's
    /// own sample), else the first candidate ([`pick_group`]).
    pub fn pick(
        &self,
        obs: &[f32],
        extras: &[&[f32]],
        t: &[u32],
        candidates: &[f32],
        n: usize,
    ) -> Result<Picks> {
        let b = t.len();
        if n == 0 {
            return Err(VerifierError::Input(
                "best-of-N needs at least one candidate per group (n = 0)".into(),
            ));
        }
        let m = batch(b, n)?;
        let Some(spec) = self.config.ensemble.as_ref().filter(|_| self.members.len() > 1) else {
            let scores = self.score_ext(obs, extras, t, candidates, n)?;
            let index = scores.chunks(n.max(1)).map(argmax).collect();
            return Ok(Picks {
                index,
                spread: vec![0.0; m],
                scores,
                fell_back: vec![false; b],
                agreement: vec![1.0; b],
            });
        };
        let k = self.members.len();
        let mut all = vec![0f32; m * k];
        self.score_members_into(obs, extras, t, candidates, n, &mut all)?;
        let mut p = Picks {
            index: Vec::with_capacity(b),
            scores: vec![0.0; m],
            spread: vec![0.0; m],
            fell_back: Vec::with_capacity(b),
            agreement: Vec::with_capacity(b),
        };
        let mut group = vec![0f32; k * n];
        for g in 0..b {
            for j in 0..k {
                group[j * n..(j + 1) * n].copy_from_slice(&all[j * m + g * n..j * m + (g + 1) * n]);
            }
            for i in 0..n {
                let (mu, sd) = mean_spread((0..k).map(|j| group[j * n + i]));
                p.scores[g * n + i] = mu;
                p.spread[g * n + i] = sd;
            }
            let (index, fell_back, agreement) = pick_group(&group, n, spec);
            p.index.push(index);
            p.fell_back.push(fell_back);
            p.agreement.push(agreement);
        }
        Ok(p)
    }

    /// Guidance gradients for `B = t.len()` chunks (`chunks` is `B * act_dim`): d log C / d chunk
    /// (classifier) or d Q / d chunk, w.r.t. the chunk as passed; an ensemble's is the members'
    /// mean scaled by their agreement ([`agree_gradients`]). Returns `B * act_dim`.
    pub fn grad(&self, obs: &[f32], t: &[u32], chunks: &[f32]) -> Result<Vec<f32>> {
        self.grad_ext(obs, &[], t, chunks)
    }

    /// [`Self::grad`] with extra inputs.
    pub fn grad_ext(&self, obs: &[f32], extras: &[&[f32]], t: &[u32], chunks: &[f32]) -> Result<Vec<f32>> {
        let mut out = vec![0f32; chunks.len()];
        self.grad_into(obs, extras, t, chunks, &mut out)?;
        Ok(out)
    }

    /// [`Self::grad_ext`] into a caller's buffer of `B * act_dim`.
    pub fn grad_into(
        &self,
        obs: &[f32],
        extras: &[&[f32]],
        t: &[u32],
        chunks: &[f32],
        out: &mut [f32],
    ) -> Result<()> {
        if let [one] = self.members.as_slice() {
            return one.grad_into(obs, extras, t, chunks, out);
        }
        let mut agreement = vec![0f32; t.len()];
        self.grad_agreement_into(obs, extras, t, chunks, out, &mut agreement)
    }

    /// [`Self::grad_into`] that also writes each row's gradient agreement `R` (1 for one
    /// network): how the push was scaled.
    pub fn grad_agreement_into(
        &self,
        obs: &[f32],
        extras: &[&[f32]],
        t: &[u32],
        chunks: &[f32],
        out: &mut [f32],
        agreement: &mut [f32],
    ) -> Result<()> {
        let (b, d) = (t.len(), self.act_dim());
        if agreement.len() != b {
            return Err(VerifierError::Input(format!(
                "agreement buffer has length {}, expected batch {b}",
                agreement.len()
            )));
        }
        let Some(spec) = self.config.ensemble.as_ref().filter(|_| self.members.len() > 1) else {
            agreement.iter_mut().for_each(|a| *a = 1.0);
            return self.members[0].grad_into(obs, extras, t, chunks, out);
        };
        let k = self.members.len();
        let mut all = vec![0f32; k * chunks.len()];
        self.grad_members_into(obs, extras, t, chunks, &mut all)?;
        if out.len() != chunks.len() {
            return Err(VerifierError::Input(format!(
                "gradient buffer has length {}, expected {}",
                out.len(),
                chunks.len()
            )));
        }
        let mut row = vec![0f32; k * d];
        for r in 0..b {
            for j in 0..k {
                let src = j * chunks.len() + r * d;
                row[j * d..(j + 1) * d].copy_from_slice(&all[src..src + d]);
            }
            agreement[r] = agree_gradients(&row, d, spec, &mut out[r * d..(r + 1) * d]);
        }
        Ok(())
    }

    /// Every member's gradient, member-major: `out` is `members * B * act_dim`.
    pub fn grad_members_into(
        &self,
        obs: &[f32],
        extras: &[&[f32]],
        t: &[u32],
        chunks: &[f32],
        out: &mut [f32],
    ) -> Result<()> {
        if Some(out.len()) != chunks.len().checked_mul(self.members.len()) {
            return Err(VerifierError::Input(format!(
                "member gradients buffer has length {}, expected members {} * {}",
                out.len(),
                self.members.len(),
                chunks.len()
            )));
        }
        for (net, o) in self.members.iter().zip(out.chunks_exact_mut(chunks.len().max(1))) {
            net.grad_into(obs, extras, t, chunks, o)?;
        }
        Ok(())
    }
}

fn batch(b: usize, n: usize) -> Result<usize> {
    b.checked_mul(n).ok_or_else(|| VerifierError::Input("batch size overflows".into()))
}
