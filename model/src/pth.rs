//! Reading PyTorch `torch.save` files (the zip format since PyTorch 1.6) without Python: a zip
//! archive holding `*/data.pkl` (the pickled object, tensors as persistent references to storages)
//! and one `*/data/<key>` entry per storage. Written by hand because no maintained crate reads
//! PyTorch pickles (serde-pickle has no persistent ids); only the opcodes `torch.save` of a state
//! dict emits are supported, anything else is an error naming the opcode.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::Read;
use std::path::Path;

use tch::{Kind, Tensor};

use crate::weights::{TensorSource, WeightsError};

// Every value the pickle holds is kept whole, though only dicts, tensors and storages are used.
#[allow(dead_code)]
#[derive(Debug, Clone)]
enum Value {
    None,
    Bool(bool),
    Int(i64),
    Float(f64),
    Str(String),
    Tuple(Vec<Value>),
    List(Vec<Value>),
    Dict(Vec<(Value, Value)>),
    Global(String),
    /// A callable applied to arguments that this reader does not evaluate further.
    Call(String, Vec<Value>),
    Storage { key: String, kind: Kind },
    Tensor { storage: Box<Value>, offset: i64, size: Vec<i64>, stride: Vec<i64> },
    Mark,
}

fn err(path: &Path, message: impl std::fmt::Display) -> WeightsError {
    WeightsError::File { file: path.display().to_string(), message: message.to_string() }
}

fn storage_kind(class: &str) -> Option<Kind> {
    Some(match class.rsplit('.').next()? {
        "FloatStorage" => Kind::Float,
        "DoubleStorage" => Kind::Double,
        "HalfStorage" => Kind::Half,
        "BFloat16Storage" => Kind::BFloat16,
        "LongStorage" => Kind::Int64,
        "IntStorage" => Kind::Int,
        "ShortStorage" => Kind::Int16,
        "CharStorage" => Kind::Int8,
        "ByteStorage" => Kind::Uint8,
        "BoolStorage" => Kind::Bool,
        _ => return None,
    })
}

fn ints(v: &Value) -> Option<Vec<i64>> {
    match v {
        Value::Tuple(items) | Value::List(items) => {
            items.iter().map(|i| if let Value::Int(n) = i { Some(*n) } else { None }).collect()
        }
        _ => None,
    }
}

struct Unpickler<'a> {
    data: &'a [u8],
    pos: usize,
    stack: Vec<Value>,
    memo: BTreeMap<u64, Value>,
    path: &'a Path,
}

