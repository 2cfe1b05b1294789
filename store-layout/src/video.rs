//! Frames out of a stored H.264 MP4 (a camera ingested with `--images video`, or a LeRobot video
//! in H.264): the read path's `GET /v1/episodes/{id}/frames/{camera}/{t}` of a video camera and
//! the checks of ingest's encoder decode them here, with the same OpenH264 the encoder uses.
//!
//! Only what the encoder writes is promised: constrained-baseline H.264 (no B-frames) in an MP4
//! with its samples' times in `stts`. A frame is decoded from the last sync sample at or before it,
//! so the cost of one frame is bounded by the group of pictures (ingest writes a key frame every
//! [`KEY_FRAME_INTERVAL`] frames). Other codecs (LeRobot's AV1) and reordered frames are refused
//! with an error that says so; malformed files are errors, never panics.
//!
//! `store::Store::video_codec` names a stored video's codec from its `moov` box alone (a few range
//! requests), so a writer can tell an AV1 video it will not decode without fetching it whole.

use crate::StoreError;
use openh264::decoder::Decoder;
use openh264::formats::YUVSource;
use std::io::Cursor;

/// How often ingest's encoder writes a key frame: a frame read alone decodes at most this many.
pub const KEY_FRAME_INTERVAL: u32 = 30;

/// One decoded frame: `height * width * 3` bytes, RGB, row-major.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RgbFrame {
    pub width: usize,
    pub height: usize,
    pub rgb: Vec<u8>,
}

impl RgbFrame {
    /// The frame as a PNG (what the frames route answers for a video camera).
    pub fn to_png(&self) -> Result<Vec<u8>, StoreError> {
        let mut out = Vec::new();
        let mut enc = png::Encoder::new(&mut out, self.width as u32, self.height as u32);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        enc.set_compression(png::Compression::Fast);
        let mut w =
            enc.write_header().map_err(|e| StoreError::invalid(format!("cannot write a PNG: {e}")))?;
        w.write_image_data(&self.rgb).map_err(|e| StoreError::invalid(format!("cannot write a PNG: {e}")))?;
        w.finish().map_err(|e| StoreError::invalid(format!("cannot write a PNG: {e}")))?;
        Ok(out)
    }
}

/// The H.264 track of an MP4, read from its header.
struct Track {
    reader: mp4::Mp4Reader<Cursor<Vec<u8>>>,
    id: u32,
    timescale: u32,
    /// Start time of each sample in `timescale` units (sample `i` is MP4 sample `i + 1`).
    starts: Vec<u64>,
    /// Sample indices (0-based) a decoder may start at.
    sync: Vec<usize>,
    /// SPS and PPS with Annex B start codes, given to the decoder before a sync sample.
    parameter_sets: Vec<u8>,
    /// Bytes of each NAL unit's length prefix in the samples.
    length_size: usize,
}

pub fn bad(why: impl std::fmt::Display) -> StoreError {
    StoreError::invalid(format!("video: {why}"))
}

/// Runs `f`, turning a panic inside the MP4 parser or the decoder (hostile files) into an error.
fn guarded<T>(f: impl FnOnce() -> Result<T, StoreError>) -> Result<T, StoreError> {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)) {
        Ok(r) => r,
        Err(_) => Err(bad("the MP4 or its H.264 stream is malformed (the parser gave up)")),
    }
}

impl Track {
    fn open(mp4_bytes: Vec<u8>) -> Result<Track, StoreError> {
        let size = mp4_bytes.len() as u64;
        let reader = mp4::Mp4Reader::read_header(Cursor::new(mp4_bytes), size)
            .map_err(|e| bad(format!("not a readable MP4: {e}")))?;
        let (id, trak) = reader
            .tracks()
            .iter()
            .find(|(_, t)| t.trak.mdia.minf.stbl.stsd.avc1.is_some())
            .map(|(id, t)| (*id, &t.trak))
            .ok_or_else(|| {
                bad("no H.264 track (only H.264 is decoded here; AV1 and others are played by the page)")
            })?;
        let stbl = &trak.mdia.minf.stbl;
        if stbl.ctts.as_ref().is_some_and(|c| c.entries.iter().any(|e| e.sample_offset != 0)) {
            return Err(bad("the H.264 track reorders frames (B-frames): not decodable here"));
        }
        let timescale = trak.mdia.mdhd.timescale;
        if timescale == 0 {
            return Err(bad("the track's timescale is 0"));
        }
        let count = stbl.stsz.sample_count as usize;
        let mut starts = Vec::with_capacity(count.min(1 << 20));
        let mut t = 0u64;
        for e in &stbl.stts.entries {
            for _ in 0..e.sample_count {
                if starts.len() == count {
                    break;
                }
                starts.push(t);
                t = t.saturating_add(e.sample_delta as u64);
            }
        }
        if starts.len() != count {
            return Err(bad(format!("the track has {count} samples but times for {}", starts.len())));
        }
        let sync = match &stbl.stss {
            Some(stss) => stss
                .entries
                .iter()
                .filter(|&&s| s >= 1 && (s as usize) <= count)
                .map(|&s| s as usize - 1)
                .collect(),
            None => (0..count).collect(), // no stss: every sample is a sync sample
        };
        let avcc = &stbl.stsd.avc1.as_ref().expect("found above").avcc;
        let mut parameter_sets = Vec::new();
        for nal in avcc.sequence_parameter_sets.iter().chain(&avcc.picture_parameter_sets) {
            parameter_sets.extend_from_slice(&[0, 0, 0, 1]);
            parameter_sets.extend_from_slice(&nal.bytes);
        }
        let length_size = avcc.length_size_minus_one as usize % 4 + 1;
        Ok(Track { reader, id, timescale, starts, sync, parameter_sets, length_size })
    }

