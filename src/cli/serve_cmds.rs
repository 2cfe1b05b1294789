//! `ingest`, `serve` and `worker`: the ingest crate and the API wired to the store, with the job
//! runner that executes training and ingest jobs for the API's workers.

use super::StoreArgs;
use anyhow::Result;
use futures::future::BoxFuture;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use store_feed::Automations;

#[derive(clap::Args, Debug)]
pub struct IngestArgs {
    /// A robomimic .hdf5 file, an ALOHA `episode_<i>.hdf5` file or folder of them, a LeRobot
    /// dataset folder, a `lerobot-eval` output folder (`eval_info.json` + `videos/`), or an .mcap
    /// recording.
    pub path: PathBuf,
    #[arg(long)]
    pub policy: String,
    #[arg(long)]
    pub checkpoint: String,
    #[arg(long)]
    pub task: Option<String>,
    /// auto | robomimic | aloha | lerobot | lerobot-eval | mcap
    #[arg(long, default_value = "auto")]
    pub format: String,
    /// JSON {"demo_0": true, …} or CSV lines demo_0,true.
    #[arg(long)]
    pub success_file: Option<PathBuf>,
    /// `rewards`: success iff the last reward >= --reward-threshold.
    #[arg(long)]
    pub success_from: Option<String>,
    #[arg(long, default_value_t = 1.0)]
    pub reward_threshold: f64,
    /// MCAP topic/field mapping (TOML).
    #[arg(long)]
    pub mapping: Option<PathBuf>,
    /// Ingest what is complete in a truncated recording instead of refusing it.
    #[arg(long)]
    pub recover: bool,
    /// How image cameras are stored: `png` (default) keeps every frame losslessly, one PNG per
    /// step; `video` stores each camera of an episode as one H.264 MP4 (lossy, visually
    /// lossless: ~40 dB PSNR, a fraction of the bytes; see ingest/README.md). JPEG cameras are
    /// kept as recorded either way.
    #[arg(long, default_value = "png", value_name = "png|video")]
    pub images: String,
    /// The source's per-step human-takeover flag, when not named `intervention` (LeRobot's
    /// DAgger feature): a LeRobot feature, or a robomimic demo's / ALOHA file's dataset. Kept as
    /// the steps' `intervention` column; splits train on the steps before a takeover.
    #[arg(long, value_name = "NAME")]
    pub intervention_key: Option<String>,
    /// lerobot-eval output: the `--seed` it ran with (1000 unless set). Episode i of each task
    /// ran with S + i; lerobot >= 0.4 does not record it, and without it the episodes get no
    /// seed or pair key (`ufops compare` then pairs them in arrival order).
    #[arg(long, value_name = "S")]
    pub start_seed: Option<i64>,
    /// The evaluation run these rollouts belong to (a name; see `ufops scoreboard`).
    #[arg(long)]
    pub run: Option<String>,
    /// How the run was steered: base | bon:N | cg:LAMBDA | flow:LAMBDA (default base; without
    /// --run, the run is named after it).
    #[arg(long)]
    pub steering: Option<String>,
    /// The verifier artifact that steered the run.
    #[arg(long)]
    pub run_artifact: Option<String>,
    /// Free-form tags of the run (repeatable).
    #[arg(long = "run-tag")]
    pub run_tags: Vec<String>,
    /// The run's steering telemetry: a sidecar Parquet file of best-of-N records (written by
    /// `ufops.SteeringLog`; default: SOURCE.steering.parquet, or a folder's steering.parquet,
    /// when it exists). Its records become the episodes' steering column (`ufops replay`).
    #[arg(long = "steering-log", value_name = "FILE")]
    pub steering_log: Option<std::path::PathBuf>,
    #[arg(long)]
    pub json: bool,
}

/// The run named by `--run`, `--steering`, `--run-artifact` and `--run-tag` (one rule with the
/// API's ingest: `store::RunInput::from_parts`).
pub fn run_input(
    run: Option<&str>,
    steering: Option<&str>,
    artifact: Option<&str>,
    tags: &[String],
) -> Result<Option<store::RunInput>> {
    Ok(store::RunInput::from_parts(run, steering, artifact, tags)?)
}

