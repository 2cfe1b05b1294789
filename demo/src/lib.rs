//! `demo`: the paper's pedagogical experiment, end to end, through the real store.
//!
//! It owns only the orchestration of `ufops demo`: train the base policy (sim), evaluate it and
//! ingest its rollouts as checkpoint `nav-dp/base` (store), freeze an on-policy split and train a
//! classifier and a time-to-success verifier (trainer), steer the unchanged base policy with them
//! (steer: best-of-N and guidance), repeat with an off-policy verifier for the ablation, and write
//! the report (`report.md`, `report.json`, `trajectories.png`).

pub mod diagnose;
mod report;
pub mod review_campaign;

pub use report::{MonitorSummary, Report, Row, SteeringQuality, SteeringQualityRow};

use anyhow::{Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use sim::{rollout, ChunkChoice, ChunkPolicy, DiffusionPolicy, EnvConfig, FlowPolicy, PolicyConfig};
use std::path::{Path, PathBuf};
use std::time::Instant;
use store::{EpisodeInput, Label, RunInput, SourceInput, Steering, Store, VectorColumn};
use store_artifacts::{Artifacts, Monitors};
use store_compare::Scoreboards;

pub const POLICY: &str = "nav-dp";
pub const BASE: &str = "base";
pub const ALT: &str = "alt";
/// The checkpoint the flow-matching twin's rollouts are stored under (another policy network,
/// trained on the same demonstrations).
pub const FLOW: &str = "flow-twin";

/// A run of the demo: its name, steering and artifact, and tags.
fn demo_run(name: &str, steering: Steering, artifact: Option<&str>, tags: &[&str]) -> RunInput {
    RunInput {
        name: name.to_string(),
        steering,
        artifact_id: artifact.map(str::to_string),
        tags: tags.iter().map(|t| t.to_string()).collect(),
    }
}

/// A λ as a run name shows it (`0.1`, `3`).
fn lambda_name(l: f32) -> String {
    format!("{l}")
}

/// The λ of a run's steering: the decimal the sweep was given (0.1, not 0.10000000149).
fn lambda_f64(l: f32) -> f64 {
    lambda_name(l).parse().unwrap_or(f64::from(l))
}

/// The scale of a demo run.
#[derive(Debug, Clone)]
pub struct DemoConfig {
    pub episodes: usize,
    pub demos: usize,
    pub policy_steps: usize,
    pub verifier_epochs: usize,
    pub bon_n: Vec<usize>,
    pub lambdas: Vec<f32>,
    /// The verifier's learning curve: on-policy classifiers trained on seeded samples of this many
    /// rollouts (nested), each steering one best-of-N row (the full set is the main row).
    pub ablation_sizes: Vec<usize>,
    /// Verifier training stops after this many epochs without a better validation loss; `None`
    /// trains every epoch. Either way the best-validation checkpoint is kept.
    pub early_stopping_patience: Option<usize>,
    /// Also train every verifier of the ensemble rows as an ensemble of this many members and
    /// steer the rows where one verifier helps and where it hurts with it (`ufops demo
    /// --ensemble K`; the report's "Ensembles" table).
    pub ensemble: Option<usize>,
    pub seed: u64,
    pub out_dir: PathBuf,
}

impl DemoConfig {
    /// The full demo: 1000 rollouts per row.
    pub fn full(out_dir: &Path) -> Self {
        DemoConfig {
            episodes: 1000,
            demos: 100,
            policy_steps: 1500,
            verifier_epochs: 200,
            bon_n: vec![30, 10],
            // A sweep from the paper's 0.1 up: the useful strength depends on the verifier's
            // gradient scale, and the report shows where each verifier helps and where it breaks.
            lambdas: vec![0.1, 0.3, 1.0, 3.0, 10.0],
            ablation_sizes: vec![100, 250, 500],
            // The paper's low-dimensional recipe: 200 epochs, the best-validation checkpoint.
            early_stopping_patience: None,
            ensemble: None,
            seed: 0,
            out_dir: out_dir.to_path_buf(),
        }
    }
    /// `--quick`: the same loop at a scale that finishes in about a minute.
    pub fn quick(out_dir: &Path) -> Self {
        DemoConfig {
            episodes: 200,
            demos: 60,
            policy_steps: 800,
            verifier_epochs: 40,
            bon_n: vec![10],
            lambdas: vec![3.0],
            ablation_sizes: vec![50],
            early_stopping_patience: Some(10),
            ..Self::full(out_dir)
        }
    }
}

fn stage(msg: &str) -> ProgressBar {
    let pb = if std::io::IsTerminal::is_terminal(&std::io::stderr()) {
        let pb = ProgressBar::new_spinner();
        pb.set_style(ProgressStyle::with_template("{spinner} [{elapsed:>4}] {msg}").expect("valid template"));
        pb.enable_steady_tick(std::time::Duration::from_millis(120));
        pb
    } else {
        eprintln!("demo: {msg}");
        ProgressBar::hidden()
    };
    pb.set_message(msg.to_string());
    pb
}

/// The rollouts of a policy as store episodes: obs `pos` (2), `action` (2), the executed chunk.
/// `pair_key` names the initial condition (the seed that drew the starts and the noise, and the
/// episode's index): rows rolled out with the same seed pair up in `ufops compare`.
fn to_episodes(eps: &[sim::Episode], horizon: usize, seed: u64) -> Vec<EpisodeInput> {
    eps.iter()
        .enumerate()
        .map(|(i, e)| {
            let n = e.length;
            EpisodeInput {
                source_name: format!("rollout_{i}"),
                source_index: i as u32,
                task: Some("two-gap-navigation".into()),
                label: if e.success { Label::Success } else { Label::Failure },
                label_source: "sim".into(),
                tags: vec![format!("{:?}", e.outcome).to_lowercase()],
                metadata: serde_json::json!({
                    "gap": e.gap.map(|g| format!("{g:?}").to_lowercase()),
                    "pair_key": format!("seed{seed}/{i}"),
                }),
                timestamps: (0..n).map(|t| t as f64 * 0.1).collect(),
                observations: vec![VectorColumn {
                    name: "pos".into(),
                    dim: 2,
                    values: e.positions[..n].iter().flatten().copied().collect(),
                }],
                action: VectorColumn {
                    name: "action".into(),
                    dim: 2,
                    values: e.actions.iter().flatten().copied().collect(),
                },
                reward: (0..n).map(|t| if e.success && t + 1 == n { 1.0 } else { 0.0 }).collect(),
                done: (0..n).map(|t| t + 1 == n).collect(),
                action_chunk: Some(store::ChunkColumn {
                    horizon,
                    action_dim: 2,
                    values: e.action_chunks.iter().flatten().copied().collect(),
                }),
                images: vec![],
                media: vec![],
                flags: Default::default(),
            }
        })
        .collect()
}

/// Ingests rollouts as one version of `run` (or finds the version that already holds the same
/// rollouts), with each episode's steering telemetry when it logged any.
pub async fn ingest_rollouts(
    store: &Store,
    eps: &[sim::Episode],
    checkpoint: &str,
    run: RunInput,
    horizon: usize,
    seed: u64,
) -> Result<i64> {
    let inputs = to_episodes(eps, horizon, seed);
    // The run's name too: two runs whose rollouts happened to be identical stay two sources.
    let mut bytes = run.name.as_bytes().to_vec();
    for e in &inputs {
        for v in e.observations[0].values.iter().chain(&e.action.values) {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
        bytes.push(u8::from(e.label == Label::Success));
    }
    let source = SourceInput {
        path: format!("sim://{POLICY}/{checkpoint}?seed={seed}&run={}", run.name),
        sha256: store::sha256_hex(&bytes),
        format: "sim".into(),
        size_bytes: bytes.len() as u64,
        metadata: serde_json::json!({ "env": "two-gap-navigation", "seed": seed, "episodes": eps.len() }),
    };
    let mut w = match store.begin_ingest(source, POLICY, checkpoint).await {
        Ok(w) => w,
        Err(store::StoreError::AlreadyIngested { version, .. }) => return Ok(version),
        Err(e) => return Err(e.into()),
    };
    w.set_run(run)?;
    for (e, sim_ep) in inputs.into_iter().zip(eps) {
        if sim_ep.steering.is_empty() {
            w.add_episode(e).await?;
        } else {
            // The best-of-N steps it logged travel with it as the steps' steering column.
            let steering = verifier::steps::steering_array(&sim_ep.steering, e.len())?;
            w.add_episode_steered(e, steering).await?;
        }
    }
    Ok(w.commit(&format!("demo rollouts of {POLICY}/{checkpoint}")).await?.version)
}

/// One row of the report: its rates go into the report, its rollouts into the store as `run` of
/// `checkpoint` (so `ufops scoreboard` gives the row back from the store alone).
#[allow(clippy::too_many_arguments)]
async fn record(
    store: &Store,
    report: &mut Report,
    eps: &[sim::Episode],
    checkpoint: &str,
    run: RunInput,
    method: &str,
    verifier: &str,
    horizon: usize,
    seed: u64,
) -> Result<()> {
    report.add(method, verifier, checkpoint, &run.name, eps);
    ingest_rollouts(store, eps, checkpoint, run, horizon, seed).await?;
    Ok(())
}

/// Trains one verifier (or an ensemble of `ensemble` members) on a split and loads it through
/// its published artifact (sha256-checked).
#[allow(clippy::too_many_arguments)] // the recipe's parts, each set by the demo's step
async fn train_verifier(
    store: &Store,
    split_id: &str,
    kind: trainer::Kind,
    cfg: &DemoConfig,
    stride: usize,
    action_space: &trainer::ActionSpace,
    artifacts_dir: &Path,
    ensemble: Option<usize>,
) -> Result<(store_artifacts::ArtifactRecord, steer::Verifier)> {
    // The verifier takes chunks in the policy's normalised space (velocity / max_speed), as in
    // the paper; the stored rollouts hold raw velocities, so the trainer gets the normaliser.
    let mut tc = trainer::TrainConfig {
        kind,
        epochs: cfg.verifier_epochs,
        seed: cfg.seed,
        action_space: action_space.clone(),
        ..Default::default()
    };
    tc.early_stopping_patience = cfg.early_stopping_patience;
    let spec = trainer::TrainJobSpec {
        split_id: split_id.to_string(),
        kind,
        config: Some(tc),
        obs_keys: Some(vec!["pos".into()]),
        obs_history: Some(2),
        chunk_len: None,
        step_stride: Some(stride),
        ensemble,
    };
    let what = ensemble.map_or(format!("{kind:?} verifier"), |k| format!("{kind:?} ensemble of {k}"));
    let pb = stage(&format!("training the {what} on {split_id}"));
    let pb2 = pb.clone();
    let observer = Box::new(move |r: &trainer::EpochReport| {
        pb2.set_message(format!(
            "training {kind:?}: epoch {}/{} train {:.4} val {:.4}{}",
            r.epoch,
            r.epochs,
            r.train_loss,
            r.val_loss.unwrap_or(f64::NAN),
            r.val_auc.map(|a| format!(" auc {a:.3}")).unwrap_or_default()
        ))
    });
    let rec = trainer::run_train_job(store, &spec, None, observer, None).await?;
    pb.finish_and_clear();
    let dir = artifacts_dir.join(&rec.id);
    store.download_artifact(&rec.id, &dir).await?;
    let v = steer::Verifier::load_dir(&dir).with_context(|| format!("loading artifact {}", rec.id))?;
    Ok((rec, v))
}

/// Runs the whole experiment and writes the report into `cfg.out_dir`.
// Past 100 lines on purpose: the paper's experiment step by step (rollouts, labels, splits,
// training, steered evaluations, report), in the order the README tells it.
#[allow(clippy::too_many_lines, reason = "the experiment end to end, in the order its report prints")]
pub async fn run(store: &Store, cfg: &DemoConfig) -> Result<Report> {
    let t0 = Instant::now();
    let env = EnvConfig::default();
    let pc = PolicyConfig::default();
    let n = cfg.episodes;
    std::fs::create_dir_all(&cfg.out_dir)?;

    // 1. Base policy (DDPM) and its flow-matching twin, trained on expert demos, stopped early.
    let pb = stage("training the base diffusion policy and its flow twin on expert demonstrations");
    let demos = sim::expert_demos(&env, cfg.demos, cfg.seed);
    let tc = sim::PolicyTrainConfig { steps: cfg.policy_steps, seed: cfg.seed, ..Default::default() };
    let (base, flow) = tokio::task::block_in_place(|| -> Result<_> {
        Ok((DiffusionPolicy::train(&pc, &tc, &demos)?, FlowPolicy::train(&pc, &tc, &demos)?))
    })?;
    // A second, differently trained checkpoint for the off-policy ablation: trained on demos that
    // all take the wide gap, so its rollouts cover a different part of the state-action space.
    let alt_demos: Vec<sim::Demo> =
        sim::expert_demos(&env, 2 * cfg.demos, cfg.seed + 1).into_iter().filter(|d| d.wide).collect();
    let alt_tc = sim::PolicyTrainConfig { steps: cfg.policy_steps * 2, seed: cfg.seed + 1, ..tc.clone() };
    let alt = tokio::task::block_in_place(|| DiffusionPolicy::train(&pc, &alt_tc, &alt_demos))?;
    base.save(&cfg.out_dir.join("policies/base"))?;
    alt.save(&cfg.out_dir.join("policies/alt"))?;
    pb.finish_and_clear();

    let eval = |p: &dyn ChunkPolicy, s: ChunkChoice, label: &str, seed: u64| -> Result<Vec<sim::Episode>> {
        let pb = stage(&format!("{label}: {n} rollouts"));
        let r = tokio::task::block_in_place(|| rollout(p, &env, n, s, seed));
        pb.finish_and_clear();
        r
    };

    // 2. Evaluate the base policy and ingest its rollouts (success from the simulator).
    let base_eps = eval(&base, ChunkChoice::None, "evaluating the base policy", cfg.seed + 100)?;
    let base_run = || demo_run(BASE, Steering::Base, None, &[]);
    let v_base = ingest_rollouts(store, &base_eps, BASE, base_run(), pc.horizon, cfg.seed + 100).await?;
    let alt_eps = eval(&alt, sim::ChunkChoice::None, "evaluating the alt checkpoint", cfg.seed + 200)?;
    let v_alt = ingest_rollouts(store, &alt_eps, ALT, base_run(), pc.horizon, cfg.seed + 200).await?;

    // 3. On-policy split; classifier and Q verifiers. Off-policy: a classifier on alt's rollouts.
    let split_req = |off: Vec<(String, String)>| store::SplitRequest {
        policy: POLICY.into(),
        checkpoint: BASE.into(),
        version: None,
        off_policy_from: off,
        val_fraction: 0.2,
        seed: cfg.seed,
        actor: "demo".into(),
        max_episodes: None,
    };
    let on_split = store.create_split(&split_req(vec![])).await?;
    let off_split = store.create_split(&split_req(vec![(POLICY.into(), ALT.into())])).await?;
    let art_dir = cfg.out_dir.join("artifacts");
    let stride = pc.n_exec;
    let norm = pc.action_normalizer();
    let space = trainer::ActionSpace::policy(norm.scale.clone(), norm.offset.clone());
    let (c_rec, clf) =
        train_verifier(store, &on_split.id, trainer::Kind::Classifier, cfg, stride, &space, &art_dir, None)
            .await?;
    let (q_rec, q) =
        train_verifier(store, &on_split.id, trainer::Kind::Q, cfg, stride, &space, &art_dir, None).await?;
    let (off_rec, off_clf) =
        train_verifier(store, &off_split.id, trainer::Kind::Classifier, cfg, stride, &space, &art_dir, None)
            .await?;

    // 4. Steer the unchanged base policy. Common random numbers: every row of the base policy (and
    // the flow twin) faces the base rollouts' starts and environment noise (`crn`, the base
    // seed), so rows pair by initial condition (`pair_key`) and `ufops compare` needs fewer
    // rollouts; rows are positively correlated, which makes the report's Newcombe intervals (for
    // independent rows) conservative.
    let crn = cfg.seed + 100;
    let mut report = Report::new(&base_eps);
    report.meta = serde_json::json!({
        "episodes_per_row": n,
        "store_versions": { "base": v_base, "alt": v_alt },
        "splits": { "on_policy": on_split.id, "off_policy": off_split.id },
        "artifacts": { "classifier": c_rec.id, "q": q_rec.id, "off_policy_classifier": off_rec.id },
        "verifier_metrics": { "classifier": c_rec.config["metrics"]["final"], "q": q_rec.config["metrics"]["final"],
                              "off_policy_classifier": off_rec.config["metrics"]["final"] },
        "alt_checkpoint_success": sim::success_rate(&alt_eps).2,
        "fast_path": clf.backend_name(),
    });
    let mut keep_for_plot = None;
    // Every best-of-N run of the base policy with its verifier: the report ranks the verifiers'
    // figures against the gains.
    let mut bon_runs: Vec<(String, u32, store_artifacts::ArtifactRecord)> = Vec::new();
    let verifiers: [(&str, &steer::Verifier); 2] = [("C", &clf), ("Q", &q)];
    let record_of = |name: &str| if name == "C" { &c_rec } else { &q_rec };
    let artifact_of = |name: &str| record_of(name).id.as_str();
    for (name, v) in verifiers {
        let label = format!("base (DDPM), scored by {name}");
        report.diagnostics.push(diagnose::run_diagnostics(&label, &base_eps, v, &norm, env.max_speed, None)?);
    }
    for (name, v) in verifiers {
        for &nn in &cfg.bon_n {
            let label = format!("{name} x BoN (N={nn})");
            // Recorded: every best-of-N step's candidates, scores and choice go into the store with
            // the episode, for the replays below (`ufops replay`).
            let eps = eval(&base, ChunkChoice::RecordedBestOfN { scorer: v, n: nn }, &label, crn)?;
            let r = demo_run(
                &format!("{}-bon{nn}", name.to_lowercase()),
                Steering::Bon { n: nn as u32 },
                Some(artifact_of(name)),
                &["on-policy"],
            );
            bon_runs.push((r.name.clone(), nn as u32, record_of(name).clone()));
            record(store, &mut report, &eps, BASE, r, &label, "on-policy", pc.horizon, crn).await?;
            report.diagnostics.push(diagnose::run_diagnostics(&label, &eps, v, &norm, env.max_speed, None)?);
            if name == "C" && keep_for_plot.is_none() {
                keep_for_plot = Some(eps);
            }
        }
    }
    for (name, v) in verifiers {
        for &lambda in &cfg.lambdas {
            let label = format!("{name} x CG (lambda={lambda})");
            // Every guided row records what guidance did to x̂0 per denoising step (the report's
            // diagnostics table explains a collapse or a gain from them).
            let trace = diagnose::TracingScorer::new(v, pc.diffusion_steps, lambda);
            let eps = eval(&base, ChunkChoice::Guided { scorer: &trace, lambda }, &label, crn)?;
            let r = demo_run(
                &format!("{}-cg{}", name.to_lowercase(), lambda_name(lambda)),
                Steering::Cg { lambda: lambda_f64(lambda) },
                Some(artifact_of(name)),
                &["on-policy"],
            );
            record(store, &mut report, &eps, BASE, r, &label, "on-policy", pc.horizon, crn).await?;
            report.diagnostics.push(diagnose::run_diagnostics(
                &label,
                &eps,
                v,
                &norm,
                env.max_speed,
                Some(&trace),
            )?);
        }
    }
    // Flow twin: same verifier, guidance from the second Euler step on.
    let flow_base = eval(&flow, ChunkChoice::None, "flow twin, unsteered", crn)?;
    let r = demo_run(BASE, Steering::Base, None, &[]);
    record(store, &mut report, &flow_base, FLOW, r, "flow twin, unsteered", "-", pc.horizon, crn).await?;
    let nn = cfg.bon_n[0];
    let eps = eval(&flow, ChunkChoice::BestOfN { scorer: &clf, n: nn }, "flow twin, C x BoN", crn)?;
    let r = demo_run(
        &format!("c-bon{nn}"),
        Steering::Bon { n: nn as u32 },
        Some(&c_rec.id),
        &["on-policy", "ddpm-rollouts"],
    );
    let label = format!("flow twin, C x BoN (N={nn})");
    record(store, &mut report, &eps, FLOW, r, &label, "on-policy (DDPM rollouts)", pc.horizon, crn).await?;
    // 6. Off-policy ablation: the verifier trained on the alt checkpoint's rollouts.
    let eps =
        eval(&base, ChunkChoice::RecordedBestOfN { scorer: &off_clf, n: nn }, "off-policy C x BoN", crn)?;
    let r = demo_run(
        &format!("off-c-bon{nn}"),
        Steering::Bon { n: nn as u32 },
        Some(&off_rec.id),
        &["off-policy"],
    );
    let label = format!("C x BoN (N={nn})");
    bon_runs.push((r.name.clone(), nn as u32, off_rec.clone()));
    record(store, &mut report, &eps, BASE, r, &label, "off-policy (alt rollouts)", pc.horizon, crn).await?;
    let lambda = cfg.lambdas[cfg.lambdas.len() / 2];
    let eps = eval(&base, ChunkChoice::Guided { scorer: &off_clf, lambda }, "off-policy C x CG", crn)?;
    let r = demo_run(
        &format!("off-c-cg{}", lambda_name(lambda)),
        Steering::Cg { lambda: lambda_f64(lambda) },
        Some(&off_rec.id),
        &["off-policy"],
    );
    let label = format!("C x CG (lambda={lambda})");
    record(store, &mut report, &eps, BASE, r, &label, "off-policy (alt rollouts)", pc.horizon, crn).await?;

    // 7. The verifier's learning curve: classifiers on nested samples of the on-policy rollouts.
    let nn_ablation = cfg.bon_n.iter().copied().min().unwrap_or(10);
    for &size in cfg.ablation_sizes.iter().filter(|&&s| s < n) {
        let split = store
            .create_split(&store::SplitRequest { max_episodes: Some(size as u64), ..split_req(vec![]) })
            .await?;
        let (rec, v) =
            train_verifier(store, &split.id, trainer::Kind::Classifier, cfg, stride, &space, &art_dir, None)
                .await?;
        let label = format!("C x BoN (N={nn_ablation})");
        let eps = eval(
            &base,
            ChunkChoice::BestOfN { scorer: &v, n: nn_ablation },
            &format!("{label}, {size} rollouts"),
            crn,
        )?;
        let tag = format!("trained-on-{size}");
        let r = demo_run(
            &format!("c-bon{nn_ablation}-n{size}"),
            Steering::Bon { n: nn_ablation as u32 },
            Some(&rec.id),
            &["on-policy", tag.as_str()],
        );
        bon_runs.push((r.name.clone(), nn_ablation as u32, rec.clone()));
        record(
            store,
            &mut report,
            &eps,
            BASE,
            r,
            &label,
            &format!("on-policy, {size} rollouts"),
            pc.horizon,
            crn,
        )
        .await?;
    }

    report.steering_quality = Some(report::SteeringQuality::new(&report.rows, &bon_runs));

    // Counterfactual replays of the logged best-of-N steps (the store's steering column): the
    // same verifier and N must reproduce every choice; then a smaller N, the other verifier, and
    // the on-policy verifier on the off-policy run's steps.
    let pb = stage("replaying the logged best-of-N steps");
    let n0 = cfg.bon_n[0];
    let main_run = format!("c-bon{n0}");
    let small_n = cfg.bon_n.iter().copied().filter(|&k| k < n0).min();
    let mut questions: Vec<(String, String, &steer::Verifier, &str, Option<usize>)> = vec![(
        format!("does replay reproduce the logged choices (C, N={n0})?"),
        main_run.clone(),
        &clf,
        c_rec.id.as_str(),
        None,
    )];
    if let Some(k) = small_n {
        questions.push((
            format!("would N={k} have sufficed?"),
            main_run.clone(),
            &clf,
            c_rec.id.as_str(),
            Some(k),
        ));
    }
    questions.push((
        "would Q have picked differently?".into(),
        main_run.clone(),
        &q,
        q_rec.id.as_str(),
        None,
    ));
    questions.push((
        "would the on-policy C have picked differently from the off-policy one?".into(),
        format!("off-c-bon{n0}"),
        &clf,
        c_rec.id.as_str(),
        None,
    ));
    for (question, run, v, artifact, k) in questions {
        let spec = replay::ReplaySpec {
            run: run.clone(),
            policy: Some(POLICY.into()),
            checkpoint: Some(BASE.into()),
            n: k,
            ..Default::default()
        };
        let r = replay::replay(store, v, artifact, &spec).await?;
        report.replays.push(report::ReplayRow { question, run, report: r });
    }
    pb.finish_and_clear();
    let exact = &report.replays[0].report;
    anyhow::ensure!(
        exact.changed == 0 && exact.max_score_difference == Some(0.0),
        "replaying {main_run} with its own verifier and N changed {} of {} choices (largest score difference {:?})",
        exact.changed,
        exact.steps,
        exact.max_score_difference
    );

    // 8. Ensembles (`--ensemble K`): the same recipes as K members each, on the rows where one
    // verifier helps (on-policy C x BoN) and where it hurts (off-policy C x BoN, CG at the
    // largest strength), from the same starts and noise as every other row.
    if let Some(k) = cfg.ensemble {
        let (on, off) = (on_split.id.as_str(), off_split.id.as_str());
        let (clf_k, q_k) = (trainer::Kind::Classifier, trainer::Kind::Q);
        let (ce_rec, ce) = train_verifier(store, on, clf_k, cfg, stride, &space, &art_dir, Some(k)).await?;
        let (qe_rec, qe) = train_verifier(store, on, q_k, cfg, stride, &space, &art_dir, Some(k)).await?;
        let (oe_rec, oe) = train_verifier(store, off, clf_k, cfg, stride, &space, &art_dir, Some(k)).await?;
        let lambda = cfg.lambdas.iter().copied().fold(0.0f32, f32::max);
        let ln = lambda_name(lambda);
        // (split, method, ensemble, its artifact, the one-verifier run it is set against, λ)
        type Setting<'a> = (&'static str, String, &'a steer::Verifier, &'a str, String, Option<f32>);
        let bon = format!("C x BoN (N={nn})");
        let settings: Vec<Setting> = vec![
            ("on-policy", bon.clone(), &ce, &ce_rec.id, format!("c-bon{nn}"), None),
            ("off-policy (alt rollouts)", bon, &oe, &oe_rec.id, format!("off-c-bon{nn}"), None),
            (
                "on-policy",
                format!("C x CG (lambda={lambda})"),
                &ce,
                &ce_rec.id,
                format!("c-cg{ln}"),
                Some(lambda),
            ),
            (
                "on-policy",
                format!("Q x CG (lambda={lambda})"),
                &qe,
                &qe_rec.id,
                format!("q-cg{ln}"),
                Some(lambda),
            ),
        ];
        let mut rows = Vec::new();
        for (split, method, v, artifact, single_run, lambda) in settings {
            let label = format!("{method}, ensemble of {k}");
            let (choice, steering) = match lambda {
                None => (ChunkChoice::BestOfN { scorer: v, n: nn }, Steering::Bon { n: nn as u32 }),
                Some(l) => {
                    (ChunkChoice::Guided { scorer: v, lambda: l }, Steering::Cg { lambda: lambda_f64(l) })
                }
            };
            let eps = eval(&base, choice, &label, crn)?;
            let (steps, fell) = eps
                .iter()
                .fold((0u64, 0u64), |(s, f), e| (s + e.best_of_n_steps as u64, f + e.fell_back as u64));
            let run = format!("ens{k}-{single_run}");
            let r = demo_run(
                &run,
                steering,
                Some(artifact),
                &[split.split(' ').next().unwrap_or(split), "ensemble"],
            );
            let verifier = format!("{split}, ensemble of {k}");
            record(store, &mut report, &eps, BASE, r, &method, &verifier, pc.horizon, crn).await?;
            rows.push(report::EnsembleRow::new(
                &report,
                &method,
                split,
                &single_run,
                &run,
                lambda.is_none().then_some((fell, steps)),
            )?);
        }
        report.ensembles = Some(report::Ensembles {
            members: k,
            artifacts: [&ce_rec, &qe_rec, &oe_rec]
                .iter()
                .map(|r| (r.id.clone(), r.config["metrics"]["ensemble"].clone()))
                .collect(),
            rows,
        });
        store.set_alias("latest", &q_rec.id).await?;
    }

    // The learning-curve classifiers (and any ensembles) were published last: `latest` names
    // the main ones again.
    store.set_alias("latest", &c_rec.id).await?;

    // A failure alarm from the same classifier: a threshold on its per-step scores calibrated on
    // half of the base policy's unsteered successes it did not train on (α = 0.1), measured on
    // the other half and on the failures, stored as the checkpoint's `latest` monitor. Fresh
    // base rollouts (run `base-fresh`) join the split's held-out ones, so the false-alarm rate is
    // measured on hundreds of successes.
    let fresh_seed = cfg.seed + 300;
    let fresh = eval(&base, ChunkChoice::None, "fresh base rollouts for the failure monitor", fresh_seed)?;
    let fresh_run = demo_run("base-fresh", Steering::Base, None, &["monitor"]);
    ingest_rollouts(store, &fresh, BASE, fresh_run, pc.horizon, fresh_seed).await?;
    let pb = stage("calibrating a failure monitor (alpha 0.1) on the base rollouts");
    let cal = monitor::calibrate(store, &clf, &c_rec, &monitor::CalibrateSpec::default()).await?;
    let record_json = serde_json::to_vec(&cal.record)?;
    let evaluation = serde_json::to_value(&cal.evaluation)?;
    let m = store
        .put_monitor(store_artifacts::NewMonitor {
            record_json: &record_json,
            policy: POLICY,
            checkpoint: BASE,
            artifact_id: &c_rec.id,
            alpha: cal.record.alpha,
            threshold: cal.record.threshold,
            evaluation: Some(&evaluation),
            created_by: "demo",
        })
        .await?;
    pb.finish_and_clear();
    report.monitor = Some(report::MonitorSummary {
        id: m.id,
        artifact_id: c_rec.id.clone(),
        alpha: cal.record.alpha,
        threshold: cal.record.threshold,
        calibration_episodes: cal.record.calibration_episodes.len(),
        evaluation: cal.evaluation,
    });

    // The table, read back from the store alone: every row must be what the scoreboard says.
    let sb = store
        .scoreboard(&store_compare::ScoreboardRequest {
            policy: POLICY.into(),
            baseline_checkpoint: Some(BASE.into()),
            ..Default::default()
        })
        .await?;
    report.check_against(&sb)?;
    report.meta["scoreboard_version"] = serde_json::json!(sb.version);

    // 5. The report and the trajectory figure.
    let steered = keep_for_plot.context("no best-of-N row")?;
    sim::plot::plot_panels(
        &cfg.out_dir.join("trajectories.png"),
        &env,
        &[
            sim::plot::Panel::from_demos("expert demos", &demos, 60),
            sim::plot::Panel::from_episodes("base policy", &base_eps, 120),
            sim::plot::Panel::from_episodes(&format!("C x BoN (N={})", cfg.bon_n[0]), &steered, 120),
        ],
        360,
    )?;
    report.seconds = t0.elapsed().as_secs_f64();
    report.write(&cfg.out_dir)?;
    Ok(report)
}
