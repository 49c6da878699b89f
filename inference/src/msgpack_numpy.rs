//! openpi's msgpack-numpy encoding (`openpi_client/msgpack_numpy.py`), shared by the policy
//! client of `bwm evaluate` and the HTTP API of `bwm serve`: a numpy array travels as the map
//! `{b"__ndarray__": true, b"data": <raw C-order bytes>, b"dtype": "<f4", b"shape": [..]}` whose
//! marker keys are msgpack bin values (Python bytes), while ordinary dict keys are str. A numpy
//! scalar travels as `{b"__npgeneric__": true, b"data": <scalar>, b"dtype": ..}`.

use anyhow::{bail, ensure, Context, Result};
use rmpv::Value;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Dtype {
    Bool,
    U8,
    I8,
    U16,
    I16,
    U32,
    I32,
    U64,
    I64,
    F16,
    F32,
    F64,
}

impl Dtype {
    /// numpy's `dtype.str` (little-endian where the size is above one byte).
    pub fn numpy_str(self) -> &'static str {
        match self {
            Dtype::Bool => "|b1",
            Dtype::U8 => "|u1",
            Dtype::I8 => "|i1",
            Dtype::U16 => "<u2",
            Dtype::I16 => "<i2",
            Dtype::U32 => "<u4",
            Dtype::I32 => "<i4",
            Dtype::U64 => "<u8",
            Dtype::I64 => "<i8",
            Dtype::F16 => "<f2",
            Dtype::F32 => "<f4",
            Dtype::F64 => "<f8",
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Dtype::Bool => "bool",
            Dtype::U8 => "uint8",
            Dtype::I8 => "int8",
            Dtype::U16 => "uint16",
            Dtype::I16 => "int16",
            Dtype::U32 => "uint32",
            Dtype::I32 => "int32",
            Dtype::U64 => "uint64",
            Dtype::I64 => "int64",
            Dtype::F16 => "float16",
            Dtype::F32 => "float32",
            Dtype::F64 => "float64",
        }
    }

    pub fn size(self) -> usize {
        match self {
            Dtype::Bool | Dtype::U8 | Dtype::I8 => 1,
            Dtype::U16 | Dtype::I16 | Dtype::F16 => 2,
            Dtype::U32 | Dtype::I32 | Dtype::F32 => 4,
            Dtype::U64 | Dtype::I64 | Dtype::F64 => 8,
        }
    }

    /// Parses a numpy `dtype.str` such as `<f4` or `|u1` (`=` counts as little-endian, the byte
    /// order of every machine this runs on).
    pub fn parse(s: &str) -> Result<Self> {
        let (order, code) = match s.chars().next() {
            Some(c @ ('<' | '>' | '|' | '=')) => (c, &s[1..]),
            _ => ('=', s),
        };
        let dtype = match code {
            "b1" => Dtype::Bool,
            "u1" => Dtype::U8,
            "i1" => Dtype::I8,
            "u2" => Dtype::U16,
            "i2" => Dtype::I16,
            "u4" => Dtype::U32,
            "i4" => Dtype::I32,
            "u8" => Dtype::U64,
            "i8" => Dtype::I64,
            "f2" => Dtype::F16,
            "f4" => Dtype::F32,
            "f8" => Dtype::F64,
            _ => {
                bail!("unsupported numpy dtype '{s}' (supported: bool, u/int8..64, float16/32/64)")
            }
        };
        ensure!(
            order != '>' || dtype.size() == 1,
            "big-endian numpy dtype '{s}' is not supported; send little-endian ('<') arrays"
        );
        Ok(dtype)
    }
}

/// A numpy array: dtype, shape and its C-order little-endian bytes.
#[derive(Debug, Clone, PartialEq)]
pub struct NdArray {
    pub dtype: Dtype,
    pub shape: Vec<usize>,
    pub data: Vec<u8>,
}

