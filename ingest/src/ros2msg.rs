//! ROS 2 `.msg` schema text (`ros2msg`, including rosbag2's concatenation of dependencies with
//! `====` separators and `MSG: pkg/Type` headers) and a CDR decoder driven by it.
//!
//! CDR rules: a 4-byte encapsulation header (`00 01` little-endian, `00 00` big-endian, also the
//! XCDR1/XCDR2 plain variants), then fields in order, each primitive aligned to its size (max 8)
//! relative to the end of the header; strings are a u32 length (with the NUL) then bytes;
//! sequences and bounded arrays a u32 count then elements; fixed arrays have no count.

use std::collections::HashMap;

use crate::dvalue::DValue;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Prim {
    Bool,
    Byte,
    Char,
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    I64,
    U64,
    F32,
    F64,
    Str,
    WStr,
}

impl Prim {
    fn parse(t: &str) -> Option<Prim> {
        Some(match t {
            "bool" => Prim::Bool,
            "byte" | "octet" => Prim::Byte,
            "char" => Prim::Char,
            "int8" => Prim::I8,
            "uint8" => Prim::U8,
            "int16" => Prim::I16,
            "uint16" => Prim::U16,
            "int32" => Prim::I32,
            "uint32" => Prim::U32,
            "int64" => Prim::I64,
            "uint64" => Prim::U64,
            "float32" => Prim::F32,
            "float64" => Prim::F64,
            "string" => Prim::Str,
            "wstring" => Prim::WStr,
            _ => return None,
        })
    }
    fn size(self) -> usize {
        match self {
            Prim::Bool | Prim::Byte | Prim::Char | Prim::I8 | Prim::U8 => 1,
            Prim::I16 | Prim::U16 => 2,
            Prim::I32 | Prim::U32 | Prim::F32 | Prim::Str | Prim::WStr => 4,
            Prim::I64 | Prim::U64 | Prim::F64 => 8,
        }
    }
}

#[derive(Debug, Clone, PartialEq)]
pub enum BaseType {
    Prim(Prim),
    /// Index into [`Schema::msgs`].
    Msg(usize),
}

#[derive(Debug, Clone, PartialEq)]
pub enum Arity {
    One,
    Fixed(usize),
    /// Unbounded or bounded (`[<=N]`) sequence: a u32 count on the wire.
    Seq,
}

#[derive(Debug, Clone, PartialEq)]
pub struct Field {
    pub name: String,
    pub ty: BaseType,
    pub arity: Arity,
}

#[derive(Debug, Clone, PartialEq)]
pub struct MsgDef {
    pub name: String,
    pub fields: Vec<Field>,
}

/// A parsed schema: message 0 is the top-level type.
#[derive(Debug, Clone, PartialEq)]
pub struct Schema {
    pub msgs: Vec<MsgDef>,
}

struct RawField {
    ty: String,
    arity: Arity,
    name: String,
}

fn normalize(name: &str) -> String {
    // pkg/msg/Type -> pkg/Type
    let parts: Vec<&str> = name.split('/').collect();
    if parts.len() == 3 {
        format!("{}/{}", parts[0], parts[2])
    } else {
        name.to_string()
    }
}

fn package_of(name: &str) -> &str {
    name.split('/').next().unwrap_or("")
}

fn parse_fields(text: &str) -> Result<Vec<RawField>, String> {
    let mut out = Vec::new();
    for (ln, line) in text.lines().enumerate() {
        let line = match line.find('#') {
            Some(i) => &line[..i],
            None => line,
        };
        let line = line.trim();
        if line.is_empty() {
            continue;
        }
        let mut it = line.split_whitespace();
        let ty = it.next().unwrap_or("");
        let rest: String = it.collect::<Vec<_>>().join(" ");
        if rest.is_empty() {
            return Err(format!("line {}: field without a name: {line:?}", ln + 1));
        }
        // constants: `TYPE NAME=VALUE`
        let name_part = rest.split_whitespace().next().unwrap_or("");
        if name_part.contains('=')
            || rest.trim_start().starts_with('=')
            || rest.split_whitespace().nth(1).map(|s| s.starts_with('=')).unwrap_or(false)
        {
            continue;
        }
        let name = name_part.to_string();
        let (base, arity) = if let Some(i) = ty.find('[') {
            let inner = ty[i + 1..]
                .strip_suffix(']')
                .ok_or_else(|| format!("line {}: bad array type {ty:?}", ln + 1))?;
            let arity = if inner.is_empty() || inner.starts_with("<=") {
                Arity::Seq
            } else {
                Arity::Fixed(inner.parse().map_err(|_| format!("line {}: bad array size in {ty:?}", ln + 1))?)
            };
            (&ty[..i], arity)
        } else {
            (ty, Arity::One)
        };
        // bounded strings: string<=N
        let base = base.split("<=").next().unwrap_or(base);
        out.push(RawField { ty: base.to_string(), arity, name });
    }
    Ok(out)
}

