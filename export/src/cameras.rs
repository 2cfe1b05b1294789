//! Camera frames as the HDF5 formats hold them (uint8 `T x H x W x C`), for the robomimic and
//! ALOHA writers: PNG image columns (`image.<camera>`) decoded, and video cameras
//! (`media.<camera>`, stored by `ufops ingest --images video`) decoded from their H.264 MP4 with
//! [`store::video::decode_all`], each step's frame being the one shown at the step's time (its
//! `media.<camera>.timestamp`), as the frames route picks it.
//!
//! Video is lossy: those frames come back within a PSNR bound of the source, not bit for bit
//! (export/README.md has the measured bound). A video in another codec (LeRobot's AV1) is not
//! decoded in Rust: its camera is left out and the export warns, naming the camera and the codec;
//! its codec is read from the MP4's `moov` box alone, so such a video is never fetched whole.

use std::collections::{BTreeMap, HashMap};

use arrow::array::{Array, ArrayRef, AsArray, RecordBatch};
use store::steps::MEDIA_PREFIX;
use store::video::{codec_name, decode_all, is_h264, RgbFrame};
use store::{EpisodeRecord, Store, StoreError};

use crate::{ExportError, Result};

fn bad(e: &EpisodeRecord, what: impl std::fmt::Display) -> ExportError {
    ExportError::invalid(format!("episode {}: {what}", e.id))
}

/// One camera's frames of an episode: `shape` is `[H, W, C]`, `values` the frames one after
/// the other.
pub(crate) struct Frames {
    pub shape: [usize; 3],
    pub values: Vec<u8>,
}

impl Frames {
    /// The dataset's shape, `[T, H, W, C]`.
    pub fn dims(&self) -> Vec<u64> {
        let frame: usize = self.shape.iter().product();
        let t = self.values.len().checked_div(frame).unwrap_or(0);
        std::iter::once(t).chain(self.shape).map(|d| d as u64).collect()
    }

    /// The values and the dataset's shape ([`Self::dims`]).
    pub fn into_dataset(self) -> (Vec<u8>, Vec<u64>) {
        let dims = self.dims();
        (self.values, dims)
    }
}

fn decode_png(bytes: &[u8]) -> std::result::Result<(Vec<u8>, [usize; 3]), String> {
    let mut dec = png::Decoder::new(std::io::Cursor::new(bytes));
    dec.set_transformations(png::Transformations::EXPAND);
    let mut r = dec.read_info().map_err(|e| e.to_string())?;
    let mut buf = vec![0; r.output_buffer_size().ok_or("PNG too large")?];
    let info = r.next_frame(&mut buf).map_err(|e| e.to_string())?;
    buf.truncate(info.buffer_size());
    if info.bit_depth != png::BitDepth::Eight {
        return Err(format!("{:?}-bit PNG (expected 8-bit)", info.bit_depth));
    }
    Ok((buf, [info.height as usize, info.width as usize, info.color_type.samples()]))
}

/// A PNG image column's frames decoded to uint8 (all of one size).
pub(crate) fn png_frames(e: &EpisodeRecord, name: &str, col: &ArrayRef) -> Result<Frames> {
    let bin = col.as_binary_opt::<i32>().ok_or_else(|| bad(e, format!("{name} is not a binary column")))?;
    let mut values = Vec::new();
    let mut shape = [0; 3];
    for r in 0..bin.len() {
        let (px, s) = decode_png(bin.value(r)).map_err(|err| bad(e, format!("{name} row {r}: {err}")))?;
        if r > 0 && s != shape {
            return Err(bad(e, format!("{name}: frames of different sizes")));
        }
        shape = s;
        values.extend_from_slice(&px);
    }
    Ok(Frames { shape, values })
}

/// The video cameras of the steps (`media.<camera>.path` columns), in column order.
pub(crate) fn video_cameras(steps: &RecordBatch) -> Vec<String> {
    steps
        .schema()
        .fields()
        .iter()
        .filter_map(|f| f.name().strip_prefix(MEDIA_PREFIX)?.strip_suffix(".path").map(str::to_string))
        .collect()
}

/// Decodes the video cameras of the episodes an export writes, remembering each video object's
/// codec (probed once) and the cameras it left out for [`Self::warnings`].
#[derive(Default)]
pub(crate) struct VideoDecoder {
    /// The sample entry type of each video object probed (`avc1` is decoded).
    codecs: HashMap<String, String>,
    /// Episodes whose camera was left out, by (camera, sample entry type).
    left_out: BTreeMap<(String, String), usize>,
}

