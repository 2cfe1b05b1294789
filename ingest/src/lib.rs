//! ufops ingest: turns a policy's evaluation rollouts (robomimic HDF5, ALOHA/ACT HDF5 episodes,
//! LeRobot v2.1/v3.0 datasets, `lerobot-eval` output folders, MCAP recordings) into one new store
//! version. See `README.md` in this crate.
//!
//! Layers:
//! * format readers ([`robomimic`], [`aloha`], [`lerobot`], [`lerobot_eval`], [`mcapfmt`]) are plain synchronous Rust that push
//!   a [`sink::SourceMeta`], media files and [`model::EpisodeInput`]s into an [`sink::EpisodeSink`];
//! * [`read_path`] picks the reader (format detection);
//! * the async glue ([`ingest`]) runs a reader on a blocking thread, hashes the source on another,
//!   and forwards everything to the store's `IngestWriter` through a bounded channel, committing
//!   once at the end (all or nothing);
//! * [`steering`] attaches a source's steering telemetry (a sidecar of best-of-N records) to its
//!   episodes.
//!
//! Sources are untrusted: [`confine`] keeps every path a source's metadata names inside it, and
//! the readers check every declared size against the file's size and a cap before allocating
//! (see the README, *Sources are untrusted*); the `hostile-corpus` crate (tests only) generates
//! the corpus of hostile sources the tests run.

pub mod aloha;
pub mod confine;
pub mod dvalue;
pub mod error;
/// Fuzz target bodies for `cargo fuzz` (ingest/fuzz) and the mutation tests (feature `testing`).
#[cfg(any(test, feature = "testing"))]
pub mod fuzzing;
mod h5rows;
mod h5src;
pub mod hashing;
pub mod lerobot;
pub mod lerobot_eval;
pub mod mapping;
pub mod mcapfmt;
/// The data types readers produce (the store's own model).
pub use store::model;
pub mod options;
pub mod pipeline;
pub mod png;
pub mod pqfooter;
pub mod robomimic;
pub mod ros2msg;
pub mod sink;
pub mod steering;
pub mod video;

use std::path::Path;

pub use error::IngestError;
pub use model::ImageStorage;
pub use options::{Format, IngestOptions, MemoryBudget, ReadOptions};
pub use pipeline::{ingest, IngestReport, LabelTally};

use error::Result;
use sink::EpisodeSink;

const MCAP_MAGIC: &[u8] = b"\x89MCAP0\r\n";
const HDF5_MAGIC: &[u8] = b"\x89HDF\r\n\x1a\n";

/// Decides the format of `path` (a LeRobot folder, a `lerobot-eval` output folder holding
/// `eval_info.json`, an ALOHA folder of `episode_<i>.hdf5`, an
/// HDF5 file — ALOHA when it has `/observations/qpos` and `/action` and no `/data`, else
/// robomimic — or an MCAP file).
pub fn detect(path: &Path) -> Result<Format> {
    let md = std::fs::metadata(path).map_err(|e| IngestError::io(path, e))?;
    if md.is_dir() {
        if path.join("meta/info.json").is_file() {
            return Ok(Format::Lerobot);
        }
        if lerobot_eval::looks_like_dir(path) {
            return Ok(Format::LerobotEval);
        }
        if aloha::looks_like_dir(path) {
            return Ok(Format::Aloha);
        }
        return Err(IngestError::invalid(
            path.join("meta/info.json"),
            "missing: a folder is ingested as a LeRobot dataset, which needs meta/info.json (or as a lerobot-eval output folder with eval_info.json, or an ALOHA folder of episode_<i>.hdf5 files)",
        ));
    }
    if path.file_name().is_some_and(|n| n == lerobot_eval::EVAL_INFO) {
        return Err(IngestError::invalid(
            path,
            "a lerobot-eval result: ingest the folder that holds it (its videos are read from there)",
        ));
    }
    let mut head = [0u8; 8];
    use std::io::Read;
    let mut f = std::fs::File::open(path).map_err(|e| IngestError::io(path, e))?;
    let n = f.read(&mut head).map_err(|e| IngestError::io(path, e))?;
    let head = &head[..n];
    if head.starts_with(MCAP_MAGIC) {
        return Ok(Format::Mcap);
    }
    if head.starts_with(HDF5_MAGIC) || hdf5_pure::is_hdf5(path).unwrap_or(false) {
        if aloha::looks_like_file(path) {
            return Ok(Format::Aloha);
        }
        return Ok(Format::Robomimic);
    }
    let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase();
    match ext.as_str() {
        "mcap" => Err(IngestError::invalid(path, "not an MCAP file (bad magic)")),
        "hdf5" | "h5" | "he5" => Err(IngestError::invalid(path, "not an HDF5 file (no HDF5 signature)")),
        _ => Err(IngestError::invalid(
            path,
            "unknown format: not an HDF5 file, not an MCAP file, not a LeRobot folder (use --format)",
        )),
    }
}

