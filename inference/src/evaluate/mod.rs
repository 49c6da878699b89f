//! The policy evaluator (`bwm evaluate`): policies in closed loop with the world model. For each policy, task and
//! episode: connect to the policy's openpi websocket server, then repeatedly send the latest
//! frame (split into its camera views, resized) with the policy's last command as its state,
//! turn the returned action chunk into poses (the adapter), generate that many frames, and ask
//! the judge, until the horizon or a success. A failed episode (server error, disconnect, bad
//! reply) is recorded as a failure and the next episode reconnects; once every episode is
//! recorded, episodes that ended on an error are summed up by kind (connection, policy, world
//! model, judge, set-up) and make the evaluation fail.

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

use bwm_model::rollout::{PendingChunks, Rollout};
use tch::Tensor;

use crate::world_model::{WorldModel, WorldModelOptions};
use adapter::{Adapter, Fk};
use config::{AdapterKind, ChunkMode, EvalConfig, PolicyConfig};
use judge::{Judge, Subject, Verdict};
use openpi::{ConnectionError, PolicyClient};
use report::EpisodeRecord;
use tasks::{Start, Task};

/// Runs the evaluation that `config` (TOML: policies, tasks, observation layout, adapters, judge;
/// `configs/evaluate-example.toml`) describes with the world model `options` opens, and writes
/// videos/, episodes.jsonl, success_rates.csv, policies.csv and summary.json into `out`.
/// `in_flight` episodes run at once (a new episode starts as one ends), split into `streams`
/// lanes that take turns (`crate::lanes`): each lane's chunks are generated as one batch on a
/// CUDA stream of its own while the host judges another lane's frames and asks its policies for
/// actions. Each episode's frames are what it would get alone, and the records keep the config's
/// order. When episodes ended on an error (a policy's, a connection's, the world model's, the
/// judge's), the results are written all the same, the errors are summed up by kind, and the
/// evaluation fails.
pub fn run(options: &WorldModelOptions, config: &Path, out: &Path, in_flight: usize, streams: usize) -> Result<()> {
    ensure!(in_flight >= 1, "episodes in flight must be at least 1");
    crate::lanes::check(in_flight, streams)?;
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
    let (width, height) = cfg.frame_size()?;
    // What the episodes give the model is checked against its input contract first: the frame
    // size, how the dataset's pose is read, and each start's initial pose (its state).
    wm.contract.check_frame_size(width, height, &format!("resolution {}", cfg.resolution))?;
    wm.check_frame_size(&format!("resolution {}", cfg.resolution), height as i64, width as i64, in_flight)?;
    let lanes = wm.lanes(streams)?;
    let capacities = lanes.shares(in_flight)?;
    for t in &tasks {
        if t.cfg.dataset.is_some() && need_pose {
            let spec = bwm_data::ActionSpec::parse(&t.cfg.pose_actions)?;
            wm.contract.check_definition(&spec, &format!("task '{}': pose_actions {}", t.cfg.name, t.cfg.pose_actions))?;
        }
        for s in &t.starts {
            if let Some(pose) = &s.pose {
                wm.contract.check_action_dim(pose.len(), &format!("task '{}' ({}): the initial pose", t.cfg.name, s.source))?;
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
        "evaluate: {} policies x {} tasks ({per_policy} episodes per policy), horizon {} frames, chunks of K = {} frames, {} episode(s) in flight in {} stream(s), {}",
        cfg.policies.len(),
        tasks.len(),
        cfg.horizon,
        wm.spec.future,
        in_flight,
        streams,
        judge.describe()
    );
    let jobs: Vec<(&PolicyConfig, &Task, usize)> = cfg
        .policies
        .iter()
        .flat_map(|p| tasks.iter().flat_map(move |t| (0..t.starts.len()).map(move |i| (p, t, i))))
        .collect();
    let mut records = Vec::new();
    let mut kinds: Vec<Option<ErrorKind>> = Vec::new();
    let mut metadata_shown = vec![false; cfg.policies.len()];
    // Each lane's episodes in the order they started, and the chunk it has queued for those of
    // them it drives; finished episodes wait in `finished` until every earlier one is recorded.
    let mut lane_state: Vec<Lane> = capacities.into_iter().map(|capacity| Lane { capacity, live: Vec::new(), pending: None }).collect();
    let mut finished: std::collections::BTreeMap<usize, Episode> = std::collections::BTreeMap::new();
    let mut next_job = 0;
    let mut turn = 0;
    while records.len() < jobs.len() {
        let l = turn % lane_state.len();
        turn += 1;
        let lane = &mut lane_state[l];
        lanes.on(l, || {
            if let Some((positions, pending)) = lane.pending.take() {
                finish(&cfg, &judge, &jobs, &mut lane.live, &positions, pending);
            }
            for e in lane.live.extract_if(.., |e| e.driving.is_none()) {
                finished.insert(e.job, e);
            }
            while lane.live.len() < lane.capacity && next_job < jobs.len() {
                let (policy, task, i) = jobs[next_job];
                lane.live.push(Episode::start(next_job, &cfg, &wm, fk.as_mut(), policy, task, i));
                next_job += 1;
            }
            lane.pending = begin(&cfg, &wm, fk.as_mut(), &jobs, &mut lane.live);
            Ok(())
        })?;
        while let Some(e) = finished.remove(&records.len()) {
            let (policy, task, i) = jobs[e.job];
            let start = &task.starts[i];
            let run = e.run;
            // `jobs` runs policy by policy, `per_policy` episodes each.
            let policy_index = e.job / per_policy;
            if let (Some(m), false) = (&run.metadata, metadata_shown[policy_index]) {
                println!("policy '{}' ({}): server metadata {m}", policy.name, policy.url);
                metadata_shown[policy_index] = true;
            }
            let video = if run.frames.is_empty() {
                None
            } else {
                let rel = Path::new("videos").join(&policy.name).join(&task.cfg.name).join(format!("episode_{i:03}.mp4"));
                let path = out.join(&rel);
                std::fs::create_dir_all(path.parent().unwrap_or(out))?;
                let written = bwm_data::video::write_mp4_or_sheet(&path, &run.frames, start.fps, 24)
                    .with_context(|| format!("writing {}", path.display()))?;
                Some(rel.with_file_name(written.file_name().unwrap_or_default()).display().to_string())
            };
            let success = run.error.is_none() && run.verdict.as_ref().is_some_and(|v| v.success);
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
                seconds: e.seconds.unwrap_or_default(),
                actions: run.actions,
            };
            println!("[{}/{total}] {}", records.len() + 1, progress_line(&record));
            writeln!(episodes_file, "{}", serde_json::to_string(&record)?)
                .and_then(|_| episodes_file.flush())
                .with_context(|| format!("writing {}", episodes_path.display()))?;
            records.push(record);
            kinds.push(run.error.as_ref().map(|_| run.error_kind.unwrap_or(ErrorKind::Policy)));
        }
    }
    let policies: Vec<String> = cfg.policies.iter().map(|p| p.name.clone()).collect();
    let task_names: Vec<String> = tasks.iter().map(|t| t.cfg.name.clone()).collect();
    let summary = report::summarize(&policies, &task_names, &records, reference.as_ref());
    report::write(out, &summary)?;
    print!("{}", report::render(&summary));
    println!("evaluate: results in {}", out.display());
    let errors: Vec<(ErrorKind, &EpisodeRecord)> = records.iter().zip(&kinds).filter_map(|(r, k)| k.map(|k| (k, r))).collect();
    if errors.is_empty() {
        return Ok(());
    }
    println!("evaluate: {} of {} episodes ended on an error (counted as failures above):", errors.len(), records.len());
    let mut by_kind: Vec<(ErrorKind, usize, &EpisodeRecord)> = Vec::new();
    for (k, r) in &errors {
        match by_kind.iter_mut().find(|(seen, _, _)| seen == k) {
            Some(entry) => entry.1 += 1,
            None => by_kind.push((*k, 1, r)),
        }
    }
    by_kind.sort_by_key(|(k, _, _)| *k);
    for (k, n, first) in &by_kind {
        println!(
            "  {}: {n} episode{}; first: {} / {} #{} ({}): {}",
            k.name(),
            if *n == 1 { "" } else { "s" },
            first.policy,
            first.task,
            first.episode,
            first.source,
            one_line(first.error.as_deref().unwrap_or_default())
        );
    }
    let counts: Vec<String> = by_kind.iter().map(|(k, n, _)| format!("{}: {n}", k.name())).collect();
    anyhow::bail!(
        "{} of {} episodes ended on an error ({}); the results in {} count them as failures",
        errors.len(),
        records.len(),
        counts.join(", "),
        out.display()
    )
}

/// Where an episode's error arose.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
enum ErrorKind {
    /// Reaching the policy server, its handshake and metadata, or the connection lost.
    Connection,
    /// The policy server's error, a bad or late reply, actions the adapter cannot use.
    Policy,
    WorldModel,
    Judge,
    /// The episode's start: its adapter and initial state.
    Setup,
}

impl ErrorKind {
    fn name(self) -> &'static str {
        match self {
            ErrorKind::Connection => "connection",
            ErrorKind::Policy => "policy",
            ErrorKind::WorldModel => "world model",
            ErrorKind::Judge => "judge",
            ErrorKind::Setup => "set-up",
        }
    }

    /// `otherwise`, unless `err` is the policy connection's.
    fn of(err: &anyhow::Error, otherwise: ErrorKind) -> ErrorKind {
        if err.chain().any(|c| c.is::<ConnectionError>()) {
            ErrorKind::Connection
        } else {
            otherwise
        }
    }
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
    error_kind: Option<ErrorKind>,
    /// The poses sent to the world model, before normalization.
    actions: Vec<Vec<f32>>,
}

