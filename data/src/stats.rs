//! Per-dimension action statistics in the BWM release's `stat.json` format, and the
//! normalization the model sees: 2*(x-p01)/(p99-p01+1e-8) - 1, clipped to [-1, 1].
//! Also what `bwm stats` computes: a deterministic train/validation split by episode and the
//! statistics of the training episodes.

use std::path::Path;

use anyhow::{bail, ensure, Context, Result};
use serde::{Deserialize, Serialize};

use crate::actions::ActionSpec;
use crate::clips::SkipReport;
use crate::defect::{defect, DefectKind};
use crate::source::{CameraSelection, EpisodeInfo, EpisodeSource};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ActionStats {
    pub shape: Vec<usize>,
    pub min: Vec<f64>,
    pub max: Vec<f64>,
    pub p01: Vec<f64>,
    pub p99: Vec<f64>,
    pub mean: Vec<f64>,
    pub std: Vec<f64>,
}

impl ActionStats {
    /// Reads group `group` (e.g. `state_pose`) of a stat.json file.
    pub fn read(path: &Path, group: &str) -> Result<Self> {
        let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let all: serde_json::Value = serde_json::from_str(&text).with_context(|| format!("{}: not JSON", path.display()))?;
        let entry = all.get(group).with_context(|| {
            let groups: Vec<_> = all.as_object().map(|o| o.keys().cloned().collect()).unwrap_or_default();
            format!("{}: no statistics group '{group}' (groups: {})", path.display(), groups.join(", "))
        })?;
        let stats: Self = serde_json::from_value(entry.clone()).with_context(|| format!("{}: group '{group}'", path.display()))?;
        stats.check().with_context(|| format!("{}: group '{group}'", path.display()))?;
        Ok(stats)
    }

    /// Every per-dimension field holds one value per dimension (statistics read from a file or a
    /// weights' contract are checked so before they normalize anything).
    pub fn check(&self) -> Result<()> {
        let d = self.p01.len();
        ensure!(d > 0, "statistics of no dimensions");
        for (name, v) in [("min", &self.min), ("max", &self.max), ("p99", &self.p99), ("mean", &self.mean), ("std", &self.std)] {
            ensure!(v.len() == d, "'{name}' has {} values, 'p01' {d}", v.len());
        }
        Ok(())
    }

    pub fn dim(&self) -> usize {
        self.p01.len()
    }

    /// Normalizes one vector; dimensions whose p01..p99 range is empty fall back to min..max.
    pub fn normalize(&self, x: &[f32]) -> Vec<f32> {
        x.iter()
            .enumerate()
            .map(|(i, &v)| {
                let (lo, hi) = self.range(i);
                let n = 2.0 * (v as f64 - lo) / (hi - lo + 1e-8) - 1.0;
                n.clamp(-1.0, 1.0) as f32
            })
            .collect()
    }

    /// The inverse of `normalize` for values in [-1, 1] (values clipped there come back as the
    /// range's ends).
    pub fn denormalize(&self, y: &[f32]) -> Vec<f32> {
        y.iter()
            .enumerate()
            .map(|(i, &v)| {
                let (lo, hi) = self.range(i);
                ((f64::from(v) + 1.0) / 2.0 * (hi - lo + 1e-8) + lo) as f32
            })
            .collect()
    }

    fn range(&self, i: usize) -> (f64, f64) {
        if self.p99[i] > self.p01[i] {
            (self.p01[i], self.p99[i])
        } else {
            (self.min[i], self.max[i])
        }
    }
}

