//! Splits, artifacts and tokens: thin wrappers over the store.

use super::{print_json, StoreArgs};
use anyhow::{bail, Result};
use store::{Role, SplitRequest};
use store_artifacts::Artifacts;
use store_compare::PolicyAliases;
use store_feed::Automations;

#[derive(clap::Subcommand, Debug)]
pub enum SplitCommand {
    /// Freeze a train/val split of a checkpoint's labeled episodes (on-policy), or of other
    /// checkpoints' episodes (off-policy), pinned to a store version.
    Create {
        #[arg(long)]
        policy: String,
        #[arg(long)]
        checkpoint: String,
        /// Pin to this version (default: the head, after freezing unsnapshotted label changes).
        #[arg(long)]
        version: Option<i64>,
        /// Off-policy: use the episodes of these checkpoints (CKPT of the same policy, or POLICY/CKPT).
        #[arg(long, num_args = 1..)]
        off_policy_from: Vec<String>,
        #[arg(long, default_value_t = 0.2)]
        val_fraction: f64,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Keep at most N labeled episodes, a seeded sample (nested across N for the same seed).
        #[arg(long)]
        max_episodes: Option<u64>,
        #[arg(long, env = "USER", default_value = "cli")]
        actor: String,
        #[arg(long)]
        json: bool,
    },
    /// Show a split (and with --episodes its members).
    Show {
        id: String,
        #[arg(long)]
        episodes: bool,
        #[arg(long)]
        json: bool,
    },
    /// List splits.
    List {
        #[arg(long)]
        json: bool,
    },
}

pub async fn split(args: &StoreArgs, cmd: SplitCommand) -> Result<()> {
    let store = args.open().await?;
    match cmd {
        SplitCommand::Create {
            policy,
            checkpoint,
            version,
            off_policy_from,
            val_fraction,
            seed,
            max_episodes,
            actor,
            json,
        } => {
            let off = off_policy_from
                .iter()
                .map(|s| match s.split_once('/') {
                    Some((p, c)) => (p.to_string(), c.to_string()),
                    None => (policy.clone(), s.clone()),
                })
                .collect();
            let req = SplitRequest {
                policy,
                checkpoint,
                version,
                off_policy_from: off,
                val_fraction,
                seed,
                actor,
                max_episodes,
            };
            let s = store.create_split(&req).await?;
            if json {
                return print_json(&s);
            }
            println!(
                "{}: {} of {}/{} at version {} — {} train / {} val episodes",
                s.id, s.mode, s.policy, s.checkpoint, s.version, s.train_episodes, s.val_episodes
            );
            print_checkpoint_steps(&s);
        }
        SplitCommand::Show { id, episodes, json } => {
            let s = store.split(&id).await?;
            let members = if episodes { Some(store.split_episodes(&id).await?) } else { None };
            if json {
                return print_json(&serde_json::json!({ "split": s, "episodes": members }));
            }
            println!(
                "{} ({}) {}/{} version {} seed {} val {:.2}",
                s.id, s.mode, s.policy, s.checkpoint, s.version, s.seed, s.val_fraction
            );
            println!(
                "sources: {:?}; {} train / {} val",
                s.source_checkpoints, s.train_episodes, s.val_episodes
            );
            print_checkpoint_steps(&s);
            for m in members.unwrap_or_default() {
                println!("  {:<20} {:<5} {}", m.episode_id, m.part, m.label);
            }
        }
        SplitCommand::List { json } => {
            let all = store.splits().await?;
            if json {
                return print_json(&all);
            }
            for s in all {
                println!(
                    "{}  {:<10} {}/{} v{} {}+{}",
                    s.id, s.mode, s.policy, s.checkpoint, s.version, s.train_episodes, s.val_episodes
                );
            }
        }
    }
    Ok(())
}

/// Per checkpoint: the share of its steps that are the policy's own (before a human took over),
/// which is what training uses.
fn print_checkpoint_steps(s: &store::SplitRecord) {
    for c in &s.checkpoint_steps {
        println!(
            "  {}/{}: on-policy {:.1}% of steps ({} of {}; {} of {} episodes taken over by a human)",
            c.policy,
            c.checkpoint,
            100.0 * c.on_policy_fraction,
            c.on_policy_steps,
            c.steps,
            c.episodes_taken_over,
            c.episodes
        );
    }
}

