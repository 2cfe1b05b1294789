//! Paths named by a source's own metadata stay inside the source.
//!
//! A LeRobot dataset's `meta/info.json` holds path templates (`data_path`, `video_path`) filled
//! with feature keys and chunk/file indices from its episode metadata: all of it is untrusted. A
//! template such as `../../../../etc/passwd` or `/home/me/.ssh/id_ed25519`, or a symlink inside
//! the folder pointing elsewhere, would otherwise make ingest copy any readable file of the machine
//! into the store (as a media object served to every viewer). [`Root`] refuses, with an error
//! naming the field and the path: absolute paths, `..` components, and files or folders that
//! resolve (through symlinks) outside the dataset's canonical root.
//!
//! The same rule holds for the folder walk that hashes a dataset ([`crate::hashing::list_files`]):
//! a symlink out of the folder is refused, a symlink loop is walked once.

use std::path::{Component, Path, PathBuf};

use crate::error::{IngestError, Result};

/// A dataset folder and its canonical path (symlinks resolved).
#[derive(Debug, Clone)]
pub struct Root {
    dir: PathBuf,
    canon: PathBuf,
    /// Where the dataset's symlinks may also lead: see [`hub_cache_blobs`].
    blobs: Option<PathBuf>,
}

/// A dataset read straight from the Hugging Face hub cache
/// (`…/datasets--ORG--NAME/snapshots/REV/`) is a tree of symlinks into the same repository's
/// `…/datasets--ORG--NAME/blobs/`: those links stay inside what was downloaded, so they are
/// followed. Returns that `blobs` folder (canonical) for such a snapshot folder.
pub fn hub_cache_blobs(canon_root: &Path) -> Option<PathBuf> {
    let snapshots = canon_root.parent()?;
    let repo = snapshots.parent()?;
    let is_repo =
        repo.file_name()?.to_str().is_some_and(|n| n.starts_with("datasets--") || n.starts_with("models--"));
    if snapshots.file_name()? != "snapshots" || !is_repo {
        return None;
    }
    std::fs::canonicalize(repo.join("blobs")).ok().filter(|b| b.starts_with(repo))
}

/// Whether a canonical path lies inside the canonical root or, for a hub-cache snapshot, in its
/// repository's `blobs` folder.
pub fn inside(c: &Path, canon_root: &Path, blobs: Option<&Path>) -> bool {
    c.starts_with(canon_root) || blobs.is_some_and(|b| c.starts_with(b))
}

impl Root {
    pub fn new(dir: &Path) -> Result<Root> {
        let canon = std::fs::canonicalize(dir).map_err(|e| IngestError::io(dir, e))?;
        let blobs = hub_cache_blobs(&canon);
        Ok(Root { dir: dir.to_path_buf(), canon, blobs })
    }

    /// The folder as given.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The folder with symlinks resolved.
    pub fn canonical(&self) -> &Path {
        &self.canon
    }

    /// `rel`, a path the dataset's metadata produced (`field` says which: e.g. "`data_path`
    /// template for episode 3"; `src` is the file it was read from), joined to the root after
    /// checking that it is relative and has no `..`; when the file exists, it must also resolve
    /// inside the root ([`Root::check_inside`]).
    pub fn file(&self, src: &Path, field: &str, rel: &str) -> Result<PathBuf> {
        let abs = self.join(src, field, rel)?;
        self.check_inside(&abs, field)?;
        Ok(abs)
    }

    /// The lexical half of [`Root::file`] (relative, no `..`), for callers that check the
    /// symlinks once per distinct path.
    pub fn join(&self, src: &Path, field: &str, rel: &str) -> Result<PathBuf> {
        check_relative(rel).map_err(|why| {
            IngestError::invalid(src, format!("{field} gives the path {rel:?}, {why}: refused (a dataset may only name files inside its folder)"))
        })?;
        Ok(self.dir.join(rel))
    }

    /// Checks that `abs` (when it exists) resolves, through any symlinks, to a place inside the
    /// root. A missing file passes: the caller reports it as missing.
    pub fn check_inside(&self, abs: &Path, what: &str) -> Result<()> {
        match std::fs::canonicalize(abs) {
            Ok(c) if inside(&c, &self.canon, self.blobs.as_deref()) => Ok(()),
            Ok(c) => Err(IngestError::invalid(
                abs,
                format!(
                    "{what}: this path resolves (through a symlink) to {}, outside the dataset folder {}: refused",
                    c.display(),
                    self.canon.display()
                ),
            )),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
            Err(e) => Err(IngestError::io(abs, e)),
        }
    }
}

