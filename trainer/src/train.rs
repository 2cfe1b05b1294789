//! The training loop: recipe configuration, epochs over shuffled batches with AdamW, linear LR
//! decay, global-norm clipping, validation metrics each epoch, best-validation-loss selection,
//! optional early stopping, progress observer and cancellation.
//!
//! One file past 700 lines: the recipe, the loop and the per-step helpers it alone uses (the batch,
//! the dropout mask, the validation scores).

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use anyhow::{bail, ensure, Context, Result};
use candle_core::Tensor;
use rand::seq::SliceRandom;
use rand::{RngCore, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};

use crate::data::{Fitted, InputSpec, Normalization, Samples, TimeEmbedTable};
use crate::fast::{BatchSource, FastModel};
use crate::loss::{objective, objective_host, LossConfig};
use crate::metrics::{calibration, pearson, roc_auc, Calibration};
use crate::model::{Architecture, CandleModel, ExtraInput, Kind, ModelSpec, ParamSet, Variant};
use crate::optim::{clip_grad_norm, linear_factor, AdamW, AdamWConfig};
use verifier::ActionSpace;

/// Which implementation computes forward/backward during training.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum TrainBackend {
    /// The fused fast path when it supports the architecture, candle otherwise.
    #[default]
    Auto,
    /// Always the candle graph (the reference).
    Candle,
    /// The fused fast path (error if unsupported).
    Fast,
}

/// The full training recipe. Defaults are the paper's low-dim (Square) settings for the
/// contrastive classifier; see [`TrainConfig::preset`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrainConfig {
    pub kind: Kind,
    pub architecture: Architecture,
    pub optimizer: AdamWConfig,
    /// LR factor goes linearly from 1.0 to this over all optimiser steps.
    pub lr_end_factor: f64,
    pub batch_size: usize,
    pub epochs: usize,
    /// Global gradient-norm clip (<= 0 disables).
    pub grad_clip: f64,
    /// Stop after this many epochs without a better validation loss (None: run all epochs).
    pub early_stopping_patience: Option<usize>,
    pub seed: u64,
    /// Discount for the Q target `gamma^(T-t) r_T`.
    pub gamma: f64,
    /// Classifier: weight `lambda_c` of the contrastive hinge.
    pub contrastive_weight: f64,
    /// Classifier: hinge margin.
    pub contrastive_margin: f64,
    /// Classifier: `||d|| = sqrt(sum d^2 + eps)`.
    pub contrastive_eps: f64,
    /// Std of Gaussian noise added to the (standardised, layer-normed when the architecture has
    /// an input LayerNorm) observation at train time; both backends honour it.
    pub obs_noise_std: f64,
    /// In which space the action chunk is fed: the policy's normalised space (the paper's
    /// choice, the default; give the policy's normaliser `raw = x * scale + offset` so stored
    /// raw actions are mapped into it) or `standardized` (raw chunks standardised with train-set
    /// statistics, as before). Recorded in the artifact's `input.action_space`.
    pub action_space: ActionSpace,
    /// Floor of the standardisation std: a (near-)constant dimension is divided by this, not by
    /// its tiny std (which multiplied it by up to 1e6), and named in a warning.
    pub std_floor: f64,
    /// Threads for the fused path (data parallel). 1 measured fastest for the low-dim model.
    pub threads: usize,
    pub backend: TrainBackend,
    /// After the verifier, train its observation-only twin (same samples, recipe and seed; the
    /// action input held constant) and record how much the chunk adds (`metrics.final.
    /// action_sensitivity`, [`verifier::ActionSensitivity`]). Doubles training time; needs
    /// validation samples.
    pub obs_only_twin: bool,
    /// K > 1 trains an ensemble of K members on the same split (seeds `seed + k`, bootstrap
    /// resamples of the training episodes, the full set's statistics), published as one
    /// artifact (trainer/ARTIFACT.md, "Ensembles"); only the first member has the twin. 1 (the
    /// default, not written, so one network's recipe and artifact id are what they were)
    /// trains one network.
    #[serde(skip_serializing_if = "is_one")]
    pub ensemble: usize,
}

fn is_one(k: &usize) -> bool {
    *k == 1
}

