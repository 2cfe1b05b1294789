//! One frame of an episode's image column (`image.<camera>`: one PNG per step), read alone: the
//! footer of the steps file comes from the cache, and parquet's push decoder, given a selection
//! of one row and a projection of one column, asks for the one page (at most
//! [`crate::steps::PAGE_MAX_BYTES`] of PNGs, cut between episodes) that holds the frame. The
//! labeling page loads frames this way as the timeline moves (`GET /v1/episodes/{id}/frames/…`).

use crate::steps::{IMAGE_PREFIX, MEDIA_PREFIX};
use crate::{Store, StoreError};
use arrow::array::{Array, ArrayRef, BinaryArray, LargeBinaryArray};
use arrow::datatypes::Schema;
use parquet::arrow::arrow_reader::{RowSelection, RowSelectionPolicy, RowSelector};
use parquet::arrow::push_decoder::ParquetPushDecoderBuilder;
use parquet::arrow::ProjectionMask;
use parquet::DecodeResult;

/// How a camera's frames are stored.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[serde(rename_all = "lowercase")]
pub enum CameraKind {
    /// A video object (`media.<name>.path` / `.timestamp` columns; served with range requests).
    Video,
    /// An image column (`image.<name>`): one PNG per step, served frame by frame.
    Image,
}

/// One camera of an episode, as its steps file's schema declares it.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct Camera {
    /// The camera's key (`agentview_image`, `observation.images.front`).
    pub name: String,
    pub kind: CameraKind,
    /// `[H, W, C]` of an image column (its `ufops.shape` metadata), when recorded.
    pub shape: Option<[usize; 3]>,
    /// An image column's frame encoding (`ufops.encoding`: `png`, or `jpeg` kept as recorded).
    pub encoding: Option<String>,
}

/// The cameras a steps schema declares, images and videos, in column order.
pub fn cameras_of(schema: &Schema) -> Vec<Camera> {
    let mut out = Vec::new();
    for f in schema.fields() {
        if let Some(name) = f.name().strip_prefix(IMAGE_PREFIX) {
            let shape = f.metadata().get("ufops.shape").and_then(|s| parse_shape(s));
            let encoding = Some(image_encoding(f.metadata()).to_string());
            out.push(Camera { name: name.to_string(), kind: CameraKind::Image, shape, encoding });
        } else if let Some(name) = f.name().strip_prefix(MEDIA_PREFIX).and_then(|n| n.strip_suffix(".path")) {
            out.push(Camera { name: name.to_string(), kind: CameraKind::Video, shape: None, encoding: None });
        }
    }
    out
}

/// An image column's encoding from its field metadata (`png` when unrecorded, as written before
/// the key existed).
fn image_encoding(meta: &std::collections::HashMap<String, String>) -> &'static str {
    match meta.get("ufops.encoding").map(|e| e.to_ascii_lowercase()).as_deref() {
        Some("jpeg") | Some("jpg") => "jpeg",
        _ => "png",
    }
}

fn parse_shape(s: &str) -> Option<[usize; 3]> {
    let dims: Vec<usize> = s
        .trim()
        .strip_prefix('[')?
        .strip_suffix(']')?
        .split(',')
        .map(|d| d.trim().parse().ok())
        .collect::<Option<_>>()?;
    <[usize; 3]>::try_from(dims).ok()
}

/// Where a frame is: the steps file, the row group and the row in it (for validators such as an
/// `ETag`: the object is immutable, so the triple names the bytes).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FrameLocation {
    pub data_file: String,
    pub row_group: usize,
    pub row: usize,
    /// The frame's encoding: `png` or `jpeg` (its MIME type is `image/<encoding>`).
    pub encoding: &'static str,
    /// The camera is a video (`media.<camera>`): the frame is decoded from it and served as a
    /// PNG (lossy when the video is: see [`crate::video`]).
    pub from_video: bool,
}

