//! `hostile-corpus`: the generator of ingest's hostile-input corpus, for tests only: sources whose own metadata tries to make
//! ingest read outside them, or whose declared sizes would drive memory (or describe frames that
//! are not there: ALOHA's `compress_len`). Every file is written by
//! code here into a folder the caller gives (a temp dir): nothing hand-edited is committed.
//! `tests/hostile_corpus.rs` runs `ufops ingest` on each one and checks that it is refused with
//! the expected message, a non-zero exit, bounded peak memory and the store unchanged.
//!
//! Files are made with the real writers (hdf5-pure, arrow/parquet) and then made hostile by a
//! program: an HDF5 dataspace patched to declare far more than was written (its object header
//! checksum recomputed), a Parquet page header and MCAP records built byte by byte from their
//! specifications.
//!
//! One file at 700 lines: the corpus is a catalogue of short cases, read in one place.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{Context, Result};
use arrow::array::{ArrayRef, FixedSizeListArray, Float32Array, Float64Array, Int64Array, RecordBatch};
use arrow::datatypes::{DataType, Field};
use h5stream::lookup3;
use serde_json::{json, Value};

/// What a hostile source attacks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Attack {
    /// Makes ingest read a file outside the source (templates, keys, symlinks).
    Path,
    /// Declares sizes that would drive memory (HDF5 shapes, MCAP chunks/messages, Parquet pages,
    /// metadata files, template widths).
    Size,
}

/// One hostile source.
#[derive(Debug, Clone)]
pub struct Case {
    pub name: &'static str,
    pub attack: Attack,
    /// The file or dataset folder to ingest.
    pub path: PathBuf,
    /// A piece of the error message ingest must give.
    pub expect: &'static str,
}

