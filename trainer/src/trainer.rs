//! The training run: model init, the step (micro-batches, accumulation, recomputation, AdamW),
//! non-finite handling, checkpoints and resume, metrics, validation.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::rc::Rc;
use std::time::Instant;

use anyhow::{bail, ensure, Context, Result};
use bwm_checkpoints::optimizer_shards::OptimizerState;
use bwm_checkpoints::run_dir::RunLock;
use bwm_checkpoints::{write_tensors, CheckpointRoot};
use bwm_checkpoints::contract::InputContract;
use bwm_data::latent_cache::{clip_for_sample, global_sample_index, CacheIndex, Clip, LatentCache};
use bwm_data::prefetch::{load_clips, ClipBatch, Prefetcher};
use bwm_model::lora::LoraState;
use bwm_model::vae::{VaeConfig, WanVae};
use bwm_model::weights::{SafetensorsSource, WeightSource};
use bwm_model::{BwmModel, ModelConfig, ParamStore};
use serde::{Deserialize, Serialize};
use tch::{Device, Kind, Tensor};

use crate::config::{InitSource, RunConfig};
use crate::dist::{Backend, Collective, DistEnv};
use crate::distill::Distillation;
use crate::flops;
use crate::metrics::{Progress, StepMetrics};
use crate::objective::Objective;
use crate::optim::{AdamW, Sharding};
use crate::recompute::{forward_backward_per_sample, BlockGradSink, Recompute};
use crate::run_log::LineLog;
use crate::step_graph::StepGraph;
use crate::tensorboard::EventWriter;
use crate::validation;

/// Where a run starts.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Resume {
    /// A fresh run (an existing checkpoint folder is an error, so nothing is overwritten).
    No,
    /// The newest complete checkpoint of the run folder, or fresh when there is none.
    Auto,
    /// This checkpoint folder; it must exist and match the config.
    Path(PathBuf),
}

impl std::str::FromStr for Resume {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> Result<Self> {
        Ok(match s {
            "no" | "none" => Resume::No,
            "auto" => Resume::Auto,
            path => Resume::Path(PathBuf::from(path)),
        })
    }
}

/// What a checkpoint's `state.json` holds besides the tensors.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainState {
    /// Optimizer steps attempted (the next step's index); updates skipped for non-finite values
    /// count too.
    pub step: u64,
    /// AdamW updates applied (bias correction counts these).
    pub optimizer_step: u64,
    /// Global samples consumed: the loader position.
    pub samples_seen: u64,
    pub nonfinite_in_row: u32,
    pub nonfinite_total: u64,
    pub world_size: usize,
    /// Names of the trained tensors, in order.
    pub trainable: Vec<String>,
    /// The run config the checkpoint was written with (TOML).
    pub config: String,
}

pub struct Trainer {
    pub cfg: RunConfig,
    pub model: BwmModel,
    /// The shared state of the model's LoRA adapters (`model.lora`): their dropout is on while a
    /// step trains.
    pub lora: Option<Rc<LoraState>>,
    pub opt: AdamW,
    pub objective: Objective,
    pub cache: LatentCache,
    /// What a caller of the trained model must send it, written into every checkpoint
    /// (`contract.json`), from what the cache records of how its clips were made.
    pub contract: InputContract,
    /// Encodes the clips of a raw cache as they are read (`data.vae`); None for a cache of latents.
    pub clip_encoder: Option<WanVae>,
    /// Reads the next micro-batches in the background (started by the first `load_batch`).
    loader: std::sync::Mutex<Loader>,
    pub train_clips: usize,
    pub device: Device,
    pub state: TrainState,
    pub out_dir: PathBuf,
    pub checkpoints: CheckpointRoot,
    events: Option<EventWriter>,
    metrics_file: Option<LineLog>,
    /// Validations in a row whose action gap was negligible (`validation::NEGLIGIBLE_ACTION_GAP`).
    negligible_action_gaps: u32,
    /// `losses.tsv`: every step's loss (the loss curve; `metrics.jsonl` holds logged steps only).
    loss_file: Option<LineLog>,
    /// The data-parallel group (a group of one without torchrun's variables).
    pub comm: Box<dyn Collective>,
    /// The run folder's lock (`train.lock`), held by rank 0 until the trainer is dropped.
    pub run_lock: Option<RunLock>,
    /// Where each step's summary goes (stdout by default; tests capture it).
    pub history: Vec<StepMetrics>,
    /// Per DiT block, the indices in `opt.params` of its trained parameters.
    block_params: Vec<Vec<usize>>,
    /// The step recorded as a CUDA graph (`train.cuda_graph`).
    graph: Option<StepGraph>,
    /// The teacher and grid of step distillation (`[distill]`), which then makes the batches.
    pub distill: Option<Distillation>,
}

