//! The policy evaluator (`bwm evaluate`): policies in closed loop with the world model. For each policy, task and
//! episode: connect to the policy's openpi websocket server, then repeatedly send the latest
//! frame (split into its camera views, resized) with the policy's last command as its state,
//! turn the returned action chunk into poses (the adapter), generate that many frames, and ask
//! the judge, until the horizon or a success. A failed episode (server error, disconnect, bad
//! reply) is recorded as a failure and the next episode reconnects.

mod adapter;
mod config;
mod judge;
mod observation;
mod openpi;
mod report;
mod tasks;

use std::fs::File;
use std::io::Write;
use std::path::Path;
use std::time::{Duration, Instant};

use anyhow::{ensure, Context, Result};
use bwm_data::frames::{frames_to_tensor, tensor_to_frames};
use image::RgbImage;

use crate::world_model::{WorldModel, WorldModelOptions};
use adapter::{Adapter, Fk};
use config::{AdapterKind, ChunkMode, EvalConfig, PolicyConfig};
use judge::{Judge, Subject, Verdict};
use openpi::PolicyClient;
use report::EpisodeRecord;
use tasks::{Start, Task};

/// Runs the evaluation that `config` (TOML: policies, tasks, observation layout, adapters, judge;
/// `configs/evaluate-example.toml`) describes with the world model `options` opens, and writes
/// videos/, episodes.jsonl, success_rates.csv, policies.csv and summary.json into `out`.
pub fn run(options: &WorldModelOptions, config: &Path, out: &Path) -> Result<()> {
    let cfg = EvalConfig::read(config)?;
    ensure!(
        options.stats.is_some(),
        "evaluate turns policy commands into the model's normalized actions: pass --stats stat.json (the statistics the model was trained with)"
    );
    let reference = cfg
        .reference
        .as_deref()
        .map(report::read_reference)
        .transpose()?;
    let need_pose = cfg
        .policies
        .iter()
        .any(|p| p.adapter.kind != AdapterKind::Joint);
    let need_joints = cfg
        .policies
        .iter()
        .any(|p| p.adapter.kind == AdapterKind::Joint);
    let mut fk = match (&cfg.fk, need_joints) {
        (Some(f), true) => Some(Fk::start(f)?),
        _ => None,
    };
    let judge = Judge::new(&cfg.judge)?;
    let tasks = tasks::load_tasks(&cfg, need_pose, need_joints)?;
    for p in &cfg.policies {
        let keys = cfg.observation_of(p).image_keys.len();
        for t in &tasks {
            if let Some(s) = t.starts.iter().find(|s| s.views != keys) {
                anyhow::bail!(
                    "policy '{}' sends {keys} camera image(s) but task '{}' frames hold {} view(s) ({})",
                    p.name,
                    t.cfg.name,
                    s.views,
                    s.source
                );
            }
        }
    }
    let wm = options.load()?;
    let d = wm.action_dim();
    for t in &tasks {
        for s in &t.starts {
            if let Some(pose) = &s.pose {
                ensure!(
                    pose.len() == d,
                    "task '{}' ({}): the initial pose has {} values; the model takes {d}",
                    t.cfg.name,
                    s.source,
                    pose.len()
                );
            }
        }
    }
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let episodes_path = out.join("episodes.jsonl");
    let mut episodes_file = File::create(&episodes_path)
        .with_context(|| format!("creating {}", episodes_path.display()))?;
    let per_policy: usize = tasks.iter().map(|t| t.starts.len()).sum();
    let total = per_policy * cfg.policies.len();
    println!(
        "evaluate: {} policies x {} tasks ({per_policy} episodes per policy), horizon {} frames, chunks of K = {} frames, {}",
        cfg.policies.len(),
        tasks.len(),
        cfg.horizon,
        wm.spec.future,
        judge.describe()
    );
    let mut records = Vec::new();
    for policy in &cfg.policies {
        let mut metadata_shown = false;
        for task in &tasks {
            for (i, start) in task.starts.iter().enumerate() {
                let t0 = Instant::now();
                let run = run_episode(&cfg, &wm, &judge, fk.as_mut(), policy, task, i, start);
                if let (Some(m), false) = (&run.metadata, metadata_shown) {
                    println!(
                        "policy '{}' ({}): server metadata {m}",
                        policy.name, policy.url
                    );
                    metadata_shown = true;
                }
                let video = if run.frames.is_empty() {
                    None
                } else {
                    let rel = Path::new("videos")
                        .join(&policy.name)
                        .join(&task.cfg.name)
                        .join(format!("episode_{i:03}.mp4"));
                    let path = out.join(&rel);
                    std::fs::create_dir_all(path.parent().unwrap_or(out))?;
                    let written = bwm_data::video::write_mp4_or_sheet(&path, &run.frames, start.fps, 24)
                        .with_context(|| format!("writing {}", path.display()))?;
                    Some(rel.with_file_name(written.file_name().unwrap_or_default()).display().to_string())
                };
                let success =
                    run.error.is_none() && run.verdict.as_ref().is_some_and(|v| v.success);
                let record = EpisodeRecord {
                    policy: policy.name.clone(),
                    task: task.cfg.name.clone(),
                    episode: i,
                    source: start.source.clone(),
                    success,
                    frames: run.frames.len(),
                    chunks: run.chunks,
                    policy_requests: run.requests,
                    success_probability: run.verdict.as_ref().and_then(|v| v.probability),
                    judge: run.verdict.as_ref().map(|v| v.detail.clone()),
                    error: run.error.as_ref().map(|e| format!("{e:#}")),
                    video,
                    seconds: t0.elapsed().as_secs_f64(),
                };
                println!("[{}/{total}] {}", records.len() + 1, progress_line(&record));
                writeln!(episodes_file, "{}", serde_json::to_string(&record)?)
                    .and_then(|_| episodes_file.flush())
                    .with_context(|| format!("writing {}", episodes_path.display()))?;
                records.push(record);
            }
        }
    }
    let policies: Vec<String> = cfg.policies.iter().map(|p| p.name.clone()).collect();
    let task_names: Vec<String> = tasks.iter().map(|t| t.cfg.name.clone()).collect();
    let summary = report::summarize(&policies, &task_names, &records, reference.as_ref());
    report::write(out, &summary)?;
    print!("{}", report::render(&summary));
    println!("evaluate: results in {}", out.display());
    Ok(())
}

