//! h5stream owns writing an HDF5 file in one pass, and HDF5's metadata checksum ([`lookup3`]).
//!
//! Each dataset's bytes go to the file as soon as they are given, and a group's object header
//! once its children are written (children before parents, the root last), so memory holds one
//! dataset — or one slice of it, through [`Writer::stream`] — and the links of the groups still
//! open, never the file. [`Writer`] takes datasets and finished [`Group`]s in that order and
//! returns each one's address for its parent's links; [`Writer::finish`] takes the root:
//!
//! ```
//! use h5stream::{Attr, Group, Writer};
//! # let dir = tempfile::tempdir().unwrap();
//! # let path = dir.path().join("demo.hdf5");
//! let mut w = Writer::create(&path)?;
//! let mut demo = Group::default();
//! demo.link("actions", w.dataset(&[2, 3], &[0.1f32, 0.2, 0.3, 0.4, 0.5, 0.6])?); // written now
//! demo.attr("num_samples", Attr::I64(2));
//! let mut data = Group::default();
//! data.link("demo_0", w.group(demo)?); // its header, after its children
//! data.attr("env_args", Attr::Str(r#"{"env_name": "Lift"}"#.into()));
//! let mut root = Group::default();
//! root.link("data", w.group(data)?);
//! w.finish(root)?; // the root, the heap, the superblock; then fsync
//! # Ok::<(), std::io::Error>(())
//! ```
//!
//! Why hand-written: `hdf5-pure`'s `FileBuilder` holds the whole file until it writes it, and
//! its in-place editor rebuilds every group it touches (export/README.md, "Why its own HDF5
//! writer", has the figures). The layout is the small part of the HDF5 format (specification
//! 3.0) that robomimic's and ALOHA's files need, in encodings libhdf5 ≥ 1.8 and `hdf5-pure`
//! both read:
//!
//! * superblock version 2 (offsets and lengths of 8 bytes), rewritten at the end with the root
//!   group's address and the end of file;
//! * version 2 object headers, one chunk, Jenkins lookup3 checksums;
//! * groups with compact link storage (Link Info, Group Info and one Link message per child);
//! * datasets with contiguous layout: dataspace, datatype (little-endian integers of 8 to 64
//!   bits, IEEE floats, fixed-length null-padded ASCII strings), fill value and layout
//!   messages, and attributes;
//! * attributes in their object's header (a group's or a dataset's), scalar or 1-D: those
//!   numbers, fixed-length null-padded strings and variable-length strings (ASCII or UTF-8),
//!   whose bytes sit in global heap collections reserved as the file grows and filled in when
//!   full.
//!
//! What it does not do: chunked or filtered datasets, dense (fractal heap) link storage,
//! editing. Limits of the format surface as errors, never as a malformed file: one message
//! holds at most 65,535 bytes (a name or an attribute past that is refused).

use std::fs::File;
use std::io::{self, BufWriter, Seek, SeekFrom, Write};
use std::path::Path;

/// The address HDF5 writes for "none".
const UNDEFINED: u64 = u64::MAX;
const SUPERBLOCK_SIZE: u64 = 48;
/// Global heap collections: libhdf5 allocates at least 4 KiB; strings are packed into
/// collections of 64 KiB unless one needs more.
const HEAP_MIN: usize = 4096;
const HEAP_DEFAULT: usize = 64 * 1024;
const HEAP_HEADER: usize = 16;
const HEAP_OBJECT_HEADER: usize = 16;

// Object header message types (spec IV.A.2).
const MSG_DATASPACE: u8 = 0x01;
const MSG_LINK_INFO: u8 = 0x02;
const MSG_DATATYPE: u8 = 0x03;
const MSG_FILL_VALUE: u8 = 0x05;
const MSG_LINK: u8 = 0x06;
const MSG_LAYOUT: u8 = 0x08;
const MSG_GROUP_INFO: u8 = 0x0A;
const MSG_ATTRIBUTE: u8 = 0x0C;

/// An attribute's value: a scalar, a 1-D array of numbers, or strings.
#[derive(Debug, Clone, PartialEq)]
pub enum Attr {
    /// A 64-bit signed integer.
    I64(i64),
    /// A 64-bit IEEE float.
    F64(f64),
    /// A variable-length UTF-8 string (what h5py reads back as `str`).
    Str(String),
    /// A number of any [`Element`] type, or a 1-D array of them: [`Attr::number`],
    /// [`Attr::numbers`].
    Numbers(Numbers),
    /// One string (a scalar attribute) or a 1-D array of them, stored as `kind` says.
    Strings {
        /// The strings; exactly one when `array` is false.
        values: Vec<String>,
        /// A 1-D array (else a scalar).
        array: bool,
        /// Fixed- or variable-length, ASCII or UTF-8.
        kind: StrKind,
    },
}