pub fn ingest_options(a: &IngestArgs) -> Result<ingest::IngestOptions> {
    let success_from_rewards = match a.success_from.as_deref() {
        None => None,
        Some("rewards") => Some(a.reward_threshold),
        Some(other) => anyhow::bail!("--success-from {other:?}: only `rewards` is supported"),
    };
    Ok(ingest::IngestOptions {
        policy: a.policy.clone(),
        checkpoint: a.checkpoint.clone(),
        task: a.task.clone(),
        format: a.format.parse()?,
        success_file: a.success_file.clone(),
        success_from_rewards,
        mapping: a.mapping.clone(),
        recover: a.recover,
        images: a.images.parse()?,
        progress: !a.json,
        memory: Default::default(),
        run: run_input(a.run.as_deref(), a.steering.as_deref(), a.run_artifact.as_deref(), &a.run_tags)?,
        intervention_key: a.intervention_key.clone(),
        start_seed: a.start_seed,
        steering_log: a.steering_log.clone(),
    })
}

pub async fn ingest(args: &StoreArgs, a: IngestArgs) -> Result<()> {
    let store = args.open_or_create().await?;
    let opts = ingest_options(&a)?;
    let r = ingest::ingest(&store, &a.path, &opts).await?;
    if a.json {
        return super::print_json(&r);
    }
    if r.already_ingested {
        println!(
            "{} is already in the store (version {}, sha256 {}): nothing to do",
            a.path.display(),
            r.version,
            r.sha256
        );
    } else {
        println!(
            "version {}: {} episodes, {} steps from {} ({}, {:.1} MB) — labels: {} success, {} failure, {} unknown",
            r.version,
            r.episodes,
            r.steps,
            a.path.display(),
            r.format,
            r.bytes as f64 / 1e6,
            r.labels.success,
            r.labels.failure,
            r.labels.unknown
        );
    }
    // What the ingest left out (or recovered around), one warning per line.
    for n in &r.notes {
        eprintln!("warning: {n}");
    }
    Ok(())
}

/// Runs the API's jobs: `train` through the trainer, `ingest` through the ingest crate, `export`
/// through the export crate.
pub struct Runner;

fn train_spec(spec: &serde_json::Value) -> Result<trainer::TrainJobSpec, String> {
    let mut v = spec.clone();
    let mut recipe = None;
    if let Some(o) = v.as_object_mut() {
        // The API records the split's policy/checkpoint for display; the split decides them.
        o.remove("policy");
        o.remove("checkpoint");
        o.retain(|_, x| !x.is_null());
        // `config` is a recipe like a `--config` file: it may carry the input spec too.
        recipe = o.remove("config");
    }
    let mut spec: trainer::TrainJobSpec =
        serde_json::from_value(v).map_err(|e| format!("bad training job spec: {e}"))?;
    if let Some(recipe) = recipe {
        let (config, input) = trainer::TrainConfig::from_recipe(recipe)
            .map_err(|e| format!("bad training job config: {e:#}"))?;
        spec.config = Some(config);
        spec.obs_keys = spec.obs_keys.or(input.obs_keys);
        spec.obs_history = spec.obs_history.or(input.obs_history);
        spec.chunk_len = spec.chunk_len.or(input.chunk_len);
        spec.step_stride = spec.step_stride.or(input.step_stride);
    }
    Ok(spec)
}

impl api::JobRunner for Runner {
    fn run<'a>(
        &'a self,
        store: &'a store::Store,
        job: &'a store_jobs::JobRecord,
        ctx: api::JobContext,
    ) -> BoxFuture<'a, Result<serde_json::Value, String>> {
        Box::pin(async move {
            match job.kind {
                store_jobs::JobKind::Train => train_job(store, job, ctx).await,
                store_jobs::JobKind::Ingest => ingest_job(store, job).await,
                store_jobs::JobKind::Export => export_job(store, job, &ctx).await,
                store_jobs::JobKind::Score => score_job(store, job, &ctx).await,
                store_jobs::JobKind::Scoreboard => {
                    store.run_scoreboard_job(&job.spec).await.map_err(|e| e.to_string())
                }
            }
        })
    }
}

