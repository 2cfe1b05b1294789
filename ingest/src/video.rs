//! Cameras stored as video (`ufops ingest --images video`): each image-array camera of an
//! episode (robomimic image observations, ALOHA raw cameras, LeRobot v2.1 PNG image features)
//! becomes one H.264 MP4 per episode and camera, stored like LeRobot's videos (a content-addressed
//! media object and a `media.<camera>` column of per-step times), so the labeling page plays it.
//!
//! Why H.264 (constrained baseline, OpenH264): every browser plays it, Debian's Chromium
//! included (checked by the page test), and OpenH264 encodes 480×640 frames at tens of frames
//! per second on one core, where the AV1 encoders in Rust (rav1e) are an order of magnitude
//! slower at comparable quality. The `openh264` crate compiles Cisco's source with `cc` (no
//! system library, no download); ingest/README.md has its build time, the bytes on disk, the
//! encode rate and the frame error. Video is lossy (the frames come back within a PSNR bound,
//! not bit for bit), which is why PNG stays the default.
//!
//! [`Mp4Encoder`] takes frames one at a time and writes the MP4 as it goes, so memory is one
//! frame (plus the sample table) whatever the episode's length. [`VideoSink`] wraps the sink a
//! reader writes to and turns the episodes' PNG cameras into videos on the reader's thread.
//! JPEG cameras (ALOHA's compressed ones) are kept as recorded, and cameras that are not 8-bit
//! (16-bit depth images) stay PNG: H.264 would lose what they hold.

use std::fs::File;
use std::io::{BufWriter, Read};
use std::path::{Path, PathBuf};

use openh264::encoder::{
    BitRate, Complexity, Encoder, EncoderConfig, FrameRate, IntraFramePeriod, Profile, QpRange,
    RateControlMode, SpsPpsStrategy, UsageType, VuiConfig,
};
use openh264::formats::{RgbSliceU8, YUVBuffer};
use openh264::OpenH264API;
use sha2::{Digest, Sha256};

use crate::error::{IngestError, Result};
use crate::model::{EpisodeInput, ExtraColumn, FrameStream, Frames, ImageColumn, MediaColumn, MediaFile};
use crate::sink::{EpisodeSink, SourceMeta};

/// The MP4 track's clock: 90 kHz, the usual one for video (frame times to 11 µs).
pub const TIMESCALE: u32 = 90_000;

/// Highest quantizer the encoder may use (0 best, 51 worst): visually lossless on robot
/// cameras (ingest/README.md has the measured PSNR).
pub const MAX_QP: u8 = 20;

/// A frame's duration when a single frame or the last one has no next step to measure it by.
const DEFAULT_FRAME_TICKS: u64 = TIMESCALE as u64 / 30;

/// A finished video: the MP4 on disk and the time of each frame in it.
#[derive(Debug, Clone, PartialEq)]
pub struct EncodedVideo {
    pub path: PathBuf,
    pub sha256: String,
    pub size_bytes: u64,
    /// Seconds from the video's start of each pushed frame (exactly the sample's start).
    pub timestamps: Vec<f64>,
}

/// An encoded frame waiting for the next one, which gives its duration.
struct Pending {
    start: u64,
    bytes: Vec<u8>,
    sync: bool,
}

/// Encodes RGB frames, one at a time, into an H.264 MP4 file.
pub struct Mp4Encoder {
    path: PathBuf,
    width: usize,
    height: usize,
    encoder: Encoder,
    yuv: YUVBuffer,
    mp4: mp4::Mp4Writer<BufWriter<File>>,
    track_added: bool,
    pending: Option<Pending>,
    starts: Vec<u64>,
    /// Time of the first frame pushed (the video starts there).
    origin: Option<f64>,
}

fn enc_err(what: &str, e: impl std::fmt::Display) -> IngestError {
    IngestError::Frames(format!("video encoding: {what}: {e}"))
}

