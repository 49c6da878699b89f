//! Weight sources built from other sources: a union of files (a diffusers transformer plus its
//! action-encoder component), an overlay (trained tensors over the base weights they started
//! from), a renaming that refuses collisions, in-memory tensors, and LoRA adapters merged into
//! the weights they adapt.

use std::collections::{BTreeMap, BTreeSet};

use anyhow::{bail, Result};
use bwm_model::lora::{is_adapter_key, split_adapter_key};
use bwm_model::weights::{WeightSource, WeightsError};
use tch::{Device, Kind, Tensor};

/// Several sources presented as one; each name comes from exactly one of them.
pub struct UnionSource {
    parts: Vec<Box<dyn WeightSource>>,
    owner: BTreeMap<String, usize>,
    description: String,
}

impl UnionSource {
    /// An error names the key when two parts hold it.
    pub fn new(parts: Vec<Box<dyn WeightSource>>) -> Result<Self> {
        let mut owner = BTreeMap::new();
        for (i, part) in parts.iter().enumerate() {
            for name in part.names() {
                if let Some(prev) = owner.insert(name.clone(), i) {
                    bail!(
                        "name collision: '{name}' is held by both {} and {}",
                        parts[prev].describe(),
                        part.describe()
                    );
                }
            }
        }
        let description = parts.iter().map(|p| p.describe()).collect::<Vec<_>>().join(" + ");
        Ok(Self { parts, owner, description })
    }

    /// `primary` wins where both hold a name (trained tensors over base weights).
    pub fn overlay(primary: Box<dyn WeightSource>, fallback: Box<dyn WeightSource>) -> Self {
        let mut owner: BTreeMap<String, usize> = fallback.names().into_iter().map(|n| (n, 1)).collect();
        for n in primary.names() {
            owner.insert(n, 0);
        }
        let description = format!("{} over {}", primary.describe(), fallback.describe());
        Self { parts: vec![primary, fallback], owner, description }
    }
}

impl WeightSource for UnionSource {
    fn describe(&self) -> String {
        self.description.clone()
    }
    fn names(&self) -> Vec<String> {
        self.owner.keys().cloned().collect()
    }
    fn shape(&self, name: &str) -> Option<Vec<i64>> {
        self.owner.get(name).and_then(|&i| self.parts[i].shape(name))
    }
    fn load(&self, name: &str, kind: Kind, device: Device) -> Result<Tensor, WeightsError> {
        let i = *self.owner.get(name).ok_or_else(|| WeightsError::missing(self.describe(), name))?;
        self.parts[i].load(name, kind, device)
    }
}

/// Another source under new names, given as (name presented, name in the inner source) pairs;
/// unlike `bwm_model::weights::RenamedSource` it refuses two inner names for one presented name.
pub struct MappedSource {
    inner: Box<dyn WeightSource>,
    to_inner: BTreeMap<String, String>,
}

impl MappedSource {
    pub fn new(inner: Box<dyn WeightSource>, pairs: impl IntoIterator<Item = (String, String)>) -> Result<Self> {
        let mut to_inner = BTreeMap::new();
        for (presented, original) in pairs {
            if let Some(prev) = to_inner.insert(presented.clone(), original.clone()) {
                bail!("name collision in {}: '{prev}' and '{original}' both become '{presented}'", inner.describe());
            }
        }
        Ok(Self { inner, to_inner })
    }
}

impl WeightSource for MappedSource {
    fn describe(&self) -> String {
        self.inner.describe()
    }
    fn names(&self) -> Vec<String> {
        self.to_inner.keys().cloned().collect()
    }
    fn shape(&self, name: &str) -> Option<Vec<i64>> {
        self.to_inner.get(name).and_then(|n| self.inner.shape(n))
    }
    fn load(&self, name: &str, kind: Kind, device: Device) -> Result<Tensor, WeightsError> {
        let n = self.to_inner.get(name).ok_or_else(|| WeightsError::missing(self.describe(), name))?;
        self.inner.load(n, kind, device)
    }
}


/// Weights with LoRA adapters merged in: each `<m>.weight` that has `<m>.lora_A.weight` and
/// `<m>.lora_B.weight` beside it is presented as `W + scale B A` (computed in fp32, then cast to
/// the dtype asked for); the adapter tensors themselves are not presented.
pub struct LoraMergedSource {
    inner: Box<dyn WeightSource>,
    scale: f64,
    /// Module paths `<m>` with an adapter.
    adapted: BTreeSet<String>,
}

impl LoraMergedSource {
    /// `adapters` over `base`, merged: the adapted weights of `base` with `adapters`' updates.
    pub fn over(adapters: Box<dyn WeightSource>, base: Box<dyn WeightSource>, scale: f64) -> Result<Self> {
        Self::new(Box::new(UnionSource::overlay(adapters, base)), scale)
    }

    /// An error names the adapter whose other half or base weight is missing, or whose shapes do
    /// not fit the weight.
    pub fn new(inner: Box<dyn WeightSource>, scale: f64) -> Result<Self> {
        let mut adapted = BTreeSet::new();
        for name in inner.names() {
            let Some((module, "lora_A")) = split_adapter_key(&name) else { continue };
            let (a, b, w) = (name.clone(), format!("{module}.lora_B.weight"), format!("{module}.weight"));
            let (Some(sa), Some(sb)) = (inner.shape(&a), inner.shape(&b)) else {
                bail!("{}: '{a}' has no '{b}' beside it", inner.describe());
            };
            let Some(sw) = inner.shape(&w) else {
                bail!("{}: the adapter '{a}' adapts '{w}', which neither the checkpoint nor its base weights hold", inner.describe());
            };
            if sa.len() != 2 || sb.len() != 2 || sw != [sb[0], sa[1]] || sa[0] != sb[1] {
                bail!("{}: the adapter of '{w}' {sw:?} has A {sa:?} and B {sb:?}, which do not make its shape", inner.describe());
            }
            adapted.insert(module.to_string());
        }
        if let Some(b) = inner.names().iter().find(|n| matches!(split_adapter_key(n), Some((m, "lora_B")) if !adapted.contains(m))) {
            bail!("{}: '{b}' has no lora_A beside it", inner.describe());
        }
        Ok(Self { inner, scale, adapted })
    }
}

impl WeightSource for LoraMergedSource {
    fn describe(&self) -> String {
        format!("{} (LoRA merged)", self.inner.describe())
    }
    fn names(&self) -> Vec<String> {
        self.inner.names().into_iter().filter(|n| !is_adapter_key(n)).collect()
    }
    fn shape(&self, name: &str) -> Option<Vec<i64>> {
        if is_adapter_key(name) {
            return None;
        }
        self.inner.shape(name)
    }
    fn load(&self, name: &str, kind: Kind, device: Device) -> Result<Tensor, WeightsError> {
        if is_adapter_key(name) {
            return Err(WeightsError::missing(self.describe(), name));
        }
        match name.strip_suffix(".weight").filter(|m| self.adapted.contains(*m)) {
            Some(module) => {
                let w = self.inner.load(name, Kind::Float, device)?;
                let a = self.inner.load(&format!("{module}.lora_A.weight"), Kind::Float, device)?;
                let b = self.inner.load(&format!("{module}.lora_B.weight"), Kind::Float, device)?;
                Ok((w + b.matmul(&a) * self.scale).to_kind(kind))
            }
            None => self.inner.load(name, kind, device),
        }
    }
}