/// The verifier's input spec as a recipe file may give it (see
/// [`TrainConfig::from_recipe_file`]); command-line flags override it.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RecipeInput {
    /// Observation keys in order (observation columns or layers).
    pub obs_keys: Option<Vec<String>>,
    /// `T_o`.
    pub obs_history: Option<usize>,
    /// `H`: the policy's action chunk length.
    pub chunk_len: Option<usize>,
    /// Train on steps `t % step_stride == 0`.
    pub step_stride: Option<usize>,
}

impl RecipeInput {
    const KEYS: [&'static str; 4] = ["obs_keys", "obs_history", "chunk_len", "step_stride"];
}

/// Bounds of [`TrainConfig::validate`].
pub const MAX_BATCH: usize = 65_536;
pub const MAX_EPOCHS: usize = 100_000;
pub const MAX_THREADS: usize = 256;
pub const MAX_LAYERS: usize = 16;
pub const MAX_WIDTH: usize = 16_384;
/// Elements (f32) of one layer's weights or one batch of its activations: 2^28 = 1 GiB.
pub const MAX_ELEMENTS: usize = 1 << 28;

impl Default for TrainConfig {
    fn default() -> Self {
        TrainConfig {
            kind: Kind::Classifier,
            architecture: Architecture::lowdim(),
            optimizer: AdamWConfig::default(),
            lr_end_factor: 0.01,
            batch_size: 1024,
            epochs: 200,
            grad_clip: 1.0,
            early_stopping_patience: None,
            seed: 0,
            gamma: 0.99,
            contrastive_weight: 0.1,
            contrastive_margin: 1.0,
            contrastive_eps: 1e-9,
            obs_noise_std: 0.0,
            action_space: ActionSpace::default(),
            std_floor: 1e-3,
            threads: 1,
            backend: TrainBackend::Auto,
            obs_only_twin: true,
            ensemble: 1,
        }
    }
}

impl TrainConfig {
    /// Paper presets: `Lowdim` (Square low-dim column) or `Features` (Square image column:
    /// GELU, LayerNorm, spectral norm, lr 5e-5, wd 1e-4, obs noise 0.02; Q dropout 0.1).
    pub fn preset(kind: Kind, variant: Variant) -> Self {
        let mut c = TrainConfig { kind, ..Default::default() };
        if variant == Variant::Features {
            c.architecture = Architecture::features();
            c.optimizer.lr = 5e-5;
            c.optimizer.weight_decay = 1e-4;
            c.obs_noise_std = 0.02;
            if kind == Kind::Q {
                c.architecture.dropout = 0.1;
            }
        }
        c
    }

    /// Load from a `.json` or `.toml` file (missing fields take the defaults).
    pub fn from_file(path: &Path) -> Result<Self> {
        let s = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let is_toml = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("toml"));
        let c: TrainConfig = if is_toml {
            toml::from_str(&s).with_context(|| format!("parsing {}", path.display()))?
        } else {
            serde_json::from_str(&s).with_context(|| format!("parsing {}", path.display()))?
        };
        c.validate()?;
        Ok(c)
    }

