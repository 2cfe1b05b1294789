//! `meta/stats.json`'s numbers: running min / max / mean / std per feature dimension, and the
//! column values they are gathered from.

use arrow::array::{Array, ArrayRef, AsArray};
use arrow::datatypes::{DataType, Float32Type, Float64Type};
use serde_json::{json, Value};

/// Running min / max / mean / std per dimension (meta/stats.json).
#[derive(Default)]
pub(super) struct Stats {
    min: Vec<f64>,
    max: Vec<f64>,
    sum: Vec<f64>,
    sumsq: Vec<f64>,
    count: u64,
}

impl Stats {
    pub(super) fn add(&mut self, dim: usize, values: impl Iterator<Item = f64>) {
        if self.min.is_empty() {
            self.min = vec![f64::INFINITY; dim];
            self.max = vec![f64::NEG_INFINITY; dim];
            self.sum = vec![0.0; dim];
            self.sumsq = vec![0.0; dim];
        }
        for (k, v) in values.into_iter().enumerate() {
            let d = k % dim;
            self.min[d] = self.min[d].min(v);
            self.max[d] = self.max[d].max(v);
            self.sum[d] += v;
            self.sumsq[d] += v * v;
            if d + 1 == dim {
                self.count += 1;
            }
        }
    }
    pub(super) fn json(&self) -> Value {
        let n = self.count.max(1) as f64;
        let mean: Vec<f64> = self.sum.iter().map(|s| s / n).collect();
        let std: Vec<f64> =
            self.sumsq.iter().zip(&mean).map(|(q, m)| (q / n - m * m).max(0.0).sqrt()).collect();
        json!({"min": self.min, "max": self.max, "mean": mean, "std": std, "count": [self.count]})
    }
}

pub(super) fn f32_values(col: &ArrayRef) -> Vec<f64> {
    match col.data_type() {
        DataType::FixedSizeList(_, _) => {
            let l = col.as_fixed_size_list();
            let d = l.value_length() as usize;
            let v = l.values().as_primitive::<Float32Type>();
            v.values()[l.offset() * d..(l.offset() + l.len()) * d].iter().map(|&x| x as f64).collect()
        }
        DataType::Float32 => col.as_primitive::<Float32Type>().values().iter().map(|&x| x as f64).collect(),
        DataType::Float64 => col.as_primitive::<Float64Type>().values().to_vec(),
        DataType::Int64 => {
            col.as_primitive::<arrow::datatypes::Int64Type>().values().iter().map(|&x| x as f64).collect()
        }
        DataType::Boolean => {
            col.as_boolean().iter().map(|b| if b == Some(true) { 1.0 } else { 0.0 }).collect()
        }
        _ => Vec::new(),
    }
}