impl Mp4Encoder {
    /// A new MP4 at `path` for frames of `width × height` (both even: H.264's 4:2:0 sampling).
    pub fn create(path: &Path, width: usize, height: usize) -> Result<Mp4Encoder> {
        if width == 0 || height == 0 || width % 2 == 1 || height % 2 == 1 || width > 3840 || height > 3840 {
            return Err(IngestError::Usage(format!(
                "frames of {width}x{height} cannot be stored as video (H.264 here needs even sides up to 3840); \
                 use --images png"
            )));
        }
        let config = EncoderConfig::new()
            .usage_type(UsageType::CameraVideoRealTime)
            .profile(Profile::Baseline)
            .rate_control_mode(RateControlMode::Quality)
            .bitrate(BitRate::from_bps(50_000_000))
            .max_frame_rate(FrameRate::from_hz(30.0))
            .qp(QpRange::new(0, MAX_QP))
            .skip_frames(false)
            .complexity(Complexity::Medium)
            .intra_frame_period(IntraFramePeriod::from_num_frames(store::video::KEY_FRAME_INTERVAL))
            .sps_pps_strategy(SpsPpsStrategy::ConstantId)
            // One thread: the stream (and so the object's sha256) is the same on every run, and
            // the ingest's other core is the store writer's.
            .num_threads(1)
            // openh264's RGB→YUV conversion is BT.601 limited range: say so, so browsers invert it.
            .vui(VuiConfig::bt601());
        let encoder = Encoder::with_api_config(OpenH264API::from_source(), config)
            .map_err(|e| enc_err("cannot start", e))?;
        let file = File::create(path).map_err(|e| IngestError::io(path, e))?;
        let mp4_config = mp4::Mp4Config {
            major_brand: str::parse("isom").map_err(|e| enc_err("brand", e))?,
            minor_version: 512,
            compatible_brands: ["isom", "iso2", "avc1", "mp41"]
                .iter()
                .map(|b| str::parse(b))
                .collect::<std::result::Result<_, _>>()
                .map_err(|e| enc_err("brand", e))?,
            timescale: 1000,
        };
        let mp4 = mp4::Mp4Writer::write_start(BufWriter::new(file), &mp4_config)
            .map_err(|e| enc_err("cannot start the MP4", e))?;
        Ok(Mp4Encoder {
            path: path.to_path_buf(),
            width,
            height,
            encoder,
            yuv: YUVBuffer::new(width, height),
            mp4,
            track_added: false,
            pending: None,
            starts: Vec::new(),
            origin: None,
        })
    }

    /// Frames pushed so far.
    pub fn frames(&self) -> usize {
        self.starts.len()
    }

    /// Encodes one frame (`height * width * 3` RGB bytes) shown from `seconds` (the step's time;
    /// times that do not increase are nudged one tick past the previous frame).
    pub fn push_frame(&mut self, rgb: &[u8], seconds: f64) -> Result<()> {
        if rgb.len() != self.width * self.height * 3 {
            return Err(IngestError::Frames(format!(
                "video encoding: frame {} has {} bytes, expected {}x{}x3",
                self.starts.len(),
                rgb.len(),
                self.height,
                self.width
            )));
        }
        let origin = *self.origin.get_or_insert(if seconds.is_finite() { seconds } else { 0.0 });
        let at = if seconds.is_finite() {
            ((seconds - origin).max(0.0) * TIMESCALE as f64).round() as u64
        } else {
            0
        };
        let start = match self.starts.last() {
            None => 0,
            Some(&prev) if !seconds.is_finite() => prev + DEFAULT_FRAME_TICKS,
            Some(&prev) => at.max(prev + 1),
        };
        if let Some(&prev) = self.starts.last() {
            if start - prev > u32::MAX as u64 {
                return Err(IngestError::Frames(format!(
                    "video encoding: steps {} and {} are more than 13 hours apart",
                    self.starts.len() - 1,
                    self.starts.len()
                )));
            }
        }
        self.yuv.read_rgb8(RgbSliceU8::new(rgb, (self.width, self.height)));
        let frame_index = self.starts.len();
        let stream =
            self.encoder.encode(&self.yuv).map_err(|e| enc_err(&format!("frame {frame_index}"), e))?;
        // Annex B NAL units → the MP4's length-prefixed sample; SPS/PPS go to the track header.
        let (mut sps, mut pps, mut sample, mut sync) = (None, None, Vec::new(), false);
        for l in 0..stream.num_layers() {
            let Some(layer) = stream.layer(l) else { continue };
            for n in 0..layer.nal_count() {
                let Some(nal) = layer.nal_unit(n).map(strip_start_code) else { continue };
                match nal.first().map(|b| b & 0x1f) {
                    None => {}
                    Some(7) => sps = Some(nal.to_vec()),
                    Some(8) => pps = Some(nal.to_vec()),
                    Some(t) => {
                        sync |= t == 5;
                        sample.extend_from_slice(&(nal.len() as u32).to_be_bytes());
                        sample.extend_from_slice(nal);
                    }
                }
            }
        }
        if sample.is_empty() {
            return Err(IngestError::Frames(format!(
                "video encoding: the encoder skipped frame {frame_index}"
            )));
        }
        if !self.track_added {
            let (Some(sps), Some(pps)) = (sps, pps) else {
                return Err(IngestError::Frames("video encoding: the first frame has no SPS/PPS".into()));
            };
            let track = mp4::TrackConfig {
                track_type: mp4::TrackType::Video,
                timescale: TIMESCALE,
                language: "und".into(),
                media_conf: mp4::MediaConfig::AvcConfig(mp4::AvcConfig {
                    width: self.width as u16,
                    height: self.height as u16,
                    seq_param_set: sps,
                    pic_param_set: pps,
                }),
            };
            self.mp4.add_track(&track).map_err(|e| enc_err("MP4 track", e))?;
            self.track_added = true;
        }
        self.flush_pending(Some(start))?;
        self.pending = Some(Pending { start, bytes: sample, sync });
        self.starts.push(start);
        Ok(())
    }