/// How an [`Attr::Strings`] is stored; h5py reads ASCII ones back as `bytes`, UTF-8 ones as
/// `str` (variable-length) or `bytes` (fixed-length). The bytes are written as given: an ASCII
/// string's are not checked, as libhdf5 does not check them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StrKind {
    /// Fixed-length UTF-8, null-padded to the longest value (at least one byte).
    FixedUtf8,
    /// Fixed-length ASCII, null-padded to the longest value (at least one byte).
    FixedAscii,
    /// Variable-length UTF-8 (bytes in the global heap).
    VarUtf8,
    /// Variable-length ASCII (bytes in the global heap).
    VarAscii,
}

/// The numbers of an [`Attr::Numbers`], little-endian, and whether they are one scalar.
#[derive(Debug, Clone, PartialEq)]
pub struct Numbers {
    dtype: Dtype,
    bytes: Vec<u8>,
    /// `None` for a scalar, else the array's length.
    len: Option<u64>,
}

impl Attr {
    /// A scalar attribute of any [`Element`] type.
    pub fn number<T: Element>(value: T) -> Attr {
        let mut bytes = Vec::new();
        T::put(&[value], &mut bytes);
        Attr::Numbers(Numbers { dtype: T::DTYPE, bytes, len: None })
    }
    /// A 1-D array attribute of any [`Element`] type.
    pub fn numbers<T: Element>(values: &[T]) -> Attr {
        let mut bytes = Vec::new();
        T::put(values, &mut bytes);
        Attr::Numbers(Numbers { dtype: T::DTYPE, bytes, len: Some(values.len() as u64) })
    }
    /// One string, stored as `kind` says.
    pub fn string(value: &str, kind: StrKind) -> Attr {
        Attr::Strings { values: vec![value.to_string()], array: false, kind }
    }
    /// A 1-D array of strings, stored as `kind` says.
    pub fn strings(values: Vec<String>, kind: StrKind) -> Attr {
        Attr::Strings { values, array: true, kind }
    }
}

/// A dataset's element type; [`Element`] maps Rust numbers onto it.
#[doc(hidden)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Dtype {
    I8,
    I16,
    I32,
    I64,
    U8,
    U16,
    U32,
    U64,
    F32,
    F64,
    /// Fixed-length ASCII, null-padded, of this many bytes.
    Ascii(u32),
}

/// A number a dataset or an attribute can hold (the signed and unsigned integers of 8 to 64
/// bits, `f32`, `f64`), written little-endian.
pub trait Element: Copy + sealed::Sealed {
    #[doc(hidden)]
    const DTYPE: Dtype;
    #[doc(hidden)]
    fn put(values: &[Self], out: &mut Vec<u8>);
}

mod sealed {
    pub trait Sealed {}
    impl Sealed for i8 {}
    impl Sealed for i16 {}
    impl Sealed for i32 {}
    impl Sealed for i64 {}
    impl Sealed for u8 {}
    impl Sealed for u16 {}
    impl Sealed for u32 {}
    impl Sealed for u64 {}
    impl Sealed for f32 {}
    impl Sealed for f64 {}
}

macro_rules! element {
    ($t:ty, $d:expr) => {
        impl Element for $t {
            const DTYPE: Dtype = $d;
            fn put(values: &[Self], out: &mut Vec<u8>) {
                out.reserve(values.len() * std::mem::size_of::<$t>());
                for v in values {
                    out.extend_from_slice(&v.to_le_bytes());
                }
            }
        }
    };
}
element!(i8, Dtype::I8);
element!(i16, Dtype::I16);
element!(i32, Dtype::I32);
element!(i64, Dtype::I64);
element!(u8, Dtype::U8);
element!(u16, Dtype::U16);
element!(u32, Dtype::U32);
element!(u64, Dtype::U64);
element!(f32, Dtype::F32);
element!(f64, Dtype::F64);

/// Values converted to bytes at a time by [`DatasetWriter::write`] (512 KiB of `f64`).
const WRITE_CHUNK: usize = 64 * 1024;

/// A group being filled: its children's links and its attributes, written by [`Writer::group`].
#[derive(Debug, Default)]
pub struct Group {
    links: Vec<(String, u64)>,
    attrs: Vec<(String, Attr)>,
}

impl Group {
    /// Links a written child (its address from [`Writer::dataset`] or [`Writer::group`]).
    pub fn link(&mut self, name: &str, address: u64) {
        self.links.push((name.to_string(), address));
    }
    /// Sets an attribute (a second value under the same name replaces the first).
    pub fn attr(&mut self, name: &str, value: Attr) {
        match self.attrs.iter_mut().find(|(n, _)| n == name) {
            Some(slot) => slot.1 = value,
            None => self.attrs.push((name.to_string(), value)),
        }
    }
}

/// A global heap collection being filled: its address (reserved in the file) and its bytes.
struct Collection {
    address: u64,
    bytes: Vec<u8>,
    size: usize,
    next_index: u16,
}

/// Writes one HDF5 file front to back (see the module's header).
pub struct Writer {
    out: BufWriter<File>,
    /// The file's length so far (the next object's address).
    eof: u64,
    heap: Option<Collection>,
    /// Reused for every dataset's bytes and every object header.
    scratch: Vec<u8>,
}

