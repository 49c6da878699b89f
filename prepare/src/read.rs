//! Reading the clips of this rank's shards, on a thread of their own: frames read from the source,
//! x0 enhanced when asked, every frame fitted to the cache's size and the actions normalized, sent
//! to the encoder as plain bytes and numbers.

use std::path::Path;
use std::sync::mpsc::SyncSender;

use anyhow::{bail, ensure, Context, Result};
use bwm_data::clips::{ClipPlan, EpisodeFrames};
use bwm_data::frames::fit;
use bwm_data::latent_cache::ClipEntry;
use bwm_data::{ActionStats, CameraSelection, EpisodeSource, ResizeMode};
use image::RgbImage;

use crate::folder::ShardSkip;
use crate::plan::upscale_factor;

/// The most frames after x0 read at once from an episode for a group of clips.
pub(crate) const MAX_SPAN: usize = 512;

/// What the reading thread sends the encoder.
pub(crate) enum Input {
    Clip(ClipInput),
    Skip(ShardSkip),
    /// Every clip of this shard has been sent.
    End(usize),
}

/// A clip as plain bytes and numbers: the reading thread does no tensor work, since torch's
/// OpenMP threads started from a second thread spin on the cores the encoder needs.
pub(crate) struct ClipInput {
    pub(crate) entry: ClipEntry,
    /// [F, H, W, 3] RGB.
    pub(crate) pixels: Vec<u8>,
    /// [F, d_a] normalized, row-major.
    pub(crate) actions: Vec<f32>,
}

/// Reads, resizes and normalizes the clips of the shards to encode, on its own thread.
pub(crate) struct Reader<'a> {
    pub(crate) source: &'a dyn EpisodeSource,
    pub(crate) plan: &'a ClipPlan,
    pub(crate) cameras: &'a CameraSelection,
    pub(crate) stats: &'a ActionStats,
    pub(crate) size: (u32, u32),
    pub(crate) resize: ResizeMode,
    pub(crate) allow_upscale: bool,
    pub(crate) enhance_x0: Option<&'a str>,
}

impl Reader<'_> {
    pub(crate) fn read(&self, shards: &[usize], jobs: &[Vec<(usize, usize)>], tx: SyncSender<Input>) {
        let mut x0: Option<(usize, std::result::Result<RgbImage, String>)> = None;
        for (&shard, clips) in shards.iter().zip(jobs) {
            for group in groups(self.plan, clips) {
                let (e, _) = group[0];
                let ep = &self.plan.episodes[e];
                if x0.as_ref().is_none_or(|(i, _)| *i != e) {
                    x0 = Some((e, self.x0(e).map_err(|err| format!("{err:#}"))));
                }
                let read = match x0.as_ref().map(|(_, r)| r) {
                    Some(Ok(first)) => self.read_group(e, &group).map(|frames| (first, frames)).map_err(|err| format!("{err:#}")),
                    Some(Err(reason)) => Err(reason.clone()),
                    None => return,
                };
                let skip = |clips: usize, reason: String| Input::Skip(ShardSkip { episode: ep.info.index, clips, reason });
                let sent = match read {
                    Ok((first, frames)) => group.iter().all(|&(_, w)| match self.clip(e, w, first, &frames) {
                        Ok(c) => tx.send(Input::Clip(c)).is_ok(),
                        Err(err) => tx.send(skip(1, format!("{err:#}"))).is_ok(),
                    }),
                    Err(reason) => tx.send(skip(group.len(), reason)).is_ok(),
                };
                if !sent {
                    return;
                }
            }
            if tx.send(Input::End(shard)).is_err() {
                return;
            }
        }
    }

    /// The episode's x0 at the target size, enhanced first when asked.
    fn x0(&self, e: usize) -> Result<RgbImage> {
        let ep = &self.plan.episodes[e];
        let x0 = self.source.frames(ep.episode, 0..1, self.cameras)?.pop().context("frame 0 was not read")?;
        let Some(cmd) = self.enhance_x0 else { return Ok(fit(&x0, self.size.0, self.size.1, self.resize)) };
        let enhanced = enhance(cmd, &x0, ep.episode).context("--enhance-x0")?;
        let (w, h) = enhanced.dimensions();
        if !self.allow_upscale && upscale_factor((w, h), self.size, self.resize) > 1.0 {
            bail!("--enhance-x0 returned {w}x{h}, smaller than the target {}x{} (pass --allow-upscale to accept)", self.size.0, self.size.1);
        }
        Ok(fit(&enhanced, self.size.0, self.size.1, self.resize))
    }

    /// The frames of a group of windows of one episode, resized (x0 is taken from `x0`).
    fn read_group(&self, e: usize, group: &[(usize, usize)]) -> Result<EpisodeFrames> {
        let ep = &self.plan.episodes[e];
        let windows: Vec<_> = group.iter().map(|&(_, w)| ep.windows[w].clone()).collect();
        let frames = EpisodeFrames::read(self.source, ep.episode, &windows, self.cameras)?;
        Ok(frames.map(|f| fit(f, self.size.0, self.size.1, self.resize)))
    }

    fn clip(&self, e: usize, w: usize, x0: &RgbImage, frames: &EpisodeFrames) -> Result<ClipInput> {
        let ep = &self.plan.episodes[e];
        let window = &ep.windows[w];
        let images = window.frames.iter().map(|&f| if f == 0 { Ok(x0) } else { frames.get(f) }).collect::<Result<Vec<_>>>()?;
        let (width, height) = self.size;
        let mut bytes = Vec::with_capacity(images.len() * (width * height * 3) as usize);
        for img in &images {
            ensure!(img.dimensions() == self.size, "a frame is {}x{} after resizing", img.width(), img.height());
            bytes.extend_from_slice(img.as_raw());
        }
        let actions: Vec<f32> = window.frames.iter().flat_map(|&i| self.stats.normalize(&ep.actions[i])).collect();
        Ok(ClipInput {
            entry: ClipEntry { file: String::new(), episode: ep.info.index, frames: window.frames.clone(), task: ep.info.task.clone() },
            pixels: bytes,
            actions,
        })
    }
}