/// Parses a `ros2msg` schema for the top-level type `top_name` (e.g. `sensor_msgs/msg/JointState`).
pub fn parse_schema(top_name: &str, text: &str) -> Result<Schema, String> {
    // split into sections
    let mut sections: Vec<(String, String)> = Vec::new();
    let mut cur_name = normalize(top_name);
    let mut cur = String::new();
    let mut lines = text.lines().peekable();
    while let Some(line) = lines.next() {
        let t = line.trim();
        if t.len() >= 3 && t.chars().all(|c| c == '=') {
            sections.push((std::mem::take(&mut cur_name), std::mem::take(&mut cur)));
            // next non-empty line must be MSG: name
            for l in lines.by_ref() {
                let l = l.trim();
                if l.is_empty() {
                    continue;
                }
                match l.strip_prefix("MSG:") {
                    Some(n) => cur_name = normalize(n.trim()),
                    None => return Err(format!("expected `MSG: pkg/Type` after a separator, got {l:?}")),
                }
                break;
            }
            continue;
        }
        cur.push_str(line);
        cur.push('\n');
    }
    sections.push((cur_name, cur));

    let mut defs: HashMap<String, Vec<RawField>> = HashMap::new();
    let mut order: Vec<String> = Vec::new();
    for (name, body) in &sections {
        if name.is_empty() {
            return Err("a section has no MSG: name".into());
        }
        let fields = parse_fields(body).map_err(|e| format!("in {name}: {e}"))?;
        if !defs.contains_key(name) {
            order.push(name.clone());
        }
        defs.insert(name.clone(), fields);
    }
    // builtins that rosbag2 sometimes omits
    for (n, body) in [
        ("builtin_interfaces/Time", "int32 sec\nuint32 nanosec\n"),
        ("builtin_interfaces/Duration", "int32 sec\nuint32 nanosec\n"),
        ("std_msgs/Header", "builtin_interfaces/Time stamp\nstring frame_id\n"),
    ] {
        if !defs.contains_key(n) {
            defs.insert(n.to_string(), parse_fields(body).expect("builtin"));
            order.push(n.to_string());
        }
    }

    let mut schema = Schema { msgs: Vec::new() };
    let mut index: HashMap<String, usize> = HashMap::new();
    let top = normalize(top_name);
    resolve(&top, &defs, &mut schema, &mut index, 0)?;
    Ok(schema)
}

fn lookup(ty: &str, ctx_pkg: &str, defs: &HashMap<String, Vec<RawField>>) -> Option<String> {
    let ty = normalize(ty);
    if defs.contains_key(&ty) {
        return Some(ty);
    }
    if ty == "Header" {
        return Some("std_msgs/Header".into());
    }
    if ty == "time" {
        return Some("builtin_interfaces/Time".into());
    }
    if ty == "duration" {
        return Some("builtin_interfaces/Duration".into());
    }
    if !ty.contains('/') {
        let q = format!("{ctx_pkg}/{ty}");
        if defs.contains_key(&q) {
            return Some(q);
        }
        let mut found = defs.keys().filter(|k| k.rsplit('/').next() == Some(ty.as_str()));
        if let Some(k) = found.next() {
            return Some(k.clone());
        }
    }
    None
}

fn resolve(
    name: &str,
    defs: &HashMap<String, Vec<RawField>>,
    schema: &mut Schema,
    index: &mut HashMap<String, usize>,
    depth: usize,
) -> Result<usize, String> {
    if let Some(&i) = index.get(name) {
        return Ok(i);
    }
    if depth > 32 {
        return Err(format!("message types nest too deeply at {name}"));
    }
    let raw = defs.get(name).ok_or_else(|| format!("no definition for message type {name}"))?;
    let idx = schema.msgs.len();
    schema.msgs.push(MsgDef { name: name.to_string(), fields: Vec::new() });
    index.insert(name.to_string(), idx);
    let pkg = package_of(name).to_string();
    let mut fields = Vec::new();
    for f in raw {
        let ty = match Prim::parse(&f.ty) {
            Some(p) => BaseType::Prim(p),
            None => {
                let full = lookup(&f.ty, &pkg, defs)
                    .ok_or_else(|| format!("{name}.{}: unknown type {}", f.name, f.ty))?;
                BaseType::Msg(resolve(&full, defs, schema, index, depth + 1)?)
            }
        };
        fields.push(Field { name: f.name.clone(), ty, arity: f.arity.clone() });
    }
    schema.msgs[idx].fields = fields;
    Ok(idx)
}