impl Writer {
    /// Creates (truncates) `path`; the superblock is written by [`finish`](Self::finish).
    pub fn create(path: &Path) -> io::Result<Writer> {
        let mut out = BufWriter::with_capacity(1 << 20, File::create(path)?);
        out.write_all(&[0; SUPERBLOCK_SIZE as usize])?;
        Ok(Writer { out, eof: SUPERBLOCK_SIZE, heap: None, scratch: Vec::new() })
    }

    fn append(&mut self, bytes: &[u8]) -> io::Result<u64> {
        let at = self.eof;
        self.out.write_all(bytes)?;
        self.eof += bytes.len() as u64;
        Ok(at)
    }

    /// Writes a dataset of `shape` (row-major `values`, whose count must be the shape's
    /// product) and returns its object header's address.
    pub fn dataset<T: Element>(&mut self, shape: &[u64], values: &[T]) -> io::Result<u64> {
        check_count(shape, values.len())?;
        let mut d = self.stream::<T>(shape)?;
        d.write(values)?;
        d.finish()
    }

    /// Starts a dataset of `shape` whose values (row-major) are given a slice at a time
    /// ([`DatasetWriter::write`]): each slice goes to the file as it comes, so memory holds a
    /// slice, not the dataset. Nothing else is written until it is finished (it borrows the
    /// writer); dropped unfinished, its bytes stay in the file, linked from nowhere.
    pub fn stream<T: Element>(&mut self, shape: &[u64]) -> io::Result<DatasetWriter<'_, T>> {
        let want = check_shape(shape)?;
        let data_at = self.eof;
        Ok(DatasetWriter {
            w: self,
            shape: shape.to_vec(),
            want,
            written: 0,
            data_at,
            attrs: Vec::new(),
            _element: std::marker::PhantomData,
        })
    }

    /// Writes a 1-D dataset of fixed-length ASCII strings as wide as the longest (at least
    /// one byte), null-padded: what h5py reads as `bytes` (robomimic's masks).
    pub fn ascii_strings(&mut self, values: &[&str]) -> io::Result<u64> {
        if let Some(s) = values.iter().find(|s| !s.is_ascii()) {
            return Err(invalid(format!("{s:?} is not ASCII")));
        }
        let width = values.iter().map(|s| s.len()).max().unwrap_or(0).max(1);
        let mut bytes = vec![0u8; width * values.len()];
        for (slot, s) in bytes.chunks_mut(width).zip(values) {
            slot[..s.len()].copy_from_slice(s.as_bytes());
        }
        let width = u32::try_from(width).map_err(|_| invalid("a string of 4 GiB".into()))?;
        let data_at = if bytes.is_empty() { UNDEFINED } else { self.append(&bytes)? };
        self.dataset_header(&[values.len() as u64], Dtype::Ascii(width), data_at, bytes.len() as u64, &[])
    }

    /// A dataset's object header, after its contiguous data (`len` bytes at `data_at`).
    fn dataset_header(
        &mut self,
        shape: &[u64],
        dtype: Dtype,
        data_at: u64,
        len: u64,
        attrs: &[(String, Attr)],
    ) -> io::Result<u64> {
        let mut h = Header::default();
        h.message(MSG_DATASPACE, &dataspace(shape))?;
        h.message(MSG_DATATYPE, &datatype(dtype))?;
        // Version 3; space allocated late, fill value written "if set" (none set): libhdf5's
        // defaults for a contiguous dataset.
        h.message(MSG_FILL_VALUE, &[3, 0x02 | (2 << 2)])?;
        let mut layout = vec![3, 1];
        layout.extend_from_slice(&data_at.to_le_bytes());
        layout.extend_from_slice(&len.to_le_bytes());
        h.message(MSG_LAYOUT, &layout)?;
        self.attributes(&mut h, attrs)?;
        let header = h.finish()?;
        self.append(&header)
    }

    /// The Attribute messages of an object (names checked unique, as a group's links are).
    fn attributes(&mut self, h: &mut Header, attrs: &[(String, Attr)]) -> io::Result<()> {
        for (name, value) in attrs {
            let a = self.attribute(name, value)?;
            h.message(MSG_ATTRIBUTE, &a)?;
        }
        Ok(())
    }

    /// Writes a group's object header (its children are already written) and returns its
    /// address.
    pub fn group(&mut self, g: Group) -> io::Result<u64> {
        // Two links of one name would make a file whose readers disagree on what the name is.
        let mut names: Vec<&str> = g.links.iter().map(|(n, _)| n.as_str()).collect();
        names.sort_unstable();
        if let Some(w) = names.windows(2).find(|w| w[0] == w[1]) {
            return Err(invalid(format!("two links named {:?} in one group", w[0])));
        }
        let mut h = Header::default();
        // Link Info version 0: no creation order, no dense storage (fractal heap and name
        // index undefined).
        let mut info = vec![0, 0];
        info.extend_from_slice(&UNDEFINED.to_le_bytes());
        info.extend_from_slice(&UNDEFINED.to_le_bytes());
        h.message(MSG_LINK_INFO, &info)?;
        // Group Info version 0. Past libhdf5's default of 8 compact links, it says how many
        // this group holds compactly (readers iterate the Link messages whatever it says).
        match u16::try_from(g.links.len()) {
            Ok(n) if n > 8 => {
                let mut gi = vec![0, 1];
                gi.extend_from_slice(&n.to_le_bytes());
                gi.extend_from_slice(&6u16.to_le_bytes());
                h.message(MSG_GROUP_INFO, &gi)?;
            }
            _ => h.message(MSG_GROUP_INFO, &[0, 0])?,
        }
        for (name, address) in &g.links {
            h.message(MSG_LINK, &link(name, *address)?)?;
        }
        self.attributes(&mut h, &g.attrs)?;
        let header = h.finish()?;
        self.append(&header)
    }

    /// An Attribute message (version 3), scalar or 1-D; a variable-length string's bytes go to
    /// the global heap.
    fn attribute(&mut self, name: &str, value: &Attr) -> io::Result<Vec<u8>> {
        if name.is_empty() || name.contains('\0') {
            return Err(invalid(format!("attribute name {name:?}")));
        }
        let (dtype, space, data): (Vec<u8>, Vec<u8>, Vec<u8>) = match value {
            Attr::I64(v) => (datatype(Dtype::I64), dataspace(&[]), v.to_le_bytes().to_vec()),
            Attr::F64(v) => (datatype(Dtype::F64), dataspace(&[]), v.to_le_bytes().to_vec()),
            Attr::Str(s) => {
                (vlen_string(true), dataspace(&[]), self.vlen_refs(name, std::slice::from_ref(s))?)
            }
            Attr::Numbers(n) => {
                let space = match n.len {
                    None => dataspace(&[]),
                    Some(len) => dataspace(&[len]),
                };
                (datatype(n.dtype), space, n.bytes.clone())
            }
            Attr::Strings { values, array, kind } => {
                let space = if *array {
                    dataspace(&[values.len() as u64])
                } else if values.len() == 1 {
                    dataspace(&[])
                } else {
                    return Err(invalid(format!("attribute {name}: {} strings for a scalar", values.len())));
                };
                match kind {
                    StrKind::FixedUtf8 | StrKind::FixedAscii => {
                        let ascii = *kind == StrKind::FixedAscii;
                        let width = values.iter().map(|s| s.len()).max().unwrap_or(0).max(1);
                        let mut bytes = vec![0u8; width * values.len()];
                        for (slot, s) in bytes.chunks_mut(width).zip(values) {
                            slot[..s.len()].copy_from_slice(s.as_bytes());
                        }
                        let width = u32::try_from(width)
                            .map_err(|_| invalid(format!("attribute {name} of 4 GiB")))?;
                        (fixed_string(width, !ascii), space, bytes)
                    }
                    StrKind::VarUtf8 | StrKind::VarAscii => {
                        let utf8 = *kind == StrKind::VarUtf8;
                        (vlen_string(utf8), space, self.vlen_refs(name, values)?)
                    }
                }
            }
        };
        let name_len = u16::try_from(name.len() + 1)
            .map_err(|_| invalid(format!("attribute name of {} bytes", name.len())))?;
        let mut a = vec![3, 0];
        a.extend_from_slice(&name_len.to_le_bytes());
        a.extend_from_slice(&(dtype.len() as u16).to_le_bytes());
        a.extend_from_slice(&(space.len() as u16).to_le_bytes());
        a.push(u8::from(!name.is_ascii())); // name's character set: ASCII or UTF-8
        a.extend_from_slice(name.as_bytes());
        a.push(0);
        a.extend_from_slice(&dtype);
        a.extend_from_slice(&space);
        a.extend_from_slice(&data);
        Ok(a)
    }

    /// Each string as a global heap object, and the references to them (16 bytes each).
    fn vlen_refs(&mut self, name: &str, values: &[String]) -> io::Result<Vec<u8>> {
        let mut d = Vec::with_capacity(16 * values.len());
        for s in values {
            let len = u32::try_from(s.len()).map_err(|_| invalid(format!("attribute {name} of 4 GiB")))?;
            let (collection, index) = self.heap_object(s.as_bytes())?;
            d.extend_from_slice(&len.to_le_bytes());
            d.extend_from_slice(&collection.to_le_bytes());
            d.extend_from_slice(&index.to_le_bytes());
        }
        Ok(d)
    }

    /// Stores `bytes` as a global heap object and returns (collection address, index).
    fn heap_object(&mut self, bytes: &[u8]) -> io::Result<(u64, u32)> {
        let need = HEAP_OBJECT_HEADER + bytes.len().div_ceil(8) * 8;
        let fits =
            self.heap.as_ref().is_some_and(|c| c.size - c.bytes.len() >= need && c.next_index < u16::MAX);
        if !fits {
            self.close_heap()?;
            // Reserve the collection's space now (its address goes into headers written
            // before it is full); its bytes are written in place when it is closed.
            let size = HEAP_DEFAULT.max(HEAP_HEADER + need).max(HEAP_MIN).div_ceil(8) * 8;
            let address = self.eof;
            let zeros = [0u8; 8192];
            let mut left = size;
            while left > 0 {
                let n = left.min(zeros.len());
                self.append(&zeros[..n])?;
                left -= n;
            }
            let mut head = Vec::with_capacity(size);
            head.extend_from_slice(b"GCOL");
            head.extend_from_slice(&[1, 0, 0, 0]);
            head.extend_from_slice(&(size as u64).to_le_bytes());
            self.heap = Some(Collection { address, bytes: head, size, next_index: 1 });
        }
        let c = self.heap.as_mut().expect("a collection with room");
        let index = c.next_index;
        c.next_index += 1;
        c.bytes.extend_from_slice(&index.to_le_bytes());
        c.bytes.extend_from_slice(&0u16.to_le_bytes()); // reference count
        c.bytes.extend_from_slice(&[0; 4]);
        c.bytes.extend_from_slice(&(bytes.len() as u64).to_le_bytes());
        c.bytes.extend_from_slice(bytes);
        c.bytes.resize(c.bytes.len().div_ceil(8) * 8, 0);
        Ok((c.address, u32::from(index)))
    }

    /// Writes the open collection in place: its objects, then free space to its end.
    fn close_heap(&mut self) -> io::Result<()> {
        let Some(mut c) = self.heap.take() else { return Ok(()) };
        let free = c.size - c.bytes.len();
        if free >= HEAP_OBJECT_HEADER {
            // Object 0 is the free space; its size counts its own header.
            c.bytes.extend_from_slice(&0u16.to_le_bytes());
            c.bytes.extend_from_slice(&[0; 6]);
            c.bytes.extend_from_slice(&(free as u64).to_le_bytes());
        }
        self.out.seek(SeekFrom::Start(c.address))?;
        self.out.write_all(&c.bytes)?;
        self.out.seek(SeekFrom::Start(self.eof))?;
        Ok(())
    }

    /// Writes the root group, the heap's last collection and the superblock, and makes the
    /// file durable.
    pub fn finish(mut self, root: Group) -> io::Result<()> {
        let root = self.group(root)?;
        self.close_heap()?;
        let mut sb = Vec::with_capacity(SUPERBLOCK_SIZE as usize);
        sb.extend_from_slice(b"\x89HDF\r\n\x1a\n");
        sb.extend_from_slice(&[2, 8, 8, 0]); // version 2; offsets and lengths of 8 bytes; flags
        sb.extend_from_slice(&0u64.to_le_bytes()); // base address
        sb.extend_from_slice(&UNDEFINED.to_le_bytes()); // no superblock extension
        sb.extend_from_slice(&self.eof.to_le_bytes());
        sb.extend_from_slice(&root.to_le_bytes());
        let sum = lookup3(&sb);
        sb.extend_from_slice(&sum.to_le_bytes());
        self.out.seek(SeekFrom::Start(0))?;
        self.out.write_all(&sb)?;
        let file = self.out.into_inner().map_err(|e| e.into_error())?;
        file.sync_all()
    }
}

