//! Which of libtorch's scaled-dot-product-attention kernels may run: libtorch's own choice
//! (`auto`) or one kernel family forced, process-wide, as `torch.nn.attention.sdpa_kernel` does in
//! Python. Every attention of the DiT and the VAE goes through `scaled_dot_product_attention`, so
//! this picks the kernel of all of them; the math path stays enabled under a forced family for the
//! attentions it cannot take (the VAE's single head of 384 or 1024 channels is wider than the
//! flash and cuDNN kernels go), so forcing one never leaves an attention without a kernel.

use std::sync::OnceLock;

use anyhow::{bail, Result};
use tch::Tensor;

extern "C" {
    fn bwm_sdp_set(flash: bool, efficient: bool, cudnn: bool, math: bool);
    fn bwm_sdp_get(flash: *mut bool, efficient: *mut bool, cudnn: *mut bool, math: *mut bool);
}

/// A kernel family of `scaled_dot_product_attention`, or libtorch's own choice among them.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum SdpBackend {
    /// libtorch's choice among the kernels enabled when the process started (on Hopper with bf16
    /// inputs libtorch 2.11 picks cuDNN, measured the fastest there: docs/performance.md).
    #[default]
    Auto,
    Flash,
    /// The memory-efficient (xFormers/CUTLASS) kernel.
    Efficient,
    Cudnn,
    /// The unfused reference path (every device).
    Math,
}

impl SdpBackend {
    pub const NAMES: [&'static str; 5] = ["auto", "flash", "efficient", "cudnn", "math"];

    pub fn name(self) -> &'static str {
        Self::NAMES[self as usize]
    }
}

impl std::str::FromStr for SdpBackend {
    type Err = anyhow::Error;

    fn from_str(s: &str) -> Result<Self> {
        Ok(match s {
            "auto" => Self::Auto,
            "flash" => Self::Flash,
            "efficient" => Self::Efficient,
            "cudnn" => Self::Cudnn,
            "math" => Self::Math,
            other => bail!("unknown attention backend '{other}' (one of {})", Self::NAMES.join(", ")),
        })
    }
}

impl std::fmt::Display for SdpBackend {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// (flash, efficient, cudnn, math)
type Enabled = (bool, bool, bool, bool);

fn enabled() -> Enabled {
    let (mut flash, mut efficient, mut cudnn, mut math) = (false, false, false, false);
    // SAFETY: the shim writes four bools through the pointers it is given and nothing else.
    unsafe { bwm_sdp_get(&mut flash, &mut efficient, &mut cudnn, &mut math) };
    (flash, efficient, cudnn, math)
}

/// libtorch's switches as they were before this module first changed them.
fn defaults() -> Enabled {
    static DEFAULTS: OnceLock<Enabled> = OnceLock::new();
    *DEFAULTS.get_or_init(enabled)
}

/// Lets only `backend`'s kernels (and the math path, for what they cannot take) run from now on,
/// in the whole process (`Auto`: libtorch's defaults). [`kernel_for`] tells which one a given
/// attention gets.
pub fn set_backend(backend: SdpBackend) {
    let (flash, efficient, cudnn, math) = match backend {
        SdpBackend::Auto => defaults(),
        other => {
            defaults();
            (other == SdpBackend::Flash, other == SdpBackend::Efficient, other == SdpBackend::Cudnn, true)
        }
    };
    // SAFETY: sets four flags of libtorch's global context; no pointers cross.
    unsafe { bwm_sdp_set(flash, efficient, cudnn, math) };
}

/// The backend set now: `Auto` when libtorch's defaults are in force, else the one fused kernel
/// family enabled (`Math` when none is).
pub fn backend() -> SdpBackend {
    match enabled() {
        e if e == defaults() => SdpBackend::Auto,
        (true, false, false, true) => SdpBackend::Flash,
        (false, true, false, true) => SdpBackend::Efficient,
        (false, false, true, true) => SdpBackend::Cudnn,
        (false, false, false, true) => SdpBackend::Math,
        _ => SdpBackend::Auto,
    }
}

/// The kernel `scaled_dot_product_attention` runs for inputs like these ([batch, heads, tokens,
/// head dim], no mask, no dropout) under the switches set now; an error when none can.
pub fn kernel_for(q: &Tensor, k: &Tensor, v: &Tensor) -> Result<&'static str> {
    let none = || {
        format!(
            "no attention kernel enabled under backend '{}' takes inputs {:?} {:?} on {:?}",
            backend(),
            q.size(),
            q.kind(),
            q.device()
        )
    };
    // libtorch's message carries a C++ backtrace after its first line.
    let choice = Tensor::f_internal_fused_sdp_choice(q, k, v, None::<Tensor>, 0.0, false, None, false)
        .map_err(|e| anyhow::anyhow!("{}: {}", none(), e.to_string().lines().next().unwrap_or_default()))?;
    Ok(match choice {
        0 => "math",
        1 => "flash",
        2 => "efficient",
        3 => "cudnn",
        4 => "overrideable",
        _ => bail!(none()),
    })
}