#[derive(clap::Args, Debug)]
pub struct ArtifactsArgs {
    #[command(subcommand)]
    pub command: Option<ArtifactCommand>,
    #[arg(long)]
    pub policy: Option<String>,
    #[arg(long)]
    pub checkpoint: Option<String>,
    #[arg(long)]
    pub kind: Option<String>,
    #[arg(long)]
    pub json: bool,
}

#[derive(clap::Subcommand, Debug)]
pub enum ArtifactCommand {
    /// Point NAME (for the artifact's policy, checkpoint and kind) at ARTIFACT.
    Alias { name: String, artifact: String },
    /// Show one artifact (an id or POLICY/CHECKPOINT/KIND@ALIAS).
    Show {
        artifact: String,
        #[arg(long)]
        json: bool,
    },
    /// Copy an artifact's files into a directory (checking their sha256).
    Download { artifact: String, dir: std::path::PathBuf },
}

pub async fn artifacts(args: &StoreArgs, a: ArtifactsArgs) -> Result<()> {
    let store = args.open().await?;
    match a.command {
        None => {
            let list =
                store.artifacts(a.policy.as_deref(), a.checkpoint.as_deref(), a.kind.as_deref()).await?;
            if a.json {
                return print_json(&list);
            }
            for r in list {
                let m = &r.config["metrics"];
                // Verifier quality on the split's held-out samples (classifier calibration).
                let f = &m["final"];
                let num = |v: &serde_json::Value| {
                    v.as_f64().map(|x| format!("{x:.3}")).unwrap_or_else(|| "-".into())
                };
                let sensitivity = verifier::ActionSensitivity::from_metrics(m)
                    .map(|s| format!("  {}", s.summary()))
                    .unwrap_or_default();
                println!(
                    "{}  {:<10} {}/{}  split {}  aliases [{}]  val_loss {}  auroc {}  acc {}  brier {}  ece {}{sensitivity}",
                    r.id,
                    r.kind,
                    r.policy,
                    r.checkpoint,
                    r.split_id.as_deref().unwrap_or("-"),
                    r.aliases.join(", "),
                    num(&f["best_val_loss"]),
                    num(&f["val_auc"]),
                    num(&f["val_calibration"]["accuracy"]),
                    num(&f["val_calibration"]["brier"]),
                    num(&f["val_calibration"]["ece"]),
                );
            }
            // The policy's aliases (`prod`) and the evidence of their last move.
            if let Some(policy) = &a.policy {
                let aliases = store.policy_aliases(policy).await?;
                if !aliases.is_empty() {
                    println!();
                    super::compare_cmd::print_aliases(&aliases);
                }
            }
        }
        Some(ArtifactCommand::Alias { name, artifact }) => {
            let id = store.resolve_artifact(&artifact).await?.id;
            let r = store.set_alias(&name, &id).await?;
            println!("{}/{}/{}@{name} -> {}", r.policy, r.checkpoint, r.kind, r.id);
        }
        Some(ArtifactCommand::Show { artifact, json }) => {
            let r = store.resolve_artifact(&artifact).await?;
            if json {
                return print_json(&r);
            }
            println!("{} {} {}/{} aliases [{}]", r.id, r.kind, r.policy, r.checkpoint, r.aliases.join(", "));
            for f in &r.files {
                println!("  {:<20} {:>10} bytes  sha256 {}", f.name, f.size_bytes, f.sha256);
            }
            println!("{}", serde_json::to_string_pretty(&r.config["metrics"])?);
        }
        Some(ArtifactCommand::Download { artifact, dir }) => {
            let id = store.resolve_artifact(&artifact).await?.id;
            store.download_artifact(&id, &dir).await?;
            println!("artifact {id} written to {}", dir.display());
        }
    }
    Ok(())
}

#[derive(clap::Subcommand, Debug)]
pub enum TokenCommand {
    /// Create an API token; the secret is shown once.
    Create {
        #[arg(long)]
        name: String,
        /// viewer | labeler | trainer | admin
        #[arg(long)]
        role: String,
        #[arg(long)]
        json: bool,
    },
    List {
        #[arg(long)]
        json: bool,
    },
    Revoke {
        id: String,
    },
}