fn invalid(msg: String) -> io::Error {
    io::Error::new(io::ErrorKind::InvalidInput, msg)
}

/// The number of values a dataset of `shape` holds (HDF5's rank is at most 32).
fn check_shape(shape: &[u64]) -> io::Result<u64> {
    // HDF5's largest rank (H5S_MAX_RANK).
    if shape.len() > 32 {
        return Err(invalid(format!("a dataset of rank {} (at most 32)", shape.len())));
    }
    shape
        .iter()
        .try_fold(1u64, |a, &d| a.checked_mul(d))
        .ok_or_else(|| invalid(format!("a dataset of shape {shape:?} holds more than 2^64 values")))
}

fn check_count(shape: &[u64], count: usize) -> io::Result<()> {
    if check_shape(shape)? != count as u64 {
        return Err(invalid(format!("{count} values do not fill a dataset of shape {shape:?}")));
    }
    Ok(())
}

/// A dataset being written a slice at a time ([`Writer::stream`]): its values go to the file as
/// they are given, its header (with its attributes) when it is [finished](Self::finish).
pub struct DatasetWriter<'w, T: Element> {
    w: &'w mut Writer,
    shape: Vec<u64>,
    /// The values the shape holds, and those written so far.
    want: u64,
    written: u64,
    data_at: u64,
    attrs: Vec<(String, Attr)>,
    _element: std::marker::PhantomData<T>,
}

