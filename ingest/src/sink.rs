//! What a format reader produces: the source's metadata first, then media files and episodes.
//! Readers are plain synchronous Rust; the async glue in [`crate::pipeline`] runs them on a
//! blocking thread and forwards what they emit to the store through a bounded channel.

use crate::error::{IngestError, Result};
use crate::model::{EpisodeInput, ExtraColumn, Frames, MediaFile};

/// Pulls every streamed camera of `episode` to its end (a reader's errors in its frames surface
/// here, as they would in the store's writer), keeping the frames in memory when `keep`.
pub fn pull_frames(episode: &mut EpisodeInput, keep: bool) -> Result<()> {
    for im in &mut episode.images {
        if matches!(im.frames, Frames::Stream(_)) {
            let frames = std::mem::take(&mut im.frames);
            if keep {
                im.frames = Frames::Encoded(
                    frames.collect_encoded().map_err(|e| IngestError::Frames(e.to_string()))?,
                );
            } else {
                for f in frames {
                    f.map_err(|e| IngestError::Frames(e.to_string()))?;
                }
            }
        }
    }
    Ok(())
}

/// What the reader learned about the source before any episode (format + metadata JSON).
#[derive(Debug, Clone, PartialEq)]
pub struct SourceMeta {
    pub format: String,
    pub metadata: serde_json::Value,
}

pub trait EpisodeSink {
    /// Called exactly once, before any media or episode.
    fn source(&mut self, meta: SourceMeta) -> Result<()>;
    /// A media file that later episodes reference (by sha256). May be called once per file.
    fn media(&mut self, file: MediaFile) -> Result<()>;
    fn episode(&mut self, episode: EpisodeInput) -> Result<()> {
        self.episode_with_extras(episode, Vec::new())
    }
    /// An episode and the per-step arrays of the source the step model has no place for
    /// (stored as `extra.<name>` columns, so an export can give them back).
    fn episode_with_extras(&mut self, episode: EpisodeInput, extras: Vec<ExtraColumn>) -> Result<()>;
}

/// A sink that keeps everything in memory (tests, small files, fuzzing); streamed cameras are
/// collected into memory.
#[derive(Debug, Default)]
pub struct CollectSink {
    pub source: Option<SourceMeta>,
    pub media: Vec<MediaFile>,
    pub episodes: Vec<EpisodeInput>,
    /// The extra columns of each episode (same order as `episodes`).
    pub extras: Vec<Vec<ExtraColumn>>,
}

impl EpisodeSink for CollectSink {
    fn source(&mut self, meta: SourceMeta) -> Result<()> {
        self.source = Some(meta);
        Ok(())
    }
    fn media(&mut self, file: MediaFile) -> Result<()> {
        self.media.push(file);
        Ok(())
    }
    fn episode_with_extras(&mut self, mut episode: EpisodeInput, extras: Vec<ExtraColumn>) -> Result<()> {
        pull_frames(&mut episode, true)?;
        self.episodes.push(episode);
        self.extras.push(extras);
        Ok(())
    }
}

/// A sink that only counts (used by fuzzing and benchmarks of the reader alone); streamed
/// cameras are pulled to their end and dropped, so a reader's errors in them surface.
#[derive(Debug, Default)]
pub struct CountSink {
    pub episodes: usize,
    pub steps: usize,
    pub media: usize,
}

impl EpisodeSink for CountSink {
    fn source(&mut self, _meta: SourceMeta) -> Result<()> {
        Ok(())
    }
    fn media(&mut self, _file: MediaFile) -> Result<()> {
        self.media += 1;
        Ok(())
    }
    fn episode_with_extras(&mut self, mut episode: EpisodeInput, _extras: Vec<ExtraColumn>) -> Result<()> {
        pull_frames(&mut episode, false)?;
        self.episodes += 1;
        self.steps += episode.len();
        Ok(())
    }
}
