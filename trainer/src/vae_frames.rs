//! The frames a VAE is trained on ([`FrameSets`]): decoded and resized from any dataset `bwm
//! prepare` reads, split into training and held-out videos, and stored as u8 safetensors so that
//! a machine without FFmpeg can train from frames decoded elsewhere; and a dataset's frames after
//! a round trip through a trained VAE ([`reconstruct`]).

use std::path::Path;

use anyhow::{bail, ensure, Context, Result};
use bwm_data::frames::{fit, frames_to_tensor, unit_to_u8};
use bwm_data::{CameraSelection, EpisodeSource, ResizeMode};
use bwm_model::vae::WanVae;
use tch::{Kind, Tensor};

use bwm_metrics::image::psnr;
use crate::vae_train::FrameSets;

/// Which episodes and frames of a dataset become [`FrameSets`], at what size.
#[derive(Clone, Debug)]
pub struct FrameSelection {
    pub cameras: CameraSelection,
    /// Only the first N episodes (default: all).
    pub max_episodes: Option<usize>,
    /// Whole episodes (positions) held out; when empty, the last `holdout_tail` of every
    /// episode's frames is held out instead.
    pub holdout: Vec<usize>,
    pub holdout_tail: f64,
    /// Frame size (width, height).
    pub size: (u32, u32),
    pub resize: ResizeMode,
}

/// Every frame of each episode (positions in `source.episodes()`), resized, as [3, F, H, W] in [-1, 1].
pub fn episode_videos(source: &dyn EpisodeSource, episodes: &[usize], cameras: &CameraSelection, size: (u32, u32), mode: ResizeMode) -> Result<Vec<Tensor>> {
    episodes
        .iter()
        .map(|&i| {
            let length = source.episodes()[i].length;
            let frames = source.frames(i, 0..length, cameras)?;
            let resized: Vec<_> = frames.iter().map(|f| fit(f, size.0, size.1, mode)).collect();
            frames_to_tensor(&resized).with_context(|| format!("episode position {i} of {}", source.describe()))
        })
        .collect()
}

/// One episode's frames after a round trip through a VAE ([`reconstruct`]).
pub struct Reconstruction {
    /// The dataset's own episode number.
    pub episode_index: i64,
    /// [3, F, H, W] u8.
    pub frames: Tensor,
    /// PSNR (dB) of the reconstruction against the episode's resized frames.
    pub psnr: f64,
}

/// Every frame of the episodes at `episodes` (positions in `source.episodes()`) through `vae` on
/// `device`: what a world model decoding with this VAE could show at best. `on_episode(done)`
/// after each.
pub fn reconstruct(
    source: &dyn EpisodeSource,
    episodes: &[usize],
    cameras: &CameraSelection,
    size: (u32, u32),
    mode: ResizeMode,
    vae: &WanVae,
    device: tch::Device,
    on_episode: &mut dyn FnMut(usize),
) -> Result<Vec<Reconstruction>> {
    let mut out = Vec::with_capacity(episodes.len());
    for (done, &i) in episodes.iter().enumerate() {
        let video = episode_videos(source, &[i], cameras, size, mode)?.remove(0);
        let back = vae.round_trip(&video.to_device(device).unsqueeze(0))?.squeeze_dim(0).to_device(tch::Device::Cpu);
        let frames = unit_to_u8(&back);
        out.push(Reconstruction { episode_index: source.episodes()[i].index, psnr: psnr(&back, &video), frames });
        on_episode(done + 1);
    }
    Ok(out)
}

/// Writes reconstructions as u8 tensors `episode.<episode_index>` ([3, F, H, W]) of one
/// safetensors file, through a temporary file renamed into place.
pub fn write_reconstructions(path: &Path, reconstructions: &[Reconstruction]) -> Result<()> {
    let named: Vec<(String, &Tensor)> = reconstructions.iter().map(|r| (format!("episode.{}", r.episode_index), &r.frames)).collect();
    let tmp = path.with_extension("safetensors.partial");
    Tensor::write_safetensors(&named, &tmp).with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("renaming {} to {}", tmp.display(), path.display()))
}

impl FrameSets {
    /// Decodes and splits the selected frames of `source`, printing what was selected.
    pub fn from_dataset(source: &dyn EpisodeSource, s: &FrameSelection) -> Result<FrameSets> {
        let n = source.episodes().len().min(s.max_episodes.unwrap_or(usize::MAX));
        ensure!(n > 0, "{}: no episodes", source.describe());
        if s.holdout.is_empty() {
            ensure!(s.holdout_tail > 0.0 && s.holdout_tail < 1.0, "--holdout-tail must lie in (0, 1), got {}", s.holdout_tail);
            let all: Vec<usize> = (0..n).collect();
            let videos = episode_videos(source, &all, &s.cameras, s.size, s.resize)?;
            let (mut train, mut holdout) = (Vec::new(), Vec::new());
            for (episode, v) in videos.into_iter().enumerate() {
                let f = v.size()[1];
                ensure!(
                    f >= 2,
                    "episode {episode} has {f} frame(s): --holdout-tail holds out the end of every episode, which needs 2 frames or more (hold out whole episodes with --holdout)"
                );
                let held = ((f as f64 * s.holdout_tail).round() as i64).clamp(1, f - 1);
                train.push(v.narrow(1, 0, f - held));
                holdout.push(v.narrow(1, f - held, held));
            }
            println!("frames: {n} episodes, the last {:.0}% of each held out, frames at {}x{} ({:?})", s.holdout_tail * 100.0, s.size.0, s.size.1, s.resize);
            return Ok(FrameSets { train, holdout });
        }
        let holdout = &s.holdout;
        ensure!(holdout.iter().all(|&i| i < n), "--holdout {holdout:?}: the dataset has episodes 0..{n}");
        let train: Vec<usize> = (0..n).filter(|i| !holdout.contains(i)).collect();
        ensure!(!train.is_empty(), "every episode is held out; nothing to train on");
        println!("frames: {} episodes for training {:?}, held out {:?}, frames at {}x{} ({:?})", train.len(), train, holdout, s.size.0, s.size.1, s.resize);
        Ok(FrameSets {
            train: episode_videos(source, &train, &s.cameras, s.size, s.resize)?,
            holdout: episode_videos(source, holdout, &s.cameras, s.size, s.resize)?,
        })
    }

