//! The model card (`README.md`) of an export, and the summary of the run's `metrics.jsonl` that it
//! and `config.json`'s `training` report.

use std::path::Path;

use anyhow::Result;
use bwm_model::ModelConfig;

use crate::repo::{human_bytes, RepoConfig, WrittenFile, ACTION_STATS_FILE, CONFIG_FILE};
use crate::run_info::{CheckpointState, RunInfo};

/// A summary of the run's `metrics.jsonl`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct MetricsSummary {
    pub records: usize,
    pub last_step: u64,
    pub last_loss: f64,
    pub mean_loss_recent: f64,
    pub recent: usize,
    pub min_loss: f64,
    pub mean_samples_per_s: Option<f64>,
}

/// The summary of the run's metrics up to step `up_to` (the exported checkpoint's; None: all). A
/// step logged twice (a run resumed from a checkpoint before it) counts once, as last logged.
pub fn summarize_metrics(path: &Path, up_to: Option<u64>) -> Result<Option<MetricsSummary>> {
    let Ok(text) = std::fs::read_to_string(path) else { return Ok(None) };
    let by_step: std::collections::BTreeMap<u64, (f64, Option<f64>)> = text
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .filter_map(|v| {
            let step = v.get("step")?.as_u64()?;
            let loss = v.get("loss")?.as_f64()?;
            Some((step, (loss, v.get("samples_per_s").and_then(|s| s.as_f64()))))
        })
        .filter(|(step, (l, _))| l.is_finite() && up_to.is_none_or(|last| *step <= last))
        .collect();
    let rows: Vec<(u64, f64, Option<f64>)> = by_step.into_iter().map(|(step, (loss, sps))| (step, loss, sps)).collect();
    if rows.is_empty() {
        return Ok(None);
    }
    let recent = (rows.len() / 10).clamp(1, 100);
    let tail = &rows[rows.len() - recent..];
    let sps: Vec<f64> = rows.iter().filter_map(|r| r.2).collect();
    Ok(Some(MetricsSummary {
        records: rows.len(),
        last_step: rows[rows.len() - 1].0,
        last_loss: rows[rows.len() - 1].1,
        mean_loss_recent: tail.iter().map(|r| r.1).sum::<f64>() / recent as f64,
        recent,
        min_loss: rows.iter().map(|r| r.1).fold(f64::INFINITY, f64::min),
        mean_samples_per_s: (!sps.is_empty()).then(|| sps.iter().sum::<f64>() / sps.len() as f64),
    }))
}

/// What the model card of an export says.
pub struct CardFacts<'a> {
    /// The exported model's architecture.
    pub model: &'a ModelConfig,
    /// The training run behind the weights, when known (a checkpoint's stored config or `--config`).
    pub run: Option<&'a RunInfo>,
    /// The training checkpoint exported, when the input is one.
    pub state: Option<&'a CheckpointState>,
    /// The repo id the card names (also the `--push` target).
    pub repo_id: Option<&'a str>,
    /// The export's `config.json`.
    pub cfg: &'a RepoConfig,
    pub metrics: Option<MetricsSummary>,
    /// The group of `action_stats.json`, when exported.
    pub stats_group: Option<String>,
    pub files: &'a [WrittenFile],
}

