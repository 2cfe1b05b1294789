//! Object storage through `object_store`: a local directory by default, S3-compatible storage
//! (`s3://bucket/prefix`, endpoint and keys from the usual `AWS_*` variables) when configured.
//! Every read request and every byte it returns is counted ([`FetchCounts`]), so benchmarks,
//! tests and `/metrics` can see what a read path really fetched.

use crate::{StoreConfig, StoreError};
use bytes::Bytes;
use futures::{StreamExt, TryStreamExt};
use object_store::multipart::{MultipartStore, PartId};
use object_store::path::Path as ObjPath;
use object_store::{GetOptions, GetRange, ObjectStore, PutMode, PutOptions, PutPayload, WriteMultipart};
use sha2::Digest;
use std::ops::Range;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use tokio::io::AsyncReadExt;

/// How long a writer's pending-object records protect its objects without being renewed: 60 s,
/// or `UFOPS_WRITER_LEASE_SECONDS` (tests shorten it to see a killed writer's leftovers collected).
pub(crate) fn writer_lease_ms() -> i64 {
    std::env::var("UFOPS_WRITER_LEASE_SECONDS")
        .ok()
        .and_then(|v| v.parse::<f64>().ok())
        .filter(|s| s.is_finite() && *s > 0.0 && *s <= 86_400.0)
        .map(|s| (s * 1000.0) as i64)
        .unwrap_or(60_000)
}

/// Local files up to this size are copied into the store with one put; larger ones (a LeRobot
/// mp4 may be 500 MB) stream as a multipart upload in parts of this size, so memory stays bounded
/// by a few parts whatever the file's size.
const FILE_PART_BYTES: usize = 8 << 20;
/// Parts being uploaded at once.
const FILE_PARTS_IN_FLIGHT: usize = 2;

pub(crate) struct Objects {
    store: Arc<dyn ObjectStore>,
    desc: String,
    /// For a local directory: its root (to find staging files a killed writer left).
    local_root: Option<std::path::PathBuf>,
    /// For S3: the bucket's multipart API, so each upload's id can be recorded and a killed
    /// writer's upload aborted by gc (S3 keeps, and bills, an incomplete upload's parts forever).
    multipart: Option<S3Multipart>,
    counters: Counters,
}

/// Multipart uploads in flight on S3 are recorded as one small JSON object each under this
/// prefix ([`UploadRecord`]): written when the upload starts, renewed while it runs, deleted
/// when it completes or aborts. gc aborts the uploads whose record lapsed (their writer died).
pub(crate) const UPLOADS_PREFIX: &str = "_uploads";

/// The record of one multipart upload in flight (S3).
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub(crate) struct UploadRecord {
    /// The object being uploaded (relative to the store's prefix).
    pub path: String,
    pub upload_id: String,
    pub created_ms: i64,
    /// The writer renews this while it uploads; past it, the writer is taken as dead.
    pub expires_ms: i64,
}

/// The bucket behind an S3 store, with the store's prefix (multipart calls take full paths).
struct S3Multipart {
    s3: object_store::aws::AmazonS3,
    prefix: String,
}

impl S3Multipart {
    fn full(&self, path: &str) -> ObjPath {
        if self.prefix.is_empty() {
            ObjPath::from(path)
        } else {
            ObjPath::from(format!("{}/{path}", self.prefix))
        }
    }
}

/// Ranges of one object closer than this are fetched in one request (the gap is fetched too).
/// `object_store`'s default is 1 MiB, which makes one episode's read fetch its neighbours' pages
/// of the small columns (measured: 315 KB instead of 4 KB for a 2.3 KB episode); 4 KiB merges
/// ranges split by a page header or a tiny page only. Whole-split reads ask for contiguous pages,
/// which merge whatever the gap.
pub(crate) const COALESCE_GAP: u64 = 4 << 10;

/// Read requests made to the object store and the bytes they returned, since the store was
/// opened. One `get_ranges` call counts once per request it turns into (ranges closer than
/// `COALESCE_GAP` are merged into one).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct FetchCounts {
    /// GET requests (whole objects and byte ranges).
    pub get_requests: u64,
    /// HEAD requests (existence and size checks).
    pub head_requests: u64,
    /// Bytes returned by GET requests.
    pub bytes_fetched: u64,
}