/// Writes every case under `dir` (one sub-folder per case) and lists them.
// Past 100 lines on purpose: the list of cases, one short block each, read as a catalogue.
#[allow(clippy::too_many_lines, reason = "the hostile corpus, one case after another")]
pub fn write_corpus(dir: &Path) -> Result<Vec<Case>> {
    let mut cases = Vec::new();
    let mut add = |name: &'static str,
                   attack: Attack,
                   expect: &'static str,
                   write: &dyn Fn(&Path) -> Result<PathBuf>|
     -> Result<()> {
        let d = dir.join(name);
        std::fs::create_dir_all(&d)?;
        let path = write(&d).with_context(|| format!("writing hostile case {name}"))?;
        cases.push(Case { name, attack, path, expect });
        Ok(())
    };

    // --- LeRobot: paths named by the dataset's metadata ----------------------------------------
    add("lerobot_data_path_parent", Attack::Path, "climbs out with `..`", &|d| {
        write_data(&d.join("outside/file-000.parquet"), 2, 5)?;
        lerobot(
            &d.join("ds"),
            &LeRobot {
                data_path: Some("../outside/file-{file_index:03d}.parquet".into()),
                ..Default::default()
            },
        )
    })?;
    add("lerobot_data_path_absolute", Attack::Path, "which is absolute", &|d| {
        let outside = d.join("outside/file-000.parquet");
        write_data(&outside, 2, 5)?;
        let tpl = d.join("outside/file-{file_index:03d}.parquet").to_string_lossy().into_owned();
        lerobot(&d.join("ds"), &LeRobot { data_path: Some(tpl), ..Default::default() })
    })?;
    // The attack of the issue: any readable file of the machine copied into the store as "video".
    add("lerobot_video_path_absolute", Attack::Path, "which is absolute", &|d| {
        std::fs::write(d.join("secret.txt"), b"a private key")?;
        let tpl = d.join("secret.txt").to_string_lossy().into_owned();
        lerobot(
            &d.join("ds"),
            &LeRobot { video: Some(VIDEO_KEY.into()), video_path: Some(tpl), ..Default::default() },
        )
    })?;
    add("lerobot_video_key_parent", Attack::Path, "climbs out with `..`", &|d| {
        // the default template `videos/{video_key}/chunk-000/file-000.mp4` with this key leaves the dataset
        std::fs::create_dir_all(d.join("outside/chunk-000"))?;
        std::fs::write(d.join("outside/chunk-000/file-000.mp4"), b"a private file")?;
        lerobot(&d.join("ds"), &LeRobot { video: Some("../../outside".into()), ..Default::default() })
    })?;
    add("lerobot_symlinked_data_file", Attack::Path, "outside the", &|d| {
        let outside = d.join("outside/file-000.parquet");
        write_data(&outside, 2, 5)?;
        let ds = lerobot(&d.join("ds"), &LeRobot::default())?;
        let inside = ds.join("data/chunk-000/file-000.parquet");
        std::fs::remove_file(&inside)?;
        std::os::unix::fs::symlink(&outside, &inside)?;
        Ok(ds)
    })?;
    add("lerobot_symlinked_video_file", Attack::Path, "outside the", &|d| {
        std::fs::write(d.join("secret.txt"), b"a private key")?;
        let ds = lerobot(&d.join("ds"), &LeRobot { video: Some(VIDEO_KEY.into()), ..Default::default() })?;
        let inside = ds.join(format!("videos/{VIDEO_KEY}/chunk-000/file-000.mp4"));
        std::fs::remove_file(&inside)?;
        std::os::unix::fs::symlink(d.join("secret.txt"), &inside)?;
        Ok(ds)
    })?;
    // --- lerobot-eval output: the video paths eval_info.json lists -------------------------------
    add("lerobot_eval_video_path_parent", Attack::Path, "climbs out with `..`", &|d| {
        std::fs::write(d.join("secret.mp4"), b"a private file")?;
        lerobot_eval(&d.join("eval"), "outputs/eval/x/videos/../../secret.mp4", None)
    })?;
    add("lerobot_eval_video_path_elsewhere", Attack::Path, "not inside a `videos/` folder", &|d| {
        std::fs::write(d.join("secret.txt"), b"a private key")?;
        lerobot_eval(&d.join("eval"), &d.join("secret.txt").to_string_lossy(), None)
    })?;
    add("lerobot_eval_symlinked_video", Attack::Path, "outside the", &|d| {
        std::fs::write(d.join("secret.txt"), b"a private key")?;
        let root = lerobot_eval(&d.join("eval"), LEROBOT_EVAL_VIDEO, None)?;
        std::os::unix::fs::symlink(d.join("secret.txt"), root.join("videos/pusht_0/eval_episode_0.mp4"))?;
        Ok(root)
    })?;

    // --- Declared sizes ----------------------------------------------------------------------
    add("lerobot_eval_huge_eval_info", Attack::Size, "metadata file of", &|d| {
        let root = lerobot_eval(&d.join("eval"), LEROBOT_EVAL_VIDEO, Some(&mp4_header(10, &[(1, 1)], 1)))?;
        let mut info = std::fs::read(root.join("eval_info.json"))?;
        info.resize(info.len() + (17 << 20), b' ');
        std::fs::write(root.join("eval_info.json"), info)?;
        Ok(root)
    })?;
    add("lerobot_eval_video_declares_frames", Attack::Size, "declares 4294967295 frames", &|d| {
        // 2^32 - 1 frames, each 1 tick long, in a 200-byte file (the times would take 32 GB)
        let mp4 = mp4_header(10, &[(u32::MAX, 1)], u32::MAX);
        lerobot_eval(&d.join("eval"), LEROBOT_EVAL_VIDEO, Some(&mp4))
    })?;
    add("lerobot_template_width", Attack::Size, "asks for a width of", &|d| {
        lerobot(
            &d.join("ds"),
            &LeRobot {
                data_path: Some("data/chunk-{chunk_index:0999999999d}/file-{file_index:03d}.parquet".into()),
                ..Default::default()
            },
        )
    })?;
    add("lerobot_huge_info_json", Attack::Size, "metadata file of", &|d| {
        let ds = lerobot(&d.join("ds"), &LeRobot::default())?;
        // a valid info.json followed by 17 MB of blanks (a JSON list of millions of names reads the same way)
        let mut info = std::fs::read(ds.join("meta/info.json"))?;
        info.resize(info.len() + (17 << 20), b' ');
        std::fs::write(ds.join("meta/info.json"), info)?;
        Ok(ds)
    })?;
    add("lerobot_snappy_page_bomb", Attack::Size, "uncompressed bytes from", &|d| {
        let ds = lerobot(&d.join("ds"), &LeRobot::default())?;
        // a data file whose one page says it inflates to 2 GB (snappy zero-fills that much)
        std::fs::write(ds.join("data/chunk-000/file-000.parquet"), parquet_page_bomb(i32::MAX))?;
        Ok(ds)
    })?;
    add("robomimic_unwritten_chunks", Attack::Size, "declares shape", &|d| {
        // 16 rows written, 2^24 rows declared: 1 GB of float64 from a ~10 kB file
        robomimic_declaring(&d.join("rollouts.hdf5"), 1 << 24)
    })?;
    add("robomimic_shape_overflow", Attack::Size, "overflows 64 bits", &|d| {
        robomimic_declaring(&d.join("rollouts.hdf5"), 1 << 62)
    })?;
    add("mcap_chunk_declares_huge", Attack::Size, "uncompressed bytes from", &|d| {
        let frame = zstd_rle_frame(1 << 20, 0);
        let p = d.join("rec.mcap");
        std::fs::write(&p, mcap_with_chunk(&frame, 1 << 40))?;
        Ok(p)
    })?;
    add("mcap_zstd_bomb", Attack::Size, "uncompressed bytes from", &|d| {
        // 600 MB of zeros in 18 kB of RLE blocks, padded (a skippable frame) to a 2,800:1 ratio
        let total = 600u64 << 20;
        let mut frame = skippable_frame(200 << 10);
        frame.extend(zstd_rle_frame(total, 0));
        let p = d.join("rec.mcap");
        std::fs::write(&p, mcap_with_chunk(&frame, total))?;
        Ok(p)
    })?;
    add("mcap_huge_json_event", Attack::Size, "decoded on a mapped topic", &|d| {
        // a 24 MB JSON list on the episode event topic (decoded: ~1 GB of values)
        let msg: Vec<u8> = std::iter::once(b'[')
            .chain(std::iter::repeat_n(*b"0,", 12 << 20).flatten())
            .chain(*b"0]")
            .collect();
        let recs = json_channel_and_message("/episode_event", &msg);
        let mut frame = skippable_frame(64 << 10);
        frame.extend(zstd::bulk::compress(&recs, 3)?);
        let p = d.join("rec.mcap");
        std::fs::write(&p, mcap_with_chunk(&frame, recs.len() as u64))?;
        Ok(p)
    })?;
    // --- ALOHA episodes whose compress_len / frame counts describe frames that are not there --
    add(
        "aloha_compress_len_past_padding",
        Attack::Size,
        "points past the 64-byte rows of /observations/images/cam_high",
        &|d| aloha_episode(&d.join("episode_0.hdf5"), AlohaFault::LengthPastRow),
    )?;
    add("aloha_compress_len_short", Attack::Size, "/compress_len declares 2 frames per camera", &|d| {
        aloha_episode(&d.join("episode_0.hdf5"), AlohaFault::FewerLengths)
    })?;
    add("aloha_images_fewer_rows", Attack::Size, "/observations/images/cam_high has 2 frames", &|d| {
        aloha_episode(&d.join("episode_0.hdf5"), AlohaFault::FewerFrames)
    })?;
    Ok(cases)
}

