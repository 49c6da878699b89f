//! Reading tensors by name from safetensors files: one file, or shards listed by a
//! `*.safetensors.index.json`. Files are memory-mapped; each tensor is copied out and cast when a
//! module asks for it.

use std::collections::BTreeMap;
use std::fs::File;
use std::path::{Path, PathBuf};

use memmap2::Mmap;
use safetensors::tensor::{Dtype, SafeTensors};
use tch::{Device, Kind, Tensor};

/// Weight loading errors: each is one line that names the file and the key.
#[derive(Debug, thiserror::Error)]
pub enum WeightsError {
    #[error("{file}: missing key '{key}' (expected shape {expected:?})")]
    Missing { file: String, key: String, expected: Vec<i64> },
    #[error("{file}: unexpected key '{key}' (no module of this model has that name)")]
    Unexpected { file: String, key: String },
    #[error("{file}: key '{key}' has shape {found:?}, expected {expected:?}")]
    Shape { file: String, key: String, found: Vec<i64>, expected: Vec<i64> },
    #[error("{file}: key '{key}' has unsupported dtype {dtype}")]
    Dtype { file: String, key: String, dtype: String },
    #[error("{file}: {message}")]
    File { file: String, message: String },
}

impl WeightsError {
    /// A key the model asked for that the file does not hold.
    pub fn missing(file: String, key: &str) -> Self {
        WeightsError::Missing { file, key: key.to_string(), expected: vec![] }
    }
}

/// Anything tensors can be read from by checkpoint name.
pub trait WeightSource {
    /// Names the file(s), for error messages.
    fn describe(&self) -> String;
    fn names(&self) -> Vec<String>;
    fn shape(&self, name: &str) -> Option<Vec<i64>>;
    fn load(&self, name: &str, kind: Kind, device: Device) -> Result<Tensor, WeightsError>;
}

/// Tensors held in memory (a model's parameters, a `.pth` file's state dict, test data).
pub struct TensorSource {
    tensors: BTreeMap<String, Tensor>,
    description: String,
}

impl TensorSource {
    pub fn new(tensors: impl IntoIterator<Item = (String, Tensor)>, description: impl Into<String>) -> Self {
        Self { tensors: tensors.into_iter().collect(), description: description.into() }
    }

    pub fn tensors(&self) -> &BTreeMap<String, Tensor> {
        &self.tensors
    }
}

impl WeightSource for TensorSource {
    fn describe(&self) -> String {
        self.description.clone()
    }
    fn names(&self) -> Vec<String> {
        self.tensors.keys().cloned().collect()
    }
    fn shape(&self, name: &str) -> Option<Vec<i64>> {
        self.tensors.get(name).map(|t| t.size())
    }
    fn load(&self, name: &str, kind: Kind, device: Device) -> Result<Tensor, WeightsError> {
        let t = self.tensors.get(name).ok_or_else(|| WeightsError::missing(self.describe(), name))?;
        Ok(t.to_device(device).to_kind(kind))
    }
}

struct Entry {
    file: usize,
    dtype: Dtype,
    shape: Vec<i64>,
}

/// Safetensors file(s), memory-mapped.
pub struct SafetensorsSource {
    files: Vec<(PathBuf, Mmap)>,
    entries: BTreeMap<String, Entry>,
    description: String,
}

fn file_error(path: &Path, message: impl std::fmt::Display) -> WeightsError {
    WeightsError::File { file: path.display().to_string(), message: message.to_string() }
}

fn kind_of(dtype: Dtype) -> Option<Kind> {
    Some(match dtype {
        Dtype::F64 => Kind::Double,
        Dtype::F32 => Kind::Float,
        Dtype::F16 => Kind::Half,
        Dtype::BF16 => Kind::BFloat16,
        Dtype::I64 => Kind::Int64,
        Dtype::I32 => Kind::Int,
        Dtype::I16 => Kind::Int16,
        Dtype::I8 => Kind::Int8,
        Dtype::U8 => Kind::Uint8,
        Dtype::BOOL => Kind::Bool,
        _ => return None,
    })
}

