//! A bounds check of a Parquet footer before the `parquet` crate decodes it.
//!
//! The crate sizes its vectors from the element counts written in the footer's Thrift lists
//! (`Vec::with_capacity(count)`) before reading the elements: a corrupt count of 10^8 row groups in
//! a 100-byte file makes it reserve ~9 GB (found by fuzzing the LeRobot reader), and a count near
//! `i32::MAX` aborts the process on allocation failure. Here the footer is walked first as plain
//! Thrift compact protocol: every list, set, map and binary must fit in the bytes that are left
//! (each element takes at least one byte), lists hold at most [`MAX_LIST`] elements, nesting is
//! bounded, and the whole structure must end inside the footer. A footer that passes can only
//! make the parquet crate allocate in proportion to its real size.
//!
//! [`check_pages`] then walks the page headers of every column chunk the footer lists: the parquet
//! crate sizes a page's decompression buffer from the header's `uncompressed_page_size` (snappy
//! zero-fills it: a 100-byte page declaring 2 GB makes the process touch 2 GB). Each page must lie
//! inside its column chunk and declare at most [`MAX_PAGE_RATIO`] times its compressed size (plus
//! [`PAGE_SLACK`]) and at most [`MAX_PAGE_BYTES`].

use parquet::file::reader::ChunkReader;

/// More elements than any real footer list holds (row groups, columns, schema elements, …).
pub const MAX_LIST: u64 = 1 << 20;

/// Largest believable ratio of a page's declared uncompressed size to its compressed size
/// (snappy cannot pass ~22:1, gzip 1032:1; zstd of constant data can, hence the margin).
pub const MAX_PAGE_RATIO: u64 = 4096;
/// Declared uncompressed bytes allowed on top of the ratio (tiny pages, v2 level bytes).
pub const PAGE_SLACK: u64 = 1 << 20;
/// Largest declared uncompressed page (writers cut pages at ~1 MB; a page holding one large
/// binary value is that value's size).
pub const MAX_PAGE_BYTES: u64 = 256 << 20;
/// Largest page header read (headers hold statistics: min/max values of the page).
const MAX_PAGE_HEADER: u64 = 16 << 20;

/// Checks the page headers of every column chunk of `meta` (see the module doc); the error names
/// the row group, the column and the sizes.
pub fn check_pages<R: ChunkReader>(
    r: &R,
    meta: &parquet::file::metadata::ParquetMetaData,
) -> Result<(), String> {
    let len = r.len();
    for (g, rg) in meta.row_groups().iter().enumerate() {
        for c in rg.columns() {
            let col = c.column_path().string();
            let start = c.dictionary_page_offset().unwrap_or(c.data_page_offset());
            let size = c.compressed_size();
            let (Ok(start), Ok(size)) = (u64::try_from(start), u64::try_from(size)) else {
                return Err(format!("row group {g}, column {col}: negative byte range {start}+{size}"));
            };
            let end = start.checked_add(size).filter(|&e| e <= len).ok_or_else(|| {
                format!("row group {g}, column {col}: byte range {start}+{size} outside the {len}-byte file")
            })?;
            let mut pos = start;
            let mut page = 0usize;
            while pos < end {
                let (hlen, unc, comp) = read_page_header(r, pos, end).map_err(|e| {
                    format!(
                        "row group {g}, column {col}, page {page} at byte {pos}: corrupt page header: {e}"
                    )
                })?;
                let (Ok(unc), Ok(comp)) = (u64::try_from(unc), u64::try_from(comp)) else {
                    return Err(format!("row group {g}, column {col}, page {page}: negative page sizes ({unc} uncompressed, {comp} compressed)"));
                };
                let next = pos.checked_add(hlen).and_then(|p| p.checked_add(comp)).filter(|&p| p <= end).ok_or_else(|| {
                    format!("row group {g}, column {col}, page {page} at byte {pos}: {comp} compressed bytes run past the column chunk's end at byte {end}")
                })?;
                let max = comp.saturating_mul(MAX_PAGE_RATIO).saturating_add(PAGE_SLACK).min(MAX_PAGE_BYTES);
                if unc > max {
                    return Err(format!(
                        "row group {g}, column {col}, page {page}: declares {unc} uncompressed bytes from {comp} compressed bytes (at most {max}: {MAX_PAGE_RATIO}:1 and {MAX_PAGE_BYTES} bytes): refused"
                    ));
                }
                pos = next;
                page += 1;
            }
        }
    }
    Ok(())
}

