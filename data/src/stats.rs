//! Per-dimension action statistics in the BWM release's `stat.json` format, and the
//! normalization the model sees: 2*(x-p01)/(p99-p01+1e-8) - 1, clipped to [-1, 1].

use std::path::Path;

use anyhow::{ensure, Context, Result};
use serde::{Deserialize, Serialize};

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
        let d = stats.p01.len();
        ensure!(
            [&stats.min, &stats.max, &stats.p99, &stats.mean, &stats.std].iter().all(|v| v.len() == d),
            "{}: group '{group}' has fields of different lengths",
            path.display()
        );
        Ok(stats)
    }

    pub fn dim(&self) -> usize {
        self.p01.len()
    }

    /// Normalizes one vector; dimensions whose p01..p99 range is empty fall back to min..max.
    pub fn normalize(&self, x: &[f32]) -> Vec<f32> {
        x.iter()
            .enumerate()
            .map(|(i, &v)| {
                let (lo, hi) = if self.p99[i] > self.p01[i] { (self.p01[i], self.p99[i]) } else { (self.min[i], self.max[i]) };
                let n = 2.0 * (v as f64 - lo) / (hi - lo + 1e-8) - 1.0;
                n.clamp(-1.0, 1.0) as f32
            })
            .collect()
    }
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
    }
}