    /// Load a recipe file that may also carry the verifier's input spec (`obs_keys`,
    /// `obs_history`, `chunk_len`, `step_stride` at its top level), so one file reproduces a
    /// verifier: the training config and the input spec it was trained with.
    pub fn from_recipe_file(path: &Path) -> Result<(Self, RecipeInput)> {
        let s = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let is_toml = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("toml"));
        let v: serde_json::Value = if is_toml {
            toml::from_str(&s).with_context(|| format!("parsing {}", path.display()))?
        } else {
            serde_json::from_str(&s).with_context(|| format!("parsing {}", path.display()))?
        };
        Self::from_recipe(v).with_context(|| format!("in {}", path.display()))
    }

    /// A recipe as a JSON value (a file's contents, or a training job's `config`): the training
    /// config plus the input spec keys at its top level.
    pub fn from_recipe(mut v: serde_json::Value) -> Result<(Self, RecipeInput)> {
        let mut input = serde_json::Map::new();
        if let Some(obj) = v.as_object_mut() {
            for key in RecipeInput::KEYS {
                if let Some(x) = obj.remove(key) {
                    input.insert(key.to_string(), x);
                }
            }
        }
        let input: RecipeInput =
            serde_json::from_value(serde_json::Value::Object(input)).context("parsing the input spec")?;
        let c: TrainConfig = serde_json::from_value(v).context("parsing the training config")?;
        c.validate()?;
        Ok((c, input))
    }

    /// The loss hyper-parameters.
    pub fn loss(&self) -> LossConfig {
        LossConfig {
            contrastive_weight: self.contrastive_weight,
            contrastive_margin: self.contrastive_margin,
            contrastive_eps: self.contrastive_eps,
        }
    }

    pub fn validate(&self) -> Result<()> {
        self.architecture.validate()?;
        ensure!(self.batch_size > 0, "batch_size must be > 0");
        // Bounds: a config comes from API clients, and sizes drive memory. Far beyond any
        // verifier of the paper (widths 256-1024, batches 256-4096) and below what takes a
        // worker down.
        ensure!(self.batch_size <= MAX_BATCH, "batch_size {} is more than {MAX_BATCH}", self.batch_size);
        ensure!(
            (1..=MAX_EPOCHS).contains(&self.epochs),
            "epochs must be in 1..={MAX_EPOCHS}, got {}",
            self.epochs
        );
        ensure!(
            (1..=MAX_THREADS).contains(&self.threads),
            "threads must be in 1..={MAX_THREADS}, got {}",
            self.threads
        );
        let a = &self.architecture;
        ensure!(
            a.trunk_dims.len() <= MAX_LAYERS,
            "{} trunk layers: at most {MAX_LAYERS}",
            a.trunk_dims.len()
        );
        let widths =
            std::iter::once(a.encoder_width).chain([a.t_embed_dim]).chain(a.trunk_dims.iter().copied());
        for w in widths.clone() {
            ensure!(w <= MAX_WIDTH, "layer width {w} is more than {MAX_WIDTH}");
        }
        let widest = widths.max().unwrap_or(1);
        // Weights of the widest layer pair, and one batch of its activations, in f32 elements.
        let weights = widest.checked_mul(widest);
        let activations = self.batch_size.checked_mul(widest);
        ensure!(
            weights.is_some_and(|n| n <= MAX_ELEMENTS) && activations.is_some_and(|n| n <= MAX_ELEMENTS),
            "batch_size {} x width {widest} is too large (at most {MAX_ELEMENTS} f32 values per layer)",
            self.batch_size
        );
        ensure!(self.optimizer.lr.is_finite(), "lr must be finite");
        ensure!(self.optimizer.lr > 0.0, "lr must be > 0");
        ensure!(self.gamma > 0.0 && self.gamma <= 1.0, "gamma must be in (0, 1]");
        ensure!(self.obs_noise_std >= 0.0 && self.obs_noise_std.is_finite(), "obs_noise_std must be >= 0");
        ensure!(self.std_floor > 0.0 && self.std_floor.is_finite(), "std_floor must be > 0");
        ensure!(
            (1..=verifier::MAX_MEMBERS).contains(&self.ensemble),
            "ensemble must be in 1..={}, got {}",
            verifier::MAX_MEMBERS,
            self.ensemble
        );
        Ok(())
    }
}

/// Progress of one finished epoch.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EpochReport {
    /// 1-based.
    pub epoch: usize,
    pub epochs: usize,
    pub train_loss: f64,
    pub val_loss: Option<f64>,
    /// Classifier: AUC of the logit vs success; Q: AUC of the value vs success.
    pub val_auc: Option<f64>,
    /// Q only: Pearson correlation of the value with the discounted target on val.
    pub val_pearson: Option<f64>,
    /// LR at the end of the epoch.
    pub lr: f64,
    pub seconds: f64,
    /// This epoch's weights are the best so far (kept).
    pub best: bool,
}

/// Final metrics (stored in `config.json`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Metrics {
    pub best_epoch: usize,
    /// Best validation loss (train loss when there is no validation set).
    pub best_val_loss: Option<f64>,
    pub val_auc: Option<f64>,
    pub val_pearson: Option<f64>,
    /// Classifier only: the best epoch's calibration on the split's held-out (val) samples.
    #[serde(default)]
    pub val_calibration: Option<Calibration>,
    pub final_train_loss: f64,
    pub epochs_run: usize,
    pub early_stopped: bool,
    pub train_samples: usize,
    pub val_samples: usize,
    pub train_positive_fraction: f64,
    pub seconds: f64,
    pub samples_per_second: f64,
    pub backend: String,
    /// Data warnings (e.g. constant dimensions whose std was clamped).
    #[serde(default)]
    pub warnings: Vec<String>,
    /// How much the action chunk matters to the held-out scores, from the observation-only twin
    /// (absent when the recipe turns the twin off or there are no validation samples).
    #[serde(default)]
    pub action_sensitivity: Option<verifier::ActionSensitivity>,
}