pub async fn token(args: &StoreArgs, cmd: TokenCommand) -> Result<()> {
    let store = args.open().await?;
    match cmd {
        TokenCommand::Create { name, role, json } => {
            let role: Role = role.parse()?;
            let (secret, rec) = store.create_token(&name, role).await?;
            if json {
                return print_json(&serde_json::json!({ "token": secret, "record": rec }));
            }
            eprintln!(
                "token {} ({}, {}) — store the secret now, it is not shown again:",
                rec.id,
                rec.name,
                rec.role.as_str()
            );
            println!("{secret}");
        }
        TokenCommand::List { json } => {
            let all = store.tokens().await?;
            if json {
                return print_json(&all);
            }
            for t in all {
                println!(
                    "{}  {:<16} {:<8} {}{}",
                    t.id,
                    t.name,
                    t.role.as_str(),
                    t.created_at,
                    if t.revoked_at.is_some() { "  revoked" } else { "" }
                );
            }
        }
        TokenCommand::Revoke { id } => {
            if id.is_empty() {
                bail!("token id is empty");
            }
            store.revoke_token(&id).await?;
            println!("token {id} revoked");
        }
    }
    Ok(())
}

pub async fn layers(
    args: &StoreArgs,
    episode: Option<String>,
    version: Option<i64>,
    json: bool,
) -> Result<()> {
    let store = args.open().await?;
    if let Some(id) = episode {
        let held = store.episode_layers(&id, version).await?;
        if json {
            return print_json(&held);
        }
        println!("{:<32} {:>6} {:>8}  producer", "layer", "dim", "version");
        for l in held {
            println!("{:<32} {:>6} {:>8}  {}", l.layer, l.dim, l.version_added, &l.producer_hash[..12]);
        }
        return Ok(());
    }
    let all = store.layers().await?;
    if json {
        return print_json(&all);
    }
    println!("{:<32} {:>6} {:>9} {:>8}  producer", "layer", "dim", "episodes", "version");
    for l in all {
        println!(
            "{:<32} {:>6} {:>9} {:>8}  {} {}",
            l.name,
            l.dim,
            l.episodes,
            l.version,
            &l.producer_hash[..12],
            l.producer
        );
    }
    Ok(())
}

#[derive(clap::Subcommand, Debug)]
pub enum AutomationCommand {
    /// Declare an automation: a rule that queues jobs from the change feed (api/README.md,
    /// *Automations*). It runs in `ufops serve`.
    Add {
        #[arg(long)]
        policy: String,
        /// train_on_labels | score_on_publish | scoreboard_on_run_labeled
        #[arg(long)]
        rule: String,
        /// The rule's parameters as JSON, e.g. '{"min_labeled": 200, "chunk_len": 16}'.
        #[arg(long, default_value = "{}")]
        params: String,
        #[arg(long, default_value = "cli")]
        actor: String,
        #[arg(long)]
        json: bool,
    },
    List {
        #[arg(long)]
        policy: Option<String>,
        #[arg(long)]
        json: bool,
    },
    /// Delete an automation (the jobs it queued go on).
    Rm {
        id: String,
        #[arg(long, default_value = "cli")]
        actor: String,
    },
}

pub async fn automation(args: &StoreArgs, cmd: AutomationCommand) -> Result<()> {
    let store = args.open().await?;
    match cmd {
        AutomationCommand::Add { policy, rule, params, actor, json } => {
            let params: serde_json::Value =
                serde_json::from_str(&params).map_err(|e| anyhow::anyhow!("--params is not JSON: {e}"))?;
            let a = store.create_automation(&policy, rule.parse()?, &params, &actor).await?;
            if json {
                return print_json(&a);
            }
            println!("{}  {}  {}  {}", a.id, a.policy, a.rule.as_str(), a.params);
        }
        AutomationCommand::List { policy, json } => {
            let all = store.automations(policy.as_deref()).await?;
            if json {
                return print_json(&all);
            }
            for a in all {
                println!(
                    "{}  {:<12} {:<26} fired {:<4} at event {}  {}",
                    a.id,
                    a.policy,
                    a.rule.as_str(),
                    a.fired,
                    a.cursor_seq,
                    a.params
                );
            }
        }
        AutomationCommand::Rm { id, actor } => {
            store.delete_automation(&id, &actor).await?;
            println!("automation {id} deleted");
        }
    }
    Ok(())
}
