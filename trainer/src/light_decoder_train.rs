//! `bwm train-light-decoder`: fits a light decoder (`bwm_model::light_decoder`) to a trained VAE's
//! decoder. Each step encodes a batch of training clips with the VAE (posterior means, normalized
//! as the DiT sees them), decodes those latents with both decoders, and moves the light one towards
//! the VAE's frames (mean squared error): it learns to reproduce the decoder, not the dataset, so
//! that a world model's latents decode as they would through the VAE. Held-out clips measure the
//! agreement (PSNR against the VAE's decoded frames) and each decoder against the real frames.

use std::collections::BTreeMap;
use std::path::Path;
use std::time::Instant;

use anyhow::{ensure, Context, Result};
use bwm_metrics::image::psnr;
use bwm_model::light_decoder::{LightDecoder, LightDecoderConfig, CONFIG_KEY};
use bwm_model::vae::WanVae;
use tch::{Device, Kind, Tensor};

use crate::config::OptimSection;
use crate::dist::LocalCollective;
use crate::optim::{AdamW, Sharding};
use crate::vae_train::{clip_starts, pick_clips, stack_clips, FrameSets};

#[derive(Clone)]
pub struct LightDecoderTrainSettings {
    pub cfg: LightDecoderConfig,
    /// Frames per training clip (1 + 4k): as long as the clips the world model decodes.
    pub clip_frames: usize,
    pub batch: usize,
    pub steps: u64,
    pub lr: f64,
    pub seed: u64,
    pub device: Device,
    /// Held-out agreement every N steps (0: only at the end).
    pub eval_every: u64,
}

/// Mean PSNR over the held-out clips (dB).
#[derive(Debug, Clone, Copy)]
pub struct Agreement {
    /// The light decoder's frames against the VAE decoder's, from the same latents.
    pub light_vs_vae: f64,
    /// The light decoder's frames against the real frames.
    pub light_vs_frames: f64,
    /// The VAE's own round trip against the real frames.
    pub vae_vs_frames: f64,
}

pub struct TrainedLightDecoder {
    pub decoder: LightDecoder,
    /// Its parameters under checkpoint names (f32).
    pub params: Vec<(String, Tensor)>,
    pub holdout: Agreement,
    pub steps: u64,
    pub clip_frames: usize,
    pub seconds: f64,
}

/// The held-out agreement of `decoder` with `vae`'s decoder over non-overlapping clips.
pub fn agreement(vae: &WanVae, decoder: &LightDecoder, videos: &[Tensor], frames: usize, device: Device) -> Result<Agreement> {
    let starts = clip_starts(videos, frames, frames);
    ensure!(!starts.is_empty(), "no held-out clip of {frames} frames to measure the light decoder on");
    let mut sums = [0.0; 3];
    for chunk in starts.chunks(4) {
        let x = stack_clips(videos, chunk, frames, device);
        let (light, full) = tch::no_grad(|| -> Result<(Tensor, Tensor)> {
            let z = vae.encode(&x)?;
            Ok((decoder.decode(&z)?.to_kind(Kind::Float).clamp(-1.0, 1.0), vae.decode(&z)?.to_kind(Kind::Float).clamp(-1.0, 1.0)))
        })?;
        let n = chunk.len() as f64;
        sums[0] += psnr(&light, &full) * n;
        sums[1] += psnr(&light, &x) * n;
        sums[2] += psnr(&full, &x) * n;
    }
    let n = starts.len() as f64;
    Ok(Agreement { light_vs_vae: sums[0] / n, light_vs_frames: sums[1] / n, vae_vs_frames: sums[2] / n })
}

pub fn train_light_decoder(vae: &WanVae, data: &FrameSets, s: &LightDecoderTrainSettings, on_log: &mut dyn FnMut(&str)) -> Result<TrainedLightDecoder> {
    ensure!(s.clip_frames >= 1 && (s.clip_frames - 1) % 4 == 0, "clip frames must be 1+4k, got {}", s.clip_frames);
    ensure!(s.batch > 0 && s.steps > 0, "the light decoder needs a batch and steps (--batch, --steps)");
    let starts = clip_starts(&data.train, s.clip_frames, 1);
    ensure!(!starts.is_empty(), "no training video has {} frames", s.clip_frames);
    ensure!(!data.holdout.is_empty(), "no held-out video to measure the light decoder on");
    let (decoder, store) = LightDecoder::random(&s.cfg, Kind::Float, s.device, s.seed as i64)?;
    decoder.check_vae(&vae.cfg).context("the light decoder's settings")?;
    let optim: OptimSection =
        toml::from_str(&format!("lr = {}\nweight_decay = 0.0\ngrad_clip = 1.0\nwarmup_steps = 20\nschedule = \"cosine\"\nmin_lr_ratio = 0.05", s.lr))?;
    let mut opt = AdamW::new(&store.named_parameters(), &["*".into()], &[], &optim, s.steps, Sharding::SINGLE)?;
    let start = Instant::now();
    for step in 0..s.steps {
        let x = stack_clips(&data.train, &pick_clips(&starts, s.batch, s.seed, step), s.clip_frames, s.device);
        let (z, target) = tch::no_grad(|| -> Result<(Tensor, Tensor)> {
            let z = vae.encode(&x)?;
            let target = vae.decode(&z)?.to_kind(Kind::Float).clamp(-1.0, 1.0);
            Ok((z.to_kind(Kind::Float), target))
        })?;
        let mse = (decoder.decode(&z)? - &target).square().mean(Kind::Float);
        mse.f_backward()?;
        opt.collect_grads();
        let report = opt.step(1.0, &mut LocalCollective::new())?;
        let last = step + 1 == s.steps;
        if (step + 1) % 50 == 0 || last || report.is_none() {
            let m = mse.double_value(&[]);
            on_log(&format!(
                "step {:>5}/{}  mse against the VAE's frames {m:.5} (PSNR {:.2} dB)  {:.2} s/step{}",
                step + 1,
                s.steps,
                10.0 * (4.0 / m).log10(),
                start.elapsed().as_secs_f64() / (step + 1) as f64,
                if report.is_none() { "  (non-finite: update skipped)" } else { "" }
            ));
        }
        if s.eval_every > 0 && (step + 1) % s.eval_every == 0 && !last {
            let a = agreement(vae, &decoder, &data.holdout, s.clip_frames, s.device)?;
            on_log(&format!("step {:>5}: held-out PSNR against the VAE's frames {:.2} dB", step + 1, a.light_vs_vae));
        }
    }
    let holdout = agreement(vae, &decoder, &data.holdout, s.clip_frames, s.device)?;
    let params = store.named_parameters().into_iter().map(|(n, t)| (n, t.detach().to_kind(Kind::Float))).collect();
    Ok(TrainedLightDecoder { decoder, params, holdout, steps: s.steps, clip_frames: s.clip_frames, seconds: start.elapsed().as_secs_f64() })
}