/// The run's model, with its LoRA adapters (`model.lora`) and their shared state.
fn build_model(cfg: &RunConfig, model_cfg: &ModelConfig, device: Device) -> Result<(BwmModel, Option<Rc<LoraState>>)> {
    let kind = cfg.model.dtype.kind();
    // The adapters are added to the built model (drawn from their own keyed streams, they leave
    // the base weights' draws as they were), before the weight file's keys are checked.
    let mut lora = None;
    let mut with_lora = |model: &mut BwmModel| -> Result<()> {
        if let Some(cfg_lora) = &cfg.model.lora {
            lora = Some(bwm_model::lora::add_adapters(model, cfg_lora.clone(), cfg.run.seed)?);
        }
        Ok(())
    };
    let model = match &cfg.model.init {
        InitSource::Random => bwm_model::vb::with_seed(cfg.run.seed as i64, || {
            let store = ParamStore::random(kind, device);
            BwmModel::build_converted(&store, model_cfg, &mut with_lora)
        }),
        // Any layout (Wan-native, diffusers, BWM release, an export of this trainer), local or a
        // Hub repo id, presented under Wan-native names.
        InitSource::BwmCheckpoint { path } => {
            let opened = bwm_checkpoints::open::open_any(&path.to_string_lossy())?;
            let (store, model_cfg, what) = bwm_checkpoints::open::weight_store(opened, Some(model_cfg), kind, device)?;
            BwmModel::build_converted(&store, &model_cfg, &mut with_lora).with_context(|| format!("building the model from {what}"))
        }
        InitSource::WanPretrained { path } => {
            // The DiT from the official shards; the action encoder is new, its output layers zero,
            // so at step 0 the cross-attention context is zero and the time embedding unchanged.
            let opened = bwm_checkpoints::open::open_any(&path.to_string_lossy())?;
            let model = bwm_model::vb::with_seed(cfg.run.seed as i64, || {
                let store = ParamStore::from_weights_with_fresh(
                    opened.into_source(),
                    bwm_model::bwm::ACTION_MODE_OPTIONAL,
                    &["action_encoder."],
                    kind,
                    device,
                );
                BwmModel::build_converted(&store, model_cfg, &mut with_lora)
            })?;
            tch::no_grad(|| {
                for l in [&model.action_encoder.action_mlp1.l2, &model.action_encoder.action_mlp2.l2] {
                    let _ = l.weight.shallow_clone().zero_();
                    let _ = l.bias.shallow_clone().zero_();
                }
            });
            Ok(model)
        }
    }?;
    Ok((model, lora))
}

impl Trainer {
    /// A trainer for this process's place in the job: torchrun's variables (RANK, WORLD_SIZE,
    /// LOCAL_RANK, MASTER_ADDR, MASTER_PORT) make it one rank of a data-parallel group, over NCCL
    /// on `cuda:LOCAL_RANK` or over TCP on the CPU.
    pub fn new(cfg: RunConfig, resume: Resume) -> Result<Self> {
        let env = DistEnv::from_env()?;
        let mut cfg = cfg;
        if env.world_size > 1 && cfg.run.device != "cpu" && tch::Cuda::is_available() {
            cfg.run.device = format!("cuda:{}", env.local_rank);
        }
        let device = bwm_model::device::parse_device(&cfg.run.device)?;
        let backend = if device.is_cuda() { Backend::Nccl } else { Backend::Tcp };
        let comm = crate::dist::init(backend, &env).context("joining the data-parallel group")?;
        Self::with_collective(cfg, resume, comm)
    }

    pub fn with_collective(cfg: RunConfig, resume: Resume, mut comm: Box<dyn Collective>) -> Result<Self> {
        let device = bwm_model::device::parse_device(&cfg.run.device)?;
        let model_cfg = cfg.model.model_config()?;
        let out_dir = cfg.out_dir();
        let checkpoints = CheckpointRoot::new(out_dir.join("checkpoints"));
        // Checked before the lock, whoever holds it: an existing run started fresh, a missing
        // checkpoint folder.
        resume_folder(&resume, &checkpoints)?;

        let cache = LatentCache::open(&cfg.data.latent_cache)?;
        let train_clips = cache.training_clips(cfg.data.holdout_episodes)?;
        let contract = InputContract::from_index(model_cfg.action.action_dim as usize, &cache.index, &cache.extras, &cfg.data.latent_cache)
            .context("the input contract of the run's latent cache")?;
        let latent_frames = cache.index.latent_shape[1];
        ensure!(
            latent_frames > cfg.objective.condition_latents,
            "cached clips have {latent_frames} latent frames; objective.condition_latents = {} leaves no future latent",
            cfg.objective.condition_latents
        );
        let channels = cache.index.latent_shape[0];
        ensure!(
            channels == model_cfg.dit.in_dim && channels == model_cfg.dit.out_dim,
            "cached latents have {channels} channels (the VAE's z_dim); model.dit.in_dim and out_dim are {} and {}",
            model_cfg.dit.in_dim,
            model_cfg.dit.out_dim
        );
        ensure!(
            cache.index.action_dim == model_cfg.action.action_dim,
            "cached actions have {} dimensions; model.action.action_dim is {}",
            cache.index.action_dim,
            model_cfg.action.action_dim
        );

        // The lock creates the run folder: taken once the config and the cache agree, so that a
        // refused config leaves nothing behind.
        let run_lock = lock_run_folder(&out_dir, &checkpoints, comm.as_mut(), device)?;
        // Decided under the lock, after a crash's leftovers are repaired (a checkpoint put back
        // counts).
        let resume_from = resume_folder(&resume, &checkpoints)?;

        let clip_encoder = clip_encoder(&cfg, &cache, device)?;
        let (mut model, lora) = build_model(&cfg, &model_cfg, device)?;
        model.dit.residual = cfg.model.residual.kind(cfg.model.dtype.kind());
        if cfg.train.fp8 {
            bwm_model::fp8::train_in_fp8(&mut model, bwm_model::fp8::BLOCK_LINEARS, cfg.train.fp8_min_rows as i64).context("train.fp8")?;
        }
        let graph = if cfg.train.cuda_graph { Some(StepGraph::new(&cfg, device, comm.world_size(), lora.is_some())?) } else { None };
        let named = model.store.named_parameters();
        let sharding = Sharding { rank: comm.rank(), world: comm.world_size(), sharded: cfg.train.shard_optimizer };
        let mut opt = AdamW::new(&named, &cfg.trainable_patterns(), &cfg.train.frozen, &cfg.optim, cfg.train.steps, sharding)?;
        let block_params: Vec<Vec<usize>> = (0..model.dit.blocks.len())
            .map(|b| {
                let prefix = format!("blocks.{b}.");
                opt.params.iter().enumerate().filter(|(_, p)| p.name.starts_with(&prefix)).map(|(k, _)| k).collect()
            })
            .collect();
        let objective = Objective::new(&cfg.objective, cfg.run.seed);
        let distill = match &cfg.distill {
            Some(d) => Some(Distillation::new(d, &model_cfg, cfg.objective.shift, cfg.model.dtype.kind(), device, cfg.run.seed)?),
            None => None,
        };
        let config_text = cfg.to_toml()?;
        let mut state = TrainState {
            step: 0,
            optimizer_step: 0,
            samples_seen: 0,
            nonfinite_in_row: 0,
            nonfinite_total: 0,
            world_size: 1,
            trainable: opt.params.iter().map(|p| p.name.clone()).collect(),
            config: config_text,
        };
        if let Some(dir) = &resume_from {
            state = restore(dir, &cfg, &mut opt, &state.trainable, comm.as_mut())?;
        }
        state.world_size = comm.world_size();
        check_identical_weights(comm.as_mut(), &opt)?;
        std::fs::create_dir_all(&out_dir).with_context(|| format!("creating {}", out_dir.display()))?;
        std::fs::write(out_dir.join("config.toml"), cfg.to_toml()?)?;
        let lead = comm.rank() == 0;
        let events = if cfg.log.tensorboard && lead { Some(EventWriter::create(&out_dir.join("tensorboard"))?) } else { None };
        let append = |name: &str| -> Result<Option<LineLog>> { if lead { LineLog::open(&out_dir.join(name)).map(Some) } else { Ok(None) } };
        let (metrics_file, loss_file) = (append("metrics.jsonl")?, append(crate::run_log::LOSSES_FILE)?);
        Ok(Self { cfg, model, lora, opt, objective, cache, contract, clip_encoder, loader: Default::default(), train_clips, device, state, out_dir, checkpoints, events, metrics_file, negligible_action_gaps: 0, loss_file, comm, run_lock, history: Vec::new(), block_params, graph, distill })
    }