/// (header length, uncompressed_page_size, compressed_page_size) of the page header at `pos`.
fn read_page_header<R: ChunkReader>(r: &R, pos: u64, end: u64) -> Result<(u64, i64, i64), String> {
    // most headers are tens of bytes (more with statistics): start small, grow when cut off
    let mut want = (end - pos).min(1 << 10);
    loop {
        let buf = r.get_bytes(pos, want as usize).map_err(|e| format!("cannot read it: {e}"))?;
        let mut w = Walker { buf: &buf, pos: 0 };
        match w.page_header() {
            Ok((unc, comp)) => return Ok((w.pos as u64, unc, comp)),
            Err(e) if w.pos >= buf.len() || e.contains("left") || e == "unexpected end" => {
                let more = (want * 8).min(end - pos).min(MAX_PAGE_HEADER);
                if more <= want {
                    return Err(e);
                }
                want = more;
            }
            Err(e) => return Err(e),
        }
    }
}
const MAX_DEPTH: usize = 64;

/// Checks the footer of the Parquet file `r`; the error says what is wrong.
pub fn check<R: ChunkReader>(r: &R) -> Result<(), String> {
    let len = r.len();
    if len < 12 {
        return Err(format!("file of {len} bytes is too small for a Parquet file"));
    }
    let tail = r.get_bytes(len - 8, 8).map_err(|e| format!("cannot read the footer: {e}"))?;
    if tail.len() != 8 {
        return Err("cannot read the footer".into());
    }
    match &tail[4..8] {
        b"PAR1" => {}
        b"PARE" => return Err("encrypted Parquet files are not supported".into()),
        _ => return Err("no PAR1 magic at the end of the file".into()),
    }
    let meta_len = u32::from_le_bytes([tail[0], tail[1], tail[2], tail[3]]) as u64;
    if meta_len == 0 || meta_len + 12 > len {
        return Err(format!("footer length {meta_len} does not fit in the {len}-byte file"));
    }
    let meta = r
        .get_bytes(len - 8 - meta_len, meta_len as usize)
        .map_err(|e| format!("cannot read the footer: {e}"))?;
    if meta.len() as u64 != meta_len {
        return Err("cannot read the footer".into());
    }
    let mut w = Walker { buf: &meta, pos: 0 };
    w.structure(0).map_err(|e| format!("corrupt footer metadata at byte {}: {e}", w.pos))
}

struct Walker<'a> {
    buf: &'a [u8],
    pos: usize,
}

// Compact protocol type ids.
const BOOL_TRUE: u8 = 1;
const BOOL_FALSE: u8 = 2;
const BYTE: u8 = 3;
const I16: u8 = 4;
const I32: u8 = 5;
const I64: u8 = 6;
const DOUBLE: u8 = 7;
const BINARY: u8 = 8;
const LIST: u8 = 9;
const SET: u8 = 10;
const MAP: u8 = 11;
const STRUCT: u8 = 12;