fn progress_line(r: &EpisodeRecord) -> String {
    let head = format!("{} / {} #{} ({})", r.policy, r.task, r.episode, r.source);
    let tail = format!(
        "{} frames, {} chunks, {} policy requests, {:.1} s",
        r.frames, r.chunks, r.policy_requests, r.seconds
    );
    match (&r.error, r.success) {
        (Some(e), _) => format!("{head}: FAILED ({}); {tail}", one_line(e)),
        (None, true) => format!(
            "{head}: success{}; {tail}",
            r.success_probability
                .map_or(String::new(), |p| format!(" (p = {p:.3})"))
        ),
        (None, false) => format!(
            "{head}: failure{}; {tail}",
            r.success_probability
                .map_or(String::new(), |p| format!(" (p = {p:.3})"))
        ),
    }
}

/// The first line of a message and, for a multi-line one (a traceback), its last line.
fn one_line(e: &str) -> String {
    let lines: Vec<&str> = e.lines().map(str::trim).filter(|l| !l.is_empty()).collect();
    match lines.as_slice() {
        [] => String::new(),
        [one] => one.to_string(),
        [first, .., last] => format!("{first} ... {last}"),
    }
}

#[derive(Default)]
struct EpisodeRun {
    frames: Vec<RgbImage>,
    chunks: usize,
    requests: usize,
    /// The policy server's metadata, as text.
    metadata: Option<String>,
    verdict: Option<Verdict>,
    error: Option<anyhow::Error>,
}

