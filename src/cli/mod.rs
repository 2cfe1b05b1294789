//! Argument definitions and dispatch of every subcommand.

mod catalog_cmds;
mod compare_cmd;
mod dev;
mod events_cmd;
mod export_cmd;
mod monitor_cmds;
mod replay_cmd;
mod review_cmds;
mod run_cmds;
mod scoreboard_cmd;
mod serve_cmds;
mod store_cmds;
mod view_cmd;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
use std::path::PathBuf;

#[derive(Parser, Debug)]
#[command(
    name = "ufops",
    version,
    about = "Update-free on-policy steering: rollouts store, verifiers, steering"
)]
pub struct Cli {
    #[command(flatten)]
    pub store: StoreArgs,
    #[command(subcommand)]
    pub command: Command,
}

#[derive(clap::Args, Debug, Clone)]
pub struct StoreArgs {
    /// Data directory (SQLite catalog and local objects live here by default).
    #[arg(long, global = true, env = "UFOPS_DATA_DIR", default_value = "./ufops-data")]
    pub data_dir: PathBuf,
    /// Catalog database: sqlite://PATH or postgres://USER@HOST/DB.
    #[arg(long, global = true, env = "UFOPS_DATABASE_URL")]
    pub database_url: Option<String>,
    /// Object storage: a local path or s3://BUCKET/PREFIX.
    #[arg(long, global = true, env = "UFOPS_OBJECT_STORE")]
    pub object_store: Option<String>,
}

impl StoreArgs {
    pub fn config(&self) -> store::StoreConfig {
        store::StoreConfig {
            data_dir: self.data_dir.clone(),
            database_url: self.database_url.clone(),
            object_store_url: self.object_store.clone(),
        }
    }
    /// Opens the store, which must exist: a command run in the wrong directory says so instead of
    /// creating an empty store there.
    pub async fn open(&self) -> Result<store::Store> {
        if self.database_url.is_none() && !self.data_dir.join("catalog.sqlite").is_file() {
            anyhow::bail!(
                "no store at {} (it has no catalog.sqlite): create one with `ufops init`, or point to yours with \
                 --data-dir DIR (or UFOPS_DATA_DIR; --database-url for Postgres)",
                self.data_dir.display()
            );
        }
        self.open_or_create().await
    }

    /// Opens the store, creating it (and applying migrations) when there is none: `init`, `demo`
    /// and the commands that write what a new store starts with (`ingest`, `dev synth`) or wait
    /// for it (`serve`, `worker`).
    pub async fn open_or_create(&self) -> Result<store::Store> {
        Ok(store::Store::open(&self.config()).await?)
    }
}

/// The episode filters: one set of flags for `episodes`, `export` and `rank`.
#[derive(clap::Args, Debug)]
pub struct EpisodeFilterArgs {
    /// Store version. `export` and `rank` read the labels frozen in it (default: the head);
    /// `episodes` reads this past version (default: now, with the latest labels).
    #[arg(long)]
    pub version: Option<i64>,
    #[arg(long)]
    pub policy: Option<String>,
    #[arg(long)]
    pub checkpoint: Option<String>,
    #[arg(long)]
    pub task: Option<String>,
    /// success | failure | unknown (true/false also accepted; `--success` is the older name).
    #[arg(long, alias = "success")]
    pub label: Option<String>,
    #[arg(long)]
    pub tag: Option<String>,
}

