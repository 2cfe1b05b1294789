//! The videos of an episode: `video` features (each mp4 located through the `video_path`
//! template, hashed and emitted once, referenced by time). Image columns are read as columns
//! (`columns.rs`).

use serde_json::{json, Map, Value};

use super::episode::Ctx;
use super::info::fill_template;
use super::meta::{EpisodeMeta, VideoRef};
use crate::error::{IngestError, Result};
use crate::model::{MediaColumn, MediaFile};
use crate::sink::EpisodeSink;

impl Ctx<'_> {
    fn media_for(
        &mut self,
        key: &str,
        v: Option<&VideoRef>,
        episode_index: u64,
        sink: &mut dyn EpisodeSink,
    ) -> Result<(MediaFile, f64)> {
        let tpl = self.info.video_path.clone().unwrap_or_else(|| {
            if self.info.is_v3() {
                "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4".into()
            } else {
                "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4".into()
            }
        });
        let (chunk, file, from) = match v {
            Some(v) => (v.chunk_index, v.file_index, v.from_timestamp),
            None => (episode_index / self.info.chunks_size, 0, 0.0),
        };
        let field = format!("`video_path` template {tpl:?} (feature {key:?}, episode {episode_index})");
        let rel = fill_template(
            &tpl,
            &[
                ("video_key", key, 0),
                ("chunk_index", "", chunk),
                ("file_index", "", file),
                ("episode_chunk", "", episode_index / self.info.chunks_size),
                ("episode_index", "", episode_index),
            ],
        )
        .map_err(|m| IngestError::invalid(self.info_path, format!("{field}: {m}")))?;
        let abs = self.confine.join(self.info_path, &field, &rel)?;
        if let Some(m) = self.emitted_media.get(&abs) {
            return Ok((m.clone(), from));
        }
        self.confine.check_inside(&abs, &field)?;
        if !abs.is_file() {
            return Err(IngestError::invalid(
                &abs,
                format!("missing video file for feature {key}, episode {episode_index}"),
            ));
        }
        let (sha, size) = crate::hashing::hash_file(&abs)?;
        let ct = if rel.ends_with(".mp4") { "video/mp4" } else { "application/octet-stream" };
        let m = MediaFile { sha256: sha, local_path: abs.clone(), content_type: ct.into(), size_bytes: size };
        sink.media(m.clone())?;
        self.emitted_media.insert(abs, m.clone());
        Ok((m, from))
    }

    /// One [`MediaColumn`] per `video` feature of episode `e` (each frame's time inside its mp4:
    /// the file's `from_timestamp` plus the row's own `timestamps`), and the episode metadata's
    /// `videos` entry.
    pub(super) fn video_columns(
        &mut self,
        e: u64,
        meta: &EpisodeMeta,
        timestamps: &[f64],
        sink: &mut dyn EpisodeSink,
    ) -> Result<(Vec<MediaColumn>, Map<String, Value>)> {
        let mut media = Vec::new();
        let mut video_md = Map::new();
        let vkeys: Vec<String> = self.info.video_keys().iter().map(|f| f.key.clone()).collect();
        for key in vkeys {
            let (m, from) = self.media_for(&key, meta.videos.get(&key), e, sink)?;
            let short = key.strip_prefix("observation.").unwrap_or(&key).to_string();
            video_md.insert(key.clone(), json!({"sha256": m.sha256, "from_timestamp": from, "file": m.local_path.strip_prefix(self.root).unwrap_or(&m.local_path).to_string_lossy()}));
            media.push(MediaColumn {
                name: short,
                sha256: m.sha256.clone(),
                timestamps: timestamps.iter().map(|t| from + t).collect(),
            });
        }
        Ok((media, video_md))
    }
}