#[allow(clippy::too_many_arguments)]
fn run_episode(
    cfg: &EvalConfig,
    wm: &WorldModel,
    judge: &Judge,
    fk: Option<&mut Fk>,
    policy: &PolicyConfig,
    task: &Task,
    episode: usize,
    start: &Start,
) -> EpisodeRun {
    let mut run = EpisodeRun::default();
    if let Err(e) = drive(cfg, wm, judge, fk, policy, task, episode, start, &mut run) {
        run.error = Some(e);
    }
    run
}

#[allow(clippy::too_many_arguments)]
fn drive(
    cfg: &EvalConfig,
    wm: &WorldModel,
    judge: &Judge,
    mut fk: Option<&mut Fk>,
    policy: &PolicyConfig,
    task: &Task,
    episode: usize,
    start: &Start,
    run: &mut EpisodeRun,
) -> Result<()> {
    let obs_cfg = cfg.observation_of(policy);
    let mut adapter = Adapter::new(
        &policy.adapter,
        wm.action_dim(),
        start.pose.as_deref(),
        start.joints.as_deref(),
        fk.as_deref_mut(),
    )?;
    let x0 = frames_to_tensor(std::slice::from_ref(&start.x0))?.squeeze_dim(1);
    let a0 = wm.normalize(&[adapter.pose().to_vec()])?.get(0);
    let mut rollout = wm.rollout(&x0, &a0)?;
    let timeout = Duration::from_secs_f64(cfg.timeout_s);
    let mut client = PolicyClient::connect(&policy.url, timeout)
        .with_context(|| format!("policy '{}'", policy.name))?;
    run.metadata = Some(client.metadata.to_string());
    let k = wm.spec.future;
    let subject = Subject {
        policy: &policy.name,
        task: &task.cfg.name,
        prompt: &start.prompt,
        episode,
        rules: &task.cfg.rules,
    };
    while run.frames.len() < cfg.horizon {
        let want = k.min(cfg.horizon - run.frames.len());
        let latest = run.frames.last().unwrap_or(&start.x0).clone();
        let mut poses: Vec<Vec<f32>> = Vec::with_capacity(want);
        while poses.len() < want {
            let obs = observation::observation(&latest, adapter.state(), &start.prompt, obs_cfg)?;
            run.requests += 1;
            let reply = client.infer(&obs)?;
            let rows = observation::action_rows(&reply, &obs_cfg.actions_key)?;
            ensure!(
                !rows.is_empty(),
                "the policy returned an empty action chunk"
            );
            let need = want - poses.len();
            let take = match policy.chunk {
                ChunkMode::Rerequest => rows.len().min(need),
                ChunkMode::Cut if rows.len() >= need => need,
                ChunkMode::Cut => {
                    let cut = rows.len() / 4 * 4;
                    ensure!(
                        cut > 0,
                        "the policy returned {} action(s); chunk = \"cut\" keeps whole groups of 4 (use chunk = \"rerequest\")",
                        rows.len()
                    );
                    cut
                }
            };
            poses.extend(adapter.apply(&rows[..take], fk.as_deref_mut())?);
            if policy.chunk == ChunkMode::Cut {
                break;
            }
        }
        let actions = wm.normalize(&poses)?;
        let chunk = rollout.next_chunk(&actions).context("world model")?;
        run.frames.extend(tensor_to_frames(&chunk.frames)?);
        run.chunks += 1;
        if cfg.stop_on_success {
            let verdict = judge.judge(&run.frames, &subject).context("judge")?;
            let done = verdict.success;
            run.verdict = Some(verdict);
            if done {
                return Ok(());
            }
        }
    }
    if !cfg.stop_on_success {
        run.verdict = Some(judge.judge(&run.frames, &subject).context("judge")?);
    }
    Ok(())
}