impl EpisodeFilterArgs {
    /// The label filter, parsed.
    pub fn label(&self) -> Result<Option<store::Label>> {
        Ok(self.label.as_deref().map(str::parse::<store::Label>).transpose()?)
    }
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Create the store (catalog + object storage) and apply migrations.
    Init,
    /// List the store's versions.
    Versions {
        #[arg(long)]
        json: bool,
    },
    /// List episodes, now or at a past version.
    Episodes(store_cmds::EpisodesArgs),
    /// Set an episode's success label (recorded as an audit event).
    Label(store_cmds::LabelArgs),
    /// Show an episode's label history.
    History {
        episode: String,
        #[arg(long)]
        json: bool,
    },
    /// Freeze the current labels into a new version.
    Snapshot {
        #[arg(long, default_value = "label snapshot")]
        message: String,
        #[arg(long, env = "USER", default_value = "cli")]
        actor: String,
    },
    /// Delete objects that no version references (left by crashed or aborted writes).
    Gc {
        /// Keep unreferenced objects younger than this (a writer may still be committing).
        #[arg(long, default_value_t = 3600)]
        grace_seconds: u64,
        #[arg(long)]
        dry_run: bool,
        #[arg(long)]
        json: bool,
    },
    /// Train/val splits per checkpoint.
    Split {
        #[command(subcommand)]
        command: catalog_cmds::SplitCommand,
    },
    /// List verifier artifacts, set aliases, show or download one.
    Artifacts(catalog_cmds::ArtifactsArgs),
    /// Failure monitors: calibrate an alarm on a verifier's scores with a stated false-alarm
    /// rate, evaluate it against labels, list, show and alias them.
    Monitor {
        #[command(subcommand)]
        command: monitor_cmds::MonitorCommand,
    },
    /// List the store's layers (derived per-step data such as a policy encoder's features, one
    /// row per layer and producer), or those one episode holds (now or at --version).
    /// Layers are written from Python (`ufops.features.compute_layer`) and read joined to the
    /// steps as `obs.<layer>`; `ufops train --obs-keys LAYER …` trains on them.
    Layers {
        #[arg(long)]
        episode: Option<String>,
        #[arg(long, requires = "episode")]
        version: Option<i64>,
        #[arg(long)]
        json: bool,
    },
    /// Automations: rules per policy that train, score and snapshot by themselves when the
    /// change feed says so (run by `ufops serve`).
    Automation {
        #[command(subcommand)]
        command: catalog_cmds::AutomationCommand,
    },
    /// API tokens.
    Token {
        #[command(subcommand)]
        command: catalog_cmds::TokenCommand,
    },
    /// Ingest evaluation rollouts (robomimic HDF5, ALOHA HDF5, LeRobot v2.1/v3.0, MCAP) as one new version.
    Ingest(serve_cmds::IngestArgs),
    /// Export a version, split or filter as a LeRobot v3.0 dataset, a robomimic HDF5 file or ALOHA episode files.
    Export(export_cmd::ExportArgs),
    /// Episodes ordered by a verifier's score, lowest first (which demonstrations or rollouts to
    /// review, relabel or leave out).
    Rank(export_cmd::RankArgs),
    /// The change feed: every catalog change (ingests, labels, votes, versions, splits, jobs,
    /// artifacts, aliases, exports) with its sequence number, from any point; `--follow` waits
    /// for new ones. From the store, or from `ufops serve` with `--api`.
    Events(events_cmd::EventsArgs),
    /// Re-score a steered run's logged best-of-N steps (steering telemetry) with another verifier
    /// artifact or only the first K candidates, without the robot: how often the choice changes,
    /// and the score margin ("would N = 8 have sufficed?", "would verifier v2 pick differently?").
    Replay(replay_cmd::ReplayArgs),
    /// The review loop: store a verifier's episode scores, list episodes in a review order,
    /// show or set a policy's labeling campaign and its labelers' agreement.
    Review {
        #[command(subcommand)]
        command: review_cmds::ReviewCommand,
    },
    /// Serve the HTTP API (and run queued jobs in-process unless --no-worker).
    Serve(serve_cmds::ServeArgs),
    /// Print the HTTP API's OpenAPI document (what `ufops serve` serves at /openapi.json), or
    /// write it to a file: `ufops openapi --write api/openapi.json` regenerates the committed copy.
    Openapi {
        #[arg(long, value_name = "PATH")]
        write: Option<std::path::PathBuf>,
    },
    /// Claim and run queued jobs (training, ingest) from the catalog.
    Worker {
        #[arg(long)]
        id: Option<String>,
        #[arg(long, default_value_t = 30_000)]
        lease_ms: i64,
    },
    /// Train a verifier on a split and publish it as an artifact.
    Train(run_cmds::TrainArgs),
    /// Score (obs history, action chunk, t) rows with an artifact (a directory, id or P/C/KIND@ALIAS):
    /// input JSON {"rows": [{"obs": [...], "action": [...], "t": 3}]}; the action chunk in the
    /// artifact's action space (the policy's normalised space; see --raw-actions).
    Score {
        #[arg(long)]
        artifact: String,
        #[arg(long)]
        input: PathBuf,
        /// Also print each row's guidance gradient (d log C / d action, or d Q / d action).
        #[arg(long)]
        grad: bool,
        /// The rows' actions are raw: map them into the artifact's action space first.
        #[arg(long)]
        raw_actions: bool,
        /// Fetch the artifact from a `ufops serve` API (http://HOST:PORT) instead of the store.
        #[arg(long)]
        api: Option<String>,
        /// Bearer token for --api (role viewer or above).
        #[arg(long, env = "UFOPS_TOKEN", hide_env_values = true)]
        token: Option<String>,
    },
    /// The paper's pedagogical experiment end to end on this store.
    Demo {
        /// A small scale that finishes in about a minute.
        #[arg(long)]
        quick: bool,
        /// Guidance strengths of the CG rows (default 0.1,0.3,1,3,10; the paper uses 0.1).
        #[arg(long, value_delimiter = ',')]
        lambdas: Option<Vec<f32>>,
        /// Train verifiers on nested samples of this many rollouts for the learning-curve rows
        /// (default 100,250,500; sizes at or above the rollouts per row are skipped).
        #[arg(long, value_delimiter = ',')]
        ablation_sizes: Option<Vec<usize>>,
        /// Also steer with ensembles of K members (on-policy and off-policy C x BoN, C and Q x CG
        /// at the largest strength) beside the one-verifier rows: the report's "Ensembles" table.
        #[arg(long, value_name = "K")]
        ensemble: Option<usize>,
    },
    /// Success per checkpoint × task × run at a version, with Wilson intervals and Newcombe
    /// intervals against a baseline run.
    Scoreboard(scoreboard_cmd::ScoreboardArgs),
    /// Is B better than A yet? An anytime-valid comparison of two checkpoints or runs, per task
    /// and pooled; exits 0 (B not worse), 1 (B worse) or 2 (undecided) for CI pipelines.
    Compare(compare_cmd::CompareArgs),
    /// A policy's aliases (`prod`): list, move (protected ones only on a decided comparison), history.
    Alias {
        #[command(subcommand)]
        command: compare_cmd::AliasCommand,
    },
    /// Write a rerun recording (.rrd) of success vs failure trajectories and verifier scores.
    View(view_cmd::ViewArgs),
    /// Developer tools used by the tests.
    #[command(hide = true)]
    Dev {
        #[command(subcommand)]
        command: dev::DevCommand,
    },
}