impl NdArray {
    pub fn new(dtype: Dtype, shape: Vec<usize>, data: Vec<u8>) -> Result<Self> {
        let elements = shape
            .iter()
            .try_fold(1usize, |acc, &d| acc.checked_mul(d))
            .context("array shape overflows")?;
        let bytes = elements
            .checked_mul(dtype.size())
            .context("array size overflows")?;
        ensure!(
            data.len() == bytes,
            "{} array of shape {shape:?} needs {bytes} data bytes, got {}",
            dtype.name(),
            data.len()
        );
        Ok(Self { dtype, shape, data })
    }

    pub fn from_u8(shape: Vec<usize>, data: Vec<u8>) -> Result<Self> {
        Self::new(Dtype::U8, shape, data)
    }

    pub fn from_f32(shape: Vec<usize>, values: &[f32]) -> Result<Self> {
        Self::new(
            Dtype::F32,
            shape,
            values.iter().flat_map(|v| v.to_le_bytes()).collect(),
        )
    }

    /// "float32 (4, 14)", as numpy would print dtype and shape.
    pub fn describe(&self) -> String {
        let dims: Vec<String> = self.shape.iter().map(|d| d.to_string()).collect();
        let shape = if dims.len() == 1 {
            format!("({},)", dims[0])
        } else {
            format!("({})", dims.join(", "))
        };
        format!("{} {shape}", self.dtype.name())
    }

    /// The values as f32, converted from any numeric dtype (bool as 0/1).
    pub fn to_f32(&self) -> Vec<f32> {
        let n = self.dtype.size();
        self.data
            .chunks_exact(n)
            .map(|b| match self.dtype {
                Dtype::Bool => f32::from(u8::from(b[0] != 0)),
                Dtype::U8 => f32::from(b[0]),
                Dtype::I8 => f32::from(b[0] as i8),
                Dtype::U16 => f32::from(u16::from_le_bytes([b[0], b[1]])),
                Dtype::I16 => f32::from(i16::from_le_bytes([b[0], b[1]])),
                Dtype::U32 => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f32,
                Dtype::I32 => i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f32,
                Dtype::U64 => u64::from_le_bytes(b.try_into().unwrap_or_default()) as f32,
                Dtype::I64 => i64::from_le_bytes(b.try_into().unwrap_or_default()) as f32,
                Dtype::F16 => half::f16::from_le_bytes([b[0], b[1]]).to_f32(),
                Dtype::F32 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]),
                Dtype::F64 => f64::from_le_bytes(b.try_into().unwrap_or_default()) as f32,
            })
            .collect()
    }

    /// The msgpack-numpy map, keys in the order openpi's `pack_array` writes them.
    pub fn to_value(&self) -> Value {
        Value::Map(vec![
            (Value::Binary(b"__ndarray__".to_vec()), Value::Boolean(true)),
            (
                Value::Binary(b"data".to_vec()),
                Value::Binary(self.data.clone()),
            ),
            (
                Value::Binary(b"dtype".to_vec()),
                Value::from(self.dtype.numpy_str()),
            ),
            (
                Value::Binary(b"shape".to_vec()),
                Value::Array(self.shape.iter().map(|&d| Value::from(d as u64)).collect()),
            ),
        ])
    }

    /// The array a msgpack-numpy map describes; None when `v` is not such a map.
    pub fn from_value(v: &Value) -> Option<Result<Self>> {
        map_get(v, "__ndarray__")?;
        Some((|| {
            let dtype = map_get(v, "dtype")
                .and_then(Value::as_str)
                .context("ndarray without a 'dtype' string")?;
            let dtype = Dtype::parse(dtype)?;
            let shape = map_get(v, "shape")
                .and_then(Value::as_array)
                .context("ndarray without a 'shape' list")?;
            let shape = shape
                .iter()
                .map(|d| {
                    d.as_u64()
                        .and_then(|d| usize::try_from(d).ok())
                        .context("ndarray shape entries must be non-negative integers")
                })
                .collect::<Result<Vec<_>>>()?;
            let data = match map_get(v, "data") {
                Some(Value::Binary(b)) => b.clone(),
                _ => bail!("ndarray without binary 'data'"),
            };
            Self::new(dtype, shape, data)
        })())
    }
}

