//! The run folder's append-only logs, `losses.tsv` (every optimizer step's loss) and
//! `metrics.jsonl` (the logged steps' metrics): written a whole line at a time, read back for the
//! loss curve (`bwm_metrics::plot::loss_plot`).

use std::path::Path;

use anyhow::{Context, Result};

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
