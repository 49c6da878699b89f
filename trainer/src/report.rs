//! What a person looks at after a run: the loss curve (SVG) from `metrics.jsonl`, and a rollout
//! video of a held-out clip with the ground truth on the left and the model's frames on the right.

use std::path::Path;

use anyhow::{ensure, Context, Result};
use bwm_data::frames::{frame_strip, tensor_to_frames};
use bwm_model::vae::WanVae;
use plotters::prelude::*;
use tch::Kind;

use crate::image_metrics::psnr;
use crate::trainer::Trainer;
use crate::validation::rollout_clip;

/// Every optimizer step's loss, `step<TAB>loss` lines, in the run folder.
pub const LOSSES_FILE: &str = "losses.tsv";

/// An append-only log of the run folder, one record a line (`losses.tsv`, `metrics.jsonl`). Each
/// line goes out in one write of the whole formatted line, so a process killed between writes
/// leaves whole lines; a write cut short all the same (a crash of the machine, a full disk) leaves
/// an unterminated last line, which opening the log removes, so that a resumed run's first line
/// never joins a fragment (`4` then `5\t0.3` would read as step 45).
pub struct LineLog {
    file: std::fs::File,
    path: std::path::PathBuf,
}

impl LineLog {
    /// Opens `path` for appending (created when missing), without an unterminated last line.
    pub fn open(path: &Path) -> Result<Self> {
        let file = std::fs::OpenOptions::new().read(true).append(true).create(true).open(path).with_context(|| format!("opening {}", path.display()))?;
        let len = file.metadata().with_context(|| format!("reading {}", path.display()))?.len();
        let whole = whole_lines_len(&file, len).with_context(|| format!("reading {}", path.display()))?;
        if whole < len {
            let mut cut = vec![0u8; (len - whole).min(200) as usize];
            std::os::unix::fs::FileExt::read_exact_at(&file, &mut cut, whole).with_context(|| format!("reading {}", path.display()))?;
            file.set_len(whole).with_context(|| format!("truncating {}", path.display()))?;
            eprintln!(
                "warning: {}: removed its unterminated last line ({} bytes, a write cut short by a crash): {:?}",
                path.display(),
                len - whole,
                String::from_utf8_lossy(&cut)
            );
        }
        Ok(Self { file, path: path.to_path_buf() })
    }

    /// Appends `line` (without its newline), the record of optimizer step `step`.
    pub fn append(&mut self, line: &str, step: u64) -> Result<()> {
        use std::io::Write;
        let record = format!("{line}\n");
        let name = self.path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        // Fault injection for the crash-safety test, BWM_FAULT_CUT_APPEND=<file name>:<step>: that
        // step's line is written in two halves with a window between them in which the test kills
        // the process, as a crash of the machine or a full disk can cut a write short.
        if std::env::var("BWM_FAULT_CUT_APPEND").is_ok_and(|v| v == format!("{name}:{step}")) {
            let half = record.len() / 2;
            self.file.write_all(&record.as_bytes()[..half]).with_context(|| format!("appending to {}", self.path.display()))?;
            eprintln!("append: cut {name} at step {step}");
            std::thread::sleep(std::time::Duration::from_secs(600));
            return self.file.write_all(&record.as_bytes()[half..]).with_context(|| format!("appending to {}", self.path.display()));
        }
        self.file.write_all(record.as_bytes()).with_context(|| format!("appending to {}", self.path.display()))
    }
}

/// The length of the first `len` bytes of `file` up to and with its last newline.
fn whole_lines_len(file: &std::fs::File, len: u64) -> std::io::Result<u64> {
    use std::os::unix::fs::FileExt;
    let mut buf = vec![0u8; 64 * 1024];
    let mut end = len;
    while end > 0 {
        let start = end.saturating_sub(buf.len() as u64);
        let chunk = &mut buf[..(end - start) as usize];
        file.read_exact_at(chunk, start)?;
        if let Some(i) = chunk.iter().rposition(|&b| b == b'\n') {
            return Ok(start + i as u64 + 1);
        }
        end = start;
    }
    Ok(0)
}