impl Store {
    /// The cameras of an episode visible now (or in `version`): its image columns and videos.
    pub async fn episode_cameras(&self, id: &str, version: Option<i64>) -> Result<Vec<Camera>, StoreError> {
        let loc = self.locate_episodes(&[id.to_string()], version).await?.remove(0);
        let schema = self.steps_schema(&loc.data_file).await?;
        Ok(cameras_of(&schema))
    }

    /// Where step `t` of an episode's image column `camera` is, checking that the episode is
    /// visible (now, or in `version`), that it has that image column and that step: each missing
    /// one is [`StoreError::NotFound`] naming it. Reads the footer (cached), no data.
    pub async fn locate_frame(
        &self,
        id: &str,
        version: Option<i64>,
        camera: &str,
        t: u64,
    ) -> Result<FrameLocation, StoreError> {
        let loc = self.locate_episodes(&[id.to_string()], version).await?.remove(0);
        let schema = self.steps_schema(&loc.data_file).await?;
        let (encoding, from_video) = match schema.field_with_name(&format!("{IMAGE_PREFIX}{camera}")) {
            Ok(field) => (image_encoding(field.metadata()), false),
            Err(_) if schema.field_with_name(&format!("{MEDIA_PREFIX}{camera}.path")).is_ok() => {
                ("png", true)
            }
            Err(_) => {
                return Err(StoreError::not_found("camera", format!("{camera:?} of episode {id}")));
            }
        };
        if t >= loc.row_count as u64 {
            return Err(StoreError::not_found(
                "step",
                format!("{t} of episode {id} (its steps are 0 to {})", loc.row_count.saturating_sub(1)),
            ));
        }
        Ok(FrameLocation {
            data_file: loc.data_file,
            row_group: loc.row_group,
            row: loc.row_offset + t as usize,
            encoding,
            from_video,
        })
    }

    /// The PNG of step `t` of an episode's image column `camera` (see [`Self::locate_frame`]):
    /// only that column's page holding the row is fetched.
    pub async fn read_frame(
        &self,
        id: &str,
        version: Option<i64>,
        camera: &str,
        t: u64,
    ) -> Result<bytes::Bytes, StoreError> {
        let at = self.locate_frame(id, version, camera, t).await?;
        self.read_frame_at(&at, camera).await
    }