// --- lerobot-eval output ------------------------------------------------------------------------

/// The video path lerobot-eval lists for the first episode of PushT (relative to where it ran).
const LEROBOT_EVAL_VIDEO: &str = "outputs/eval/x/videos/pusht_0/eval_episode_0.mp4";

/// A lerobot-eval (0.4) output folder under `root`: one task `pusht_0`, one successful episode
/// whose video is listed as `listed`, and, when given, `video` written where lerobot-eval writes it.
fn lerobot_eval(root: &Path, listed: &str, video: Option<&[u8]>) -> Result<PathBuf> {
    let info = json!({
        "per_task": [{"task_group": "pusht", "task_id": 0, "metrics": {
            "sum_rewards": [1.0], "max_rewards": [1.0], "successes": [true], "video_paths": [listed]}}],
        "per_group": {"pusht": {"pc_success": 100.0, "n_episodes": 1, "video_paths": [listed]}},
        "overall": {"pc_success": 100.0, "n_episodes": 1, "video_paths": [listed]}
    });
    std::fs::create_dir_all(root.join("videos/pusht_0"))?;
    std::fs::write(root.join("eval_info.json"), serde_json::to_vec_pretty(&info)?)?;
    if let Some(v) = video {
        std::fs::write(root.join("videos/pusht_0/eval_episode_0.mp4"), v)?;
    }
    Ok(root.to_path_buf())
}

fn mp4_box(kind: &[u8; 4], payload: &[u8]) -> Vec<u8> {
    let mut v = ((payload.len() + 8) as u32).to_be_bytes().to_vec();
    v.extend_from_slice(kind);
    v.extend_from_slice(payload);
    v
}

