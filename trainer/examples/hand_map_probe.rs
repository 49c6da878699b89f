//! Whether the hand map (`model.action.hand_map`, docs/training.md) lets a DiT draw contact that
//! depends on where the commanded hand is relative to an object seen in the frames: a synthetic
//! probe on the CPU, a few minutes per run.
//!
//!     cargo run --release -p bwm-trainer --example hand_map_probe -- [--steps 8000] [--seed 11] [--out DIR]
//!
//! Each clip's latents (16 channels, 4 latent frames of 16 x 16: x0, two of history, one future)
//! hold a hand (a blob on channels 0-3) at the commanded position of the last action of each latent
//! frame, mapped onto the latent grid by a fixed camera the model is not given, and a handle (a blob
//! on channels 4-7) at a random place. The hand's history moves half way towards where it ends;
//! the future frame's actions jump to its end, 0-4 cells from the handle in any direction. Contact:
//! the handle is drawn 3 cells further down in the future frame exactly when the hand ends within 2
//! cells of it (one token of the 1x2x2 patch), so the outcome is decided by geometry inside a token,
//! as the Meta-World drawer's is (docs/fidelity.md, "What the trainings show").
//!
//! The same tiny DiT (width 64, 2 blocks) trains on the same clips and draws, once without the map
//! and once with it; on 128 held-out clips the future frame is estimated in one step from pure
//! noise, averaged over 8 noise draws (the model's expected frame), and the handle is counted as
//! drawn moved when that estimate lies closer to the moved handle than to the resting one. Printed
//! (and in DIR/hand_map_probe.json): per run the held-out outcomes drawn right, the contact drawn
//! where there is none (invented) and the contact not drawn (missed). With --out, a run already
//! trained there to its end is scored again rather than trained again.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use bwm_data::latent_cache::{CacheIndex, CacheWriter, ClipEntry};
use bwm_trainer::{Resume, RunConfig, Trainer};
use tch::{Device, Kind, Tensor};

const CLIPS: usize = 1024;
const HELD_OUT: usize = 128;
const GRID: i64 = 16;
/// Contact when the hand ends within this many latent cells of the handle.
const REACH: f64 = 2.0;
/// How far the handle moves on contact (cells, down).
const PULL: f64 = 3.0;
/// Noise draws averaged per held-out clip.
const DRAWS: u64 = 8;

/// The camera: an action's (x, y) in -1..1 to latent-grid coordinates (u, v), and back.
const CAMERA: [[f64; 2]; 2] = [[4.8, 1.8], [-1.2, 4.2]];
const CENTRE: f64 = 7.5;

fn to_grid(x: f64, y: f64) -> (f64, f64) {
    (CENTRE + CAMERA[0][0] * x + CAMERA[0][1] * y, CENTRE + CAMERA[1][0] * x + CAMERA[1][1] * y)
}

fn from_grid(u: f64, v: f64) -> (f64, f64) {
    let [[a, b], [c, d]] = CAMERA;
    let (p, q, det) = (u - CENTRE, v - CENTRE, a * d - b * c);
    ((d * p - b * q) / det, (a * q - c * p) / det)
}

/// A blob of height 3 and width 0.7 cells at (u, v), [GRID, GRID].
fn blob(u: f64, v: f64) -> Tensor {
    let g = Tensor::arange(GRID, (Kind::Float, Device::Cpu));
    let d2 = (g.view([1, GRID]) - u).square() + (g.view([GRID, 1]) - v).square();
    (d2 * (-0.5 / 0.49)).exp() * 3.0
}

/// Where a held-out clip's handle rests and whether the hand reaches it.
struct Truth {
    handle: (f64, f64),
    contact: bool,
}

