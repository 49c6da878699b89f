//! A model's input contract: what a caller must send it, recorded with its weights as
//! `contract.json` (in a training checkpoint's `step-N/` folder, at the root of an export). It
//! holds the action vector (its width, what each value means, how a dataset's columns become it,
//! the statistics that normalize it), the frames (size, frame rate, cameras and how they are laid
//! out, how other sizes are fitted), the history and chunk lengths, the sampler the model's
//! fidelity was measured at, and the keys each interface reads.
//!
//! Training writes it from its latent cache (whose `index.json` records how the clips were made),
//! `bwm export` carries it over, `bwm sampler` records the sampler in it, `bwm info --checkpoint`
//! shows it, and rollout, evaluate and serve take their defaults from it and refuse what
//! contradicts it, with one line naming the value and the contract's.
//!
//! Every section but `format` and `observation_keys` may be absent: weights from before the
//! contract, or from elsewhere, record what they can (an export without its run, a checkpoint
//! whose cache has moved). What is absent is not checked.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{ensure, Context, Result};
use bwm_data::latent_cache::{read_index, write_atomically, INDEX_FILE};
use bwm_data::{ActionSpec, ActionStats, CacheIndex, CameraLayout, CameraSelection, IndexExtras, ResizeMode};
use serde::{Deserialize, Serialize};

use bwm_model::schedule::Solver;

/// The file's name, beside the weights.
pub const CONTRACT_FILE: &str = "contract.json";
/// The layout of the file this code writes and reads.
pub const CONTRACT_FORMAT: u32 = 1;
/// How raw actions become the model's values (`bwm_data::ActionStats::normalize`).
pub const NORMALIZATION_FORMULA: &str = "2*(x - p01)/(p99 - p01 + 1e-8) - 1, clipped to [-1, 1] (min/max where p99 <= p01)";

/// Sampler steps for weights that record no sampler (`crate::sampler::resolve`): the reference implementation's 50.
pub const UNRECORDED_STEPS: usize = 50;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SamplerRecord {
    /// Sampler steps per generated chunk.
    pub steps: usize,
    pub solver: Solver,
    /// What measured the model's fidelity at this setting (a command, a report, a number).
    pub measured: String,
}