/// An episode in flight: its record so far and, until it ends, what drives it.
struct Episode<'w> {
    /// Position in the evaluation's list of (policy, task, episode).
    job: usize,
    t0: Instant,
    run: EpisodeRun,
    driving: Option<Driving<'w>>,
    /// Seconds from start to end, once ended.
    seconds: Option<f64>,
}

struct Driving<'w> {
    adapter: Adapter,
    rollout: Rollout<'w>,
    client: PolicyClient,
}

impl<'w> Episode<'w> {
    /// Connects to the policy and starts the rollout at the start's first frame; a failure ends
    /// the episode at once (recorded as a failure with its error).
    fn start(job: usize, cfg: &EvalConfig, wm: &'w WorldModel, fk: Option<&mut Fk>, policy: &PolicyConfig, task: &Task, i: usize) -> Self {
        let mut e = Episode { job, t0: Instant::now(), run: EpisodeRun::default(), driving: None, seconds: None };
        let start = &task.starts[i];
        let driving = (|| -> std::result::Result<Driving<'w>, (ErrorKind, anyhow::Error)> {
            let adapter = Adapter::new(&policy.adapter, wm.action_dim(), start.pose.as_deref(), start.joints.as_deref(), fk).map_err(|e| (ErrorKind::Setup, e))?;
            let (w, h) = start.x0.dimensions();
            let rollout = crate::fallible::guarded(
                || format!("starting a rollout at a {h}x{w} (HxW) x0"),
                || {
                    let x0 = frames_to_tensor(std::slice::from_ref(&start.x0))?.squeeze_dim(1);
                    let a0 = wm.normalize(&[adapter.pose().to_vec()])?.get(0);
                    wm.rollout(&x0, &a0)
                },
            )
            .map_err(|e| (ErrorKind::WorldModel, e))?;
            let timeout = Duration::from_secs_f64(cfg.timeout_s);
            let client = PolicyClient::connect(&policy.url, timeout).with_context(|| format!("policy '{}'", policy.name)).map_err(|e| (ErrorKind::of(&e, ErrorKind::Policy), e))?;
            Ok(Driving { adapter, rollout, client })
        })();
        match driving {
            Ok(d) => {
                e.run.metadata = Some(d.client.metadata.to_string());
                e.driving = Some(d);
            }
            Err((kind, err)) => e.fail(kind, err),
        }
        e
    }

    /// Ends the episode (success, horizon).
    fn end(&mut self) {
        self.driving = None;
        self.seconds = Some(self.t0.elapsed().as_secs_f64());
    }

    /// Ends the episode on an error of `kind`.
    fn fail(&mut self, kind: ErrorKind, error: anyhow::Error) {
        self.run.error = Some(error);
        self.run.error_kind = Some(kind);
        self.end();
    }
}