impl FetchCounts {
    /// What happened between two readings of the counters.
    pub fn since(self, earlier: FetchCounts) -> FetchCounts {
        FetchCounts {
            get_requests: self.get_requests.saturating_sub(earlier.get_requests),
            head_requests: self.head_requests.saturating_sub(earlier.head_requests),
            bytes_fetched: self.bytes_fetched.saturating_sub(earlier.bytes_fetched),
        }
    }
}

#[derive(Default)]
struct Counters {
    gets: AtomicU64,
    heads: AtomicU64,
    bytes: AtomicU64,
}

impl Counters {
    fn get(&self, bytes: u64) {
        self.gets.fetch_add(1, Ordering::Relaxed);
        self.bytes.fetch_add(bytes, Ordering::Relaxed);
    }
    fn head(&self) {
        self.heads.fetch_add(1, Ordering::Relaxed);
    }
}

/// An object as seen by a listing (for gc).
pub(crate) struct ObjectEntry {
    pub path: String,
    pub last_modified_ms: i64,
}

impl Objects {
    pub fn open(config: &StoreConfig) -> Result<Objects, StoreError> {
        let url = config.object_store_url.clone();
        match url.as_deref() {
            Some(u) if u.starts_with("s3://") => {
                let rest = &u["s3://".len()..];
                let (bucket, prefix) = match rest.split_once('/') {
                    Some((b, p)) => (b, p.trim_end_matches('/')),
                    None => (rest, ""),
                };
                if bucket.is_empty() {
                    return Err(StoreError::invalid(format!("object store URL {u:?} names no bucket")));
                }
                let mut builder = object_store::aws::AmazonS3Builder::from_env()
                    .with_bucket_name(bucket)
                    .with_allow_http(true);
                if let Ok(ep) = std::env::var("AWS_ENDPOINT_URL") {
                    builder = builder.with_endpoint(ep);
                }
                if std::env::var("AWS_REGION").is_err() && std::env::var("AWS_DEFAULT_REGION").is_err() {
                    builder = builder.with_region("us-east-1");
                }
                let s3 = builder
                    .build()
                    .map_err(|e| StoreError::invalid(format!("cannot configure S3 store {u:?}: {e}")))?;
                let store: Arc<dyn ObjectStore> = if prefix.is_empty() {
                    Arc::new(s3.clone())
                } else {
                    Arc::new(object_store::prefix::PrefixStore::new(s3.clone(), prefix))
                };
                Ok(Objects {
                    store,
                    desc: u.to_string(),
                    local_root: None,
                    multipart: Some(S3Multipart { s3, prefix: prefix.to_string() }),
                    counters: Counters::default(),
                })
            }
            Some(u) if u.contains("://") && !u.starts_with("file://") => Err(StoreError::invalid(format!(
                "unsupported object store URL {u:?}: use a local path, file:///PATH or s3://BUCKET/PREFIX"
            ))),
            other => {
                let dir = match other {
                    Some(u) => std::path::PathBuf::from(u.trim_start_matches("file://")),
                    None => config.data_dir.join("objects"),
                };
                std::fs::create_dir_all(&dir).map_err(|e| {
                    StoreError::invalid(format!("cannot create object directory {}: {e}", dir.display()))
                })?;
                let local = object_store::local::LocalFileSystem::new_with_prefix(&dir)
                    .map_err(|e| StoreError::invalid(format!("cannot open {}: {e}", dir.display())))?;
                Ok(Objects {
                    store: Arc::new(local),
                    desc: dir.display().to_string(),
                    local_root: Some(dir),
                    multipart: None,
                    counters: Counters::default(),
                })
            }
        }
    }

    pub fn describe(&self) -> String {
        self.desc.clone()
    }

    pub fn fetch_counts(&self) -> FetchCounts {
        FetchCounts {
            get_requests: self.counters.gets.load(Ordering::Relaxed),
            head_requests: self.counters.heads.load(Ordering::Relaxed),
            bytes_fetched: self.counters.bytes.load(Ordering::Relaxed),
        }
    }

    /// Writes a new object; fails with `AlreadyExists` rather than overwrite (put-if-absent).
    pub async fn put_new(&self, path: &str, data: Bytes) -> Result<(), object_store::Error> {
        let opts = PutOptions { mode: PutMode::Create, ..Default::default() };
        match self.store.put_opts(&ObjPath::from(path), PutPayload::from(data.clone()), opts).await {
            Ok(_) => Ok(()),
            // Some S3-compatible servers lack conditional puts; our names are unique anyway.
            Err(object_store::Error::NotImplemented) => {
                self.store.put(&ObjPath::from(path), PutPayload::from(data)).await.map(|_| ())
            }
            Err(e) => Err(e),
        }
    }