fn write_clips(dir: &Path, seed: i64) -> Result<Vec<Truth>> {
    tch::manual_seed(seed);
    let index = CacheIndex::new(vec![16, 4, GRID, GRID], 4, 8, 4, [128, 128], 25.0, "hand_map_probe");
    let mut w = CacheWriter::create(dir, index)?;
    let mut truth = Vec::with_capacity(CLIPS);
    let uniform = |lo: f64, hi: f64| lo + (hi - lo) * Tensor::rand([1], (Kind::Float, Device::Cpu)).double_value(&[0]);
    for i in 0..CLIPS {
        let handle = (uniform(4.0, 11.0), uniform(3.0, 9.0));
        let (distance, angle) = (uniform(0.0, 4.0), uniform(0.0, std::f64::consts::TAU));
        let end = (handle.0 + distance * angle.cos(), handle.1 + distance * angle.sin());
        let start = (uniform(1.0, 14.0), uniform(1.0, 14.0));
        let contact = distance < REACH;
        // 13 pixel frames' actions (x, y, z, gripper): 9 of x0 and history, 4 of the future.
        let rows: Vec<Tensor> = (0..13)
            .map(|f| {
                let (u, v) = if f < 9 {
                    let k = f as f64 / 24.0;
                    (start.0 + (end.0 - start.0) * k, start.1 + (end.1 - start.1) * k)
                } else {
                    end
                };
                let (x, y) = from_grid(u, v);
                Tensor::from_slice(&[x as f32, y as f32, 0.0, if f < 9 { -1.0 } else { 1.0 }])
            })
            .collect();
        let actions = Tensor::stack(&rows, 0);
        let background = Tensor::randn([16, GRID, GRID], (Kind::Float, Device::Cpu)) * 0.2;
        let frames: Vec<Tensor> = (0..4i64)
            .map(|l| {
                let last = 4 * l; // the last action of latent frame l's group (frame 0 for x0)
                let (u, v) = to_grid(actions.double_value(&[last, 0]), actions.double_value(&[last, 1]));
                let frame = background.copy();
                let pulled = if l == 3 && contact { PULL } else { 0.0 };
                let _ = frame.narrow(0, 0, 4).g_add_(&blob(u, v).unsqueeze(0));
                let _ = frame.narrow(0, 4, 4).g_add_(&blob(handle.0, handle.1 + pulled).unsqueeze(0));
                frame
            })
            .collect();
        let entry = ClipEntry { file: String::new(), episode: i as i64, frames: (0..13).collect(), task: "hand_map_probe".into() };
        w.add(entry, &Tensor::stack(&frames, 1), &actions, None)?;
        truth.push(Truth { handle, contact });
    }
    w.finish()?;
    Ok(truth)
}

fn config(cache: &Path, out: &Path, steps: u64, seed: i64, map: bool) -> Result<RunConfig> {
    let hands = if map { ", hand_map = { hands = [[0, 1, 2]] }" } else { "" };
    let text = format!(
        r#"
[run]
name = "hand_map_probe"
out_dir = "{out}"
seed = {seed}
device = "cpu"

[model]
preset = "tiny"
dtype = "f32"
dit = {{ dim = 64, in_dim = 16, out_dim = 16, ffn_dim = 128, freq_dim = 32, text_dim = 16, num_heads = 2, num_layers = 2, eps = 1e-6, patch_size = [1, 2, 2] }}
action = {{ action_dim = 4{hands} }}

[data]
latent_cache = "{cache}"
holdout_episodes = {HELD_OUT}

[optim]
lr = 1e-3
warmup_steps = 30

[train]
steps = {steps}
micro_batch = 8

[log]
tensorboard = false
progress = false
"#,
        out = out.display(),
        cache = cache.display()
    );
    RunConfig::parse(&text, &[])
}

