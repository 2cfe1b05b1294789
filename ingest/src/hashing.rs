//! Source identity: sha256 of a file, or of a folder (its files in sorted relative-path order:
//! for each file, the relative path with `/` separators, a NUL byte, the length as u64 LE, then
//! the contents).

use std::io::Read;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use sha2::{Digest, Sha256};

use crate::error::{IngestError, Result};

const BUF: usize = 4 << 20;

/// sha256 (hex) and size of one file.
pub fn hash_file(path: &Path) -> Result<(String, u64)> {
    hash_file_progress(path, None)
}

fn hash_file_progress(path: &Path, progress: Option<&AtomicU64>) -> Result<(String, u64)> {
    let mut f = std::fs::File::open(path).map_err(|e| IngestError::io(path, e))?;
    let mut h = Sha256::new();
    let size = hash_reader_progress(&mut f, &mut h, progress).map_err(|e| IngestError::io(path, e))?;
    Ok((hex::encode(h.finalize()), size))
}

fn hash_reader_progress(
    r: &mut impl Read,
    h: &mut Sha256,
    progress: Option<&AtomicU64>,
) -> std::io::Result<u64> {
    let mut buf = vec![0u8; BUF];
    let mut n = 0u64;
    loop {
        let k = match r.read(&mut buf) {
            Ok(0) => break,
            Ok(k) => k,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(e),
        };
        h.update(&buf[..k]);
        n += k as u64;
        if let Some(p) = progress {
            p.fetch_add(k as u64, Ordering::Relaxed);
        }
    }
    Ok(n)
}

/// sha256 (hex) of bytes in memory (a whole file: the same as [`hash_file`] of it).
pub fn hash_bytes(bytes: &[u8]) -> String {
    hex::encode(Sha256::digest(bytes))
}

/// All regular files under `root`, as (relative path with `/`, absolute path), sorted.
/// Hidden entries (`.git`, `.cache`, ...) are skipped. A symlink that resolves outside `root` is
/// refused with an error naming it (a source may not pull in files from elsewhere, see
/// [`crate::confine`]); a folder reached twice through symlinks (a loop) is walked once.
pub fn list_files(root: &Path) -> Result<Vec<(String, PathBuf)>> {
    let canon_root = std::fs::canonicalize(root).map_err(|e| IngestError::io(root, e))?;
    let blobs = crate::confine::hub_cache_blobs(&canon_root);
    let mut seen_dirs = std::collections::HashSet::from([canon_root.clone()]);
    let mut out = Vec::new();
    let mut stack = vec![root.to_path_buf()];
    while let Some(dir) = stack.pop() {
        let rd = std::fs::read_dir(&dir).map_err(|e| IngestError::io(&dir, e))?;
        for ent in rd {
            let ent = ent.map_err(|e| IngestError::io(&dir, e))?;
            let name = ent.file_name();
            if name.to_string_lossy().starts_with('.') {
                continue;
            }
            let p = ent.path();
            let ft = ent.file_type().map_err(|e| IngestError::io(&p, e))?;
            let ft = if ft.is_symlink() {
                let target = std::fs::canonicalize(&p).map_err(|e| IngestError::io(&p, e))?;
                if !crate::confine::inside(&target, &canon_root, blobs.as_deref()) {
                    return Err(IngestError::invalid(
                        &p,
                        format!(
                            "a symlink to {}, outside the source folder {}: refused (copy the files in instead)",
                            target.display(),
                            canon_root.display()
                        ),
                    ));
                }
                std::fs::metadata(&p).map_err(|e| IngestError::io(&p, e))?.file_type()
            } else {
                ft
            };
            if ft.is_dir() {
                let c = std::fs::canonicalize(&p).map_err(|e| IngestError::io(&p, e))?;
                if seen_dirs.insert(c) {
                    stack.push(p);
                }
            } else if ft.is_file() {
                let rel = p
                    .strip_prefix(root)
                    .unwrap_or(&p)
                    .components()
                    .map(|c| c.as_os_str().to_string_lossy().into_owned())
                    .collect::<Vec<_>>()
                    .join("/");
                out.push((rel, p));
            }
        }
    }
    out.sort();
    Ok(out)
}

/// sha256 (hex) and total size of a folder.
pub fn hash_folder(root: &Path) -> Result<(String, u64)> {
    hash_folder_progress(root, None)
}

fn hash_folder_progress(root: &Path, progress: Option<&AtomicU64>) -> Result<(String, u64)> {
    let files = list_files(root)?;
    let mut h = Sha256::new();
    let mut total = 0u64;
    for (rel, abs) in files {
        let mut f = std::fs::File::open(&abs).map_err(|e| IngestError::io(&abs, e))?;
        let len = f.metadata().map_err(|e| IngestError::io(&abs, e))?.len();
        h.update(rel.as_bytes());
        h.update([0u8]);
        h.update(len.to_le_bytes());
        let n = hash_reader_progress(&mut f, &mut h, progress).map_err(|e| IngestError::io(&abs, e))?;
        if n != len {
            return Err(IngestError::invalid(&abs, "file changed while it was being read"));
        }
        total += n;
    }
    Ok((hex::encode(h.finalize()), total))
}

/// sha256 and size of a file or a folder.
pub fn hash_path(path: &Path) -> Result<(String, u64)> {
    hash_path_progress(path, None)
}

/// Like [`hash_path`], adding the bytes read so far to `progress`.
pub fn hash_path_progress(path: &Path, progress: Option<&AtomicU64>) -> Result<(String, u64)> {
    let md = std::fs::metadata(path).map_err(|e| IngestError::io(path, e))?;
    if md.is_dir() {
        hash_folder_progress(path, progress)
    } else {
        hash_file_progress(path, progress)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A symlink loop inside the folder is walked once (it used to be walked forever), and a
    /// symlink inside that stays inside is followed.
    #[test]
    fn symlink_loops_end_and_inner_links_are_followed() {
        let d = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(d.path().join("data")).unwrap();
        std::fs::write(d.path().join("data/a.parquet"), b"a").unwrap();
        std::os::unix::fs::symlink(d.path(), d.path().join("data/loop")).unwrap();
        std::os::unix::fs::symlink(d.path().join("data/a.parquet"), d.path().join("b.parquet")).unwrap();
        let files: Vec<String> = list_files(d.path()).unwrap().into_iter().map(|(r, _)| r).collect();
        assert_eq!(files, ["b.parquet", "data/a.parquet"]);
    }

    #[test]
    fn symlinks_out_of_the_folder_are_refused() {
        let outside = tempfile::tempdir().unwrap();
        std::fs::write(outside.path().join("id_ed25519"), b"secret").unwrap();
        let d = tempfile::tempdir().unwrap();
        std::os::unix::fs::symlink(outside.path().join("id_ed25519"), d.path().join("video.mp4")).unwrap();
        let e = list_files(d.path()).unwrap_err().to_string();
        assert!(e.contains("video.mp4") && e.contains("outside the source folder"), "{e}");
        assert!(hash_path(d.path()).is_err());
    }
}