/// The value of `key` in a msgpack map, whether the key was written as str or as bin.
pub fn map_get<'a>(v: &'a Value, key: &str) -> Option<&'a Value> {
    v.as_map()?.iter().find_map(|(k, val)| {
        let matches = match k {
            Value::String(s) => s.as_str() == Some(key),
            Value::Binary(b) => b.as_slice() == key.as_bytes(),
            _ => false,
        };
        matches.then_some(val)
    })
}

/// The Python scalar inside a numpy-scalar map (`__npgeneric__`), else `v` itself.
pub fn scalar(v: &Value) -> &Value {
    match map_get(v, "__npgeneric__") {
        Some(_) => map_get(v, "data").unwrap_or(v),
        None => v,
    }
}

/// The array under `key` of a map: missing keys and non-arrays are errors naming the key.
pub fn array_at(v: &Value, key: &str) -> Result<NdArray> {
    let field = map_get(v, key).with_context(|| format!("no '{key}' entry"))?;
    NdArray::from_value(field)
        .with_context(|| {
            format!("'{key}' is not a numpy array (msgpack-numpy map with b\"__ndarray__\")")
        })?
        .with_context(|| format!("'{key}'"))
}

/// A map with str keys (a Python dict with str keys).
pub fn str_map(entries: Vec<(&str, Value)>) -> Value {
    Value::Map(
        entries
            .into_iter()
            .map(|(k, v)| (Value::from(k), v))
            .collect(),
    )
}

/// Sets `path` (one key per nesting level) in a str-keyed map, creating inner maps as needed.
pub fn insert_path(map: &mut Value, path: &[String], value: Value) -> Result<()> {
    let Some((first, rest)) = path.split_first() else {
        bail!("empty key path")
    };
    let Value::Map(entries) = map else {
        bail!("cannot set '{first}': the parent is not a map")
    };
    let pos = entries
        .iter()
        .position(|(k, _)| k.as_str() == Some(first.as_str()));
    if rest.is_empty() {
        match pos {
            Some(i) => entries[i].1 = value,
            None => entries.push((Value::from(first.as_str()), value)),
        }
        return Ok(());
    }
    let i = match pos {
        Some(i) => i,
        None => {
            entries.push((Value::from(first.as_str()), Value::Map(Vec::new())));
            entries.len() - 1
        }
    };
    insert_path(&mut entries[i].1, rest, value).with_context(|| format!("under '{first}'"))
}

/// The value at `path` of nested maps.
pub fn get_path<'a>(v: &'a Value, path: &[String]) -> Option<&'a Value> {
    path.iter().try_fold(v, |node, key| map_get(node, key))
}

pub fn encode(v: &Value) -> Vec<u8> {
    let mut out = Vec::new();
    // Writing into a Vec cannot fail.
    let _ = rmpv::encode::write_value(&mut out, v);
    out
}

