//! Where an episode's videos are, from the catalog (`episode_media`, migration 0005), so serving a
//! video needs no steps file. Ingest records the rows at commit; a steps file written before the
//! migration is indexed the first time one of its episodes' media is asked for: only its
//! `media.*` columns are read (their pages), and the file is marked done in the same transaction.

use crate::catalog::{insert_rows, RowExt, Val};
use crate::steps::MEDIA_PREFIX;
use crate::{EpisodeLocation, Store, StoreError};
use arrow::array::{Array, Float64Array, StringArray};
use store_layout::video;

/// Where one camera's frames of an episode live.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct EpisodeMedia {
    pub episode_id: String,
    pub key: String,
    /// The video object's store path (`media/<sha256>.<ext>`).
    pub path: String,
    /// From the media catalog; `None` when the object is not listed there (then ask the store).
    pub content_type: Option<String>,
    pub size_bytes: Option<u64>,
    /// Time of the episode's first and last frame inside the video, in seconds.
    pub start_seconds: f64,
    pub end_seconds: f64,
}

fn is_media_column(name: &str) -> bool {
    name.starts_with(MEDIA_PREFIX)
}

impl Store {
    /// The video `key` of an episode visible now (`media.<key>.path` in its steps).
    pub async fn episode_media(&self, id: &str, key: &str) -> Result<EpisodeMedia, StoreError> {
        let row = sqlx::query(
            "SELECT e.data_file, e.version_removed, d.media_indexed FROM episodes e \
             JOIN data_files d ON d.path = e.data_file WHERE e.id = $1",
        )
        .bind(id)
        .fetch_optional(&self.catalog().pool)
        .await?
        .ok_or_else(|| StoreError::not_found("episode", id))?;
        if row.oi("version_removed")?.is_some() {
            return Err(StoreError::not_found("episode", id));
        }
        if row.oi("media_indexed")?.is_none() {
            self.index_file_media(&row.s("data_file")?).await?;
        }
        let m = sqlx::query(
            "SELECT m.path, m.start_seconds, m.end_seconds, o.content_type, o.size_bytes FROM episode_media m \
             LEFT JOIN media_objects o ON o.path = m.path WHERE m.episode_id = $1 AND m.media_key = $2",
        )
        .bind(id)
        .bind(key)
        .fetch_optional(&self.catalog().pool)
        .await?
        .ok_or_else(|| StoreError::not_found("media", format!("{key:?} of episode {id}")))?;
        Ok(EpisodeMedia {
            episode_id: id.to_string(),
            key: key.to_string(),
            path: m.s("path")?,
            content_type: m.os("content_type")?,
            size_bytes: m.oi("size_bytes")?.and_then(|s| u64::try_from(s).ok()),
            start_seconds: m.f("start_seconds")?,
            end_seconds: m.f("end_seconds")?,
        })
    }

    /// Records the media of every episode of a steps file written before migration 0005.
    async fn index_file_media(&self, data_file: &str) -> Result<(), StoreError> {
        let schema = self.steps_schema(data_file).await?;
        let keys: Vec<String> = schema
            .fields()
            .iter()
            .filter_map(|f| f.name().strip_prefix(MEDIA_PREFIX)?.strip_suffix(".path").map(str::to_string))
            .collect();
        let mut rows: Vec<Vec<Val>> = Vec::new();
        if !keys.is_empty() {
            let eps = sqlx::query(
                "SELECT id, row_group, COALESCE(row_offset, 0) AS row_offset, COALESCE(row_count, length) AS row_count \
                 FROM episodes WHERE data_file = $1",
            )
            .bind(data_file)
            .fetch_all(&self.catalog().pool)
            .await?;
            let mut locations = Vec::with_capacity(eps.len());
            for r in &eps {
                let id = r.s("id")?;
                locations.push(EpisodeLocation::try_from_parts(
                    &id,
                    data_file.to_string(),
                    r.i("row_group")?,
                    r.i("row_offset")?,
                    r.i("row_count")?,
                )?);
            }
            let ids: Vec<String> = locations.iter().map(|l| l.episode_id.clone()).collect();
            let mut stream = self.read_episodes_projected(locations, Some(is_media_column));
            while let Some(item) = stream.next().await {
                let ep = item?;
                let id = &ids[ep.index];
                for key in &keys {
                    let paths = ep
                        .steps
                        .column_by_name(&format!("{MEDIA_PREFIX}{key}.path"))
                        .and_then(|c| c.as_any().downcast_ref::<StringArray>());
                    let times = ep
                        .steps
                        .column_by_name(&format!("{MEDIA_PREFIX}{key}.timestamp"))
                        .and_then(|c| c.as_any().downcast_ref::<Float64Array>());
                    let (Some(paths), Some(times)) = (paths, times) else {
                        return Err(StoreError::Corrupt(format!(
                            "steps file {data_file}: media columns of {key:?} are not utf8 + float64"
                        )));
                    };
                    if paths.is_empty() || paths.is_null(0) {
                        continue;
                    }
                    let first = if times.is_empty() { 0.0 } else { times.value(0) };
                    let last = if times.is_empty() { first } else { times.value(times.len() - 1) };
                    rows.push(vec![
                        id.as_str().into(),
                        key.as_str().into(),
                        paths.value(0).into(),
                        first.into(),
                        last.into(),
                    ]);
                }
            }
        }
        let mut tx = self.catalog().begin_write().await?;
        insert_rows(
            &mut tx,
            "episode_media",
            &["episode_id", "media_key", "path", "start_seconds", "end_seconds"],
            rows,
            "ON CONFLICT DO NOTHING",
        )
        .await?;
        sqlx::query("UPDATE data_files SET media_indexed = 1 WHERE path = $1")
            .bind(data_file)
            .execute(&mut *tx)
            .await?;
        tx.commit().await?;
        Ok(())
    }
}