    /// Writes the waiting frame, lasting until `next` (or as long as the frame before it).
    fn flush_pending(&mut self, next: Option<u64>) -> Result<()> {
        let Some(p) = self.pending.take() else { return Ok(()) };
        let duration = match next {
            Some(n) => n - p.start,
            None => match self.starts.len() {
                0 | 1 => DEFAULT_FRAME_TICKS,
                k => self.starts[k - 1] - self.starts[k - 2],
            },
        };
        let sample = mp4::Mp4Sample {
            start_time: p.start,
            duration: duration as u32,
            rendering_offset: 0,
            is_sync: p.sync,
            bytes: p.bytes.into(),
        };
        self.mp4.write_sample(1, &sample).map_err(|e| enc_err("MP4 sample", e))
    }

    /// Closes the MP4 and hashes it. No frame pushed is an error (there is nothing to play).
    pub fn finish(mut self) -> Result<EncodedVideo> {
        if self.starts.is_empty() {
            return Err(IngestError::Frames("video encoding: no frame".into()));
        }
        self.flush_pending(None)?;
        self.mp4.write_end().map_err(|e| enc_err("MP4 end", e))?;
        let path = self.path.clone();
        let mut file =
            self.mp4.into_writer().into_inner().map_err(|e| IngestError::io(&path, e.into_error()))?;
        std::io::Write::flush(&mut file).map_err(|e| IngestError::io(&path, e))?;
        drop(file);
        let (sha256, size_bytes) = sha256_file(&path)?;
        let timestamps = self.starts.iter().map(|&s| s as f64 / TIMESCALE as f64).collect();
        Ok(EncodedVideo { path, sha256, size_bytes, timestamps })
    }
}

fn strip_start_code(nal: &[u8]) -> &[u8] {
    nal.strip_prefix(&[0, 0, 0, 1]).or_else(|| nal.strip_prefix(&[0, 0, 1])).unwrap_or(nal)
}

fn sha256_file(path: &Path) -> Result<(String, u64)> {
    let mut f = File::open(path).map_err(|e| IngestError::io(path, e))?;
    let mut h = Sha256::new();
    let mut buf = vec![0u8; 1 << 20];
    let mut n = 0u64;
    loop {
        let k = f.read(&mut buf).map_err(|e| IngestError::io(path, e))?;
        if k == 0 {
            break;
        }
        h.update(&buf[..k]);
        n += k as u64;
    }
    Ok((hex::encode(h.finalize()), n))
}

/// A PNG frame as 8-bit RGB (gray is repeated, alpha dropped), or `None` when it is not 8-bit.
pub fn png_to_rgb(png_bytes: &[u8]) -> Result<Option<(usize, usize, Vec<u8>)>> {
    let bad = |e: &dyn std::fmt::Display| {
        IngestError::Frames(format!("video encoding: a frame is not a readable PNG: {e}"))
    };
    let mut reader = png::Decoder::new(std::io::Cursor::new(png_bytes)).read_info().map_err(|e| bad(&e))?;
    let info = reader.info();
    if info.bit_depth != png::BitDepth::Eight || info.color_type == png::ColorType::Indexed {
        return Ok(None);
    }
    let (w, h, color) = (info.width as usize, info.height as usize, info.color_type);
    let size = reader.output_buffer_size().ok_or_else(|| bad(&"too large"))?;
    let mut buf = vec![0u8; size];
    let out = reader.next_frame(&mut buf).map_err(|e| bad(&e))?;
    buf.truncate(out.buffer_size());
    let channels = match color {
        png::ColorType::Grayscale => 1,
        png::ColorType::GrayscaleAlpha => 2,
        png::ColorType::Rgb => return Ok(Some((w, h, buf))),
        png::ColorType::Rgba => 4,
        png::ColorType::Indexed => return Ok(None),
    };
    let mut rgb = Vec::with_capacity(w * h * 3);
    for px in buf.chunks_exact(channels) {
        match channels {
            1 | 2 => rgb.extend_from_slice(&[px[0], px[0], px[0]]),
            _ => rgb.extend_from_slice(&px[..3]),
        }
    }
    Ok(Some((w, h, rgb)))
}