/// Writes the light decoder (weights, config and held-out agreement in the metadata) atomically.
pub fn save_light_decoder(trained: &TrainedLightDecoder, vae_path: &Path, path: &Path) -> Result<()> {
    let h = &trained.holdout;
    let meta = BTreeMap::from([
        (CONFIG_KEY.to_string(), serde_json::to_string(&trained.decoder.cfg)?),
        ("bwm.vae".to_string(), vae_path.display().to_string()),
        ("bwm.holdout_psnr_vs_vae_db".to_string(), format!("{:.3}", h.light_vs_vae)),
        ("bwm.holdout_psnr_vs_frames_db".to_string(), format!("{:.3}", h.light_vs_frames)),
        ("bwm.vae_holdout_psnr_db".to_string(), format!("{:.3}", h.vae_vs_frames)),
        ("bwm.steps".to_string(), trained.steps.to_string()),
        ("bwm.clip_frames".to_string(), trained.clip_frames.to_string()),
    ]);
    bwm_checkpoints::write_tensors_replacing(path, &trained.params, &meta)
}

#[cfg(test)]
mod tests {
    use super::*;
    use bwm_model::vae::VaeConfig;

    /// Videos of a square moving across a plain background, in [-1, 1].
    fn videos(n: i64, frames: i64, side: i64) -> Vec<Tensor> {
        (0..n)
            .map(|v| {
                let video = Tensor::full([3, frames, side, side], -0.5, (Kind::Float, Device::Cpu));
                for t in 0..frames {
                    let at = (v * 3 + t) % (side - 8);
                    let _ = video.narrow(1, t, 1).narrow(2, 4, 8).narrow(3, at, 8).fill_(0.8);
                }
                video
            })
            .collect()
    }

    #[test]
    fn learns_the_vaes_frames_and_round_trips_through_its_file() {
        let dir = bwm_testdir::TestDir::new("light-decoder");
        let vae_cfg = VaeConfig { z_dim: 8, ..VaeConfig::with_width(8, 8) };
        let (vae, _) = WanVae::random(&vae_cfg, Kind::Float, Device::Cpu, 0).unwrap();
        let data = FrameSets { train: videos(3, 9, 32), holdout: videos(1, 9, 32) };
        let cfg = LightDecoderConfig { widths: [16, 16, 8, 8], blocks: 1, ..LightDecoderConfig::for_vae(&vae_cfg) };
        let settings = LightDecoderTrainSettings { cfg, clip_frames: 5, batch: 2, steps: 200, lr: 1e-2, seed: 1, device: Device::Cpu, eval_every: 0 };
        let (untrained, _) = LightDecoder::random(&settings.cfg, Kind::Float, Device::Cpu, 1).unwrap();
        let before = agreement(&vae, &untrained, &data.holdout, 5, Device::Cpu).unwrap();
        let mut lines = Vec::new();
        let trained = train_light_decoder(&vae, &data, &settings, &mut |l| lines.push(l.to_string())).unwrap();
        assert!(
            trained.holdout.light_vs_vae > before.light_vs_vae + 3.0,
            "trained {:.2} dB against the VAE's frames, untrained {:.2}",
            trained.holdout.light_vs_vae,
            before.light_vs_vae
        );
        assert!(lines.iter().any(|l| l.starts_with("step   200/200")), "{lines:?}");
        let path = dir.join("light.safetensors");
        save_light_decoder(&trained, Path::new("vae.safetensors"), &path).unwrap();
        let loaded = LightDecoder::load(&path, Kind::Float, Device::Cpu).unwrap();
        let z = Tensor::randn([1, 8, 2, 2, 2], (Kind::Float, Device::Cpu));
        assert!(loaded.decode(&z).unwrap().equal(&trained.decoder.decode(&z).unwrap()), "the file holds the trained weights");
        assert!(!dir.join("light.safetensors.tmp").exists());
        // A VAE file is not a light decoder.
        let vae_path = dir.join("vae.safetensors");
        bwm_checkpoints::write_tensors(&vae_path, &[("w".to_string(), Tensor::zeros([1], (Kind::Float, Device::Cpu)))], &BTreeMap::new()).unwrap();
        let e = LightDecoder::load(&vae_path, Kind::Float, Device::Cpu).err().expect("refused");
        assert!(format!("{e:#}").contains("is not a light decoder"), "{e:#}");
    }
}
