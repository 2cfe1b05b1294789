//! The async glue: one ingest = one store version, all or nothing.
//!
//! The format reader runs on a blocking thread and pushes into a bounded channel (so memory stays
//! bounded: at most [`CHANNEL_DEPTH`] episodes in flight); the source's sha256 is computed on a
//! second blocking thread at the same time. Once the hash and the source metadata are known the
//! store's `IngestWriter` is opened and fed; any error aborts it, so the store stays exactly as
//! it was.

use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use tokio::sync::mpsc;

use crate::error::{IngestError, Result};
use crate::model::{EpisodeInput, Label, MediaFile, SourceInput};
use crate::options::{Format, IngestOptions, ReadOptions};
use crate::sink::{EpisodeSink, SourceMeta};

/// Episodes (or media files) buffered between the reader thread and the store writer.
pub const CHANNEL_DEPTH: usize = 4;

#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct LabelCounts {
    pub success: usize,
    pub failure: usize,
    pub unknown: usize,
}

/// What one `ufops ingest` did.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct IngestReport {
    pub path: PathBuf,
    pub format: String,
    pub sha256: String,
    /// The new version, or the version that already holds this source (`already_ingested`).
    pub version: i64,
    /// True when the same content was ingested before: nothing was written.
    pub already_ingested: bool,
    pub episodes: usize,
    pub steps: u64,
    pub labels: LabelCounts,
    /// Size of the source (file, or all files of the folder).
    pub bytes: u64,
    pub media_files: usize,
    /// Things worth telling the user (e.g. episodes left out by `--recover`).
    pub notes: Vec<String>,
}

impl std::fmt::Display for IngestReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.already_ingested {
            return write!(
                f,
                "{} (sha256 {}) is already in the store: version {} holds it; nothing to do",
                self.path.display(),
                &self.sha256[..12.min(self.sha256.len())],
                self.version
            );
        }
        write!(
            f,
            "ingested {} ({}, {:.1} MB) as version {}: {} episodes, {} steps, labels: {} success / {} failure / {} unknown",
            self.path.display(),
            self.format,
            self.bytes as f64 / 1e6,
            self.version,
            self.episodes,
            self.steps,
            self.labels.success,
            self.labels.failure,
            self.labels.unknown
        )?;
        if self.media_files > 0 {
            write!(f, ", {} media files", self.media_files)?;
        }
        for n in &self.notes {
            write!(f, "\nnote: {n}")?;
        }
        Ok(())
    }
}

enum Msg {
    Source(SourceMeta),
    Media(MediaFile),
    Episode(Box<EpisodeInput>),
}

struct ChannelSink {
    tx: mpsc::Sender<Msg>,
}

impl ChannelSink {
    fn send(&self, m: Msg) -> Result<()> {
        self.tx.blocking_send(m).map_err(|_| IngestError::Cancelled)
    }
}

impl EpisodeSink for ChannelSink {
    fn source(&mut self, meta: SourceMeta) -> Result<()> {
        self.send(Msg::Source(meta))
    }
    fn media(&mut self, file: MediaFile) -> Result<()> {
        self.send(Msg::Media(file))
    }
    fn episode(&mut self, episode: EpisodeInput) -> Result<()> {
        self.send(Msg::Episode(Box::new(episode)))
    }
}

fn join_err(e: tokio::task::JoinError) -> IngestError {
    if e.is_panic() {
        IngestError::Usage(format!("internal error: a reader thread panicked: {e}"))
    } else {
        IngestError::Cancelled
    }
}

struct Progress {
    bar: Option<indicatif::ProgressBar>,
}

impl Progress {
    fn new(enabled: bool, total: u64) -> Self {
        if !enabled || !std::io::stderr().is_terminal() {
            return Progress { bar: None };
        }
        let bar = indicatif::ProgressBar::new(total.max(1));
        let style = indicatif::ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] [{bar:30}] {bytes}/{total_bytes} ({bytes_per_sec}) {msg}",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
        .progress_chars("=> ");
        bar.set_style(style);
        bar.set_draw_target(indicatif::ProgressDrawTarget::stderr());
        Progress { bar: Some(bar) }
    }
    fn update(&self, bytes: u64, episodes: usize, steps: u64) {
        if let Some(b) = &self.bar {
            b.set_position(bytes);
            b.set_message(format!("{episodes} episodes, {steps} steps"));
        }
    }
    fn finish(&self) {
        if let Some(b) = &self.bar {
            b.finish_and_clear();
        }
    }
}

fn store_err(path: &Path, e: store::StoreError) -> IngestError {
    IngestError::Store(format!("{}: {e}", path.display()))
}