/// An MP4 of headers only (`ftyp`, then `moov` with one H.264 video track): `count` samples
/// (`stsz`) timed by the `stts` entries `(samples, duration)` at `timescale` ticks a second.
pub fn mp4_header(timescale: u32, stts: &[(u32, u32)], count: u32) -> Vec<u8> {
    let mut mdhd = vec![0u8; 24];
    mdhd[12..16].copy_from_slice(&timescale.to_be_bytes());
    let mut stsd = vec![0, 0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 16];
    stsd.extend_from_slice(b"avc1");
    let mut t = vec![0u8; 4];
    t.extend_from_slice(&(stts.len() as u32).to_be_bytes());
    for (n, d) in stts {
        t.extend_from_slice(&n.to_be_bytes());
        t.extend_from_slice(&d.to_be_bytes());
    }
    let mut sz = vec![0u8; 4];
    sz.extend_from_slice(&100u32.to_be_bytes());
    sz.extend_from_slice(&count.to_be_bytes());
    let stbl = [mp4_box(b"stsd", &stsd), mp4_box(b"stts", &t), mp4_box(b"stsz", &sz)].concat();
    let minf = [mp4_box(b"vmhd", &[0; 12]), mp4_box(b"stbl", &stbl)].concat();
    let mdia = [mp4_box(b"mdhd", &mdhd), mp4_box(b"minf", &minf)].concat();
    let moov = mp4_box(b"moov", &mp4_box(b"trak", &mp4_box(b"mdia", &mdia)));
    [mp4_box(b"ftyp", b"isom\0\0\x02\0isomavc1"), moov].concat()
}

// --- ALOHA episodes ----------------------------------------------------------------------------

/// What is wrong with a generated ALOHA episode.
#[derive(Clone, Copy)]
enum AlohaFault {
    /// `compress_len[0, 2]` is larger than the camera's padded rows.
    LengthPastRow,
    /// `compress_len` has 2 columns for 4 steps.
    FewerLengths,
    /// A raw camera holds 2 frames for 4 steps.
    FewerFrames,
}

/// A 4-step ALOHA episode (`qpos`, `qvel`, `action`, one camera `cam_high`) with `fault`.
fn aloha_episode(path: &Path, fault: AlohaFault) -> Result<PathBuf> {
    use hdf5_pure::{AttrValue, FileBuilder};
    const T: u64 = 4;
    let mut b = FileBuilder::new();
    let vec: Vec<f32> = (0..T * 14).map(|k| k as f32 * 0.01).collect();
    let mut obs = b.create_group("observations");
    obs.create_dataset("qpos").with_f32_data(&vec).with_shape(&[T, 14]);
    obs.create_dataset("qvel").with_f32_data(&vec).with_shape(&[T, 14]);
    let mut images = obs.create_group("images");
    match fault {
        AlohaFault::FewerFrames => {
            images.create_dataset("cam_high").with_u8_data(&[7u8; 2 * 8 * 8 * 3]).with_shape(&[2, 8, 8, 3]);
        }
        AlohaFault::LengthPastRow | AlohaFault::FewerLengths => {
            // rows of 64 bytes: a tiny "JPEG" (SOI ... EOI) then zeros
            let mut rows = vec![0u8; (T * 64) as usize];
            for r in rows.chunks_mut(64) {
                r[..4].copy_from_slice(&[0xFF, 0xD8, 0xFF, 0xD9]);
            }
            images.create_dataset("cam_high").with_u8_data(&rows).with_shape(&[T, 64]);
            let lens: Vec<f32> = match fault {
                AlohaFault::LengthPastRow => vec![4.0, 4.0, 5000.0, 4.0],
                _ => vec![4.0, 4.0],
            };
            let n = lens.len() as u64;
            b.create_dataset("compress_len").with_f32_data(&lens).with_shape(&[1, n]);
            b.set_attr("compress", AttrValue::I8(1));
        }
    }
    obs.add_group(images.finish());
    b.add_group(obs.finish());
    b.create_dataset("action").with_f32_data(&vec).with_shape(&[T, 14]);
    b.set_attr("sim", AttrValue::I8(0));
    b.write(path)?;
    Ok(path.to_path_buf())
}

// --- LeRobot v3.0 datasets ---------------------------------------------------------------------

const VIDEO_KEY: &str = "observation.images.front";