    /// Checks the VAE that validation and the end-of-run rollout decode the cache's latents with
    /// (`validation.vae`, where set) before training starts, not at the first validation steps
    /// into the run.
    pub fn check_validation_vae(&self) -> Result<()> {
        let Some(path) = &self.cfg.validation.vae else { return Ok(()) };
        let vae = WanVae::config_of(path).with_context(|| format!("validation.vae {}", path.display()))?;
        check_vae_fits(&vae, &self.cache.index, &self.cache.dir, &format!("validation.vae {}", path.display()))
    }

    /// Trains to `train.steps`, checkpointing and validating as configured.
    pub fn run(&mut self) -> Result<()> {
        self.run_until(&std::sync::atomic::AtomicBool::new(false)).map(|_| ())
    }

    /// As [`Trainer::run`], and after each optimizer step the ranks agree whether any of them saw
    /// `stop` set (a signal): then they all stop at that step with a checkpoint of it, whose
    /// folder is returned. `None` when the run reached `train.steps`.
    pub fn run_until(&mut self, stop: &std::sync::atomic::AtomicBool) -> Result<Option<PathBuf>> {
        let total = self.cfg.train.steps;
        if self.state.step >= total {
            println!("run already at step {} of {total}; nothing to do", self.state.step);
            return Ok(None);
        }
        let lead = self.comm.rank() == 0;
        let mut progress = Progress::new(self.state.step, total, self.cfg.log.progress && lead);
        let mut stopped = None;
        while self.state.step < total {
            let m = self.train_step()?;
            progress.update(self.state.step, &m);
            let step = self.state.step;
            if let Some(f) = self.loss_file.as_mut() {
                f.append(&format!("{step}\t{}", m.loss), step)?;
            }
            if (step % self.cfg.log.every == 0 || step == total) && lead {
                progress.println(&m.summary_line(total));
                self.log_metrics(&m)?;
            }
            let every = self.cfg.validation.every;
            if every > 0 && (step % every == 0 || step == total) && self.train_clips < self.cache.len() && lead {
                let report = validation::run(self, step)?;
                progress.println(&report.summary_line(step));
                if let Some(f) = self.metrics_file.as_mut() {
                    let line = serde_json::json!({"step": step, "validation": {"latent_mse": report.latent_mse, "psnr": report.psnr, "ssim": report.ssim, "actions": report.actions, "action_gap": report.actions.relative_gap()}});
                    f.append(&line.to_string(), step)?;
                }
                // After warm-up, two validations in a row whose held-out loss barely moves with
                // the actions: the model is learning a video model, not a simulator of them.
                if step > self.cfg.optim.warmup_steps && report.actions.relative_gap() < validation::NEGLIGIBLE_ACTION_GAP {
                    self.negligible_action_gaps += 1;
                    if self.negligible_action_gaps == 2 {
                        progress.println(&format!(
                            "warning: the held-out loss with other clips' actions is within {:.0}% of the loss with their own at two validations in a row (now {:+.2}%): the model is not using its actions; check the actions in the cache (`bwm prepare --actions`) and `objective.action_dropout`",
                            100.0 * validation::NEGLIGIBLE_ACTION_GAP,
                            100.0 * report.actions.relative_gap()
                        ));
                    }
                } else {
                    self.negligible_action_gaps = 0;
                }
            }
            self.history.push(m);
            let mut requested = stop.load(std::sync::atomic::Ordering::SeqCst);
            if self.comm.world_size() > 1 {
                let mut flag = Tensor::from_slice(&[requested as i32 as f32]).to_device(self.device);
                self.comm.all_reduce_sum(&mut flag).context("agreeing whether a rank was asked to stop")?;
                requested = flag.double_value(&[0]) > 0.0;
            }
            let ck = self.cfg.checkpoint.every;
            if (ck > 0 && step % ck == 0) || step == total || requested {
                let dir = self.save_checkpoint()?;
                if lead {
                    progress.println(&format!("checkpoint {}", dir.display()));
                }
                if requested && step < total {
                    stopped = Some(dir);
                    break;
                }
            }
        }
        progress.finish();
        if let Some(ev) = self.events.as_mut() {
            ev.flush()?;
        }
        Ok(stopped)
    }

