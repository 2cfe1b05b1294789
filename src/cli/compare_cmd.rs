//! `ufops compare`: the anytime-valid comparison of two arms, as a table or JSON, with a gate's
//! exit status; `ufops alias`: a policy's aliases, protected ones moved only on a decided comparison.

use super::StoreArgs;
use anyhow::{bail, Result};
use std::io::Write;
use store_compare::{Compare, PolicyAliases};

/// How to compare (shared by `compare` and `alias move`).
#[derive(clap::Args, Debug, Clone)]
pub struct CompareOptions {
    /// The probability of ever making a false claim, however often anyone looks.
    #[arg(long, default_value_t = 0.05)]
    pub alpha: f64,
    /// δ in rate units (0.05 = 5 pp): "worse" means worse by more than δ, and with δ > 0 the
    /// comparison can end in "no practical difference" or "not worse".
    #[arg(long, default_value_t = 0.0)]
    pub margin: f64,
    /// The difference the evaluation is planned to detect, as for a fixed-n power analysis: bets
    /// are sized for it (decides sooner when it is right; validity does not depend on it).
    #[arg(long)]
    pub plan_effect: Option<f64>,
    /// The episode metadata field that pairs rollouts across arms (same initial condition or
    /// seed; default `pair_key`; `source_index` or `source_name`: the episode's place in its
    /// source; `""`: no pairing, arrival order).
    #[arg(long)]
    pub pair_key: Option<String>,
    /// Compare a progress score in [0, 1] from this metadata field instead of success labels.
    #[arg(long)]
    pub progress: Option<String>,
}

#[derive(clap::Args, Debug)]
pub struct CompareArgs {
    #[arg(long)]
    pub policy: String,
    /// The baseline arm: CHECKPOINT or CHECKPOINT/RUN (`-` for episodes without a run).
    #[arg(long)]
    pub a: String,
    /// The candidate arm.
    #[arg(long)]
    pub b: String,
    /// The version whose labels count (default: the latest).
    #[arg(long)]
    pub version: Option<i64>,
    /// Only this task.
    #[arg(long)]
    pub task: Option<String>,
    #[command(flatten)]
    pub options: CompareOptions,
    /// table | json
    #[arg(long, default_value = "table")]
    pub format: String,
}

fn pct(x: f64) -> String {
    format!("{:+.1}", 100.0 * x)
}

fn print_slice(s: &store_compare::ComparisonSlice) {
    let needed = match (s.decided_at_pairs, s.more_pairs) {
        (Some(n), _) => format!("decided after {n} pairs ({} rollouts)", 2 * n),
        (None, Some(m)) => format!("about {m} more pairs ({} rollouts) at the observed rates", 2 * m),
        (None, None) => "no decision in sight at the observed rates".into(),
    };
    println!(
        "| {} | {} | {} | {:.1}% | {:.1}% | {} pp | [{}, {}] | {} | {} |",
        s.task.as_deref().unwrap_or("pooled"),
        s.decision,
        s.pairs,
        100.0 * s.rate_a,
        100.0 * s.rate_b,
        pct(s.diff),
        pct(s.confidence_sequence.0),
        pct(s.confidence_sequence.1),
        s.alpha,
        needed,
    );
}

/// Prints the comparison as a table.
pub fn print_comparison(c: &store_compare::Comparison) {
    println!(
        "# {}: {} against {} at version {} (alpha {}, margin {} pp{}; {}; {})\n",
        c.policy,
        c.b,
        c.a,
        c.version,
        c.alpha,
        100.0 * c.margin,
        c.plan_effect.map(|e| format!(", planned effect {} pp", 100.0 * e)).unwrap_or_default(),
        c.outcome,
        if c.pairing == "arrival order" {
            "paired in arrival order".to_string()
        } else {
            format!("paired by {}", c.pairing)
        },
    );
    println!("| task | decision | pairs | A | B | B − A | confidence sequence | alpha | rollouts |");
    println!("|---|---|---|---|---|---|---|---|---|");
    for s in &c.tasks {
        if c.tasks.len() > 1 {
            print_slice(s);
        }
    }
    print_slice(&c.pooled);
    let p = &c.pooled;
    if p.unpaired_a + p.unpaired_b + p.pending_a + p.pending_b > 0 {
        println!(
            "\nnot compared: {} of A and {} of B without a partner, {} of A and {} of B without an outcome yet",
            p.unpaired_a, p.unpaired_b, p.pending_a, p.pending_b
        );
    }
    println!("\ngate: {} (exit {}); method: {}", c.gate, c.exit_code, c.method);
}

