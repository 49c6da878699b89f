//! Per-step metrics, the stdout summary line, TensorBoard scalars and the progress bar.

use indicatif::{ProgressBar, ProgressStyle};
use serde::Serialize;
use tch::Device;

use crate::optim::StepReport;

/// Timestep buckets for `loss_by_t/*`: grid indices in tenths of the 1000-step grid (index 0 is
/// the noisiest).
const BUCKET: usize = 100;

#[derive(Debug, Clone, Serialize)]
pub struct StepMetrics {
    pub step: u64,
    /// Mean weighted loss of the step's samples (NaN when non-finite).
    pub loss: f64,
    /// (timestep grid index, loss) of each sample.
    pub samples: Vec<(usize, f64)>,
    pub lr: Option<f64>,
    pub grad_norm: Option<f64>,
    pub clipped: bool,
    pub skipped: bool,
    pub nonfinite_total: u64,
    pub seconds: f64,
    pub samples_per_s: f64,
    pub tokens_per_s: f64,
    pub tflops: f64,
    pub mfu: Option<f64>,
    /// Achieved TFLOP/s over the device's measured dense matmul rate (`log.matmul_tflops`).
    pub matmul_share: Option<f64>,
    /// Device memory in use at the end of the step, MiB (CUDA only).
    pub peak_memory_mib: Option<f64>,
    /// Time the step waited for its batches (the background loader was behind), and its share
    /// of the step time.
    pub loader_wait_s: f64,
    pub loader_wait_share: f64,
    /// Time in collectives during the step (NCCL: GPU time of their kernels, including the part
    /// overlapped with the backward walk; TCP: wall time), and its share of the step time.
    pub collective_s: f64,
    pub collective_share: f64,
}

impl StepMetrics {
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        step: u64,
        losses: &[f64],
        tids: &[usize],
        report: Option<StepReport>,
        seconds: f64,
        tokens: i64,
        model_flops: f64,
        peak_tflops: Option<f64>,
        nonfinite_total: u64,
        device: Device,
    ) -> Self {
        let loss = losses.iter().sum::<f64>() / losses.len().max(1) as f64;
        let tflops = model_flops / seconds / 1e12;
        Self {
            step,
            loss,
            samples: tids.iter().copied().zip(losses.iter().copied()).collect(),
            lr: report.map(|r| r.lr),
            grad_norm: report.map(|r| r.grad_norm),
            clipped: report.map(|r| r.clipped).unwrap_or(false),
            skipped: report.is_none(),
            nonfinite_total,
            seconds,
            samples_per_s: losses.len() as f64 / seconds,
            tokens_per_s: tokens as f64 / seconds,
            tflops,
            mfu: peak_tflops.map(|p| tflops / p),
            matmul_share: None,
            peak_memory_mib: bwm_model::device::memory::used_mib(device),
            loader_wait_s: 0.0,
            loader_wait_share: 0.0,
            collective_s: 0.0,
            collective_share: 0.0,
        }
    }

    /// `rate`: the measured dense matmul TFLOP/s of all devices of the step together.
    pub fn set_matmul_rate(&mut self, rate: f64) {
        self.matmul_share = Some(self.tflops / rate);
    }

    pub fn set_loader_wait(&mut self, seconds: f64) {
        self.loader_wait_s = seconds;
        self.loader_wait_share = if self.seconds > 0.0 { seconds / self.seconds } else { 0.0 };
    }

    pub fn set_collective_time(&mut self, seconds: f64) {
        self.collective_s = seconds;
        self.collective_share = if self.seconds > 0.0 { seconds / self.seconds } else { 0.0 };
    }

    /// (tag, value) pairs for TensorBoard.
    pub fn scalars(&self) -> Vec<(String, f64)> {
        let mut out = vec![
            ("train/loss".to_string(), self.loss),
            ("perf/samples_per_s".to_string(), self.samples_per_s),
            ("perf/tokens_per_s".to_string(), self.tokens_per_s),
            ("perf/tflops".to_string(), self.tflops),
            ("train/nonfinite_total".to_string(), self.nonfinite_total as f64),
            ("perf/loader_wait_s".to_string(), self.loader_wait_s),
            ("perf/loader_wait_share".to_string(), self.loader_wait_share),
            ("perf/collective_s".to_string(), self.collective_s),
            ("perf/collective_share".to_string(), self.collective_share),
        ];
        if let Some(lr) = self.lr {
            out.push(("train/lr".into(), lr));
        }
        if let Some(g) = self.grad_norm {
            out.push(("train/grad_norm".into(), g));
        }
        if let Some(m) = self.mfu {
            out.push(("perf/mfu".into(), m));
        }
        if let Some(m) = self.matmul_share {
            out.push(("perf/matmul_share".into(), m));
        }
        if let Some(m) = self.peak_memory_mib {
            out.push(("perf/memory_mib".into(), m));
        }
        let mut buckets: std::collections::BTreeMap<usize, (f64, usize)> = Default::default();
        for &(t, l) in &self.samples {
            let e = buckets.entry(t / BUCKET).or_default();
            e.0 += l;
            e.1 += 1;
        }
        for (b, (sum, n)) in buckets {
            out.push((format!("loss_by_t/{:03}-{:03}", b * BUCKET, b * BUCKET + BUCKET - 1), sum / n as f64));
        }
        out
    }

    pub fn summary_line(&self, total: u64) -> String {
        let mut s = format!("step {:>6}/{total}  loss {:.5}", self.step, self.loss);
        match (self.lr, self.grad_norm) {
            (Some(lr), Some(g)) => s += &format!("  lr {lr:.2e}  grad_norm {g:.3}{}", if self.clipped { " (clipped)" } else { "" }),
            _ => s += "  update skipped (non-finite)",
        }
        s += &format!("  {:.2} s/step  {:.1} samples/s  {:.0} tokens/s  {:.2} TFLOP/s", self.seconds, self.samples_per_s, self.tokens_per_s, self.tflops);
        if let Some(m) = self.mfu {
            s += &format!("  MFU {:.1}%", 100.0 * m);
        }
        if let Some(m) = self.matmul_share {
            s += &format!("  {:.1}% of the measured matmul rate", 100.0 * m);
        }
        if let Some(m) = self.peak_memory_mib {
            s += &format!("  mem {m:.0} MiB");
        }
        s += &format!("  loader wait {:.3} s ({:.1}%)", self.loader_wait_s, 100.0 * self.loader_wait_share);
        if self.collective_s > 0.0 {
            s += &format!("  collectives {:.3} s ({:.1}%)", self.collective_s, 100.0 * self.collective_share);
        }
        s
    }
}

