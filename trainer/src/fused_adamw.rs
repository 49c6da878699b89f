//! AdamW's update of a slice of the flat fp32 state in one CUDA kernel, compiled with NVRTC at
//! first use: it reads the gradient, the moments and the master weights once and writes them
//! once, where the tensor path makes about a dozen element-wise passes over 20 GB buffers per 5B
//! step (tch 0.24 exposes no `_fused_adamw_`). It runs on libtorch's stream (the legacy default
//! stream, see `dist::nccl`), in order with the tensor operations around it.

use std::sync::{Arc, Mutex, OnceLock};

use anyhow::{ensure, Context, Result};
use cudarc::driver::{CudaContext, CudaFunction, LaunchConfig, PushKernelArg};
use tch::{Device, Kind, Tensor};

/// The element-wise operations in the order the tensor path applies them (`optim::AdamW::step`);
/// the scalars are computed in f64 on the host, as the tensor path's are (1 - b2 rounded from an
/// f32 b2 would be off by 1e-5).
const SOURCE: &str = r#"
// fp32 -> bf16, rounding to nearest even (as c10::BFloat16 and __float2bfloat16_rn).
__device__ unsigned short to_bf16(float x) {
  unsigned int u = __float_as_uint(x);
  if ((u & 0x7fffffffu) > 0x7f800000u) return (unsigned short)((u >> 16) | 0x40u);
  return (unsigned short)((u + 0x7fffu + ((u >> 16) & 1u)) >> 16);
}

extern "C" __global__ void adamw_update(const float* g, float* m, float* v, float* w, float* ema,
    float* out_f32, unsigned short* out_bf16, long long n, float grad_scale, float one_minus_b1,
    float b2, float one_minus_b2, float decay, float eps, float sqrt_bc2, float lr_over_bc1,
    float ema_weight) {
  for (long long i = blockIdx.x * (long long)blockDim.x + threadIdx.x; i < n;
       i += (long long)gridDim.x * blockDim.x) {
    float gi = g[i] * grad_scale;
    float mi = m[i] + one_minus_b1 * (gi - m[i]);
    float vi = v[i] * b2 + gi * (gi * one_minus_b2);
    float denom = sqrtf(vi) / sqrt_bc2 + eps;
    float wi = w[i] * decay - mi / denom * lr_over_bc1;
    m[i] = mi;
    v[i] = vi;
    w[i] = wi;
    if (ema) ema[i] = ema[i] + ema_weight * (wi - ema[i]);
    if (out_f32) out_f32[i] = wi;
    if (out_bf16) out_bf16[i] = to_bf16(wi);
  }
}
"#;

/// The hyper-parameters of one update.
#[derive(Clone, Copy, Debug)]
pub struct Update {
    pub grad_scale: f64,
    pub b1: f64,
    pub b2: f64,
    pub lr: f64,
    pub weight_decay: f64,
    pub eps: f64,
    /// Bias corrections 1 - b1^t and 1 - b2^t.
    pub bc1: f64,
    pub bc2: f64,
    /// EMA decay, when an EMA is kept.
    pub ema_decay: Option<f64>,
}

pub struct FusedAdamW {
    ctx: Arc<CudaContext>,
    function: CudaFunction,
}

impl FusedAdamW {
    /// The kernel for `device`, compiled once per device; an error says why it is unavailable
    /// (no NVRTC library on the library path, a CPU device, ...).
    pub fn for_device(device: Device) -> Result<Arc<FusedAdamW>> {
        type Kernels = Mutex<Vec<(usize, Arc<FusedAdamW>)>>;
        static KERNELS: OnceLock<Kernels> = OnceLock::new();
        let Device::Cuda(index) = device else { anyhow::bail!("the fused AdamW kernel runs on CUDA devices only") };
        let mut kernels = KERNELS.get_or_init(Default::default).lock().map_err(|_| anyhow::anyhow!("the fused AdamW cache is poisoned"))?;
        if let Some((_, k)) = kernels.iter().find(|(i, _)| *i == index) {
            return Ok(k.clone());
        }
        crate::dist::ensure_torch_cuda_loaded()?;
        // SAFETY: probing a shared library by name.
        ensure!(unsafe { cudarc::nvrtc::sys::is_culib_present() }, "NVRTC (libnvrtc.so) is not on the library path");
        let ptx = cudarc::nvrtc::compile_ptx(SOURCE).context("compiling the fused AdamW kernel with NVRTC")?;
        let ctx = CudaContext::new(index).context("binding the CUDA context")?;
        let module = ctx.load_module(ptx).context("loading the fused AdamW kernel")?;
        let function = module.load_function("adamw_update").context("the fused AdamW kernel")?;
        let k = Arc::new(FusedAdamW { ctx, function });
        kernels.push((index, k.clone()));
        Ok(k)
    }