/// Encodes one camera's PNG frames into an MP4 at `path`, frame `i` shown from `times[i]`.
/// `Ok(None)` when the camera is not 8-bit (it stays PNG): its frames come back untouched.
pub fn encode_camera(
    path: &Path,
    name: &str,
    frames: Frames,
    times: &[f64],
) -> Result<std::result::Result<EncodedVideo, Frames>> {
    let n = frames.len();
    let mut it = frames.into_iter();
    let Some(first) = it.next() else {
        return Err(IngestError::Frames(format!("camera {name:?} has no frame")));
    };
    let first = first.map_err(|e| IngestError::Frames(e.to_string()))?;
    let Some((w, h, rgb)) = png_to_rgb(&first)? else {
        let rest = std::iter::once(Ok(first)).chain(it);
        return Ok(Err(Frames::Stream(FrameStream::new(name, n, "png", rest))));
    };
    let mut enc =
        Mp4Encoder::create(path, w, h).map_err(|e| IngestError::Frames(format!("camera {name:?}: {e}")))?;
    let time = |i: usize| times.get(i).copied().unwrap_or(f64::NAN);
    enc.push_frame(&rgb, time(0))?;
    for (i, f) in it.enumerate().map(|(i, f)| (i + 1, f)) {
        let f = f.map_err(|e| IngestError::Frames(e.to_string()))?;
        let (fw, fh, rgb) = png_to_rgb(&f)?.ok_or_else(|| {
            IngestError::Frames(format!("camera {name:?}: frame {i} is not 8-bit like frame 0"))
        })?;
        if (fw, fh) != (w, h) {
            return Err(IngestError::Frames(format!(
                "camera {name:?}: frame {i} is {fw}x{fh}, frame 0 was {w}x{h}"
            )));
        }
        enc.push_frame(&rgb, time(i))?;
    }
    if enc.frames() != n {
        return Err(IngestError::Frames(format!("camera {name:?}: {} frames for {n} steps", enc.frames())));
    }
    Ok(Ok(enc.finish()?))
}

/// Wraps the sink a reader writes to: every PNG camera of an episode is encoded into an MP4 in
/// `dir` (which must outlive the ingest: the store copies the files when it takes the media),
/// announced as media, and replaced by a media column of the frames' times.
pub struct VideoSink<'a, S: EpisodeSink> {
    inner: &'a mut S,
    dir: PathBuf,
    videos: usize,
}

impl<'a, S: EpisodeSink> VideoSink<'a, S> {
    pub fn new(inner: &'a mut S, dir: &Path) -> Self {
        VideoSink { inner, dir: dir.to_path_buf(), videos: 0 }
    }
}

impl<S: EpisodeSink> EpisodeSink for VideoSink<'_, S> {
    fn source(&mut self, meta: SourceMeta) -> Result<()> {
        self.inner.source(meta)
    }
    fn media(&mut self, file: MediaFile) -> Result<()> {
        self.inner.media(file)
    }
    fn episode_with_extras(&mut self, mut episode: EpisodeInput, extras: Vec<ExtraColumn>) -> Result<()> {
        let mut kept = Vec::new();
        for mut im in std::mem::take(&mut episode.images) {
            if im.encoding() != "png" || im.frames.is_empty() {
                kept.push(im);
                continue;
            }
            let path = self.dir.join(format!("{}.mp4", self.videos));
            self.videos += 1;
            let frames = std::mem::take(&mut im.frames);
            match encode_camera(&path, &im.name, frames, &episode.timestamps)? {
                Err(frames) => kept.push(ImageColumn { frames, ..im }),
                Ok(video) => {
                    self.inner.media(MediaFile {
                        sha256: video.sha256.clone(),
                        local_path: video.path,
                        content_type: "video/mp4".into(),
                        size_bytes: video.size_bytes,
                    })?;
                    if let Some(meta) = episode.metadata.as_object_mut() {
                        let entry =
                            meta.entry("ufops.images_as_video").or_insert_with(|| serde_json::json!({}));
                        if let Some(cams) = entry.as_object_mut() {
                            cams.insert(
                                im.name.clone(),
                                serde_json::json!({"codec": "h264", "shape": im.shape, "max_qp": MAX_QP, "lossless": false}),
                            );
                        }
                    }
                    episode.media.push(MediaColumn {
                        name: im.name,
                        sha256: video.sha256,
                        timestamps: video.timestamps,
                    });
                }
            }
        }
        episode.images = kept;
        self.inner.episode_with_extras(episode, extras)
    }
}
