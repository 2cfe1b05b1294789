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
    Hash(String, u64),
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
    fn source_hash(&mut self, sha256: String, size: u64) -> Result<()> {
        self.send(Msg::Hash(sha256, size))
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
    let mut read_opts = ReadOptions::from_ingest(opts)?;
    let format = match opts.format {
        Format::Auto => crate::detect(path)?,
        f => f,
    };
    let total = source_size(path)?;

    // Hash the source on its own thread while the reader decodes; a robomimic file read whole is
    // hashed by its reader from the bytes it already holds (no second read of the file).
    let hashed = Arc::new(AtomicU64::new(0));
    read_opts.hash_source = format == Format::Robomimic
        && std::fs::metadata(path).map(|m| m.is_file()).unwrap_or(false)
        && total <= crate::robomimic::STREAMING_THRESHOLD;
    let hash_task = (!read_opts.hash_source).then(|| {
        let p = path.to_path_buf();
        let h = hashed.clone();
        tokio::task::spawn_blocking(move || crate::hashing::hash_path_progress(&p, Some(&h)))
    });

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
            if let Some(h) = hash_task {
                let _ = h.await;
            }
            return Err(match r {
                Err(e) => e,
                Ok(_) => IngestError::invalid(path, "the reader produced nothing"),
            });
        }
    };
    let meta_episodes = meta.metadata.get("num_demos").and_then(|v| v.as_u64());
    let source = SourceInput {
        path: path.display().to_string(),
        sha256: String::new(),
        format: meta.format.clone(),
        size_bytes: total,
        metadata: meta.metadata,
    };
    let mut report = IngestReport {
        path: path.to_path_buf(),
        format: meta.format,
        sha256: String::new(),
        version: 0,
        already_ingested: false,
        episodes: 0,
        steps: 0,
        labels: LabelCounts::default(),
        bytes: total,
        media_files: 0,
        notes: Vec::new(),
    };
    // The writer encodes episodes while the hash is still being computed; nothing is written to
    // object storage before the hash is known (and checked against the store).
    let mut writer = match store.begin_ingest_unhashed(source, &opts.policy, &opts.checkpoint) {
        Ok(w) => w,
        Err(e) => {
            drop(rx);
            let _ = reader.await;
            if let Some(h) = hash_task {
                let _ = h.await;
            }
            progress.finish();
            return Err(store_err(path, e));
        }
    };

    enum Fed {
        Done,
        /// The channel closed without the reader reporting the hash it was asked for.
        NoHash,
        AlreadyIngested(i64),
    }
    enum Event {
        Hash(Result<(String, u64)>),
        Msg(Option<Msg>),
    }
    let mut hash_task = hash_task;
    let mut hash_known = false;
    // Robomimic: the source's metadata says how many episodes to expect (progress without a
    // separate hashing pass to count bytes).
    let expected_episodes = meta_episodes.filter(|&n| n > 0);
    // Feed the writer; on any error abort (nothing becomes visible).
    let fed: Result<Fed> = async {
        let mut open = true;
        while open || hash_task.is_some() {
            let ev = tokio::select! {
                biased;
                h = async { hash_task.as_mut().expect("guarded").await }, if hash_task.is_some() => {
                    Event::Hash(h.map_err(join_err).and_then(|r| r))
                }
                m = rx.recv(), if open => Event::Msg(m),
            };
            let (sha256, size) = match ev {
                Event::Hash(h) => {
                    hash_task = None;
                    h?
                }
                Event::Msg(Some(Msg::Hash(sha, n))) => (sha, n),
                Event::Msg(None) => {
                    open = false;
                    continue;
                }
                Event::Msg(Some(Msg::Source(_))) => continue,
                Event::Msg(Some(Msg::Media(f))) => {
                    writer.add_media(&f).await.map_err(|e| store_err(path, e))?;
                    report.media_files += 1;
                    continue;
                }
                Event::Msg(Some(Msg::Episode(ep))) => {
                    report.episodes += 1;
                    report.steps += ep.len() as u64;
                    match ep.label {
                        Label::Success => report.labels.success += 1,
                        Label::Failure => report.labels.failure += 1,
                        Label::Unknown => report.labels.unknown += 1,
                    }
                    writer.push_episode(*ep).await.map_err(|e| store_err(path, e))?;
                    let pos = match expected_episodes {
                        Some(n) if hash_task.is_none() => total.saturating_mul(report.episodes as u64) / n,
                        _ => hashed.load(Ordering::Relaxed),
                    };
                    progress.update(pos, report.episodes, report.steps);
                    continue;
                }
            };
            // The source's hash: check the store for it; from now on files can be written.
            hash_known = true;
            report.sha256 = sha256.clone();
            report.bytes = size;
            match writer.set_source_hash(&sha256, size).await {
                Ok(()) => {}
                Err(store::StoreError::AlreadyIngested { version, .. }) => return Ok(Fed::AlreadyIngested(version)),
                Err(e) => return Err(store_err(path, e)),
            }
        }
        Ok(if hash_known { Fed::Done } else { Fed::NoHash })
    }
    .await;
    drop(rx);
    if let Some(h) = hash_task.take() {
        let _ = h.await;
    }
    let read_result = reader.await.map_err(join_err);
    if let Ok(Fed::AlreadyIngested(version)) = fed {
        progress.finish();
        let _ = writer.abort().await;
        report.version = version;
        report.already_ingested = true;
        report.episodes = 0;
        report.steps = 0;
        report.labels = LabelCounts::default();
        report.media_files = 0;
        return Ok(report);
    }
    let outcome = match (fed, read_result) {
        (Err(e), _) => Err(e),
        (Ok(_), Err(e)) => Err(e),
        (Ok(_), Ok(Err(e))) => Err(e),
        (Ok(Fed::NoHash), Ok(Ok(_))) => {
            Err(IngestError::invalid(path, "internal error: the reader did not report the file's hash"))
        }
        (Ok(_), Ok(Ok(out))) => Ok(out),
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