    /// The PNG at a located frame. The page holding it is decoded once and kept in a small cache
    /// (the labeling page asks for neighbouring steps one after the other: a page of 84×84 PNGs
    /// holds dozens of them).
    pub async fn read_frame_at(&self, at: &FrameLocation, camera: &str) -> Result<bytes::Bytes, StoreError> {
        if at.from_video {
            return self.read_video_frame(at, camera).await;
        }
        let fm = self.file_meta(&at.data_file).await?;
        let corrupt = |why: String| StoreError::Corrupt(format!("steps file {}: {why}", at.data_file));
        let md = fm.meta.metadata();
        if at.row_group >= md.num_row_groups() {
            return Err(corrupt(format!("no row group {}", at.row_group)));
        }
        let rg_rows = md.row_group(at.row_group).num_rows().max(0) as usize;
        if at.row >= rg_rows {
            return Err(corrupt(format!(
                "row group {} has {rg_rows} rows, not {}",
                at.row_group,
                at.row + 1
            )));
        }
        let column = format!("{IMAGE_PREFIX}{camera}");
        let root = fm
            .meta
            .schema()
            .index_of(&column)
            .map_err(|_| StoreError::not_found("camera", format!("{camera:?} (an image column)")))?;
        // The rows of the page holding the frame (its leaf column's offset index), else the row alone.
        let parquet = fm.meta.parquet_schema();
        let leaf = (0..parquet.num_columns()).find(|&c| parquet.get_column_root_idx(c) == root);
        let pages = leaf.and_then(|c| Some(md.offset_index()?.get(at.row_group)?.get(c)?.page_locations()));
        let (first, end) = match pages {
            Some(pages) if !pages.is_empty() => {
                let k = pages.partition_point(|p| p.first_row_index as usize <= at.row).max(1) - 1;
                let first = (pages[k].first_row_index.max(0) as usize).min(at.row);
                let end =
                    pages.get(k + 1).map_or(rg_rows, |p| (p.first_row_index.max(0) as usize).min(rg_rows));
                (first, end.max(at.row + 1))
            }
            _ => (at.row, at.row + 1),
        };
        let key = (at.data_file.clone(), at.row_group, root, first);
        let cell = self.inner.frame_pages.cell(&key);
        let mut fresh = false;
        let rows = cell
            .get_or_try_init(|| async {
                fresh = true;
                self.decode_rows(&fm, &at.data_file, at.row_group, root, first, end - first).await
            })
            .await?
            .clone();
        if fresh {
            self.inner.frame_pages.loaded(&key, rows.get_array_memory_size());
        }
        let i = at.row - first;
        let value = if let Some(a) = rows.as_any().downcast_ref::<BinaryArray>() {
            (i < a.len() && a.is_valid(i)).then(|| bytes::Bytes::copy_from_slice(a.value(i)))
        } else if let Some(a) = rows.as_any().downcast_ref::<LargeBinaryArray>() {
            (i < a.len() && a.is_valid(i)).then(|| bytes::Bytes::copy_from_slice(a.value(i)))
        } else {
            return Err(corrupt(format!("{column} is {}, not binary", rows.data_type())));
        };
        value.ok_or_else(|| corrupt(format!("{column} has no frame at row {}", at.row)))
    }

    /// A video camera's frame at a located step: the step's `media.<camera>.path` and
    /// `.timestamp` cells are read, then the video object, and the frame shown at that time is
    /// decoded (from the key frame before it) and encoded as PNG. Videos larger than
    /// [`MAX_DECODED_VIDEO_BYTES`] are refused (the page plays them; a frame of them is not worth
    /// fetching them whole here).
    async fn read_video_frame(&self, at: &FrameLocation, camera: &str) -> Result<bytes::Bytes, StoreError> {
        let fm = self.file_meta(&at.data_file).await?;
        let corrupt = |why: String| StoreError::Corrupt(format!("steps file {}: {why}", at.data_file));
        let cell = |suffix: &str| -> Result<usize, StoreError> {
            let column = format!("{MEDIA_PREFIX}{camera}.{suffix}");
            fm.meta.schema().index_of(&column).map_err(|_| corrupt(format!("no column {column}")))
        };
        let (path_root, time_root) = (cell("path")?, cell("timestamp")?);
        let path = self.decode_rows(&fm, &at.data_file, at.row_group, path_root, at.row, 1).await?;
        let time = self.decode_rows(&fm, &at.data_file, at.row_group, time_root, at.row, 1).await?;
        let path = path
            .as_any()
            .downcast_ref::<arrow::array::StringArray>()
            .filter(|a| a.is_valid(0))
            .map(|a| a.value(0).to_string())
            .ok_or_else(|| corrupt(format!("{MEDIA_PREFIX}{camera}.path has no path at row {}", at.row)))?;
        let seconds = time
            .as_any()
            .downcast_ref::<arrow::array::Float64Array>()
            .filter(|a| a.is_valid(0))
            .map(|a| a.value(0))
            .ok_or_else(|| {
                corrupt(format!("{MEDIA_PREFIX}{camera}.timestamp has no time at row {}", at.row))
            })?;
        let size = self.objects().size(&path).await?;
        if size > MAX_DECODED_VIDEO_BYTES {
            return Err(StoreError::invalid(format!(
                "camera {camera:?} is a video of {size} bytes: frames are decoded here from videos up to \
                 {MAX_DECODED_VIDEO_BYTES} bytes; play it instead"
            )));
        }
        let mp4 = self.objects().get(&path).await?.to_vec();
        let png = tokio::task::spawn_blocking(move || crate::video::decode_frame_at(mp4, seconds)?.to_png())
            .await
            .map_err(|e| StoreError::invalid(format!("frame decoder stopped: {e}")))??;
        Ok(bytes::Bytes::from(png))
    }