/// Consecutive clips of one episode whose frames after x0 span at most `MAX_SPAN` frames.
pub(crate) fn groups(plan: &ClipPlan, clips: &[(usize, usize)]) -> Vec<Vec<(usize, usize)>> {
    let bounds = |e: usize, w: usize| {
        let frames = &plan.episodes[e].windows[w].frames;
        let lo = frames.iter().copied().filter(|&f| f > 0).min().unwrap_or(1);
        (lo, frames.iter().copied().max().unwrap_or(0))
    };
    let mut out: Vec<Vec<(usize, usize)>> = Vec::new();
    let mut span = (0, 0);
    for &(e, w) in clips {
        let (lo, hi) = bounds(e, w);
        match out.last_mut() {
            Some(g) if g[0].0 == e && hi.max(span.1) + 1 - lo.min(span.0) <= MAX_SPAN => {
                g.push((e, w));
                span = (lo.min(span.0), hi.max(span.1));
            }
            _ => {
                out.push(vec![(e, w)]);
                span = (lo, hi);
            }
        }
    }
    out
}

/// Runs the x0 enhancement command on one image (files in a temporary folder, removed after).
pub(crate) fn enhance(cmd: &str, x0: &RgbImage, episode: usize) -> Result<RgbImage> {
    let dir = tempfile::Builder::new()
        .prefix(&format!("bwm-enhance-x0-{episode}-"))
        .tempdir()
        .context("creating a temporary folder for the x0 enhancement")?;
    let (input, output) = (dir.path().join("in.png"), dir.path().join("out.png"));
    let quote = |p: &Path| format!("'{}'", p.display().to_string().replace('\'', "'\\''"));
    let line = cmd.replace("{in}", &quote(&input)).replace("{out}", &quote(&output));
    x0.save(&input).with_context(|| format!("writing {}", input.display()))?;
    let run = std::process::Command::new("sh").arg("-c").arg(&line).output().with_context(|| format!("running `{line}`"))?;
    if !run.status.success() {
        let stderr = String::from_utf8_lossy(&run.stderr);
        let tail: String = stderr.trim().lines().last().unwrap_or_default().chars().take(300).collect();
        bail!("`{line}` failed ({}): {tail}", run.status);
    }
    Ok(image::open(&output).with_context(|| format!("reading the enhanced x0 {}", output.display()))?.to_rgb8())
}