    /// Writes a content-addressed object: an existing object of that name already holds it.
    pub async fn put_content_addressed(&self, path: &str, data: Bytes) -> Result<(), StoreError> {
        if self.exists(path).await? {
            return Ok(());
        }
        match self.put_new(path, data).await {
            Ok(()) | Err(object_store::Error::AlreadyExists { .. }) => Ok(()),
            Err(e) => Err(e.into()),
        }
    }

    /// Copies the local (media) file `local` into the content-addressed object `path`, checking on the
    /// way that its content has the sha256 `sha256`: a file that changed since it was hashed is
    /// refused and nothing becomes visible (a multipart upload is completed only after the
    /// whole content matched, and aborted otherwise). Returns the number of bytes read.
    pub async fn put_file_content_addressed(
        &self,
        path: &str,
        local: &std::path::Path,
        sha256: &str,
    ) -> Result<u64, StoreError> {
        let io = |e: std::io::Error| StoreError::invalid(format!("cannot read {}: {e}", local.display()));
        let mut f = tokio::fs::File::open(local).await.map_err(io)?;
        let len = f.metadata().await.map_err(io)?.len();
        let changed = |actual: String| {
            StoreError::invalid(format!(
                "media file {} changed while ingesting: sha256 {actual}, expected {sha256}",
                local.display()
            ))
        };
        if len <= FILE_PART_BYTES as u64 {
            let mut data = Vec::with_capacity(len as usize);
            f.read_to_end(&mut data).await.map_err(io)?;
            let actual = crate::sha256_hex(&data);
            if actual != sha256 {
                return Err(changed(actual));
            }
            let n = data.len() as u64;
            self.put_content_addressed(path, Bytes::from(data)).await?;
            return Ok(n);
        }
        let mut hasher = sha2::Sha256::new();
        let mut total = 0u64;
        if self.exists(path).await? {
            // Stored already: only check that the file still is what the caller hashed.
            while let Some(part) = read_part(&mut f).await.map_err(io)? {
                hasher.update(&part);
                total += part.len() as u64;
            }
            let actual = hex::encode(hasher.finalize());
            return if actual == sha256 { Ok(total) } else { Err(changed(actual)) };
        }
        self.upload_parts(path, &mut f, io, |part| match part {
            Some(p) => {
                hasher.update(p);
                Ok(())
            }
            None => {
                let actual = hex::encode(hasher.finalize_reset());
                if actual == sha256 {
                    Ok(())
                } else {
                    Err(changed(actual))
                }
            }
        })
        .await
    }

    /// Writes a new object from an open local file (a steps file built in a temporary file) of
    /// `len` bytes, read from its current position: one put (if absent) when it is small,
    /// streamed in parts otherwise, so memory stays a few parts whatever its size.
    pub async fn put_new_file(&self, path: &str, file: std::fs::File, len: u64) -> Result<(), StoreError> {
        let io = |e: std::io::Error| {
            StoreError::invalid(format!("cannot read back a temporary file for {path}: {e}"))
        };
        let mut f = tokio::fs::File::from_std(file);
        if len <= FILE_PART_BYTES as u64 {
            let mut data = Vec::with_capacity(len as usize);
            f.read_to_end(&mut data).await.map_err(io)?;
            return Ok(self.put_new(path, Bytes::from(data)).await?);
        }
        let copied = self.upload_parts(path, &mut f, io, |_| Ok(())).await?;
        if copied != len {
            return Err(StoreError::invalid(format!("{path}: copied {copied} of {len} bytes")));
        }
        Ok(())
    }

    /// For a local store, an empty file to build the new object `path` in, and its guard. It
    /// lies in the object directory's root under a staging name (`<name>#<digits>`: listings
    /// hide it, and gc removes it once old if a crash left it; not under the object's own
    /// folder, so nothing shows there before the object is stored), and
    /// [`Self::put_new_staged`] links it into place instead of copying it. `None` for S3.
    pub(crate) fn local_staging_file(
        &self,
        path: &str,
    ) -> Result<Option<(std::fs::File, Staging)>, StoreError> {
        let Some(root) = &self.local_root else { return Ok(None) };
        let name = path.replace('/', "-");
        for n in 1..=1000 {
            let staged = root.join(format!("{name}#{n}"));
            match std::fs::OpenOptions::new().read(true).write(true).create_new(true).open(&staged) {
                Ok(f) => return Ok(Some((f, Staging { local: Some(staged) }))),
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
                Err(e) => {
                    return Err(StoreError::invalid(format!("cannot create {}: {e}", staged.display())))
                }
            }
        }
        Err(StoreError::invalid(format!("no free staging name for {path}")))
    }

