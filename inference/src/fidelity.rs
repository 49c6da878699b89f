//! The fidelity report (`bwm fidelity`): how well the world model simulates held-out episodes. Each episode is rolled
//! out autoregressively from its first frame over its whole length, driven by its own recorded
//! actions, by another episode's and by zero actions (the model's [-1, 1] centre), and scored
//! frame by frame (PSNR, SSIM) against the real frames, next to the copy-last-frame baseline (x0
//! held for the whole episode). The margins over the other and the zero actions are the model's
//! action sensitivity, as training's validation reports it on held-out clips.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{ensure, Context, Result};
use bwm_data::frames::{fit, frame_strip};
use bwm_data::open_dataset;
use bwm_metrics::image::{psnr_frames, ssim_frames};
use image::RgbImage;
use serde_json::{json, Value};
use tch::Tensor;

use crate::rollout::{after_x0, generate_frames_together};
use crate::world_model::{EpisodeFlags, WorldModelOptions};

/// What `run` scores and where it writes the report (the flags of `bwm fidelity`).
#[derive(Clone, Debug)]
pub struct FidelityOptions {
    /// Dataset of held-out episodes (x0, recorded actions and the real frames).
    pub data: PathBuf,
    /// Episode positions to score (default: all); at least two, as each is also driven by
    /// another's actions (the next listed episode of the same task).
    pub episodes: Vec<usize>,
    /// How the dataset's episodes are read (actions, cameras, frame size); unset: as the
    /// weights' input contract says.
    pub reading: EpisodeFlags,
    /// Longest rollout, in frames including x0 (default: the whole episode).
    pub max_frames: Option<usize>,
    /// Horizons (frames after x0) at which mean PSNR/SSIM are reported, besides the full episode.
    pub horizons: Vec<usize>,
    /// Side-by-side videos per task (real | own actions | other actions | zero actions |
    /// copy-last-frame).
    pub videos: usize,
    /// Episodes rolled out at once (both of each one's rollouts), their chunks generated as one
    /// batch; the scores are what each episode gets alone.
    pub in_flight: usize,
    /// Lanes the rollouts in flight are split into, each on a CUDA stream of its own
    /// (`crate::lanes`).
    pub streams: usize,
    /// Output folder: fidelity.json, episodes.jsonl (and episodes.key.json, the settings it was
    /// scored with: a later run with the same ones resumes it), `psnr_<task>.svg`, `ssim_<task>.svg`, videos/.
    pub out: PathBuf,
}

/// The predictors scored, in report order.
const PREDICTORS: [&str; 4] = ["model", "other_actions", "zero_actions", "copy_last_frame"];

/// Per-frame scores of one episode (frame 1 first; x0 is given, not scored).
struct Scored {
    task: String,
    psnr: BTreeMap<&'static str, Vec<f64>>,
    ssim: BTreeMap<&'static str, Vec<f64>>,
}

