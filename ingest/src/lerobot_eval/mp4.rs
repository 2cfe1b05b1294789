//! How many frames an episode's MP4 holds and when each is shown, from its `moov` box alone:
//! the track's timescale (`mdhd`), its sample count (`stsz`) and their durations (`stts`). The
//! media data is never read, and the file is untrusted: at most [`MAX_TOP_LEVEL_BOXES`] box headers
//! are looked at, a `moov` over [`MAX_MOOV_BYTES`] is refused, and the sample count is checked
//! against the file's size and [`MAX_FRAMES`] before the times are allocated.

use std::io::{Read, Seek, SeekFrom};
use std::path::Path;

use crate::error::{IngestError, Result};
use store::video::{box_header, boxes, child};

/// Top-level boxes looked at for `moov` (an MP4 has a handful: `ftyp`, `free`, `mdat`, `moov`).
const MAX_TOP_LEVEL_BOXES: usize = 64;
/// The largest `moov` read (it holds the sample tables: a few MB for hours of video).
const MAX_MOOV_BYTES: u64 = 64 << 20;
/// The most frames an episode's video may have (11 hours at 100 frames per second).
pub(super) const MAX_FRAMES: u64 = 1 << 22;

/// What the episode's steps need from its video.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct VideoInfo {
    /// When each frame starts, in seconds from the video's start (one per frame, in order).
    pub(super) times: Vec<f64>,
    /// The frame rate when every frame lasts as long (imageio writes a constant rate).
    pub(super) fps: Option<f64>,
    /// The codec's common name (`H.264` for what lerobot-eval writes through imageio).
    pub(super) codec: String,
}

fn u32_at(b: &[u8], at: usize) -> Option<u32> {
    Some(u32::from_be_bytes(b.get(at..at + 4)?.try_into().ok()?))
}

/// Reads the video track of the MP4 at `path` (see the module docs).
pub(super) fn probe(path: &Path) -> Result<VideoInfo> {
    let mut f = std::fs::File::open(path).map_err(|e| IngestError::io(path, e))?;
    let size = f.metadata().map_err(|e| IngestError::io(path, e))?.len();
    probe_from(path, &mut f, size)
}

/// [`probe`] of `size` bytes read from `f` (`path` names them in errors).
pub(super) fn probe_from(path: &Path, f: &mut (impl Read + Seek), size: u64) -> Result<VideoInfo> {
    let bad = |why: String| IngestError::invalid(path, format!("not a readable MP4 video: {why}"));
    let mut at = 0u64;
    for _ in 0..MAX_TOP_LEVEL_BOXES {
        if at + 8 > size {
            break;
        }
        let mut head = vec![0u8; (size - at).min(16) as usize];
        f.seek(SeekFrom::Start(at))
            .and_then(|_| f.read_exact(&mut head))
            .map_err(|e| IngestError::io(path, e))?;
        let (kind, total, header) = box_header(&head, size - at)
            .ok_or_else(|| bad(format!("the box at byte {at} overruns the file")))?;
        if &kind == b"moov" {
            if total > MAX_MOOV_BYTES {
                return Err(bad(format!("a moov box of {total} bytes (at most {MAX_MOOV_BYTES} are read)")));
            }
            let mut moov = vec![0u8; (total - header) as usize];
            f.seek(SeekFrom::Start(at + header))
                .and_then(|_| f.read_exact(&mut moov))
                .map_err(|e| IngestError::io(path, e))?;
            return from_moov(&moov, size).map_err(bad);
        }
        at += total;
    }
    Err(bad("no moov box".into()))
}