    /// Stores the staging file `staged`, open as `file` (`len` bytes, positioned at its start),
    /// as the new object `path` (put-if-absent). A local staging file is hard-linked into place
    /// (no copy; a link across file systems falls back to one), anything else is uploaded.
    pub(crate) async fn put_new_staged(
        &self,
        path: &str,
        mut staged: Staging,
        mut file: std::fs::File,
        len: u64,
    ) -> Result<(), StoreError> {
        if let (Some(local), Some(root)) = (staged.local.take(), &self.local_root) {
            let dest = root.join(path);
            if let Some(dir) = dest.parent() {
                tokio::fs::create_dir_all(dir)
                    .await
                    .map_err(|e| StoreError::invalid(format!("cannot create {}: {e}", dir.display())))?;
            }
            // The version that references the object commits right after, durably (the catalog
            // syncs its log): its bytes must be on disk first, and so must its name.
            file = tokio::task::spawn_blocking(move || file.sync_data().map(|()| file))
                .await
                .map_err(|e| StoreError::invalid(format!("syncing {path}: {e}")))?
                .map_err(|e| StoreError::invalid(format!("cannot sync the staged file of {path}: {e}")))?;
            // the hard link fails when `dest` exists: put-if-absent, as `put_new`
            let linked = tokio::fs::hard_link(&local, &dest).await;
            let _ = tokio::fs::remove_file(&local).await;
            match linked {
                Ok(()) => {
                    if let Some(dir) = dest.parent().map(std::path::Path::to_path_buf) {
                        tokio::task::spawn_blocking(move || std::fs::File::open(&dir)?.sync_all())
                            .await
                            .map_err(|e| StoreError::invalid(format!("syncing {path}: {e}")))?
                            .map_err(|e| {
                                StoreError::invalid(format!("cannot sync the folder of {path}: {e}"))
                            })?;
                    }
                    return Ok(());
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                    return Err(object_store::Error::AlreadyExists {
                        path: path.to_string(),
                        source: Box::new(e),
                    }
                    .into())
                }
                Err(_) => {} // e.g. another file system mounted under the root: copy instead
            }
        }
        self.put_new_file(path, file, len).await
    }

    /// Copies a local file into the object `path` (replacing it), streamed in parts: memory is a
    /// few parts whatever the file's size. Returns the number of bytes copied.
    pub async fn put_file(&self, path: &str, local: &std::path::Path) -> Result<u64, StoreError> {
        let io = |e: std::io::Error| StoreError::invalid(format!("cannot read {}: {e}", local.display()));
        let mut f = tokio::fs::File::open(local).await.map_err(io)?;
        self.upload_parts(path, &mut f, io, |_| Ok(())).await
    }

    /// Streams the rest of `f` into the object `path` as a multipart upload (a few parts in
    /// memory at once). `check` sees each part (`Some`) and then the end (`None`); an error from
    /// it, or from reading, aborts the upload so nothing becomes visible. Returns the bytes copied.
    async fn upload_parts(
        &self,
        path: &str,
        f: &mut tokio::fs::File,
        io: impl Fn(std::io::Error) -> StoreError,
        mut check: impl FnMut(Option<&[u8]>) -> Result<(), StoreError>,
    ) -> Result<u64, StoreError> {
        if let Some(mp) = &self.multipart {
            return self.upload_parts_recorded(mp, path, f, io, check).await;
        }
        let upload = self.store.put_multipart(&ObjPath::from(path)).await?;
        let mut w = WriteMultipart::new_with_chunk_size(upload, FILE_PART_BYTES);
        let mut total = 0u64;
        let copied: Result<(), StoreError> = async {
            while let Some(part) = read_part(f).await.map_err(&io)? {
                check(Some(&part))?;
                total += part.len() as u64;
                w.wait_for_capacity(FILE_PARTS_IN_FLIGHT).await?;
                w.put(Bytes::from(part));
            }
            check(None)
        }
        .await;
        match copied {
            Ok(()) => {
                w.finish().await?;
                Ok(total)
            }
            Err(e) => {
                let _ = w.abort().await;
                Err(e)
            }
        }
    }