/// Scores the world model that `options` opens on the held-out episodes `a` names and writes
/// fidelity.json, episodes.jsonl, the per-task curves and side-by-side videos into `a.out`.
pub fn run(options: &WorldModelOptions, a: &FidelityOptions) -> Result<()> {
    ensure!(a.horizons.iter().all(|&h| h > 0), "--horizons must be positive frame counts");
    ensure!(a.in_flight >= 1, "episodes in flight must be at least 1");
    crate::lanes::check(3 * a.in_flight, a.streams)?;
    let options = options.with_stats_beside(Some(&a.data));
    let source = open_dataset(&a.data)?;
    let infos = source.episodes();
    let episodes: Vec<usize> = if a.episodes.is_empty() { (0..infos.len()).collect() } else { a.episodes.clone() };
    ensure!(episodes.len() >= 2, "fidelity needs at least two episodes (each is also driven by another's actions); {} selected", episodes.len());
    for &e in &episodes {
        ensure!(e < infos.len(), "--episodes {e}: the dataset has {} episodes", infos.len());
    }
    let wm = options.load()?;
    let reading = wm.episode_reading(&a.reading, 16)?;
    let (spec, cameras, size) = (&reading.actions, &reading.cameras, reading.size);
    wm.check_frame_size(&format!("frames of {}x{} (--resolution)", size.0, size.1), size.1 as i64, size.0 as i64, 3 * a.in_flight)?;
    let lanes = wm.lanes(a.streams)?;
    println!(
        "fidelity: {} episodes of {}; chunks of {} frames, {} history frames, {} sampler steps, {} episode(s) in flight in {} stream(s)",
        episodes.len(),
        source.describe(),
        wm.spec.future,
        wm.spec.history,
        wm.spec.steps,
        a.in_flight,
        a.streams
    );
    std::fs::create_dir_all(a.out.join("videos")).with_context(|| format!("creating {}", a.out.display()))?;
    // Episodes scored by an earlier run of the same settings into the same folder (one cut short)
    // are kept, not rolled out again.
    let run_key = json!({
        "data": a.data.display().to_string(),
        "model": options.identity(&wm.spec),
        "actions": reading.actions,
        "camera": reading.cameras,
        "resolution": format!("{}x{}", size.0, size.1),
        "resize": format!("{:?}", reading.resize),
        "max_frames": a.max_frames,
        "episodes": episodes,
        "predictors": PREDICTORS,
    });
    let episodes_path = a.out.join("episodes.jsonl");
    let mut done = earlier_episodes(&a.out, &run_key)?;
    if !done.is_empty() {
        println!("fidelity: resuming: {} of {} episodes already scored in {}", done.len(), episodes.len(), episodes_path.display());
    }
    bwm_data::latent_cache::write_atomically(&a.out, RUN_KEY_FILE, serde_json::to_string_pretty(&run_key)?.as_bytes())?;
    let mut episodes_file = std::fs::File::create(&episodes_path).with_context(|| format!("creating {}", episodes_path.display()))?;
    for (line, _) in done.values() {
        writeln!(episodes_file, "{line}").with_context(|| format!("writing {}", episodes_path.display()))?;
    }
    let mut scored = Vec::new();
    let mut videos_per_task: BTreeMap<String, usize> = BTreeMap::new();
    let start = Instant::now();
    // Episodes still to score, in order, rolled out `a.in_flight` at a time.
    let mut todo = Vec::new();
    for (i, &e) in episodes.iter().enumerate() {
        let info = &infos[e];
        if let Some((_, record)) = done.remove(&info.index) {
            let video = video_path(a, &info.task, info.index);
            if video.exists() || video.with_extension("png").exists() {
                *videos_per_task.entry(info.task.clone()).or_default() += 1;
            }
            scored.push(record);
        } else {
            todo.push((i, e));
        }
    }
    for group in todo.chunks(a.in_flight) {
        let t0 = Instant::now();
        let mut inputs = Vec::with_capacity(group.len());
        for &(i, e) in group {
            let info = &infos[e];
            let other = other_episode(&episodes, i, |p| infos[p].task.as_str());
            let length = info.length.min(infos[other].length).min(a.max_frames.unwrap_or(usize::MAX)).max(1);
            ensure!(length >= 2, "episode {} has fewer than two frames to score", info.index);
            let what = |p: usize| format!("episode {} (position {p})", infos[p].index);
            let own = source.vectors(e, spec).with_context(|| what(e))?[..length].to_vec();
            let others = source.vectors(other, spec).with_context(|| what(other))?[..length].to_vec();
            let truth: Vec<RgbImage> =
                source.frames(e, 0..length, cameras).with_context(|| what(e))?.iter().map(|f| fit(f, size.0, size.1, reading.resize)).collect();
            inputs.push((e, other, length, truth, wm.normalize(&own)?, wm.normalize(&others)?));
        }
        // Each episode three times: its own actions, another episode's, zero actions (the model's
        // [-1, 1] centre) after x0's own.
        let jobs: Vec<(&RgbImage, Tensor)> = inputs
            .iter()
            .flat_map(|(_, _, _, truth, own, others)| {
                let zero = Tensor::cat(&[own.narrow(0, 0, 1), own.narrow(0, 1, own.size()[0] - 1).zeros_like()], 0);
                [(&truth[0], own.shallow_clone()), (&truth[0], others.shallow_clone()), (&truth[0], zero)]
            })
            .collect();
        let names: Vec<String> = group.iter().map(|&(_, e)| infos[e].index.to_string()).collect();
        let mut generated = generate_frames_together(&wm, &lanes, &jobs, &mut |chunk: usize, total: usize, made: usize| {
            print!("\r  episode(s) {}: chunk {chunk} ({made}/{total} frames, own, other and zero actions)   ", names.join(", "));
            let _ = std::io::stdout().flush();
        })?
        .into_iter();
        for (e, other, length, truth, _, _) in inputs {
            let info = &infos[e];
            let mut next = || generated.next().context("a rollout is missing");
            let (model, driven_by_other, zero_actions) = (next()?, next()?, next()?);
            let copy_last = vec![truth[0].clone(); length];
            let record = score(&info.task, &truth, [&model, &driven_by_other, &zero_actions, &copy_last], wm.device)?;
            let mean = |m: &BTreeMap<&str, Vec<f64>>, k: &str| m[k].iter().sum::<f64>() / m[k].len() as f64;
            println!(
                "\r  episode {} ({}; other actions from episode {}): {} frames, PSNR model {:.2} / other actions {:.2} / zero actions {:.2} / copy-last {:.2} dB ({:.1} s{})",
                info.index,
                display_task(&info.task),
                infos[other].index,
                length,
                mean(&record.psnr, "model"),
                mean(&record.psnr, "other_actions"),
                mean(&record.psnr, "zero_actions"),
                mean(&record.psnr, "copy_last_frame"),
                t0.elapsed().as_secs_f64(),
                if group.len() > 1 { format!(" for {} episodes together", group.len()) } else { String::new() }
            );
            let line = json!({
                "episode_index": info.index,
                "task": info.task,
                "other_episode_index": infos[other].index,
                "frames": length,
                "psnr": record.psnr,
                "ssim": record.ssim,
            });
            writeln!(episodes_file, "{line}").with_context(|| format!("writing {}", episodes_path.display()))?;
            let shown = videos_per_task.entry(info.task.clone()).or_default();
            if *shown < a.videos {
                *shown += 1;
                let panels: Vec<RgbImage> = (0..length)
                    .map(|k| frame_strip(&[vec![truth[k].clone(), model[k].clone(), driven_by_other[k].clone(), zero_actions[k].clone(), copy_last[k].clone()]]))
                    .collect::<Result<_>>()?;
                let path = video_path(a, &info.task, info.index);
                bwm_data::video::write_mp4_or_sheet(&path, &panels, source.fps(e)?, 8)?;
            }
            scored.push(record);
        }
    }
    let mut by_task: BTreeMap<String, Vec<&Scored>> = BTreeMap::new();
    for s in &scored {
        by_task.entry(s.task.clone()).or_default().push(s);
    }
    let mut tasks = serde_json::Map::new();
    for (task, group) in &by_task {
        let summary = summarize(group, &a.horizons);
        for metric in ["psnr", "ssim"] {
            let series: Vec<(String, Vec<(f64, f64)>)> = PREDICTORS
                .iter()
                .map(|p| {
                    let curve = summary["per_frame"][p][metric].as_array().cloned().unwrap_or_default();
                    (p.replace('_', " "), curve.iter().enumerate().map(|(k, v)| ((k + 1) as f64, v.as_f64().unwrap_or(f64::NAN))).collect())
                })
                .collect();
            let path = a.out.join(format!("{metric}_{}.svg", file_stem(task)));
            let title = format!("{} per frame, {} ({} episodes)", metric.to_uppercase(), display_task(task), group.len());
            bwm_metrics::plot::line_plot(&series, &title, "frames after x0", metric, &path)?;
        }
        tasks.insert(task.clone(), summary);
    }
    let all = summarize(&scored.iter().collect::<Vec<_>>(), &a.horizons);
    let report = json!({
        "data": a.data.display().to_string(),
        "checkpoint": options.checkpoint,
        "episodes": scored.len(),
        "resolution": format!("{}x{}", reading.size.0, reading.size.1),
        "history": wm.spec.history,
        "future": wm.spec.future,
        "sample_steps": wm.spec.steps,
        "solver": wm.spec.solver.to_string(),
        "shift": wm.spec.shift,
        "guidance": wm.spec.guidance,
        "history_sigma": wm.spec.history_sigma,
        "seed": wm.spec.seed,
        "fp8": wm.fp8.map(|s| s.to_string()),
        "tasks": tasks,
        "all": all,
        "seconds": start.elapsed().as_secs_f64(),
    });
    let path = a.out.join("fidelity.json");
    bwm_data::latent_cache::write_atomically(&a.out, "fidelity.json", serde_json::to_string_pretty(&report)?.as_bytes())?;
    println!("{}", render(&report, &a.horizons));
    println!("fidelity: {} ({:.1} s)", path.display(), start.elapsed().as_secs_f64());
    Ok(())
}

