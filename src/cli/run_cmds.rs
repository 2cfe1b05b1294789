//! Training, scoring and the demo: wiring of trainer, steer and demo to the store.

use super::{print_json, StoreArgs};
use anyhow::{Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;
use store_jobs::JobQueue;

#[derive(clap::Args, Debug)]
pub struct TrainArgs {
    #[arg(long)]
    pub split: String,
    /// classifier | q
    #[arg(long)]
    pub kind: String,
    /// Training recipe (.json or .toml). Missing fields take the paper's defaults: its image
    /// recipe (features variant) when an observation key is a layer (encoder features), else its
    /// low-dimensional one. The file may also give the input spec (`obs_keys`, `obs_history`,
    /// `chunk_len`, `step_stride`); the flags below override it.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Observation keys in order: observation columns (`observation.state`) and layers
    /// (`features.dp-resnet18`, see `ufops layers`), space- or comma-separated. Default: every
    /// observation column of the split's first episode, in the source's order.
    #[arg(long, num_args = 1.., value_delimiter = ',')]
    pub obs_keys: Option<Vec<String>>,
    /// Observation history T_o (default 2, the paper's).
    #[arg(long)]
    pub obs_history: Option<usize>,
    /// The policy's action chunk length H (actions executed per prediction; 1 for a policy that
    /// acts step by step). Default: the length of the chunks the episodes store (`action_chunk`;
    /// giving another length is an error); required when they store none.
    #[arg(long)]
    pub chunk_len: Option<usize>,
    /// Train only on steps t with t % STRIDE == 0 (where a chunking policy re-planned; usually
    /// its chunk length). Default 1: every step.
    #[arg(long)]
    pub step_stride: Option<usize>,
    /// The policy's action normaliser, raw = x * SCALE + OFFSET, one value per action dimension:
    /// the verifier takes chunks in the policy's normalised space (the default, identity when
    /// not given). Overrides the config's `action_space`.
    /// Negative values are values, not flags (`--action-offset -0.38 0.28`): a LeRobot min-max
    /// normaliser's offsets are often negative.
    #[arg(long, num_args = 1.., allow_negative_numbers = true, conflicts_with = "standardize_actions")]
    pub action_scale: Option<Vec<f32>>,
    #[arg(long, num_args = 1.., allow_negative_numbers = true, requires = "action_scale")]
    pub action_offset: Option<Vec<f32>>,
    /// Feed raw chunks standardised with train-set statistics instead (the older recipe).
    #[arg(long)]
    pub standardize_actions: bool,
    /// Train an ensemble of K members (seeds seed+k, bootstrap resamples of the split's training
    /// episodes) published as one artifact: its score is the members' mean, steering ranks by
    /// mean − κ·spread and falls back to the policy's own chunk when the members disagree
    /// (trainer/ARTIFACT.md, "Ensembles"). Costs K times the training (recipe key `ensemble`).
    #[arg(long, value_name = "K")]
    pub ensemble: Option<usize>,
    #[arg(long, env = "USER", default_value = "cli")]
    pub actor: String,
    #[arg(long)]
    pub json: bool,
}

pub fn parse_kind(s: &str) -> Result<trainer::Kind> {
    match s {
        "classifier" => Ok(trainer::Kind::Classifier),
        "q" => Ok(trainer::Kind::Q),
        _ => anyhow::bail!("unknown verifier kind {s:?}: classifier or q"),
    }
}

pub async fn train(args: &StoreArgs, a: TrainArgs) -> Result<()> {
    let store = args.open().await?;
    let kind = parse_kind(&a.kind)?;
    let (mut config, recipe_input) = match &a.config {
        Some(p) => {
            let (c, input) = trainer::TrainConfig::from_recipe_file(p)?;
            (Some(c), input)
        }
        None => (None, trainer::RecipeInput::default()),
    };
    if a.action_scale.is_some() || a.standardize_actions {
        let c = config.get_or_insert_with(|| trainer::TrainConfig { kind, ..Default::default() });
        c.action_space = match &a.action_scale {
            Some(scale) => {
                let offset = a.action_offset.clone().unwrap_or_else(|| vec![0.0; scale.len()]);
                anyhow::ensure!(
                    offset.len() == scale.len(),
                    "--action-offset needs one value per --action-scale value"
                );
                trainer::ActionSpace::policy(scale.clone(), offset)
            }
            None => trainer::ActionSpace::Standardized,
        };
    }
    if let Some(c) = config.as_mut() {
        c.kind = kind;
    }
    let spec = trainer::TrainJobSpec {
        split_id: a.split.clone(),
        kind,
        config,
        obs_keys: a.obs_keys.or(recipe_input.obs_keys),
        obs_history: a.obs_history.or(recipe_input.obs_history),
        chunk_len: a.chunk_len.or(recipe_input.chunk_len),
        step_stride: a.step_stride.or(recipe_input.step_stride),
        ensemble: a.ensemble,
    };
    let job = store.create_job(store_jobs::JobKind::Train, &serde_json::to_value(&spec)?, &a.actor).await?;
    let worker = api::worker_identity("cli");
    let claimed = store.claim_job(&worker, 3_600_000).await?;
    anyhow::ensure!(
        claimed.as_ref().map(|j| j.id.as_str()) == Some(job.id.as_str()),
        "another queued job was claimed first; run `ufops worker`"
    );
    let attempt = claimed.map(|j| j.attempts).unwrap_or(1);
    let pb = if std::io::IsTerminal::is_terminal(&std::io::stderr()) {
        let pb = ProgressBar::new(1);
        pb.set_style(ProgressStyle::with_template("{bar:30} epoch {pos}/{len} {msg}").expect("template"));
        pb
    } else {
        ProgressBar::hidden()
    };
    let pb2 = pb.clone();
    let observer = Box::new(move |r: &trainer::EpochReport| {
        pb2.set_length(r.epochs as u64);
        pb2.set_position(r.epoch as u64);
        pb2.set_message(format!(
            "train {:.4} val {:.4}{}",
            r.train_loss,
            r.val_loss.unwrap_or(f64::NAN),
            r.val_auc.map(|x| format!(" auc {x:.3}")).unwrap_or_default()
        ));
    });
    let result = trainer::run_train_job(&store, &spec, Some(&job.id), observer, None).await;
    pb.finish_and_clear();
    match result {
        Ok(rec) => {
            store
                .finish_job(&job.id, &worker, attempt, Ok(serde_json::json!({ "artifact": rec.id })))
                .await?;
            if a.json {
                return print_json(&rec);
            }
            println!(
                "artifact {} ({} for {}/{}), aliases [{}]",
                rec.id,
                rec.kind,
                rec.policy,
                rec.checkpoint,
                rec.aliases.join(", ")
            );
            println!("metrics: {}", rec.config["metrics"]["final"]);
            // How much the chunk matters, next to the AUROC (the trainer already logged a flagged
            // verifier's reason as a warning).
            if let Some(s) = verifier::ActionSensitivity::from_metrics(&rec.config["metrics"]) {
                println!("{}", s.summary());
            }
            if rec.config["metrics"]["ensemble"].is_object() {
                println!("ensemble: {}", rec.config["metrics"]["ensemble"]);
            }
            Ok(())
        }
        Err(e) => {
            store.finish_job(&job.id, &worker, attempt, Err(format!("{e:#}"))).await?;
            Err(e)
        }
    }
}

/// What `ufops score` does besides scoring.
pub struct ScoreOptions {
    /// Also print the guidance gradient of each row.
    pub grad: bool,
    /// Rows carry raw actions: map them into the artifact's action space first.
    pub raw_actions: bool,
}

/// Scores rows with an artifact through the verifier core: from `ufops serve` (`--api`), a
/// directory, or the store (id or POLICY/CHECKPOINT/KIND@ALIAS).
pub async fn score(
    args: &StoreArgs,
    artifact: &str,
    input: &PathBuf,
    api: Option<&str>,
    token: Option<&str>,
    opts: ScoreOptions,
) -> Result<()> {
    let dir = PathBuf::from(artifact);
    let v = if let Some(base) = api {
        let token = token.context("--api needs a token: --token or UFOPS_TOKEN")?;
        let src = steer::http::ApiSource::new(base, token);
        let reference = artifact.to_string();
        tokio::task::spawn_blocking(move || steer::http::load_verifier(&src, &reference)).await??
    } else if dir.join(verifier::MANIFEST_FILE).exists() {
        verifier::Verifier::load_dir(&dir)?
    } else {
        super::export_cmd::StoreVerifier::load(&args.open().await?, artifact).await?.verifier
    };
    let text = std::fs::read_to_string(input).with_context(|| format!("reading {}", input.display()))?;
    let mut rows = trainer::parse_rows(&text)?;
    if opts.raw_actions {
        let space = &v.config().input.action_space;
        let a = v.config().input.layout.action_dim;
        rows.iter_mut().for_each(|r| space.raw_to_input(&mut r.action, a));
    }
    let scores = trainer::score_rows(&v, &rows)?;
    let mut out = serde_json::json!({ "artifact": v.id(), "scores": scores });
    if v.members() > 1 {
        out["members"] = v.members().into();
        out["spread"] = serde_json::to_value(trainer::spread_rows(&v, &rows)?)?;
    }
    if opts.grad {
        out["grads"] = serde_json::to_value(trainer::grad_rows(&v, &rows)?)?;
    }
    print_json(&out)
}

pub async fn demo(
    args: &StoreArgs,
    quick: bool,
    lambdas: Option<Vec<f32>>,
    ablation: Option<Vec<usize>>,
    ensemble: Option<usize>,
) -> Result<()> {
    let store = args.open_or_create().await?;
    let out = args.data_dir.join("demo");
    let mut cfg = if quick { demo::DemoConfig::quick(&out) } else { demo::DemoConfig::full(&out) };
    if let Some(l) = lambdas {
        anyhow::ensure!(
            !l.is_empty() && l.iter().all(|x| x.is_finite() && *x >= 0.0),
            "--lambdas: finite values >= 0"
        );
        cfg.lambdas = l;
    }
    if let Some(a) = ablation {
        anyhow::ensure!(a.iter().all(|&s| s > 0), "--ablation-sizes: sizes of at least 1");
        cfg.ablation_sizes = a;
    }
    if let Some(k) = ensemble {
        anyhow::ensure!(
            (2..=verifier::MAX_MEMBERS).contains(&k),
            "--ensemble: 2 to {} members",
            verifier::MAX_MEMBERS
        );
        cfg.ensemble = Some(k);
    }
    eprintln!(
        "ufops demo{}: {} rollouts per row, store {}",
        if quick { " --quick" } else { "" },
        cfg.episodes,
        store.describe()
    );
    let report = demo::run(&store, &cfg).await?;
    println!("{}", report.markdown());
    print!("{}", report.monitor_markdown());
    if let Some(q) = &report.steering_quality {
        println!("\n{}", q.markdown());
    }
    println!(
        "runtime {:.0} s; report: {} and report.json; figure: {}",
        report.seconds,
        out.join("report.md").display(),
        out.join("trajectories.png").display()
    );
    Ok(())
}