/// The result of training: everything `artifact::write_artifact` needs.
#[derive(Clone, Debug)]
pub struct Trained {
    pub spec: ModelSpec,
    pub input: InputSpec,
    pub norm: Normalization,
    /// What the action input is (recorded in the artifact).
    pub action_space: ActionSpace,
    /// Best weights, inference-ready (spectral norm folded in).
    pub params: ParamSet,
    pub config: TrainConfig,
    pub metrics: Metrics,
    pub history: Vec<EpochReport>,
    /// An ensemble's members' best weights in member order (`params` is member 0's), with the
    /// rules the artifact records; empty for one network.
    pub members: Vec<ParamSet>,
    /// The ensemble's held-out figures (`metrics.ensemble` in the artifact); `None` for one
    /// network.
    pub ensemble: Option<crate::metrics::EnsembleMetrics>,
}

/// Error returned when the cancel flag was raised.
#[derive(Debug, thiserror::Error)]
#[error("training cancelled")]
pub struct Cancelled;

/// The model spec a config and input spec imply.
pub fn model_spec(input: &InputSpec, cfg: &TrainConfig) -> ModelSpec {
    let mut arch = cfg.architecture.clone();
    arch.t_embed_dim = input.t_embed_dim;
    arch.extra_inputs = input
        .extra_inputs
        .iter()
        .map(|e| ExtraInput { name: e.name.clone(), dim: e.dim, width: e.width })
        .collect();
    ModelSpec { kind: cfg.kind, arch, obs_dim: input.obs_dim(), act_dim: input.act_dim() }
}

enum Engine {
    Fast(Box<FastModel>),
    Candle(Box<CandleModel>),
}

/// One network (with its twin when the recipe asks): [`crate::train_samples`] for `ensemble = 1`, and
/// each member of an ensemble, whose statistics `norm` are the whole training set's.
pub(crate) fn train_one(
    tr: Samples,
    va: Samples,
    input: &InputSpec,
    cfg: &TrainConfig,
    norm: Option<&Normalization>,
    observer: &mut dyn FnMut(&EpochReport),
    cancel: Option<&AtomicBool>,
) -> Result<Trained> {
    let twin = (cfg.obs_only_twin && !va.is_empty()).then(|| (without_actions(&tr), without_actions(&va)));
    let (mut trained, full_val) = fit(tr, va, input, cfg, norm, observer, cancel)?;
    if let (Some((ttr, tva)), Some(full_val)) = (twin, full_val) {
        let start = Instant::now();
        // The twin's epochs are not the verifier's: the observer sees only the verifier's.
        let (_, twin_val) = fit(ttr, tva, input, cfg, norm, &mut |_| {}, cancel)
            .context("training the observation-only twin")?;
        if let Some(twin_val) = twin_val {
            let mut s = crate::metrics::action_sensitivity(&full_val.y, &twin_val.y, &full_val.labels, 10);
            s.twin_seconds = start.elapsed().as_secs_f64();
            if let Some(reason) = &s.reason {
                tracing::warn!("{reason}");
            }
            trained.metrics.action_sensitivity = Some(s);
        }
    }
    Ok(trained)
}

/// The samples with the action input held constant (zero raw actions): what the
/// observation-only twin trains on.
fn without_actions(s: &Samples) -> Samples {
    let mut twin = s.clone();
    twin.act.iter_mut().for_each(|a| *a = 0.0);
    twin
}

/// The best epoch's outputs on the validation samples, in the fixed validation order, with their
/// labels.
struct BestValidation {
    y: Vec<f32>,
    labels: Vec<f32>,
}