    /// Rows `first..first + count` of one root column of a row group.
    async fn decode_rows(
        &self,
        fm: &crate::read::FileMeta,
        file: &str,
        row_group: usize,
        root: usize,
        first: usize,
        count: usize,
    ) -> Result<ArrayRef, StoreError> {
        let rg_rows = fm.meta.metadata().row_group(row_group).num_rows().max(0) as usize;
        let mut selectors = Vec::with_capacity(3);
        if first > 0 {
            selectors.push(RowSelector::skip(first));
        }
        selectors.push(RowSelector::select(count));
        if first + count < rg_rows {
            selectors.push(RowSelector::skip(rg_rows - first - count));
        }
        let mut decoder = ParquetPushDecoderBuilder::new_with_metadata(fm.meta.clone())
            .with_row_groups(vec![row_group])
            .with_projection(ProjectionMask::roots(fm.meta.parquet_schema(), [root]))
            .with_row_selection(RowSelection::from(selectors))
            .with_row_selection_policy(RowSelectionPolicy::Selectors)
            .with_batch_size(count.max(1))
            .build()?;
        let mut parts: Vec<ArrayRef> = Vec::new();
        loop {
            match decoder.try_decode()? {
                DecodeResult::NeedsData(ranges) => {
                    let data = fm.fetch(self, file, &ranges).await?;
                    decoder.push_ranges(ranges, data)?;
                }
                DecodeResult::Data(batch) => parts.push(batch.column(0).clone()),
                DecodeResult::Finished => break,
            }
        }
        let refs: Vec<&dyn Array> = parts.iter().map(|a| a.as_ref()).collect();
        let rows = match refs.len() {
            1 => parts.pop().expect("one part"),
            _ => arrow::compute::concat(&refs)?,
        };
        if rows.len() != count {
            return Err(StoreError::Corrupt(format!(
                "steps file {file}: read {} rows of row group {row_group}, expected {count}",
                rows.len()
            )));
        }
        Ok(rows)
    }
}

/// The largest video a frame is decoded from on request (the object is fetched whole).
pub const MAX_DECODED_VIDEO_BYTES: u64 = 256 << 20;

/// Decoded pages of image columns, by `(steps file, row group, column, first row)`, within
/// [`PAGE_CACHE_BYTES`].
pub(crate) type PageCache = crate::lru::ByteLru<PageKey, ArrayRef>;

type PageKey = (String, usize, usize, usize);

/// Bytes of decoded pages kept (a page holds at most [`crate::steps::PAGE_MAX_BYTES`] of
/// frames, so this is a few dozen pages: every camera of the episodes being labeled).
pub(crate) const PAGE_CACHE_BYTES: usize = 64 << 20;

#[cfg(test)]
mod tests {
    use crate::*;

