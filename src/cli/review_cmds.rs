//! `ufops review`: the review loop from a terminal. `score` stores a verifier's episode scores
//! (what the score job of `POST /v1/review/score` runs); `queue` lists episodes in a review
//! order, a page at a time (what `GET /v1/episodes?order=…` serves); `campaign` shows or sets
//! how many labelers must agree (`/v1/campaigns/{policy}`); `agreement` reports how well they
//! do (`/v1/agreement`).

use super::{print_json, StoreArgs};
use anyhow::{Context, Result};
use clap::Subcommand;
use store::{EpisodeFilter, Label};
use store_labeling::{Consensus, ReviewOrder, ReviewQueue};

#[derive(Subcommand, Debug)]
pub enum ReviewCommand {
    /// Score every current episode of a policy (or of one checkpoint) with a verifier and store
    /// the scores the review orders read.
    Score {
        #[arg(long)]
        policy: String,
        #[arg(long)]
        checkpoint: Option<String>,
        /// The verifier: an artifact id or POLICY/CHECKPOINT/KIND@ALIAS. Default: the policy's
        /// review artifact, or with --checkpoint its classifier@latest.
        #[arg(long)]
        artifact: Option<String>,
        #[arg(long)]
        json: bool,
    },
    /// List episodes in a review order: uncertain (score nearest 0.5 first), disagreement (score
    /// furthest from the label first) or source (by label source); unscored episodes last.
    Queue {
        #[arg(long, default_value = "uncertain")]
        order: String,
        #[arg(long)]
        policy: Option<String>,
        #[arg(long)]
        checkpoint: Option<String>,
        #[arg(long)]
        task: Option<String>,
        /// success | failure | unknown
        #[arg(long)]
        label: Option<String>,
        /// Read the episodes and labels of this past version (default: now).
        #[arg(long)]
        version: Option<i64>,
        /// The next page: the cursor the previous page printed.
        #[arg(long)]
        after: Option<String>,
        #[arg(long, default_value_t = 50, value_parser = clap::value_parser!(i64).range(1..=10_000))]
        limit: i64,
        #[arg(long)]
        json: bool,
    },
    /// Show a policy's labeling campaign, or set it: verdicts an episode needs, and whether
    /// labelers see each other's verdicts before giving theirs.
    Campaign {
        #[arg(long)]
        policy: String,
        #[arg(long, value_parser = clap::value_parser!(i64).range(1..=10))]
        labels_needed: Option<i64>,
        #[arg(long, requires = "labels_needed")]
        blind: Option<bool>,
        #[arg(long, env = "USER", default_value = "cli")]
        actor: String,
        #[arg(long)]
        json: bool,
    },
    /// Agreement between a policy's labelers: Cohen's κ per pair, Krippendorff's α overall.
    Agreement {
        #[arg(long)]
        policy: String,
        #[arg(long)]
        json: bool,
    },
}

fn or_dash(x: Option<f64>) -> String {
    x.map_or("-".to_string(), |v| format!("{v:.3}"))
}

pub async fn review(args: &StoreArgs, command: ReviewCommand) -> Result<()> {
    let store = args.open().await?;
    match command {
        ReviewCommand::Score { policy, checkpoint, artifact, json } => {
            let artifact_id = store
                .artifact_to_score(&policy, checkpoint.as_deref(), artifact.as_deref())
                .await?
                .with_context(|| match &checkpoint {
                    Some(c) => format!(
                        "no review artifact for {policy}/{c}: give --artifact or alias a classifier@latest"
                    ),
                    None => {
                        format!("{policy} has no review artifact setting: give --artifact or --checkpoint")
                    }
                })?;
            let scorer = super::export_cmd::StoreVerifier::load(&store, &artifact_id).await?;
            let spec = ::export::score_job::ScoreJobSpec { artifact_id, policy, checkpoint };
            let r =
                ::export::score_job::run_score_job(&store, None, &spec, &scorer.verifier, &|_| {}, &|| false)
                    .await?;
            if json {
                return print_json(&r);
            }
            println!("{} episodes scored by {}", r.episodes_scored, r.artifact_id);
            Ok(())
        }
        ReviewCommand::Queue { order, policy, checkpoint, task, label, version, after, limit, json } => {
            let order: ReviewOrder = order.parse()?;
            let filter = EpisodeFilter {
                version,
                policy,
                checkpoint,
                task,
                label: label.as_deref().map(str::parse::<Label>).transpose()?,
                ..Default::default()
            };
            let mut entries = store.review_queue(&filter, order, after.as_deref(), limit + 1).await?;
            let next_cursor = (entries.len() as i64 > limit).then(|| {
                entries.truncate(limit as usize);
                entries.last().map(|e| e.cursor.clone())
            });
            let next_cursor = next_cursor.flatten();
            if json {
                return print_json(&serde_json::json!({"entries": entries, "next_cursor": next_cursor}));
            }
            println!("{:<40} {:<8} {:>8}  artifact", "episode", "label", "score");
            for e in &entries {
                let score = e.score.map_or("-".to_string(), |s| format!("{s:.4}"));
                let artifact = e.artifact_id.as_deref().unwrap_or("-");
                println!("{:<40} {:<8} {:>8}  {artifact}", e.episode.id, e.episode.label.as_str(), score);
            }
            if let Some(c) = next_cursor {
                println!("next page: --after '{c}'");
            }
            Ok(())
        }
        ReviewCommand::Campaign { policy, labels_needed, blind, actor, json } => {
            let c = match labels_needed {
                Some(n) => store.set_campaign(&policy, n, blind.unwrap_or(false), &actor).await?,
                None => store.campaign(&policy).await?,
            };
            if json {
                return print_json(&c);
            }
            println!(
                "{}: {} verdict(s) per episode, {}",
                c.policy,
                c.labels_needed,
                if c.blind { "blind" } else { "not blind" }
            );
            Ok(())
        }
        ReviewCommand::Agreement { policy, json } => {
            let a = store.agreement(&policy).await?;
            if json {
                return print_json(&a);
            }
            println!(
                "{}: {} episodes voted ({} agreed, {} disputed, {} settled, {} pending); Krippendorff's alpha {}",
                a.policy, a.episodes_voted, a.agreed, a.disputed, a.settled, a.pending, or_dash(a.krippendorff_alpha)
            );
            for p in &a.pairs {
                println!(
                    "  {} / {}: {} common episodes, observed {}, kappa {}",
                    p.a,
                    p.b,
                    p.episodes,
                    or_dash(p.observed),
                    or_dash(p.kappa)
                );
            }
            Ok(())
        }
    }
}