/// Held-out outcomes: (drawn right, invented, of no contact, missed, of contact).
fn score(t: &Trainer, truth: &[Truth]) -> Result<[usize; 5]> {
    let (mut right, mut invented, mut apart, mut missed, mut contact) = (0, 0, 0, 0, 0);
    let sigma = t.objective.schedule.sigmas[0];
    for (c, truth) in truth.iter().enumerate().skip(CLIPS - HELD_OUT) {
        let clip = t.cache.load(c, Device::Cpu)?;
        let mut handle = Tensor::zeros([GRID, GRID], (Kind::Float, Device::Cpu));
        for k in 0..DRAWS {
            let draw = t.objective.draw(1_000_000 + DRAWS * c as u64 + k, &t.cache.index.latent_shape);
            let clean_history = draw.history_noise.zeros_like().unsqueeze(0);
            let p = t.objective.prepare(&clip.latents.unsqueeze(0), &draw.noise.unsqueeze(0), &clean_history, &[0])?;
            let velocity = tch::no_grad(|| t.model.forward(&p.input, &p.frame_timesteps, &clip.actions.unsqueeze(0)))?;
            // x_t = (1 - sigma) x0 + sigma noise and v = noise - x0, so x0 = x_t - sigma v.
            let future = (&p.input - velocity * sigma).narrow(2, 3, 1).squeeze();
            handle += future.narrow(0, 4, 4).mean_dim(&[0i64][..], false, Kind::Float) / DRAWS as f64;
        }
        let (u, v) = truth.handle;
        let near = |target: Tensor| (&handle - target).square().sum(Kind::Float).double_value(&[]);
        let drawn = near(blob(u, v + PULL)) < near(blob(u, v));
        right += (drawn == truth.contact) as usize;
        invented += (drawn && !truth.contact) as usize;
        missed += (!drawn && truth.contact) as usize;
        apart += !truth.contact as usize;
        contact += truth.contact as usize;
    }
    Ok([right, invented, apart, missed, contact])
}

fn main() -> Result<()> {
    let (mut steps, mut seed, mut out) = (8000u64, 11i64, None::<PathBuf>);
    let mut args = std::env::args().skip(1);
    while let Some(flag) = args.next() {
        let mut value = || args.next().with_context(|| format!("{flag} needs a value"));
        match flag.as_str() {
            "--steps" => steps = value()?.parse().context("--steps is a whole number")?,
            "--seed" => seed = value()?.parse().context("--seed is a whole number")?,
            "--out" => out = Some(PathBuf::from(value()?)),
            other => bail!("unknown argument {other}; usage: hand_map_probe [--steps N] [--seed S] [--out DIR]"),
        }
    }
    let keep = out.is_some();
    let dir = out.unwrap_or_else(|| std::env::temp_dir().join(format!("hand_map_probe-{}", std::process::id())));
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let result = (|| -> Result<serde_json::Value> {
        let cache = dir.join("cache");
        let _ = std::fs::remove_dir_all(&cache);
        let truth = write_clips(&cache, seed)?;
        let mut runs = serde_json::Map::new();
        for map in [false, true] {
            let name = if map { "with the hand map" } else { "without it" };
            let run_dir = dir.join(if map { "run-map" } else { "run-plain" });
            if !keep {
                let _ = std::fs::remove_dir_all(&run_dir);
            }
            let start = std::time::Instant::now();
            let mut trainer = Trainer::new(config(&cache, &run_dir, steps, seed, map)?, Resume::Auto)?;
            trainer.run()?;
            let [right, invented, apart, missed, contact] = score(&trainer, &truth)?;
            println!(
                "{name}: {steps} steps, seed {seed}: held out, {right} of {HELD_OUT} outcomes drawn right; contact invented in {invented} of {apart} \
                 clips without it, missed in {missed} of {contact} with it ({:.0} s)",
                start.elapsed().as_secs_f64()
            );
            runs.insert(
                name.into(),
                serde_json::json!({"right": right, "invented": invented, "without_contact": apart, "missed": missed, "with_contact": contact}),
            );
        }
        Ok(serde_json::json!({"steps": steps, "seed": seed, "held_out": HELD_OUT, "runs": runs}))
    })();
    let report = match result {
        Ok(report) => report,
        Err(e) => {
            if !keep {
                let _ = std::fs::remove_dir_all(&dir);
            }
            return Err(e);
        }
    };
    if keep {
        let path = dir.join("hand_map_probe.json");
        std::fs::write(&path, serde_json::to_string_pretty(&report)? + "\n").with_context(|| format!("writing {}", path.display()))?;
    } else {
        std::fs::remove_dir_all(&dir).with_context(|| format!("removing {}", dir.display()))?;
    }
    Ok(())
}