/// The `README.md` of an export: model, training, metrics, actions, files and how to load them.
pub fn model_card(f: &CardFacts) -> String {
    let c = f.model;
    let repo = f.repo_id.map(String::from).unwrap_or_else(|| "OWNER/NAME".into());
    let title = f
        .repo_id
        .and_then(|r| r.split('/').nth(1))
        .map(String::from)
        .or_else(|| f.run.map(|r| r.name().to_string()).filter(|n| !n.is_empty()))
        .unwrap_or_else(|| "BWM world model".into());
    let mut s = String::from("---\nlicense: apache-2.0\n");
    if let Some(b) = &f.cfg.base_model {
        s += &format!("base_model: {b}\n");
    }
    s += "library_name: bwm\npipeline_tag: image-to-video\ntags:\n- world-model\n- robotics\n- action-conditioned\n- video-generation\n- wan2.2\n---\n\n";
    s += &format!("# {title}\n\n");
    s += "An action-conditioned robot world model: the Wan2.2-TI2V DiT driven by the BWM action encoder instead of text \
(frame-level action tokens as the cross-attention context, latent-level action vectors added to the timestep embedding), \
post-trained with the `bwm` trainer. Given the first frame, recent history latents and an action trajectory, it predicts the future video latents (Wan2.2 VAE).\n\n";
    s += "## Model\n\n| | |\n|---|---|\n";
    s += &format!("| base model | {} |\n", f.cfg.base_model.clone().unwrap_or_else(|| "none (trained from random initialization)".into()));
    s += &format!(
        "| DiT | dim {}, {} layers, {} heads, ffn {}, patch {:?}, in/out {} channels |\n",
        c.dit.dim, c.dit.num_layers, c.dit.num_heads, c.dit.ffn_dim, c.dit.patch_size, c.dit.in_dim
    );
    s += &format!(
        "| action interface | {}-D actions, P={} copies of a_0 prepended, G={} actions per latent frame |\n",
        c.action.action_dim, c.action.prepend, c.action.group
    );
    s += &format!("| parameters | {} in {} tensors |\n", f.cfg.weights.parameters, f.cfg.weights.tensors);
    s += &format!("| layout | `{}` |\n| dtype | {} |\n| EMA weights | {} |\n\n", f.cfg.layout, f.cfg.weights.dtype, if f.cfg.weights.ema { "yes" } else { "no" });

    s += "## Training\n\n";
    match (f.run, f.state) {
        (Some(run), state) => {
            s += "| | |\n|---|---|\n";
            s += &format!("| run | `{}` |\n", run.name());
            if let Some(st) = state {
                s += &format!("| steps | {} (optimizer updates {}) |\n| samples seen | {} |\n", st.step, st.optimizer_step, st.samples_seen);
            }
            if let Some(p) = run.steps_planned {
                s += &format!("| steps planned | {p} |\n");
            }
            if let Some(lr) = run.lr {
                s += &format!("| learning rate | {lr} |\n");
            }
            if let (Some(mb), Some(ga)) = (run.micro_batch, run.grad_accum) {
                s += &format!("| batch | micro-batch {mb} x accumulation {ga} |\n");
            }
            if let Some(d) = run.ema_decay {
                s += &format!("| EMA decay | {d} |\n");
            }
            s += &format!("| training dtype | {} |\n", run.stated_dtype().map_or("?", |d| d.name()));
            if let Some(cache) = &run.latent_cache {
                s += &format!("| data | latent cache `{}` ({}) |\n", cache.display(), run.held_out);
            }
            if let Some(cond) = &f.cfg.conditioning {
                let g = |k: &str| cond.get(k).map(|v| v.to_string()).unwrap_or_else(|| "?".into());
                s += &format!(
                    "| clips | {} pixel frames (1 + {} history + {} future), {} condition latents, resolution {}, {} fps |\n",
                    g("pixel_frames"),
                    g("history_frames"),
                    g("future_frames"),
                    g("condition_latents"),
                    g("resolution"),
                    g("fps")
                );
            }
            s += "\n";
        }
        (None, _) => s += "Exported from a weights file; no training run information was given.\n\n",
    }

    s += "## Metrics\n\n";
    match &f.metrics {
        Some(m) => {
            s += "From the run's `metrics.jsonl` (flow-matching training loss, timestep-weighted):\n\n| | |\n|---|---|\n";
            s += &format!("| logged steps | {} (last step {}) |\n", m.records, m.last_step);
            s += &format!("| final loss | {:.5} |\n", m.last_loss);
            s += &format!("| mean loss, last {} logged steps | {:.5} |\n", m.recent, m.mean_loss_recent);
            s += &format!("| lowest logged loss | {:.5} |\n", m.min_loss);
            if let Some(sps) = m.mean_samples_per_s {
                s += &format!("| throughput | {sps:.2} samples/s |\n");
            }
            s += "\n";
        }
        None => s += "No `metrics.jsonl` was found for this export.\n\n",
    }

    s += "## Actions\n\n";
    match &f.stats_group {
        Some(g) => {
            s += &format!(
                "Raw actions are normalized per dimension with the statistics in `{ACTION_STATS_FILE}` (group `{g}`): \
`2*(x - p01)/(p99 - p01 + 1e-8) - 1`, clipped to [-1, 1] (min/max where p01 = p99).\n\n"
            )
        }
        None => s += "No action statistics were exported: normalize actions to [-1, 1] as in training (`2*(x - p01)/(p99 - p01 + 1e-8) - 1` with the dataset's `stat.json`).\n\n",
    }

    s += "## Files\n\n";
    for file in f.files {
        s += &format!("- `{}` ({})\n", file.path, human_bytes(file.bytes));
    }
    s += &format!("- `{CONFIG_FILE}`: model, action interface, clip and normalization settings\n\n");
    if !f.cfg.weights.missing_keys.is_empty() {
        s += &format!(
            "Deliberately absent: {} (`{}`...): {}\n\n",
            f.cfg.weights.missing_keys.len(),
            f.cfg.weights.missing_keys[0],
            f.cfg.weights.missing_reason.clone().unwrap_or_default()
        );
    }

    s += "## How to load\n\n";
    s += &format!(
        "With `bwm` (any layout, picked from the files; a local folder or a Hub repo id through the Hugging Face cache):\n\n```rust\nlet model = bwm_checkpoints::open::load_model(\"{repo}\", None, tch::Kind::BFloat16, tch::Device::Cuda(0))?;\n```\n\n\
or `bwm convert dit {repo} OUT --to wan|diffusers|bwm-release`.\n\n"
    );
    let layout = f.cfg.layout.as_str();
    match layout {
        "diffusers" => {
            s += "With diffusers (the DiT; the action encoder is the `action_encoder/` component, which diffusers has no class for):\n\n```python\nfrom diffusers import WanTransformer3DModel\n";
            s += &format!("dit = WanTransformer3DModel.from_pretrained(\"{repo}\", subfolder=\"transformer\")\n```\n\n");
            s += "diffusers reports `condition_embedder.text_embedder.*` as newly initialized: it is absent on purpose (unused with actions).\n\n";
        }
        _ => {
            let prefix = f.cfg.weights.action_encoder_prefix.clone();
            s += "With DiffSynth-Studio (`diffsynth==2.0.11`, as the BWM release):\n\n```python\nimport json, torch\nfrom safetensors.torch import load_file\nfrom diffsynth.models.wan_video_dit import WanModel\n";
            s += "index = json.load(open(\"model.safetensors.index.json\"))\nsd = {}\nfor f in sorted(set(index[\"weight_map\"].values())):\n    sd.update(load_file(f))\n";
            s += &format!("enc = {{k[len(\"{prefix}\"):]: v for k, v in sd.items() if k.startswith(\"{prefix}\")}}\ndit_sd = {{k: v for k, v in sd.items() if not k.startswith(\"{prefix}\")}}\n");
            s += &format!(
                "dit = WanModel(dim={}, in_dim={}, ffn_dim={}, out_dim={}, text_dim={}, freq_dim={}, eps={:e}, patch_size={:?}, num_heads={}, num_layers={},\n              has_image_input=False, seperated_timestep=True, require_clip_embedding=False, require_vae_embedding=False, fuse_vae_embedding_in_latents=True)\n",
                c.dit.dim, c.dit.in_dim, c.dit.ffn_dim, c.dit.out_dim, c.dit.text_dim, c.dit.freq_dim, c.dit.eps, c.dit.patch_size, c.dit.num_heads, c.dit.num_layers
            );
            s += "missing, unexpected = dit.load_state_dict(dit_sd, strict=False)   # missing: text_embedding.* only\n```\n\n";
        }
    }
    s += "## License\n\nApache-2.0, as the Wan2.2 base model.\n";
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_summary_stops_at_the_exported_step_and_counts_a_relogged_step_once() {
        let dir = bwm_testdir::tmp_dir("model-card-metrics");
        let path = dir.path().join("metrics.jsonl");
        // Steps 1-3, then a resume from step 2's checkpoint logs 3 again, then 4 and 5.
        let lines = [(1, 4.0), (2, 3.0), (3, 9.0), (3, 2.0), (4, 1.5), (5, 1.0)];
        std::fs::write(&path, lines.iter().map(|(s, l)| format!("{{\"step\": {s}, \"loss\": {l}}}\n")).collect::<String>()).unwrap();
        let at3 = summarize_metrics(&path, Some(3)).unwrap().unwrap();
        assert_eq!((at3.records, at3.last_step, at3.last_loss, at3.min_loss), (3, 3, 2.0, 2.0));
        let all = summarize_metrics(&path, None).unwrap().unwrap();
        assert_eq!((all.records, all.last_step, all.last_loss), (5, 5, 1.0));
    }
}
