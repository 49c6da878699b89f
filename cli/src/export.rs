//! `bwm export`: a training checkpoint (or any weights) as a Hugging Face model repository folder,
//! optionally pushed to the Hub.

use std::path::PathBuf;

use anyhow::{Context, Result};
use bwm_checkpoints::export::{export, ExportDtype, ExportOptions};
use bwm_checkpoints::hub::{push_folder, HubEnv, PushEvent, PushOptions};
use bwm_checkpoints::repo::{human_bytes, parse_size};
use bwm_checkpoints::DitLayout;
use clap::Args;

#[derive(Args)]
pub struct ExportArgs {
    /// A training checkpoint folder (`runs/NAME/checkpoints/step-00001000`), or weights in any
    /// layout (file, folder or Hub repo id) together with --config or --preset.
    #[arg(long)]
    checkpoint: String,
    /// The repository folder to write (appears atomically when complete).
    #[arg(long)]
    out: PathBuf,
    /// Key layout: wan (Wan-native / DiffSynth names), diffusers (WanTransformer3DModel +
    /// action_encoder/ component) or bwm-release (the public BWM checkpoint's names).
    #[arg(long, default_value = "wan")]
    layout: DitLayout,
    /// Export the EMA weights kept in the checkpoint's optimizer.safetensors.
    #[arg(long)]
    ema: bool,
    /// A LoRA checkpoint: merge its adapters into the base weights (--base, else the run's
    /// model.init) and write full weights. Without it a LoRA checkpoint's adapters are written
    /// alone, in the diffusers/PEFT layout (pytorch_lora_weights.safetensors) whatever --layout.
    #[arg(long)]
    merge_lora: bool,
    /// Stored dtype: bf16 or fp32.
    #[arg(long, default_value = "bf16")]
    dtype: ExportDtype,
    /// Largest shard (5GB, 500MB, 2GiB, ...).
    #[arg(long, default_value = "5GB")]
    shard_size: String,
    /// The dataset's stat.json; the normalization group is copied into action_stats.json.
    #[arg(long)]
    action_stats: Option<PathBuf>,
    /// The stat.json group the actions were normalized with.
    #[arg(long, default_value = "state_pose")]
    action_stats_group: String,
    /// Run config TOML (a bare weights file; for a checkpoint it must match the stored config).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Model preset for a bare weights file (tiny, wan22_ti2v_5b).
    #[arg(long)]
    preset: Option<String>,
    /// Weights (path or repo id) for frozen tensors the checkpoint lacks; default: the run's model.init.
    #[arg(long)]
    base: Option<String>,
    /// The run's metrics.jsonl (default: found beside the run's checkpoints/ folder).
    #[arg(long)]
    metrics: Option<PathBuf>,
    /// Hub id of the base model named in the model card.
    #[arg(long)]
    base_model: Option<String>,
    /// Replace a non-empty output folder.
    #[arg(long)]
    overwrite: bool,
    /// Upload the folder to this Hub model repo (OWNER/NAME); token from HF_TOKEN, endpoint from
    /// HF_ENDPOINT. The repo's files become the folder's: files of an earlier push that the folder
    /// does not hold are deleted (the Hub's .gitattributes stays).
    #[arg(long, value_name = "OWNER/NAME")]
    push: Option<String>,
    /// Create the pushed repo private (an existing public repo is refused).
    #[arg(long, requires = "push")]
    private: bool,
}