    /// The sample shown at `seconds`: the last one starting at or before it (1 ms of slack for
    /// times rounded to the timescale).
    fn sample_at(&self, seconds: f64) -> Result<usize, StoreError> {
        if !seconds.is_finite() || seconds < 0.0 || self.starts.is_empty() {
            return Err(bad(format!("no frame at {seconds} s (the video has {} frames)", self.starts.len())));
        }
        let ticks = ((seconds + 1e-3) * self.timescale as f64).floor() as u64;
        let n = self.starts.partition_point(|&s| s <= ticks);
        Ok(n.max(1) - 1)
    }

    /// Sample `i` (0-based) as Annex B (start codes instead of length prefixes).
    fn annex_b(&mut self, i: usize, out: &mut Vec<u8>) -> Result<(), StoreError> {
        let sample = self
            .reader
            .read_sample(self.id, i as u32 + 1)
            .map_err(|e| bad(format!("cannot read sample {i}: {e}")))?
            .ok_or_else(|| bad(format!("sample {i} is missing")))?;
        let mut b: &[u8] = &sample.bytes;
        while !b.is_empty() {
            if b.len() < self.length_size {
                return Err(bad(format!("sample {i} ends inside a NAL unit's length")));
            }
            let len = b[..self.length_size].iter().fold(0usize, |a, &x| (a << 8) | x as usize);
            b = &b[self.length_size..];
            if len > b.len() {
                return Err(bad(format!("sample {i} declares a NAL unit of {len} bytes past its end")));
            }
            out.extend_from_slice(&[0, 0, 0, 1]);
            out.extend_from_slice(&b[..len]);
            b = &b[len..];
        }
        Ok(())
    }

    /// Decodes samples `first..=last` (first a sync sample), calling `each` with every picture.
    fn decode(
        &mut self,
        first: usize,
        last: usize,
        mut each: impl FnMut(usize, RgbFrame),
    ) -> Result<(), StoreError> {
        let mut decoder = Decoder::new().map_err(|e| bad(format!("cannot start the H.264 decoder: {e}")))?;
        let mut packet = Vec::new();
        for i in first..=last {
            packet.clear();
            if self.sync.binary_search(&i).is_ok() {
                packet.extend_from_slice(&self.parameter_sets);
            }
            self.annex_b(i, &mut packet)?;
            let picture =
                decoder.decode(&packet).map_err(|e| bad(format!("sample {i} does not decode: {e}")))?;
            let Some(yuv) = picture else {
                return Err(bad(format!("sample {i} gave no picture")));
            };
            let (width, height) = yuv.dimensions();
            let mut rgb = vec![0u8; width * height * 3];
            yuv.write_rgb8(&mut rgb);
            each(i, RgbFrame { width, height, rgb });
        }
        Ok(())
    }
}

/// The frame shown at `seconds` of an H.264 MP4 (decoded from the key frame before it).
pub fn decode_frame_at(mp4_bytes: Vec<u8>, seconds: f64) -> Result<RgbFrame, StoreError> {
    guarded(|| {
        let mut track = Track::open(mp4_bytes)?;
        let target = track.sample_at(seconds)?;
        let k = track.sync.partition_point(|&s| s <= target);
        let Some(&first) = k.checked_sub(1).and_then(|k| track.sync.get(k)) else {
            return Err(bad(format!("no key frame at or before frame {target}")));
        };
        let mut out = None;
        track.decode(first, target, |i, f| {
            if i == target {
                out = Some(f);
            }
        })?;
        out.ok_or_else(|| bad(format!("frame {target} gave no picture")))
    })
}