/// Trains one model on the samples; with validation samples, also returns the best epoch's
/// validation outputs.
// One function past 100 lines on purpose: the seeded stream is drawn in one fixed order (see
// `train_samples`).
#[allow(
    clippy::too_many_lines,
    reason = "the training loop draws its seeded stream in one fixed order, read top to bottom"
)]
fn fit(
    mut tr: Samples,
    mut va: Samples,
    input: &InputSpec,
    cfg: &TrainConfig,
    norm: Option<&Normalization>,
    observer: &mut dyn FnMut(&EpochReport),
    cancel: Option<&AtomicBool>,
) -> Result<(Trained, Option<BestValidation>)> {
    let start = Instant::now();
    let Prepared { spec, norm, warnings, temb } = prepare(&mut tr, &mut va, input, cfg, norm)?;

    let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
    let mut params = spec.init_params(&mut rng);
    let (mut engine, backend_name) = Engine::new(&spec, &params, cfg, &mut rng)?;

    let n = tr.len();
    let bs = cfg.batch_size;
    let steps_per_epoch = n.div_ceil(bs);
    let total_steps = (steps_per_epoch * cfg.epochs) as u64;
    let mut opt = AdamW::new(cfg.optimizer, params.values.iter().map(|v| v.len()));
    let mut dropout = DropoutMask::new(spec.arch.dropout, bs, spec.arch.z_dim());
    let noise = if cfg.obs_noise_std > 0.0 { Some(Normal::new(0.0, cfg.obs_noise_std)?) } else { None };
    let target_of = |s: &Samples| -> Vec<f32> {
        match cfg.kind {
            Kind::Classifier => s.label.clone(),
            Kind::Q => s.q_target.clone(),
        }
    };
    let tr_target = target_of(&tr);
    let va_target = target_of(&va);
    // A fixed validation order (contrastive pairs are formed within batches).
    let mut va_order: Vec<u32> = (0..va.len() as u32).collect();
    va_order.shuffle(&mut ChaCha8Rng::seed_from_u64(cfg.seed ^ 0x5eed_7a11));

    let mut perm: Vec<u32> = (0..n as u32).collect();
    let mut tgt = vec![0f32; bs];
    let mut grads = params.zeros_like();
    let mut best: Option<(f64, usize, ParamSet, EpochReport)> = None;
    // The best epoch's calibration on val (kept beside `best`, not in every epoch's report).
    let mut best_calibration: Option<Calibration> = None;
    let mut best_val_y: Option<Vec<f32>> = None;
    let mut history = Vec::new();
    let mut since_best = 0usize;
    let mut early_stopped = false;
    let mut last_train_loss = f64::NAN;
    let mut samples_seen = 0usize;

    for epoch in 1..=cfg.epochs {
        let t0 = Instant::now();
        perm.shuffle(&mut rng);
        let mut loss_sum = 0f64;
        for rows in perm.chunks(bs) {
            if cancel.is_some_and(|c| c.load(Ordering::Relaxed)) {
                return Err(Cancelled.into());
            }
            let b = rows.len();
            for (d, &i) in tgt.iter_mut().zip(rows) {
                *d = tr_target[i as usize];
            }
            let m = dropout.sample(&mut rng, b);
            // Drawn in the same order for both backends, so they train the same model.
            let obs_noise =
                noise.map(|d| (0..b * spec.obs_dim).map(|_| d.sample(&mut rng) as f32).collect::<Vec<_>>());
            let batch = Batch { samples: &tr, temb: &temb, rows, target: &tgt[..b], mask: m, obs_noise };
            let loss = engine.loss_and_grads(&params, batch, cfg, &mut grads)?;
            ensure!(loss.is_finite(), "training loss is not finite (epoch {epoch})");
            loss_sum += loss * b as f64;
            if cfg.grad_clip > 0.0 {
                clip_grad_norm(&mut grads, cfg.grad_clip);
            }
            let lr = cfg.optimizer.lr * linear_factor(opt.steps(), total_steps, 1.0, cfg.lr_end_factor);
            opt.step(&mut params.values, &grads, lr);
            if let Engine::Candle(model) = &engine {
                model.set_params(&params)?;
            }
        }
        samples_seen += n;
        last_train_loss = loss_sum / n as f64;
        let lr_now = cfg.optimizer.lr * linear_factor(opt.steps(), total_steps, 1.0, cfg.lr_end_factor);

        let (val_y, val_scores) = if va.is_empty() {
            (None, ValScores::default())
        } else {
            let (y, loss) = evaluate(&mut engine, &params, &spec, &va, &va_target, &va_order, &temb, cfg)?;
            let scores = ValScores::of(loss, &y, &va, &va_order, cfg.kind);
            (Some(y), scores)
        };
        let ValScores { loss: val_loss, auc: val_auc, pearson: val_pearson, calibration: val_calibration } =
            val_scores;
        let sel = val_loss.unwrap_or(last_train_loss);
        let is_best = best.as_ref().is_none_or(|b| sel < b.0);
        let rep = EpochReport {
            epoch,
            epochs: cfg.epochs,
            train_loss: last_train_loss,
            val_loss,
            val_auc,
            val_pearson,
            lr: lr_now,
            seconds: t0.elapsed().as_secs_f64(),
            best: is_best,
        };
        if is_best {
            let p = match &engine {
                Engine::Candle(m) if spec.arch.spectral_norm => m.inference_params()?,
                _ => params.clone(),
            };
            best = Some((sel, epoch, p, rep.clone()));
            best_calibration = val_calibration;
            best_val_y = val_y;
            since_best = 0;
        } else {
            since_best += 1;
        }
        observer(&rep);
        history.push(rep);
        if cfg.early_stopping_patience.is_some_and(|p| since_best >= p) {
            early_stopped = true;
            break;
        }
    }
    let seconds = start.elapsed().as_secs_f64();
    let Some((sel, best_epoch, best_params, best_rep)) = best else { bail!("no epoch was run (epochs = 0)") };
    let metrics = Metrics {
        best_epoch,
        best_val_loss: Some(sel),
        val_auc: best_rep.val_auc,
        val_pearson: best_rep.val_pearson,
        val_calibration: best_calibration.take(),
        final_train_loss: last_train_loss,
        epochs_run: history.len(),
        early_stopped,
        train_samples: n,
        val_samples: va.len(),
        train_positive_fraction: tr.class_counts().0 as f64 / n as f64,
        seconds,
        samples_per_second: samples_seen as f64 / seconds.max(1e-9),
        backend: backend_name.into(),
        warnings,
        action_sensitivity: None,
    };
    let best_validation = best_val_y
        .map(|y| BestValidation { y, labels: va_order.iter().map(|&i| va.label[i as usize]).collect() });
    let trained = Trained {
        spec,
        input: input.clone(),
        norm,
        action_space: cfg.action_space.clone(),
        params: best_params,
        config: cfg.clone(),
        metrics,
        history,
        members: Vec::new(),
        ensemble: None,
    };
    Ok((trained, best_validation))
}