/// A small LeRobot v3.0 dataset (2 episodes of 5 frames), optionally with one video feature.
#[derive(Default)]
struct LeRobot {
    data_path: Option<String>,
    video_path: Option<String>,
    /// The key of a `video` feature (its mp4 is written at the default template's place).
    video: Option<String>,
}

fn parquet_file(path: &Path, cols: Vec<(&str, ArrayRef)>) -> Result<()> {
    std::fs::create_dir_all(path.parent().context("no parent")?)?;
    let batch = RecordBatch::try_from_iter(cols)?;
    let f = std::fs::File::create(path)?;
    let mut w = parquet::arrow::ArrowWriter::try_new(f, batch.schema(), None)?;
    w.write(&batch)?;
    w.close()?;
    Ok(())
}

fn f32_list(values: Vec<f32>, dim: i32) -> Result<ArrayRef> {
    let item = Arc::new(Field::new("item", DataType::Float32, true));
    Ok(Arc::new(FixedSizeListArray::try_new(item, dim, Arc::new(Float32Array::from(values)), None)?))
}

/// The data file of `episodes` episodes of `steps` frames.
fn write_data(path: &Path, episodes: usize, steps: usize) -> Result<()> {
    let n = episodes * steps;
    parquet_file(
        path,
        vec![
            ("observation.state", f32_list((0..n * 2).map(|k| k as f32).collect(), 2)?),
            ("action", f32_list((0..n * 2).map(|k| (k % 7) as f32).collect(), 2)?),
            (
                "timestamp",
                Arc::new(Float32Array::from_iter_values((0..n).map(|r| (r % steps) as f32 / 10.0))),
            ),
            ("frame_index", Arc::new(Int64Array::from_iter_values((0..n).map(|r| (r % steps) as i64)))),
            ("episode_index", Arc::new(Int64Array::from_iter_values((0..n).map(|r| (r / steps) as i64)))),
            ("index", Arc::new(Int64Array::from_iter_values(0..n as i64))),
            ("task_index", Arc::new(Int64Array::from(vec![0i64; n]))),
        ],
    )
}

/// Writes the dataset under `root` and returns `root`.
fn lerobot(root: &Path, o: &LeRobot) -> Result<PathBuf> {
    let (episodes, steps) = (2usize, 5usize);
    let mut features = json!({
        "observation.state": {"dtype": "float32", "shape": [2]},
        "action": {"dtype": "float32", "shape": [2]},
        "timestamp": {"dtype": "float32", "shape": [1]},
        "frame_index": {"dtype": "int64", "shape": [1]},
        "episode_index": {"dtype": "int64", "shape": [1]},
        "index": {"dtype": "int64", "shape": [1]},
        "task_index": {"dtype": "int64", "shape": [1]}
    });
    if let Some(k) = &o.video {
        features[k.as_str()] = json!({"dtype": "video", "shape": [8, 8, 3]});
    }
    let mut info = json!({"codebase_version": "v3.0", "fps": 10, "robot_type": "toy", "total_episodes": episodes, "features": features});
    if let Some(t) = &o.data_path {
        info["data_path"] = Value::String(t.clone());
    }
    if let Some(t) = &o.video_path {
        info["video_path"] = Value::String(t.clone());
    }
    std::fs::create_dir_all(root.join("meta"))?;
    std::fs::write(root.join("meta/info.json"), serde_json::to_vec_pretty(&info)?)?;
    let ep: Vec<i64> = (0..episodes as i64).collect();
    let mut cols: Vec<(String, ArrayRef)> = vec![
        ("episode_index".into(), Arc::new(Int64Array::from(ep.clone()))),
        ("length".into(), Arc::new(Int64Array::from(vec![steps as i64; episodes]))),
        (
            "dataset_from_index".into(),
            Arc::new(Int64Array::from_iter_values(ep.iter().map(|e| e * steps as i64))),
        ),
        (
            "dataset_to_index".into(),
            Arc::new(Int64Array::from_iter_values(ep.iter().map(|e| (e + 1) * steps as i64))),
        ),
        ("data/chunk_index".into(), Arc::new(Int64Array::from(vec![0i64; episodes]))),
        ("data/file_index".into(), Arc::new(Int64Array::from(vec![0i64; episodes]))),
    ];
    if let Some(k) = &o.video {
        cols.push((format!("videos/{k}/chunk_index"), Arc::new(Int64Array::from(vec![0i64; episodes]))));
        cols.push((format!("videos/{k}/file_index"), Arc::new(Int64Array::from(vec![0i64; episodes]))));
        cols.push((
            format!("videos/{k}/from_timestamp"),
            Arc::new(Float64Array::from_iter_values(ep.iter().map(|e| *e as f64 * steps as f64 / 10.0))),
        ));
        let mp4 = root.join(format!("videos/{k}/chunk-000/file-000.mp4"));
        if let Some(parent) = mp4.parent() {
            std::fs::create_dir_all(parent)?;
        }
        std::fs::write(&mp4, b"\0\0\0\x18ftypisom not a real video")?;
    }
    parquet_file(
        &root.join("meta/episodes/chunk-000/file-000.parquet"),
        cols.iter().map(|(n, a)| (n.as_str(), a.clone())).collect(),
    )?;
    write_data(&root.join("data/chunk-000/file-000.parquet"), episodes, steps)?;
    Ok(root.to_path_buf())
}