/// Where `run` records the settings its episodes.jsonl was scored with.
const RUN_KEY_FILE: &str = "episodes.key.json";

/// The side-by-side video of one episode (a PNG contact sheet beside it in builds without video).
fn video_path(a: &FidelityOptions, task: &str, episode_index: i64) -> PathBuf {
    a.out.join("videos").join(format!("{}_episode_{:06}.mp4", file_stem(task), episode_index))
}

/// The scored lines of an earlier run into `out` with the same settings and their scores, by
/// episode index; none when the settings differ or there was no such run. A line cut short by a
/// kill is dropped.
fn earlier_episodes(out: &std::path::Path, run_key: &Value) -> Result<BTreeMap<i64, (Value, Scored)>> {
    let (key_path, lines_path) = (out.join(RUN_KEY_FILE), out.join("episodes.jsonl"));
    let (Ok(key), Ok(lines)) = (std::fs::read_to_string(&key_path), std::fs::read_to_string(&lines_path)) else {
        return Ok(BTreeMap::new());
    };
    if serde_json::from_str::<Value>(&key).ok().as_ref() != Some(run_key) {
        println!("fidelity: {} was scored with other settings; starting over", lines_path.display());
        return Ok(BTreeMap::new());
    }
    Ok(lines
        .lines()
        .filter_map(|l| serde_json::from_str::<Value>(l).ok())
        .filter_map(|v| {
            let scored = scored_from_line(&v).ok()?;
            Some((v["episode_index"].as_i64()?, (v, scored)))
        })
        .collect())
}