impl SafetensorsSource {
    /// Opens `path`: a `.safetensors` file, a `*.safetensors.index.json` shard index, or a
    /// directory holding exactly one of those.
    pub fn open(path: impl AsRef<Path>) -> Result<Self, WeightsError> {
        let path = path.as_ref();
        if path.is_dir() {
            return Self::open(find_weights_in_dir(path)?);
        }
        let name = path.file_name().and_then(|n| n.to_str()).unwrap_or_default();
        if name.ends_with(".index.json") {
            let text = std::fs::read_to_string(path).map_err(|e| file_error(path, e))?;
            let index: serde_json::Value = serde_json::from_str(&text).map_err(|e| file_error(path, e))?;
            let map = index
                .get("weight_map")
                .and_then(|m| m.as_object())
                .ok_or_else(|| file_error(path, "no \"weight_map\" object in the shard index"))?;
            let dir = path.parent().unwrap_or(Path::new("."));
            let mut shards: Vec<PathBuf> = Vec::new();
            for (key, file) in map {
                let file = file
                    .as_str()
                    .ok_or_else(|| file_error(path, format!("weight_map entry for '{key}' is not a file name")))?;
                let shard = dir.join(file);
                if !shards.contains(&shard) {
                    shards.push(shard);
                }
            }
            let source = Self::open_files(&shards, path.display().to_string())?;
            for key in map.keys() {
                if !source.entries.contains_key(key) {
                    return Err(WeightsError::File {
                        file: path.display().to_string(),
                        message: format!("key '{key}' is listed in the index but absent from its shard"),
                    });
                }
            }
            Ok(source)
        } else {
            Self::open_files(&[path.to_path_buf()], path.display().to_string())
        }
    }

    /// The stored dtype of `name`, when the file holds it and tch has that dtype.
    pub fn kind(&self, name: &str) -> Option<Kind> {
        self.entries.get(name).and_then(|e| kind_of(e.dtype))
    }

    fn open_files(paths: &[PathBuf], description: String) -> Result<Self, WeightsError> {
        let mut files = Vec::new();
        let mut entries = BTreeMap::new();
        for (i, path) in paths.iter().enumerate() {
            let file = File::open(path).map_err(|e| file_error(path, e))?;
            // SAFETY: the map is read-only; a file truncated underneath us is caught by the
            // length validation below or faults, as with any mmap reader.
            let mmap = unsafe { Mmap::map(&file) }.map_err(|e| file_error(path, e))?;
            let tensors = SafeTensors::deserialize(&mmap)
                .map_err(|e| file_error(path, format!("not a valid safetensors file ({e})")))?;
            for (name, view) in tensors.tensors() {
                let shape = view.shape().iter().map(|&d| d as i64).collect();
                if entries.insert(name.clone(), Entry { file: i, dtype: view.dtype(), shape }).is_some() {
                    return Err(file_error(path, format!("key '{name}' appears in more than one shard")));
                }
            }
            files.push((path.clone(), mmap));
        }
        Ok(Self { files, entries, description })
    }
}

fn find_weights_in_dir(dir: &Path) -> Result<PathBuf, WeightsError> {
    let mut index = Vec::new();
    let mut single = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(|e| file_error(dir, e))? {
        let path = entry.map_err(|e| file_error(dir, e))?.path();
        let name = path.file_name().and_then(|n| n.to_str()).unwrap_or_default().to_string();
        if name.ends_with(".safetensors.index.json") {
            index.push(path);
        } else if name.ends_with(".safetensors") {
            single.push(path);
        }
    }
    match (index.len(), single.len()) {
        (1, _) => Ok(index.remove(0)),
        (0, 1) => Ok(single.remove(0)),
        (0, 0) => Err(file_error(dir, "no .safetensors file or shard index in this directory")),
        _ => Err(file_error(dir, "several weight files and no single shard index: name the file")),
    }
}

