//! The device the model runs on, for every crate above the model (prepare, inference, trainer):
//! device and dtype names as users write them (`--device`, `run.device`, `--dtype`), waiting for
//! queued work, uploads, and the memory in use (`memory`). Here rather than in the trainer, so that
//! a program embedding the world model does not link the training loop for them.

use anyhow::{bail, Result};
use tch::{Device, Kind, Tensor};

pub mod memory;

/// `auto` (CUDA device 0 when available, else CPU), `cpu`, `cuda` or `cuda:N`, checked against the
/// devices this process sees.
pub fn parse_device(s: &str) -> Result<Device> {
    let device = match device_syntax(s)? {
        None => return Ok(Device::cuda_if_available()),
        Some(d) => d,
    };
    if let Device::Cuda(i) = device {
        let n = tch::Cuda::device_count();
        if (i as i64) >= n {
            bail!("device {s}: CUDA is not available here ({n} devices visible)");
        }
    }
    Ok(device)
}

/// The syntax check alone (a config may name a GPU on a machine without one); `None` for `auto`.
pub fn device_syntax(s: &str) -> Result<Option<Device>> {
    Ok(Some(match s {
        "auto" => return Ok(None),
        "cpu" => Device::Cpu,
        "cuda" => Device::Cuda(0),
        s if s.starts_with("cuda:") => match s[5..].parse() {
            Ok(i) => Device::Cuda(i),
            Err(_) => bail!("device '{s}': expected auto, cpu, cuda or cuda:N"),
        },
        _ => bail!("device '{s}': expected auto, cpu, cuda or cuda:N"),
    }))
}

pub fn parse_kind(s: &str) -> Result<Kind> {
    match s {
        "f32" | "fp32" | "float32" => Ok(Kind::Float),
        "bf16" | "bfloat16" => Ok(Kind::BFloat16),
        _ => bail!("dtype '{s}': expected f32 or bf16"),
    }
}

/// Waits for the work queued on `device` (a no-op on the CPU): what a wall-clock timing of GPU
/// work needs before reading the clock.
pub fn synchronize(device: Device) {
    if let Device::Cuda(i) = device {
        tch::Cuda::synchronize(i as i64);
    }
}

/// `t` on `device`. To a CUDA device through pinned memory without the host waiting: a copy from
/// pageable memory waits for the work queued before it, and the host's work after it then leaves
/// the GPU idle (a 5B step's next batch waited for the previous step's 35 ms update). `_pin_memory`,
/// as `pin_memory` given a device warns on every call that it is deprecated.
pub fn upload(t: &Tensor, device: Device) -> Tensor {
    if device.is_cuda() && t.device() == Device::Cpu {
        t.internal_pin_memory(device).to_device_(device, t.kind(), true, false)
    } else {
        t.to_device(device)
    }
}