/// The per-frame scores of one episodes.jsonl line.
fn scored_from_line(line: &Value) -> Result<Scored> {
    let task = line["task"].as_str().context("no task")?.to_string();
    let mut out = Scored { task, psnr: BTreeMap::new(), ssim: BTreeMap::new() };
    for p in PREDICTORS {
        for (metric, map) in [("psnr", &mut out.psnr), ("ssim", &mut out.ssim)] {
            let values = line[metric][p].as_array().with_context(|| format!("no {metric} of {p}"))?;
            let values: Option<Vec<f64>> = values.iter().map(Value::as_f64).collect();
            map.insert(p, values.with_context(|| format!("{metric} of {p} is not a list of numbers"))?);
        }
    }
    ensure!(!out.psnr["model"].is_empty(), "no scored frame");
    Ok(out)
}

/// The episode whose actions drive the counterfactual rollout of `episodes[i]`: the next listed
/// one of the same task, else the next listed one.
fn other_episode<'a>(episodes: &[usize], i: usize, task: impl Fn(usize) -> &'a str) -> usize {
    let n = episodes.len();
    let after = (1..n).map(|d| episodes[(i + d) % n]);
    after.clone().find(|&p| task(p) == task(episodes[i])).unwrap_or_else(|| episodes[(i + 1) % n])
}

