//! A trace of libtorch's own profiler (Kineto) around a stretch of work: the operators the host
//! ran and, with CUDA, every kernel and copy on the GPU's timeline (CUPTI sees the kernels of
//! every library in the process, NVRTC-compiled ones too), saved as a Chrome trace that
//! chrome://tracing and Perfetto open. tch exposes no profiler, so starting and stopping it is C++
//! (src/profiler.cpp).

use std::ffi::{c_char, CStr, CString};
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::{bail, Context, Result};

extern "C" {
    fn bwm_profiler_last_error() -> *const c_char;
    fn bwm_profiler_start(cuda: bool) -> bool;
    fn bwm_profiler_stop(path: *const c_char) -> bool;
}

/// libtorch has one profiler per process.
static RUNNING: AtomicBool = AtomicBool::new(false);

fn last_error() -> String {
    // SAFETY: the shim returns a pointer to its thread-local error string, valid until the next call.
    unsafe { CStr::from_ptr(bwm_profiler_last_error()) }.to_string_lossy().into_owned()
}

/// A running profiler; [`Profiler::finish`] saves its trace. Dropped unfinished, it stops without
/// saving.
pub struct Profiler {
    running: bool,
}

impl Profiler {
    /// Starts recording the host's operators, and with `cuda` the GPU's kernels, copies and
    /// runtime calls. One profiler runs at a time in a process.
    pub fn start(cuda: bool) -> Result<Self> {
        if RUNNING.swap(true, Ordering::SeqCst) {
            bail!("a profiler is already running in this process");
        }
        // SAFETY: a plain call into the shim; errors come back as false.
        if !unsafe { bwm_profiler_start(cuda) } {
            RUNNING.store(false, Ordering::SeqCst);
            bail!("starting libtorch's profiler: {}", last_error());
        }
        Ok(Self { running: true })
    }

    /// Stops the profiler and writes its Chrome trace (JSON) at `path`.
    pub fn finish(mut self, path: &Path) -> Result<()> {
        let c_path = CString::new(path.as_os_str().as_encoded_bytes()).with_context(|| format!("trace path {}", path.display()))?;
        self.running = false;
        RUNNING.store(false, Ordering::SeqCst);
        // SAFETY: `c_path` is a NUL-terminated string that outlives the call.
        if !unsafe { bwm_profiler_stop(c_path.as_ptr()) } {
            bail!("saving the profiler's trace at {}: {}", path.display(), last_error());
        }
        Ok(())
    }
}

impl Drop for Profiler {
    fn drop(&mut self) {
        if self.running {
            // SAFETY: stops the profiler this value started; nothing is saved.
            unsafe { bwm_profiler_stop(std::ptr::null()) };
            RUNNING.store(false, Ordering::SeqCst);
        }
    }
}

/// Where a trace's GPU time went: the union of its kernels, copies and sets against the span of
/// all its events, and the kernels with the most GPU time.
#[derive(Debug, Clone)]
pub struct GpuSummary {
    /// Microseconds from the first event of the trace to the end of the last.
    pub span_us: f64,
    /// Microseconds in which at least one kernel, copy or set ran on the GPU.
    pub busy_us: f64,
    /// (name, calls, total microseconds), most time first.
    pub kernels: Vec<(String, usize, f64)>,
}