impl<'a> Unpickler<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], WeightsError> {
        let end = self.pos.checked_add(n).filter(|&e| e <= self.data.len());
        let end = end.ok_or_else(|| err(self.path, "data.pkl ends in the middle of an opcode"))?;
        let s = &self.data[self.pos..end];
        self.pos = end;
        Ok(s)
    }

    fn u8(&mut self) -> Result<u8, WeightsError> {
        Ok(self.take(1)?[0])
    }

    fn u32(&mut self) -> Result<u32, WeightsError> {
        Ok(u32::from_le_bytes(self.take(4)?.try_into().unwrap()))
    }

    fn line(&mut self) -> Result<String, WeightsError> {
        let rest = &self.data[self.pos..];
        let n = rest.iter().position(|&b| b == b'\n').ok_or_else(|| err(self.path, "unterminated GLOBAL"))?;
        let s = String::from_utf8_lossy(&rest[..n]).into_owned();
        self.pos += n + 1;
        Ok(s)
    }

    fn pop(&mut self) -> Result<Value, WeightsError> {
        self.stack.pop().ok_or_else(|| err(self.path, "pickle stack underflow"))
    }

    fn pop_mark(&mut self) -> Result<Vec<Value>, WeightsError> {
        let at = self.stack.iter().rposition(|v| matches!(v, Value::Mark)).ok_or_else(|| err(self.path, "no MARK"))?;
        let items = self.stack.split_off(at + 1);
        self.stack.pop();
        Ok(items)
    }

    fn str(&mut self, n: usize) -> Result<(), WeightsError> {
        let s = String::from_utf8_lossy(self.take(n)?).into_owned();
        self.stack.push(Value::Str(s));
        Ok(())
    }

    fn reduce(&self, func: Value, args: Value) -> Result<Value, WeightsError> {
        let Value::Global(name) = func else { return Ok(Value::Call("?".into(), vec![func, args])) };
        let args = match args {
            Value::Tuple(a) => a,
            other => vec![other],
        };
        Ok(match name.as_str() {
            "collections.OrderedDict" | "builtins.dict" => Value::Dict(Vec::new()),
            "torch._utils._rebuild_tensor_v2" | "torch._utils._rebuild_tensor" => {
                let bad = || err(self.path, format!("unexpected arguments to {name}"));
                let storage = args.first().cloned().ok_or_else(bad)?;
                let offset = match args.get(1) {
                    Some(Value::Int(o)) => *o,
                    _ => return Err(bad()),
                };
                let size = args.get(2).and_then(ints).ok_or_else(bad)?;
                let stride = args.get(3).and_then(ints).ok_or_else(bad)?;
                Value::Tensor { storage: Box::new(storage), offset, size, stride }
            }
            _ => Value::Call(name, args),
        })
    }

    fn run(mut self) -> Result<Value, WeightsError> {
        loop {
            let op = self.u8()?;
            match op {
                0x80 => {
                    self.u8()?; // PROTO
                }
                0x95 => {
                    self.take(8)?; // FRAME
                }
                b'c' => {
                    let (module, name) = (self.line()?, self.line()?);
                    self.stack.push(Value::Global(format!("{module}.{name}")));
                }
                0x93 => {
                    // STACK_GLOBAL
                    let (name, module) = (self.pop()?, self.pop()?);
                    match (module, name) {
                        (Value::Str(m), Value::Str(n)) => self.stack.push(Value::Global(format!("{m}.{n}"))),
                        _ => return Err(err(self.path, "STACK_GLOBAL on non-strings")),
                    }
                }
                b'q' => {
                    let i = self.u8()? as u64;
                    self.memo.insert(i, self.stack.last().cloned().unwrap_or(Value::None));
                }
                b'r' => {
                    let i = self.u32()? as u64;
                    self.memo.insert(i, self.stack.last().cloned().unwrap_or(Value::None));
                }
                0x94 => {
                    let i = self.memo.len() as u64;
                    self.memo.insert(i, self.stack.last().cloned().unwrap_or(Value::None));
                }
                b'h' | b'j' => {
                    let i = if op == b'h' { self.u8()? as u64 } else { self.u32()? as u64 };
                    let v = self.memo.get(&i).cloned().ok_or_else(|| err(self.path, format!("memo {i} unset")))?;
                    self.stack.push(v);
                }
                b'}' => self.stack.push(Value::Dict(Vec::new())),
                b']' => self.stack.push(Value::List(Vec::new())),
                b')' => self.stack.push(Value::Tuple(Vec::new())),
                b'(' => self.stack.push(Value::Mark),
                b't' => {
                    let items = self.pop_mark()?;
                    self.stack.push(Value::Tuple(items));
                }
                0x85..=0x87 => {
                    let n = (op - 0x84) as usize;
                    let at = self.stack.len().checked_sub(n).ok_or_else(|| err(self.path, "pickle stack underflow"))?;
                    let items = self.stack.split_off(at);
                    self.stack.push(Value::Tuple(items));
                }
                b'X' => {
                    let n = self.u32()? as usize;
                    self.str(n)?;
                }
                0x8c => {
                    let n = self.u8()? as usize;
                    self.str(n)?;
                }
                0x8d => {
                    let n = u64::from_le_bytes(self.take(8)?.try_into().unwrap()) as usize;
                    self.str(n)?;
                }
                b'J' => {
                    let v = i32::from_le_bytes(self.take(4)?.try_into().unwrap());
                    self.stack.push(Value::Int(v as i64));
                }
                b'K' => {
                    let v = self.u8()?;
                    self.stack.push(Value::Int(v as i64));
                }
                b'M' => {
                    let v = u16::from_le_bytes(self.take(2)?.try_into().unwrap());
                    self.stack.push(Value::Int(v as i64));
                }
                0x8a => {
                    let n = self.u8()? as usize;
                    let bytes = self.take(n)?;
                    let mut buf = [if bytes.last().is_some_and(|b| b & 0x80 != 0) { 0xff } else { 0 }; 8];
                    buf[..n.min(8)].copy_from_slice(&bytes[..n.min(8)]);
                    self.stack.push(Value::Int(i64::from_le_bytes(buf)));
                }
                b'G' => {
                    let v = f64::from_be_bytes(self.take(8)?.try_into().unwrap());
                    self.stack.push(Value::Float(v));
                }
                0x88 => self.stack.push(Value::Bool(true)),
                0x89 => self.stack.push(Value::Bool(false)),
                b'N' => self.stack.push(Value::None),
                b'R' | 0x81 => {
                    let (args, func) = (self.pop()?, self.pop()?);
                    let v = self.reduce(func, args)?;
                    self.stack.push(v);
                }
                b'b' => {
                    self.pop()?; // BUILD: state of objects this reader keeps opaque
                }
                b's' => {
                    let (v, k) = (self.pop()?, self.pop()?);
                    if let Some(Value::Dict(d)) = self.stack.last_mut() {
                        d.push((k, v));
                    }
                }
                b'u' => {
                    let items = self.pop_mark()?;
                    if let Some(Value::Dict(d)) = self.stack.last_mut() {
                        let mut it = items.into_iter();
                        while let (Some(k), Some(v)) = (it.next(), it.next()) {
                            d.push((k, v));
                        }
                    }
                }
                b'a' => {
                    let v = self.pop()?;
                    if let Some(Value::List(l)) = self.stack.last_mut() {
                        l.push(v);
                    }
                }
                b'e' => {
                    let items = self.pop_mark()?;
                    if let Some(Value::List(l)) = self.stack.last_mut() {
                        l.extend(items);
                    }
                }
                b'Q' => {
                    // BINPERSID: ('storage', <class>, key, location, numel)
                    let pid = self.pop()?;
                    let Value::Tuple(t) = pid else { return Err(err(self.path, "persistent id is not a tuple")) };
                    let (class, key) = match (t.get(1), t.get(2)) {
                        (Some(Value::Global(c)), Some(Value::Str(k))) => (c.clone(), k.clone()),
                        _ => return Err(err(self.path, "persistent id is not a storage reference")),
                    };
                    let kind =
                        storage_kind(&class).ok_or_else(|| err(self.path, format!("unsupported storage type {class}")))?;
                    self.stack.push(Value::Storage { key, kind });
                }
                b'.' => return self.pop(),
                other => return Err(err(self.path, format!("unsupported pickle opcode 0x{other:02x} at byte {}", self.pos - 1))),
            }
        }
    }
}