    fn png_of(i: u32, t: usize) -> Vec<u8> {
        // Not a real PNG: the store keeps the bytes as they are. Incompressible, and large enough
        // that an episode's frames fill several pages (about 20 frames a page).
        let mut b = format!("\u{89}PNG frame {i}/{t} ").into_bytes();
        let mut x = (i as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ t as u64;
        while b.len() < 50_000 + t * 13 {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            b.push(x as u8);
        }
        b
    }

    /// A frame is the bytes written, read from its own page: far fewer bytes than the episode's
    /// image column; a missing episode, camera or step is NotFound naming it.
    #[tokio::test]
    async fn one_frame_reads_one_page() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(&StoreConfig::local(dir.path())).await.unwrap();
        let src = SourceInput {
            path: "img".into(),
            sha256: sha256_hex(b"img"),
            format: "test".into(),
            size_bytes: 1,
            metadata: serde_json::json!({}),
        };
        let mut w = store.begin_ingest(src, "pol", "c").await.unwrap();
        for i in 0..3u32 {
            let mut ep = crate::read::tests::episode(i, 120);
            for cam in ["agentview_image", "eye_in_hand_image"] {
                ep.images.push(ImageColumn {
                    name: cam.into(),
                    shape: [84, 84, 3],
                    frames: Frames::Encoded(
                        (0..120).map(|t| png_of(i + if cam.starts_with('e') { 100 } else { 0 }, t)).collect(),
                    ),
                });
            }
            w.add_episode(ep).await.unwrap();
        }
        w.commit("t").await.unwrap();
        let eps = store.episodes(&EpisodeFilter::default()).await.unwrap();
        let e = &eps[1];
        let cams = store.episode_cameras(&e.id, None).await.unwrap();
        let got: Vec<serde_json::Value> = cams.iter().map(|c| serde_json::to_value(c).unwrap()).collect();
        let want = |name: &str| serde_json::json!({"name": name, "kind": "image", "shape": [84, 84, 3], "encoding": "png"});
        assert_eq!(got, [want("agentview_image"), want("eye_in_hand_image")]);
        assert_eq!(store.locate_frame(&e.id, None, "agentview_image", 5).await.unwrap().encoding, "png");
        let i = e.source_index as u32;
        store.read_frame(&e.id, None, "agentview_image", 0).await.unwrap(); // footer cached
        let before = store.fetch_counts();
        assert_eq!(store.read_frame(&e.id, None, "agentview_image", 77).await.unwrap(), png_of(i, 77));
        let fetched = store.fetch_counts().since(before).bytes_fetched;
        let column: u64 = (0..120).map(|t| png_of(i, t).len() as u64).sum();
        assert!(fetched < column / 3, "one frame fetched {fetched} bytes of a {column}-byte column");
        assert_eq!(
            store.read_frame(&e.id, None, "eye_in_hand_image", 119).await.unwrap(),
            png_of(i + 100, 119)
        );
        // Neighbouring steps come from the page already decoded: 31 frames, a few pages fetched.
        let before = store.fetch_counts();
        for t in 60..=90usize {
            assert_eq!(
                store.read_frame(&e.id, None, "agentview_image", t as u64).await.unwrap(),
                png_of(i, t)
            );
        }
        let run = store.fetch_counts().since(before);
        assert!(run.get_requests <= 3, "31 neighbouring frames: {run:?}");
        assert!(run.bytes_fetched < 4 * crate::steps::PAGE_MAX_BYTES as u64, "{run:?}");
        let v = Some(eps[2].version_added);
        assert_eq!(
            store.read_frame(&eps[2].id, v, "agentview_image", 0).await.unwrap(),
            png_of(eps[2].source_index as u32, 0)
        );
        for (id, cam, t, what) in [
            ("nope-1", "agentview_image", 0, "episode"),
            (e.id.as_str(), "wrist", 0, "camera"),
            (e.id.as_str(), "agentview_image", 120, "step"),
        ] {
            match store.read_frame(id, None, cam, t).await {
                Err(StoreError::NotFound { what: w, .. }) => assert_eq!(w, what),
                other => panic!("{id} {cam} {t}: {other:?}"),
            }
        }
        // A vector column is no camera.
        assert!(matches!(
            store.read_frame(&e.id, None, "obs.pos", 0).await,
            Err(StoreError::NotFound { .. })
        ));
    }

    #[test]
    fn shapes() {
        assert_eq!(super::parse_shape("[84, 84, 3]"), Some([84, 84, 3]));
        assert_eq!(super::parse_shape("[84, 84]"), None);
        assert_eq!(super::parse_shape("84,84,3"), None);
    }
}
