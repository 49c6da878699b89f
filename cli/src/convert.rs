//! `bwm convert`: DiT weights between the wan, diffusers and bwm-release layouts; the Wan2.2 VAE
//! from `.pth` (or diffusers names) to safetensors.

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use bwm_checkpoints::convert::{convert_dit, convert_vae, ConvertOptions, VaeNaming};
use bwm_checkpoints::export::ExportDtype;
use bwm_checkpoints::repo::{human_bytes, parse_size};
use bwm_checkpoints::run_info::RunInfo;
use bwm_checkpoints::DitLayout;
use bwm_model::ModelConfig;
use clap::{Args, Subcommand};

#[derive(Args)]
pub struct ConvertArgs {
    #[command(subcommand)]
    what: ConvertWhat,
}

#[derive(Subcommand)]
enum ConvertWhat {
    /// The DiT + action encoder: INPUT in any layout (file, folder or Hub repo id; detected) to
    /// OUTPUT, one .safetensors file or a sharded repository folder.
    Dit(DitArgs),
    /// The Wan2.2 VAE: a .pth or safetensors file (Wan or diffusers names; detected) to one
    /// .safetensors file.
    Vae(VaeArgs),
}

#[derive(Args)]
struct DitArgs {
    input: String,
    /// A file ending in .safetensors, or a folder (shards + index).
    output: PathBuf,
    /// Target layout: wan, diffusers or bwm-release.
    #[arg(long)]
    to: DitLayout,
    /// Stored dtype: keep, bf16 or fp32.
    #[arg(long, default_value = "keep")]
    dtype: String,
    /// Largest shard of a folder output.
    #[arg(long, default_value = "5GB")]
    shard_size: String,
    /// Model preset when the input carries no config (tiny, wan22_ti2v_5b).
    #[arg(long)]
    preset: Option<String>,
    /// Run config TOML giving the model config.
    #[arg(long, conflicts_with = "preset")]
    config: Option<PathBuf>,
    #[arg(long)]
    overwrite: bool,
}

#[derive(Args)]
struct VaeArgs {
    input: PathBuf,
    /// The .safetensors file to write.
    output: PathBuf,
    /// Target names: wan (`Wan2.2_VAE.pth` names, what bwm loads) or diffusers (AutoencoderKLWan).
    #[arg(long, default_value = "wan")]
    to: VaeNaming,
    /// Stored dtype: keep, bf16 or fp32.
    #[arg(long, default_value = "keep")]
    dtype: String,
    #[arg(long)]
    overwrite: bool,
}

fn dtype(s: &str) -> Result<Option<ExportDtype>> {
    Ok(match s {
        "keep" => None,
        other => Some(other.parse()?),
    })
}

pub fn run(args: ConvertArgs) -> Result<()> {
    match args.what {
        ConvertWhat::Dit(a) => {
            let model = match (&a.preset, &a.config) {
                (Some(p), _) => Some(ModelConfig::preset(p)?),
                (None, Some(c)) => Some(RunInfo::load(c)?.model),
                (None, None) => None,
            };
            let opts = ConvertOptions {
                to: a.to,
                dtype: dtype(&a.dtype).context("--dtype")?,
                shard_size: parse_size(&a.shard_size).context("--shard-size")?,
                overwrite: a.overwrite,
                model,
            };
            let r = convert_dit(&a.input, &a.output, &opts, &mut |line| eprintln!("{line}"))?;
            let bytes: u64 = r.files.iter().map(|f| f.bytes).sum();
            println!("converted {} tensors from {} to {}: {} ({})", r.tensors, r.from, r.to, a.output.display(), human_bytes(bytes));
            if !r.dropped.is_empty() {
                println!("left out {} text_embedding tensors (the bwm-release layout has none)", r.dropped.len());
            }
        }
        ConvertWhat::Vae(a) => {
            if a.output.extension().and_then(|e| e.to_str()) != Some("safetensors") {
                bail!("{}: the VAE output must be a .safetensors file", a.output.display());
            }
            let r = convert_vae(&a.input, &a.output, a.to, dtype(&a.dtype).context("--dtype")?, a.overwrite)?;
            println!("converted {} VAE tensors ({:?} names -> {:?} names): {} ({})", r.tensors, r.from, r.to, a.output.display(), human_bytes(r.bytes));
        }
    }
    Ok(())
}