    /// One optimizer step over `grad_accum` micro-batches.
    pub fn train_step(&mut self) -> Result<StepMetrics> {
        let lora = self.lora.clone();
        if let Some(l) = &lora {
            // Dropout masks come from libtorch's generator, seeded per step so that a resumed
            // run draws the masks an uninterrupted one would.
            if l.cfg.dropout > 0.0 {
                tch::manual_seed((self.cfg.run.seed as i64) ^ ((self.state.step as i64 + 1) << 20));
            }
            l.set_training(true);
        }
        let result = self.train_step_inner();
        if let Some(l) = &lora {
            l.set_training(false);
        }
        result
    }

    fn train_step_inner(&mut self) -> Result<StepMetrics> {
        let start = Instant::now();
        let cfg = &self.cfg;
        let (mb, accum) = (cfg.train.micro_batch, cfg.train.grad_accum);
        let (rank, world) = (self.comm.rank(), self.comm.world_size());
        let step = self.state.step;
        // Per-sample losses stay on the device until the step's end: reading them after each
        // micro-step would make the host wait for the GPU and leave it idle while the next
        // micro-batch is staged.
        let mut sample_losses = Vec::with_capacity(accum);
        let mut tids = Vec::with_capacity(mb * accum);
        let mut tokens = 0i64;
        let mut sample_flops = 0.0;
        let recompute = if cfg.train.recompute { Recompute::Blocks { keep_last: cfg.train.recompute_keep_last } } else { Recompute::Off };
        for micro in 0..accum {
            let indices: Vec<u64> = (0..mb).map(|i| global_sample_index(step, micro, rank, i, mb, accum, world)).collect();
            let batch = self.load_batch(&indices)?;
            let prepared = match &self.distill {
                Some(d) => {
                    let segments: Vec<usize> = indices.iter().map(|&i| d.segment(i)).collect();
                    d.prepare(&self.objective, &batch.latents, &batch.noise, &batch.history_noise, &batch.actions, &segments)?
                }
                None => self.objective.prepare(&batch.latents, &batch.noise, &batch.history_noise, &batch.tids)?,
            };
            let grid = self.model.dit.token_grid(&prepared.input)?;
            let sample_tokens = grid.0 * grid.1 * grid.2;
            tokens += mb as i64 * sample_tokens;
            // Attention is quadratic in the sequence: FLOPs add up per sample, not over the summed tokens.
            sample_flops += mb as f64 * flops::train_flops(&self.model.cfg, sample_tokens, batch.actions.size()[1]);
            let input = prepared.input.to_kind(self.model.store.kind());
            let per_sample = match self.graph.as_mut() {
                Some(graph) => graph.step(&self.model, &self.objective, &input, &prepared, &batch.actions, batch.action_keep.as_ref())?,
                None => {
                    let objective = &self.objective;
                    let last_micro = micro + 1 == accum && world > 1 && cfg.train.overlap_grad_reduce;
                    let mut sink = BlockAccumulators { opt: &mut self.opt, blocks: &self.block_params, reduce: last_micro.then_some(self.comm.as_mut()), last_micro_step: micro + 1 == accum };
                    let loss = |pred: &Tensor| objective.per_sample_loss(pred, &prepared);
                    forward_backward_per_sample(&self.model, &input, &prepared.frame_timesteps, &batch.actions, batch.action_keep.as_ref(), recompute, &loss, &mut sink)?
                }
            };
            sample_losses.push(per_sample.to_kind(Kind::Float));
            tids.extend(prepared.timestep_indices.iter().copied());
            self.opt.collect_grads();
        }
        // The gradients' reduction and norm are queued before anything is read back, and the
        // step's one read (the losses' flags, the norm, each sample's loss) is one transfer: the
        // host's work between reads left the GPU idle about 2 ms a 5B step (--profile).
        let begun = self.opt.begin_step(self.comm.as_mut())?;
        // Every rank takes the same decision: skip when any rank saw a non-finite loss; the
        // gradient norm is computed after the reduction, so it is the same everywhere.
        let sample_losses = Tensor::cat(&sample_losses, 0);
        let nonfinite = sample_losses.isfinite().all().logical_not().to_kind(Kind::Float);
        let mut flags = Tensor::stack(&[nonfinite, sample_losses.mean(Kind::Float)], 0);
        if world > 1 {
            self.comm.all_reduce_sum(&mut flags).context("agreeing on the step's losses")?;
        }
        let read = Tensor::cat(&[flags.to_kind(Kind::Double), begun.sum_of_squares.view([1]), sample_losses.to_kind(Kind::Double)], 0);
        let read = Vec::<f64>::try_from(read.to_device(Device::Cpu))?;
        let (all_finite, global_loss, sum_of_squares) = (read[0] == 0.0, read[1] / world as f64, read[2]);
        let losses = read[3..].to_vec();
        let report = if all_finite {
            self.opt.finish_step(begun, sum_of_squares, (accum * world) as f64, self.comm.as_mut())?
        } else {
            self.opt.discard_grads();
            None
        };
        self.state.step += 1;
        self.state.samples_seen += (mb * accum * world) as u64;
        match report {
            Some(_) => self.state.nonfinite_in_row = 0,
            None => {
                self.state.nonfinite_in_row += 1;
                self.state.nonfinite_total += 1;
                eprintln!(
                    "step {}: non-finite loss or gradient; update skipped ({} in a row, {} in all)",
                    self.state.step, self.state.nonfinite_in_row, self.state.nonfinite_total
                );
                if self.state.nonfinite_in_row >= self.cfg.train.max_nonfinite_in_row {
                    bail!(
                        "{} optimizer steps in a row had a non-finite loss or gradient (train.max_nonfinite_in_row = {}); stopping at step {}. Lower optim.lr or check the data",
                        self.state.nonfinite_in_row,
                        self.cfg.train.max_nonfinite_in_row,
                        self.state.step
                    );
                }
            }
        }
        self.state.optimizer_step = self.opt.step;
        let seconds = start.elapsed().as_secs_f64();
        let model_flops = sample_flops * world as f64;
        let peak = self.cfg.log.peak_tflops.map(|p| p * world as f64);
        let mut m = StepMetrics::new(self.state.step, &losses, &tids, report, seconds, tokens * world as i64, model_flops, peak, self.state.nonfinite_total, self.device);
        m.samples_per_s *= world as f64;
        m.loss = global_loss;
        if let Some(rate) = self.cfg.log.matmul_tflops {
            m.set_matmul_rate(rate * world as f64);
        }
        m.set_loader_wait(self.take_loader_wait());
        m.set_collective_time(self.comm.take_collective_seconds());
        Ok(m)
    }

