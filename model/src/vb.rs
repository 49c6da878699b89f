//! Parameter creation by path, in the style of candle's `VarBuilder`: a module asks
//! `vb.pp("blocks").pp(i).pp("self_attn").pp("q")` for `weight`, and the full dotted path is the
//! checkpoint key. The same module code therefore builds from random init, from a weight file, or
//! as a shape-only tree (no allocation) for counting the 5B model.

use std::cell::RefCell;
use std::collections::BTreeSet;
use std::rc::Rc;

use tch::{Device, Kind, Tensor};

use crate::keyed_rng::{self, Purpose};
use crate::weights::{WeightSource, WeightsError};

/// How a parameter is initialized when it is not read from a weight file.
#[derive(Debug, Clone, Copy)]
pub enum Init {
    Zeros,
    Ones,
    /// Normal(0, std).
    Randn { std: f64 },
    /// Uniform(-bound, bound), PyTorch's default for Linear weights and biases (bound = 1/sqrt(fan_in)).
    Uniform { bound: f64 },
    /// Uniform(-bound, bound) from its own stream keyed by (seed, index), not libtorch's
    /// generator: parameters added to a model (`Vb::add`) leave the draws of the others as they
    /// were.
    KeyedUniform { bound: f64, seed: u64, index: u64, purpose: Purpose },
}

enum Source {
    Random,
    /// Zero-stride views of one element: the module tree with its names and shapes, no storage.
    ShapesOnly,
    /// Keys under `fresh_prefixes` that the file lacks are initialized like `Random` (a new
    /// module added to a pretrained model).
    Weights { source: Box<dyn WeightSource>, optional_prefixes: Vec<String>, fresh_prefixes: Vec<String> },
}

/// Every parameter created so far, in creation order, with its full checkpoint name.
pub struct ParamStore {
    params: RefCell<Vec<(String, Tensor)>>,
    consumed: RefCell<BTreeSet<String>>,
    source: Source,
    kind: Kind,
    device: Device,
}

/// Runs `f` with libtorch's global generator seeded with `seed`, holding a process-wide lock so
/// that no other thread's draws (a parallel test, a second model being built) interleave with
/// `f`'s: the same seed then always gives the same weights.
pub fn with_seed<T>(seed: i64, f: impl FnOnce() -> T) -> T {
    static LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());
    let _guard = LOCK.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
    tch::manual_seed(seed);
    f()
}

impl ParamStore {
    /// Parameters drawn from libtorch's global CPU generator (seed it with `with_seed`), the
    /// same on every device.
    pub fn random(kind: Kind, device: Device) -> Rc<Self> {
        Self::with_source(Source::Random, kind, device)
    }

    /// Shape-only parameters: expanded scalars, so the full 5B tree costs no memory.
    pub fn shapes_only(kind: Kind) -> Rc<Self> {
        Self::with_source(Source::ShapesOnly, kind, Device::Cpu)
    }

    /// Parameters read from `source` by name, cast to `kind` on `device`. Keys under
    /// `optional_prefixes` may be absent from the file (the module is then left out) and are not
    /// reported as unexpected when the model does not use them.
    pub fn from_weights(
        source: Box<dyn WeightSource>,
        optional_prefixes: &[&str],
        kind: Kind,
        device: Device,
    ) -> Rc<Self> {
        Self::from_weights_with_fresh(source, optional_prefixes, &[], kind, device)
    }

    /// As `from_weights`, drawing parameters under `fresh_prefixes` at random (libtorch's global
    /// generator) when the file does not hold them.
    pub fn from_weights_with_fresh(
        source: Box<dyn WeightSource>,
        optional_prefixes: &[&str],
        fresh_prefixes: &[&str],
        kind: Kind,
        device: Device,
    ) -> Rc<Self> {
        let list = |v: &[&str]| v.iter().map(|s| s.to_string()).collect();
        Self::with_source(
            Source::Weights { source, optional_prefixes: list(optional_prefixes), fresh_prefixes: list(fresh_prefixes) },
            kind,
            device,
        )
    }

    fn with_source(source: Source, kind: Kind, device: Device) -> Rc<Self> {
        Rc::new(Self {
            params: RefCell::new(Vec::new()),
            consumed: RefCell::new(BTreeSet::new()),
            source,
            kind,
            device,
        })
    }

    pub fn root(self: &Rc<Self>) -> Vb {
        Vb { store: self.clone(), prefix: String::new() }
    }

    pub fn kind(&self) -> Kind {
        self.kind
    }

    pub fn device(&self) -> Device {
        self.device
    }

    /// All parameters with their checkpoint names, in creation order.
    pub fn named_parameters(&self) -> Vec<(String, Tensor)> {
        self.params.borrow().iter().map(|(n, t)| (n.clone(), t.shallow_clone())).collect()
    }

    pub fn num_parameters(&self) -> i64 {
        self.params.borrow().iter().map(|(_, t)| t.size().iter().product::<i64>()).sum()
    }

