//! `ufops review`: the verifier-ordered review queue from a terminal. `score` stores a verifier's
//! episode scores (what the score job of `POST /v1/review/score` runs); `queue` lists episodes
//! in a review order, a page at a time (what `GET /v1/episodes?order=…` serves).

use super::{print_json, StoreArgs};
use anyhow::{Context, Result};
use clap::Subcommand;
use store::{EpisodeFilter, Label, ReviewOrder};

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
}

pub async fn review(args: &StoreArgs, command: ReviewCommand) -> Result<()> {
    let store = args.open().await?;
    match command {
        ReviewCommand::Score { policy, checkpoint, artifact, json } => {
            let artifact_id = store
                .artifact_to_score(&policy, checkpoint.as_deref(), artifact.as_deref())
                .await?
                .with_context(|| match &checkpoint {
                    Some(c) => format!("no review artifact for {policy}/{c}: give --artifact or alias a classifier@latest"),
                    None => format!("{policy} has no review artifact setting: give --artifact or --checkpoint"),
                })?;
            let scorer = super::export_cmd::StoreScorer::load(&store, &artifact_id).await?;
            let spec = ::export::score_job::ScoreJobSpec { artifact_id, policy, checkpoint };
            let r = ::export::score_job::run_score_job(&store, None, &spec, &scorer, &|_| {}, &|| false).await?;
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
    }
}