/// Lines of a run log that count: whole lines (an unterminated last one may have been cut by a
/// kill mid-write), not blank, with their numbers.
fn whole_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.split_inclusive('\n').enumerate().filter(|(_, l)| l.ends_with('\n') && !l.trim().is_empty()).map(|(i, l)| (i + 1, l.trim_end()))
}

/// Warns about the lines of `path` that were skipped as unreadable (damage no run of this version
/// writes: a cut line that an older one appended to).
fn warn_skipped(path: &Path, skipped: &[usize]) {
    if let Some(first) = skipped.first() {
        eprintln!("warning: {}: skipped {} unreadable line(s), the first line {first}", path.display(), skipped.len());
    }
}

/// (step, loss) of every step of the run in `out_dir`: from `losses.tsv`, else (runs written
/// before it existed) the logged steps of `metrics.jsonl`. A resumed run appends; the last entry
/// of a step wins. An unterminated last line is left out, and so, with a warning, is a line that
/// does not parse: the curve is a report, and a damaged line must not fail a finished run.
pub fn read_run_losses(out_dir: &Path) -> Result<Vec<(u64, f64)>> {
    let path = out_dir.join(LOSSES_FILE);
    if !path.exists() {
        return read_losses(&out_dir.join("metrics.jsonl"));
    }
    let text = std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    let mut by_step = std::collections::BTreeMap::new();
    let mut skipped = Vec::new();
    for (n, line) in whole_lines(&text) {
        let parsed = line.split_once('\t').and_then(|(s, l)| Some((s.parse::<u64>().ok()?, l.trim().parse::<f64>().ok()?)));
        match parsed {
            Some((step, loss)) => drop(by_step.insert(step, loss)),
            None => skipped.push(n),
        }
    }
    warn_skipped(&path, &skipped);
    Ok(by_step.into_iter().collect())
}

/// (step, loss) of every logged step in `metrics.jsonl` (a resumed run appends; the last entry
/// of a step wins).
pub fn read_losses(metrics: &Path) -> Result<Vec<(u64, f64)>> {
    let text = std::fs::read_to_string(metrics).with_context(|| format!("reading {}", metrics.display()))?;
    let mut by_step = std::collections::BTreeMap::new();
    let mut skipped = Vec::new();
    for (n, line) in whole_lines(&text) {
        match serde_json::from_str::<serde_json::Value>(line) {
            Ok(v) => {
                if let (Some(step), Some(loss)) = (v["step"].as_u64(), v["loss"].as_f64()) {
                    by_step.insert(step, loss);
                }
            }
            Err(_) => skipped.push(n),
        }
    }
    warn_skipped(metrics, &skipped);
    Ok(by_step.into_iter().collect())
}

/// Draws the per-step loss and its running mean (window 10% of the run) to an SVG file.
pub fn loss_plot(losses: &[(u64, f64)], title: &str, out: &Path) -> Result<()> {
    ensure!(!losses.is_empty(), "no logged loss to plot");
    let finite: Vec<(u64, f64)> = losses.iter().copied().filter(|(_, l)| l.is_finite()).collect();
    ensure!(!finite.is_empty(), "no finite loss to plot");
    let window = (finite.len() / 10).max(1);
    let smooth: Vec<(u64, f64)> = (0..finite.len())
        .map(|i| {
            let lo = i.saturating_sub(window - 1);
            let s = &finite[lo..=i];
            (finite[i].0, s.iter().map(|(_, l)| l).sum::<f64>() / s.len() as f64)
        })
        .collect();
    let max_step = finite.last().map(|(s, _)| *s).unwrap_or(1).max(1);
    let max_loss = finite.iter().map(|(_, l)| *l).fold(0.0, f64::max) * 1.05;
    let root = SVGBackend::new(out, (900, 500)).into_drawing_area();
    let draw = || -> std::result::Result<(), Box<dyn std::error::Error>> {
        root.fill(&WHITE)?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 22))
            .margin(15)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(0u64..max_step, 0f64..max_loss)?;
        chart.configure_mesh().x_desc("optimizer step").y_desc("weighted flow-matching loss").draw()?;
        chart
            .draw_series(LineSeries::new(finite.iter().copied(), RGBColor(170, 190, 230)))?
            .label("per step")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], RGBColor(170, 190, 230)));
        chart
            .draw_series(LineSeries::new(smooth.iter().copied(), BLUE.stroke_width(2)))?
            .label(format!("mean of last {window}"))
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLUE.stroke_width(2)));
        chart.configure_series_labels().background_style(WHITE.mix(0.8)).border_style(BLACK).draw()?;
        root.present()?;
        Ok(())
    };
    draw().map_err(|e| anyhow::anyhow!("drawing {}: {e}", out.display()))
}

