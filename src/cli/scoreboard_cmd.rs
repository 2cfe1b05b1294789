//! `ufops scoreboard`: the store's scoreboard as a table, JSON or CSV.

use super::StoreArgs;
use anyhow::{bail, Result};
use store_compare::Scoreboards;

#[derive(clap::Args, Debug)]
pub struct ScoreboardArgs {
    #[arg(long)]
    pub policy: String,
    /// The version whose frozen labels count (default: the latest; `ufops snapshot` freezes
    /// label changes made since).
    #[arg(long)]
    pub version: Option<i64>,
    #[arg(long)]
    pub checkpoint: Option<String>,
    #[arg(long)]
    pub task: Option<String>,
    /// The baseline run (default `base`; `-` for episodes ingested without a run).
    #[arg(long)]
    pub baseline: Option<String>,
    /// The baseline's checkpoint (default: each row's own).
    #[arg(long)]
    pub baseline_checkpoint: Option<String>,
    /// table | json | csv
    #[arg(long, default_value = "table")]
    pub format: String,
}

fn pct(x: f64) -> String {
    format!("{:.1}", 100.0 * x)
}

pub async fn scoreboard(args: &StoreArgs, a: ScoreboardArgs) -> Result<()> {
    if !matches!(a.format.as_str(), "table" | "json" | "csv") {
        bail!("--format {:?}: table, json or csv", a.format);
    }
    let store = args.open().await?;
    let req = store_compare::ScoreboardRequest {
        policy: a.policy,
        version: a.version,
        checkpoint: a.checkpoint,
        task: a.task,
        baseline: a.baseline,
        baseline_checkpoint: a.baseline_checkpoint,
    };
    let sb = store.scoreboard(&req).await?;
    match a.format.as_str() {
        "json" => super::print_json(&sb),
        "csv" => {
            print!("{}", sb.to_csv());
            Ok(())
        }
        _ => {
            println!("# {} at version {} (baseline: run {})\n", sb.policy, sb.version, sb.baseline);
            println!(
                "| checkpoint | task | run | steering | verifier | success | 95% CI (Wilson) | unlabeled | Δ to baseline | 95% CI of Δ (Newcombe) | rollouts to separate | unlabeled to flip |"
            );
            println!("|---|---|---|---|---|---|---|---|---|---|---|---|");
            for r in &sb.rows {
                let run = r.run.as_ref();
                let b = r.baseline.as_ref();
                let labeled = r.successes + r.failures;
                println!(
                    "| {} | {} | {}{} | {} | {} | {}/{} = {}% | [{}, {}] | {} | {} | {} | {} | {} |",
                    r.checkpoint,
                    r.task.as_deref().unwrap_or("-"),
                    r.run_name,
                    run.filter(|x| !x.tags.is_empty())
                        .map(|x| format!(" ({})", x.tags.join(", ")))
                        .unwrap_or_default(),
                    run.map(|x| x.steering.to_string()).unwrap_or_else(|| "-".into()),
                    verifier_cell(r),
                    r.successes,
                    labeled,
                    r.rate.map(pct).unwrap_or_else(|| "-".into()),
                    pct(r.wilson_95.0),
                    pct(r.wilson_95.1),
                    r.unlabeled,
                    b.map(|b| format!("{:+.1} pp", 100.0 * b.diff)).unwrap_or_else(|| "-".into()),
                    b.map(|b| format!("[{:+.1}, {:+.1}]", 100.0 * b.newcombe_95.0, 100.0 * b.newcombe_95.1))
                        .unwrap_or_else(|| "-".into()),
                    b.and_then(|b| b.rollouts_to_separate)
                        .map(|n| n.to_string())
                        .unwrap_or_else(|| "-".into()),
                    b.map(|b| b.unlabeled_to_flip.map(|n| n.to_string()).unwrap_or_else(|| "none".into()))
                        .unwrap_or_else(|| "-".into()),
                );
            }
            Ok(())
        }
    }
}

/// The table's verifier cell: the artifact id with its held-out AUROC and how much of it the
/// action chunk earns (the trainer's observation-only twin), flagged when unlikely to steer well.
fn verifier_cell(r: &store_compare::ScoreboardRow) -> String {
    let Some(id) = r.run.as_ref().and_then(|x| x.artifact_id.as_deref()) else { return "-".into() };
    let Some(q) = &r.verifier_quality else { return id.to_string() };
    let n = |k: &str| q[k].as_f64().map(|x| format!("{x:.3}"));
    let mut figures: Vec<String> =
        [("AUROC", "auroc"), ("action", "action_auroc"), ("obs-only", "obs_only_auroc")]
            .into_iter()
            .filter_map(|(name, k)| n(k).map(|v| format!("{name} {v}")))
            .collect();
    if q["steering_flagged"] == true {
        figures.push("FLAGGED: unlikely to steer well".into());
    }
    if figures.is_empty() {
        id.to_string()
    } else {
        format!("{id} ({})", figures.join(", "))
    }
}