pub fn run(args: ExportArgs) -> Result<()> {
    let env = HubEnv::from_env();
    if let Some(repo) = &args.push {
        // Fail before the (long) export when the push cannot happen.
        anyhow::ensure!(bwm_checkpoints::hub::is_repo_id(repo) && !repo.contains('@'), "--push expects OWNER/NAME, got '{repo}'");
        anyhow::ensure!(env.token.is_some(), "--push needs a Hugging Face token with write access: set HF_TOKEN (or log in with `hf auth login`)");
    }
    let opts = ExportOptions {
        layout: args.layout,
        dtype: args.dtype,
        ema: args.ema,
        merge_lora: args.merge_lora,
        shard_size: parse_size(&args.shard_size).context("--shard-size")?,
        overwrite: args.overwrite,
        action_stats: args.action_stats,
        action_stats_group: Some(args.action_stats_group),
        base: args.base,
        config: args.config,
        preset: args.preset,
        metrics: args.metrics,
        repo_id: args.push.clone(),
        base_model_id: args.base_model,
        fail_after_shards: None,
    };
    if !args.merge_lora && bwm_checkpoints::lora_export::is_lora_checkpoint(&args.checkpoint)? {
        anyhow::ensure!(args.push.is_none(), "--push of a LoRA checkpoint's adapters is not supported; push the --merge-lora export, or upload the adapter folder");
        let unheld: Vec<&str> = [
            ("--ema", opts.ema),
            ("--action-stats", opts.action_stats.is_some()),
            ("--base", opts.base.is_some()),
            ("--config", opts.config.is_some()),
            ("--metrics", opts.metrics.is_some()),
            ("--base-model", opts.base_model_id.is_some()),
        ]
        .into_iter()
        .filter_map(|(flag, given)| given.then_some(flag))
        .collect();
        anyhow::ensure!(
            unheld.is_empty(),
            "{}: a LoRA checkpoint's adapters are exported alone, in the diffusers/PEFT layout, which holds none of that; pass --merge-lora to export merged weights with it",
            unheld.join(", ")
        );
        let a = bwm_checkpoints::lora_export::export_lora_adapters(&args.checkpoint, &args.out, args.dtype, args.overwrite)?;
        println!(
            "exported the LoRA adapters of {} layers ({} parameters, diffusers/PEFT layout) to {}",
            a.layers,
            a.parameters,
            a.out.join(bwm_checkpoints::lora_export::LORA_WEIGHTS_FILE).display()
        );
        if !a.left_out.is_empty() {
            println!(
                "left out: {} trained tensors besides the adapters (e.g. {}); an adapter file cannot hold them, --merge-lora writes them with the merged weights",
                a.left_out.len(),
                a.left_out[0]
            );
        }
        return Ok(());
    }
    let report = export(&args.checkpoint, &args.out, &opts, &mut |line| eprintln!("{line}"))?;
    let bytes: u64 = report.files.iter().map(|f| f.bytes).sum();
    println!(
        "exported {} tensors ({} parameters, {} layout) to {} ({} files, {})",
        report.tensors,
        report.parameters,
        report.layout,
        report.out.display(),
        report.files.len(),
        human_bytes(bytes)
    );
    if !report.declared_missing.is_empty() {
        println!("declared missing (unused with actions): {} tensors under text_embedding.*", report.declared_missing.len());
    }
    if report.from_base > 0 {
        println!("{} frozen tensors the checkpoint lacks were taken from the base weights", report.from_base);
    }
    if let Some(repo) = &args.push {
        push(&args.out, repo, args.private, &env).with_context(|| {
            format!(
                "the export in {} is complete; retry the upload alone with `bwm push --dir {} --repo {repo}{}`",
                args.out.display(),
                args.out.display(),
                if args.private { " --private" } else { "" }
            )
        })?;
    }
    Ok(())
}

/// `bwm push`: uploads a finished export folder, as `bwm export --push` does after exporting (to
/// retry a push that failed without exporting again).
#[derive(Args)]
pub struct PushArgs {
    /// The export folder (`bwm export --out`).
    #[arg(long)]
    dir: PathBuf,
    /// The Hub model repo (OWNER/NAME); token from HF_TOKEN, endpoint from HF_ENDPOINT. The repo's
    /// files become the folder's: files of an earlier push that the folder does not hold are
    /// deleted (the Hub's .gitattributes stays).
    #[arg(long, value_name = "OWNER/NAME")]
    repo: String,
    /// Create the repo private (an existing public repo is refused).
    #[arg(long)]
    private: bool,
}

pub fn run_push(args: PushArgs) -> Result<()> {
    let env = HubEnv::from_env();
    anyhow::ensure!(bwm_checkpoints::hub::is_repo_id(&args.repo) && !args.repo.contains('@'), "--repo expects OWNER/NAME, got '{}'", args.repo);
    // Only what loads: a complete export (config.json, every shard its index names), not a folder
    // an export left cut short.
    bwm_checkpoints::open::open_local(&args.dir).with_context(|| format!("{}: not a complete `bwm export` folder", args.dir.display()))?;
    push(&args.dir, &args.repo, args.private, &env)
}

/// Pushes `dir` to `repo`, printing progress.
fn push(dir: &std::path::Path, repo: &str, private: bool, env: &HubEnv) -> Result<()> {
    let opts = PushOptions::new(repo, private, env);
    let mut last_pct = std::collections::BTreeMap::new();
    let pushed = push_folder(dir, &opts, &mut |e| match e {
        PushEvent::RepoReady { url, created } => eprintln!("{} {url}", if *created { "created" } else { "using existing" }),
        PushEvent::Hashed { path, bytes } => eprintln!("hashed {path} ({})", human_bytes(*bytes)),
        PushEvent::Uploading { path, sent, total } => {
            let pct = if *total == 0 { 100 } else { sent * 100 / total };
            if last_pct.insert(path.clone(), pct) != Some(pct) {
                eprintln!("uploading {path}: {pct}% of {}", human_bytes(*total));
            }
        }
        PushEvent::AlreadyOnHub { path } => eprintln!("{path}: already on the Hub"),
        PushEvent::Deleting { paths } => eprintln!("deleting {} files of an earlier push that this export does not hold: {}", paths.len(), paths.join(", ")),
        PushEvent::Committing { files } => eprintln!("committing {files} files"),
    })?;
    println!(
        "pushed to {} ({} LFS files, {} regular){}",
        pushed.repo_url,
        pushed.lfs_files,
        pushed.regular_files,
        pushed.commit_url.map(|u| format!(": {u}")).unwrap_or_default()
    );
    Ok(())
}
