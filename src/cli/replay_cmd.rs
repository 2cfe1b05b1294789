//! `ufops replay`: re-score a steered run's logged best-of-N steps with another verifier artifact
//! or fewer candidates, without the robot (the `replay` crate).

use anyhow::Result;
use clap::Args;

use super::export_cmd::StoreVerifier;
use super::{print_json, StoreArgs};

#[derive(Args, Debug)]
pub struct ReplayArgs {
    /// The run: its id, or its name (every run of that name; narrow with --policy/--checkpoint).
    #[arg(long)]
    run: String,
    /// The verifier to replay with: an artifact id or POLICY/CHECKPOINT/KIND@ALIAS. Default: the
    /// artifact the run names (its own verifier).
    #[arg(long)]
    artifact: Option<String>,
    /// Score only the first K candidates of each logged step ("would N = K have sufficed?").
    #[arg(long, value_name = "K")]
    n: Option<usize>,
    #[arg(long)]
    policy: Option<String>,
    #[arg(long)]
    checkpoint: Option<String>,
    /// The store version to read (default: the current state).
    #[arg(long)]
    version: Option<i64>,
    #[arg(long)]
    json: bool,
}

pub async fn run(store_args: &StoreArgs, a: ReplayArgs) -> Result<()> {
    let store = store_args.open().await?;
    let spec = replay::ReplaySpec {
        run: a.run.clone(),
        policy: a.policy,
        checkpoint: a.checkpoint,
        version: a.version,
        n: a.n,
    };
    let reference = match a.artifact {
        Some(r) => r,
        None => {
            let mut named: Vec<String> =
                replay::runs_named(&store, &a.run).await?.into_iter().filter_map(|r| r.artifact_id).collect();
            named.sort();
            named.dedup();
            match named.as_slice() {
                [one] => one.clone(),
                [] => anyhow::bail!("run {:?} names no artifact: pass --artifact", a.run),
                _ => anyhow::bail!(
                    "the runs named {:?} used several artifacts ({}): pass --artifact",
                    a.run,
                    named.join(", ")
                ),
            }
        }
    };
    let v = StoreVerifier::load(&store, &reference).await?;
    let r = replay::replay(&store, &v.verifier, &v.artifact, &spec).await?;
    if a.json {
        return print_json(&r);
    }
    let n = r.replay_n.map_or_else(
        || {
            format!(
                "each step's own N ({})",
                r.logged_n.iter().map(usize::to_string).collect::<Vec<_>>().join(", ")
            )
        },
        |k| {
            format!(
                "the first {k} of N = {} candidates",
                r.logged_n.iter().map(usize::to_string).collect::<Vec<_>>().join(", ")
            )
        },
    );
    println!(
        "replayed {} logged best-of-N steps of {} episodes (runs {}; {} without telemetry) with artifact {} on {n}",
        r.steps,
        r.episodes - r.episodes_without_telemetry,
        r.runs.join(", "),
        r.episodes_without_telemetry,
        r.artifact_id
    );
    println!("  logged with: {}", r.logged_artifacts.join(", "));
    println!(
        "  choice changed: {}/{} = {:.1}% (Wilson 95% {:.1}–{:.1}%)",
        r.changed,
        r.steps,
        100.0 * r.changed_fraction,
        100.0 * r.changed_interval.0,
        100.0 * r.changed_interval.1
    );
    println!(
        "  margin (replayed score of its pick − of the logged pick): mean {:.4}, median {:.4}",
        r.mean_margin, r.median_margin
    );
    if let Some(g) = r.mean_logged_regret {
        println!(
            "  on the changed steps the logging verifier scored the replayed pick {g:.4} lower on average"
        );
    }
    println!(
        "  logged choice vs a random candidate (logging verifier): +{:.4} on average; score spread {:.4}",
        r.mean_lift_over_random, r.mean_score_spread
    );
    if let Some(d) = r.max_score_difference {
        println!(
            "  same artifact and N: every score reproduced {}",
            if d == 0.0 { "bit for bit".to_string() } else { format!("within {d:e}") }
        );
    }
    Ok(())
}