/// The episodes in flight of one lane (`crate::lanes`).
struct Lane<'w> {
    capacity: usize,
    live: Vec<Episode<'w>>,
    /// The chunk queued for the episodes at these positions of `live`.
    pending: Option<(Vec<usize>, PendingChunks)>,
}

/// The policies' next actions for every episode in `live` that is still driven, then one
/// batched world-model chunk for all of them, queued (`Rollout::begin_chunks`): the positions of
/// those episodes and their chunk. Episodes whose policy or chunk fails end here.
fn begin(cfg: &EvalConfig, wm: &WorldModel, mut fk: Option<&mut Fk>, jobs: &[(&PolicyConfig, &Task, usize)], live: &mut [Episode]) -> Option<(Vec<usize>, PendingChunks)> {
    let (mut windows, mut positions) = (Vec::new(), Vec::new());
    for (pos, e) in live.iter_mut().enumerate().filter(|(_, e)| e.driving.is_some()) {
        let (policy, task, i) = jobs[e.job];
        match next_poses(cfg, wm, fk.as_deref_mut(), policy, &task.starts[i], e) {
            Ok(poses) => {
                windows.push(poses);
                positions.push(pos);
            }
            Err(err) => e.fail(ErrorKind::of(&err, ErrorKind::Policy), err),
        }
    }
    if positions.is_empty() {
        return None;
    }
    let rollouts: Vec<&Rollout> = positions.iter().filter_map(|&p| live[p].driving.as_ref().map(|d| &d.rollout)).collect();
    match crate::fallible::guarded(|| format!("generating a chunk of {} episode(s)", rollouts.len()), || Rollout::begin_chunks(&rollouts, &windows)) {
        Ok(pending) => Some((positions, pending)),
        Err(err) => {
            end_all(live, &positions, &err);
            None
        }
    }
}

