//! Parsing of `--device` and `--dtype` flags.

use anyhow::{bail, Result};
use tch::{Device, Kind};

pub fn parse_device(s: &str) -> Result<Device> {
    let device = match s {
        "cpu" => Device::Cpu,
        "cuda" => Device::Cuda(0),
        s if s.starts_with("cuda:") => match s[5..].parse() {
            Ok(i) => Device::Cuda(i),
            Err(_) => bail!("--device {s}: expected cpu, cuda or cuda:N"),
        },
        _ => bail!("--device {s}: expected cpu, cuda or cuda:N"),
    };
    if let Device::Cuda(i) = device {
        let n = tch::Cuda::device_count();
        if (i as i64) >= n {
            bail!("--device {s}: CUDA is not available here ({n} devices visible)");
        }
    }
    Ok(device)
}

pub fn parse_kind(s: &str) -> Result<Kind> {
    match s {
        "f32" | "fp32" | "float32" => Ok(Kind::Float),
        "bf16" | "bfloat16" => Ok(Kind::BFloat16),
        _ => bail!("--dtype {s}: expected f32 or bf16"),
    }
}
