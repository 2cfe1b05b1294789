//! `ufops export`: a version, split or filter of the store as a LeRobot v3.0 dataset or a
//! robomimic HDF5 file (the export crate).

use super::{print_json, StoreArgs};
use anyhow::{bail, Result};
use std::io::IsTerminal;
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
pub struct ExportArgs {
    /// The new dataset folder (lerobot) or .hdf5 file (robomimic); must not exist.
    pub out: PathBuf,
    /// lerobot (v3.0) | robomimic
    #[arg(long)]
    pub format: String,
    /// Store version (default: the head). Labels are the ones frozen in it.
    #[arg(long)]
    pub version: Option<i64>,
    /// A split id: its episodes at its version (robomimic: mask/train and mask/valid).
    #[arg(long)]
    pub split: Option<String>,
    #[arg(long)]
    pub policy: Option<String>,
    #[arg(long)]
    pub checkpoint: Option<String>,
    #[arg(long)]
    pub task: Option<String>,
    /// success | failure | unknown
    #[arg(long)]
    pub label: Option<String>,
    #[arg(long)]
    pub tag: Option<String>,
    #[arg(long)]
    pub json: bool,
}

pub async fn export(args: &StoreArgs, a: ExportArgs) -> Result<()> {
    let store = args.open().await?;
    let sel = ::export::Selection {
        version: a.version,
        split: a.split.clone(),
        policy: a.policy.clone(),
        checkpoint: a.checkpoint.clone(),
        task: a.task.clone(),
        label: a.label.as_deref().map(str::parse).transpose()?,
        tag: a.tag.clone(),
    };
    let selected = ::export::select(&store, &sel).await?;
    let bar = (!a.json && std::io::stderr().is_terminal()).then(|| {
        let b = indicatif::ProgressBar::new(selected.episodes.len() as u64);
        b.set_style(
            indicatif::ProgressStyle::with_template("{spinner} [{elapsed_precise}] [{bar:30}] {pos}/{len} episodes")
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
                .progress_chars("=> "),
        );
        b
    });
    let tick = |done: usize, _total: usize| {
        if let Some(b) = &bar {
            b.set_position(done as u64);
        }
    };
    let progress: ::export::Progress<'_> = Some(&tick);
    let report = match a.format.as_str() {
        "lerobot" => ::export::lerobot::export(&store, &selected, &a.out, progress).await,
        "robomimic" => ::export::robomimic::export(&store, &selected, &a.out, progress).await,
        other => bail!("--format {other:?}: expected lerobot or robomimic"),
    };
    if let Some(b) = &bar {
        b.finish_and_clear();
    }
    let report = report?;
    if a.json {
        return print_json(&report);
    }
    println!(
        "exported {} episodes, {} frames of version {} as {} to {} ({:.1} MB) — labels: {} success, {} failure, {} unknown",
        report.episodes,
        report.frames,
        report.version,
        report.format,
        report.path.display(),
        report.bytes as f64 / 1e6,
        report.labels.success,
        report.labels.failure,
        report.labels.unknown
    );
    for w in &report.warnings {
        eprintln!("warning: {w}");
    }
    Ok(())
}