impl Store {
    /// The sample entry type of a stored MP4's video track (`video::video_sample_entry`), from its
    /// top-level box headers and its `moov` box: the media data is not read.
    pub async fn video_codec(&self, path: &str) -> Result<String, StoreError> {
        let size = self.object_size(path).await?;
        let mut at = 0u64;
        for _ in 0..video::MAX_TOP_LEVEL_BOXES {
            if at + 8 > size {
                break;
            }
            let head = self.get_object_range(path, at..(at + 16).min(size)).await?;
            let (kind, total, header) = video::box_header(&head, size - at)
                .ok_or_else(|| video::bad(format!("{path}: a box overruns the file")))?;
            if &kind == b"moov" {
                if total > video::MAX_MOOV_BYTES {
                    return Err(video::bad(format!("{path}: a moov box of {total} bytes")));
                }
                let moov = self.get_object_range(path, at + header..at + total).await?;
                return video::video_sample_entry(&moov)
                    .ok_or_else(|| video::bad(format!("{path}: no video track")));
            }
            at += total;
        }
        Err(video::bad(format!("{path}: no moov box")))
    }
}

#[cfg(test)]
mod tests {
    use crate::*;

    /// Ingest records each episode's video; a store from before migration 0005 is indexed on
    /// first use from the media columns alone, to the same answer.
    #[tokio::test]
    async fn media_from_the_catalog_and_backfilled() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(&StoreConfig::local(dir.path())).await.unwrap();
        let video = dir.path().join("cam.mp4");
        std::fs::write(&video, vec![7u8; 5000]).unwrap();
        let sha = sha256_hex(&std::fs::read(&video).unwrap());
        let src = SourceInput {
            path: "v".into(),
            sha256: sha256_hex(b"v"),
            format: "test".into(),
            size_bytes: 1,
            metadata: serde_json::json!({}),
        };
        let mut w = store.begin_ingest(src, "pol", "c").await.unwrap();
        let file = MediaFile {
            sha256: sha.clone(),
            local_path: video,
            content_type: "video/mp4".into(),
            size_bytes: 5000,
        };
        w.add_media(&file).await.unwrap();
        for i in 0..300u32 {
            let mut ep = crate::read::tests::episode(i, 50 + i as usize % 7);
            if i < 150 {
                let n = ep.len();
                let start = i as f64 * 10.0;
                ep.media.push(MediaColumn {
                    name: "front".into(),
                    sha256: sha.clone(),
                    timestamps: (0..n).map(|t| start + t as f64 / 10.0).collect(),
                });
            }
            w.add_episode(ep).await.unwrap();
        }
        w.commit("t").await.unwrap();
        let eps = store.episodes(&EpisodeFilter::default()).await.unwrap();
        let with = &eps[4];
        let m = store.episode_media(&with.id, "front").await.unwrap();
        assert_eq!(m.path, format!("media/{sha}.mp4"));
        assert_eq!((m.content_type.as_deref(), m.size_bytes), (Some("video/mp4"), Some(5000)));
        let n = with.length as f64;
        assert_eq!((m.start_seconds, m.end_seconds), (40.0, 40.0 + (n - 1.0) / 10.0));
        assert!(matches!(store.episode_media(&with.id, "wrist").await, Err(StoreError::NotFound { .. })));
        assert!(matches!(store.episode_media(&eps[200].id, "front").await, Err(StoreError::NotFound { .. })));

        // As if written before migration 0005: no rows, file not indexed.
        sqlx::query("DELETE FROM episode_media").execute(&store.catalog().pool).await.unwrap();
        sqlx::query("UPDATE data_files SET media_indexed = NULL")
            .execute(&store.catalog().pool)
            .await
            .unwrap();
        let before = store.fetch_counts();
        assert_eq!(store.episode_media(&with.id, "front").await.unwrap(), m);
        let fetched = store.fetch_counts().since(before).bytes_fetched;
        let size: u64 = std::fs::metadata(dir.path().join("objects").join(&with.data_file)).unwrap().len();
        assert!(fetched * 4 < size, "indexing read {fetched} bytes of a {size}-byte file");
        let rows: i64 = sqlx::query_scalar("SELECT COUNT(*) FROM episode_media")
            .fetch_one(&store.catalog().pool)
            .await
            .unwrap();
        assert_eq!(rows, 150);
        // Indexed once: the next look-up reads no steps at all.
        let before = store.fetch_counts();
        store.episode_media(&eps[10].id, "front").await.unwrap();
        assert_eq!(store.fetch_counts().since(before), FetchCounts::default());

        store.delete_episodes(std::slice::from_ref(&with.id), "t", "gone").await.unwrap();
        assert!(matches!(store.episode_media(&with.id, "front").await, Err(StoreError::NotFound { .. })));
    }
}