/// A training job: trains, publishes the artifact, reports each epoch; cancelled through `ctx`.
async fn train_job(
    store: &store::Store,
    job: &store_jobs::JobRecord,
    ctx: api::JobContext,
) -> Result<serde_json::Value, String> {
    let mut job_spec = job.spec.clone();
    // An automation's job freezes its split when it runs, so the split holds every label so far.
    if let Some(freeze) = job_spec.as_object_mut().and_then(|o| {
        o.remove("automation");
        o.remove("freeze")
    }) {
        let text = |k: &str| job.spec.get(k).and_then(|v| v.as_str()).map(String::from);
        let split = store
            .create_split(&store::SplitRequest {
                policy: text("policy").ok_or("the job's spec has no policy")?,
                checkpoint: text("checkpoint").ok_or("the job's spec has no checkpoint")?,
                version: None,
                off_policy_from: Vec::new(),
                val_fraction: freeze.get("val_fraction").and_then(|v| v.as_f64()).unwrap_or(0.2),
                seed: freeze.get("seed").and_then(|v| v.as_u64()).unwrap_or(0),
                actor: format!("job:{}", job.id),
                max_episodes: None,
            })
            .await
            .map_err(|e| format!("freezing the split: {e}"))?;
        ctx.progress(serde_json::json!({"split_id": split.id}));
        job_spec["split_id"] = serde_json::json!(split.id);
    }
    let spec = train_spec(&job_spec)?;
    let cancel = Arc::new(AtomicBool::new(false));
    let (c2, ctx2) = (cancel.clone(), ctx.clone());
    let watcher = tokio::spawn(async move {
        ctx2.cancelled().await;
        c2.store(true, Ordering::SeqCst);
    });
    let ctx3 = ctx.clone();
    let observer = Box::new(move |r: &trainer::EpochReport| {
        ctx3.progress(serde_json::to_value(r).unwrap_or_default());
    });
    let r = trainer::run_train_job(store, &spec, Some(&job.id), observer, Some(cancel)).await;
    watcher.abort();
    let rec = r.map_err(|e| format!("{e:#}"))?;
    Ok(serde_json::json!({ "artifact_id": rec.id, "metrics": rec.config["metrics"]["final"] }))
}

/// An ingest job: the options of `ufops ingest` from the job's spec.
async fn ingest_job(store: &store::Store, job: &store_jobs::JobRecord) -> Result<serde_json::Value, String> {
    let s = &job.spec;
    let field = |k: &str| s.get(k).and_then(|v| v.as_str()).map(String::from);
    let path = field("path").ok_or("ingest job has no path")?;
    let opts = ingest::IngestOptions {
        policy: field("policy").ok_or("ingest job has no policy")?,
        checkpoint: field("checkpoint").ok_or("ingest job has no checkpoint")?,
        task: field("task"),
        format: field("format").unwrap_or_else(|| "auto".into()).parse().map_err(|e| format!("{e}"))?,
        success_file: None,
        success_from_rewards: s.get("reward_threshold").and_then(|v| v.as_f64()),
        mapping: None,
        recover: s.get("recover").and_then(|v| v.as_bool()).unwrap_or(false),
        images: field("images").unwrap_or_else(|| "png".into()).parse().map_err(|e| format!("{e}"))?,
        progress: false,
        memory: Default::default(),
        intervention_key: field("intervention_key"),
        start_seed: s.get("start_seed").and_then(|v| v.as_i64()),
        // The sidecar beside the source, when there is one.
        steering_log: None,
        run: {
            let tags: Vec<String> = s
                .get("run_tags")
                .and_then(|v| v.as_array())
                .map(|a| a.iter().filter_map(|t| t.as_str().map(String::from)).collect())
                .unwrap_or_default();
            let (run, steering, artifact) = (field("run"), field("steering"), field("run_artifact"));
            run_input(run.as_deref(), steering.as_deref(), artifact.as_deref(), &tags)
                .map_err(|e| format!("{e:#}"))?
        },
    };
    let r = ingest::ingest(store, std::path::Path::new(&path), &opts).await.map_err(|e| format!("{e:#}"))?;
    serde_json::to_value(&r).map_err(|e| e.to_string())
}