/// What `rollout_video` wrote and how the rollout compares with holding the last given frame.
#[derive(Debug, Clone)]
pub struct RolloutReport {
    pub path: std::path::PathBuf,
    /// Predicted frames scored (those after x0 and the history).
    pub future_frames: usize,
    /// PSNR (dB) of the model's predicted frames against the ground truth.
    pub model_psnr: f64,
    /// PSNR (dB) of the last given frame, held, against the same ground-truth frames.
    pub copy_last_psnr: f64,
}

/// Rolls out the first held-out clip (the first clip when none is held out) and writes an mp4 of
/// ground truth (left) beside the prediction (right), condition frames included, at the cache's
/// fps (a PNG contact sheet when built without video). Scores the predicted frames against the
/// ground truth next to the copy-last-frame baseline on the same frames.
pub fn rollout_video(trainer: &Trainer, vae_path: &Path, out: &Path) -> Result<RolloutReport> {
    let device = trainer.device;
    let vae = WanVae::load_any(vae_path, Kind::Float, device).with_context(|| format!("VAE {}", vae_path.display()))?;
    let clip_index = if trainer.train_clips < trainer.cache.len() { trainer.train_clips } else { 0 };
    let clip = trainer.clip(clip_index)?;
    let steps = trainer.cfg.validation.sample_steps;
    let predicted = rollout_clip(trainer, &clip.latents.unsqueeze(0), &clip.actions.unsqueeze(0), clip_index as u64, steps)?;
    let pred = tch::no_grad(|| vae.decode(&predicted))?.squeeze_dim(0).clamp(-1.0, 1.0);
    let truth = match &clip.frames {
        Some(f) => f.to_kind(Kind::Float) / 127.5 - 1.0,
        None => tch::no_grad(|| vae.decode(&clip.latents.unsqueeze(0)))?.squeeze_dim(0).clamp(-1.0, 1.0),
    };
    let (truth, pred) = (truth.to_device(tch::Device::Cpu), pred.to_device(tch::Device::Cpu));
    let frames = truth.size()[1].min(pred.size()[1]);
    let given = (1 + trainer.cache.index.history_frames as i64).min(frames - 1).max(1);
    let future = frames - given;
    let real = truth.narrow(1, given, future);
    let model_psnr = psnr(&pred.narrow(1, given, future), &real);
    let copy_last_psnr = psnr(&truth.narrow(1, given - 1, 1).expand_as(&real), &real);
    let (truth, pred) = (tensor_to_frames(&truth)?, tensor_to_frames(&pred)?);
    let frames = truth
        .into_iter()
        .zip(pred)
        .map(|(t, p)| frame_strip(&[vec![t, p]]))
        .collect::<Result<Vec<_>>>()?;
    let path = bwm_data::video::write_mp4_or_sheet(out, &frames, trainer.cache.index.fps, 16)?;
    Ok(RolloutReport { path, future_frames: future as usize, model_psnr, copy_last_psnr })
}

