//! An HDF5 file being read as untrusted input: its path (every error names it) and the most
//! decoded bytes one of its datasets may declare, whatever its header says. robomimic and ALOHA
//! files, and the windowed reads of their cameras (`h5rows`), share it.

use std::path::Path;

use crate::error::IngestError;

/// Decoded size of one dataset that is believed whatever the file's size (small datasets
/// holding only the fill value cost nothing to allow).
const DECLARED_BYTES_FLOOR: u64 = 1 << 20;

/// Largest believable ratio of a dataset's decoded size to the file's size: deflate, the
/// strongest filter robomimic files use, cannot exceed 1032:1.
pub const MAX_DECLARED_RATIO: u64 = 1100;

/// Largest decoded size of one dataset, whatever the file's size: a demo is decoded whole, so
/// this bounds memory (a 2,000-step demo of 480x640 RGB frames is 1.8 GB).
pub const MAX_DATASET_BYTES: u64 = 2 << 30;

/// The file being read: its path (errors name it) and how many decoded bytes one of its
/// datasets may declare. Derefs to the path.
pub(crate) struct Src<'a> {
    pub(crate) path: &'a Path,
    pub(crate) file_len: u64,
}

impl Src<'_> {
    pub(crate) fn new(path: &Path, file_len: u64) -> Src<'_> {
        Src { path, file_len }
    }

    /// What one dataset may declare: the file's size times [`MAX_DECLARED_RATIO`] (at least
    /// [`DECLARED_BYTES_FLOOR`]), never more than [`MAX_DATASET_BYTES`].
    pub(crate) fn max_dataset_bytes(&self) -> u64 {
        self.file_len.saturating_mul(MAX_DECLARED_RATIO).clamp(DECLARED_BYTES_FLOOR, MAX_DATASET_BYTES)
    }
}

impl std::ops::Deref for Src<'_> {
    type Target = Path;
    fn deref(&self) -> &Path {
        self.path
    }
}

impl AsRef<Path> for Src<'_> {
    fn as_ref(&self) -> &Path {
        self.path
    }
}

pub(crate) fn h5err(
    path: &Path,
    what: impl std::fmt::Display,
) -> impl FnOnce(hdf5_pure::Error) -> IngestError {
    let what = what.to_string();
    let path = path.to_path_buf();
    move |e| IngestError::invalid(path, format!("{what}: {e}"))
}

/// Reads shorter than this are served from [`BLOCK_BYTES`]-aligned blocks read whole; longer
/// ones (a demo's larger datasets) go to the file as they are.
const SMALL_READ_BYTES: usize = 64 << 10;

/// Size of one cached block of the file.
const BLOCK_BYTES: u64 = 256 << 10;

/// Blocks kept (least recently used dropped): memory is at most this many blocks, whatever
/// the file says.
const BLOCKS_KEPT: usize = 4;

/// A [`hdf5_pure::Source`] that turns the HDF5 reader's many small reads (object headers,
/// B-tree nodes, heaps, attributes and small datasets, each a `pread` of tens of bytes, ~100 a
/// demo) into one read per [`BLOCK_BYTES`] block: the metadata of a demo lies beside its data.
pub(crate) struct BlockCached<S> {
    inner: S,
    /// (block index, its bytes), most recently used last.
    blocks: std::sync::Mutex<Vec<(u64, Vec<u8>)>>,
}

impl<S: hdf5_pure::Source> BlockCached<S> {
    pub(crate) fn new(inner: S) -> Self {
        BlockCached { inner, blocks: std::sync::Mutex::new(Vec::with_capacity(BLOCKS_KEPT)) }
    }