impl<T: Element> DatasetWriter<'_, T> {
    /// Writes the next values (row-major); more than the shape holds is refused.
    pub fn write(&mut self, values: &[T]) -> io::Result<()> {
        if self.written + values.len() as u64 > self.want {
            return Err(invalid(format!(
                "{} values do not fit a dataset of shape {:?}",
                self.written + values.len() as u64,
                self.shape
            )));
        }
        let mut bytes = std::mem::take(&mut self.w.scratch);
        let mut r = Ok(());
        for chunk in values.chunks(WRITE_CHUNK) {
            bytes.clear();
            T::put(chunk, &mut bytes);
            r = self.w.append(&bytes).map(|_| ());
            if r.is_err() {
                break;
            }
        }
        self.w.scratch = bytes;
        r?;
        self.written += values.len() as u64;
        Ok(())
    }

    /// Sets an attribute of the dataset (a second value under the same name replaces the first).
    pub fn attr(&mut self, name: &str, value: Attr) {
        match self.attrs.iter_mut().find(|(n, _)| n == name) {
            Some(slot) => slot.1 = value,
            None => self.attrs.push((name.to_string(), value)),
        }
    }

    /// Writes the dataset's header and returns its address; refused when fewer values were
    /// written than the shape holds.
    pub fn finish(self) -> io::Result<u64> {
        if self.written != self.want {
            return Err(invalid(format!(
                "{} values do not fill a dataset of shape {:?}",
                self.written, self.shape
            )));
        }
        let len = self.want * std::mem::size_of::<T>() as u64;
        let data_at = if len == 0 { UNDEFINED } else { self.data_at };
        self.w.dataset_header(&self.shape, T::DTYPE, data_at, len, &self.attrs)
    }
}