/// The first video track's frame times from a `moov` payload (`file_size` bounds its count).
fn from_moov(moov: &[u8], file_size: u64) -> std::result::Result<VideoInfo, String> {
    let codec = store::video::video_sample_entry(moov).ok_or("no video track")?;
    let trak = boxes(moov)
        .filter(|(k, _)| k == b"trak")
        .find(|(_, t)| {
            child(t, b"mdia").and_then(|m| child(m, b"minf")).and_then(|m| child(m, b"vmhd")).is_some()
        })
        .map(|(_, t)| t)
        .ok_or("no video track")?;
    let mdia = child(trak, b"mdia").ok_or("the video track has no mdia box")?;
    let mdhd = child(mdia, b"mdhd").ok_or("the video track has no mdhd box")?;
    let timescale = match mdhd.first() {
        Some(1) => u32_at(mdhd, 20),
        _ => u32_at(mdhd, 12),
    }
    .filter(|&t| t > 0)
    .ok_or("the video track's timescale is missing or 0")?;
    let stbl =
        child(mdia, b"minf").and_then(|m| child(m, b"stbl")).ok_or("the video track has no stbl box")?;
    let stsz = child(stbl, b"stsz").ok_or("the video track has no stsz box")?;
    let count = u32_at(stsz, 8).ok_or("the stsz box is cut short")? as u64;
    if count == 0 {
        return Err("the video has no frames".into());
    }
    if count > MAX_FRAMES.min(file_size) {
        return Err(format!(
            "the video declares {count} frames in a file of {file_size} bytes (at most {MAX_FRAMES} are read)"
        ));
    }
    let stts = child(stbl, b"stts").ok_or("the video track has no stts box")?;
    let entries = u32_at(stts, 4).ok_or("the stts box is cut short")? as usize;
    if entries.saturating_mul(8) > stts.len().saturating_sub(8) {
        return Err(format!("the stts box declares {entries} entries in {} bytes", stts.len()));
    }
    let mut starts = Vec::with_capacity(count as usize);
    let (mut t, mut deltas) = (0u64, std::collections::BTreeSet::new());
    for e in 0..entries {
        let (n, delta) = (u32_at(stts, 8 + 8 * e).unwrap_or(0), u32_at(stts, 12 + 8 * e).unwrap_or(0));
        if n > 0 {
            deltas.insert(delta);
        }
        for _ in 0..n {
            if starts.len() as u64 == count {
                return Err(format!("the stts box times more than the {count} frames of stsz"));
            }
            starts.push(t as f64 / timescale as f64);
            t = t.saturating_add(delta as u64);
        }
    }
    if starts.len() as u64 != count {
        return Err(format!("the video has {count} frames but stts times {}", starts.len()));
    }
    let fps = match deltas.iter().collect::<Vec<_>>()[..] {
        [&d] if d > 0 => Some(timescale as f64 / d as f64),
        _ => None,
    };
    Ok(VideoInfo { times: starts, fps, codec: store::video::codec_name(&codec) })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The `moov` payload of `hostile_corpus::mp4_header`'s file.
    fn moov(timescale: u32, stts: &[(u32, u32)], count: u32) -> Vec<u8> {
        let file = hostile_corpus::mp4_header(timescale, stts, count);
        let at = file.windows(4).position(|w| w == b"moov").unwrap();
        file[at + 4..].to_vec()
    }

    #[test]
    fn frame_times_come_from_stts() {
        let v = from_moov(&moov(10240, &[(3, 1024)], 3), 1 << 20).unwrap();
        assert_eq!((v.times, v.fps, v.codec.as_str()), (vec![0.0, 0.1, 0.2], Some(10.0), "H.264"));
        let v = from_moov(&moov(1000, &[(1, 100), (1, 50)], 2), 1 << 20).unwrap();
        assert_eq!((v.times, v.fps), (vec![0.0, 0.1], None));
    }

    #[test]
    fn declared_counts_are_checked_before_allocating() {
        let e = from_moov(&moov(10, &[(u32::MAX, 1)], u32::MAX), 1 << 20).unwrap_err();
        assert!(e.contains("declares 4294967295 frames"), "{e}");
        let e = from_moov(&moov(10, &[(2, 1)], 3), 1 << 20).unwrap_err();
        assert!(e.contains("3 frames but stts times 2"), "{e}");
        let e = from_moov(&moov(10, &[(4, 1)], 3), 1 << 20).unwrap_err();
        assert!(e.contains("more than the 3 frames"), "{e}");
        let e = from_moov(&moov(0, &[(3, 1)], 3), 1 << 20).unwrap_err();
        assert!(e.contains("timescale"), "{e}");
        let mut m = moov(10, &[(3, 1)], 3);
        let at = m.windows(4).position(|w| w == b"stts").unwrap() + 8;
        m[at..at + 4].copy_from_slice(&u32::MAX.to_be_bytes());
        assert!(from_moov(&m, 1 << 20).unwrap_err().contains("declares 4294967295 entries"));
    }
}