/// What training needs before its first draw: the model's spec, the normalization fitted on the
/// training samples (applied to both sets, actions moved into the verifier's input space) and
/// the time-embedding table covering every step.
struct Prepared {
    spec: ModelSpec,
    norm: Normalization,
    warnings: Vec<String>,
    temb: TimeEmbedTable,
}

fn prepare(
    tr: &mut Samples,
    va: &mut Samples,
    input: &InputSpec,
    cfg: &TrainConfig,
    fixed: Option<&Normalization>,
) -> Result<Prepared> {
    cfg.validate()?;
    let spec = model_spec(input, cfg);
    spec.arch.validate()?;
    ensure!(!tr.is_empty(), "no training samples");
    ensure!(
        tr.obs_dim == spec.obs_dim && tr.act_dim == spec.act_dim,
        "sample dims do not match the input spec"
    );
    cfg.action_space.validate(input.action_dim)?;
    // Actions: into the policy's space (the paper), or standardised raw chunks (older recipe).
    let standardize_actions = !cfg.action_space.is_policy();
    cfg.action_space.raw_to_input(&mut tr.act, input.action_dim);
    cfg.action_space.raw_to_input(&mut va.act, input.action_dim);
    let Fitted { norm, warnings } = match fixed {
        Some(n) => Fitted { norm: n.clone(), warnings: Vec::new() },
        None => Normalization::fit(tr, input, standardize_actions, cfg.std_floor as f32),
    };
    for w in &warnings {
        tracing::warn!("{w}");
    }
    norm.apply(&mut tr.obs, &mut tr.act);
    norm.apply(&mut va.obs, &mut va.act);
    let mut temb = TimeEmbedTable::new(spec.arch.t_embed_dim);
    let max_t = tr.t.iter().chain(&va.t).copied().max().unwrap_or(0);
    temb.ensure(max_t);

    Ok(Prepared { spec, norm, warnings, temb })
}

/// One training batch: rows of the samples, their targets and the step's random draws.
struct Batch<'a> {
    samples: &'a Samples,
    temb: &'a TimeEmbedTable,
    rows: &'a [u32],
    target: &'a [f32],
    mask: Option<&'a [f32]>,
    obs_noise: Option<Vec<f32>>,
}