/// An export job (curated by a verifier's scores when its selection asks for them).
async fn export_job(
    store: &store::Store,
    job: &store_jobs::JobRecord,
    ctx: &api::JobContext,
) -> Result<serde_json::Value, String> {
    let spec: ::export::job::ExportJobSpec =
        serde_json::from_value(job.spec.clone()).map_err(|e| format!("bad export job spec: {e}"))?;
    let scorer = match &spec.selection.score {
        Some(r) => Some(
            super::export_cmd::StoreVerifier::load(store, &r.artifact).await.map_err(|e| format!("{e:#}"))?,
        ),
        None => None,
    };
    let progress = |v: serde_json::Value| ctx.progress(v);
    let cancelled = || ctx.is_cancelled();
    let scorer = scorer.as_ref().map(|s| &s.verifier as &dyn verifier::StepScorer);
    let r = ::export::job::run_export_job(store, &job.id, &spec, scorer, &progress, &cancelled)
        .await
        .map_err(|e| e.to_string())?;
    serde_json::to_value(&r).map_err(|e| e.to_string())
}

/// A score job: the review queue's scores of a verifier artifact.
async fn score_job(
    store: &store::Store,
    job: &store_jobs::JobRecord,
    ctx: &api::JobContext,
) -> Result<serde_json::Value, String> {
    let spec: ::export::score_job::ScoreJobSpec =
        serde_json::from_value(job.spec.clone()).map_err(|e| format!("bad score job spec: {e}"))?;
    let scorer = super::export_cmd::StoreVerifier::load(store, &spec.artifact_id)
        .await
        .map_err(|e| format!("{e:#}"))?;
    let progress = |v: serde_json::Value| ctx.progress(v);
    let cancelled = || ctx.is_cancelled();
    let r = ::export::score_job::run_score_job(
        store,
        Some(&job.id),
        &spec,
        &scorer.verifier,
        &progress,
        &cancelled,
    )
    .await
    .map_err(|e| e.to_string())?;
    serde_json::to_value(&r).map_err(|e| e.to_string())
}