/// Every frame of an H.264 MP4 in order, with its time in seconds (checks and exports; a long
/// video's frames are many: `each` takes them one at a time).
pub fn decode_all(mp4_bytes: Vec<u8>, mut each: impl FnMut(f64, RgbFrame)) -> Result<usize, StoreError> {
    guarded(|| {
        let mut track = Track::open(mp4_bytes)?;
        let n = track.starts.len();
        if n == 0 {
            return Ok(0);
        }
        if track.sync.first() != Some(&0) {
            return Err(bad("the first frame is not a key frame"));
        }
        let starts = track.starts.clone();
        let scale = track.timescale as f64;
        track.decode(0, n - 1, |i, f| each(starts[i] as f64 / scale, f))?;
        Ok(n)
    })
}

/// Top-level boxes looked at for `moov` before giving up (an MP4 has a handful).
pub const MAX_TOP_LEVEL_BOXES: usize = 64;

/// The largest `moov` box read to name a codec (it holds the sample tables: a few MB for hours).
pub const MAX_MOOV_BYTES: u64 = 64 << 20;

/// A box header at the start of `b` with `left` bytes up to its parent's end: its type, its total
/// size and its header's size; `None` when it is cut short or overruns its parent. (ISO BMFF box
/// walking, shared with ingest's MP4 probe.)
pub fn box_header(b: &[u8], left: u64) -> Option<([u8; 4], u64, u64)> {
    let size = u32::from_be_bytes(b.get(0..4)?.try_into().ok()?) as u64;
    let kind: [u8; 4] = b.get(4..8)?.try_into().ok()?;
    let (total, header) = match size {
        0 => (left, 8),
        1 => (u64::from_be_bytes(b.get(8..16)?.try_into().ok()?), 16),
        n => (n, 8),
    };
    (total >= header && total <= left).then_some((kind, total, header))
}

/// The boxes inside a box's payload, as (type, payload); stops at the first malformed one.
pub fn boxes(mut buf: &[u8]) -> impl Iterator<Item = ([u8; 4], &[u8])> {
    std::iter::from_fn(move || {
        let (kind, total, header) = box_header(buf, buf.len() as u64)?;
        let payload = &buf[header as usize..total as usize];
        buf = &buf[total as usize..];
        Some((kind, payload))
    })
}

/// The payload of the first box of type `kind` inside `payload`.
pub fn child<'a>(payload: &'a [u8], kind: &[u8; 4]) -> Option<&'a [u8]> {
    boxes(payload).find(|(k, _)| k == kind).map(|(_, p)| p)
}

/// The sample entry type of the first video track (one whose `minf` has a `vmhd`) in a `moov`
/// payload: `avc1` (H.264), `av01` (AV1), `hvc1` / `hev1` (H.265), `vp09` (VP9).
pub fn video_sample_entry(moov: &[u8]) -> Option<String> {
    boxes(moov).filter(|(k, _)| k == b"trak").find_map(|(_, trak)| {
        let minf = child(child(trak, b"mdia")?, b"minf")?;
        child(minf, b"vmhd")?;
        let stsd = child(child(minf, b"stbl")?, b"stsd")?;
        // version and flags, entry count, then the first entry's size and type.
        Some(String::from_utf8_lossy(stsd.get(12..16)?).into_owned())
    })
}

/// Whether a sample entry type is what [`decode_all`] decodes (H.264 in `avc1`).
pub fn is_h264(sample_entry: &str) -> bool {
    sample_entry == "avc1"
}

/// A codec's common name from its sample entry type (the type itself when unknown).
pub fn codec_name(sample_entry: &str) -> String {
    match sample_entry {
        "avc1" | "avc3" => "H.264".into(),
        "av01" => "AV1".into(),
        "hvc1" | "hev1" => "H.265".into(),
        "vp09" => "VP9".into(),
        "vp08" => "VP8".into(),
        other => other.into(),
    }
}

/// Peak signal-to-noise ratio of `b` against `a` (8-bit samples), in dB; infinite when equal.
pub fn psnr(a: &[u8], b: &[u8]) -> f64 {
    assert_eq!(a.len(), b.len(), "psnr of buffers of different sizes");
    let se: f64 = a.iter().zip(b).map(|(&x, &y)| (x as f64 - y as f64).powi(2)).sum();
    if se == 0.0 {
        return f64::INFINITY;
    }
    10.0 * (255.0f64 * 255.0 / (se / a.len() as f64)).log10()
}