/// Reads a Chrome trace that [`Profiler::finish`] wrote.
pub fn gpu_summary(trace: &Path) -> Result<GpuSummary> {
    let text = std::fs::read_to_string(trace).with_context(|| format!("reading the trace {}", trace.display()))?;
    let json: serde_json::Value = serde_json::from_str(&text).with_context(|| format!("parsing the trace {}", trace.display()))?;
    let events = json["traceEvents"].as_array().with_context(|| format!("{} has no traceEvents", trace.display()))?;
    let (mut first, mut last) = (f64::INFINITY, f64::NEG_INFINITY);
    let mut on_gpu = Vec::new();
    let mut kernels: std::collections::HashMap<&str, (usize, f64)> = Default::default();
    for e in events {
        let (Some(ts), Some(dur)) = (e["ts"].as_f64(), e["dur"].as_f64()) else { continue };
        first = first.min(ts);
        last = last.max(ts + dur);
        let cat = e["cat"].as_str().unwrap_or("");
        if matches!(cat, "kernel" | "gpu_memcpy" | "gpu_memset") {
            on_gpu.push((ts, ts + dur));
            let k = kernels.entry(e["name"].as_str().unwrap_or("?")).or_default();
            k.0 += 1;
            k.1 += dur;
        }
    }
    on_gpu.sort_by(|a, b| a.0.total_cmp(&b.0));
    let (mut busy, mut open) = (0.0, None::<(f64, f64)>);
    for (s, e) in on_gpu {
        open = match open {
            Some((os, oe)) if s <= oe => Some((os, oe.max(e))),
            Some((os, oe)) => {
                busy += oe - os;
                Some((s, e))
            }
            None => Some((s, e)),
        };
    }
    if let Some((os, oe)) = open {
        busy += oe - os;
    }
    let mut kernels: Vec<(String, usize, f64)> = kernels.into_iter().map(|(n, (c, t))| (n.to_string(), c, t)).collect();
    kernels.sort_by(|a, b| b.2.total_cmp(&a.2));
    Ok(GpuSummary { span_us: if last > first { last - first } else { 0.0 }, busy_us: busy, kernels })
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::{Device, Kind, Tensor};

    /// A hand-made trace: GPU time is the union of overlapping kernels and copies, host events
    /// count only towards the span.
    #[test]
    fn gpu_time_is_the_union_of_what_ran_on_the_gpu() {
        let dir = bwm_testdir::TestDir::new("profiler-summary");
        let path = dir.path().join("trace.json");
        let event = |cat: &str, name: &str, ts: f64, dur: f64| serde_json::json!({"ph": "X", "cat": cat, "name": name, "ts": ts, "dur": dur});
        let trace = serde_json::json!({"traceEvents": [
            event("cpu_op", "aten::mm", 0.0, 100.0),
            event("kernel", "gemm", 10.0, 20.0),
            event("kernel", "adamw", 25.0, 10.0),
            event("gpu_memcpy", "Memcpy HtoD", 50.0, 5.0),
            event("kernel", "gemm", 60.0, 20.0),
            {"ph": "i", "name": "instant", "ts": 1.0},
        ]});
        std::fs::write(&path, trace.to_string()).unwrap();
        let s = gpu_summary(&path).unwrap();
        assert_eq!((s.span_us, s.busy_us), (100.0, 25.0 + 5.0 + 20.0));
        assert_eq!(s.kernels[0], ("gemm".to_string(), 2, 40.0));
        assert_eq!(s.kernels.len(), 3);
    }

    /// The trace holds the operators run while the profiler ran, and not those run after it.
    #[test]
    fn the_trace_holds_the_operators_run_between_start_and_finish() {
        let dir = bwm_testdir::TestDir::new("profiler");
        let path = dir.path().join("trace.json");
        let p = Profiler::start(false).unwrap();
        let e = Profiler::start(false).err().expect("a second profiler must be refused");
        assert!(format!("{e:#}").contains("already running"), "{e:#}");
        let a = Tensor::ones([64, 64], (Kind::Float, Device::Cpu));
        let _ = a.matmul(&a);
        p.finish(&path).unwrap();
        let _ = a.cumsum(0, Kind::Float);
        let trace: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
        let names: Vec<&str> = trace["traceEvents"].as_array().unwrap().iter().filter_map(|e| e["name"].as_str()).collect();
        assert!(names.contains(&"aten::matmul"), "aten::matmul is missing from {} events", names.len());
        assert!(!names.contains(&"aten::cumsum"), "an operator run after finish is in the trace");
        // No GPU here: the span is the host's, and nothing ran on a GPU.
        let summary = gpu_summary(&path).unwrap();
        assert!(summary.span_us > 0.0 && summary.busy_us == 0.0 && summary.kernels.is_empty(), "{summary:?}");
        // Dropped without finishing: stopped, and another may start.
        drop(Profiler::start(false).unwrap());
        Profiler::start(false).unwrap().finish(&dir.path().join("again.json")).unwrap();
    }
}