impl Engine {
    /// The batch's loss, its gradients written into `grads`.
    fn loss_and_grads(
        &mut self,
        params: &ParamSet,
        b: Batch<'_>,
        cfg: &TrainConfig,
        grads: &mut [Vec<f32>],
    ) -> Result<f64> {
        Ok(match self {
            Engine::Fast(f) => {
                let src =
                    BatchSource { obs: &b.samples.obs, act: &b.samples.act, t: &b.samples.t, temb: b.temb };
                let l = f.loss_and_grads(
                    params,
                    &src,
                    b.rows,
                    b.target,
                    b.mask,
                    b.obs_noise.as_deref(),
                    cfg.kind,
                    &cfg.loss(),
                );
                for (g, s) in grads.iter_mut().zip(&f.grads) {
                    g.copy_from_slice(s);
                }
                l
            }
            Engine::Candle(model) => candle_step(model, b, cfg, grads)?,
        })
    }

    /// The backend `cfg` asks for (`auto`: the fast one where it supports the architecture), and
    /// its name for the metrics.
    fn new(
        spec: &ModelSpec,
        params: &ParamSet,
        cfg: &TrainConfig,
        rng: &mut ChaCha8Rng,
    ) -> Result<(Engine, &'static str)> {
        let use_fast = match cfg.backend {
            TrainBackend::Candle => false,
            TrainBackend::Fast => {
                ensure!(crate::fast::supports(spec), "backend \"fast\" does not support this architecture");
                true
            }
            TrainBackend::Auto => crate::fast::supports(spec),
        };
        Ok(if use_fast {
            (
                Engine::Fast(Box::new(FastModel::new(spec, params, cfg.batch_size, cfg.threads.max(1))?)),
                "fast",
            )
        } else {
            (Engine::Candle(Box::new(CandleModel::new(spec, params, rng)?)), "candle")
        })
    }
}

/// The penultimate layer's dropout masks, drawn from the training's seeded stream so both
/// backends train the same model.
struct DropoutMask {
    p: f64,
    keep_scale: f32,
    /// A unit is dropped when its 16-bit uniform is below this (probability resolution 2^-16).
    threshold: u32,
    width: usize,
    mask: Vec<f32>,
    bytes: Vec<u8>,
}

impl DropoutMask {
    fn new(p: f64, batch: usize, width: usize) -> DropoutMask {
        DropoutMask {
            p,
            keep_scale: (1.0 / (1.0 - p)) as f32,
            threshold: (p * 65536.0).round() as u32,
            width,
            mask: vec![0f32; batch * width],
            bytes: vec![0u8; 2 * batch * width],
        }
    }

    /// A mask for `rows` rows (scaled by 1/(1-p) where kept), or `None` without dropout.
    fn sample(&mut self, rng: &mut ChaCha8Rng, rows: usize) -> Option<&[f32]> {
        if self.p <= 0.0 {
            return None;
        }
        let n = rows * self.width;
        // 16-bit little-endian uniforms from the seeded stream.
        let bytes = &mut self.bytes[..2 * n];
        rng.fill_bytes(bytes);
        for (v, h) in self.mask[..n].iter_mut().zip(bytes.chunks_exact(2)) {
            let u = u16::from_le_bytes([h[0], h[1]]) as u32;
            *v = if u < self.threshold { 0.0 } else { self.keep_scale };
        }
        Some(&self.mask[..n])
    }
}

/// One epoch's scores on the validation samples.
#[derive(Default)]
struct ValScores {
    loss: Option<f64>,
    auc: Option<f64>,
    /// Q-function: correlation of the predictions with the discounted targets.
    pearson: Option<f64>,
    /// Classifier: reliability of the predicted probabilities.
    calibration: Option<Calibration>,
}

impl ValScores {
    /// From the model's outputs `y` (logits or values) on `va` in `order`, and its `loss`.
    fn of(loss: f64, y: &[f32], va: &Samples, order: &[u32], kind: Kind) -> ValScores {
        let labels: Vec<f32> = order.iter().map(|&i| va.label[i as usize]).collect();
        let pearson = match kind {
            Kind::Q => pearson(y, &order.iter().map(|&i| va.q_target[i as usize]).collect::<Vec<f32>>()),
            Kind::Classifier => None,
        };
        let calibration = match kind {
            Kind::Classifier => {
                let p: Vec<f64> = y.iter().map(|&l| 1.0 / (1.0 + (-(l as f64)).exp())).collect();
                calibration(&p, &labels, 10)
            }
            Kind::Q => None,
        };
        ValScores { loss: Some(loss), auc: roc_auc(y, &labels), pearson, calibration }
    }
}