    /// Updates `m`, `v`, `w` (and `ema`) in place from the gradient `g`: contiguous f32 tensors
    /// of the same length on this kernel's device. `publish` (f32 or bf16, same length) receives
    /// the updated weights `w` in its dtype, saving a pass over `w` to copy them.
    pub fn update(&self, g: &Tensor, m: &Tensor, v: &Tensor, w: &Tensor, ema: Option<&Tensor>, publish: Option<&Tensor>, u: &Update) -> Result<()> {
        let n = g.numel();
        for t in [g, m, v, w].into_iter().chain(ema) {
            ensure!(t.kind() == Kind::Float && t.is_contiguous() && t.numel() == n && t.device() == g.device(), "fused AdamW: tensors must be contiguous f32 of one length and device");
        }
        if let Some(t) = publish {
            ensure!(
                matches!(t.kind(), Kind::Float | Kind::BFloat16) && t.is_contiguous() && t.numel() == n && t.device() == g.device(),
                "fused AdamW: the published weights must be contiguous f32 or bf16 of the state's length and device"
            );
        }
        if n == 0 {
            return Ok(());
        }
        self.ctx.bind_to_thread()?;
        let ptr = |t: &Tensor| t.data_ptr() as u64;
        let (pg, pm, pv, pw, pe) = (ptr(g), ptr(m), ptr(v), ptr(w), ema.map_or(0, ptr));
        let published = |kind: Kind| publish.filter(|t| t.kind() == kind).map_or(0, ptr);
        let (out_f32, out_bf16) = (published(Kind::Float), published(Kind::BFloat16));
        let n = n as i64;
        let f = |x: f64| x as f32;
        let decay = if u.weight_decay > 0.0 { 1.0 - u.lr * u.weight_decay } else { 1.0 };
        let (scale, one_minus_b1, b2, one_minus_b2, decay, eps) = (f(u.grad_scale), f(1.0 - u.b1), f(u.b2), f(1.0 - u.b2), f(decay), f(u.eps));
        let (sqrt_bc2, lr_over_bc1, ema_weight) = (f(u.bc2.sqrt()), f(u.lr / u.bc1), f(1.0 - u.ema_decay.unwrap_or(1.0)));
        let blocks = (n as u64).div_ceil(256).min(65_535 * 8) as u32;
        let cfg = LaunchConfig { grid_dim: (blocks, 1, 1), block_dim: (256, 1, 1), shared_mem_bytes: 0 };
        let stream = self.ctx.default_stream();
        let mut launch = stream.launch_builder(&self.function);
        launch.arg(&pg).arg(&pm).arg(&pv).arg(&pw).arg(&pe).arg(&out_f32).arg(&out_bf16).arg(&n);
        launch.arg(&scale).arg(&one_minus_b1).arg(&b2).arg(&one_minus_b2).arg(&decay).arg(&eps).arg(&sqrt_bc2).arg(&lr_over_bc1).arg(&ema_weight);
        // SAFETY: the pointers are live contiguous CUDA buffers of n elements of their types (checked above)
        // that outlive the kernel (tch's caching allocator reuses memory in stream order, and the
        // kernel is on libtorch's stream); the arguments match the kernel's signature.
        unsafe { launch.launch(cfg) }.context("launching the fused AdamW kernel")?;
        Ok(())
    }
}