impl ActionStats {
    /// Statistics of the rows (all of one width), per dimension, in f64: min, max, the 1st and
    /// 99th percentiles by linear interpolation (numpy's default method), mean, and the
    /// population standard deviation (numpy's default, ddof = 0).
    pub fn compute<'a>(rows: impl IntoIterator<Item = &'a [f32]>) -> Result<Self> {
        let mut columns: Vec<Vec<f64>> = Vec::new();
        for (i, row) in rows.into_iter().enumerate() {
            if i == 0 {
                ensure!(!row.is_empty(), "statistics of zero-width rows");
                columns = vec![Vec::new(); row.len()];
            }
            ensure!(row.len() == columns.len(), "row {i} has {} values, row 0 has {}", row.len(), columns.len());
            for (c, &v) in columns.iter_mut().zip(row) {
                ensure!(v.is_finite(), "row {i} holds a non-finite value");
                c.push(f64::from(v));
            }
        }
        ensure!(!columns.is_empty(), "statistics of no rows");
        let d = columns.len();
        let mut s = Self { shape: vec![d], min: vec![], max: vec![], p01: vec![], p99: vec![], mean: vec![], std: vec![] };
        for mut c in columns {
            c.sort_by(f64::total_cmp);
            let n = c.len() as f64;
            let mean = c.iter().sum::<f64>() / n;
            let var = c.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / n;
            s.min.push(c[0]);
            s.max.push(c[c.len() - 1]);
            s.p01.push(percentile(&c, 1.0));
            s.p99.push(percentile(&c, 99.0));
            s.mean.push(mean);
            s.std.push(var.sqrt());
        }
        Ok(s)
    }
}

/// The `q`-th percentile (0..=100) of sorted values, numpy's `method="linear"` computed the way
/// numpy does: virtual index (n-1)*q/100, then `a + (b-a)*t`, or `b - (b-a)*(1-t)` when t >= 0.5.
pub fn percentile(sorted: &[f64], q: f64) -> f64 {
    let n = sorted.len();
    if n == 0 {
        return f64::NAN;
    }
    let virtual_index = (n - 1) as f64 * (q / 100.0);
    let below = virtual_index.floor();
    if virtual_index >= (n - 1) as f64 {
        return sorted[n - 1];
    }
    if virtual_index <= 0.0 {
        return sorted[0];
    }
    let i = below as usize;
    let (a, b) = (sorted[i], sorted[i + 1]);
    let t = virtual_index - below;
    let diff = b - a;
    if t >= 0.5 {
        b - diff * (1.0 - t)
    } else {
        a + diff * t
    }
}

/// How many episodes go to validation: `{"fraction": 0.1}` (rounded) or `{"count": 2}`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum ValidationSize {
    Fraction(f64),
    Count(usize),
}

/// The train/validation split by episode.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SplitSpec {
    pub seed: u64,
    pub validation: ValidationSize,
}

impl Default for SplitSpec {
    fn default() -> Self {
        Self { seed: 0, validation: ValidationSize::Fraction(0.0) }
    }
}

/// Positions in `EpisodeSource::episodes()`, each list in increasing order.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct EpisodeSplit {
    pub train: Vec<usize>,
    pub validation: Vec<usize>,
}