    /// Writes the videos as u8 tensors `train.NNNN` and `holdout.NNNN` of one safetensors file.
    pub fn write(&self, path: &Path) -> Result<()> {
        let mut named: Vec<(String, Tensor)> = Vec::new();
        for (split, videos) in [("train", &self.train), ("holdout", &self.holdout)] {
            for (i, v) in videos.iter().enumerate() {
                named.push((format!("{split}.{i:04}"), unit_to_u8(v)));
            }
        }
        Tensor::write_safetensors(&named, path).with_context(|| format!("writing {}", path.display()))
    }

    /// Reads what [`FrameSets::write`] wrote.
    pub fn read(path: &Path) -> Result<FrameSets> {
        let mut named = Tensor::read_safetensors(path).with_context(|| format!("reading {}", path.display()))?;
        named.sort_by(|a, b| a.0.cmp(&b.0));
        let mut data = FrameSets { train: vec![], holdout: vec![] };
        let mut size = None;
        for (name, t) in named {
            ensure!(t.kind() == Kind::Uint8 && t.dim() == 4 && t.size()[0] == 3, "{}: '{name}' is not a [3, F, H, W] u8 video", path.display());
            let hw = (t.size()[2], t.size()[3]);
            let first = size.get_or_insert_with(|| (hw, name.clone())).clone();
            ensure!(hw == first.0, "{}: '{name}' has {}x{} (HxW) frames, '{}' {}x{}: one size for all", path.display(), hw.0, hw.1, first.1, first.0 .0, first.0 .1);
            let v = t.to_kind(Kind::Float) / 127.5 - 1.0;
            match name.split('.').next() {
                Some("train") => data.train.push(v),
                Some("holdout") => data.holdout.push(v),
                _ => bail!("{}: unexpected tensor '{name}' (expected train.N / holdout.N)", path.display()),
            }
        }
        ensure!(!data.train.is_empty() && !data.holdout.is_empty(), "{}: needs training and held-out videos", path.display());
        Ok(data)
    }

    /// The frames' (width, height), one for all videos.
    pub fn size(&self) -> (u32, u32) {
        let s = self.train[0].size();
        (s[3] as u32, s[2] as u32)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn video(frames: i64, seed: i64) -> Tensor {
        bwm_model::vb::with_seed(seed, || Tensor::rand([3, frames, 8, 8], (Kind::Float, tch::Device::Cpu))) * 2.0 - 1.0
    }

    #[test]
    fn frame_sets_survive_a_write_and_read_to_u8_rounding() -> Result<()> {
        let dir = bwm_testdir::TestDir::new("vae-frames");
        let path = dir.path().join("frames.safetensors");
        let sets = FrameSets { train: vec![video(5, 1), video(3, 2)], holdout: vec![video(2, 3)] };
        sets.write(&path)?;
        let back = FrameSets::read(&path)?;
        assert_eq!((back.train.len(), back.holdout.len()), (2, 1));
        for (a, b) in sets.train.iter().chain(&sets.holdout).zip(back.train.iter().chain(&back.holdout)) {
            assert_eq!(a.size(), b.size());
            let err = (a - b).abs().max().double_value(&[]);
            assert!(err <= 1.0 / 127.5 + 1e-6, "u8 round trip off by {err}");
        }
        Ok(())
    }

    #[test]
    fn reading_frames_rejects_foreign_tensors_and_a_missing_split() -> Result<()> {
        let dir = bwm_testdir::TestDir::new("vae-frames-bad");
        let path = dir.path().join("bad.safetensors");
        Tensor::write_safetensors(&[("train.0000", Tensor::zeros([3, 2, 4, 4], (Kind::Float, tch::Device::Cpu)))], &path)?;
        let err = FrameSets::read(&path).unwrap_err().to_string();
        assert!(err.contains("is not a [3, F, H, W] u8 video"), "{err}");
        Tensor::write_safetensors(&[("train.0000", Tensor::zeros([3, 2, 4, 4], (Kind::Uint8, tch::Device::Cpu)))], &path)?;
        let err = FrameSets::read(&path).unwrap_err().to_string();
        assert!(err.contains("needs training and held-out videos"), "{err}");
        let u8s = |h: i64| Tensor::zeros([3, 2, h, 4], (Kind::Uint8, tch::Device::Cpu));
        Tensor::write_safetensors(&[("train.0000", u8s(4)), ("holdout.0000", u8s(6))], &path)?;
        let err = FrameSets::read(&path).unwrap_err().to_string();
        assert!(err.contains("'train.0000' has 4x4 (HxW) frames, 'holdout.0000' 6x4: one size for all"), "{err}");
        Ok(())
    }
}
