//! The `bwm evaluate` config file (TOML): policies, tasks, observation layout, action adapters,
//! chunk handling, judge. Relative paths are relative to the config file's folder.

use std::path::{Path, PathBuf};

use anyhow::{bail, ensure, Context, Result};
use bwm_data::{ActionSpec, CameraSelection, ResizeMode};
use serde::Deserialize;

use bwm_data::frames::parse_resolution;

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EvalConfig {
    /// Frames generated per episode after x0; an episode ends earlier on success.
    pub horizon: usize,
    /// World-model frame size WIDTHxHEIGHT (multiples of 32); several camera views are stacked
    /// top to bottom inside it.
    pub resolution: String,
    /// How x0 images and dataset frames are fitted to `resolution`.
    #[serde(default)]
    pub resize: ResizeMode,
    /// Frame rate of the rollout videos (default: the dataset episode's, else 30).
    #[serde(default)]
    pub fps: Option<f64>,
    /// Ask the judge after every chunk and stop the episode at its first success.
    #[serde(default = "yes")]
    pub stop_on_success: bool,
    /// Seconds to wait for one policy reply (and for the connection).
    #[serde(default = "default_timeout")]
    pub timeout_s: f64,
    /// Default observation layout of the policies.
    #[serde(default)]
    pub observation: ObservationConfig,
    pub policies: Vec<PolicyConfig>,
    pub tasks: Vec<TaskConfig>,
    pub judge: JudgeConfig,
    /// Forward kinematics for `joint` adapters.
    #[serde(default)]
    pub fk: Option<FkConfig>,
    /// Reference success rates, CSV `policy,task,success_rate` (rates in [0, 1]).
    #[serde(default)]
    pub reference: Option<PathBuf>,
}

fn yes() -> bool {
    true
}

fn default_timeout() -> f64 {
    120.0
}

/// A key of the observation dict; a list names nested dicts (ALOHA's `["images", "cam_high"]`).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(untagged)]
pub enum KeyPath {
    Key(String),
    Path(Vec<String>),
}

impl KeyPath {
    pub fn parts(&self) -> Vec<String> {
        match self {
            KeyPath::Key(k) => vec![k.clone()],
            KeyPath::Path(p) => p.clone(),
        }
    }

