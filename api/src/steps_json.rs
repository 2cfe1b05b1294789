//! The step table as columnar JSON: `{column name: [value per row]}`; vectors become arrays.
//! Binary columns (PNG frames) are omitted and named in `omitted` (use Arrow IPC for them).
//! The steering column becomes one object per best-of-N step (`artifact_id`, `chosen`,
//! `latency_us`, `scores`; null between them) without its candidate chunks, which only a replay
//! needs (they are in the Arrow IPC form).

use arrow::array::{Array, AsArray, RecordBatch};
use arrow::datatypes::{DataType, Float16Type, Float32Type, Float64Type, Int32Type, Int64Type, UInt32Type};
use serde_json::{Map, Value};

fn num(x: f64) -> Value {
    serde_json::Number::from_f64(x).map(Value::Number).unwrap_or(Value::Null)
}

fn values(a: &dyn Array) -> Option<Vec<Value>> {
    let n = a.len();
    let v: Vec<Value> = match a.data_type() {
        DataType::Utf8 => {
            let s = a.as_string::<i32>();
            (0..n).map(|i| if s.is_null(i) { Value::Null } else { Value::from(s.value(i)) }).collect()
        }
        DataType::Boolean => {
            let b = a.as_boolean();
            (0..n).map(|i| if b.is_null(i) { Value::Null } else { Value::from(b.value(i)) }).collect()
        }
        DataType::Int32 => {
            let x = a.as_primitive::<Int32Type>();
            (0..n).map(|i| if x.is_null(i) { Value::Null } else { Value::from(x.value(i)) }).collect()
        }
        DataType::Int64 => {
            let x = a.as_primitive::<Int64Type>();
            (0..n).map(|i| if x.is_null(i) { Value::Null } else { Value::from(x.value(i)) }).collect()
        }
        DataType::Float32 => {
            let x = a.as_primitive::<Float32Type>();
            (0..n).map(|i| if x.is_null(i) { Value::Null } else { num(x.value(i) as f64) }).collect()
        }
        DataType::Float64 => {
            let x = a.as_primitive::<Float64Type>();
            (0..n).map(|i| if x.is_null(i) { Value::Null } else { num(x.value(i)) }).collect()
        }
        DataType::UInt32 => {
            let x = a.as_primitive::<UInt32Type>();
            (0..n).map(|i| if x.is_null(i) { Value::Null } else { Value::from(x.value(i)) }).collect()
        }
        DataType::Float16 => {
            let x = a.as_primitive::<Float16Type>();
            (0..n).map(|i| if x.is_null(i) { Value::Null } else { num(x.value(i).to_f64()) }).collect()
        }
        DataType::List(_) => {
            let l = a.as_list::<i32>();
            (0..n).map(|i| row_array(l.is_null(i), || l.value(i))).collect()
        }
        DataType::Struct(fields) => {
            let st = a.as_struct();
            let mut children = Vec::new();
            for (f, c) in fields.iter().zip(st.columns()) {
                if f.name() == "candidates" {
                    continue;
                }
                children.push((f.name().clone(), values(c.as_ref())?));
            }
            (0..n)
                .map(|i| {
                    if st.is_null(i) {
                        return Value::Null;
                    }
                    Value::Object(children.iter().map(|(k, v)| (k.clone(), v[i].clone())).collect())
                })
                .collect()
        }
        DataType::FixedSizeList(_, _) => {
            let l = a.as_fixed_size_list();
            (0..n).map(|i| row_array(l.is_null(i), || l.value(i))).collect()
        }
        _ => return None,
    };
    Some(v)
}

/// One row of a list column as a JSON array (null for a null row or values JSON cannot hold).
fn row_array(null: bool, row: impl FnOnce() -> arrow::array::ArrayRef) -> Value {
    if null {
        return Value::Null;
    }
    values(row().as_ref()).map(Value::Array).unwrap_or(Value::Null)
}

/// `(columns, omitted column names)`
pub fn columns(batch: &RecordBatch) -> (Map<String, Value>, Vec<String>) {
    let mut out = Map::new();
    let mut omitted = Vec::new();
    for (f, c) in batch.schema().fields().iter().zip(batch.columns()) {
        match values(c.as_ref()) {
            Some(v) => {
                out.insert(f.name().clone(), Value::Array(v));
            }
            None => omitted.push(f.name().clone()),
        }
    }
    (out, omitted)
}