struct Cur<'a> {
    buf: &'a [u8],
    pos: usize,
    le: bool,
    /// XCDR2 aligns 8-byte primitives to 4.
    max_align: usize,
}

impl<'a> Cur<'a> {
    fn align(&mut self, n: usize) -> Result<(), String> {
        let n = n.min(self.max_align);
        let rem = self.pos % n;
        if rem != 0 {
            self.pos += n - rem;
        }
        if self.pos > self.buf.len() {
            return Err("message ends inside alignment padding".into());
        }
        Ok(())
    }
    fn take(&mut self, n: usize) -> Result<&'a [u8], String> {
        let end = self.pos.checked_add(n).ok_or("length overflow")?;
        if end > self.buf.len() {
            return Err(format!("message too short: needs {end} bytes, has {}", self.buf.len()));
        }
        let s = &self.buf[self.pos..end];
        self.pos = end;
        Ok(s)
    }
    fn u32(&mut self) -> Result<u32, String> {
        self.align(4)?;
        let b: [u8; 4] = self.take(4)?.try_into().expect("4 bytes");
        Ok(if self.le { u32::from_le_bytes(b) } else { u32::from_be_bytes(b) })
    }
    fn remaining(&self) -> usize {
        self.buf.len().saturating_sub(self.pos)
    }
}

macro_rules! num {
    ($c:expr, $t:ty, $n:expr) => {{
        $c.align($n)?;
        let b: [u8; $n] = $c.take($n)?.try_into().expect("size");
        if $c.le {
            <$t>::from_le_bytes(b)
        } else {
            <$t>::from_be_bytes(b)
        }
    }};
}

fn read_prim(c: &mut Cur, p: Prim) -> Result<DValue, String> {
    Ok(match p {
        Prim::Bool => DValue::Bool(c.take(1)?[0] != 0),
        Prim::Byte | Prim::U8 | Prim::Char => DValue::UInt(c.take(1)?[0] as u64),
        Prim::I8 => DValue::Int(c.take(1)?[0] as i8 as i64),
        Prim::I16 => DValue::Int(num!(c, i16, 2) as i64),
        Prim::U16 => DValue::UInt(num!(c, u16, 2) as u64),
        Prim::I32 => DValue::Int(num!(c, i32, 4) as i64),
        Prim::U32 => DValue::UInt(num!(c, u32, 4) as u64),
        Prim::I64 => DValue::Int(num!(c, i64, 8)),
        Prim::U64 => DValue::UInt(num!(c, u64, 8)),
        Prim::F32 => DValue::Float(num!(c, f32, 4) as f64),
        Prim::F64 => DValue::Float(num!(c, f64, 8)),
        Prim::Str => {
            let n = c.u32()? as usize;
            let b = c.take(n)?;
            let b = b.strip_suffix(&[0]).unwrap_or(b);
            DValue::Str(String::from_utf8_lossy(b).into_owned())
        }
        Prim::WStr => {
            let n = c.u32()? as usize;
            let b = c.take(n.checked_mul(4).ok_or("wstring length overflow")?)?;
            let s: String = b
                .chunks(4)
                .filter_map(|ch| {
                    let v = if c.le {
                        u32::from_le_bytes(ch.try_into().ok()?)
                    } else {
                        u32::from_be_bytes(ch.try_into().ok()?)
                    };
                    char::from_u32(v)
                })
                .filter(|&ch| ch != '\0')
                .collect();
            DValue::Str(s)
        }
    })
}

fn min_wire_size(_schema: &Schema, t: &BaseType) -> usize {
    match t {
        BaseType::Prim(p) => p.size(),
        // a nested message takes at least one byte (an empty one is a dummy byte)
        BaseType::Msg(_) => 1,
    }
}

fn read_msg(schema: &Schema, idx: usize, c: &mut Cur, depth: usize) -> Result<DValue, String> {
    if depth > 64 {
        return Err("message nests too deeply".into());
    }
    let def = &schema.msgs[idx];
    if def.fields.is_empty() {
        // an empty struct is serialized as one dummy byte
        c.take(1)?;
        return Ok(DValue::Msg(Vec::new()));
    }
    let mut out = Vec::with_capacity(def.fields.len());
    for f in &def.fields {
        let v = match f.arity {
            Arity::One => read_one(schema, &f.ty, c, depth)?,
            Arity::Fixed(n) => read_many(schema, &f.ty, n, c, depth)?,
            Arity::Seq => {
                let n = c.u32()? as usize;
                if n.saturating_mul(min_wire_size(schema, &f.ty)) > c.remaining() {
                    return Err(format!(
                        "{}.{}: sequence of {n} elements does not fit in the message",
                        def.name, f.name
                    ));
                }
                read_many(schema, &f.ty, n, c, depth)?
            }
        };
        out.push((f.name.clone(), v));
    }
    Ok(DValue::Msg(out))
}