impl WeightSource for SafetensorsSource {
    fn describe(&self) -> String {
        self.description.clone()
    }

    fn names(&self) -> Vec<String> {
        self.entries.keys().cloned().collect()
    }

    fn shape(&self, name: &str) -> Option<Vec<i64>> {
        self.entries.get(name).map(|e| e.shape.clone())
    }

    fn load(&self, name: &str, kind: Kind, device: Device) -> Result<Tensor, WeightsError> {
        let entry = self.entries.get(name).ok_or_else(|| WeightsError::missing(self.describe(), name))?;
        let (path, mmap) = &self.files[entry.file];
        let tensors = SafeTensors::deserialize(mmap).map_err(|e| file_error(path, e))?;
        let view = tensors.tensor(name).map_err(|e| file_error(path, e))?;
        let file_kind = kind_of(entry.dtype).ok_or_else(|| WeightsError::Dtype {
            file: path.display().to_string(),
            key: name.to_string(),
            dtype: format!("{:?}", entry.dtype),
        })?;
        let tensor = Tensor::f_from_data_size(view.data(), &entry.shape, file_kind)
            .map_err(|e| file_error(path, format!("key '{name}': {e}")))?;
        Ok(tensor.to_device(device).to_kind(kind))
    }
}

/// Presents another source under renamed keys (checkpoint layouts that differ only in names).
pub struct RenamedSource<S> {
    inner: S,
    /// (name the model asks for, name in the file)
    to_file: BTreeMap<String, String>,
}

impl<S: WeightSource> RenamedSource<S> {
    /// `rename` maps a key of the file to the model's key, or `None` to hide it.
    pub fn new(inner: S, rename: impl Fn(&str) -> Option<String>) -> Self {
        let to_file = inner.names().into_iter().filter_map(|n| rename(&n).map(|m| (m, n))).collect();
        Self { inner, to_file }
    }
}

impl<S: WeightSource> WeightSource for RenamedSource<S> {
    fn describe(&self) -> String {
        self.inner.describe()
    }
    fn names(&self) -> Vec<String> {
        self.to_file.keys().cloned().collect()
    }
    fn shape(&self, name: &str) -> Option<Vec<i64>> {
        self.to_file.get(name).and_then(|f| self.inner.shape(f))
    }
    fn load(&self, name: &str, kind: Kind, device: Device) -> Result<Tensor, WeightsError> {
        let file_name = self.to_file.get(name).ok_or_else(|| WeightsError::missing(self.describe(), name))?;
        self.inner.load(file_name, kind, device)
    }
}

/// The `__metadata__` string map of one safetensors file (empty when it has none).
pub fn safetensors_metadata(path: &Path) -> Result<BTreeMap<String, String>, WeightsError> {
    let file = File::open(path).map_err(|e| file_error(path, e))?;
    // SAFETY: read-only map, as in `SafetensorsSource`.
    let mmap = unsafe { Mmap::map(&file) }.map_err(|e| file_error(path, e))?;
    let (_, meta) = SafeTensors::read_metadata(&mmap).map_err(|e| file_error(path, format!("not a valid safetensors file ({e})")))?;
    Ok(meta.metadata().clone().map(|m| m.into_iter().collect()).unwrap_or_default())
}

/// Reads every tensor of a safetensors file into memory (for test cases and small files).
pub fn read_all(path: impl AsRef<Path>) -> Result<BTreeMap<String, Tensor>, WeightsError> {
    let source = SafetensorsSource::open(path)?;
    let mut out = BTreeMap::new();
    for name in source.names() {
        let kind = kind_of(source.entries[&name].dtype).unwrap_or(Kind::Float);
        out.insert(name.clone(), source.load(&name, kind, Device::Cpu)?);
    }
    Ok(out)
}
