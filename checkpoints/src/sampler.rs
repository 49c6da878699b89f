//! The sampler a model's fidelity was measured at, recorded with its weights in their input
//! contract (`contract.json`, see `contract`) in a training checkpoint's folder (`step-N/`) or at
//! the root of an export, written by the sampler sweep or by hand (`bwm sampler`), carried by
//! `bwm export`, and used by the world-model commands
//! (rollout, fidelity, evaluate, serve, bench-rollout) when no `--sample-steps` / `--solver` is
//! given. Weights without one are sampled at [`UNRECORDED_STEPS`] Euler steps, the reference's.

use std::path::{Path, PathBuf};

use anyhow::Result;
use bwm_model::schedule::Solver;

pub use crate::contract::{SamplerRecord, UNRECORDED_STEPS};

/// Where the record of weights at `location` (a checkpoint or export folder, or a weights file)
/// lives: their input contract.
pub fn record_path(location: &Path) -> PathBuf {
    crate::contract::path_of(location)
}

/// The record of weights at `location`; None when there is none.
pub fn read(location: &Path) -> Result<Option<SamplerRecord>> {
    Ok(crate::contract::read(location)?.and_then(|c| c.sampler))
}

/// Records the sampler in the contract of the weights at `location` (replacing any record; a
/// contract that recorded nothing else is made), whole or not at all.
pub fn write(location: &Path, record: &SamplerRecord) -> Result<PathBuf> {
    record.validate()?;
    let mut contract = crate::contract::read(location)?.unwrap_or_else(crate::contract::InputContract::unknown);
    contract.sampler = Some(record.clone());
    crate::contract::write(location, &contract)
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
            "sampler: {what}; these weights record no sampler (in their {}), so unset settings take the reference's {UNRECORDED_STEPS} Euler steps (pass --sample-steps, or record the measured setting with `bwm sampler`)",
            crate::contract::CONTRACT_FILE
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
        let p = Path::new("ckpt/contract.json");
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
        assert_eq!(path, dir.path().join(crate::contract::CONTRACT_FILE));
        assert_eq!(read(dir.path()).unwrap(), Some(record(4)));
        // A weights file's record is the one beside it.
        assert_eq!(read(&dir.path().join("model.safetensors")).unwrap(), Some(record(4)));
        assert!(write(dir.path(), &record(0)).is_err());
        // Recording a sampler keeps what else the contract says.
        let mut contract = crate::contract::InputContract::of_model(4);
        contract.sampler = Some(record(4));
        crate::contract::write(dir.path(), &contract).unwrap();
        write(dir.path(), &record(8)).unwrap();
        let now = crate::contract::read(dir.path()).unwrap().unwrap();
        assert_eq!((now.actions, now.sampler), (contract.actions, Some(record(8))));
        let text = std::fs::read_to_string(&path).unwrap().replace("\"euler\"", "\"heun\"");
        std::fs::write(&path, text).unwrap();
        let e = format!("{:#}", read(dir.path()).unwrap_err());
        assert!(e.contains("contract.json") && e.contains("heun"), "{e}");
    }
}
