//! The MCAP record stream: records read linearly, chunks decompressed (sizes bounded first)
//! and CRC-checked, and a cut-off file told apart from a corrupt one.

use std::io::Read;
use std::path::Path;

use mcap::records::Record;
use mcap::sans_io::linear_reader::{LinearReadEvent, LinearReader, LinearReaderOptions};

use crate::error::{IngestError, Result};

/// Largest believable compression ratio / decompressed size of one chunk. A chunk is decompressed
/// whole, so its declared `uncompressed_size` is checked against both before anything is
/// allocated (writers cut chunks at a few MB: the mcap CLI and rosbag2 at 4 MiB, a chunk holding
/// one big message is that message's size).
pub const MAX_CHUNK_RATIO: u64 = 4096;
pub const MAX_CHUNK_BYTES: u64 = 256 << 20;

pub(super) enum End {
    Clean,
    Truncated(String),
}

/// Streams all records of an MCAP; `on` sees each record (chunks are decompressed).
pub(super) fn stream_records(
    path: &Path,
    r: &mut dyn Read,
    size_hint: u64,
    on: &mut dyn FnMut(Record<'_>) -> Result<()>,
) -> Result<End> {
    let limit = (size_hint as usize).saturating_add(1024).max(1 << 16);
    // Chunks are emitted whole and unpacked here: the crate's in-place unpacking of
    // uncompressed chunks underflows on a record longer than its chunk (fuzzing found it).
    let opts = LinearReaderOptions::default().with_emit_chunks(true).with_record_length_limit(limit);
    let mut reader = LinearReader::new_with_options(opts);
    let mut total = 0u64;
    while let Some(ev) = reader.next_event() {
        match ev {
            Ok(LinearReadEvent::ReadRequest(need)) => {
                let buf = reader.insert(need.clamp(1, 8 << 20));
                let n = loop {
                    match r.read(buf) {
                        Ok(n) => break n,
                        Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                        Err(e) => return Err(IngestError::io(path, e)),
                    }
                };
                total += n as u64;
                reader.notify_read(n);
            }
            Ok(LinearReadEvent::Record { opcode, data }) => {
                let rec = mcap::parse_record(opcode, data).map_err(|e| {
                    IngestError::invalid(
                        path,
                        format!("corrupt MCAP record (opcode {opcode:#04x}) near byte {total}: {e}"),
                    )
                })?;
                match rec {
                    Record::Chunk { header, data } => unpack_chunk(path, total, header, &data, on)?,
                    rec => on(rec)?,
                }
            }
            Err(mcap::McapError::UnexpectedEof) => {
                return Ok(End::Truncated(format!("the file ends in the middle of a record after {total} bytes (no footer): the recording was cut off")));
            }
            Err(mcap::McapError::BadMagic) => {
                return Err(IngestError::invalid(path, "not an MCAP file (bad magic)"));
            }
            Err(e) => {
                return Err(IngestError::invalid(path, format!("corrupt MCAP data near byte {total}: {e}")))
            }
        }
    }
    Ok(End::Clean)
}

/// Yields the records inside a chunk, checking its CRC and lengths.
fn unpack_chunk(
    path: &Path,
    at: u64,
    header: mcap::records::ChunkHeader,
    data: &[u8],
    on: &mut dyn FnMut(Record<'_>) -> Result<()>,
) -> Result<()> {
    let bad = |m: String| IngestError::invalid(path, format!("corrupt MCAP chunk near byte {at}: {m}"));
    let owned;
    let data: &[u8] = if header.compression.is_empty() {
        data
    } else {
        // bound the claimed size by a generous compression ratio before allocating it
        let max =
            (data.len() as u64).saturating_mul(MAX_CHUNK_RATIO).saturating_add(1 << 16).min(MAX_CHUNK_BYTES);
        if header.uncompressed_size > max {
            return Err(bad(format!(
                "claims {} uncompressed bytes from {} compressed bytes (more than {max}: at most {MAX_CHUNK_RATIO}:1 and {MAX_CHUNK_BYTES} bytes): refused",
                header.uncompressed_size,
                data.len()
            )));
        }
        let want = header.uncompressed_size as usize;
        owned = match header.compression.as_str() {
            "zstd" => zstd::bulk::decompress(data, want).map_err(|e| bad(format!("zstd: {e}")))?,
            "lz4" => {
                use std::io::Read as _;
                let mut out = Vec::with_capacity(want);
                let dec = lz4::Decoder::new(data).map_err(|e| bad(format!("lz4: {e}")))?;
                dec.take(want as u64 + 1).read_to_end(&mut out).map_err(|e| bad(format!("lz4: {e}")))?;
                out
            }
            other => return Err(bad(format!("unsupported chunk compression {other:?}"))),
        };
        &owned
    };
    if header.uncompressed_size != data.len() as u64 {
        return Err(bad(format!(
            "uncompressed_size {} but {} bytes of records",
            header.uncompressed_size,
            data.len()
        )));
    }
    if header.uncompressed_crc != 0 {
        let c = crc32(data);
        if c != header.uncompressed_crc {
            return Err(bad(format!(
                "CRC mismatch (saved {:#010x}, computed {c:#010x})",
                header.uncompressed_crc
            )));
        }
    }
    let mut p = 0usize;
    while p < data.len() {
        if data.len() - p < 9 {
            return Err(bad("ends in the middle of a record header".into()));
        }
        let op = data[p];
        let len = u64::from_le_bytes(data[p + 1..p + 9].try_into().expect("8 bytes"));
        if len > (data.len() - p - 9) as u64 {
            return Err(bad(format!(
                "record of {len} bytes (opcode {op:#04x}) runs past the end of its chunk"
            )));
        }
        let body = &data[p + 9..p + 9 + len as usize];
        let rec = mcap::parse_record(op, body).map_err(|e| bad(format!("record (opcode {op:#04x}): {e}")))?;
        on(rec)?;
        p += 9 + len as usize;
    }
    Ok(())
}

fn crc32(data: &[u8]) -> u32 {
    // CRC-32 (IEEE), table-less bitwise is too slow for big chunks: use a small table.
    static TABLE: std::sync::OnceLock<[u32; 256]> = std::sync::OnceLock::new();
    let t = TABLE.get_or_init(|| {
        let mut t = [0u32; 256];
        for (i, e) in t.iter_mut().enumerate() {
            let mut c = i as u32;
            for _ in 0..8 {
                c = if c & 1 != 0 { 0xedb8_8320 ^ (c >> 1) } else { c >> 1 };
            }
            *e = c;
        }
        t
    });
    let mut c = !0u32;
    for &b in data {
        c = t[((c ^ b as u32) & 0xff) as usize] ^ (c >> 8);
    }
    !c
}