fn splitmix64(mut x: u64) -> u64 {
    x = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    x = (x ^ (x >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    x ^ (x >> 31)
}

/// Splits by the dataset's episode numbers: each distinct `EpisodeInfo::index` gets a key hashed
/// from (seed, index), the lowest keys go to validation. Entries sharing an episode number stay
/// together, and adding episodes does not move the others between train and validation unless
/// the validation count changes. At least one episode stays in training.
pub fn split_episodes(episodes: &[EpisodeInfo], spec: &SplitSpec) -> Result<EpisodeSplit> {
    let mut ids: Vec<i64> = episodes.iter().map(|e| e.index).collect();
    ids.sort_unstable();
    ids.dedup();
    let n = ids.len();
    ensure!(n > 0, "no episodes to split");
    let count = match spec.validation {
        ValidationSize::Fraction(f) => {
            ensure!(f.is_finite() && (0.0..1.0).contains(&f), "validation fraction {f} must be in [0, 1)");
            (n as f64 * f).round() as usize
        }
        ValidationSize::Count(c) => c,
    };
    ensure!(count < n, "{count} validation episodes leave none of the {n} for training");
    let seed = splitmix64(spec.seed);
    ids.sort_by_key(|&id| (splitmix64(seed ^ splitmix64(id as u64)), id));
    let validation_ids: std::collections::HashSet<i64> = ids[..count].iter().copied().collect();
    let (validation, train) = (0..episodes.len()).partition(|&i| validation_ids.contains(&episodes[i].index));
    Ok(EpisodeSplit { train, validation })
}

/// Statistics groups computed from a set of episodes.
#[derive(Debug, Clone)]
pub struct StatsResult {
    /// (stats group, statistics), in the order of the specs.
    pub groups: Vec<(String, ActionStats)>,
    /// Frames counted (per group).
    pub frames: usize,
    pub report: SkipReport,
}

/// The statistics of each spec's vectors over the episodes at positions `episodes` (the
/// training split). An episode whose vectors fail for any spec, or, when `cameras` is given,
/// whose video does not hold as many frames as it has rows, is skipped and counted, so the
/// statistics cover the episodes training can use.
pub fn compute_stats(
    source: &dyn EpisodeSource,
    episodes: &[usize],
    specs: &[ActionSpec],
    cameras: Option<&CameraSelection>,
) -> Result<StatsResult> {
    ensure!(!specs.is_empty(), "no action specs to compute statistics for");
    for (i, s) in specs.iter().enumerate() {
        s.validate().with_context(|| format!("action spec for group '{}'", s.stats_group))?;
        if specs[..i].iter().any(|o| o.stats_group == s.stats_group) {
            bail!("two action specs write the statistics group '{}'", s.stats_group);
        }
    }
    let infos = source.episodes();
    let mut report = SkipReport { episodes: episodes.len(), ..Default::default() };
    let mut rows: Vec<Vec<Vec<f32>>> = vec![Vec::new(); specs.len()];
    for &e in episodes {
        let Some(info) = infos.get(e) else { bail!("{}: episode position {e} out of range", source.describe()) };
        let got = (|| -> Result<Vec<Vec<Vec<f32>>>> {
            let vectors = specs.iter().map(|s| source.vectors(e, s)).collect::<Result<Vec<_>>>()?;
            if let Some(cameras) = cameras {
                let frames = source.frame_count(e, cameras)?;
                let n = vectors[0].len();
                if frames != n {
                    return defect(DefectKind::CountMismatch, format!("the video holds {frames} frames of the episode, the data {n} rows"));
                }
            }
            Ok(vectors)
        })();
        match got {
            Ok(v) => {
                report.used += 1;
                for (all, ep) in rows.iter_mut().zip(v) {
                    all.extend(ep);
                }
            }
            Err(err) => report.skip(e, info, &err),
        }
    }
    if report.used == 0 {
        let first = report.skipped.first().map(|s| format!("; first: episode {}: {}", s.index, s.reason)).unwrap_or_default();
        bail!("{}: no usable episode for statistics among {}{first}", source.describe(), episodes.len());
    }
    let frames = rows[0].len();
    let groups = specs
        .iter()
        .zip(&rows)
        .map(|(s, r)| {
            let stats = ActionStats::compute(r.iter().map(Vec::as_slice)).with_context(|| format!("statistics group '{}'", s.stats_group))?;
            Ok((s.stats_group.clone(), stats))
        })
        .collect::<Result<Vec<_>>>()?;
    Ok(StatsResult { groups, frames, report })
}

/// Writes statistics groups as a `stat.json` (the release's layout: `{group: {shape, min, max,
/// p01, p99, mean, std}}`, groups in the given order), replacing the file only when complete.
pub fn write_stat_json(path: &Path, groups: &[(String, ActionStats)]) -> Result<()> {
    let mut text = String::from("{\n");
    for (i, (name, stats)) in groups.iter().enumerate() {
        let body = serde_json::to_string_pretty(stats)?;
        let body = body.replace('\n', "\n  ");
        text.push_str(&format!("  {}: {body}{}\n", serde_json::to_string(name)?, if i + 1 < groups.len() { "," } else { "" }));
    }
    text.push_str("}\n");
    let name = path.file_name().with_context(|| format!("{} names no file", path.display()))?;
    let tmp = path.with_file_name(format!(".{}.{}.tmp", name.to_string_lossy(), std::process::id()));
    std::fs::write(&tmp, text).with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("renaming {} to {}", tmp.display(), path.display())).inspect_err(|_| {
        let _ = std::fs::remove_file(&tmp);
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn normalization_maps_percentiles_to_unit_range_and_clips() {
        let s = ActionStats {
            shape: vec![2],
            min: vec![-5.0, 0.0],
            max: vec![5.0, 1.0],
            p01: vec![-1.0, 0.0],
            p99: vec![1.0, 0.0],
            mean: vec![0.0, 0.5],
            std: vec![1.0, 0.5],
        };
        let n = s.normalize(&[1.0, 1.0]);
        assert!((n[0] - 1.0).abs() < 1e-6);
        assert!((n[1] - 1.0).abs() < 1e-6, "empty p01..p99 falls back to min..max");
        assert_eq!(s.normalize(&[-3.0, 0.0]), vec![-1.0, -1.0]);
        let x = [0.25f32, 0.75];
        let back = s.denormalize(&s.normalize(&x));
        assert!(back.iter().zip(&x).all(|(a, b)| (a - b).abs() < 1e-6), "{back:?}");
        s.check().unwrap();
        let short = ActionStats { p99: vec![1.0], ..s };
        assert_eq!(short.check().unwrap_err().to_string(), "'p99' has 1 values, 'p01' 2");
    }

    #[test]
    fn percentiles_interpolate_like_numpy() {
        let v = [1.0, 2.0, 4.0, 8.0];
        // (n-1) * 0.01 = 0.03: 1 + 1 * 0.03; 0.99 -> 2.97: 4 + 4 * 0.97 computed as 8 - 4 * 0.03.
        assert!((percentile(&v, 1.0) - 1.03).abs() < 1e-15);
        assert_eq!(percentile(&v, 99.0), 8.0 - 4.0 * (1.0 - (3.0 * 0.99 - 2.0)));
        assert_eq!(percentile(&v, 0.0), 1.0);
        assert_eq!(percentile(&v, 100.0), 8.0);
        assert_eq!(percentile(&[5.0], 1.0), 5.0);
    }

    #[test]
    fn split_is_deterministic_by_episode_number() {
        let infos: Vec<EpisodeInfo> = (0..20).map(|i| EpisodeInfo { index: 100 + i, length: 10, task: String::new() }).collect();
        let spec = SplitSpec { seed: 7, validation: ValidationSize::Fraction(0.2) };
        let a = split_episodes(&infos, &spec).unwrap();
        assert_eq!(a, split_episodes(&infos, &spec).unwrap());
        assert_eq!((a.train.len(), a.validation.len()), (16, 4));
        let b = split_episodes(&infos, &SplitSpec { seed: 8, ..spec }).unwrap();
        assert_ne!(a.validation, b.validation, "another seed, another split");
        // Appending episodes keeps the earlier validation choices when the count is fixed.
        let more: Vec<EpisodeInfo> = (0..30).map(|i| EpisodeInfo { index: 100 + i, length: 10, task: String::new() }).collect();
        let c4 = SplitSpec { seed: 7, validation: ValidationSize::Count(4) };
        let small = split_episodes(&infos, &c4).unwrap();
        let big = split_episodes(&more, &c4).unwrap();
        assert!(big.validation.iter().all(|v| small.validation.contains(v) || *v >= 20));
        assert!(split_episodes(&infos, &SplitSpec { seed: 0, validation: ValidationSize::Count(20) }).is_err());
        assert!(split_episodes(&infos, &SplitSpec { seed: 0, validation: ValidationSize::Fraction(1.0) }).is_err());
        // Entries sharing an episode number stay on one side.
        let dup: Vec<EpisodeInfo> = [1, 1, 2, 2, 3, 3].iter().map(|&i| EpisodeInfo { index: i, length: 1, task: String::new() }).collect();
        let d = split_episodes(&dup, &SplitSpec { seed: 1, validation: ValidationSize::Count(1) }).unwrap();
        assert_eq!(d.validation.len(), 2);
        assert_eq!(dup[d.validation[0]].index, dup[d.validation[1]].index);
        assert_eq!(
            serde_json::from_str::<SplitSpec>(r#"{"seed": 3, "validation": {"count": 2}}"#).unwrap().validation,
            ValidationSize::Count(2)
        );
    }
}
