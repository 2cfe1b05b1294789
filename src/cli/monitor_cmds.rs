//! `ufops monitor`: calibrate a failure monitor on a verifier artifact's checkpoint, evaluate it
//! against labels, list, show and alias monitors (the `monitor` crate and the store's records).

use anyhow::{Context, Result};
use clap::Subcommand;
use std::io::Write;
use std::path::PathBuf;

use super::export_cmd::StoreVerifier;
use super::{print_json, StoreArgs};
use store_artifacts::{Artifacts, Monitors};

#[derive(Subcommand, Debug)]
pub enum MonitorCommand {
    /// Calibrate a monitor for a verifier artifact: a threshold on its per-step scores so that
    /// on a successful episode of the artifact's checkpoint the alarm fires with probability at
    /// most --alpha (split conformal prediction on the labeled successes it did not train on),
    /// measured on held-out episodes, stored and aliased `latest`. The guarantee holds on average
    /// over calibration draws; with --confidence it holds for this calibration with that
    /// probability (training-conditional threshold).
    Calibrate {
        /// The verifier artifact: id or POLICY/CHECKPOINT/KIND@ALIAS.
        #[arg(long)]
        artifact: String,
        /// The false-alarm rate on successful episodes to guarantee (at most).
        #[arg(long, default_value_t = 0.1)]
        alpha: f64,
        /// 1 − δ: set the training-conditional threshold, whose false-alarm rate is at most
        /// --alpha with probability at least this over the draw of the calibration episodes
        /// (needs at least ln δ / ln(1 − α) calibration successes: 22 at α = δ = 0.1).
        #[arg(long)]
        confidence: Option<f64>,
        /// Weight of the past in the moving average of the risk 1 − score (0: per step).
        #[arg(long, default_value_t = 0.8)]
        smoothing: f64,
        /// Draws the calibration episodes.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Share of the successes to calibrate on (the rest measure the false-alarm rate).
        #[arg(long, default_value_t = 0.5)]
        calibration_fraction: f64,
        /// The store version whose labels to read (default: the head).
        #[arg(long)]
        version: Option<i64>,
        /// Also point this alias of the checkpoint's monitors at it.
        #[arg(long)]
        alias: Option<String>,
        #[arg(long, env = "USER", default_value = "cli")]
        actor: String,
        #[arg(long)]
        json: bool,
    },
    /// Repeat the calibration over random draws of the calibration successes (seeds 0, 1, …),
    /// with the split-conformal and the training-conditional threshold, and measure each draw's
    /// false-alarm rate on its held-out successes and detection rate on the failures: how often
    /// each threshold's false-alarm rate exceeds --alpha. Stores nothing.
    Draws {
        /// The verifier artifact: id or POLICY/CHECKPOINT/KIND@ALIAS.
        #[arg(long)]
        artifact: String,
        #[arg(long, default_value_t = 0.1)]
        alpha: f64,
        /// 1 − δ of the training-conditional threshold.
        #[arg(long, default_value_t = 0.9)]
        confidence: f64,
        /// How many calibration draws.
        #[arg(long, default_value_t = 200)]
        draws: u64,
        #[arg(long, default_value_t = 0.8)]
        smoothing: f64,
        #[arg(long, default_value_t = 0.5)]
        calibration_fraction: f64,
        #[arg(long)]
        version: Option<i64>,
        /// Every draw's figures too, as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Evaluate a monitor against labels: false-alarm rate on held-out successes (Wilson 95%),
    /// detection rate on failures, lead time before a failure's labeled span or end.
    Evaluate {
        /// Monitor: id or POLICY/CHECKPOINT@ALIAS.
        monitor: String,
        /// The store version to evaluate at (default: the monitor's own: its calibration's figures).
        #[arg(long)]
        version: Option<i64>,
        /// Write every evaluated step (episode, step, score, statistic, alarm) as JSON lines.
        #[arg(long, value_name = "PATH")]
        trace: Option<PathBuf>,
        #[arg(long)]
        json: bool,
    },
    /// List monitors.
    List {
        #[arg(long)]
        policy: Option<String>,
        #[arg(long)]
        checkpoint: Option<String>,
        #[arg(long)]
        artifact: Option<String>,
        #[arg(long)]
        json: bool,
    },
    /// Print a monitor's record (the JSON `steer::Monitor` and `ufops.Monitor` load), or write it.
    Show {
        monitor: String,
        #[arg(long, value_name = "PATH")]
        out: Option<PathBuf>,
    },
    /// Point an alias of the monitor's checkpoint at it.
    Alias { monitor: String, alias: String },
}

fn percent(x: Option<f64>) -> String {
    x.map_or("-".into(), |x| format!("{:.1}%", x * 100.0))
}

fn print_evaluation(e: &monitor::Evaluation) {
    println!(
        "  false alarms on held-out successes: {}/{} = {} (Wilson 95% {:.1}–{:.1}%)",
        e.false_alarms,
        e.successes,
        percent(e.false_alarm_rate),
        e.false_alarm_interval.0 * 100.0,
        e.false_alarm_interval.1 * 100.0
    );
    println!(
        "  failures detected: {}/{} = {} (Wilson 95% {:.1}–{:.1}%), {} before their onset",
        e.detected,
        e.failures,
        percent(e.detection_rate),
        e.detection_interval.0 * 100.0,
        e.detection_interval.1 * 100.0,
        e.detected_before_onset
    );
    match (e.lead_steps_median, e.lead_steps_quartiles) {
        (Some(m), Some((q1, q3))) => println!(
            "  lead time: median {m:.1} steps (quartiles {q1:.1}–{q3:.1}) before the onset ({} failures with labeled spans, \
             the others' end)",
            e.failures_with_spans
        ),
        _ => println!("  lead time: no failure detected"),
    }
}

async fn load_record(
    store: &store::Store,
    reference: &str,
) -> Result<(store_artifacts::MonitorEntry, verifier::MonitorRecord)> {
    let entry = store.resolve_monitor(reference).await?;
    let record = verifier::MonitorRecord::from_json(entry.record.to_string().as_bytes())
        .with_context(|| format!("monitor {}", entry.id))?;
    Ok((entry, record))
}

#[allow(clippy::too_many_lines, reason = "one arm per monitor subcommand, each a few calls")]
pub async fn run(args: &StoreArgs, command: MonitorCommand) -> Result<()> {
    let store = args.open().await?;
    match command {
        MonitorCommand::Calibrate {
            artifact,
            alpha,
            confidence,
            smoothing,
            seed,
            calibration_fraction,
            version,
            alias,
            actor,
            json,
        } => {
            let v = StoreVerifier::load(&store, &artifact).await?;
            let rec = store.artifact(&v.artifact).await?;
            let spec = monitor::CalibrateSpec {
                alpha,
                confidence,
                statistic: verifier::monitor::Statistic::RiskEma { smoothing },
                seed,
                calibration_fraction,
                version,
            };
            let cal = monitor::calibrate(&store, &v.verifier, &rec, &spec).await?;
            let record_json = serde_json::to_vec(&cal.record)?;
            let evaluation = serde_json::to_value(&cal.evaluation)?;
            let mut entry = store
                .put_monitor(store_artifacts::NewMonitor {
                    record_json: &record_json,
                    policy: &rec.policy,
                    checkpoint: &rec.checkpoint,
                    artifact_id: &rec.id,
                    alpha,
                    threshold: cal.record.threshold,
                    evaluation: Some(&evaluation),
                    created_by: &actor,
                })
                .await?;
            if let Some(a) = alias {
                entry = store.set_monitor_alias(&a, &entry.id).await?;
            }
            if json {
                return print_json(&entry);
            }
            println!(
                "monitor {} for artifact {} ({}/{}): alpha {alpha}, threshold {:.4} on the risk's moving average \
                 (smoothing {smoothing}), {} calibration successes at version {}; aliases {}",
                entry.id,
                rec.id,
                rec.policy,
                rec.checkpoint,
                cal.record.threshold,
                cal.record.calibration_episodes.len(),
                cal.record.version,
                entry.aliases.join(", ")
            );
            println!("  guarantee: {}", cal.record.guarantee());
            print_evaluation(&cal.evaluation);
            match &cal.marginal {
                Some((tau, e)) => {
                    println!("for comparison, the split-conformal threshold of the same episodes: {tau:.4}");
                    print_evaluation(e);
                }
                None if confidence.is_some() => println!(
                    "for comparison: too few calibration successes for a split-conformal threshold at alpha {alpha}"
                ),
                None => {}
            }
            Ok(())
        }
        MonitorCommand::Draws {
            artifact,
            alpha,
            confidence,
            draws,
            smoothing,
            calibration_fraction,
            version,
            json,
        } => {
            let v = StoreVerifier::load(&store, &artifact).await?;
            let rec = store.artifact(&v.artifact).await?;
            let spec = monitor::CalibrateSpec {
                alpha,
                confidence: Some(confidence),
                statistic: verifier::monitor::Statistic::RiskEma { smoothing },
                seed: 0,
                calibration_fraction,
                version,
            };
            let d = monitor::calibration_draws(&store, &v.verifier, &rec, &spec, draws).await?;
            if json {
                return print_json(&d);
            }
            println!(
                "{} calibration draws for artifact {} ({}/{}) at version {}: {} of {} successes calibrate, {} held \
                 out; {} failures; alpha {alpha}, confidence {confidence} (smoothing {smoothing})",
                d.draws.len(),
                rec.id,
                rec.policy,
                rec.checkpoint,
                d.version,
                d.calibration,
                d.successes,
                d.held_out,
                d.failures
            );
            println!(
                "{:<32} {:>5} {:>14} {:>10} {:>10} {:>10} {:>10} {:>10}",
                "threshold",
                "rank",
                "draws FA > α",
                "(exact)",
                "median FA",
                "mean FA",
                "median det",
                "median τ"
            );
            let conditional = format!("training-conditional ({confidence})");
            for (name, s) in
                [("split conformal (marginal)", &d.marginal), (conditional.as_str(), &d.conditional)]
            {
                println!(
                    "{:<32} {:>5} {:>14} {:>10} {:>10} {:>10} {:>10} {:>10.4}",
                    name,
                    s.rank.map_or("-".into(), |k| k.to_string()),
                    percent(Some(s.above_alpha)),
                    percent(s.above_alpha_expected),
                    percent(Some(s.false_alarm_rate_median)),
                    percent(Some(s.false_alarm_rate_mean)),
                    percent(s.detection_rate_median),
                    s.threshold_median
                );
            }
            println!(
                "FA: false-alarm rate on a draw's {} held-out successes; (exact): the share of all partitions whose \
                 held-out rate exceeds α for that rank, with distinct peaks, whatever the verifier (a rate measured on \
                 {} episodes is noisy: the guarantees are about fresh successes); det: detection rate on the failures",
                d.held_out, d.held_out
            );
            let r = &d.resampled;
            println!(
                "resampled, the pool's {} successes as the population ({} calibrations of {} drawn with replacement, \
                 each one's false-alarm rate on the whole pool): rate > α in {} of calibrations split conformal \
                 (theory {}), {} training-conditional (theory {}, at most δ = {:.2}); mean rate {} vs {}",
                d.successes,
                r.draws,
                d.calibration,
                percent(Some(r.marginal_above_alpha)),
                percent(r.marginal_expected),
                percent(Some(r.conditional_above_alpha)),
                percent(r.conditional_expected),
                1.0 - confidence,
                percent(Some(r.marginal_false_alarm_rate_mean)),
                percent(Some(r.conditional_false_alarm_rate_mean))
            );
            Ok(())
        }
        MonitorCommand::Evaluate { monitor: reference, version, trace, json } => {
            let (entry, record) = load_record(&store, &reference).await?;
            let v = StoreVerifier::load(&store, &entry.artifact_id).await?;
            let artifact = store.artifact(&entry.artifact_id).await?;
            let (evaluation, traces) =
                monitor::evaluate(&store, &v.verifier, &artifact, &record, version).await?;
            if let Some(path) = trace {
                let f =
                    std::fs::File::create(&path).with_context(|| format!("creating {}", path.display()))?;
                let mut out = std::io::BufWriter::new(f);
                for t in &traces {
                    for (k, s) in t.steps.iter().enumerate() {
                        serde_json::to_writer(
                            &mut out,
                            &serde_json::json!({
                                "episode_id": t.episode_id, "label": t.label, "step": k, "score": s.score,
                                "statistic": s.statistic, "alarm": s.alarm,
                            }),
                        )?;
                        out.write_all(b"\n")?;
                    }
                }
                out.flush()?;
            }
            if json {
                return print_json(&serde_json::json!({ "monitor": entry.id, "evaluation": evaluation }));
            }
            println!("monitor {} at version {}:", entry.id, evaluation.version);
            print_evaluation(&evaluation);
            Ok(())
        }
        MonitorCommand::List { policy, checkpoint, artifact, json } => {
            let all = store.monitors(policy.as_deref(), checkpoint.as_deref(), artifact.as_deref()).await?;
            if json {
                return print_json(&all);
            }
            println!(
                "{:<18} {:<24} {:<18} {:>6} {:>9} {:>14} {:>11}  aliases",
                "monitor", "policy/checkpoint", "artifact", "alpha", "threshold", "false alarms", "detected"
            );
            for m in all {
                let e: Option<monitor::Evaluation> =
                    m.evaluation.clone().and_then(|e| serde_json::from_value(e).ok());
                println!(
                    "{:<18} {:<24} {:<18} {:>6} {:>9.4} {:>14} {:>11}  {}",
                    m.id,
                    format!("{}/{}", m.policy, m.checkpoint),
                    m.artifact_id,
                    m.alpha,
                    m.threshold,
                    e.as_ref().map_or("-".into(), |e| percent(e.false_alarm_rate)),
                    e.as_ref().map_or("-".into(), |e| percent(e.detection_rate)),
                    m.aliases.join(",")
                );
            }
            Ok(())
        }
        MonitorCommand::Show { monitor: reference, out } => {
            let (entry, _) = load_record(&store, &reference).await?;
            let text = serde_json::to_string_pretty(&entry.record)?;
            match out {
                Some(p) => {
                    std::fs::write(&p, text + "\n").with_context(|| format!("writing {}", p.display()))?
                }
                None => println!("{text}"),
            }
            Ok(())
        }
        MonitorCommand::Alias { monitor: reference, alias } => {
            let (entry, _) = load_record(&store, &reference).await?;
            let m = store.set_monitor_alias(&alias, &entry.id).await?;
            println!("monitor {}: aliases {}", m.id, m.aliases.join(", "));
            Ok(())
        }
    }
}