    pub fn display(&self) -> String {
        self.parts().join(".")
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ImageLayout {
    /// uint8 [H, W, 3] (DROID, LIBERO).
    #[default]
    Hwc,
    /// uint8 [3, H, W] (ALOHA).
    Chw,
}

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ObservationConfig {
    /// One key per camera view, in the top-to-bottom order of the stacked frame.
    #[serde(default = "default_image_keys")]
    pub image_keys: Vec<KeyPath>,
    /// Policy image size WIDTHxHEIGHT.
    #[serde(default = "default_image_size")]
    pub image_size: String,
    /// openpi resizes with padding (`image_tools.resize_with_pad`).
    #[serde(default = "default_image_resize")]
    pub image_resize: ResizeMode,
    #[serde(default)]
    pub image_layout: ImageLayout,
    #[serde(default = "default_state_key")]
    pub state_key: KeyPath,
    #[serde(default = "default_prompt_key")]
    pub prompt_key: KeyPath,
    /// Key of the action chunk in the policy's reply.
    #[serde(default = "default_actions_key")]
    pub actions_key: KeyPath,
}

impl Default for ObservationConfig {
    fn default() -> Self {
        Self {
            image_keys: default_image_keys(),
            image_size: default_image_size(),
            image_resize: default_image_resize(),
            image_layout: ImageLayout::default(),
            state_key: default_state_key(),
            prompt_key: default_prompt_key(),
            actions_key: default_actions_key(),
        }
    }
}

fn default_image_keys() -> Vec<KeyPath> {
    vec![KeyPath::Key("observation/image".into())]
}
fn default_image_size() -> String {
    "224x224".into()
}
fn default_image_resize() -> ResizeMode {
    ResizeMode::Pad
}
fn default_state_key() -> KeyPath {
    KeyPath::Key("observation/state".into())
}
fn default_prompt_key() -> KeyPath {
    KeyPath::Key("prompt".into())
}
fn default_actions_key() -> KeyPath {
    KeyPath::Key("actions".into())
}

impl ObservationConfig {
    /// Policy image (width, height).
    pub fn image_size(&self) -> Result<(u32, u32)> {
        parse_resolution(&self.image_size, 1).context("observation.image_size")
    }
}

/// What to do with an action chunk whose length is not K (the world model's chunk).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ChunkMode {
    /// Use at most K actions; a shorter chunk is cut down to a multiple of 4 (whole latent frames).
    #[default]
    Cut,
    /// Ask the policy again (same frame, state advanced to the last commanded pose) until K
    /// actions are gathered; the surplus of the last reply is dropped.
    Rerequest,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PolicyConfig {
    pub name: String,
    /// `ws://host:port` of an openpi policy server.
    pub url: String,
    #[serde(default)]
    pub chunk: ChunkMode,
    #[serde(default)]
    pub adapter: AdapterConfig,
    /// Replaces the top-level `[observation]` for this policy.
    #[serde(default)]
    pub observation: Option<ObservationConfig>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AdapterKind {
    /// Absolute end-effector poses.
    #[default]
    EefAbs,
    /// End-effector deltas, integrated from the last commanded pose.
    EefDelta,
    /// Joint positions, turned into poses by the `[fk]` provider.
    Joint,
}

#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AdapterConfig {
    #[serde(default)]
    pub kind: AdapterKind,
    /// Positions in the policy's action vector that make the command, in the model's action
    /// order (default: the first d_a).
    #[serde(default)]
    pub indices: Option<Vec<usize>>,
    /// eef_delta: command positions taken as absolute values, not integrated (e.g. grippers).
    #[serde(default)]
    pub absolute: Vec<usize>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FkConfig {
    /// Program and arguments; it reads `{"joints": [[...], ...]}` lines on stdin and answers each
    /// with a `{"poses": [[...], ...]}` line (poses in the model's action layout, raw units).
    pub command: Vec<String>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TaskConfig {
    pub name: String,
    /// Task text sent as the prompt (default: the dataset episode's task text, else the name).
    #[serde(default)]
    pub prompt: Option<String>,
    /// Episodes from a dataset (any format `open_dataset` reads): x0 is frame 0, the initial
    /// pose/joints are frame 0's vectors.
    #[serde(default)]
    pub dataset: Option<PathBuf>,
    /// Dataset episode positions (default: all).
    #[serde(default)]
    pub episodes: Option<Vec<usize>>,
    #[serde(default)]
    pub cameras: CameraSelection,
    /// How the dataset's pose vector is read: an `ActionSpec` preset (eef_abs, robotwin_eef_abs, ...),
    /// COLUMN:INDICES (e.g. `observation.state:0-3`) or an action spec JSON file.
    #[serde(default = "default_pose_actions")]
    pub pose_actions: String,
    /// How the dataset's joint vector is read (joint adapters).
    #[serde(default = "default_joint_actions")]
    pub joint_actions: String,
    /// Episodes from files instead of a dataset.
    #[serde(default)]
    pub starts: Vec<StartConfig>,
    /// Success rules for `judge.kind = "rules"`; all must hold.
    #[serde(default)]
    pub rules: Vec<ColorRule>,
}

fn default_pose_actions() -> String {
    "eef_abs".into()
}
fn default_joint_actions() -> String {
    "joint_abs".into()
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StartConfig {
    /// x0: one image per camera view, stacked top to bottom.
    pub images: Vec<PathBuf>,
    /// Initial pose (raw units, the model's action layout): a JSON list or a 1-D .npy.
    #[serde(default)]
    pub pose: Option<PathBuf>,
    /// Initial joint positions for joint adapters (JSON list or .npy).
    #[serde(default)]
    pub joints: Option<PathBuf>,
    #[serde(default)]
    pub prompt: Option<String>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JudgeConfig {
    pub kind: JudgeKind,
    /// http: the endpoint taking POSTed frames.
    #[serde(default)]
    pub url: Option<String>,
    /// http: success when the returned probability is at least this.
    #[serde(default = "default_threshold")]
    pub threshold: f64,
    /// http: send at most this many frames, evenly spaced, the last one included (default: all).
    #[serde(default)]
    pub max_frames: Option<usize>,
    #[serde(default = "default_judge_timeout")]
    pub timeout_s: f64,
}

fn default_threshold() -> f64 {
    0.5
}
fn default_judge_timeout() -> f64 {
    60.0
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum JudgeKind {
    Http,
    Rules,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Presence {
    Present,
    Absent,
}

/// A colour mask in a region of interest: on each of the last `last_frames` frames, the share of
/// the region's pixels whose R, G and B all lie within [rgb_min, rgb_max] is at least
/// `min_fraction` (present) or below it (absent).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ColorRule {
    pub expect: Presence,
    pub rgb_min: [u8; 3],
    pub rgb_max: [u8; 3],
    /// left, top, right, bottom as fractions of the frame.
    #[serde(default = "whole_frame")]
    pub roi: [f64; 4],
    #[serde(default = "one")]
    pub last_frames: usize,
    pub min_fraction: f64,
}

fn whole_frame() -> [f64; 4] {
    [0.0, 0.0, 1.0, 1.0]
}
fn one() -> usize {
    1
}

/// Names become file names: letters, digits, `_`, `-` and `.` only.
/// A timeout the clock can hold: a positive number of seconds below 1e9 (NaN and infinity refused).
fn check_timeout(key: &str, seconds: f64) -> Result<()> {
    ensure!(seconds > 0.0 && seconds < 1e9, "{key} {seconds} must be a positive number of seconds below 1e9");
    Ok(())
}

fn check_name(what: &str, name: &str) -> Result<()> {
    ensure!(
        !name.is_empty()
            && name != "."
            && name != ".."
            && name
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || "_-.".contains(c)),
        "{what} name '{name}': use letters, digits, '_', '-' and '.' only (it names output files)"
    );
    Ok(())
}

impl EvalConfig {
    pub fn read(path: &Path) -> Result<Self> {
        let text =
            std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let mut cfg: Self = toml::from_str(&text)
            .with_context(|| format!("{}: invalid evaluate config", path.display()))?;
        let base = path.parent().map(Path::to_path_buf).unwrap_or_default();
        cfg.resolve_paths(&base);
        cfg.validate()
            .with_context(|| format!("{}", path.display()))?;
        Ok(cfg)
    }

    fn resolve_paths(&mut self, base: &Path) {
        let fix = |p: &mut PathBuf| {
            if p.is_relative() {
                *p = base.join(&*p);
            }
        };
        for t in &mut self.tasks {
            if let Some(d) = &mut t.dataset {
                fix(d);
            }
            for s in &mut t.starts {
                s.images.iter_mut().for_each(fix);
                s.pose.iter_mut().for_each(fix);
                s.joints.iter_mut().for_each(fix);
            }
        }
        if let Some(r) = &mut self.reference {
            fix(r);
        }
    }

    /// The frame size (width, height).
    pub fn frame_size(&self) -> Result<(u32, u32)> {
        parse_resolution(&self.resolution, 32).context("resolution")
    }

    pub fn observation_of<'a>(&'a self, p: &'a PolicyConfig) -> &'a ObservationConfig {
        p.observation.as_ref().unwrap_or(&self.observation)
    }

    /// Everything that can be checked before the model is loaded.
    pub fn validate(&self) -> Result<()> {
        ensure!(self.horizon > 0, "horizon must be at least 1 frame");
        let (_, height) = self.frame_size()?;
        check_timeout("timeout_s", self.timeout_s)?;
        if let Some(fps) = self.fps {
            ensure!(fps > 0.0 && fps.is_finite(), "fps {fps} must be positive");
        }
        ensure!(!self.policies.is_empty(), "no [[policies]]");
        ensure!(!self.tasks.is_empty(), "no [[tasks]]");
        for (i, p) in self.policies.iter().enumerate() {
            check_name("policy", &p.name)?;
            ensure!(
                !self.policies[..i].iter().any(|q| q.name == p.name),
                "policy '{}' is listed twice",
                p.name
            );
            ensure!(
                p.url.starts_with("ws://"),
                "policy '{}': url '{}' must start with ws://",
                p.name,
                p.url
            );
            let obs = self.observation_of(p);
            let views = obs.image_keys.len() as u32;
            ensure!(
                views > 0,
                "policy '{}': observation.image_keys is empty",
                p.name
            );
            ensure!(
                height % views == 0,
                "policy '{}': {views} image keys split the {height}-pixel-high frame into unequal views",
                p.name
            );
            obs.image_size()
                .with_context(|| format!("policy '{}'", p.name))?;
            if p.adapter.kind == AdapterKind::Joint && self.fk.is_none() {
                bail!(
                    "policy '{}' uses the joint adapter, which needs a forward-kinematics provider: add [fk] command = [\"program\", \"args\"...] (reads {{\"joints\": [[...]]}} lines, answers {{\"poses\": [[...]]}} lines)",
                    p.name
                );
            }
            if !p.adapter.absolute.is_empty() && p.adapter.kind != AdapterKind::EefDelta {
                bail!(
                    "policy '{}': adapter.absolute only applies to the eef_delta adapter",
                    p.name
                );
            }
        }
        if let Some(fk) = &self.fk {
            ensure!(!fk.command.is_empty(), "[fk] command is empty");
        }
        for (i, t) in self.tasks.iter().enumerate() {
            check_name("task", &t.name)?;
            ensure!(
                !self.tasks[..i].iter().any(|u| u.name == t.name),
                "task '{}' is listed twice",
                t.name
            );
            match (&t.dataset, t.starts.is_empty()) {
                (Some(_), false) => bail!("task '{}': give either dataset or [[tasks.starts]], not both", t.name),
                (None, true) => bail!("task '{}': give a dataset or [[tasks.starts]] (x0 images + initial state files)", t.name),
                (None, false) => ensure!(t.episodes.is_none(), "task '{}': episodes selects dataset episodes; this task has none", t.name),
                (Some(_), true) => {
                    ActionSpec::parse(&t.pose_actions).with_context(|| format!("task '{}': pose_actions", t.name))?;
                    ActionSpec::parse(&t.joint_actions).with_context(|| format!("task '{}': joint_actions", t.name))?;
                }
            }
            for (j, s) in t.starts.iter().enumerate() {
                ensure!(
                    !s.images.is_empty(),
                    "task '{}' start {j}: no images",
                    t.name
                );
                for p in s.images.iter().chain(&s.pose).chain(&s.joints) {
                    ensure!(
                        p.is_file(),
                        "task '{}' start {j}: {} does not exist",
                        t.name,
                        p.display()
                    );
                }
            }
            for (j, r) in t.rules.iter().enumerate() {
                r.validate()
                    .with_context(|| format!("task '{}' rule {j}", t.name))?;
            }
        }
        match self.judge.kind {
            JudgeKind::Http => {
                let url = self
                    .judge
                    .url
                    .as_deref()
                    .context("judge.kind = \"http\" needs judge.url")?;
                ensure!(
                    url.starts_with("http://") || url.starts_with("https://"),
                    "judge.url '{url}' must be http(s)://"
                );
                ensure!(
                    (0.0..=1.0).contains(&self.judge.threshold),
                    "judge.threshold must lie in [0, 1]"
                );
                check_timeout("judge.timeout_s", self.judge.timeout_s)?;
                ensure!(
                    self.judge.max_frames != Some(0),
                    "judge.max_frames must be at least 1"
                );
            }
            JudgeKind::Rules => {
                ensure!(
                    self.judge.url.is_none(),
                    "judge.url is for judge.kind = \"http\""
                );
                for t in &self.tasks {
                    ensure!(
                        !t.rules.is_empty(),
                        "judge.kind = \"rules\" but task '{}' has no [[tasks.rules]]",
                        t.name
                    );
                }
            }
        }
        if let Some(r) = &self.reference {
            ensure!(r.is_file(), "reference {} does not exist", r.display());
        }
        Ok(())
    }
}

impl ColorRule {
    pub fn validate(&self) -> Result<()> {
        let [l, t, r, b] = self.roi;
        ensure!(
            (0.0..=1.0).contains(&l) && (0.0..=1.0).contains(&t) && (0.0..=1.0).contains(&r) && (0.0..=1.0).contains(&b) && l < r && t < b,
            "roi {:?} must be [left, top, right, bottom] fractions with left < right and top < bottom",
            self.roi
        );
        ensure!(
            (0..3).all(|c| self.rgb_min[c] <= self.rgb_max[c]),
            "rgb_min {:?} exceeds rgb_max {:?}",
            self.rgb_min,
            self.rgb_max
        );
        ensure!(self.last_frames > 0, "last_frames must be at least 1");
        ensure!(
            (0.0..=1.0).contains(&self.min_fraction),
            "min_fraction must lie in [0, 1]"
        );
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_example_config_parses_and_unknown_fields_are_refused() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/evaluate-example.toml");
        let text = std::fs::read_to_string(&path).unwrap();
        let cfg = EvalConfig::read(&path).unwrap();
        assert!(cfg.policies.len() >= 2 && cfg.tasks.len() >= 2);
        assert!(
            cfg.tasks.iter().all(|t| t
                .dataset
                .as_ref()
                .is_some_and(|d| d.join("demo.jsonl").is_file())),
            "dataset paths resolve from the config's folder"
        );
        let bad = text.replacen("horizon", "horizn", 1);
        let err = format!("{:#}", toml::from_str::<EvalConfig>(&bad).unwrap_err());
        assert!(err.contains("horizn"), "{err}");
    }

    fn minimal(extra: &str) -> EvalConfig {
        let text = format!(
            r#"
horizon = 8
resolution = "32x64"
{extra}
[[tasks]]
name = "t"
dataset = "/nonexistent"
[judge]
kind = "http"
url = "http://127.0.0.1:1/j"
"#
        );
        toml::from_str(&text).unwrap()
    }

    #[test]
    fn joint_without_fk_is_refused_at_start_up() {
        let cfg = minimal("[[policies]]\nname = \"p\"\nurl = \"ws://127.0.0.1:1\"\nadapter = { kind = \"joint\" }\n");
        let err = format!("{:#}", cfg.validate().unwrap_err());
        assert!(
            err.contains("forward-kinematics provider") && err.contains("[fk]"),
            "{err}"
        );
        let cfg = minimal("[fk]\ncommand = [\"fk\"]\n[[policies]]\nname = \"p\"\nurl = \"ws://127.0.0.1:1\"\nadapter = { kind = \"joint\" }\n");
        cfg.validate().unwrap();
    }

    #[test]
    fn views_must_split_the_frame_and_names_must_be_file_safe() {
        let cfg = minimal(
            "[observation]\nimage_keys = [\"a\", \"b\", \"c\"]\n[[policies]]\nname = \"p\"\nurl = \"ws://127.0.0.1:1\"\n",
        );
        assert!(format!("{:#}", cfg.validate().unwrap_err()).contains("unequal views"));
        let cfg = minimal("[[policies]]\nname = \"../p\"\nurl = \"ws://127.0.0.1:1\"\n");
        assert!(format!("{:#}", cfg.validate().unwrap_err()).contains("letters, digits"));
        let cfg = minimal(
            "[observation]\nimage_keys = [[\"images\", \"cam_high\"], [\"images\", \"cam_low\"]]\n[[policies]]\nname = \"p\"\nurl = \"ws://127.0.0.1:1\"\n",
        );
        cfg.validate().unwrap();
        assert_eq!(
            cfg.observation.image_keys[1].parts(),
            vec!["images".to_string(), "cam_low".to_string()]
        );
    }
}
