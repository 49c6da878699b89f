//! Opens a tiny world model with random weights (and a random VAE), starts it from a grey first
//! frame, steps it twice with 4 actions each and writes the 8 generated frames as PNGs.
//!
//!     cargo run --release -p bwm-inference --example step -- OUT_DIR
//!
//! With trained weights, set `checkpoint`, `vae` and `stats` instead (see `bwm rollout --help`).

use anyhow::{Context, Result};
use bwm_data::frames::tensor_to_frames;
use bwm_inference::tch::{Kind, Tensor};
use bwm_inference::WorldModelOptions;

fn main() -> Result<()> {
    let out = std::path::PathBuf::from(std::env::args().nth(1).unwrap_or_else(|| "step-frames".into()));
    let wm = WorldModelOptions {
        random_weights: Some("tiny".into()),
        device: "cpu".into(),
        history: Some(4),
        future: Some(4),
        sample_steps: Some(2),
        ..Default::default()
    }
    .load()?;
    let d = wm.action_dim() as i64;
    // x0: [3, H, W] in [-1, 1]; actions: one normalized row per frame, in [-1, 1].
    let x0 = Tensor::zeros([3, 32, 32], (Kind::Float, wm.device));
    let mut rollout = wm.rollout(&x0, &Tensor::zeros([d], (Kind::Float, wm.device)))?;
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    let mut written = 0;
    for step in 0..2 {
        let actions = Tensor::full([4, d], 0.1 * (step + 1) as f64, (Kind::Float, wm.device));
        let chunk = rollout.next_chunk(&actions)?;
        for frame in tensor_to_frames(&chunk.frames)? {
            let path = out.join(format!("frame_{written:03}.png"));
            frame.save(&path).with_context(|| format!("writing {}", path.display()))?;
            written += 1;
        }
    }
    println!("step: {written} frames in {}", out.display());
    Ok(())
}