/// Runs the right reader over `path`, pushing everything into `sink`.
pub fn read_path(
    path: &Path,
    format: Format,
    opts: &ReadOptions,
    sink: &mut dyn EpisodeSink,
) -> Result<Format> {
    Ok(read_path_report(path, format, opts, sink)?.format)
}

/// What a reader run found besides the episodes.
#[derive(Debug, Clone)]
pub struct ReadOutcome {
    pub format: Format,
    pub notes: Vec<String>,
}

/// [`read_path`], also returning notes for the user (e.g. what `--recover` left out).
///
/// A panic inside a decoding library (none is known: fuzzing found and worked around the ones in
/// `mcap` and `parquet`) is turned into an error naming the file, as a last line of defence.
pub fn read_path_report(
    path: &Path,
    format: Format,
    opts: &ReadOptions,
    sink: &mut dyn EpisodeSink,
) -> Result<ReadOutcome> {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| read_path_inner(path, format, opts, sink)))
    {
        Ok(r) => r,
        Err(p) => Err(IngestError::invalid(
            path,
            format!("the file is corrupt: a decoder failed ({})", panic_message(p.as_ref())),
        )),
    }
}

/// The text of a caught panic's payload.
pub(crate) fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    payload
        .downcast_ref::<String>()
        .cloned()
        .or_else(|| payload.downcast_ref::<&str>().map(|s| s.to_string()))
        .unwrap_or_else(|| "unknown".into())
}

fn read_path_inner(
    path: &Path,
    format: Format,
    opts: &ReadOptions,
    sink: &mut dyn EpisodeSink,
) -> Result<ReadOutcome> {
    let format = match format {
        Format::Auto => detect(path)?,
        f => f,
    };
    let mut notes = Vec::new();
    if let (Some(s), false) = (opts.start_seed, format == Format::LerobotEval) {
        return Err(IngestError::Usage(format!(
            "--start-seed {s}: only lerobot-eval output needs it (its eval_info.json records no seeds); this is {format}"
        )));
    }
    match format {
        Format::Robomimic => notes.extend(robomimic::read_file_notes(path, opts, sink)?),
        Format::Aloha => notes.extend(aloha::read_path(path, opts, sink)?),
        Format::Lerobot => lerobot::read_dir(path, opts, sink)?,
        Format::LerobotEval => notes.extend(lerobot_eval::read_dir(path, opts, sink)?),
        Format::Mcap => {
            let r = mcapfmt::read_file(path, opts, sink)?;
            if let Some(t) = &r.summary.truncated {
                notes.push(t.clone());
            }
            if !r.incomplete.is_empty() {
                notes.push(format!("left out (incomplete): {}", r.incomplete.join(", ")));
            }
            if !r.skipped_empty.is_empty() {
                notes.push(format!(
                    "left out (no messages on the mapped topics): episodes {}",
                    r.skipped_empty.iter().map(|i| i.to_string()).collect::<Vec<_>>().join(", ")
                ));
            }
        }
        Format::Auto => unreachable!("resolved above"),
    }
    Ok(ReadOutcome { format, notes })
}