    /// Copies the bytes of block `index` from `offset` on into `out` (reading the block if it is
    /// not kept); returns how many were copied.
    fn copy_from_block(
        &self,
        blocks: &mut Vec<(u64, Vec<u8>)>,
        index: u64,
        offset: u64,
        out: &mut [u8],
    ) -> std::result::Result<usize, hdf5_pure::FormatError> {
        let at = match blocks.iter().position(|(i, _)| *i == index) {
            Some(at) => at,
            None => {
                let start = index * BLOCK_BYTES;
                let end = (start + BLOCK_BYTES).min(self.inner.len());
                // `start < len`: the caller checked that the read ends inside the file
                let mut bytes = if blocks.len() >= BLOCKS_KEPT { blocks.remove(0).1 } else { Vec::new() };
                bytes.resize((end - start) as usize, 0);
                self.inner.read_at(start, &mut bytes)?;
                blocks.push((index, bytes));
                blocks.len() - 1
            }
        };
        let entry = blocks.remove(at);
        let from = (offset - index * BLOCK_BYTES) as usize;
        let n = out.len().min(entry.1.len().saturating_sub(from));
        out[..n].copy_from_slice(&entry.1[from..from + n]);
        blocks.push(entry);
        Ok(n)
    }
}

impl<S: hdf5_pure::Source> hdf5_pure::Source for BlockCached<S> {
    fn len(&self) -> u64 {
        self.inner.len()
    }

    fn read_at(&self, offset: u64, buf: &mut [u8]) -> std::result::Result<(), hdf5_pure::FormatError> {
        let past_end = offset.checked_add(buf.len() as u64).is_none_or(|end| end > self.inner.len());
        if buf.len() >= SMALL_READ_BYTES || past_end {
            return self.inner.read_at(offset, buf);
        }
        let mut blocks = self.blocks.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        let mut done = 0;
        while done < buf.len() {
            let at = offset + done as u64;
            let n = self.copy_from_block(&mut blocks, at / BLOCK_BYTES, at, &mut buf[done..])?;
            if n == 0 {
                // unreachable: the read ends inside the file, so every block it touches holds bytes
                return self.inner.read_at(at, &mut buf[done..]);
            }
            done += n;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use hdf5_pure::Source;

    /// An in-memory file counting the reads that reach it.
    struct Counted {
        bytes: Vec<u8>,
        reads: std::sync::atomic::AtomicUsize,
    }

    impl Source for Counted {
        fn len(&self) -> u64 {
            self.bytes.len() as u64
        }
        fn read_at(&self, offset: u64, buf: &mut [u8]) -> std::result::Result<(), hdf5_pure::FormatError> {
            self.reads.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            let at = offset as usize;
            let part = self.bytes.get(at..at.saturating_add(buf.len())).ok_or(
                hdf5_pure::FormatError::UnexpectedEof {
                    expected: at.saturating_add(buf.len()),
                    available: self.bytes.len(),
                },
            )?;
            buf.copy_from_slice(part);
            Ok(())
        }
    }

    /// Every read returns the file's bytes (across block boundaries, at the end, large ones
    /// straight through), reads past the end fail as the file's own do, small neighbouring reads
    /// cost one read of the file, and no more than `BLOCKS_KEPT` blocks are held.
    #[test]
    fn block_cache_returns_the_files_bytes_and_bounds_memory() {
        let len = 3 * BLOCK_BYTES as usize + 1234;
        let bytes: Vec<u8> = (0..len).map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8).collect();
        let src = BlockCached::new(Counted { bytes: bytes.clone(), reads: Default::default() });
        let mut x = 12_345u64;
        for _ in 0..5000 {
            x = x.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
            let off = (x >> 20) as usize % len;
            let n = match x % 5 {
                0 => (x >> 8) as usize % (SMALL_READ_BYTES * 2),
                _ => (x >> 8) as usize % 300,
            }
            .min(len - off);
            let got = src.read_exact_at(off as u64, n).unwrap();
            assert_eq!(got, bytes[off..off + n], "read of {n} at {off}");
            assert!(src.blocks.lock().unwrap().len() <= BLOCKS_KEPT);
        }
        assert!(src.read_exact_at(len as u64 - 4, 5).is_err());
        assert!(src.read_exact_at(u64::MAX - 1, 4).is_err());
        assert!(src.read_at(len as u64 - 4, &mut [0u8; 5]).is_err());
        let mut last = [0u8; 4];
        src.read_at(len as u64 - 4, &mut last).unwrap();
        assert_eq!(last, bytes[len - 4..]);

        let src = BlockCached::new(Counted { bytes, reads: Default::default() });
        for k in 0..1000u64 {
            src.read_exact_at(k * 100, 40).unwrap();
        }
        assert_eq!(src.inner.reads.load(std::sync::atomic::Ordering::Relaxed), 1);
    }
}