/// Each predictor's PSNR and SSIM per frame after x0, computed on `device`.
fn score(task: &str, truth: &[RgbImage], predicted: [&Vec<RgbImage>; 4], device: tch::Device) -> Result<Scored> {
    ensure!(truth.len() >= 2, "{} frames: none after x0 to score", truth.len());
    let real = after_x0(truth, device)?;
    let mut out = Scored { task: task.to_string(), psnr: BTreeMap::new(), ssim: BTreeMap::new() };
    for (name, frames) in PREDICTORS.iter().zip(predicted) {
        ensure!(frames.len() == truth.len(), "{name}: {} frames for {} real ones", frames.len(), truth.len());
        let pred = after_x0(frames, device)?;
        out.psnr.insert(name, psnr_frames(&pred, &real)?);
        out.ssim.insert(name, ssim_frames(&pred, &real)?);
    }
    Ok(out)
}

/// Per-frame mean curves and horizon means (frames 1..=h of each episode that long, then the mean
/// over those episodes), with the model's margins over the two baselines.
fn summarize(group: &[&Scored], horizons: &[usize]) -> Value {
    let longest = group.iter().map(|s| s.psnr["model"].len()).max().unwrap_or(0);
    let mut per_frame = serde_json::Map::new();
    for p in PREDICTORS {
        let curve = |m: fn(&Scored) -> &BTreeMap<&'static str, Vec<f64>>| -> Vec<f64> {
            (0..longest)
                .map(|k| {
                    let v: Vec<f64> = group.iter().filter_map(|s| m(s)[p].get(k).copied()).collect();
                    v.iter().sum::<f64>() / v.len() as f64
                })
                .collect()
        };
        per_frame.insert(p.into(), json!({ "psnr": curve(|s| &s.psnr), "ssim": curve(|s| &s.ssim) }));
    }
    let mut at = serde_json::Map::new();
    let mut margins = serde_json::Map::new();
    let mut keys: Vec<(String, Option<usize>)> = horizons.iter().map(|&h| (h.to_string(), Some(h))).collect();
    keys.push(("full".into(), None));
    for (key, h) in keys {
        let episodes: Vec<&&Scored> = group.iter().filter(|s| h.is_none_or(|h| s.psnr["model"].len() >= h)).collect();
        if episodes.is_empty() {
            continue;
        }
        let mean_of = |m: fn(&Scored) -> &BTreeMap<&'static str, Vec<f64>>, p: &str| -> f64 {
            let per_episode: Vec<f64> = episodes
                .iter()
                .map(|s| {
                    let v = &m(s)[p];
                    let v = &v[..h.unwrap_or(v.len()).min(v.len())];
                    v.iter().sum::<f64>() / v.len() as f64
                })
                .collect();
            per_episode.iter().sum::<f64>() / per_episode.len() as f64
        };
        let mut row = serde_json::Map::new();
        for p in PREDICTORS {
            row.insert(p.into(), json!({ "psnr": mean_of(|s| &s.psnr, p), "ssim": mean_of(|s| &s.ssim, p) }));
        }
        row.insert("episodes".into(), json!(episodes.len()));
        let model = mean_of(|s| &s.psnr, "model");
        margins.insert(
            key.clone(),
            json!({
                "psnr_over_copy_last_frame_db": model - mean_of(|s| &s.psnr, "copy_last_frame"),
                "psnr_over_other_actions_db": model - mean_of(|s| &s.psnr, "other_actions"),
                "psnr_over_zero_actions_db": model - mean_of(|s| &s.psnr, "zero_actions"),
            }),
        );
        at.insert(key, Value::Object(row));
    }
    json!({ "episodes": group.len(), "horizons": at, "margins": margins, "per_frame": per_frame })
}