fn read_one(schema: &Schema, t: &BaseType, c: &mut Cur, depth: usize) -> Result<DValue, String> {
    match t {
        BaseType::Prim(p) => read_prim(c, *p),
        BaseType::Msg(i) => read_msg(schema, *i, c, depth + 1),
    }
}

fn read_many(schema: &Schema, t: &BaseType, n: usize, c: &mut Cur, depth: usize) -> Result<DValue, String> {
    if n.saturating_mul(min_wire_size(schema, t)) > c.remaining() {
        return Err(format!("array of {n} elements does not fit in the message"));
    }
    let mut v = Vec::with_capacity(n);
    for _ in 0..n {
        v.push(read_one(schema, t, c, depth)?);
    }
    Ok(DValue::List(v))
}

/// Decodes one CDR-encoded message.
pub fn decode_cdr(schema: &Schema, data: &[u8]) -> Result<DValue, String> {
    if data.len() < 4 {
        return Err("CDR message shorter than its 4-byte encapsulation header".into());
    }
    let (le, max_align) = match (data[0], data[1]) {
        (0x00, 0x00) | (0x00, 0x02) => (false, 8), // CDR_BE, PL_CDR_BE
        (0x00, 0x01) | (0x00, 0x03) => (true, 8),  // CDR_LE, PL_CDR_LE
        (0x00, 0x06) | (0x00, 0x08) | (0x00, 0x0a) => (false, 4), // XCDR2 BE
        (0x00, 0x07) | (0x00, 0x09) | (0x00, 0x0b) => (true, 4), // XCDR2 LE
        (a, b) => return Err(format!("unknown CDR encapsulation {a:#04x} {b:#04x}")),
    };
    let mut c = Cur { buf: &data[4..], pos: 0, le, max_align };
    read_msg(schema, 0, &mut c, 0)
}

#[cfg(test)]
mod tests {
    use super::*;

    const JOINT_STATE: &str = "# comment\nstd_msgs/Header header\n\nstring[] name\nfloat64[] position\nfloat64[] velocity\nfloat64[] effort\n\n================================================================================\nMSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n\n================================================================================\nMSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n";

    #[test]
    fn parses_joint_state() {
        let s = parse_schema("sensor_msgs/msg/JointState", JOINT_STATE).unwrap();
        assert_eq!(s.msgs[0].fields.len(), 5);
        // hand-built CDR: header{stamp{1,2}, "ab"}, name ["x"], position [1.5], velocity [], effort []
        let mut b = vec![0u8, 1, 0, 0];
        let mut body = Vec::new();
        body.extend(1i32.to_le_bytes());
        body.extend(2u32.to_le_bytes());
        body.extend(3u32.to_le_bytes());
        body.extend(b"ab\0");
        body.push(0); // pad to 4
        body.extend(1u32.to_le_bytes());
        body.extend(2u32.to_le_bytes());
        body.extend(b"x\0");
        body.extend([0, 0]); // pad to 4
        body.extend(1u32.to_le_bytes());
        // the count ends at 32: already aligned for the f64
        body.extend(1.5f64.to_le_bytes());
        body.extend(0u32.to_le_bytes());
        body.extend(0u32.to_le_bytes());
        b.extend(body);
        let v = decode_cdr(&s, &b).unwrap();
        assert_eq!(v.numbers("position"), Some(vec![1.5]));
        assert_eq!(v.get_path("header.frame_id").and_then(|x| x.as_str()), Some("ab"));
    }

    #[test]
    fn constants_and_bounds() {
        let s = parse_schema(
            "a/msg/B",
            "int32 X=3\nint32 Y = 4\nstring<=10 s\nfloat32[<=3] f\nuint8[2] u\nint32 d 7\n",
        )
        .unwrap();
        let names: Vec<_> = s.msgs[0].fields.iter().map(|f| f.name.as_str()).collect();
        assert_eq!(names, ["s", "f", "u", "d"]);
        assert_eq!(s.msgs[0].fields[1].arity, Arity::Seq);
        assert_eq!(s.msgs[0].fields[2].arity, Arity::Fixed(2));
    }
}