/// A progress bar with ETA on stderr when it is a terminal; plain lines otherwise.
pub struct Progress {
    bar: Option<ProgressBar>,
}

impl Progress {
    pub fn new(start: u64, total: u64, enabled: bool) -> Self {
        let bar = (enabled && std::io::IsTerminal::is_terminal(&std::io::stderr())).then(|| {
            let bar = ProgressBar::new(total).with_position(start);
            bar.set_style(
                ProgressStyle::with_template("{bar:40} {pos}/{len} steps  {elapsed_precise} elapsed, ETA {eta_precise}  {msg}")
                    .expect("valid template"),
            );
            bar.reset_eta();
            bar
        });
        Self { bar }
    }

    pub fn update(&mut self, step: u64, m: &StepMetrics) {
        if let Some(bar) = &self.bar {
            bar.set_position(step);
            bar.set_message(format!("loss {:.4}", m.loss));
        }
    }

    pub fn println(&self, line: &str) {
        match &self.bar {
            Some(bar) => bar.println(line),
            None => println!("{line}"),
        }
    }

    pub fn finish(&self) {
        if let Some(bar) = &self.bar {
            bar.finish_and_clear();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mfu_and_the_matmul_share_are_reported_side_by_side() {
        // 2 samples of 1e15 model FLOPs each in 5 s: 400 TFLOP/s.
        let mut m = StepMetrics::new(3, &[0.5, 0.7], &[10, 20], None, 5.0, 1000, 2e15, Some(1000.0), 0, Device::Cpu);
        assert!((m.tflops - 400.0).abs() < 1e-9);
        assert_eq!(m.mfu, Some(0.4));
        assert_eq!(m.matmul_share, None, "no matmul rate configured");
        m.set_matmul_rate(800.0);
        assert_eq!(m.matmul_share, Some(0.5));
        let line = m.summary_line(10);
        assert!(line.contains("MFU 40.0%") && line.contains("50.0% of the measured matmul rate"), "{line}");
        let json = serde_json::to_value(&m).unwrap();
        assert_eq!(json["matmul_share"], 0.5);
    }
}
