//! Cameras: a video column (LeRobot mp4) as one static AssetVideo per video object plus a
//! VideoFrameReference per step; an image column as one EncodedImage per (kept) step.

use super::{f64_col, EpisodeSteps, Out, Recorder, StepIndex};
use crate::{rr, ViewError};
use arrow::array::{Array, BinaryArray, LargeBinaryArray, RecordBatch, StringArray};
use re_sdk_types::archetypes::{AssetVideo, EncodedImage, VideoFrameReference};
use re_sdk_types::components::{MediaType, VideoTimestamp};
use store::Store;

impl Recorder<'_> {
    /// The episode's cameras, in the steps' column order: a video (LeRobot mp4) as one static
    /// AssetVideo per object plus a VideoFrameReference per step; an image column as one
    /// EncodedImage per step, the stored bytes (PNG, or JPEG as recorded) with their media type.
    /// Returns `(camera key, entity path)` of each camera that logged frames.
    pub(super) async fn log_cameras(
        &mut self,
        store: &Store,
        e: &EpisodeSteps<'_>,
    ) -> Result<Vec<(String, String)>, ViewError> {
        let (opts, batch, base) = (self.opts, e.batch, &e.base);
        let stride = opts.image_stride.max(1);
        let mut cameras: Vec<(String, String)> = Vec::new();
        for cam in store::cameras_of(batch.schema().as_ref()) {
            let part = re_sdk::EntityPathPart::from(cam.name.as_str()).escaped_string();
            let at = e.at();
            let logged_frames = match cam.kind {
                store::CameraKind::Video if !opts.no_videos => {
                    let cam_path = format!("{base}/camera/{part}");
                    let (videos, frames) =
                        self.out.video_camera(store, batch, &cam.name, &cam_path, at).await?;
                    self.report.videos += videos;
                    self.report.video_frames += frames;
                    (frames > 0).then_some(cam_path)
                }
                store::CameraKind::Image if !opts.no_images => {
                    let img_path = format!("{base}/image/{part}");
                    let media = match cam.encoding.as_deref() {
                        Some("jpeg") => MediaType::jpeg(),
                        _ => MediaType::png(),
                    };
                    let frames = self.out.image_camera(batch, &cam.name, media, stride, &img_path, at)?;
                    self.report.images += frames;
                    (frames > 0).then_some(img_path)
                }
                _ => None,
            };
            if let Some(path) = logged_frames {
                self.cameras_seen.insert(cam.name.clone());
                cameras.push((cam.name.clone(), path));
            }
        }
        Ok(cameras)
    }
}

/// An image column's frames as byte slices (Binary or LargeBinary), `None` where null.
fn binary_frames(col: &dyn Array) -> Option<Vec<Option<&[u8]>>> {
    if let Some(a) = col.as_any().downcast_ref::<BinaryArray>() {
        return Some((0..a.len()).map(|i| a.is_valid(i).then(|| a.value(i))).collect());
    }
    let a = col.as_any().downcast_ref::<LargeBinaryArray>()?;
    Some((0..a.len()).map(|i| a.is_valid(i).then(|| a.value(i))).collect())
}

impl Out<'_> {
    /// An image-column camera: one EncodedImage per kept step (every `stride`-th, non-null),
    /// the stored bytes as they are with their media type. Returns the frames logged.
    fn image_camera(
        &mut self,
        batch: &RecordBatch,
        key: &str,
        media: MediaType,
        stride: usize,
        path: &str,
        at: StepIndex<'_>,
    ) -> Result<usize, ViewError> {
        let Some(frames) = batch
            .column_by_name(&format!("{}{key}", store::steps::IMAGE_PREFIX))
            .and_then(|c| binary_frames(c))
        else {
            return Err(ViewError::Invalid(format!("image column {key:?} is not binary")));
        };
        let rows: Vec<usize> =
            (0..frames.len()).step_by(stride.max(1)).filter(|&i| frames[i].is_some()).collect();
        if rows.is_empty() {
            return Ok(0);
        }
        let arch = EncodedImage::update_fields()
            .with_many_blob(rows.iter().map(|&i| frames[i].unwrap_or_default().to_vec()))
            .with_many_media_type(vec![media; rows.len()]);
        let cols = arch.columns_of_unit_batches().map_err(rr)?.collect::<Vec<_>>();
        self.send(path.to_string(), &at.of(rows.iter().copied()), cols)?;
        Ok(rows.len())
    }

    /// A video camera (`media.<key>.path` / `.timestamp`): each video object it references is
    /// logged once, static, as an AssetVideo at `media/<key>/<file>`; every step becomes a
    /// VideoFrameReference to it at the step's frame time inside the video (in a v3.0 file
    /// shared by many episodes, the episode's own span of it). Returns (videos embedded now,
    /// frame references).
    async fn video_camera(
        &mut self,
        store: &Store,
        batch: &RecordBatch,
        key: &str,
        path: &str,
        at: StepIndex<'_>,
    ) -> Result<(usize, usize), ViewError> {
        let n = batch.num_rows();
        let paths = batch
            .column_by_name(&format!("{}{key}.path", store::steps::MEDIA_PREFIX))
            .and_then(|c| c.as_any().downcast_ref::<StringArray>())
            .ok_or_else(|| ViewError::Invalid(format!("media column {key:?} is not utf8")))?;
        let times = f64_col(batch, &format!("{}{key}.timestamp", store::steps::MEDIA_PREFIX))?;
        let part = re_sdk::EntityPathPart::from(key).escaped_string();
        let (mut videos, mut frames) = (0, 0);
        // Consecutive runs of the same video object (usually one per episode).
        let mut row = 0;
        while row < n {
            if !paths.is_valid(row) {
                row += 1;
                continue;
            }
            let obj = paths.value(row).to_string();
            let end = (row..n).find(|&i| !paths.is_valid(i) || paths.value(i) != obj).unwrap_or(n);
            let video_path = match self.videos.get(&obj) {
                Some(p) => p.clone(),
                None => {
                    let data = store.get_object(&obj).await?;
                    let file = obj.rsplit('/').next().unwrap_or(&obj);
                    let file = re_sdk::EntityPathPart::from(file).escaped_string();
                    let vpath = format!("media/{part}/{file}");
                    let media =
                        MediaType::guess_from_path(&obj).or_else(|| MediaType::guess_from_data(&data));
                    self.rec
                        .log_static(vpath.as_str(), &AssetVideo::from_file_contents(data.to_vec(), media))
                        .map_err(rr)?;
                    self.entities.insert(vpath.clone());
                    self.videos.insert(obj.clone(), vpath.clone());
                    videos += 1;
                    vpath
                }
            };
            let k = end - row;
            let arch = VideoFrameReference::update_fields()
                .with_many_timestamp((row..end).map(|i| VideoTimestamp::from_secs(times.value(i))))
                .with_many_video_reference(vec![video_path; k]);
            let cols = arch.columns_of_unit_batches().map_err(rr)?.collect::<Vec<_>>();
            self.send(path.to_string(), &at.of(row..end), cols)?;
            frames += k;
            row = end;
        }
        Ok((videos, frames))
    }
}