/// Lines `(label, points)` on one chart, written as SVG (fidelity curves and the like).
pub fn line_plot(series: &[(String, Vec<(f64, f64)>)], title: &str, x_desc: &str, y_desc: &str, out: &Path) -> Result<()> {
    let points = || series.iter().flat_map(|(_, p)| p.iter().copied()).filter(|(x, y)| x.is_finite() && y.is_finite());
    ensure!(points().next().is_some(), "no finite points to plot");
    let (x_lo, x_hi) = points().fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), (x, _)| (lo.min(x), hi.max(x)));
    let (y_lo, y_hi) = points().fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), (_, y)| (lo.min(y), hi.max(y)));
    let pad = ((y_hi - y_lo) * 0.05).max(1e-3);
    let palette = [BLUE, RED, RGBColor(0, 150, 0), MAGENTA, RGBColor(230, 140, 0), CYAN, BLACK];
    let root = SVGBackend::new(out, (900, 500)).into_drawing_area();
    let draw = || -> std::result::Result<(), Box<dyn std::error::Error>> {
        root.fill(&WHITE)?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 22))
            .margin(15)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(x_lo..x_hi.max(x_lo + 1.0), (y_lo - pad)..(y_hi + pad))?;
        chart.configure_mesh().x_desc(x_desc).y_desc(y_desc).draw()?;
        for (i, (label, pts)) in series.iter().enumerate() {
            let color = palette[i % palette.len()];
            chart
                .draw_series(LineSeries::new(pts.iter().copied().filter(|(x, y)| x.is_finite() && y.is_finite()), color.stroke_width(2)))?
                .label(label.as_str())
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2)));
        }
        chart.configure_series_labels().background_style(WHITE.mix(0.8)).border_style(BLACK).draw()?;
        root.present()?;
        Ok(())
    };
    draw().map_err(|e| anyhow::anyhow!("drawing {}: {e}", out.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_step_loss_is_read_and_a_cut_last_line_is_skipped() {
        let dir = bwm_testdir::TestDir::new("losses");
        std::fs::write(dir.join("metrics.jsonl"), "{\"step\": 2, \"loss\": 9.0}\n").unwrap();
        assert_eq!(read_run_losses(&dir).unwrap(), vec![(2, 9.0)], "metrics.jsonl when losses.tsv is absent");
        // A resumed run appends step 2 again; the kill that ended it cut the last line.
        std::fs::write(dir.join(LOSSES_FILE), "1\t0.5\n2\t0.25\n3\tNaN\n2\t0.3\n4\t0.").unwrap();
        let losses = read_run_losses(&dir).unwrap();
        assert_eq!(losses.iter().map(|(s, _)| *s).collect::<Vec<_>>(), vec![1, 2, 3]);
        assert_eq!((losses[1].1, losses[2].1.is_nan()), (0.3, true));
        // A damaged line (an older version appended to a cut one) is skipped, not a failed run.
        std::fs::write(dir.join(LOSSES_FILE), "1\t0.5\n2\t0.2\t0.25\n3\t0.25\n").unwrap();
        assert_eq!(read_run_losses(&dir).unwrap(), vec![(1, 0.5), (3, 0.25)]);
    }

    #[test]
    fn a_log_reopened_after_a_cut_write_appends_whole_lines() {
        let dir = bwm_testdir::TestDir::new("line-log");
        let path = dir.join(LOSSES_FILE);
        // A kill cut step 4's line after its first byte; the resumed run appends step 5.
        std::fs::write(&path, "1\t0.5\n4").unwrap();
        LineLog::open(&path).unwrap().append("5\t0.3", 5).unwrap();
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "1\t0.5\n5\t0.3\n");
        assert_eq!(read_run_losses(&dir).unwrap(), vec![(1, 0.5), (5, 0.3)]);
        // A fragment with no line before it, and a log longer than one read of its tail.
        std::fs::write(&path, "30").unwrap();
        LineLog::open(&path).unwrap().append("1\t0.5", 1).unwrap();
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "1\t0.5\n");
        let long = format!("1\t0.5\n{}", "x".repeat(200_000));
        std::fs::write(&path, long).unwrap();
        LineLog::open(&path).unwrap().append("2\t0.25", 2).unwrap();
        assert_eq!(read_run_losses(&dir).unwrap(), vec![(1, 0.5), (2, 0.25)]);
        // metrics.jsonl the same; a reader of a log whose writer was killed skips the cut line.
        let metrics = dir.join("metrics.jsonl");
        std::fs::write(&metrics, "{\"step\": 2, \"loss\": 9.0}\n{\"step\": 3, \"lo").unwrap();
        assert_eq!(read_losses(&metrics).unwrap(), vec![(2, 9.0)]);
        LineLog::open(&metrics).unwrap().append("{\"step\": 3, \"loss\": 8.0}", 3).unwrap();
        assert_eq!(read_losses(&metrics).unwrap(), vec![(2, 9.0), (3, 8.0)]);
    }
}