    /// The micro-batch of global samples `indices`: from the background loader when it is the
    /// next one of the sequence the loader reads ahead (every micro-batch from the current step to
    /// `train.steps`); otherwise the loader is restarted at it (a new run, a resume), or, for a
    /// batch outside the sequence, it is read here.
    fn load_batch(&self, indices: &[u64]) -> Result<Batch> {
        let mut loader = self.loader.lock().map_err(|_| anyhow::anyhow!("the batch loader's lock is poisoned"))?;
        let key = indices.to_vec();
        let mut staged = loader.prefetch.as_mut().and_then(|p| p.next(&key));
        if staged.is_none() {
            loader.collect_wait();
            loader.prefetch = self.start_loader(&key)?;
            staged = loader.prefetch.as_mut().and_then(|p| p.next(&key));
        }
        loader.collect_wait();
        let staged = match staged {
            Some(s) => s?,
            None => {
                let start = Instant::now();
                let s = stage_batch(&self.cache, &self.objective, self.cfg.run.seed, self.train_clips, indices);
                loader.waited += start.elapsed();
                s?
            }
        };
        let shape: Vec<i64> = std::iter::once(indices.len() as i64).chain(self.cache.index.latent_shape.iter().copied()).collect();
        let (latents, actions) = staged.clips.tensors(&self.cache);
        let d = self.device;
        let upload = |t: Tensor| bwm_model::device::upload(&t, d);
        let latents = match (latents, staged.clips.frames(&self.cache)) {
            (Some(l), _) => upload(l),
            (None, Some(frames)) => self.encode_frames(&frames)?,
            (None, None) => bail!("the loader returned neither latents nor frames"),
        };
        Ok(Batch {
            latents,
            actions: upload(actions),
            noise: upload(Tensor::from_slice(&staged.noise).view(shape.as_slice())),
            history_noise: upload(Tensor::from_slice(&staged.history_noise).view(shape.as_slice())),
            action_keep: (self.objective.action_dropout > 0.0).then(|| {
                let keep: Vec<f32> = staged.keep_actions.iter().map(|&k| if k { 1.0 } else { 0.0 }).collect();
                upload(Tensor::from_slice(&keep))
            }),
            tids: staged.tids,
        })
    }

    /// Latents [B, C, F, h, w] f32 on the training device of raw clips' u8 frames [B, 3, F, H, W].
    fn encode_frames(&self, frames: &Tensor) -> Result<Tensor> {
        let vae = self.clip_encoder.as_ref().context("a raw clip needs data.vae to be encoded")?;
        let latents = vae.encode_u8(&frames.to_device(self.device)).context("encoding raw clips with data.vae")?;
        Ok(latents.to_kind(Kind::Float))
    }

    /// Clip `i` of the cache on the training device, its latents encoded here for a raw cache.
    pub fn clip(&self, i: usize) -> Result<Clip> {
        if self.clip_encoder.is_none() {
            return self.cache.load(i, self.device);
        }
        let (frames, actions) = self.cache.load_frames(i, self.device)?;
        let latents = self.encode_frames(&frames.unsqueeze(0))?.squeeze_dim(0);
        Ok(Clip { latents, actions, frames: Some(frames) })
    }

    /// A loader reading the micro-batches from the one whose samples are `first` (a micro-batch
    /// of the current step) to the end of the run; None when `first` is no such micro-batch.
    fn start_loader(&self, first: &[u64]) -> Result<Option<Prefetcher<Vec<u64>, Staged>>> {
        let (mb, accum) = (self.cfg.train.micro_batch, self.cfg.train.grad_accum);
        let (rank, world) = (self.comm.rank(), self.comm.world_size());
        let (step, total) = (self.state.step, self.cfg.train.steps);
        let samples = move |s: u64, m: usize| -> Vec<u64> { (0..mb).map(|i| global_sample_index(s, m, rank, i, mb, accum, world)).collect() };
        let Some(micro) = (0..accum).find(|&m| samples(step, m) == first) else { return Ok(None) };
        let sequence = (step..total.max(step + 1)).flat_map(move |s| (0..accum).map(move |m| samples(s, m))).skip(micro);
        let cache = self.cache.clone();
        let objective = Objective::new(&self.cfg.objective, self.cfg.run.seed);
        let (seed, n) = (self.cfg.run.seed, self.train_clips);
        Prefetcher::spawn(LOADER_DEPTH, sequence, move |g: &Vec<u64>| stage_batch(&cache, &objective, seed, n, g)).map(Some)
    }

