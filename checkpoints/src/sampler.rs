//! The sampler a model's fidelity was measured at, recorded with its weights: `sampler.json` in a
//! training checkpoint's folder (`step-N/`) or at the root of an export, written by the sampler
//! sweep or by hand (`bwm sampler`), copied by `bwm export`, and used by the world-model commands
//! (rollout, fidelity, evaluate, serve, bench-rollout) when no `--sample-steps` / `--solver` is
//! given. Weights without one are sampled at [`UNRECORDED_STEPS`] Euler steps, the reference's.

use std::path::{Path, PathBuf};

use anyhow::{ensure, Context, Result};
use bwm_model::schedule::Solver;
use serde::{Deserialize, Serialize};

/// The file's name, beside the weights.
pub const SAMPLER_FILE: &str = "sampler.json";

/// Sampler steps for weights that record no sampler: the reference implementation's 50.
pub const UNRECORDED_STEPS: usize = 50;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SamplerRecord {
    /// Sampler steps per generated chunk.
    pub steps: usize,
    pub solver: Solver,
    /// What measured the model's fidelity at this setting (a command, a report, a number).
    pub measured: String,
}

impl SamplerRecord {
    pub fn validate(&self) -> Result<()> {
        ensure!(self.steps > 0, "sampler steps must be positive, got {}", self.steps);
        ensure!(!self.measured.trim().is_empty(), "say what measured the model's fidelity at this sampler (`measured`)");
        Ok(())
    }
}

/// Where the record of weights at `location` (a checkpoint or export folder, or a weights file)
/// lives: in the folder, or beside the file.
pub fn record_path(location: &Path) -> PathBuf {
    if location.is_dir() {
        location.join(SAMPLER_FILE)
    } else {
        location.parent().unwrap_or(Path::new(".")).join(SAMPLER_FILE)
    }
}

/// The record of weights at `location`; None when there is none.
pub fn read(location: &Path) -> Result<Option<SamplerRecord>> {
    let path = record_path(location);
    if !path.is_file() {
        return Ok(None);
    }
    let text = std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    let record: SamplerRecord = serde_json::from_str(&text).with_context(|| format!("{}: not a sampler record", path.display()))?;
    record.validate().with_context(|| path.display().to_string())?;
    Ok(Some(record))
}

/// Writes the record of the weights at `location` (replacing any), whole or not at all.
pub fn write(location: &Path, record: &SamplerRecord) -> Result<PathBuf> {
    record.validate()?;
    let path = record_path(location);
    let tmp = path.with_extension("json.tmp");
    std::fs::write(&tmp, serde_json::to_string_pretty(record)? + "\n").with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, &path).with_context(|| format!("renaming {} to {}", tmp.display(), path.display()))?;
    Ok(path)
}

/// The sampler a rollout uses: the one asked for, else the weights' record, else
/// [`UNRECORDED_STEPS`] Euler steps; with a line saying which and why.
pub fn resolve(asked_steps: Option<usize>, asked_solver: Option<Solver>, recorded: Option<(&SamplerRecord, &Path)>) -> (usize, Solver, String) {
    let steps = asked_steps.or(recorded.map(|(r, _)| r.steps)).unwrap_or(UNRECORDED_STEPS);
    let solver = asked_solver.or(recorded.map(|(r, _)| r.solver)).unwrap_or_default();
    let what = format!("{steps} {} steps", solver.name());
    let line = match (asked_steps.is_some() && asked_solver.is_some(), recorded) {
        (true, _) => format!("sampler: {what} (asked for)"),
        (false, Some((r, path))) => format!("sampler: {what}; recorded with the weights: {} steps {} ({}: {})", r.steps, r.solver.name(), path.display(), r.measured),
        (false, None) => format!(
            "sampler: {what}; these weights record no sampler ({SAMPLER_FILE}), so unset settings take the reference's {UNRECORDED_STEPS} Euler steps (pass --sample-steps, or record the measured setting with `bwm sampler`)"
        ),
    };
    (steps, solver, line)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record(steps: usize) -> SamplerRecord {
        SamplerRecord { steps, solver: Solver::Euler, measured: "the closed-loop study, r 0.95".into() }
    }

    /// Asked-for settings win; else the record's; else 50 Euler steps, and the line says which.
    #[test]
    fn asked_then_recorded_then_fifty() {
        let r = record(4);
        let p = Path::new("ckpt/sampler.json");
        let (s, solver, line) = resolve(None, None, Some((&r, p)));
        assert_eq!((s, solver), (4, Solver::Euler));
        assert!(line.contains("recorded with the weights") && line.contains("r 0.95"), "{line}");
        let (s, solver, line) = resolve(Some(8), None, Some((&r, p)));
        assert_eq!((s, solver), (8, Solver::Euler), "{line}");
        let (s, solver, line) = resolve(Some(2), Some(Solver::DpmPp2M), Some((&r, p)));
        assert_eq!((s, solver), (2, Solver::DpmPp2M));
        assert!(line.contains("asked for"), "{line}");
        let (s, solver, line) = resolve(None, None, None);
        assert_eq!((s, solver), (UNRECORDED_STEPS, Solver::Euler));
        assert!(line.contains("record no sampler") && line.contains("50"), "{line}");
    }

    /// A record round-trips through its folder; a bad one is refused naming the file; none reads
    /// as None.
    #[test]
    fn records_round_trip_and_bad_ones_are_named() {
        let dir = bwm_testdir::tmp_dir("sampler");
        assert_eq!(read(dir.path()).unwrap(), None);
        let path = write(dir.path(), &record(4)).unwrap();
        assert_eq!(path, dir.path().join(SAMPLER_FILE));
        assert_eq!(read(dir.path()).unwrap(), Some(record(4)));
        // A weights file's record is the one beside it.
        assert_eq!(read(&dir.path().join("model.safetensors")).unwrap(), Some(record(4)));
        assert!(write(dir.path(), &record(0)).is_err());
        std::fs::write(&path, r#"{"steps": 4, "solver": "heun", "measured": "x"}"#).unwrap();
        let e = format!("{:#}", read(dir.path()).unwrap_err());
        assert!(e.contains("sampler.json") && e.contains("heun"), "{e}");
    }
}