#[derive(clap::Args, Debug)]
pub struct ServeArgs {
    /// Address to listen on; binding beyond loopback must be asked for explicitly.
    #[arg(long, default_value = "127.0.0.1:8080")]
    pub addr: SocketAddr,
    /// Do not run jobs in this process (leave them to `ufops worker`).
    #[arg(long)]
    pub no_worker: bool,
    /// Do not run the automations from this server (another server runs them).
    #[arg(long)]
    pub no_automations: bool,
    /// The URL browsers use when the server runs behind a TLS proxy (`https://HOST[:PORT]`):
    /// session cookies get `Secure` and the CSRF origin check compares with it.
    #[arg(long, env = "UFOPS_PUBLIC_URL")]
    pub public_url: Option<String>,
    /// Seconds a request's headers may take to arrive (also the idle keep-alive time).
    #[arg(long, default_value_t = 30, value_parser = clap::value_parser!(u64).range(1..=3600))]
    pub header_timeout_secs: u64,
    /// Seconds a request body may send nothing, and a response may go unread, before it fails.
    #[arg(long, default_value_t = 30, value_parser = clap::value_parser!(u64).range(1..=3600))]
    pub body_idle_timeout_secs: u64,
    /// Requests per second one token may make on average (bursts of twice that); 0: no limit.
    #[arg(long, default_value_t = 1000)]
    pub rate_limit_per_token: u32,
    /// Checks of unknown tokens per second per peer address (bursts of ten times that); 0: no limit.
    #[arg(long, default_value_t = 100)]
    pub unverified_checks_per_peer: u32,
    /// Open connections at once; more wait in the kernel's backlog.
    #[arg(long, default_value_t = 4096, value_parser = clap::value_parser!(u64).range(1..=1_000_000))]
    pub max_connections: u64,
    /// A reverse proxy (IP address; repeatable) whose X-Forwarded-For names the client that the
    /// per-address limits count; without one, every request from the proxy shares its address.
    #[arg(long = "trusted-proxy", value_name = "IP")]
    pub trusted_proxies: Vec<std::net::IpAddr>,
    /// Days the change feed keeps its events (`GET /v1/events`, `ufops events`); 0: forever.
    #[arg(long, default_value_t = 30)]
    pub event_retention_days: u64,
    /// Hours a request's `Idempotency-Key` and its response are kept for retries.
    #[arg(long, default_value_t = 24, value_parser = clap::value_parser!(u64).range(1..=720))]
    pub idempotency_ttl_hours: u64,
    /// Seconds a request being served holds its `Idempotency-Key` without renewing it: after a
    /// crash, a retry of it waits at most this long.
    #[arg(long, default_value_t = 30, value_parser = clap::value_parser!(u64).range(1..=3600))]
    pub idempotency_lease_secs: u64,
}

/// Ctrl-C or SIGTERM (what `docker stop`, systemd and Kubernetes send): the server finishes the
/// requests in flight (up to its deadline) and the worker releases its job.
async fn shutdown_signal() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        match signal(SignalKind::terminate()) {
            Ok(mut term) => {
                tokio::select! {
                    _ = tokio::signal::ctrl_c() => {}
                    _ = term.recv() => {}
                }
            }
            Err(_) => {
                let _ = tokio::signal::ctrl_c().await;
            }
        }
    }
    #[cfg(not(unix))]
    let _ = tokio::signal::ctrl_c().await;
    eprintln!("shutting down");
}

pub async fn serve(args: &StoreArgs, a: ServeArgs) -> Result<()> {
    let store = args.open_or_create().await?;
    let mut cfg = api::ServeConfig::new(&args.data_dir);
    cfg.addr = a.addr;
    cfg.run_worker_in_process = !a.no_worker;
    cfg.run_automations = !a.no_automations;
    cfg.public_url = a.public_url;
    cfg.header_read_timeout = std::time::Duration::from_secs(a.header_timeout_secs);
    cfg.body_idle_timeout = std::time::Duration::from_secs(a.body_idle_timeout_secs);
    cfg.write_stall_timeout = std::time::Duration::from_secs(a.body_idle_timeout_secs.saturating_mul(2));
    cfg.rate_limit_per_token = a.rate_limit_per_token;
    cfg.unverified_checks_per_peer = a.unverified_checks_per_peer;
    cfg.max_connections = a.max_connections as usize;
    cfg.trusted_proxies = a.trusted_proxies;
    cfg.event_retention =
        (a.event_retention_days > 0).then(|| std::time::Duration::from_secs(a.event_retention_days * 86_400));
    cfg.idempotency_ttl = std::time::Duration::from_secs(a.idempotency_ttl_hours * 3600);
    cfg.idempotency_lease = std::time::Duration::from_secs(a.idempotency_lease_secs);
    api::serve(store, cfg, Arc::new(Runner), shutdown_signal()).await
}

pub async fn worker(args: &StoreArgs, id: Option<String>, lease_ms: i64) -> Result<()> {
    let store = args.open_or_create().await?;
    let id = id.unwrap_or_else(|| api::worker_identity("worker"));
    eprintln!("worker {id}: claiming jobs from {}", store.describe());
    api::run_worker(store, Arc::new(Runner), id, lease_ms, shutdown_signal()).await;
    Ok(())
}