impl VideoDecoder {
    /// Every video camera of one episode as frames, by camera name, decoded one after the other
    /// (one MP4 in memory at a time). A camera whose video is not H.264 is not among them.
    pub async fn episode(
        &mut self,
        store: &Store,
        e: &EpisodeRecord,
        steps: &RecordBatch,
    ) -> Result<BTreeMap<String, Frames>> {
        let mut out = BTreeMap::new();
        for cam in video_cameras(steps) {
            let (path, times) = media_of(e, steps, &cam)?;
            if !self.codecs.contains_key(&path) {
                let codec = store.video_codec(&path).await.map_err(|err| bad(e, format!("{cam}: {err}")))?;
                self.codecs.insert(path.clone(), codec);
            }
            let codec = &self.codecs[&path];
            if !is_h264(codec) {
                *self.left_out.entry((cam, codec.clone())).or_default() += 1;
                continue;
            }
            let channels = source_channels(e, &cam);
            let mp4 = store.get_object(&path).await?.to_vec();
            let frames = tokio::task::spawn_blocking(move || frames_at(mp4, &times, channels))
                .await
                .map_err(|err| bad(e, format!("{cam}: the video decoder stopped: {err}")))?
                .map_err(|err| bad(e, format!("{cam}: {err}")))?;
            out.insert(cam, frames);
        }
        Ok(out)
    }

    /// One line per camera left out, naming its codec and how many episodes it was left out of.
    pub fn warnings(&self, format: &str) -> Vec<String> {
        self.left_out
            .iter()
            .map(|((cam, codec), n)| {
                format!(
                    "left out camera {cam} of {n} episode(s): its video is {} ({codec}), and only H.264 \
                     is decoded into {format}'s image arrays (export it as LeRobot to keep the video)",
                    codec_name(codec)
                )
            })
            .collect()
    }
}

/// A video camera's object path (one per episode) and its per-step times.
fn media_of(e: &EpisodeRecord, steps: &RecordBatch, cam: &str) -> Result<(String, Vec<f64>)> {
    let col = |suffix: &str| {
        let name = format!("{MEDIA_PREFIX}{cam}.{suffix}");
        steps.column_by_name(&name).cloned().ok_or_else(|| bad(e, format!("has no column {name}")))
    };
    let (paths, times) = (col("path")?, col("timestamp")?);
    let paths = paths.as_string_opt::<i32>().ok_or_else(|| bad(e, format!("{cam}: paths are not utf8")))?;
    let times = times
        .as_primitive_opt::<arrow::datatypes::Float64Type>()
        .ok_or_else(|| bad(e, format!("{cam}: times are not float64")))?;
    if paths.null_count() > 0 || times.null_count() > 0 || paths.is_empty() {
        return Err(bad(e, format!("{cam}: steps without a video or a time")));
    }
    let path = paths.value(0);
    if paths.iter().any(|p| p != Some(path)) {
        return Err(bad(e, format!("{cam}: the steps' frames are in several videos (one is expected)")));
    }
    Ok((path.to_string(), times.values().to_vec()))
}

/// The camera's channels in the source (ingest records its shape when it encodes the video):
/// 1 for a gray camera (encoded as gray RGB), else 3.
fn source_channels(e: &EpisodeRecord, cam: &str) -> usize {
    let shape = e.metadata.get("ufops.images_as_video").and_then(|m| m.get(cam)).and_then(|c| c.get("shape"));
    match shape.and_then(|s| s.get(2)).and_then(|c| c.as_u64()) {
        Some(1) => 1,
        _ => 3,
    }
}