/// [`kernel_for`] of a self-attention over `tokens` tokens of `heads` heads of `head_dim` in
/// `kind` on `device` (the shapes a model's attention sees; no data is read).
pub fn kernel_for_shape(heads: i64, head_dim: i64, tokens: i64, kind: tch::Kind, device: tch::Device) -> Result<&'static str> {
    let q = Tensor::empty([1, heads, tokens, head_dim], (kind, device));
    kernel_for(&q, &q, &q)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Mutex;

    // The switches are process-wide: tests that set them take turns.
    static SWITCHES: Mutex<()> = Mutex::new(());

    fn qkv() -> (Tensor, Tensor, Tensor) {
        tch::manual_seed(0);
        let opts = (tch::Kind::Float, tch::Device::Cpu);
        (Tensor::randn([1, 2, 7, 16], opts), Tensor::randn([1, 2, 9, 16], opts), Tensor::randn([1, 2, 9, 16], opts))
    }

    fn attend(q: &Tensor, k: &Tensor, v: &Tensor) -> Tensor {
        Tensor::scaled_dot_product_attention(q, k, v, None::<Tensor>, 0.0, false, None, false)
    }

    #[test]
    fn names_round_trip_and_unknown_names_are_refused() {
        for name in SdpBackend::NAMES {
            assert_eq!(name.parse::<SdpBackend>().unwrap().to_string(), name);
        }
        let err = "flash3".parse::<SdpBackend>().unwrap_err().to_string();
        assert!(err.contains("flash3") && err.contains("cudnn"), "{err}");
    }

    #[test]
    fn forcing_a_kernel_changes_what_runs_and_auto_restores_the_defaults() {
        let _turn = SWITCHES.lock().unwrap_or_else(|p| p.into_inner());
        let (q, k, v) = qkv();
        set_backend(SdpBackend::Auto);
        assert_eq!(backend(), SdpBackend::Auto);
        let auto_kernel = kernel_for(&q, &k, &v).unwrap();
        let auto_out = attend(&q, &k, &v);

        set_backend(SdpBackend::Math);
        assert_eq!(backend(), SdpBackend::Math);
        assert_eq!(kernel_for(&q, &k, &v).unwrap(), "math");
        let math_out = attend(&q, &k, &v);
        assert!((&auto_out - &math_out).abs().max().double_value(&[]) < 1e-5);

        // cuDNN has no CPU kernel: the math path takes its attentions.
        set_backend(SdpBackend::Cudnn);
        assert_eq!(backend(), SdpBackend::Cudnn);
        assert_eq!(kernel_for(&q, &k, &v).unwrap(), "math");
        assert!((&attend(&q, &k, &v) - &math_out).abs().max().double_value(&[]) < 1e-6);

        set_backend(SdpBackend::Auto);
        assert_eq!(backend(), SdpBackend::Auto);
        assert_eq!(kernel_for(&q, &k, &v).unwrap(), auto_kernel);
    }
}