/// Decodes exactly one msgpack value filling `bytes`.
pub fn decode(bytes: &[u8]) -> Result<Value> {
    let mut rd = bytes;
    let v =
        rmpv::decode::read_value(&mut rd).map_err(|e| anyhow::anyhow!("not valid msgpack: {e}"))?;
    ensure!(
        rd.is_empty(),
        "not valid msgpack: {} bytes follow the first value",
        rd.len()
    );
    Ok(v)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hex(bytes: &[u8]) -> String {
        bytes.iter().map(|b| format!("{b:02x}")).collect()
    }

    /// Bytes from openpi_client 0.1.2:
    /// `packb({'a': np.arange(3, dtype=np.float32), 'b': np.zeros((1, 2), np.uint8), 's': np.float64(2.5)})`.
    const OPENPI: &str = "83a16184c40b5f5f6e6461727261795f5fc3c40464617461c40c000000000000803f00000040c4056474797065a33c6634c40573686170659103a16284c40b5f5f6e6461727261795f5fc3c40464617461c4020000c4056474797065a37c7531c4057368617065920102a173cb4004000000000000";

    #[test]
    fn encodes_byte_for_byte_as_openpi() {
        let v = str_map(vec![
            (
                "a",
                NdArray::from_f32(vec![3], &[0.0, 1.0, 2.0])
                    .unwrap()
                    .to_value(),
            ),
            (
                "b",
                NdArray::from_u8(vec![1, 2], vec![0, 0]).unwrap().to_value(),
            ),
            ("s", Value::F64(2.5)),
        ]);
        assert_eq!(hex(&encode(&v)), OPENPI);
    }

    #[test]
    fn decodes_openpi_bytes() {
        let bytes: Vec<u8> = (0..OPENPI.len())
            .step_by(2)
            .map(|i| u8::from_str_radix(&OPENPI[i..i + 2], 16).unwrap())
            .collect();
        let v = decode(&bytes).unwrap();
        let a = array_at(&v, "a").unwrap();
        assert_eq!(
            (a.dtype, a.shape.clone(), a.to_f32()),
            (Dtype::F32, vec![3], vec![0.0, 1.0, 2.0])
        );
        assert_eq!(a.describe(), "float32 (3,)");
        let b = array_at(&v, "b").unwrap();
        assert_eq!((b.dtype, b.shape.clone()), (Dtype::U8, vec![1, 2]));
        assert_eq!(map_get(&v, "s").and_then(Value::as_f64), Some(2.5));
        assert!(array_at(&v, "s")
            .unwrap_err()
            .to_string()
            .contains("not a numpy array"));
        assert!(array_at(&v, "zz")
            .unwrap_err()
            .to_string()
            .contains("no 'zz'"));
    }

    #[test]
    fn rejects_bad_input_with_messages() {
        assert!(decode(&[0xa5, b'a']).is_err(), "truncated str");
        assert!(decode(&[0x91]).is_err(), "truncated array");
        assert!(decode(&[0x01, 0x02])
            .unwrap_err()
            .to_string()
            .contains("follow"));
        let short = NdArray {
            dtype: Dtype::F32,
            shape: vec![2],
            data: vec![0; 4],
        }
        .to_value();
        let err = NdArray::from_value(&short)
            .unwrap()
            .unwrap_err()
            .to_string();
        assert!(err.contains("needs 8 data bytes, got 4"), "{err}");
        assert!(
            Dtype::parse(">f4").is_err()
                && Dtype::parse("O").is_err()
                && Dtype::parse("<c8").is_err()
        );
        assert_eq!(Dtype::parse("|u1").unwrap(), Dtype::U8);
        let huge = NdArray::new(Dtype::F64, vec![usize::MAX, 4], vec![]);
        assert!(huge.is_err());
    }

    #[test]
    fn nested_paths_and_numpy_scalars() {
        let mut m = str_map(vec![]);
        insert_path(
            &mut m,
            &["images".into(), "cam_high".into()],
            Value::from(1),
        )
        .unwrap();
        insert_path(&mut m, &["images".into(), "cam_low".into()], Value::from(2)).unwrap();
        insert_path(&mut m, &["prompt".into()], Value::from("x")).unwrap();
        assert_eq!(
            get_path(&m, &["images".into(), "cam_low".into()]).and_then(Value::as_i64),
            Some(2)
        );
        assert_eq!(m.as_map().unwrap().len(), 2);
        let g = Value::Map(vec![
            (
                Value::Binary(b"__npgeneric__".to_vec()),
                Value::Boolean(true),
            ),
            (Value::Binary(b"data".to_vec()), Value::from(7)),
            (Value::Binary(b"dtype".to_vec()), Value::from("<i8")),
        ]);
        assert_eq!(scalar(&g).as_i64(), Some(7));
        let f16 = NdArray::new(
            Dtype::F16,
            vec![1],
            half::f16::from_f32(1.5).to_le_bytes().to_vec(),
        )
        .unwrap();
        assert_eq!(f16.to_f32(), vec![1.5]);
    }
}