    /// Seconds the training thread waited for batches since the last call.
    fn take_loader_wait(&self) -> f64 {
        match self.loader.lock() {
            Ok(mut l) => {
                l.collect_wait();
                std::mem::take(&mut l.waited).as_secs_f64()
            }
            Err(_) => 0.0,
        }
    }

    fn log_metrics(&mut self, m: &StepMetrics) -> Result<()> {
        if let Some(f) = self.metrics_file.as_mut() {
            f.append(&serde_json::to_string(m)?, m.step)?;
        }
        if let Some(ev) = self.events.as_mut() {
            for (tag, value) in m.scalars() {
                ev.scalar(&tag, value, m.step)?;
            }
            ev.flush()?;
        }
        Ok(())
    }

    pub fn events(&mut self) -> Option<&mut EventWriter> {
        self.events.as_mut()
    }

    /// Writes a checkpoint of the current step (see `checkpoints`); every rank takes part. Each
    /// rank writes its slice of the optimizer state into a staging folder; rank 0 then writes the
    /// weights and the training state and moves the slices into the checkpoint, which appears
    /// whole (temporary folder, fsync, rename) or not at all.
    pub fn save_checkpoint(&mut self) -> Result<PathBuf> {
        let rank = self.comm.rank();
        // Replicated state is written once, by rank 0.
        let writers = if self.opt.is_sharded() { self.comm.world_size() } else { 1 };
        let step = self.state.step;
        let staging = self.checkpoints.staging_path(step);
        std::fs::create_dir_all(&staging).with_context(|| format!("creating {}", staging.display()))?;
        if rank < writers {
            let shard_dir = staging.join(format!(".rank-{rank}.tmp"));
            std::fs::create_dir_all(&shard_dir)?;
            let shard = bwm_checkpoints::optimizer_shards::write_shard(&shard_dir, rank, writers, self.opt.slice(), &self.opt.layout(), &self.opt.state_tensors())?;
            let name = bwm_checkpoints::optimizer_shards::shard_file_name(rank, writers);
            std::fs::rename(&shard, staging.join(&name)).with_context(|| format!("moving {}", shard.display()))?;
            std::fs::remove_dir_all(&shard_dir).ok();
        }
        self.comm.barrier().context("waiting for every rank's optimizer shard")?;
        let written = if rank == 0 { self.commit_checkpoint(&staging, writers).map(Some) } else { Ok(None) };
        // Every rank learns whether rank 0 succeeded before going on.
        let mut ok = Tensor::from_slice(&[written.is_ok() as i32 as f32]).to_device(self.device);
        self.comm.broadcast(&mut ok, 0).context("waiting for the checkpoint of rank 0")?;
        let dir = written?.unwrap_or_else(|| self.checkpoints.step_path(step));
        ensure!(ok.double_value(&[0]) > 0.0, "rank 0 failed to write the checkpoint of step {step}");
        Ok(dir)
    }

    fn commit_checkpoint(&mut self, staging: &Path, writers: usize) -> Result<PathBuf> {
        let weights: Vec<(String, Tensor)> = self.opt.params.iter().map(|p| (p.name.clone(), p.param.shallow_clone())).collect();
        let state = serde_json::to_string_pretty(&self.state)?;
        let config = self.cfg.to_toml()?;
        let meta = BTreeMap::from([("format".to_string(), "pt".to_string()), ("step".to_string(), self.state.step.to_string())]);
        let contract = &self.contract;
        let slow = std::env::var("BWM_FAULT_SLOW_CHECKPOINT_MS").ok().and_then(|v| v.parse::<u64>().ok());
        let dir = self.checkpoints.save(self.state.step, self.cfg.checkpoint.keep_last, |tmp| {
            write_tensors(&tmp.join("model.safetensors"), &weights, &meta)?;
            if let Some(ms) = slow {
                // Fault injection for the crash-safety test: a window in which the writer can be killed.
                eprintln!("checkpoint: writing {}", tmp.display());
                std::thread::sleep(std::time::Duration::from_millis(ms));
            }
            for r in 0..writers {
                let name = bwm_checkpoints::optimizer_shards::shard_file_name(r, writers);
                std::fs::rename(staging.join(&name), tmp.join(&name)).with_context(|| format!("moving the optimizer shard of rank {r}"))?;
            }
            std::fs::write(tmp.join("config.toml"), &config)?;
            bwm_checkpoints::contract::write(tmp, contract)?;
            std::fs::write(tmp.join(bwm_checkpoints::run_dir::STATE_FILE), &state)?;
            Ok(())
        })?;
        std::fs::remove_dir_all(staging).ok();
        Ok(dir.path)
    }

    pub fn out_path(&self, name: &str) -> PathBuf {
        self.out_dir.join(name)
    }
}

impl validation::ValidationRun for Trainer {
    fn config(&self) -> &RunConfig {
        &self.cfg
    }
    fn model(&self) -> &BwmModel {
        &self.model
    }
    fn objective(&self) -> &Objective {
        &self.objective
    }
    fn device(&self) -> Device {
        self.device
    }
    fn cache(&self) -> &LatentCache {
        &self.cache
    }
    fn validation_clips(&self) -> std::ops::Range<usize> {
        self.train_clips..self.cache.len()
    }
    fn clip(&self, i: usize) -> Result<Clip> {
        Trainer::clip(self, i)
    }
    fn clip_actions(&self, i: usize) -> Result<Tensor> {
        self.cache.load_actions(i, self.device)
    }
    fn out_path(&self, name: &str) -> PathBuf {
        Trainer::out_path(self, name)
    }
    fn events(&mut self) -> Option<&mut EventWriter> {
        Trainer::events(self)
    }
}