/// A version 2 object header being assembled: its messages, then the checksummed whole.
#[derive(Default)]
struct Header {
    messages: Vec<u8>,
}

impl Header {
    fn message(&mut self, kind: u8, body: &[u8]) -> io::Result<()> {
        let len = u16::try_from(body.len()).map_err(|_| {
            invalid(format!("an object header message of {} bytes (at most 65,535)", body.len()))
        })?;
        self.messages.push(kind);
        self.messages.extend_from_slice(&len.to_le_bytes());
        self.messages.push(0); // message flags
        self.messages.extend_from_slice(body);
        Ok(())
    }

    fn finish(self) -> io::Result<Vec<u8>> {
        let size =
            u32::try_from(self.messages.len()).map_err(|_| invalid("an object header of 4 GiB".into()))?;
        let mut h = Vec::with_capacity(self.messages.len() + 14);
        h.extend_from_slice(b"OHDR");
        h.push(2); // version
        h.push(0x02); // flags: chunk 0's size in 4 bytes; no times, no attribute phase change
        h.extend_from_slice(&size.to_le_bytes());
        h.extend_from_slice(&self.messages);
        let sum = lookup3(&h);
        h.extend_from_slice(&sum.to_le_bytes());
        Ok(h)
    }
}

/// A Dataspace message (version 2): scalar when `shape` is empty, else simple.
fn dataspace(shape: &[u64]) -> Vec<u8> {
    let mut d = vec![2, shape.len() as u8, 0, u8::from(!shape.is_empty())];
    for dim in shape {
        d.extend_from_slice(&dim.to_le_bytes());
    }
    d
}

/// A Datatype message (version 1 encodings).
fn datatype(t: Dtype) -> Vec<u8> {
    match t {
        Dtype::I8 => fixed_point(1, true),
        Dtype::I16 => fixed_point(2, true),
        Dtype::I32 => fixed_point(4, true),
        Dtype::I64 => fixed_point(8, true),
        Dtype::U8 => fixed_point(1, false),
        Dtype::U16 => fixed_point(2, false),
        Dtype::U32 => fixed_point(4, false),
        Dtype::U64 => fixed_point(8, false),
        Dtype::F32 => floating_point(4, 31, 23, 8, 23, 127),
        Dtype::F64 => floating_point(8, 63, 52, 11, 52, 1023),
        Dtype::Ascii(width) => fixed_string(width, false),
    }
}

/// Class 3: a fixed-length string of `width` bytes, null-padded (1), ASCII or UTF-8.
fn fixed_string(width: u32, utf8: bool) -> Vec<u8> {
    let mut d = vec![0x13, 0x01 | (u8::from(utf8) << 4), 0, 0];
    d.extend_from_slice(&width.to_le_bytes());
    d
}

/// Class 0: little-endian, zero-padded, signed or not; bit offset 0, full precision.
fn fixed_point(size: u32, signed: bool) -> Vec<u8> {
    let mut d = vec![0x10, if signed { 0x08 } else { 0 }, 0, 0];
    d.extend_from_slice(&size.to_le_bytes());
    d.extend_from_slice(&0u16.to_le_bytes());
    d.extend_from_slice(&((size * 8) as u16).to_le_bytes());
    d
}

/// Class 1: IEEE 754 little-endian, implied leading mantissa bit.
fn floating_point(size: u32, sign: u8, exp_at: u8, exp_bits: u8, mantissa_bits: u8, bias: u32) -> Vec<u8> {
    let mut d = vec![0x11, 0x20, sign, 0];
    d.extend_from_slice(&size.to_le_bytes());
    d.extend_from_slice(&0u16.to_le_bytes());
    d.extend_from_slice(&((size * 8) as u16).to_le_bytes());
    d.extend_from_slice(&[exp_at, exp_bits, 0, mantissa_bits]);
    d.extend_from_slice(&bias.to_le_bytes());
    d
}

