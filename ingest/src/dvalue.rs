//! A decoded message, independent of its wire encoding (CDR, protobuf, JSON), and field-path
//! extraction of numbers from it.

#[derive(Debug, Clone, PartialEq)]
pub enum DValue {
    Null,
    Bool(bool),
    Int(i64),
    UInt(u64),
    Float(f64),
    Str(String),
    Bytes(Vec<u8>),
    List(Vec<DValue>),
    /// Fields in declaration order.
    Msg(Vec<(String, DValue)>),
}

impl DValue {
    pub fn field(&self, name: &str) -> Option<&DValue> {
        match self {
            DValue::Msg(fields) => fields.iter().find(|(n, _)| n == name).map(|(_, v)| v),
            _ => None,
        }
    }

    pub fn as_f64(&self) -> Option<f64> {
        match self {
            DValue::Bool(b) => Some(*b as u8 as f64),
            DValue::Int(i) => Some(*i as f64),
            DValue::UInt(u) => Some(*u as f64),
            DValue::Float(f) => Some(*f),
            _ => None,
        }
    }

    pub fn as_str(&self) -> Option<&str> {
        match self {
            DValue::Str(s) => Some(s),
            _ => None,
        }
    }

    pub fn as_bool(&self) -> Option<bool> {
        match self {
            DValue::Bool(b) => Some(*b),
            DValue::Int(i) => Some(*i != 0),
            DValue::UInt(u) => Some(*u != 0),
            DValue::Str(s) => match s.to_ascii_lowercase().as_str() {
                "true" | "1" | "yes" | "success" => Some(true),
                "false" | "0" | "no" | "failure" => Some(false),
                _ => None,
            },
            _ => None,
        }
    }

    /// Resolves a dotted path (`position`, `joints.position`, `data`, `pose.position.x`).
    /// A list met on the way maps the rest of the path over its elements. Returns all numbers
    /// found, flattened, or `None` when the path does not exist.
    pub fn numbers(&self, path: &str) -> Option<Vec<f64>> {
        let parts: Vec<&str> = if path.is_empty() { vec![] } else { path.split('.').collect() };
        let mut out = Vec::new();
        if collect(self, &parts, &mut out) {
            Some(out)
        } else {
            None
        }
    }

    /// Like [`numbers`](Self::numbers) but tries `|`-separated alternatives in order.
    pub fn numbers_any(&self, paths: &str) -> Option<Vec<f64>> {
        paths.split('|').find_map(|p| self.numbers(p.trim()))
    }

    pub fn get_path(&self, path: &str) -> Option<&DValue> {
        let mut cur = self;
        for p in path.split('.') {
            if p.is_empty() {
                continue;
            }
            cur = match cur {
                DValue::Msg(_) => cur.field(p)?,
                DValue::List(items) => items.get(p.parse::<usize>().ok()?)?,
                _ => return None,
            };
        }
        Some(cur)
    }

    pub fn to_json(&self) -> serde_json::Value {
        use serde_json::Value as J;
        match self {
            DValue::Null => J::Null,
            DValue::Bool(b) => J::Bool(*b),
            DValue::Int(i) => J::from(*i),
            DValue::UInt(u) => J::from(*u),
            DValue::Float(f) => serde_json::Number::from_f64(*f).map(J::Number).unwrap_or(J::Null),
            DValue::Str(s) => J::String(s.clone()),
            DValue::Bytes(b) => J::String(format!("<{} bytes>", b.len())),
            DValue::List(l) => J::Array(l.iter().map(|v| v.to_json()).collect()),
            DValue::Msg(f) => J::Object(f.iter().map(|(k, v)| (k.clone(), v.to_json())).collect()),
        }
    }

    pub fn from_json(v: &serde_json::Value) -> DValue {
        use serde_json::Value as J;
        match v {
            J::Null => DValue::Null,
            J::Bool(b) => DValue::Bool(*b),
            J::Number(n) => {
                if let Some(i) = n.as_i64() {
                    DValue::Int(i)
                } else if let Some(u) = n.as_u64() {
                    DValue::UInt(u)
                } else {
                    DValue::Float(n.as_f64().unwrap_or(f64::NAN))
                }
            }
            J::String(s) => DValue::Str(s.clone()),
            J::Array(a) => DValue::List(a.iter().map(DValue::from_json).collect()),
            J::Object(o) => DValue::Msg(o.iter().map(|(k, v)| (k.clone(), DValue::from_json(v))).collect()),
        }
    }
}

fn collect(v: &DValue, path: &[&str], out: &mut Vec<f64>) -> bool {
    match v {
        DValue::List(items) => {
            if let Some(first) = path.first() {
                if let Ok(i) = first.parse::<usize>() {
                    return items.get(i).map(|x| collect(x, &path[1..], out)).unwrap_or(false);
                }
            }
            let mut ok = true;
            for it in items {
                ok &= collect(it, path, out);
            }
            ok
        }
        DValue::Msg(fields) => match path.split_first() {
            Some((head, rest)) => match v.field(head) {
                Some(x) => collect(x, rest, out),
                None => false,
            },
            None => {
                // every number under this message, in field order
                for (_, x) in fields {
                    collect_all(x, out);
                }
                true
            }
        },
        _ if path.is_empty() => match v.as_f64() {
            Some(x) => {
                out.push(x);
                true
            }
            None => false,
        },
        _ => false,
    }
}

fn collect_all(v: &DValue, out: &mut Vec<f64>) {
    match v {
        DValue::List(items) => items.iter().for_each(|x| collect_all(x, out)),
        DValue::Msg(fields) => fields.iter().for_each(|(_, x)| collect_all(x, out)),
        DValue::Bool(_) => {}
        other => {
            if let Some(x) = other.as_f64() {
                out.push(x);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paths() {
        let v = DValue::from_json(&serde_json::json!({
            "t": {"sec": 1, "nsec": 2},
            "joints": [{"name": "a", "position": 1.0}, {"name": "b", "position": 2.0}],
            "data": [3.0, 4.0]
        }));
        assert_eq!(v.numbers("joints.position"), Some(vec![1.0, 2.0]));
        assert_eq!(v.numbers("data.1"), Some(vec![4.0]));
        assert_eq!(v.numbers_any("position|joints.position"), Some(vec![1.0, 2.0]));
        // (serde_json orders object keys: data, joints, t{nsec, sec})
        assert_eq!(v.numbers("t"), Some(vec![2.0, 1.0]));
        assert_eq!(v.numbers(""), Some(vec![3.0, 4.0, 1.0, 2.0, 2.0, 1.0]));
        assert_eq!(v.numbers("nope"), None);
    }
}
