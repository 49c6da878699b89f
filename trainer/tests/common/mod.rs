#![allow(dead_code)]
//! Shared pieces of the trainer tests: a synthetic latent cache written through the real cache
//! writer, and a tiny run config.

use std::path::{Path, PathBuf};

use bwm_data::latent_cache::{CacheIndex, CacheWriter, ClipEntry};
use bwm_trainer::RunConfig;
use tch::{Device, Kind, Tensor};

#[allow(unused_imports)]
pub use bwm_testdir::tmp_dir;

/// `clips` clips of 4 latent frames (3 condition + 1 future) of 4x4, with 13 action frames.
/// Latents are smooth functions of the actions so that there is something to learn.
pub fn write_cache(dir: &Path, clips: usize, seed: i64) -> PathBuf {
    let _guard = rng_lock();
    write_cache_unlocked(dir, clips, seed)
}

/// `write_cache` for a caller that already holds `rng_lock`.
pub fn write_cache_unlocked(dir: &Path, clips: usize, seed: i64) -> PathBuf {
    tch::manual_seed(seed);
    let index = CacheIndex::new(vec![48, 4, 4, 4], 14, 8, 4, [64, 64], 25.0, "synthetic");
    let mut w = CacheWriter::create(dir, index).unwrap();
    for i in 0..clips {
        let actions = Tensor::rand([13, 14], (Kind::Float, Device::Cpu)) * 2.0 - 1.0;
        let base = Tensor::randn([48, 1, 4, 4], (Kind::Float, Device::Cpu));
        let drift = actions.mean_dim(&[1i64][..], false, Kind::Float).narrow(0, 0, 4).view([1, 4, 1, 1]);
        let latents = &base + drift * 2.0;
        w.add(ClipEntry { file: String::new(), episode: i as i64, frames: (0..13).collect(), task: "synthetic".into() }, &latents, &actions, None)
            .unwrap();
    }
    w.finish().unwrap();
    dir.to_path_buf()
}

/// A 1-layer model of the tiny family on the CPU, f32, no TensorBoard, no progress bar.
pub fn config(cache: &Path, out: &Path, extra: &str) -> RunConfig {
    try_config(cache, out, extra).unwrap()
}

/// `config`, with the parse error of an invalid `extra`.
pub fn try_config(cache: &Path, out: &Path, extra: &str) -> anyhow::Result<RunConfig> {
    let text = format!(
        r#"
[run]
name = "test"
out_dir = "{out}"
seed = 3
device = "cpu"

[model]
preset = "tiny"
dtype = "f32"
dit = {{ dim = 48, in_dim = 48, out_dim = 48, ffn_dim = 96, freq_dim = 32, text_dim = 16, num_heads = 2, num_layers = 2, eps = 1e-6, patch_size = [1, 2, 2] }}

[data]
latent_cache = "{cache}"

[optim]
lr = 1e-3
warmup_steps = 2

[train]
steps = 4
recompute = true

[log]
tensorboard = false
progress = false
{extra}
"#,
        out = out.display(),
        cache = cache.display()
    );
    parse_with_sections(&text)
}

/// Merges `extra` (which may repeat a section, e.g. `[train]`) into the base text.
fn parse_with_sections(text: &str) -> anyhow::Result<RunConfig> {
    let mut root = toml::Table::new();
    let mut chunks: Vec<(String, String)> = Vec::new();
    for line in text.lines() {
        let t = line.trim();
        if t.starts_with('[') && t.ends_with(']') && !t.contains('=') {
            chunks.push((t[1..t.len() - 1].to_string(), String::new()));
        } else if let Some(last) = chunks.last_mut() {
            last.1.push_str(line);
            last.1.push('\n');
        }
    }
    for (section, body) in chunks {
        let table: toml::Table = toml::from_str(&body).unwrap();
        let entry = root.entry(section).or_insert_with(|| toml::Value::Table(toml::Table::new()));
        for (k, v) in table {
            entry.as_table_mut().unwrap().insert(k, v);
        }
    }
    RunConfig::parse(&toml::to_string(&root).unwrap(), &[])
}

/// Random initialization draws from libtorch's global generator: tests that build models hold
/// this lock so that parallel tests do not interleave their draws.
pub fn rng_lock() -> std::sync::MutexGuard<'static, ()> {
    static LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());
    LOCK.lock().unwrap_or_else(|e| e.into_inner())
}

/// `Trainer::new` under the generator lock.
pub fn trainer(cfg: RunConfig, resume: bwm_trainer::Resume) -> anyhow::Result<bwm_trainer::Trainer> {
    let _guard = rng_lock();
    bwm_trainer::Trainer::new(cfg, resume)
}

/// Mean loss over fixed draws (sample indices 10_000..10_008) of clip 0, without gradients.
pub fn eval_loss(t: &bwm_trainer::Trainer) -> f64 {
    let clip = t.cache.load(0, tch::Device::Cpu).unwrap();
    let obj = &t.objective;
    let mut sum = 0.0;
    for g in 10_000..10_008u64 {
        let d = obj.draw(g, &t.cache.index.latent_shape);
        let p = obj.prepare(&clip.latents.unsqueeze(0), &d.noise.unsqueeze(0), &d.history_noise.unsqueeze(0), &[d.timestep_index]).unwrap();
        let pred = tch::no_grad(|| t.model.forward(&p.input, &p.frame_timesteps, &clip.actions.unsqueeze(0))).unwrap();
        sum += obj.loss(&pred, &p).double_value(&[]);
    }
    sum / 8.0
}

pub fn max_abs_diff(a: &Tensor, b: &Tensor) -> f64 {
    (a - b).abs().max().double_value(&[])
}