/// Class 9: a variable-length null-terminated string of unsigned bytes, UTF-8 (h5py's `str`) or
/// ASCII (h5py's `bytes`).
fn vlen_string(utf8: bool) -> Vec<u8> {
    let mut d = vec![0x19, 0x01, u8::from(utf8), 0];
    d.extend_from_slice(&16u32.to_le_bytes());
    d.extend_from_slice(&fixed_point(1, false));
    d
}

/// A Link message (version 1) for a hard link.
fn link(name: &str, address: u64) -> io::Result<Vec<u8>> {
    if name.is_empty() || name.contains('/') || name == "." {
        return Err(invalid(format!("link name {name:?}")));
    }
    let mut l = vec![1];
    match u8::try_from(name.len()) {
        Ok(n) => l.extend_from_slice(&[0x10, 1, n]), // 1-byte length; UTF-8 names
        Err(_) => {
            let n = u16::try_from(name.len())
                .map_err(|_| invalid(format!("a link name of {} bytes", name.len())))?;
            l.extend_from_slice(&[0x11, 1]);
            l.extend_from_slice(&n.to_le_bytes());
        }
    }
    l.extend_from_slice(name.as_bytes());
    l.extend_from_slice(&address.to_le_bytes());
    Ok(l)
}

/// Bob Jenkins' lookup3 `hashlittle` with an initial value of 0: HDF5's metadata checksum.
pub fn lookup3(key: &[u8]) -> u32 {
    let mut a = 0xdead_beef_u32.wrapping_add(key.len() as u32);
    let (mut b, mut c) = (a, a);
    let word = |k: &[u8]| u32::from_le_bytes([k[0], k[1], k[2], k[3]]);
    let mut k = key;
    while k.len() > 12 {
        a = a.wrapping_add(word(&k[0..4]));
        b = b.wrapping_add(word(&k[4..8]));
        c = c.wrapping_add(word(&k[8..12]));
        // mix
        a = a.wrapping_sub(c);
        a ^= c.rotate_left(4);
        c = c.wrapping_add(b);
        b = b.wrapping_sub(a);
        b ^= a.rotate_left(6);
        a = a.wrapping_add(c);
        c = c.wrapping_sub(b);
        c ^= b.rotate_left(8);
        b = b.wrapping_add(a);
        a = a.wrapping_sub(c);
        a ^= c.rotate_left(16);
        c = c.wrapping_add(b);
        b = b.wrapping_sub(a);
        b ^= a.rotate_left(19);
        a = a.wrapping_add(c);
        c = c.wrapping_sub(b);
        c ^= b.rotate_left(4);
        b = b.wrapping_add(a);
        k = &k[12..];
    }
    if k.is_empty() {
        return c;
    }
    // The last 1–12 bytes, zero-padded.
    let mut tail = [0u8; 12];
    tail[..k.len()].copy_from_slice(k);
    a = a.wrapping_add(word(&tail[0..4]));
    b = b.wrapping_add(word(&tail[4..8]));
    c = c.wrapping_add(word(&tail[8..12]));
    // final
    c ^= b;
    c = c.wrapping_sub(b.rotate_left(14));
    a ^= c;
    a = a.wrapping_sub(c.rotate_left(11));
    b ^= a;
    b = b.wrapping_sub(a.rotate_left(25));
    c ^= b;
    c = c.wrapping_sub(b.rotate_left(16));
    a ^= c;
    a = a.wrapping_sub(c.rotate_left(4));
    b ^= a;
    b = b.wrapping_sub(a.rotate_left(14));
    c ^= b;
    c = c.wrapping_sub(b.rotate_left(24));
    c
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lookup3_matches_the_reference_vectors() {
        // From lookup3.c's driver5 (initial value 0).
        assert_eq!(lookup3(b""), 0xdead_beef);
        assert_eq!(lookup3(b"Four score and seven years ago"), 0x1777_0551);
    }

    /// Everything the writer makes, read back by `hdf5-pure`'s reader (h5py reads the robomimic
    /// exports in `tests/h5py_reads_robomimic.rs`): more links than fit libhdf5's default compact
    /// group, strings that overflow one heap collection and one larger than a collection.
    #[test]
    fn hdf5_pure_reads_back_what_it_wrote() {
        use hdf5_pure::AttrValue;
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("x.h5");
        let mut w = Writer::create(&path).unwrap();
        let mut data = Group::default();
        let big = "x".repeat(100_000);
        for i in 0..300u64 {
            let mut demo = Group::default();
            let mut obs = Group::default();
            let f: Vec<f32> = (0..6).map(|k| (i * 10 + k) as f32 * 0.5).collect();
            obs.link("pos", w.dataset(&[3, 2], &f).unwrap());
            demo.link("obs", w.group(obs).unwrap());
            let d: Vec<f64> = vec![i as f64, -1.5];
            demo.link("rewards", w.dataset(&[2], &d).unwrap());
            demo.link("dones", w.dataset(&[2], &[0u8, 1]).unwrap());
            demo.link("states", w.dataset(&[1, 2], &[i as i64, -7]).unwrap());
            demo.link("empty", w.dataset::<f32>(&[0, 4], &[]).unwrap());
            demo.attr("num_samples", Attr::I64(i as i64));
            demo.attr("score", Attr::F64(i as f64 / 4.0));
            demo.attr("model_file", Attr::Str(format!("<mujoco name=\"{i}\"/>{}", "é".repeat(1000))));
            if i == 150 {
                demo.attr("big", Attr::Str(big.clone()));
                demo.attr("blank", Attr::Str(String::new()));
            }
            data.link(&format!("demo_{i}"), w.group(demo).unwrap());
        }
        data.attr("total", Attr::I64(600));
        let mut root = Group::default();
        root.link("data", w.group(data).unwrap());
        let mut mask = Group::default();
        mask.link("train", w.ascii_strings(&["demo_0", "demo_10"]).unwrap());
        root.link("mask", w.group(mask).unwrap());
        w.finish(root).unwrap();

        let f = hdf5_pure::File::open(&path).unwrap();
        let data = f.group("data").unwrap();
        assert_eq!(data.groups().unwrap().len(), 300);
        assert_eq!(data.attrs().unwrap()["total"], AttrValue::I64(600));
        for i in [0u64, 9, 150, 299] {
            let p = format!("data/demo_{i}");
            let pos = f.dataset(&format!("{p}/obs/pos")).unwrap();
            assert_eq!(pos.shape().unwrap(), vec![3, 2]);
            let want: Vec<f32> = (0..6).map(|k| (i * 10 + k) as f32 * 0.5).collect();
            assert_eq!(pos.read_f32().unwrap(), want);
            assert_eq!(f.dataset(&format!("{p}/rewards")).unwrap().read_f64().unwrap(), vec![i as f64, -1.5]);
            assert_eq!(f.dataset(&format!("{p}/dones")).unwrap().read_u8().unwrap(), vec![0, 1]);
            assert_eq!(f.dataset(&format!("{p}/states")).unwrap().read_i64().unwrap(), vec![i as i64, -7]);
            assert_eq!(f.dataset(&format!("{p}/empty")).unwrap().shape().unwrap(), vec![0, 4]);
            let attrs = f.group(&p).unwrap().attrs().unwrap();
            assert_eq!(attrs["num_samples"], AttrValue::I64(i as i64));
            assert_eq!(attrs["score"], AttrValue::F64(i as f64 / 4.0));
            let model = format!("<mujoco name=\"{i}\"/>{}", "é".repeat(1000));
            assert_eq!(attrs["model_file"], AttrValue::VarLenString(model));
            if i == 150 {
                assert_eq!(attrs["big"], AttrValue::VarLenString(big.clone()));
                assert_eq!(attrs["blank"], AttrValue::VarLenString(String::new()));
            }
        }
        assert_eq!(f.dataset("mask/train").unwrap().read_string().unwrap(), vec!["demo_0", "demo_10"]);
    }

    #[test]
    fn what_the_format_cannot_hold_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let mut w = Writer::create(&dir.path().join("x.h5")).unwrap();
        let err = w.dataset(&[2, 3], &[1f32; 5]).unwrap_err();
        assert!(err.to_string().contains("shape [2, 3]"), "{err}");
        let err = w.dataset(&[1; 33], &[1u8]).unwrap_err();
        assert!(err.to_string().contains("rank 33"), "{err}");
        let err = w.ascii_strings(&["démo"]).unwrap_err();
        assert!(err.to_string().contains("not ASCII"), "{err}");
        let mut g = Group::default();
        g.attr("a\0b", Attr::I64(1));
        assert!(w.group(g).unwrap_err().to_string().contains("attribute name"));
        let mut g = Group::default();
        let at = w.dataset(&[1], &[1u8]).unwrap();
        g.link("actions", at);
        g.link("actions", at);
        assert!(w.group(g).unwrap_err().to_string().contains("two links named \"actions\""));
        // A streamed dataset takes exactly its shape's values, and a scalar attribute one string.
        let mut d = w.stream::<i16>(&[2, 2]).unwrap();
        d.write(&[1, 2, 3]).unwrap();
        let err = d.write(&[4, 5]).unwrap_err();
        assert!(err.to_string().contains("5 values do not fit a dataset of shape [2, 2]"), "{err}");
        let err = d.finish().unwrap_err();
        assert!(err.to_string().contains("3 values do not fill"), "{err}");
        let mut d = w.stream::<u8>(&[1]).unwrap();
        d.write(&[1]).unwrap();
        d.attr(
            "two",
            Attr::Strings { values: vec!["a".into(), "b".into()], array: false, kind: StrKind::VarUtf8 },
        );
        assert!(d.finish().unwrap_err().to_string().contains("2 strings for a scalar"));
    }
}