impl SamplerRecord {
    pub fn validate(&self) -> Result<()> {
        ensure!(self.steps > 0, "sampler steps must be positive, got {}", self.steps);
        ensure!(!self.measured.trim().is_empty(), "say what measured the model's fidelity at this sampler (`measured`)");
        Ok(())
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InputContract {
    pub format: u32,
    pub actions: Option<ActionContract>,
    pub frames: Option<FrameContract>,
    pub chunk: Option<ChunkContract>,
    /// The sampler the model's fidelity was measured at (`bwm sampler`); None until one is
    /// recorded.
    pub sampler: Option<SamplerRecord>,
    /// For each interface, the keys its requests carry (see [`observation_keys`]).
    pub observation_keys: BTreeMap<String, Vec<String>>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ActionContract {
    /// Values per action vector (one vector per frame).
    pub dim: usize,
    /// What each value means, in order (`bwm_data::ActionSpec::components`); empty when the
    /// definition is unknown.
    pub components: Vec<String>,
    /// How the vectors are read from a dataset's columns (`bwm prepare --actions`).
    pub definition: Option<ActionSpec>,
    /// How raw values become the model's [-1, 1]; None: callers must send normalized actions.
    pub normalization: Option<Normalization>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Normalization {
    pub formula: String,
    /// The `stat.json` group the statistics came from.
    pub group: String,
    pub stats: ActionStats,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FrameContract {
    /// Pixels of one frame (the views stacked, when there are several).
    pub width: u32,
    pub height: u32,
    /// Frames per second of the training episodes (one action per frame).
    pub fps: f64,
    /// The cameras, in order; empty: the dataset's default camera.
    pub cameras: Vec<String>,
    pub layout: CameraLayout,
    /// How training fitted frames of another aspect ratio to this size.
    pub resize: ResizeMode,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ChunkContract {
    /// Frames of history H before each chunk (besides x0).
    pub history: usize,
    /// Frames K generated per chunk.
    pub future: usize,
}

/// The keys each interface's requests carry, for the contract's `observation_keys`.
pub fn observation_keys() -> BTreeMap<String, Vec<String>> {
    let keys = |k: &[&str]| k.iter().map(|s| s.to_string()).collect::<Vec<_>>();
    BTreeMap::from([
        ("serve POST /v1/chunk".to_string(), keys(&["frames", "actions", "normalized", "seed"])),
        ("rollout --inputs (JSON lines)".to_string(), keys(&["x0", "actions", "task"])),
        ("evaluate (episode x0 and state)".to_string(), keys(&["image", "state"])),
    ])
}

impl InputContract {
    /// A contract that records nothing but the interfaces' keys (weights of unknown origin).
    pub fn unknown() -> Self {
        Self { format: CONTRACT_FORMAT, actions: None, frames: None, chunk: None, sampler: None, observation_keys: observation_keys() }
    }

    /// A contract that records only the action width (weights whose data are unknown).
    pub fn of_model(action_dim: usize) -> Self {
        Self { actions: Some(ActionContract { dim: action_dim, components: vec![], definition: None, normalization: None }), ..Self::unknown() }
    }

    /// The contract of a model of `action_dim` trained on the latent cache in `cache`: what its
    /// `index.json` records of how the clips were made.
    pub fn from_cache(action_dim: usize, cache: &Path) -> Result<Self> {
        let (index, extras) = read_index(&cache.join(INDEX_FILE))?;
        Self::from_index(action_dim, &index, &extras, cache)
    }

    /// `from_cache` of an index already read (`LatentCache::index` and `extras`) from the cache
    /// folder `cache`.
    pub fn from_index(action_dim: usize, index: &CacheIndex, extras: &IndexExtras, cache: &Path) -> Result<Self> {
        let what = || format!("{}: the plan it was prepared from", cache.join(INDEX_FILE).display());
        let plan = extras.plan.clone().unwrap_or(serde_json::Value::Null);
        let field = |k: &str| plan.get(k).cloned().filter(|v| !v.is_null());
        let definition: Option<ActionSpec> = field("actions").map(serde_json::from_value).transpose().with_context(what)?;
        let cameras: CameraSelection = field("cameras").map(serde_json::from_value).transpose().with_context(what)?.unwrap_or_default();
        let resize: ResizeMode = field("resize").map(serde_json::from_value).transpose().with_context(what)?.unwrap_or_default();
        let stats: Option<ActionStats> = field("stats").map(serde_json::from_value).transpose().with_context(what)?;
        ensure!(
            index.action_dim as usize == action_dim,
            "{}: the cache's actions have {} values, the model takes {action_dim}",
            cache.display(),
            index.action_dim
        );
        let mut contract = Self::of_model(action_dim);
        contract.actions = Some(ActionContract {
            dim: action_dim,
            components: definition.as_ref().map(ActionSpec::components).unwrap_or_default(),
            normalization: stats.map(|stats| Normalization {
                formula: NORMALIZATION_FORMULA.into(),
                group: definition.as_ref().map(|d| d.stats_group.clone()).unwrap_or_default(),
                stats,
            }),
            definition,
        });
        let [width, height] = index.resolution;
        contract.frames = Some(FrameContract { width, height, fps: index.fps, cameras: cameras.cameras, layout: cameras.layout, resize });
        contract.chunk = Some(ChunkContract { history: index.history_frames, future: index.future_frames });
        Ok(contract)
    }

    pub fn validate(&self) -> Result<()> {
        ensure!(self.format == CONTRACT_FORMAT, "format {} (this build reads format {CONTRACT_FORMAT})", self.format);
        if let Some(a) = &self.actions {
            ensure!(a.dim > 0, "actions.dim is 0");
            ensure!(a.components.is_empty() || a.components.len() == a.dim, "{} action components named for {} values", a.components.len(), a.dim);
            if let Some(n) = &a.normalization {
                n.stats.check().context("actions.normalization.stats")?;
                ensure!(n.stats.dim() == a.dim, "the normalization statistics have {} values, the actions {}", n.stats.dim(), a.dim);
            }
            if let Some(definition) = &a.definition {
                definition.validate().context("actions.definition")?;
            }
        }
        if let Some(f) = &self.frames {
            ensure!(f.width > 0 && f.height > 0, "frames of {}x{}", f.width, f.height);
        }
        if let Some(s) = &self.sampler {
            s.validate()?;
        }
        Ok(())
    }

    /// A caller's actions of `dim` values; `what` names where they came from.
    pub fn check_action_dim(&self, dim: usize, what: &str) -> Result<()> {
        if let Some(a) = &self.actions {
            ensure!(dim == a.dim, "{what}: {dim}-D actions, but this model takes {}-D actions{} ({CONTRACT_FILE})", a.dim, components_hint(&a.components));
        }
        Ok(())
    }

    /// A caller's frames of `width` x `height`.
    pub fn check_frame_size(&self, width: u32, height: u32, what: &str) -> Result<()> {
        if let Some(f) = &self.frames {
            ensure!(
                (width, height) == (f.width, f.height),
                "{what}: {width}x{height} frames, but this model was trained on {}x{} ({CONTRACT_FILE}; WIDTHxHEIGHT)",
                f.width,
                f.height
            );
        }
        Ok(())
    }

    /// A caller's action definition (how a dataset's columns become the vectors).
    pub fn check_definition(&self, definition: &ActionSpec, what: &str) -> Result<()> {
        if let Some(known) = self.actions.as_ref().and_then(|a| a.definition.as_ref()) {
            ensure!(
                definition == known,
                "{what}: reads {} from '{}' at {:?}, but this model was trained on {} from '{}' at {:?} ({CONTRACT_FILE})",
                describe_dim(definition.dim()),
                definition.column,
                definition.indices,
                describe_dim(known.dim()),
                known.column,
                known.indices
            );
        }
        self.check_action_dim(definition.dim(), what)
    }

    /// History H and chunk K asked for (None: the contract's, else 8 and 72); a value that
    /// contradicts the contract is refused by its flag.
    pub fn chunk_or(&self, history: Option<usize>, future: Option<usize>) -> Result<(usize, usize)> {
        let c = self.chunk.unwrap_or(ChunkContract { history: 8, future: 72 });
        if let Some(known) = self.chunk {
            for (flag, asked, trained) in [("--history", history, known.history), ("--future", future, known.future)] {
                if let Some(v) = asked {
                    ensure!(v == trained, "{flag} {v}: this model was trained with {trained} ({CONTRACT_FILE}); leave {flag} out to use it");
                }
            }
        }
        Ok((history.unwrap_or(c.history), future.unwrap_or(c.future)))
    }

    /// The contract as lines for people (`bwm info --checkpoint`).
    pub fn describe(&self) -> Vec<String> {
        let unknown = "not recorded";
        let mut lines = vec![];
        match &self.actions {
            Some(a) => {
                lines.push(format!("actions: {} values per frame", a.dim));
                for (i, c) in a.components.iter().enumerate() {
                    lines.push(format!("  {i:>2}  {c}"));
                }
                match &a.definition {
                    Some(d) => lines.push(format!("  read from: column '{}', indices {:?}, statistics group '{}'", d.column, d.indices, d.stats_group)),
                    None => lines.push(format!("  read from: {unknown}")),
                }
                match &a.normalization {
                    Some(n) => {
                        lines.push(format!("  normalization: {} (group '{}')", n.formula, n.group));
                        lines.push(format!("    p01 {:?}", rounded(&n.stats.p01)));
                        lines.push(format!("    p99 {:?}", rounded(&n.stats.p99)));
                    }
                    None => lines.push(format!("  normalization: {unknown}; send normalized actions or pass --stats")),
                }
            }
            None => lines.push(format!("actions: {unknown}")),
        }
        match &self.frames {
            Some(f) => {
                let cams = if f.cameras.is_empty() { "the dataset's default camera".to_string() } else { f.cameras.join(", ") };
                let layout = match f.layout {
                    CameraLayout::Single => "one view",
                    CameraLayout::StackVertically => "views stacked top to bottom",
                };
                lines.push(format!("frames: {}x{} (WIDTHxHEIGHT) RGB, {} fps, {cams} ({layout}), other sizes fitted by {:?}", f.width, f.height, f.fps, f.resize));
            }
            None => lines.push(format!("frames: {unknown}")),
        }
        match &self.chunk {
            Some(c) => lines.push(format!("chunk: x0 + {} history frames, {} generated frames", c.history, c.future)),
            None => lines.push(format!("chunk: {unknown}")),
        }
        match &self.sampler {
            Some(s) => lines.push(format!("sampler: {} {} steps (measured: {})", s.steps, s.solver.name(), s.measured)),
            None => lines.push(format!("sampler: {unknown}; world-model commands take {UNRECORDED_STEPS} Euler steps")),
        }
        for (interface, keys) in &self.observation_keys {
            lines.push(format!("keys of {interface}: {}", keys.join(", ")));
        }
        lines
    }
}

fn describe_dim(d: usize) -> String {
    format!("{d} value{}", if d == 1 { "" } else { "s" })
}

fn components_hint(components: &[String]) -> String {
    if components.is_empty() {
        String::new()
    } else {
        format!(": {}", components.join(", "))
    }
}

fn rounded(v: &[f64]) -> Vec<f64> {
    v.iter().map(|x| (x * 1e4).round() / 1e4).collect()
}

/// Where the contract of weights at `location` (a checkpoint or export folder, or a weights file)
/// lives: in the folder, or beside the file.
pub fn path_of(location: &Path) -> PathBuf {
    if location.is_dir() {
        location.join(CONTRACT_FILE)
    } else {
        location.parent().unwrap_or(Path::new(".")).join(CONTRACT_FILE)
    }
}

/// The contract of the weights at `location`; None when there is none.
pub fn read(location: &Path) -> Result<Option<InputContract>> {
    let path = path_of(location);
    if !path.is_file() {
        return Ok(None);
    }
    let text = std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    let contract: InputContract = serde_json::from_str(&text).with_context(|| format!("{}: not an input contract", path.display()))?;
    contract.validate().with_context(|| path.display().to_string())?;
    Ok(Some(contract))
}

/// Writes the contract of the weights at `location` (replacing any), whole or not at all.
pub fn write(location: &Path, contract: &InputContract) -> Result<PathBuf> {
    contract.validate().context("the input contract to write")?;
    let path = path_of(location);
    let dir = path.parent().unwrap_or(Path::new("."));
    write_atomically(dir, CONTRACT_FILE, (serde_json::to_string_pretty(contract)? + "\n").as_bytes())?;
    Ok(path)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn stats(dim: usize) -> ActionStats {
        let v = |x: f64| vec![x; dim];
        ActionStats { shape: vec![dim], min: v(-2.0), max: v(2.0), p01: v(-1.0), p99: v(1.0), mean: v(0.0), std: v(0.5) }
    }

    /// A cache folder of the kind `bwm prepare` writes: clips of 128x96 at 10 fps, H 8, K 24,
    /// 4-D actions from observation.state:0-3.
    fn cache(dir: &Path) {
        let mut index = CacheIndex::new(vec![16, 9, 6, 8], 4, 8, 24, [128, 96], 10.0, "vae");
        index.has_frames = false;
        let extras = IndexExtras {
            plan: Some(serde_json::json!({
                "actions": ActionSpec::parse("observation.state:0-3").unwrap(),
                "cameras": CameraSelection::single("corner"),
                "resize": "pad",
                "stats": stats(4),
            })),
            ..Default::default()
        };
        bwm_data::latent_cache::write_index(dir, INDEX_FILE, &index, &extras).unwrap();
    }

    /// Training's contract records the cache's actions, frames and chunk; it round-trips through
    /// its file, and a file that is not one is refused by its path.
    #[test]
    fn a_cache_gives_the_contract_and_it_round_trips() {
        let dir = bwm_testdir::tmp_dir("contract");
        cache(dir.path());
        let c = InputContract::from_cache(4, dir.path()).unwrap();
        let a = c.actions.as_ref().unwrap();
        assert_eq!((a.dim, a.components[3].as_str()), (4, "observation.state[3]"));
        assert_eq!(a.normalization.as_ref().unwrap().group, "observation.state");
        let f = c.frames.as_ref().unwrap();
        assert_eq!((f.width, f.height, f.fps, f.cameras.as_slice(), f.resize), (128, 96, 10.0, &["corner".to_string()][..], ResizeMode::Pad));
        assert_eq!(c.chunk, Some(ChunkContract { history: 8, future: 24 }));
        assert!(InputContract::from_cache(7, dir.path()).unwrap_err().to_string().contains("the model takes 7"));

        assert_eq!(read(dir.path()).unwrap(), None);
        let path = write(dir.path(), &c).unwrap();
        assert_eq!(read(&dir.path().join("model.safetensors")).unwrap(), Some(c.clone()), "a weights file's contract is the one beside it");
        std::fs::write(&path, r#"{"format": 1, "actions": null, "frames": null, "chunk": null, "sampler": null, "observation_keys": {}, "extra": 1}"#).unwrap();
        let e = format!("{:#}", read(dir.path()).unwrap_err());
        assert!(e.contains(CONTRACT_FILE) && e.contains("extra"), "{e}");
        let lines = c.describe().join("\n");
        assert!(lines.contains("actions: 4 values per frame") && lines.contains("128x96") && lines.contains("x0 + 8 history frames, 24 generated"), "{lines}");

        // Statistics with a field short of the width, or a definition that cannot be applied,
        // are refused when the contract is read, not when an action is normalized.
        let mut short = c.clone();
        short.actions.as_mut().unwrap().normalization.as_mut().unwrap().stats.max.pop();
        let e = format!("{:#}", short.validate().unwrap_err());
        assert!(e.contains("actions.normalization.stats: 'max' has 3 values, 'p01' 4"), "{e}");
        let mut bad = c.clone();
        bad.actions.as_mut().unwrap().definition.as_mut().unwrap().absolute_to_delta = vec![9];
        let e = format!("{:#}", bad.validate().unwrap_err());
        assert!(e.contains("actions.definition: absolute_to_delta position 9"), "{e}");
    }

    /// Each mismatch is one line naming the given value and the contract's; absent sections
    /// check nothing.
    #[test]
    fn mismatches_are_refused_in_one_line_naming_both() {
        let dir = bwm_testdir::tmp_dir("contract-check");
        cache(dir.path());
        let c = InputContract::from_cache(4, dir.path()).unwrap();
        let e = c.check_action_dim(7, "--actions x").unwrap_err().to_string();
        assert!(e.contains("7-D actions") && e.contains("takes 4-D") && e.contains("observation.state[0]") && !e.contains('\n'), "{e}");
        let e = c.check_frame_size(64, 64, "x0 of episode 3").unwrap_err().to_string();
        assert!(e.contains("x0 of episode 3: 64x64 frames") && e.contains("trained on 128x96"), "{e}");
        c.check_frame_size(128, 96, "x0").unwrap();
        let e = c.check_definition(&ActionSpec::parse("observation.state:4-7").unwrap(), "--actions").unwrap_err().to_string();
        assert!(e.contains("[4, 5, 6, 7]") && e.contains("[0, 1, 2, 3]"), "{e}");
        c.check_definition(&ActionSpec::parse("observation.state:0-3").unwrap(), "--actions").unwrap();
        assert_eq!(c.chunk_or(None, None).unwrap(), (8, 24));
        assert_eq!(c.chunk_or(Some(8), None).unwrap(), (8, 24));
        let e = c.chunk_or(None, Some(72)).unwrap_err().to_string();
        assert!(e.contains("--future 72") && e.contains("trained with 24"), "{e}");
        let bare = InputContract::of_model(4);
        bare.check_frame_size(64, 64, "x").unwrap();
        assert_eq!(bare.chunk_or(None, Some(16)).unwrap(), (8, 16), "an unrecorded chunk takes any value, else 8 and 72");
        assert!(bare.check_action_dim(5, "x").is_err());
    }
}
