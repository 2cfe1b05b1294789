//! The step table as columnar JSON: `{column name: [value per row]}`; vectors become arrays.
//! Binary columns (PNG frames) are omitted and named in `omitted` (use Arrow IPC for them).

use arrow::array::{Array, AsArray, RecordBatch};
use arrow::datatypes::{DataType, Float32Type, Float64Type, Int32Type, Int64Type};
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
        DataType::FixedSizeList(_, _) => {
            let l = a.as_fixed_size_list();
            (0..n)
                .map(|i| {
                    if l.is_null(i) {
                        Value::Null
                    } else {
                        values(l.value(i).as_ref()).map(Value::Array).unwrap_or(Value::Null)
                    }
                })
                .collect()
        }
        _ => return None,
    };
    Some(v)
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
