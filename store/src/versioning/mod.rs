//! Versioning: what every write ends with. The version commit (`version.rs`: under the version
//! lock, the labels and counts that changed are frozen as spans, the version row is written and
//! the head moves), the episode counts per label state kept by every write (`counts.rs`) and a
//! version's labels as files with their checkpoints (`label_files.rs`). The writers (the ingest
//! writer, label writes, deletions, layers) hand their rows and count changes to this face.

pub(crate) mod counts;
mod label_files;
pub(crate) mod version;

pub use counts::{CountFilter, LabelCounts};