/// The view of `storage` (1-D) with `size` and `stride` at `offset`, made contiguous. What no
/// `torch.save` writes (a negative offset, size or stride; sizes and strides that do not pair up)
/// and a view reaching past the storage are errors, checked here because libtorch's `as_strided`
/// throws on them (tch turns that into a panic).
fn strided_view(storage: &Tensor, size: &[i64], stride: &[i64], offset: i64) -> Result<Tensor, String> {
    if size.len() != stride.len() {
        return Err(format!("has {} sizes and {} strides", size.len(), stride.len()));
    }
    if offset < 0 {
        return Err(format!("has a negative storage offset ({offset})"));
    }
    if size.iter().chain(stride).any(|&v| v < 0) {
        return Err(format!("has a negative size or stride (size {size:?}, stride {stride:?})"));
    }
    if size.iter().all(|&s| s > 0) {
        // One past the view's last element, in exact arithmetic.
        let end = size.iter().zip(stride).try_fold(offset, |at, (&s, &st)| (s - 1).checked_mul(st).and_then(|d| at.checked_add(d))).and_then(|at| at.checked_add(1));
        if end.is_none_or(|end| end > storage.numel() as i64) {
            return Err("reaches past the end of its storage (truncated file?)".into());
        }
    }
    storage.f_as_strided(size, stride, offset).and_then(|t| t.f_contiguous()).map_err(|e| format!("is not a view of its storage: {e}"))
}