// --- Parquet built from the Thrift compact protocol ----------------------------------------------

/// Thrift compact-protocol writer (just what a Parquet footer and page header need).
#[derive(Default)]
struct Thrift {
    out: Vec<u8>,
    last: Vec<i16>,
}

impl Thrift {
    fn varint(&mut self, mut v: u64) {
        while v >= 0x80 {
            self.out.push((v as u8) | 0x80);
            v >>= 7;
        }
        self.out.push(v as u8);
    }
    fn zigzag(&mut self, v: i64) {
        self.varint(((v << 1) ^ (v >> 63)) as u64);
    }
    fn field(&mut self, id: i16, t: u8) {
        let last = self.last.last_mut().expect("inside a struct");
        let delta = id - *last;
        *last = id;
        if (1..=15).contains(&delta) {
            self.out.push(((delta as u8) << 4) | t);
        } else {
            self.out.push(t);
            self.zigzag(id as i64);
        }
    }
    fn begin(&mut self) {
        self.last.push(0);
    }
    fn end(&mut self) {
        self.out.push(0);
        self.last.pop();
    }
    fn i32(&mut self, id: i16, v: i32) {
        self.field(id, 5);
        self.zigzag(v as i64);
    }
    fn i64(&mut self, id: i16, v: i64) {
        self.field(id, 6);
        self.zigzag(v);
    }
    fn binary(&mut self, id: i16, v: &[u8]) {
        self.field(id, 8);
        self.varint(v.len() as u64);
        self.out.extend_from_slice(v);
    }
    fn list_header(&mut self, id: i16, elem: u8, n: usize) {
        self.field(id, 9);
        if n < 15 {
            self.out.push(((n as u8) << 4) | elem);
        } else {
            self.out.push(0xf0 | elem);
            self.varint(n as u64);
        }
    }
    fn struct_field(&mut self, id: i16) {
        self.field(id, 12);
        self.begin();
    }
}

/// A Parquet file with one required INT64 column `episode_index`, one snappy data page whose
/// header declares `uncompressed` bytes for its 64 stored bytes.
pub fn parquet_page_bomb(uncompressed: i32) -> Vec<u8> {
    let payload = vec![0x55u8; 64];
    let mut page = Thrift::default();
    page.begin();
    page.i32(1, 0); // DATA_PAGE
    page.i32(2, uncompressed);
    page.i32(3, payload.len() as i32);
    page.struct_field(5); // DataPageHeader
    page.i32(1, 8); // num_values
    page.i32(2, 0); // PLAIN
    page.i32(3, 3); // RLE
    page.i32(4, 3);
    page.end();
    page.end();
    let mut file = b"PAR1".to_vec();
    let page_offset = file.len() as i64;
    file.extend_from_slice(&page.out);
    file.extend_from_slice(&payload);
    let chunk_len = file.len() as i64 - page_offset;

    let mut m = Thrift::default();
    m.begin();
    m.i32(1, 1); // version
    m.list_header(2, 12, 2); // schema
    m.begin();
    m.binary(4, b"schema");
    m.i32(5, 1); // num_children
    m.end();
    m.begin();
    m.i32(1, 2); // INT64
    m.i32(3, 0); // REQUIRED
    m.binary(4, b"episode_index");
    m.end();
    m.i64(3, 8); // num_rows
    m.list_header(4, 12, 1); // row_groups
    m.begin();
    m.list_header(1, 12, 1); // columns
    m.begin();
    m.i64(2, page_offset); // file_offset
    m.struct_field(3); // ColumnMetaData
    m.i32(1, 2); // INT64
    m.list_header(2, 5, 1);
    m.zigzag(0); // PLAIN
    m.list_header(3, 8, 1);
    m.varint(13);
    m.out.extend_from_slice(b"episode_index");
    m.i32(4, 1); // SNAPPY
    m.i64(5, 8); // num_values
    m.i64(6, uncompressed as i64);
    m.i64(7, chunk_len);
    m.i64(9, page_offset); // data_page_offset
    m.end();
    m.end();
    m.i64(2, chunk_len); // total_byte_size
    m.i64(3, 8); // num_rows
    m.end();
    m.end();
    file.extend_from_slice(&m.out);
    file.extend_from_slice(&(m.out.len() as u32).to_le_bytes());
    file.extend_from_slice(b"PAR1");
    file
}