fn render(report: &Value, horizons: &[usize]) -> String {
    let mut out = String::from("fidelity: mean PSNR dB (SSIM) over frames 1..h; model = own actions\n");
    let mut keys: Vec<String> = horizons.iter().map(usize::to_string).collect();
    keys.push("full".into());
    let mut sections: Vec<(String, &Value)> = report["tasks"].as_object().map(|m| m.iter().map(|(k, v)| (display_task(k), v)).collect()).unwrap_or_default();
    sections.push(("all tasks".into(), &report["all"]));
    for (name, v) in sections {
        out += &format!(
            "  {name} ({} episodes)\n    {:>6} {:>16} {:>16} {:>16} {:>16} {:>10} {:>10} {:>10}\n",
            v["episodes"], "h", "model", "other actions", "zero actions", "copy-last", "vs copy", "vs other", "vs zero"
        );
        for k in &keys {
            let row = &v["horizons"][k];
            if row.is_null() {
                continue;
            }
            let cell = |p: &str| format!("{:.2} ({:.3})", row[p]["psnr"].as_f64().unwrap_or(f64::NAN), row[p]["ssim"].as_f64().unwrap_or(f64::NAN));
            let m = &v["margins"][k];
            out += &format!(
                "    {k:>6} {:>16} {:>16} {:>16} {:>16} {:>+10.2} {:>+10.2} {:>+10.2}\n",
                cell("model"),
                cell("other_actions"),
                cell("zero_actions"),
                cell("copy_last_frame"),
                m["psnr_over_copy_last_frame_db"].as_f64().unwrap_or(f64::NAN),
                m["psnr_over_other_actions_db"].as_f64().unwrap_or(f64::NAN),
                m["psnr_over_zero_actions_db"].as_f64().unwrap_or(f64::NAN)
            );
        }
    }
    out
}

fn display_task(task: &str) -> String {
    if task.is_empty() {
        "(no task)".into()
    } else {
        task.to_string()
    }
}

/// A task name as a file-name part.
fn file_stem(task: &str) -> String {
    let s: String = task.chars().map(|c| if c.is_ascii_alphanumeric() || c == '-' || c == '_' { c } else { '_' }).collect();
    if s.is_empty() {
        "all".into()
    } else {
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn other_episode_prefers_the_same_task() {
        let tasks = ["a", "b", "a", "b"];
        let eps = [0, 1, 2, 3];
        assert_eq!(other_episode(&eps, 0, |p| tasks[p]), 2);
        assert_eq!(other_episode(&eps, 2, |p| tasks[p]), 0);
        assert_eq!(other_episode(&eps, 3, |p| tasks[p]), 1);
        let single = ["a", "b"];
        assert_eq!(other_episode(&[0, 1], 0, |p| single[p]), 1);
    }

    #[test]
    fn summary_means_horizons_over_long_enough_episodes() {
        let mk = |task: &str, model: Vec<f64>| {
            let n = model.len();
            let m: BTreeMap<&'static str, Vec<f64>> =
                [("model", model), ("other_actions", vec![10.0; n]), ("zero_actions", vec![12.0; n]), ("copy_last_frame", vec![5.0; n])].into_iter().collect();
            Scored { task: task.into(), psnr: m.clone(), ssim: m }
        };
        let (a, b) = (mk("t", vec![30.0, 20.0, 10.0, 0.0]), mk("t", vec![20.0, 20.0]));
        let s = summarize(&[&a, &b], &[2, 4]);
        assert_eq!(s["horizons"]["2"]["model"]["psnr"], json!(22.5));
        assert_eq!(s["horizons"]["4"]["episodes"], json!(1));
        assert_eq!(s["horizons"]["4"]["model"]["psnr"], json!(15.0));
        assert_eq!(s["margins"]["2"]["psnr_over_copy_last_frame_db"], json!(17.5));
        assert_eq!(s["margins"]["2"]["psnr_over_zero_actions_db"], json!(10.5));
        assert_eq!(s["per_frame"]["model"]["psnr"], json!([25.0, 20.0, 10.0, 0.0]));
    }
}