    /// [`Self::upload_parts`] on S3: the upload's id is recorded (an [`UploadRecord`]) before
    /// the first part and the record renewed every third of the writer lease, so that gc can
    /// abort the upload of a writer that died mid-way. The window between starting the upload
    /// and writing its record is not covered: the bucket's lifecycle rule is the second line of
    /// defence (ARCHITECTURE.md).
    async fn upload_parts_recorded(
        &self,
        mp: &S3Multipart,
        path: &str,
        f: &mut tokio::fs::File,
        io: impl Fn(std::io::Error) -> StoreError,
        mut check: impl FnMut(Option<&[u8]>) -> Result<(), StoreError>,
    ) -> Result<u64, StoreError> {
        let full = mp.full(path);
        let id = mp.s3.create_multipart(&full).await?;
        let lease = writer_lease_ms();
        let now = crate::now_ms();
        let mut record = UploadRecord {
            path: path.to_string(),
            upload_id: id.clone(),
            created_ms: now,
            expires_ms: now + lease,
        };
        let record_path = format!("{UPLOADS_PREFIX}/{}.json", uuid::Uuid::new_v4());
        if let Err(e) = self.put_record(&record_path, &record).await {
            let _ = mp.s3.abort_multipart(&full, &id).await;
            return Err(e);
        }
        let uploaded: Result<u64, StoreError> = async {
            let mut parts: Vec<Option<PartId>> = Vec::new();
            let mut in_flight = futures::stream::FuturesUnordered::new();
            let mut total = 0u64;
            let mut part = read_part(f).await.map_err(&io)?;
            // An empty file is one empty part (S3 completes no upload without parts).
            if part.is_none() {
                part = Some(Vec::new());
            }
            while let Some(bytes) = part {
                check(Some(&bytes))?;
                total += bytes.len() as u64;
                while in_flight.len() >= FILE_PARTS_IN_FLIGHT {
                    let (i, r): (usize, object_store::Result<PartId>) =
                        in_flight.next().await.expect("a part in flight");
                    parts[i] = Some(r?);
                }
                let idx = parts.len();
                parts.push(None);
                let (s3, full, id) = (&mp.s3, &full, &id);
                in_flight
                    .push(async move { (idx, s3.put_part(full, id, idx, PutPayload::from(bytes)).await) });
                if crate::now_ms() > record.expires_ms - lease * 2 / 3 {
                    record.expires_ms = crate::now_ms() + lease;
                    self.put_record(&record_path, &record).await?;
                }
                part = read_part(f).await.map_err(&io)?;
            }
            check(None)?;
            while let Some((i, r)) = in_flight.next().await {
                parts[i] = Some(r?);
            }
            let parts = parts.into_iter().map(|p| p.expect("every part was awaited")).collect();
            mp.s3.complete_multipart(&full, &id, parts).await?;
            Ok(total)
        }
        .await;
        if uploaded.is_err() {
            let _ = mp.s3.abort_multipart(&full, &id).await;
        }
        // A record left behind (this delete failed) names a finished upload: gc's abort of it
        // finds nothing to abort and removes the record.
        let _ = self.delete(&record_path).await;
        uploaded
    }

    async fn put_record(&self, record_path: &str, record: &UploadRecord) -> Result<(), StoreError> {
        let body = serde_json::to_vec(record).expect("a record serializes");
        self.store.put(&ObjPath::from(record_path), PutPayload::from(body)).await?;
        Ok(())
    }

    /// Aborts the multipart upload a lapsed [`UploadRecord`] names (nothing to abort is fine),
    /// then deletes the record.
    pub async fn abort_recorded_upload(
        &self,
        record_path: &str,
        record: &UploadRecord,
    ) -> Result<(), StoreError> {
        if let Some(mp) = &self.multipart {
            match mp.s3.abort_multipart(&mp.full(&record.path), &record.upload_id).await {
                Ok(()) | Err(object_store::Error::NotFound { .. }) => {}
                Err(e) => return Err(e.into()),
            }
        }
        self.delete(record_path).await
    }