pub async fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Init => store_cmds::init(&cli.store).await,
        Command::Versions { json } => store_cmds::versions(&cli.store, json).await,
        Command::Episodes(a) => store_cmds::episodes(&cli.store, a).await,
        Command::Label(a) => store_cmds::label(&cli.store, a).await,
        Command::History { episode, json } => store_cmds::history(&cli.store, &episode, json).await,
        Command::Snapshot { message, actor } => store_cmds::snapshot(&cli.store, &message, &actor).await,
        Command::Gc { grace_seconds, dry_run, json } => {
            store_cmds::gc(&cli.store, grace_seconds, dry_run, json).await
        }
        Command::Split { command } => catalog_cmds::split(&cli.store, command).await,
        Command::Artifacts(a) => catalog_cmds::artifacts(&cli.store, a).await,
        Command::Monitor { command } => monitor_cmds::run(&cli.store, command).await,
        Command::Layers { episode, version, json } => {
            catalog_cmds::layers(&cli.store, episode, version, json).await
        }
        Command::Token { command } => catalog_cmds::token(&cli.store, command).await,
        Command::Automation { command } => catalog_cmds::automation(&cli.store, command).await,
        Command::Ingest(a) => serve_cmds::ingest(&cli.store, a).await,
        Command::Export(a) => export_cmd::export(&cli.store, a).await,
        Command::Rank(a) => export_cmd::rank(&cli.store, a).await,
        Command::Replay(a) => replay_cmd::run(&cli.store, a).await,
        Command::Events(a) => events_cmd::run(&cli.store, a).await,
        Command::Review { command } => review_cmds::review(&cli.store, command).await,
        Command::Serve(a) => serve_cmds::serve(&cli.store, a).await,
        Command::Openapi { write } => match write {
            Some(path) => std::fs::write(&path, api::openapi_json())
                .with_context(|| format!("write {}", path.display())),
            None => {
                print!("{}", api::openapi_json());
                Ok(())
            }
        },
        Command::Worker { id, lease_ms } => serve_cmds::worker(&cli.store, id, lease_ms).await,
        Command::Train(a) => run_cmds::train(&cli.store, a).await,
        Command::Score { artifact, input, api, token, grad, raw_actions } => {
            let opts = run_cmds::ScoreOptions { grad, raw_actions };
            run_cmds::score(&cli.store, &artifact, &input, api.as_deref(), token.as_deref(), opts).await
        }
        Command::Demo { quick, lambdas, ablation_sizes, ensemble } => {
            run_cmds::demo(&cli.store, quick, lambdas, ablation_sizes, ensemble).await
        }
        Command::Scoreboard(a) => scoreboard_cmd::scoreboard(&cli.store, a).await,
        Command::Compare(a) => compare_cmd::compare(&cli.store, a).await,
        Command::Alias { command } => compare_cmd::alias(&cli.store, command).await,
        Command::View(a) => view_cmd::view(&cli.store, a).await,
        Command::Dev { command } => dev::run(&cli.store, command).await,
    }
}

impl Cli {
    /// The server and the worker run until stopped and talk to clients over sockets.
    pub fn is_long_running(&self) -> bool {
        matches!(self.command, Command::Serve(_) | Command::Worker { .. })
    }
}

/// Prints one JSON document on stdout.
pub fn print_json<T: serde::Serialize>(v: &T) -> Result<()> {
    println!("{}", serde_json::to_string_pretty(v)?);
    Ok(())
}
