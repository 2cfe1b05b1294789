//! Episode records as one Arrow table: the one definition of the columns a client sees when it
//! lists episodes as a table (the Python package's `Store.episodes()` and
//! `Client.episodes_frame()` both build their DataFrame from [`episodes_batch`], so a field added
//! to [`EpisodeRecord`] reaches them without a hand-kept copy of the schema).

use std::sync::Arc;

use arrow::array::{ArrayRef, Int64Builder, ListBuilder, RecordBatch, StringBuilder};
use arrow::datatypes::{DataType, Field, Schema, SchemaRef};

use crate::{EpisodeRecord, StoreError};

/// The columns: every field of [`EpisodeRecord`], in its declaration order (its JSON's order);
/// `label` as its word, `metadata` as
/// its JSON text (a free-form object has no single Arrow type), `tags` as a list of strings.
pub fn episodes_schema() -> SchemaRef {
    use DataType::{Int64, Utf8};
    let text = |name: &str, nullable: bool| Field::new(name, Utf8, nullable);
    let int = |name: &str| Field::new(name, Int64, false);
    Arc::new(Schema::new(vec![
        text("id", false),
        text("policy", false),
        text("checkpoint", false),
        text("task", true),
        text("source_sha256", false),
        text("source_name", false),
        int("source_index"),
        int("length"),
        Field::new("tags", DataType::List(Arc::new(Field::new("item", Utf8, true))), false),
        text("metadata", false),
        text("data_file", false),
        int("row_group"),
        int("row_offset"),
        int("row_count"),
        int("version_added"),
        text("label", false),
        text("label_source", false),
        int("label_revision"),
        text("label_actor", false),
        text("label_updated_at", false),
        text("created_at", false),
        text("run_id", true),
        Field::new("first_intervention", Int64, true),
        Field::new("intervention_steps", Int64, true),
    ]))
}

/// `records` as one batch of [`episodes_schema`] (an empty batch for none).
pub fn episodes_batch(records: &[EpisodeRecord]) -> Result<RecordBatch, StoreError> {
    let n = records.len();
    let texts = |f: &dyn Fn(&EpisodeRecord) -> Option<&str>| -> ArrayRef {
        let mut b = StringBuilder::with_capacity(n, n * 16);
        records.iter().for_each(|r| b.append_option(f(r)));
        Arc::new(b.finish())
    };
    let ints = |f: &dyn Fn(&EpisodeRecord) -> i64| -> ArrayRef {
        let mut b = Int64Builder::with_capacity(n);
        records.iter().for_each(|r| b.append_value(f(r)));
        Arc::new(b.finish())
    };
    let opt_ints = |f: &dyn Fn(&EpisodeRecord) -> Option<i64>| -> ArrayRef {
        let mut b = Int64Builder::with_capacity(n);
        records.iter().for_each(|r| b.append_option(f(r)));
        Arc::new(b.finish())
    };
    let mut tags = ListBuilder::new(StringBuilder::new());
    for r in records {
        r.tags.iter().for_each(|t| tags.values().append_value(t));
        tags.append(true);
    }
    let metadata: Vec<String> = records.iter().map(|r| r.metadata.to_string()).collect();
    let columns: Vec<ArrayRef> = vec![
        texts(&|r| Some(&r.id)),
        texts(&|r| Some(&r.policy)),
        texts(&|r| Some(&r.checkpoint)),
        texts(&|r| r.task.as_deref()),
        texts(&|r| Some(&r.source_sha256)),
        texts(&|r| Some(&r.source_name)),
        ints(&|r| r.source_index),
        ints(&|r| r.length),
        Arc::new(tags.finish()),
        Arc::new(arrow::array::StringArray::from_iter_values(&metadata)),
        texts(&|r| Some(&r.data_file)),
        ints(&|r| r.row_group),
        ints(&|r| r.row_offset),
        ints(&|r| r.row_count),
        ints(&|r| r.version_added),
        texts(&|r| Some(r.label.as_str())),
        texts(&|r| Some(&r.label_source)),
        ints(&|r| r.label_revision),
        texts(&|r| Some(&r.label_actor)),
        texts(&|r| Some(&r.label_updated_at)),
        texts(&|r| Some(&r.created_at)),
        texts(&|r| r.run_id.as_deref()),
        opt_ints(&|r| r.first_intervention),
        opt_ints(&|r| r.intervention_steps),
    ];
    Ok(RecordBatch::try_new(episodes_schema(), columns)?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Label;

    fn record(id: &str, task: Option<&str>, tags: &[&str]) -> EpisodeRecord {
        EpisodeRecord {
            id: id.into(),
            policy: "p".into(),
            checkpoint: "c".into(),
            task: task.map(Into::into),
            source_sha256: "ab".into(),
            source_name: "demo_0".into(),
            source_index: 3,
            length: 40,
            tags: tags.iter().map(|t| t.to_string()).collect(),
            metadata: serde_json::json!({"k": [1, 2]}),
            data_file: "steps/x.parquet".into(),
            row_group: 0,
            row_offset: 7,
            row_count: 40,
            version_added: 2,
            label: Label::Failure,
            label_source: "human".into(),
            label_revision: 5,
            label_actor: "ann".into(),
            label_updated_at: "2026-01-01T00:00:00Z".into(),
            created_at: "2026-01-01T00:00:00Z".into(),
            run_id: None,
            first_intervention: Some(12),
            intervention_steps: Some(5),
        }
    }

    #[test]
    fn every_field_is_a_column_in_declaration_order() {
        let r = record("e1", None, &["a", "b"]);
        // serde writes a struct's fields in declaration order (a Value would sort them).
        let text = serde_json::to_string(&r).unwrap();
        let schema = episodes_schema();
        let at = |name: &str| text.find(&format!("\"{name}\":")).unwrap_or(usize::MAX);
        let columns: Vec<&str> = schema.fields().iter().map(|f| f.name().as_str()).collect();
        assert_eq!(columns.len(), serde_json::to_value(&r).unwrap().as_object().unwrap().len());
        assert!(
            columns.windows(2).all(|w| at(w[0]) < at(w[1])),
            "columns out of the record's order: {columns:?}"
        );
        assert!(columns.iter().all(|c| at(c) != usize::MAX));
    }

    #[test]
    fn values_and_nulls_survive() {
        let batch =
            episodes_batch(&[record("e1", None, &["a", "b"]), record("e2", Some("lift"), &[])]).unwrap();
        assert_eq!(batch.num_rows(), 2);
        let col = |name: &str| batch.column_by_name(name).unwrap().clone();
        let task = col("task");
        assert!(task.is_null(0) && !task.is_null(1));
        let label = col("label");
        let label = label.as_any().downcast_ref::<arrow::array::StringArray>().unwrap();
        assert_eq!(label.value(1), "failure");
        let tags = col("tags");
        let tags = tags.as_any().downcast_ref::<arrow::array::ListArray>().unwrap();
        assert_eq!(tags.value_length(0), 2);
        assert_eq!(tags.value_length(1), 0);
        let meta = col("metadata");
        let meta = meta.as_any().downcast_ref::<arrow::array::StringArray>().unwrap();
        assert_eq!(serde_json::from_str::<serde_json::Value>(meta.value(0)).unwrap()["k"][1], 2);
        assert!(episodes_batch(&[]).unwrap().num_rows() == 0);
    }
}