/// The frames shown at `times` (seconds, one per step) of an H.264 MP4: for each time the last
/// frame starting at or before it (1 ms of slack, as [`store::video::decode_frame_at`]), the
/// first frame for a time before it. Decodes the video once, holding one frame besides the output.
pub(crate) fn frames_at(mp4: Vec<u8>, times: &[f64], channels: usize) -> Result<Frames, StoreError> {
    let mut order: Vec<usize> = (0..times.len()).collect();
    order.sort_by(|&a, &b| times[a].total_cmp(&times[b]));
    let mut out: Option<Frames> = None;
    let mut error: Option<String> = None;
    let mut done = 0;
    let mut shown: Option<RgbFrame> = None;
    let mut place = |upto: Option<f64>, f: &RgbFrame, done: &mut usize, out: &mut Option<Frames>| {
        let o = out.get_or_insert_with(|| Frames {
            shape: [f.height, f.width, channels],
            values: vec![0; times.len() * f.height * f.width * channels],
        });
        if [f.height, f.width] != o.shape[..2] {
            error.get_or_insert(format!(
                "frames of {}x{} and {}x{}",
                o.shape[1], o.shape[0], f.width, f.height
            ));
            return;
        }
        let size = f.height * f.width * channels;
        while *done < order.len() && upto.is_none_or(|u| times[order[*done]] + 1e-3 < u) {
            let row = &mut o.values[order[*done] * size..(order[*done] + 1) * size];
            if channels == 1 {
                // Gray was encoded as equal R, G and B: their mean is the gray value back.
                for (g, px) in row.iter_mut().zip(f.rgb.chunks_exact(3)) {
                    *g = ((px[0] as u16 + px[1] as u16 + px[2] as u16 + 1) / 3) as u8;
                }
            } else {
                row.copy_from_slice(&f.rgb);
            }
            *done += 1;
        }
    };
    decode_all(mp4, |start, frame| {
        if let Some(prev) = shown.take() {
            place(Some(start), &prev, &mut done, &mut out);
        }
        shown = Some(frame);
    })?;
    let last = shown.ok_or_else(|| StoreError::invalid("video: the video has no frame"))?;
    place(None, &last, &mut done, &mut out);
    if let Some(why) = error {
        return Err(StoreError::invalid(format!("video: {why}")));
    }
    out.ok_or_else(|| StoreError::invalid("video: the video has no frame"))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Ten 48x32 frames of one flat colour each, frame `i` shown from `i / 10` s.
    fn video(dir: &std::path::Path) -> (Vec<u8>, Vec<[u8; 3]>) {
        let path = dir.join("v.mp4");
        let mut enc = ingest::video::Mp4Encoder::create(&path, 48, 32).unwrap();
        let colours: Vec<[u8; 3]> = (0..10u8).map(|i| [20 + i * 20, 230 - i * 20, 100]).collect();
        for (i, c) in colours.iter().enumerate() {
            let rgb: Vec<u8> = c.iter().copied().cycle().take(48 * 32 * 3).collect();
            enc.push_frame(&rgb, i as f64 / 10.0).unwrap();
        }
        enc.finish().unwrap();
        (std::fs::read(&path).unwrap(), colours)
    }

    fn mean(px: &[u8], c: usize, channels: usize) -> f64 {
        px.iter().skip(c).step_by(channels).map(|&v| v as f64).sum::<f64>() / (px.len() / channels) as f64
    }

    /// Each step gets the frame shown at its time (the last starting at or before it, with 1 ms
    /// of slack; the first before the video starts), whatever the order of the times.
    #[test]
    fn each_step_gets_the_frame_shown_at_its_time() {
        let dir = tempfile::tempdir().unwrap();
        let (mp4, colours) = video(dir.path());
        let times = [0.35, 0.05, 0.0995, -1.0, 0.1, 5.0, 0.0];
        let want = [3, 0, 1, 0, 1, 9, 0];
        let f = frames_at(mp4.clone(), &times, 3).unwrap();
        assert_eq!(f.dims(), vec![7, 32, 48, 3]);
        let size = 32 * 48 * 3;
        for (row, &w) in want.iter().enumerate() {
            let px = &f.values[row * size..(row + 1) * size];
            for (c, &want) in colours[w].iter().enumerate() {
                let m = mean(px, c, 3);
                assert!((m - want as f64).abs() < 4.0, "step {row}: channel {c} {m}, frame {w}");
            }
        }
        // A gray camera comes back with one channel.
        let g = frames_at(mp4, &[0.0], 1).unwrap();
        assert_eq!(g.dims(), vec![1, 32, 48, 1]);
        let m = mean(&g.values, 0, 1);
        assert!((m - (20.0 + 230.0 + 100.0) / 3.0).abs() < 4.0, "{m}");
        assert!(frames_at(b"not an mp4".to_vec(), &[0.0], 3).is_err());
    }
}