/// Hands each block's gradients into the fp32 accumulators as the recomputing backward walk
/// produces them, so no model-dtype gradient of a block outlives its backward; on the step's last
/// micro-batch, with `reduce`, it then starts reducing the block's gradients across the ranks
/// while the walk goes on to the earlier blocks. Without recomputation it takes every gradient at
/// the end of the backward pass (`AdamW::take_grads`).
struct BlockAccumulators<'a> {
    opt: &'a mut AdamW,
    blocks: &'a [Vec<usize>],
    reduce: Option<&'a mut dyn Collective>,
    last_micro_step: bool,
}

impl BlockGradSink for BlockAccumulators<'_> {
    fn block_params(&self, block: usize) -> Vec<Tensor> {
        self.blocks[block].iter().map(|&k| self.opt.params[k].param.shallow_clone()).collect()
    }

    fn block_grads(&mut self, block: usize, grads: &[Tensor]) -> Result<()> {
        for (&k, g) in self.blocks[block].iter().zip(grads) {
            self.opt.accumulate(k, g);
        }
        if let Some(comm) = self.reduce.as_deref_mut() {
            self.opt.reduce_early(&self.blocks[block], comm).with_context(|| format!("reducing the gradients of block {block}"))?;
        }
        Ok(())
    }

    fn all_params(&self) -> Vec<Tensor> {
        self.opt.params.iter().map(|p| p.param.shallow_clone()).collect()
    }

    fn all_grads(&mut self, grads: Vec<Tensor>) -> Result<()> {
        self.opt.take_grads(grads, self.last_micro_step)
    }
}

struct Batch {
    latents: Tensor,
    actions: Tensor,
    noise: Tensor,
    history_noise: Tensor,
    /// `[B]`: 1 where the sample sees its actions, 0 for the null condition; None: all see them.
    action_keep: Option<Tensor>,
    tids: Vec<usize>,
}

/// Micro-batches the loader holds ready.
const LOADER_DEPTH: usize = 2;

/// The background reader of the next micro-batches, and the time the step waited for batches.
#[derive(Default)]
struct Loader {
    prefetch: Option<Prefetcher<Vec<u64>, Staged>>,
    waited: std::time::Duration,
}

impl Loader {
    fn collect_wait(&mut self) {
        if let Some(p) = self.prefetch.as_mut() {
            self.waited += p.take_waited();
        }
    }
}

/// A micro-batch as plain values (clips, noise, timesteps), built without tensor operations so
/// that the loader thread does not compete with the training thread's OpenMP workers.
struct Staged {
    clips: ClipBatch,
    noise: Vec<f32>,
    history_noise: Vec<f32>,
    keep_actions: Vec<bool>,
    tids: Vec<usize>,
}

/// The clips and the per-sample draws of global samples `indices`.
fn stage_batch(cache: &LatentCache, objective: &Objective, seed: u64, train_clips: usize, indices: &[u64]) -> Result<Staged> {
    let clips: Vec<usize> = indices.iter().map(|&g| clip_for_sample(seed, g, train_clips)).collect();
    let mut staged = Staged { clips: load_clips(cache, &clips)?, noise: Vec::new(), history_noise: Vec::new(), keep_actions: Vec::new(), tids: Vec::new() };
    for &g in indices {
        let draw = objective.draw(g, &cache.index.latent_shape);
        staged.noise.extend(Vec::<f32>::try_from(draw.noise.view([-1]))?);
        staged.history_noise.extend(Vec::<f32>::try_from(draw.history_noise.view([-1]))?);
        staged.tids.push(draw.timestep_index);
        staged.keep_actions.push(draw.keep_actions);
    }
    Ok(staged)
}

/// The VAE encoding a raw cache's clips (`data.vae`), checked to give the cache's latent shape.
fn clip_encoder(cfg: &RunConfig, cache: &LatentCache, device: Device) -> Result<Option<WanVae>> {
    let index = &cache.index;
    if index.has_latents {
        if let Some(p) = &cfg.data.vae {
            eprintln!("warning: data.vae {} is not used: {} holds encoded latents", p.display(), cache.dir.display());
        }
        return Ok(None);
    }
    let Some(path) = &cfg.data.vae else {
        bail!("{} holds raw clips (bwm prepare --raw): set data.vae to the VAE that encodes them", cache.dir.display())
    };
    let vae = WanVae::load_any(path, cfg.model.dtype.kind(), device).with_context(|| format!("data.vae {}", path.display()))?;
    check_vae_fits(&vae.cfg, index, &cache.dir, &format!("data.vae {}", path.display()))?;
    Ok(Some(vae))
}

/// Checks that a VAE of config `vae` encodes the cache's clips to the latents it holds, and so
/// decodes those back to its frames (`what` names the VAE in the error).
fn check_vae_fits(vae: &VaeConfig, index: &CacheIndex, cache_dir: &Path, what: &str) -> Result<()> {
    let [w, h] = index.resolution;
    let frames = index.pixel_frames as i64;
    let gives = vae.latent_shape(frames, h as i64, w as i64);
    ensure!(
        (frames - 1) % vae.temporal_stride() == 0 && gives == index.latent_shape,
        "{what} encodes clips of {frames} frames of {w}x{h} to latents {gives:?}; the cache {} holds {:?}",
        cache_dir.display(),
        index.latent_shape
    );
    Ok(())
}

/// The checkpoint folder a run starts from (None: fresh), or why it cannot start.
fn resume_folder(resume: &Resume, checkpoints: &CheckpointRoot) -> Result<Option<PathBuf>> {
    Ok(match resume {
        Resume::No => {
            if let Some(last) = checkpoints.latest()? {
                bail!(
                    "{} already holds checkpoint step {}; pass --resume auto to continue it, or pick another run.out_dir",
                    checkpoints.root.display(),
                    last.step
                );
            }
            None
        }
        Resume::Auto => checkpoints.latest()?.map(|d| d.path),
        Resume::Path(p) => {
            ensure!(p.is_dir(), "--resume {}: no such checkpoint folder", p.display());
            ensure!(
                p.join(bwm_checkpoints::run_dir::STATE_FILE).is_file(),
                "--resume {}: not a complete checkpoint (no {})",
                p.display(),
                bwm_checkpoints::run_dir::STATE_FILE
            );
            Some(p.clone())
        }
    })
}