fn candle_step(
    model: &CandleModel,
    batch: Batch<'_>,
    cfg: &TrainConfig,
    grads: &mut [Vec<f32>],
) -> Result<f64> {
    let Batch { samples, temb, rows, target, mask, obs_noise } = batch;
    let b = rows.len();
    model.power_iteration(1)?;
    let bt = gather_tensors(model, samples, temb, rows)?;
    let zdim = model.spec.arch.z_dim();
    let dev = model.device();
    let noise = crate::model::TrainNoise {
        drop_mask: mask.map(|m| Tensor::from_slice(m, (b, zdim), dev)).transpose()?,
        obs_noise: obs_noise.map(|v| Tensor::from_vec(v, (b, model.spec.obs_dim), dev)).transpose()?,
    };
    let (y, z) = model.forward(&bt, &noise)?;
    let loss = objective(model.spec.kind, &y, &z, target, &cfg.loss())?;
    let gs = loss.backward()?;
    for (g, v) in grads.iter_mut().zip(model.vars()) {
        match gs.get(v.as_tensor()) {
            Some(t) => g.copy_from_slice(&t.flatten_all()?.to_vec1::<f32>()?),
            None => g.iter_mut().for_each(|x| *x = 0.0),
        }
    }
    Ok(loss.to_scalar::<f32>()? as f64)
}

/// Gather rows of (standardised) samples into batch tensors.
pub fn gather_tensors(
    model: &CandleModel,
    s: &Samples,
    temb: &TimeEmbedTable,
    rows: &[u32],
) -> Result<crate::model::BatchTensors> {
    let (od, ad) = (s.obs_dim, s.act_dim);
    let te = model.spec.arch.t_embed_dim;
    let b = rows.len();
    let mut obs = Vec::with_capacity(b * od);
    let mut act = Vec::with_capacity(b * ad);
    let mut tv = Vec::with_capacity(b * te);
    let mut extras: Vec<Vec<f32>> = vec![Vec::new(); s.extras.len()];
    for &i in rows {
        let i = i as usize;
        obs.extend_from_slice(&s.obs[i * od..(i + 1) * od]);
        act.extend_from_slice(&s.act[i * ad..(i + 1) * ad]);
        tv.extend_from_slice(temb.get(s.t[i]));
        for (e, (dst, src)) in model.spec.arch.extra_inputs.iter().zip(extras.iter_mut().zip(&s.extras)) {
            dst.extend_from_slice(&src[i * e.dim..(i + 1) * e.dim]);
        }
    }
    let ex: Vec<&[f32]> = extras.iter().map(|v| v.as_slice()).collect();
    model.batch_tensors(b, &obs, &act, &tv, &ex)
}

/// Eval-mode predictions over `order` in batches of `batch_size`; returns (y in `order`, mean loss).
#[allow(clippy::too_many_arguments)]
fn evaluate(
    engine: &mut Engine,
    params: &ParamSet,
    spec: &ModelSpec,
    va: &Samples,
    target: &[f32],
    order: &[u32],
    temb: &TimeEmbedTable,
    cfg: &TrainConfig,
) -> Result<(Vec<f32>, f64)> {
    let zdim = spec.arch.z_dim();
    let mut ys = Vec::with_capacity(order.len());
    let mut loss = 0f64;
    for rows in order.chunks(cfg.batch_size) {
        let t: Vec<f32> = rows.iter().map(|&i| target[i as usize]).collect();
        let (y, z): (Vec<f32>, Vec<f32>) = match engine {
            Engine::Fast(f) => {
                let src = BatchSource { obs: &va.obs, act: &va.act, t: &va.t, temb };
                f.forward(params, &src, rows, None, None);
                (f.y()[..rows.len()].to_vec(), f.z()[..rows.len() * zdim].to_vec())
            }
            Engine::Candle(m) => {
                let bt = gather_tensors(m, va, temb, rows)?;
                let (y, z) = m.forward(&bt, &Default::default())?;
                (y.to_vec1::<f32>()?, z.flatten_all()?.to_vec1::<f32>()?)
            }
        };
        loss += objective_host(spec.kind, &y, &z, zdim, &t, &cfg.loss(), None) * rows.len() as f64;
        ys.extend_from_slice(&y);
    }
    Ok((ys, loss / order.len().max(1) as f64))
}