impl Walker<'_> {
    fn left(&self) -> u64 {
        (self.buf.len() - self.pos) as u64
    }

    fn byte(&mut self) -> Result<u8, String> {
        let b = *self.buf.get(self.pos).ok_or("unexpected end")?;
        self.pos += 1;
        Ok(b)
    }

    fn skip(&mut self, n: u64) -> Result<(), String> {
        if n > self.left() {
            return Err(format!("{n} bytes announced, {} left", self.left()));
        }
        self.pos += n as usize;
        Ok(())
    }

    fn varint(&mut self) -> Result<u64, String> {
        let mut v = 0u64;
        for shift in (0..70).step_by(7) {
            let b = self.byte()?;
            if shift == 63 && b > 1 {
                return Err("varint overflows 64 bits".into());
            }
            v |= ((b & 0x7f) as u64) << shift;
            if b & 0x80 == 0 {
                return Ok(v);
            }
        }
        Err("varint longer than 10 bytes".into())
    }

    fn count(&mut self, n: u64, what: &str) -> Result<u64, String> {
        if n > MAX_LIST {
            return Err(format!("{what} of {n} elements"));
        }
        if n > self.left() {
            return Err(format!("{what} of {n} elements in the {} bytes left", self.left()));
        }
        Ok(n)
    }

    fn value(&mut self, t: u8, depth: usize) -> Result<(), String> {
        if depth > MAX_DEPTH {
            return Err("nested too deeply".into());
        }
        match t {
            BOOL_TRUE | BOOL_FALSE | BYTE => self.skip(1),
            I16 | I32 | I64 => self.varint().map(|_| ()),
            DOUBLE => self.skip(8),
            BINARY => {
                let n = self.varint()?;
                self.skip(n)
            }
            LIST | SET => {
                let h = self.byte()?;
                let et = h & 0x0f;
                let n = if h >> 4 == 15 { self.varint()? } else { (h >> 4) as u64 };
                let n = self.count(n, "list")?;
                for _ in 0..n {
                    // In lists, booleans take one byte each.
                    self.value(if et == BOOL_FALSE { BOOL_TRUE } else { et }, depth + 1)?;
                }
                Ok(())
            }
            MAP => {
                let n = self.varint()?;
                if n == 0 {
                    return Ok(());
                }
                let n = self.count(n, "map")?;
                let kv = self.byte()?;
                for _ in 0..n {
                    self.value(kv >> 4, depth + 1)?;
                    self.value(kv & 0x0f, depth + 1)?;
                }
                Ok(())
            }
            STRUCT => self.structure(depth + 1),
            other => Err(format!("unknown Thrift type {other}")),
        }
    }

    /// A PageHeader struct: its `uncompressed_page_size` (field 2) and `compressed_page_size`
    /// (field 3); other fields are skipped.
    fn page_header(&mut self) -> Result<(i64, i64), String> {
        let (mut unc, mut comp) = (None, None);
        let mut id: i64 = 0;
        loop {
            let h = self.byte()?;
            if h == 0 {
                break;
            }
            let t = h & 0x0f;
            id = if h >> 4 == 0 { zigzag(self.varint()?) } else { id + (h >> 4) as i64 };
            match (id, t) {
                (2, I32) => unc = Some(zigzag(self.varint()?)),
                (3, I32) => comp = Some(zigzag(self.varint()?)),
                (_, BOOL_TRUE | BOOL_FALSE) => {}
                _ => self.value(t, 1)?,
            }
        }
        match (unc, comp) {
            (Some(u), Some(c)) => Ok((u, c)),
            _ => Err("no uncompressed_page_size/compressed_page_size".into()),
        }
    }

    fn structure(&mut self, depth: usize) -> Result<(), String> {
        if depth > MAX_DEPTH {
            return Err("nested too deeply".into());
        }
        loop {
            let h = self.byte()?;
            if h == 0 {
                return Ok(());
            }
            let t = h & 0x0f;
            if h >> 4 == 0 {
                // long form: the field id follows as a zigzag varint
                self.varint()?;
            }
            match t {
                // a struct field's boolean value is in the type itself
                BOOL_TRUE | BOOL_FALSE => {}
                _ => self.value(t, depth)?,
            }
        }
    }
}

fn zigzag(v: u64) -> i64 {
    ((v >> 1) as i64) ^ -((v & 1) as i64)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn file(meta: &[u8]) -> bytes::Bytes {
        let mut v = b"PAR1".to_vec();
        v.extend_from_slice(meta);
        v.extend_from_slice(&(meta.len() as u32).to_le_bytes());
        v.extend_from_slice(b"PAR1");
        v.into()
    }

    #[test]
    fn refuses_lists_longer_than_their_bytes() {
        // version=1, schema=[{name:"schema", num_children:0}], num_rows=0, row_groups: 10^8 x struct
        let mut m = vec![0x15, 0x02, 0x19, 0x1c, 0x48, 6];
        m.extend_from_slice(b"schema");
        m.extend_from_slice(&[0x15, 0x00, 0x00, 0x16, 0x00, 0x19, 0xfc]);
        let mut n = 100_000_000u64;
        while n >= 0x80 {
            m.push((n as u8) | 0x80);
            n >>= 7;
        }
        m.push(n as u8);
        m.push(0);
        let err = check(&file(&m)).unwrap_err();
        assert!(err.contains("list of 100000000 elements"), "{err}");
    }

    #[test]
    fn accepts_a_real_footer() {
        use arrow::array::{Int32Array, RecordBatch};
        let batch =
            RecordBatch::try_from_iter([("x", std::sync::Arc::new(Int32Array::from(vec![1, 2, 3])) as _)])
                .unwrap();
        let mut out = Vec::new();
        let mut w = parquet::arrow::ArrowWriter::try_new(&mut out, batch.schema(), None).unwrap();
        w.write(&batch).unwrap();
        w.close().unwrap();
        check(&bytes::Bytes::from(out)).unwrap();
    }

    #[test]
    fn refuses_bad_lengths() {
        assert!(check(&bytes::Bytes::from_static(b"PAR1")).is_err());
        let mut v = b"PAR1PAR1".to_vec();
        v.extend_from_slice(&u32::MAX.to_le_bytes());
        v.extend_from_slice(b"PAR1");
        assert!(check(&bytes::Bytes::from(v)).unwrap_err().contains("does not fit"));
    }
}