/// Ends the episodes at `positions` of `live` with the world model's error.
fn end_all(live: &mut [Episode], positions: &[usize], err: &anyhow::Error) {
    let text = format!("world model: {err:#}");
    for &p in positions {
        live[p].fail(ErrorKind::WorldModel, anyhow::anyhow!("{text}"));
    }
}

/// Reads back the chunk `begin` queued for the episodes at `positions` of `live`, adds its frames
/// to each and asks the judge. Episodes that end (success, horizon, error) lose `driving`.
fn finish(cfg: &EvalConfig, judge: &Judge, jobs: &[(&PolicyConfig, &Task, usize)], live: &mut [Episode], positions: &[usize], pending: PendingChunks) {
    let mut rollouts: Vec<&mut Rollout> = live
        .iter_mut()
        .enumerate()
        .filter(|(p, _)| positions.contains(p))
        .filter_map(|(_, e)| e.driving.as_mut().map(|d| &mut d.rollout))
        .collect();
    let n = rollouts.len();
    let chunks = crate::fallible::guarded(|| format!("reading back a chunk of {n} episode(s)"), || Rollout::finish_chunks(&mut rollouts, pending));
    drop(rollouts);
    let chunks = match chunks {
        Ok(c) => c,
        Err(err) => return end_all(live, positions, &err),
    };
    for (&p, chunk) in positions.iter().zip(chunks) {
        let e = &mut live[p];
        let (policy, task, i) = jobs[e.job];
        let start = &task.starts[i];
        let judged = (|| -> std::result::Result<bool, (ErrorKind, anyhow::Error)> {
            e.run.frames.extend(tensor_to_frames(&chunk.frames).map_err(|e| (ErrorKind::WorldModel, e))?);
            e.run.chunks += 1;
            let at_horizon = e.run.frames.len() >= cfg.horizon;
            let subject = Subject { policy: &policy.name, task: &task.cfg.name, prompt: &start.prompt, episode: i, rules: &task.cfg.rules, ends_episode: at_horizon };
            if cfg.stop_on_success || at_horizon {
                let verdict = judge.judge(&e.run.frames, &subject).context("judge").map_err(|e| (ErrorKind::Judge, e))?;
                let success = verdict.success;
                e.run.verdict = Some(verdict);
                return Ok(at_horizon || (cfg.stop_on_success && success));
            }
            Ok(false)
        })();
        match judged {
            Ok(true) => e.end(),
            Ok(false) => {}
            Err((kind, err)) => e.fail(kind, err),
        }
    }
}

/// The policy's next actions of episode `e` as the model's normalized [n, d_a] window: requests
/// the latest frame's observation until a chunk of K poses (or the horizon's rest) is filled.
fn next_poses(cfg: &EvalConfig, wm: &WorldModel, mut fk: Option<&mut Fk>, policy: &PolicyConfig, start: &Start, e: &mut Episode) -> Result<Tensor> {
    let obs_cfg = cfg.observation_of(policy);
    let Episode { run, driving, .. } = e;
    let d = driving.as_mut().context("the episode has ended")?;
    let want = wm.spec.future.min(cfg.horizon - run.frames.len());
    let latest = run.frames.last().unwrap_or(&start.x0).clone();
    let mut poses: Vec<Vec<f32>> = Vec::with_capacity(want);
    while poses.len() < want {
        let obs = observation::observation(&latest, d.adapter.state(), &start.prompt, obs_cfg)?;
        run.requests += 1;
        let reply = d.client.infer(&obs)?;
        let rows = observation::action_rows(&reply, &obs_cfg.actions_key)?;
        ensure!(!rows.is_empty(), "the policy returned an empty action chunk");
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
        poses.extend(d.adapter.apply(&rows[..take], fk.as_deref_mut())?);
        if policy.chunk == ChunkMode::Cut {
            break;
        }
    }
    let window = wm.normalize(&poses)?;
    run.actions.extend(poses);
    Ok(window)
}