    /// Objects under `prefix` (a folder: `a/b`), with their sizes.
    pub async fn list_prefix(&self, prefix: &str) -> Result<Vec<(String, u64)>, StoreError> {
        let p = ObjPath::from(prefix);
        let metas: Vec<_> = self.store.list(Some(&p)).try_collect().await?;
        Ok(metas.into_iter().map(|m| (m.location.to_string(), m.size)).collect())
    }

    pub async fn exists(&self, path: &str) -> Result<bool, StoreError> {
        self.counters.head();
        match self.store.head(&ObjPath::from(path)).await {
            Ok(_) => Ok(true),
            Err(object_store::Error::NotFound { .. }) => Ok(false),
            Err(e) => Err(e.into()),
        }
    }

    pub async fn get(&self, path: &str) -> Result<Bytes, StoreError> {
        match self.store.get(&ObjPath::from(path)).await {
            Ok(r) => {
                let b = r.bytes().await?;
                self.counters.get(b.len() as u64);
                Ok(b)
            }
            Err(object_store::Error::NotFound { .. }) => {
                self.counters.get(0);
                Err(StoreError::not_found("object", path))
            }
            Err(e) => {
                self.counters.get(0);
                Err(e.into())
            }
        }
    }

    pub async fn get_range(&self, path: &str, range: Range<u64>) -> Result<Bytes, StoreError> {
        let r = self.store.get_range(&ObjPath::from(path), range.clone()).await;
        self.counters.get(r.as_ref().map_or(0, |b| b.len() as u64));
        match r {
            // Callers slice what they asked for out of the answer: a short one is an error here.
            Ok(b) if b.len() as u64 != range.end.saturating_sub(range.start) => Err(StoreError::Corrupt(
                format!("object {path}: asked for bytes {range:?}, got {} bytes", b.len()),
            )),
            Ok(b) => Ok(b),
            Err(object_store::Error::NotFound { .. }) => Err(StoreError::not_found("object", path)),
            Err(e) => Err(e.into()),
        }
    }

    /// Several ranges of one object: ranges less than [`COALESCE_GAP`] apart are fetched as one
    /// request, up to 10 requests at once.
    pub async fn get_ranges(&self, path: &str, ranges: &[Range<u64>]) -> Result<Vec<Bytes>, StoreError> {
        object_store::coalesce_ranges(ranges, |r| self.get_range(path, r), COALESCE_GAP).await
    }

    /// The last `len` bytes of an object (all of it if smaller), their range and the object's
    /// size, in one request (a Parquet footer without knowing the file's size first).
    pub async fn get_suffix(&self, path: &str, len: u64) -> Result<(Range<u64>, Bytes, u64), StoreError> {
        let opts = GetOptions { range: Some(GetRange::Suffix(len)), ..Default::default() };
        let r = match self.store.get_opts(&ObjPath::from(path), opts).await {
            Ok(r) => r,
            Err(e) => {
                self.counters.get(0);
                return Err(match e {
                    object_store::Error::NotFound { .. } => StoreError::not_found("object", path),
                    e => e.into(),
                });
            }
        };
        let (range, size) = (r.range.clone(), r.meta.size);
        let b = r.bytes().await;
        self.counters.get(b.as_ref().map_or(0, |b| b.len() as u64));
        let b = b?;
        if b.len() as u64 != range.end - range.start || range.end != size {
            return Err(StoreError::Corrupt(format!(
                "object {path}: asked for its last {len} bytes, got {} bytes at {range:?} of {size}",
                b.len()
            )));
        }
        Ok((range, b, size))
    }

    pub async fn size(&self, path: &str) -> Result<u64, StoreError> {
        self.counters.head();
        match self.store.head(&ObjPath::from(path)).await {
            Ok(m) => Ok(m.size),
            Err(object_store::Error::NotFound { .. }) => Err(StoreError::not_found("object", path)),
            Err(e) => Err(e.into()),
        }
    }

    pub async fn list_all(&self) -> Result<Vec<ObjectEntry>, StoreError> {
        let metas: Vec<_> = self.store.list(None).try_collect().await?;
        Ok(metas
            .into_iter()
            .map(|m| ObjectEntry {
                path: m.location.to_string(),
                last_modified_ms: m.last_modified.timestamp_millis(),
            })
            .collect())
    }