fn request(
    policy: &str,
    a: store_compare::ArmSpec,
    b: store_compare::ArmSpec,
    o: &CompareOptions,
) -> store_compare::CompareRequest {
    store_compare::CompareRequest {
        alpha: o.alpha,
        margin: o.margin,
        plan_effect: o.plan_effect,
        pair_key: o.pair_key.clone(),
        progress: o.progress.clone(),
        ..store_compare::CompareRequest::new(policy, a, b)
    }
}

/// Runs the comparison and exits 0 (B not worse), 1 (B worse) or 2 (undecided).
pub async fn compare(args: &StoreArgs, a: CompareArgs) -> Result<()> {
    if !matches!(a.format.as_str(), "table" | "json") {
        bail!("--format {:?}: table or json", a.format);
    }
    let store = args.open().await?;
    let req = store_compare::CompareRequest {
        version: a.version,
        task: a.task.clone(),
        ..request(&a.policy, a.a.parse()?, a.b.parse()?, &a.options)
    };
    let c = store.compare(&req).await?;
    if a.format == "json" {
        super::print_json(&c)?;
    } else {
        print_comparison(&c);
    }
    std::io::stdout().flush()?;
    std::process::exit(c.exit_code)
}

#[derive(clap::Subcommand, Debug)]
pub enum AliasCommand {
    /// A policy's aliases, with the evidence of their last move.
    List {
        #[arg(long)]
        policy: String,
        #[arg(long)]
        json: bool,
    },
    /// Point an alias at CHECKPOINT[/RUN]. A protected alias moves only when the comparison of the
    /// new target against the current one decides "not worse" on every task (exit 1 otherwise).
    Move {
        #[arg(long)]
        policy: String,
        #[arg(long)]
        alias: String,
        #[arg(long)]
        to: String,
        /// Protect the alias from now on.
        #[arg(long)]
        protect: bool,
        #[command(flatten)]
        options: CompareOptions,
        #[arg(long, default_value = "cli")]
        actor: String,
    },
    /// An alias's moves with their evidence.
    History {
        #[arg(long)]
        policy: String,
        #[arg(long)]
        alias: String,
        #[arg(long)]
        json: bool,
    },
}

fn evidence_line(e: Option<&store_compare::Comparison>) -> String {
    match e {
        None => "no comparison (first or unprotected move)".into(),
        Some(c) => format!(
            "{} against {} at version {}: {} ({} pairs, confidence sequence [{}, {}] pp, alpha {}, margin {} pp)",
            c.b,
            c.a,
            c.version,
            c.gate,
            c.pooled.pairs,
            pct(c.pooled.confidence_sequence.0),
            pct(c.pooled.confidence_sequence.1),
            c.alpha,
            100.0 * c.margin
        ),
    }
}

/// Prints a policy's aliases (also the tail of `ufops artifacts --policy P`).
pub fn print_aliases(aliases: &[store_compare::PolicyAlias]) {
    for a in aliases {
        println!(
            "{}@{} -> {}{}  moved {} by {}; evidence: {}",
            a.policy,
            a.alias,
            a.target,
            if a.protected { " (protected)" } else { "" },
            a.updated_at,
            a.actor,
            evidence_line(a.evidence.as_ref())
        );
    }
}

pub async fn alias(args: &StoreArgs, command: AliasCommand) -> Result<()> {
    let store = args.open().await?;
    match command {
        AliasCommand::List { policy, json } => {
            let aliases = store.policy_aliases(&policy).await?;
            if json {
                return super::print_json(&aliases);
            }
            print_aliases(&aliases);
        }
        AliasCommand::Move { policy, alias, to, protect, options, actor } => {
            let mv = store_compare::MoveAlias {
                protect: protect.then_some(true),
                alpha: options.alpha,
                margin: options.margin,
                plan_effect: options.plan_effect,
                pair_key: options.pair_key.clone(),
                progress: options.progress.clone(),
                ..store_compare::MoveAlias::new(&policy, &alias, to.parse()?, &actor)
            };
            match store.move_policy_alias(&mv).await {
                Ok(a) => print_aliases(&[a]),
                Err(store::StoreError::Conflict(msg)) => {
                    eprintln!("error: {msg}");
                    std::process::exit(1);
                }
                Err(e) => return Err(e.into()),
            }
        }
        AliasCommand::History { policy, alias, json } => {
            let moves = store.policy_alias_history(&policy, &alias).await?;
            if json {
                return super::print_json(&moves);
            }
            for m in &moves {
                println!(
                    "#{} {} {} -> {} by {}; evidence: {}",
                    m.id,
                    m.created_at,
                    m.from_target.as_deref().unwrap_or("(new)"),
                    m.to_target,
                    m.actor,
                    evidence_line(m.evidence.as_ref())
                );
            }
        }
    }
    Ok(())
}