    /// After the model is built from a weight file: any key of the file that no module asked for
    /// (outside the optional prefixes) is an error naming it.
    pub fn check_all_consumed(&self) -> Result<(), WeightsError> {
        let Source::Weights { source, optional_prefixes, .. } = &self.source else { return Ok(()) };
        let consumed = self.consumed.borrow();
        let unexpected = source
            .names()
            .into_iter()
            .filter(|n| !consumed.contains(n))
            .find(|n| !optional_prefixes.iter().any(|p| n.starts_with(p.as_str())));
        match unexpected {
            Some(key) => Err(WeightsError::Unexpected { file: source.describe(), key }),
            None => Ok(()),
        }
    }
}

/// A position in the module tree.
#[derive(Clone)]
pub struct Vb {
    store: Rc<ParamStore>,
    prefix: String,
}

impl Vb {
    /// The sub-path `name` (a field name or a layer index).
    pub fn pp(&self, name: impl std::fmt::Display) -> Vb {
        let prefix =
            if self.prefix.is_empty() { name.to_string() } else { format!("{}.{}", self.prefix, name) };
        Vb { store: self.store.clone(), prefix }
    }

    /// This position's module path (empty at the root).
    pub fn prefix(&self) -> &str {
        &self.prefix
    }

    pub fn path(&self, name: &str) -> String {
        if self.prefix.is_empty() {
            name.to_string()
        } else {
            format!("{}.{}", self.prefix, name)
        }
    }

    pub fn kind(&self) -> Kind {
        self.store.kind
    }

    pub fn device(&self) -> Device {
        self.store.device
    }

    /// Whether a module under this path should be built: always for random or shape-only trees;
    /// for a weight file, when the file holds `name` or the path is not declared optional.
    pub fn provides(&self, name: &str) -> bool {
        let path = self.path(name);
        match &self.store.source {
            Source::Random | Source::ShapesOnly => true,
            Source::Weights { source, optional_prefixes, .. } => {
                source.shape(&path).is_some()
                    || !optional_prefixes.iter().any(|p| path.starts_with(p.as_str()))
            }
        }
    }

    /// The parameter `name` under this path with the given shape.
    pub fn get(&self, shape: &[i64], name: &str, init: Init) -> Result<Tensor, WeightsError> {
        let path = self.path(name);
        let tensor = self.create(&path, shape, init, false)?;
        self.store.params.borrow_mut().push((path, tensor.shallow_clone()));
        Ok(tensor)
    }

    /// A parameter `name` added to the module at this path after it was built (a conversion's,
    /// `crate::convert`): read from the weight file when it holds `name`, else drawn by `init`
    /// (whatever the file's fresh prefixes). The store lists it right after the parameters
    /// already under this path, where building the module with it would have put it, so that
    /// the order of the parameters (the optimizer's, a checkpoint's trainable list) does not
    /// depend on when it was added.
    pub fn add(&self, shape: &[i64], name: &str, init: Init) -> Result<Tensor, WeightsError> {
        let path = self.path(name);
        let tensor = self.create(&path, shape, init, true)?;
        let mut params = self.store.params.borrow_mut();
        let under = format!("{}.", self.prefix);
        let at = params.iter().rposition(|(n, _)| self.prefix.is_empty() || n.starts_with(&under)).map_or(params.len(), |i| i + 1);
        params.insert(at, (path, tensor.shallow_clone()));
        Ok(tensor)
    }

    /// The tensor of parameter `path`: drawn, shape-only, or read from the weight file (drawn when
    /// the file lacks it and `fresh` is set or a fresh prefix covers it).
    fn create(&self, path: &str, shape: &[i64], init: Init, fresh: bool) -> Result<Tensor, WeightsError> {
        let path = path.to_string();
        let store = &self.store;
        let options = (store.kind, store.device);
        let random = |init: Init| match init {
            Init::Zeros => Tensor::zeros(shape, options),
            Init::Ones => Tensor::ones(shape, options),
            // Drawn on the CPU whatever the device, so that a seed gives the same weights on every
            // device (CPU and CUDA generators differ).
            Init::Randn { std } => {
                Tensor::randn(shape, (Kind::Float, Device::Cpu)).g_mul_scalar(std).to_kind(store.kind).to_device(store.device)
            }
            Init::Uniform { bound } => {
                Tensor::empty(shape, (Kind::Float, Device::Cpu)).uniform_(-bound, bound).to_kind(store.kind).to_device(store.device)
            }
            Init::KeyedUniform { bound, seed, index, purpose } => {
                keyed_rng::uniform_tensor(shape, bound, seed, index, purpose).to_kind(store.kind).to_device(store.device)
            }
        };
        let tensor = match &store.source {
            Source::Random => random(init),
            Source::ShapesOnly => Tensor::zeros([1], options).expand(shape, false),
            Source::Weights { source, fresh_prefixes, .. }
                if source.shape(&path).is_none() && (fresh || fresh_prefixes.iter().any(|p| path.starts_with(p.as_str()))) =>
            {
                random(init)
            }
            Source::Weights { source, .. } => {
                let found = source.shape(&path).ok_or_else(|| WeightsError::Missing {
                    file: source.describe(),
                    key: path.clone(),
                    expected: shape.to_vec(),
                })?;
                if found != shape {
                    return Err(WeightsError::Shape {
                        file: source.describe(),
                        key: path,
                        found,
                        expected: shape.to_vec(),
                    });
                }
                store.consumed.borrow_mut().insert(path.clone());
                source.load(&path, store.kind, store.device)?
            }
        };
        Ok(tensor)
    }
}