/// Why `rel` may not be joined to a root, if it may not: empty, absolute, or with a `..`.
pub fn check_relative(rel: &str) -> std::result::Result<(), &'static str> {
    if rel.is_empty() {
        return Err("which is empty");
    }
    if rel.contains('\0') {
        return Err("which holds a NUL byte");
    }
    let p = Path::new(rel);
    if p.is_absolute() {
        return Err("which is absolute");
    }
    for c in p.components() {
        match c {
            Component::Normal(_) | Component::CurDir => {}
            Component::ParentDir => return Err("which climbs out with `..`"),
            Component::RootDir | Component::Prefix(_) => return Err("which is absolute"),
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn relative_paths_only() {
        assert!(check_relative("data/chunk-000/file-000.parquet").is_ok());
        assert!(check_relative("./videos/x.mp4").is_ok());
        assert_eq!(check_relative("../x"), Err("which climbs out with `..`"));
        assert_eq!(check_relative("data/../../x"), Err("which climbs out with `..`"));
        assert_eq!(check_relative("/etc/passwd"), Err("which is absolute"));
        assert_eq!(check_relative(""), Err("which is empty"));
    }

    #[test]
    fn symlinks_out_of_the_root_are_refused() {
        let outside = tempfile::tempdir().unwrap();
        std::fs::write(outside.path().join("secret"), b"s").unwrap();
        let d = tempfile::tempdir().unwrap();
        std::fs::create_dir(d.path().join("data")).unwrap();
        std::fs::write(d.path().join("data/ok.parquet"), b"x").unwrap();
        std::os::unix::fs::symlink(outside.path().join("secret"), d.path().join("data/link.parquet"))
            .unwrap();
        std::os::unix::fs::symlink(d.path().join("data/ok.parquet"), d.path().join("data/inner.parquet"))
            .unwrap();
        let r = Root::new(d.path()).unwrap();
        let src = d.path().join("meta/info.json");
        r.file(&src, "data_path", "data/ok.parquet").unwrap();
        r.file(&src, "data_path", "data/inner.parquet").unwrap();
        r.file(&src, "data_path", "data/missing.parquet").unwrap();
        let e = r.file(&src, "data_path", "data/link.parquet").unwrap_err().to_string();
        assert!(e.contains("outside the dataset folder") && e.contains("link.parquet"), "{e}");
        let e = r.file(&src, "`video_path` template", "../x.mp4").unwrap_err().to_string();
        assert!(e.contains("`video_path` template") && e.contains("\"../x.mp4\""), "{e}");
    }

    /// A hub-cache snapshot's links into its own repository's `blobs/` are followed; a link to
    /// another repository's blobs, or anywhere else, is still refused.
    #[test]
    fn hub_cache_snapshots_may_link_into_their_own_blobs() {
        let cache = tempfile::tempdir().unwrap();
        let repo = cache.path().join("datasets--org--name");
        let other = cache.path().join("datasets--org--other");
        for d in [repo.join("blobs"), repo.join("snapshots/abc123/data"), other.join("blobs")] {
            std::fs::create_dir_all(d).unwrap();
        }
        std::fs::write(repo.join("blobs/f00d"), b"x").unwrap();
        std::fs::write(other.join("blobs/beef"), b"y").unwrap();
        let snap = repo.join("snapshots/abc123");
        std::os::unix::fs::symlink(repo.join("blobs/f00d"), snap.join("data/ok.parquet")).unwrap();
        std::os::unix::fs::symlink(other.join("blobs/beef"), snap.join("data/bad.parquet")).unwrap();
        let r = Root::new(&snap).unwrap();
        let src = snap.join("meta/info.json");
        r.file(&src, "data_path", "data/ok.parquet").unwrap();
        assert!(r.file(&src, "data_path", "data/bad.parquet").is_err());
        // The same layout outside a hub cache gets no such allowance.
        assert!(hub_cache_blobs(&std::fs::canonicalize(repo.join("blobs")).unwrap()).is_none());
    }
}