/// One writer per run folder. Rank 0 takes the folder's lock (a second `bwm train` on a live run
/// fails here at once, naming the holder) and, holding it, repairs what a crash left among the
/// checkpoints; the other ranks wait for its word before they touch the folder. Rank 0 holds the
/// lock for the whole run on behalf of the job: it writes everything but the optimizer shards,
/// which the other ranks put into the staging folder of a step rank 0 is saving, so its lock
/// covers them. A lock per rank would add nothing: a second job's rank 0 fails already, and its
/// other ranks with it through this agreement, before any of them has written.
fn lock_run_folder(out_dir: &Path, checkpoints: &CheckpointRoot, comm: &mut dyn Collective, device: Device) -> Result<Option<RunLock>> {
    let lead = comm.rank() == 0;
    let taken = lead.then(|| RunLock::acquire(out_dir).and_then(|lock| checkpoints.recover().map(|()| lock)));
    if comm.world_size() > 1 {
        let mut ok = Tensor::from_slice(&[taken.as_ref().is_some_and(|t| t.is_ok()) as i32 as f32]).to_device(device);
        comm.broadcast(&mut ok, 0).context("waiting for rank 0 to take the run folder's lock")?;
        ensure!(lead || ok.double_value(&[0]) > 0.0, "rank 0 could not take the run folder {} (its error says why)", out_dir.display());
    }
    taken.transpose()
}

/// Every rank must start from the same weights: a checksum of the trained tensors is gathered and
/// compared.
fn check_identical_weights(comm: &mut dyn Collective, opt: &AdamW) -> Result<()> {
    let world = comm.world_size();
    if world == 1 {
        return Ok(());
    }
    let sum: f64 = opt.params.iter().map(|p| p.param.sum(Kind::Double).double_value(&[]) + p.param.abs().sum(Kind::Double).double_value(&[]) * 1e-3).sum();
    let device = opt.params[0].param.device();
    let mine = Tensor::from_slice(&[sum as f32]).to_device(device);
    let mut all = Tensor::zeros([world as i64], (Kind::Float, device));
    comm.all_gather(&mine, &mut all).context("comparing initial weights across ranks")?;
    let all: Vec<f32> = Vec::<f32>::try_from(&all.to_device(Device::Cpu))?;
    ensure!(
        all.iter().all(|&v| v == all[0]),
        "ranks start from different weights (checksums {all:?}); check that every rank uses the same config and init"
    );
    Ok(())
}

/// Loads a checkpoint into `opt` after checking it belongs to this config.
fn restore(dir: &Path, cfg: &RunConfig, opt: &mut AdamW, trainable: &[String], comm: &mut dyn Collective) -> Result<TrainState> {
    let state_path = dir.join(bwm_checkpoints::run_dir::STATE_FILE);
    let text = std::fs::read_to_string(&state_path).with_context(|| format!("reading {}", state_path.display()))?;
    let state: TrainState = serde_json::from_str(&text).with_context(|| format!("parsing {}", state_path.display()))?;
    let saved = RunConfig::parse(&state.config, &[]).with_context(|| format!("the config stored in {}", state_path.display()))?;
    ensure!(
        saved.model == cfg.model,
        "checkpoint {} was written for a different model section:\n  checkpoint: {:?}\n  config:     {:?}",
        dir.display(),
        saved.model,
        cfg.model
    );
    ensure!(
        state.trainable == trainable,
        "checkpoint {} trains {} tensors, this config {}; the trainable sets differ",
        dir.display(),
        state.trainable.len(),
        trainable.len()
    );
    for (what, a, b) in [
        ("run.seed", saved.run.seed.to_string(), cfg.run.seed.to_string()),
        ("train.micro_batch", saved.train.micro_batch.to_string(), cfg.train.micro_batch.to_string()),
        ("train.grad_accum", saved.train.grad_accum.to_string(), cfg.train.grad_accum.to_string()),
    ] {
        if a != b {
            eprintln!("warning: {what} was {a} in the checkpoint and is {b} now; the continuation will not match an uninterrupted run");
        }
    }
    let opt_state = OptimizerState::open(dir, &opt.layout())?;
    let loaded = opt.load_state(&opt_state, state.optimizer_step, comm)?;
    let expected = opt.state_tensors().len();
    let weights = SafetensorsSource::open(dir.join("model.safetensors"))?;
    for p in &opt.params {
        ensure!(weights.shape(&p.name).is_some(), "{}: model.safetensors lacks '{}'", dir.display(), p.name);
    }
    println!(
        "resumed from {} at step {}: {loaded}/{expected} optimizer tensors, {}/{} weight tensors loaded",
        dir.display(),
        state.step,
        opt.params.len(),
        weights.names().len()
    );
    Ok(state)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_vae_that_does_not_give_the_caches_latents_is_refused() {
        let cfg = VaeConfig::with_width(16, 16);
        let index = CacheIndex::new(cfg.latent_shape(9, 32, 64), 4, 4, 4, [64, 32], 10.0, "vae");
        check_vae_fits(&cfg, &index, Path::new("cache"), "validation.vae v").unwrap();
        let other = cfg.with_spatial_stride(8).unwrap();
        let e = check_vae_fits(&other, &index, Path::new("cache"), "validation.vae v").unwrap_err().to_string();
        assert!(e.starts_with("validation.vae v encodes clips of 9 frames of 64x32") && e.contains("the cache cache holds"), "{e}");
    }
}