    /// Half-written staging files (`name#<digits>`) of the local store, which listings hide.
    pub fn local_staging_files(&self) -> Vec<(std::path::PathBuf, i64)> {
        fn walk(dir: &std::path::Path, out: &mut Vec<(std::path::PathBuf, i64)>) {
            let Ok(rd) = std::fs::read_dir(dir) else { return };
            for e in rd.flatten() {
                let p = e.path();
                if p.is_dir() {
                    walk(&p, out);
                } else if let Some((_, suffix)) = e.file_name().to_string_lossy().split_once('#') {
                    if !suffix.is_empty() && suffix.bytes().all(|b| b.is_ascii_digit()) {
                        let ms = e
                            .metadata()
                            .and_then(|m| m.modified())
                            .ok()
                            .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
                            .map(|d| d.as_millis() as i64)
                            .unwrap_or(0);
                        out.push((p, ms));
                    }
                }
            }
        }
        let mut out = Vec::new();
        if let Some(root) = &self.local_root {
            walk(root, &mut out);
        }
        out
    }

    pub async fn delete(&self, path: &str) -> Result<(), StoreError> {
        match self.store.delete(&ObjPath::from(path)).await {
            Ok(()) | Err(object_store::Error::NotFound { .. }) => Ok(()),
            Err(e) => Err(e.into()),
        }
    }
}

/// Where a staging file ([`Objects::local_staging_file`]) lies, if anywhere; dropped before the
/// file was stored (an aborted ingest), it removes the file.
pub(crate) struct Staging {
    local: Option<std::path::PathBuf>,
}

impl Staging {
    /// A file outside the store (a temporary file): stored by copying it.
    pub(crate) fn temporary() -> Staging {
        Staging { local: None }
    }
}

impl Drop for Staging {
    fn drop(&mut self) {
        if let Some(p) = self.local.take() {
            let _ = std::fs::remove_file(p);
        }
    }
}

/// The next part (up to [`FILE_PART_BYTES`]) of a file, `None` at its end.
async fn read_part(f: &mut tokio::fs::File) -> std::io::Result<Option<Vec<u8>>> {
    let mut buf = vec![0u8; FILE_PART_BYTES];
    let mut n = 0;
    while n < buf.len() {
        match f.read(&mut buf[n..]).await? {
            0 => break,
            k => n += k,
        }
    }
    buf.truncate(n);
    Ok((n > 0).then_some(buf))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A file larger than a part streams as a multipart upload and the object holds exactly its
    /// bytes; a file whose content is not what the caller hashed is refused and leaves nothing,
    /// not even a staging file.
    #[tokio::test]
    async fn large_files_stream_in_parts_and_changed_ones_leave_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let objects = Objects::open(&StoreConfig::local(dir.path().join("store"))).unwrap();
        let data: Vec<u8> = (0..2 * FILE_PART_BYTES + 12_345).map(|i| (i * 31 % 251) as u8).collect();
        let local = dir.path().join("video.mp4");
        std::fs::write(&local, &data).unwrap();
        let sha = crate::sha256_hex(&data);
        let n = objects.put_file_content_addressed("media/a.mp4", &local, &sha).await.unwrap();
        assert_eq!(n, data.len() as u64);
        assert_eq!(objects.get("media/a.mp4").await.unwrap(), data);
        // Stored already: the file is only checked.
        assert_eq!(objects.put_file_content_addressed("media/a.mp4", &local, &sha).await.unwrap(), n);

        let wrong = "0".repeat(64);
        let err = objects.put_file_content_addressed("media/b.mp4", &local, &wrong).await.unwrap_err();
        assert!(err.to_string().contains("changed while ingesting"), "{err}");
        assert!(!objects.exists("media/b.mp4").await.unwrap());
        assert!(objects.local_staging_files().is_empty(), "{:?}", objects.local_staging_files());
        let err = objects.put_file_content_addressed("media/a.mp4", &local, &wrong).await.unwrap_err();
        assert!(err.to_string().contains("changed while ingesting"), "{err}");

        // A small file takes the single-put path, with the same check.
        std::fs::write(&local, b"small").unwrap();
        let err = objects.put_file_content_addressed("media/c.mp4", &local, &sha).await.unwrap_err();
        assert!(err.to_string().contains("changed while ingesting"), "{err}");
        let sha = crate::sha256_hex(b"small");
        assert_eq!(objects.put_file_content_addressed("media/c.mp4", &local, &sha).await.unwrap(), 5);
        assert_eq!(&objects.get("media/c.mp4").await.unwrap()[..], b"small");
    }
}
