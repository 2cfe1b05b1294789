//! `videos/`: the store's video objects copied byte for byte (never re-encoded), one file per
//! object.

use std::collections::BTreeMap;
use std::fs::File;
use std::path::Path;

use store::Store;

use super::{feature_key, fill, CHUNKS_SIZE, VIDEO_PATH};
use crate::{ExportError, ExportReport, Result};

/// Video objects are copied in pieces of this size.
const COPY_BYTES: u64 = 8 << 20;

/// Copies each video key's store objects to `videos/<key>/chunk-XXX/file-YYY.mp4` under `root`
/// (the file index is the object's place in the key's list), counting them as media files.
pub(super) async fn copy_videos(
    store: &Store,
    videos: &BTreeMap<String, Vec<String>>,
    root: &Path,
    report: &mut ExportReport,
) -> Result<()> {
    for (k, objs) in videos {
        for (i, obj) in objs.iter().enumerate() {
            let rel = fill(VIDEO_PATH, Some(&feature_key(k)), i / CHUNKS_SIZE, i % CHUNKS_SIZE);
            copy_object(store, obj, &root.join(rel)).await?;
            report.media_files += 1;
        }
    }
    Ok(())
}

/// Copies a store object to a local file in pieces (memory: one piece).
async fn copy_object(store: &Store, object: &str, dest: &Path) -> Result<u64> {
    use std::io::Write;
    let size = store.object_size(object).await?;
    std::fs::create_dir_all(dest.parent().expect("has a parent")).map_err(|e| ExportError::io(dest, e))?;
    let mut f = File::create(dest).map_err(|e| ExportError::io(dest, e))?;
    let mut at = 0;
    while at < size {
        let end = (at + COPY_BYTES).min(size);
        let bytes = store.get_object_range(object, at..end).await?;
        f.write_all(&bytes).map_err(|e| ExportError::io(dest, e))?;
        at = end;
    }
    f.sync_all().map_err(|e| ExportError::io(dest, e))?;
    Ok(size)
}