/// Ingests `path` into `store` as one new version (or reports the version that already holds
/// the same content). On any error nothing is committed and the error names the file.
pub async fn ingest(store: &store::Store, path: &Path, opts: &IngestOptions) -> Result<IngestReport> {
    if opts.policy.trim().is_empty() || opts.checkpoint.trim().is_empty() {
        return Err(IngestError::Usage("--policy and --checkpoint are required".into()));
    }
    let read_opts = ReadOptions::from_ingest(opts)?;
    let format = match opts.format {
        Format::Auto => crate::detect(path)?,
        f => f,
    };
    let total = source_size(path)?;

    // Hash the source on its own thread while the reader decodes.
    let hashed = Arc::new(AtomicU64::new(0));
    let hash_task = {
        let p = path.to_path_buf();
        let h = hashed.clone();
        tokio::task::spawn_blocking(move || crate::hashing::hash_path_progress(&p, Some(&h)))
    };

    let (tx, mut rx) = mpsc::channel::<Msg>(CHANNEL_DEPTH);
    let reader = {
        let p = path.to_path_buf();
        tokio::task::spawn_blocking(move || {
            let mut sink = ChannelSink { tx };
            crate::read_path_report(&p, format, &read_opts, &mut sink)
        })
    };

    let progress = Progress::new(opts.progress, total);

    // The first message is the source metadata (or the channel closes on a reader error).
    let first = rx.recv().await;
    let meta = match first {
        Some(Msg::Source(m)) => m,
        Some(_) => {
            drop(rx);
            let _ = reader.await;
            return Err(IngestError::Usage("internal error: reader sent data before the source".into()));
        }
        None => {
            let r = reader.await.map_err(join_err)?;
            let _ = hash_task.await;
            return Err(match r {
                Err(e) => e,
                Ok(_) => IngestError::invalid(path, "the reader produced nothing"),
            });
        }
    };
    let (sha256, size) = match hash_task.await.map_err(join_err)? {
        Ok(x) => x,
        Err(e) => {
            drop(rx);
            let _ = reader.await;
            return Err(e);
        }
    };

    let source = SourceInput {
        path: path.display().to_string(),
        sha256: sha256.clone(),
        format: meta.format.clone(),
        size_bytes: size,
        metadata: meta.metadata,
    };
    let mut report = IngestReport {
        path: path.to_path_buf(),
        format: meta.format,
        sha256: sha256.clone(),
        version: 0,
        already_ingested: false,
        episodes: 0,
        steps: 0,
        labels: LabelCounts::default(),
        bytes: size,
        media_files: 0,
        notes: Vec::new(),
    };
    let mut writer = match store.begin_ingest(source, &opts.policy, &opts.checkpoint).await {
        Ok(w) => w,
        Err(store::StoreError::AlreadyIngested { version, .. }) => {
            drop(rx);
            let _ = reader.await;
            progress.finish();
            report.version = version;
            report.already_ingested = true;
            return Ok(report);
        }
        Err(e) => {
            drop(rx);
            let _ = reader.await;
            progress.finish();
            return Err(store_err(path, e));
        }
    };

    // Feed the writer; on any error abort (nothing becomes visible).
    let fed: Result<()> = async {
        while let Some(m) = rx.recv().await {
            match m {
                Msg::Source(_) => {}
                Msg::Media(f) => {
                    writer.add_media(&f).await.map_err(|e| store_err(path, e))?;
                    report.media_files += 1;
                }
                Msg::Episode(ep) => {
                    report.episodes += 1;
                    report.steps += ep.len() as u64;
                    match ep.label {
                        Label::Success => report.labels.success += 1,
                        Label::Failure => report.labels.failure += 1,
                        Label::Unknown => report.labels.unknown += 1,
                    }
                    writer.add_episode(*ep).await.map_err(|e| store_err(path, e))?;
                    progress.update(hashed.load(Ordering::Relaxed), report.episodes, report.steps);
                }
            }
        }
        Ok(())
    }
    .await;
    drop(rx);
    let read_result = reader.await.map_err(join_err);
    let outcome = match (fed, read_result) {
        (Err(e), _) => Err(e),
        (Ok(()), Err(e)) => Err(e),
        (Ok(()), Ok(Err(e))) => Err(e),
        (Ok(()), Ok(Ok(out))) => Ok(out),
    };
    let outcome = match outcome {
        Ok(o) => o,
        Err(e) => {
            progress.finish();
            let _ = writer.abort().await;
            return Err(e);
        }
    };
    report.notes = outcome.notes;
    let msg = format!(
        "ingest {} {} ({} episodes, policy {}, checkpoint {})",
        report.format,
        path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default(),
        report.episodes,
        opts.policy,
        opts.checkpoint
    );
    let info = writer.commit(&msg).await.map_err(|e| store_err(path, e));
    progress.finish();
    let info = info?;
    report.version = info.version;
    Ok(report)
}

fn source_size(path: &Path) -> Result<u64> {
    let md = std::fs::metadata(path).map_err(|e| IngestError::io(path, e))?;
    if md.is_dir() {
        Ok(crate::hashing::list_files(path)?
            .iter()
            .map(|(_, p)| std::fs::metadata(p).map(|m| m.len()).unwrap_or(0))
            .sum())
    } else {
        Ok(md.len())
    }
}