/// All tensors of a `torch.save`d state dict, loaded into memory (described by the file's path).
pub fn open(path: impl AsRef<Path>) -> Result<TensorSource, WeightsError> {
    let path = path.as_ref();
    let file = File::open(path).map_err(|e| err(path, e))?;
    let mut zip = zip::ZipArchive::new(file)
        .map_err(|e| err(path, format!("not a PyTorch zip archive ({e}); legacy pre-1.6 .pth files are not supported")))?;
    let pkl_name = (0..zip.len())
        .filter_map(|i| zip.name_for_index(i).and_then(|n| n.ok()).map(|n| n.to_string()))
        .find(|n| n.ends_with("/data.pkl") || n == "data.pkl")
        .ok_or_else(|| err(path, "no data.pkl in the archive"))?;
    let prefix = pkl_name.trim_end_matches("data.pkl").to_string();
    let mut pkl = Vec::new();
    zip.by_name(&pkl_name).map_err(|e| err(path, e))?.read_to_end(&mut pkl).map_err(|e| err(path, e))?;
    if let Ok(mut order) = zip.by_name(&format!("{prefix}byteorder")) {
        let mut s = String::new();
        order.read_to_string(&mut s).map_err(|e| err(path, e))?;
        if s.trim() != "little" {
            return Err(err(path, format!("byte order '{}' is not supported", s.trim())));
        }
    }
    let root = Unpickler { data: &pkl, pos: 0, stack: Vec::new(), memo: BTreeMap::new(), path }.run()?;
    let mut dict = match root {
        Value::Dict(d) => d,
        _ => return Err(err(path, "the pickled object is not a dict (expected a state dict)")),
    };
    // Checkpoints that wrap the state dict: {"state_dict": {...}} or {"model_state": {...}}.
    if let Some((_, Value::Dict(inner))) = dict
        .iter()
        .find(|(k, v)| matches!(k, Value::Str(s) if s == "state_dict" || s == "model_state") && matches!(v, Value::Dict(_)))
    {
        dict = inner.clone();
    }
    let mut storages: BTreeMap<String, Tensor> = BTreeMap::new();
    let mut tensors = BTreeMap::new();
    for (k, v) in dict {
        let (Value::Str(name), Value::Tensor { storage, offset, size, stride }) = (k, v) else { continue };
        let Value::Storage { key, kind } = *storage else {
            return Err(err(path, format!("tensor '{name}' has no storage reference")));
        };
        if !storages.contains_key(&key) {
            let entry = format!("{prefix}data/{key}");
            let mut bytes = Vec::new();
            zip.by_name(&entry)
                .map_err(|e| err(path, format!("storage {entry} of '{name}': {e}")))?
                .read_to_end(&mut bytes)
                .map_err(|e| err(path, format!("storage {entry} of '{name}': {e}")))?;
            let numel = (bytes.len() / kind.elt_size_in_bytes()) as i64;
            let t = Tensor::f_from_data_size(&bytes, &[numel], kind).map_err(|e| err(path, e))?;
            storages.insert(key.clone(), t);
        }
        let t = strided_view(&storages[&key], &size, &stride, offset).map_err(|m| err(path, format!("tensor '{name}' {m}")))?;
        tensors.insert(name, t);
    }
    if tensors.is_empty() {
        return Err(err(path, "the state dict holds no tensors"));
    }
    Ok(TensorSource::new(tensors, path.display().to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    /// A `.pth` archive as `torch.save` lays it out, holding one float tensor "w" that views a
    /// storage of the four values 0, 1, 2, 3 at `offset` with `size` and `stride`.
    fn one_view_pth(path: &Path, offset: i32, size: &[u8], stride: &[i32]) {
        let mut pkl: Vec<u8> = vec![0x80, 2, b'}'];
        let unicode = |p: &mut Vec<u8>, s: &str| {
            p.push(b'X');
            p.extend((s.len() as u32).to_le_bytes());
            p.extend(s.as_bytes());
        };
        unicode(&mut pkl, "w");
        pkl.extend(b"ctorch._utils\n_rebuild_tensor_v2\n(");
        // The storage: a persistent id ('storage', FloatStorage, key, location, numel).
        pkl.push(b'(');
        unicode(&mut pkl, "storage");
        pkl.extend(b"ctorch\nFloatStorage\n");
        unicode(&mut pkl, "0");
        unicode(&mut pkl, "cpu");
        pkl.extend([b'K', 4, b't', b'Q', b'J']);
        pkl.extend(offset.to_le_bytes());
        pkl.push(b'(');
        for &s in size {
            pkl.extend([b'K', s]);
        }
        pkl.push(b't');
        pkl.push(b'(');
        for &s in stride {
            pkl.push(b'J');
            pkl.extend(s.to_le_bytes());
        }
        pkl.push(b't');
        pkl.push(0x89);
        pkl.extend(b"ccollections\nOrderedDict\n)R");
        pkl.extend(b"tRs.");
        let mut zip = zip::ZipWriter::new(File::create(path).unwrap());
        let stored = zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
        zip.start_file("archive/data.pkl", stored).unwrap();
        zip.write_all(&pkl).unwrap();
        zip.start_file("archive/data/0", stored).unwrap();
        zip.write_all(&[0f32, 1.0, 2.0, 3.0].iter().flat_map(|v| v.to_le_bytes()).collect::<Vec<u8>>()).unwrap();
        zip.finish().unwrap();
    }

    #[test]
    fn views_outside_their_storage_are_errors_not_panics() {
        let dir = bwm_testdir::TestDir::new("pth-views");
        let path = dir.join("w.pth");
        one_view_pth(&path, 1, &[2], &[2]);
        let source = open(&path).unwrap();
        assert_eq!(Vec::<f32>::try_from(&source.tensors()["w"]).unwrap(), [1.0, 3.0]);
        for (offset, size, stride, says) in [
            (-1, &[2u8][..], &[1][..], "offset"),
            (3, &[4], &[-1], "stride"),
            (0, &[2, 2], &[1], "stride"),
            (2, &[2], &[2], "past the end"),
            (0, &[2], &[i32::MAX], "past the end"),
        ] {
            one_view_pth(&path, offset, size, stride);
            let e = open(&path).err().unwrap_or_else(|| panic!("offset {offset}, size {size:?}, stride {stride:?}: accepted")).to_string();
            assert!(e.contains("'w'") && e.contains(says), "offset {offset}, size {size:?}, stride {stride:?}: {e}");
        }
    }
}