// --- HDF5 declaring more than it holds ---------------------------------------------------------

/// A robomimic file whose `data/demo_0/actions` (16 x 7 float64 written, chunked, resizable)
/// is patched to declare `rows` rows: its chunks past the first were never written.
fn robomimic_declaring(path: &Path, rows: u64) -> Result<PathBuf> {
    use hdf5_pure::{AttrValue, FileBuilder, MaxExtent};
    const T: u64 = 16;
    let mut b = FileBuilder::new();
    let mut data = b.create_group("data");
    let mut g = data.create_group("demo_0");
    let act: Vec<f64> = (0..T * 7).map(|k| k as f64 * 0.5).collect();
    g.create_dataset("actions")
        .with_f64_data(&act)
        .with_shape(&[T, 7])
        .with_maxshape(&[MaxExtent::Unlimited, MaxExtent::Fixed(7)])
        .with_chunks(&[T, 7]);
    data.add_group(g.finish());
    data.set_attr("env_args", AttrValue::String(r#"{"env_name": "Lift"}"#.into()));
    b.add_group(data.finish());
    b.write(path)?;
    let mut bytes = std::fs::read(path)?;
    // Dataspace message body (version 2): version, rank, flags (1 = max dims present), type,
    // then the dims and the max dims as u64.
    let mut pat = vec![2u8, 2, 1, 1];
    for v in [T, 7, u64::MAX, 7] {
        pat.extend_from_slice(&v.to_le_bytes());
    }
    let at = find(&bytes, &pat).context("the dataspace of data/demo_0/actions was not found")?;
    bytes[at + 4..at + 12].copy_from_slice(&rows.to_le_bytes());
    fix_object_header_checksum(&mut bytes, at)?;
    std::fs::write(path, bytes)?;
    Ok(path.to_path_buf())
}

fn find(hay: &[u8], needle: &[u8]) -> Option<usize> {
    hay.windows(needle.len()).position(|w| w == needle)
}

/// Recomputes the checksum of the version-2 object header (`OHDR`) holding byte `at`.
fn fix_object_header_checksum(bytes: &mut [u8], at: usize) -> Result<()> {
    let start =
        bytes[..at].windows(4).rposition(|w| w == b"OHDR").context("no OHDR before the patched bytes")?;
    let flags = bytes[start + 5];
    let mut p = start + 6;
    if flags & 0x20 != 0 {
        p += 16; // times
    }
    if flags & 0x10 != 0 {
        p += 4; // attribute phase change
    }
    let width = 1usize << (flags & 3);
    let mut size = 0u64;
    for (i, b) in bytes[p..p + width].iter().enumerate() {
        size |= (*b as u64) << (8 * i);
    }
    let end = p + width + size as usize;
    anyhow::ensure!(end > at && end + 4 <= bytes.len(), "the object header does not hold the patched bytes");
    let sum = lookup3(&bytes[start..end]);
    bytes[end..end + 4].copy_from_slice(&sum.to_le_bytes());
    Ok(())
}

// --- MCAP built from its record layout ---------------------------------------------------------

fn record(op: u8, body: &[u8]) -> Vec<u8> {
    let mut r = vec![op];
    r.extend_from_slice(&(body.len() as u64).to_le_bytes());
    r.extend_from_slice(body);
    r
}

fn mcap_str(out: &mut Vec<u8>, s: &str) {
    out.extend_from_slice(&(s.len() as u32).to_le_bytes());
    out.extend_from_slice(s.as_bytes());
}

/// An MCAP file holding one chunk: `compressed` (a zstd stream) declared to inflate to
/// `uncompressed` bytes.
pub fn mcap_with_chunk(compressed: &[u8], uncompressed: u64) -> Vec<u8> {
    let mut f = b"\x89MCAP0\r\n".to_vec();
    let mut h = Vec::new();
    mcap_str(&mut h, "");
    mcap_str(&mut h, "ufops hostile corpus");
    f.extend(record(0x01, &h));
    let mut c = Vec::new();
    c.extend_from_slice(&0u64.to_le_bytes()); // message start time
    c.extend_from_slice(&0u64.to_le_bytes()); // message end time
    c.extend_from_slice(&uncompressed.to_le_bytes());
    c.extend_from_slice(&0u32.to_le_bytes()); // no CRC
    mcap_str(&mut c, "zstd");
    c.extend_from_slice(&(compressed.len() as u64).to_le_bytes());
    c.extend_from_slice(compressed);
    f.extend(record(0x06, &c));
    f.extend(record(0x0f, &0u32.to_le_bytes())); // data end
    let mut footer = Vec::new();
    footer.extend_from_slice(&0u64.to_le_bytes());
    footer.extend_from_slice(&0u64.to_le_bytes());
    footer.extend_from_slice(&0u32.to_le_bytes());
    f.extend(record(0x02, &footer));
    f.extend_from_slice(b"\x89MCAP0\r\n");
    f
}

/// A Channel record (JSON messages, no schema) and one Message record on it.
fn json_channel_and_message(topic: &str, msg: &[u8]) -> Vec<u8> {
    let mut ch = Vec::new();
    ch.extend_from_slice(&1u16.to_le_bytes()); // id
    ch.extend_from_slice(&0u16.to_le_bytes()); // no schema
    mcap_str(&mut ch, topic);
    mcap_str(&mut ch, "json");
    ch.extend_from_slice(&0u32.to_le_bytes()); // empty metadata map
    let mut m = Vec::new();
    m.extend_from_slice(&1u16.to_le_bytes());
    m.extend_from_slice(&0u32.to_le_bytes()); // sequence
    m.extend_from_slice(&1u64.to_le_bytes()); // log time
    m.extend_from_slice(&1u64.to_le_bytes()); // publish time
    m.extend_from_slice(msg);
    let mut out = record(0x04, &ch);
    out.extend(record(0x05, &m));
    out
}

/// A zstd frame of `total` copies of `byte` as RLE blocks (4 bytes per 128 KiB).
pub fn zstd_rle_frame(total: u64, byte: u8) -> Vec<u8> {
    let mut f = 0xFD2F_B528u32.to_le_bytes().to_vec();
    f.push(0xE0); // 8-byte content size, single segment
    f.extend_from_slice(&total.to_le_bytes());
    let block = 128u64 << 10;
    let mut left = total;
    loop {
        let n = left.min(block);
        left -= n;
        let last = (left == 0) as u32;
        let header = last | (1 << 1) | ((n as u32) << 3);
        f.extend_from_slice(&header.to_le_bytes()[..3]);
        f.push(byte);
        if left == 0 {
            break;
        }
    }
    f
}

/// A zstd skippable frame of `n` bytes of content (decoders skip it).
pub fn skippable_frame(n: usize) -> Vec<u8> {
    let mut f = 0x184D_2A50u32.to_le_bytes().to_vec();
    f.extend_from_slice(&(n as u32).to_le_bytes());
    f.resize(8 + n, 0);
    f
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lookup3_reproduces_the_checksums_hdf5_pure_writes() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.h5");
        let mut b = hdf5_pure::FileBuilder::new();
        b.create_dataset("x").with_f64_data(&[1.0, 2.0, 3.0]);
        b.write(&p).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        let start = find(&bytes, b"OHDR").unwrap();
        let mut copy = bytes.clone();
        fix_object_header_checksum(&mut copy, start + 8).unwrap();
        assert_eq!(copy, bytes, "recomputing an untouched header's checksum changes nothing");
    }

    #[test]
    fn zstd_frames_decode() {
        let mut f = skippable_frame(100);
        f.extend(zstd_rle_frame(300 << 10, 7));
        let out = zstd::bulk::decompress(&f, 1 << 20).unwrap();
        assert_eq!(out.len(), 300 << 10);
        assert!(out.iter().all(|&b| b == 7));
    }
}
