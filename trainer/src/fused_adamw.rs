//! AdamW's update of a slice of the flat fp32 state in one CUDA kernel, compiled with NVRTC at
//! first use: it reads the gradient, the moments and the master weights once and writes them
//! once, where the tensor path makes about a dozen element-wise passes over 20 GB buffers per 5B
//! step (tch 0.24 exposes no `_fused_adamw_`). The gradient is either the flat fp32 accumulator
//! or, when a step has one micro-step on one rank, the model's own bf16 gradient tensors, read
//! where autograd left them ([`GradTable`]): that skips the accumulator's copy, its norm pass in
//! fp32 and its zeroing. The kernels run on libtorch's stream (the legacy default stream, see
//! `dist::nccl`), in order with the tensor operations around them.

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

__device__ float from_bf16(unsigned short h) { return __uint_as_float(((unsigned int)h) << 16); }

#define HYPER float grad_scale, float one_minus_b1, float b2, float one_minus_b2, float decay, \
    float eps, float sqrt_bc2, float lr_over_bc1, float ema_weight
#define STATE float* m, float* v, float* w, float* ema, float* out_f32, unsigned short* out_bf16

// One element's update from its (unscaled) gradient g: m and v in place, the new weight returned.
__device__ __forceinline__ float adamw_math(float g, float& m, float& v, float w, HYPER) {
  float gi = g * grad_scale;
  m = m + one_minus_b1 * (gi - m);
  v = v * b2 + gi * (gi * one_minus_b2);
  float denom = sqrtf(v) / sqrt_bc2 + eps;
  return w * decay - m / denom * lr_over_bc1;
}

#define HYPER_ARGS grad_scale, one_minus_b1, b2, one_minus_b2, decay, eps, sqrt_bc2, lr_over_bc1, ema_weight

// Element i of the state, from its (unscaled) gradient g.
__device__ __forceinline__ void adamw_one(long long i, float g, STATE, HYPER) {
  float mi = m[i], vi = v[i];
  float wi = adamw_math(g, mi, vi, w[i], HYPER_ARGS);
  m[i] = mi;
  v[i] = vi;
  w[i] = wi;
  if (ema) ema[i] = ema[i] + ema_weight * (wi - ema[i]);
  if (out_f32) out_f32[i] = wi;
  if (out_bf16) out_bf16[i] = to_bf16(wi);
}

// Elements i..i+3 (i a multiple of 4, so every pointer is aligned for vector loads) from four
// bf16 gradients packed in g: the memory traffic of `adamw_one` in 16-byte accesses.
__device__ __forceinline__ void adamw_four(long long i, uint2 g, STATE, HYPER) {
  float gs[4] = {__uint_as_float(g.x << 16), __uint_as_float(g.x & 0xffff0000u),
                 __uint_as_float(g.y << 16), __uint_as_float(g.y & 0xffff0000u)};
  float4 m4 = *(const float4*)(m + i), v4 = *(const float4*)(v + i), w4 = *(const float4*)(w + i);
  float ms[4] = {m4.x, m4.y, m4.z, m4.w}, vs[4] = {v4.x, v4.y, v4.z, v4.w}, ws[4] = {w4.x, w4.y, w4.z, w4.w};
  for (int h = 0; h < 4; h++) ws[h] = adamw_math(gs[h], ms[h], vs[h], ws[h], HYPER_ARGS);
  *(float4*)(m + i) = make_float4(ms[0], ms[1], ms[2], ms[3]);
  *(float4*)(v + i) = make_float4(vs[0], vs[1], vs[2], vs[3]);
  float4 wn = make_float4(ws[0], ws[1], ws[2], ws[3]);
  *(float4*)(w + i) = wn;
  if (ema) {
    float4 e = *(const float4*)(ema + i);
    *(float4*)(ema + i) = make_float4(e.x + ema_weight * (ws[0] - e.x), e.y + ema_weight * (ws[1] - e.y),
                                      e.z + ema_weight * (ws[2] - e.z), e.w + ema_weight * (ws[3] - e.w));
  }
  if (out_f32) *(float4*)(out_f32 + i) = wn;
  if (out_bf16) {
    uint2 o;
    o.x = (unsigned int)to_bf16(ws[0]) | ((unsigned int)to_bf16(ws[1]) << 16);
    o.y = (unsigned int)to_bf16(ws[2]) | ((unsigned int)to_bf16(ws[3]) << 16);
    *(uint2*)(out_bf16 + i) = o;
  }
}

extern "C" __global__ void adamw_update(const float* g, STATE, long long n, HYPER) {
  for (long long i = blockIdx.x * (long long)blockDim.x + threadIdx.x; i < n;
       i += (long long)gridDim.x * blockDim.x) {
    adamw_one(i, g[i], m, v, w, ema, out_f32, out_bf16, HYPER_ARGS);
  }
}

// One block per item (tensor, first element, count) of the gradient table: grads[tensor] is a
// contiguous bf16 gradient, offsets[tensor] the flat state's index of its first element.
extern "C" __global__ void adamw_update_bf16_tensors(const unsigned long long* grads,
    const long long* items, const long long* offsets, STATE, HYPER) {
  const long long* item = items + 3 * (long long)blockIdx.x;
  const unsigned short* g = (const unsigned short*)grads[item[0]] + item[1];
  long long first = offsets[item[0]] + item[1], n = item[2], done = 0;
  if ((first & 3) == 0 && ((unsigned long long)g & 7) == 0) {
    done = n / 4 * 4;
    for (long long q = threadIdx.x; q < n / 4; q += blockDim.x) {
      adamw_four(first + 4 * q, ((const uint2*)g)[q], m, v, w, ema, out_f32, out_bf16, HYPER_ARGS);
    }
  }
  for (long long j = done + threadIdx.x; j < n; j += blockDim.x) {
    adamw_one(first + j, from_bf16(g[j]), m, v, w, ema, out_f32, out_bf16, HYPER_ARGS);
  }
}

// partial[item] = the sum of the item's squared gradients, in f64, summed in a fixed order (the
// same gradients give the same sum on every run); 16-byte loads where the item is aligned.
extern "C" __global__ void sum_squares_bf16_tensors(const unsigned long long* grads,
    const long long* items, double* partial) {
  __shared__ double part[256];
  const long long* item = items + 3 * (long long)blockIdx.x;
  const unsigned short* g = (const unsigned short*)grads[item[0]] + item[1];
  long long n = item[2], done = 0;
  double acc = 0.0;
  if (((unsigned long long)g & 15) == 0) {
    done = n / 8 * 8;
    for (long long q = threadIdx.x; q < n / 8; q += blockDim.x) {
      uint4 p = ((const uint4*)g)[q];
      unsigned int words[4] = {p.x, p.y, p.z, p.w};
      for (int h = 0; h < 4; h++) {
        double lo = __uint_as_float(words[h] << 16), hi = __uint_as_float(words[h] & 0xffff0000u);
        acc += lo * lo + hi * hi;
      }
    }
  }
  for (long long j = done + threadIdx.x; j < n; j += blockDim.x) {
    double x = from_bf16(g[j]);
    acc += x * x;
  }
  part[threadIdx.x] = acc;
  __syncthreads();
  for (int k = 128; k > 0; k >>= 1) {
    if (threadIdx.x < k) part[threadIdx.x] += part[threadIdx.x + k];
    __syncthreads();
  }
  if (threadIdx.x == 0) partial[blockIdx.x] = part[0];
}
"#;

/// Threads per block of every kernel (`sum_squares_bf16_tensors` reduces over exactly this many).
const THREADS: u32 = 256;
/// Elements per item of a [`GradTable`]: 256 per thread.
const ITEM: i64 = 1 << 16;

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
    update: CudaFunction,
    update_tensors: CudaFunction,
    sum_squares: CudaFunction,
}

/// Where each trained tensor's gradient lies, for the kernels that read the model's bf16
/// gradients in place: the tensors cut into items of at most `ITEM` elements (one CUDA block
/// each), built once per layout; the gradients' addresses are given per step.
pub struct GradTable {
    /// (tensor, first element, count) triples, on the device.
    items: Tensor,
    /// Each tensor's first element in the flat state, on the device.
    offsets: Tensor,
    numels: Vec<i64>,
    count: u32,
    /// One past the last element of the flat state the table reaches.
    end: i64,
}

/// A step's gradients of a [`GradTable`]'s tensors and the table of their addresses the kernels
/// read (`GradTable::gradients`); holding the gradients keeps the addresses valid.
pub struct TableGradients {
    addresses: Tensor,
    grads: Vec<Tensor>,
}

impl GradTable {
    /// The table of tensors of `numels` elements starting at `offsets` in the flat state.
    pub fn new(offsets: &[i64], numels: &[i64], device: Device) -> Result<Self> {
        ensure!(offsets.len() == numels.len(), "gradient table: {} offsets for {} tensors", offsets.len(), numels.len());
        let mut items = Vec::new();
        for (k, &n) in numels.iter().enumerate() {
            for start in (0..n).step_by(ITEM as usize) {
                items.extend([k as i64, start, ITEM.min(n - start)]);
            }
        }
        let count = u32::try_from(items.len() / 3).context("gradient table: too many items for one launch")?;
        Ok(Self {
            items: Tensor::from_slice(&items).to_device(device),
            offsets: Tensor::from_slice(offsets).to_device(device),
            numels: numels.to_vec(),
            count,
            end: offsets.iter().zip(numels).map(|(o, n)| o + n).max().unwrap_or(0),
        })
    }

    /// `grads` (one per tensor of the table: contiguous bf16 of its length) with their addresses
    /// on the device, made once per step for both kernels that read them.
    pub fn gradients(&self, grads: Vec<Tensor>) -> Result<TableGradients> {
        ensure!(grads.len() == self.numels.len(), "gradient table: {} gradients for {} tensors", grads.len(), self.numels.len());
        let device = self.items.device();
        let mut addresses = Vec::with_capacity(grads.len());
        for (k, (g, &n)) in grads.iter().zip(&self.numels).enumerate() {
            ensure!(
                g.kind() == Kind::BFloat16 && g.is_contiguous() && g.numel() as i64 == n && g.device() == device,
                "gradient table: tensor {k}'s gradient must be contiguous bf16 of {n} elements on {device:?}, got {:?} {:?} on {:?}",
                g.kind(),
                g.size(),
                g.device()
            );
            addresses.push(g.data_ptr() as i64);
        }
        Ok(TableGradients { addresses: bwm_model::device::upload(&Tensor::from_slice(&addresses), device), grads })
    }

    /// The address table of `grads`, made by a table of as many tensors.
    fn check<'a>(&self, grads: &'a TableGradients) -> Result<&'a Tensor> {
        ensure!(grads.grads.len() == self.numels.len(), "gradient table: gradients of {} tensors for a table of {}", grads.grads.len(), self.numels.len());
        Ok(&grads.addresses)
    }
}

impl FusedAdamW {
    /// The kernels for `device`, compiled once per device; an error says why they are unavailable
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
        // Without multiply-add contraction: each operation rounds as the tensor path's do, and the
        // update's inlined copies cannot contract differently (with it, the vector loop's second
        // moment became fma(g, g(1-b2), v b2) and the element loop's fma(v, b2, g g(1-b2)), so an
        // element's update depended on its tensor's alignment).
        let (ctx, module) = bwm_fused_ops::load_module(index, SOURCE, "the fused AdamW kernel")?;
        let function = |name: &str| module.load_function(name).with_context(|| format!("the fused AdamW kernel {name}"));
        let k = Arc::new(FusedAdamW {
            update: function("adamw_update")?,
            update_tensors: function("adamw_update_bf16_tensors")?,
            sum_squares: function("sum_squares_bf16_tensors")?,
            ctx,
        });
        kernels.push((index, k.clone()));
        Ok(k)
    }

    /// Updates `m`, `v`, `w` (and `ema`) in place from the gradient `g`: contiguous f32 tensors
    /// of the same length on this kernel's device. `publish` (f32 or bf16, same length) receives
    /// the updated weights `w` in its dtype, saving a pass over `w` to copy them.
    pub fn update(&self, g: &Tensor, m: &Tensor, v: &Tensor, w: &Tensor, ema: Option<&Tensor>, publish: Option<&Tensor>, u: &Update) -> Result<()> {
        let n = g.numel();
        ensure!(g.kind() == Kind::Float && g.is_contiguous() && g.numel() == n, "fused AdamW: the gradient must be contiguous f32");
        let state = State::new(m, v, w, ema, publish, n, g.device())?;
        if n == 0 {
            return Ok(());
        }
        self.ctx.bind_to_thread()?;
        let (pg, n) = (g.data_ptr() as u64, n as i64);
        let blocks = (n as u64).div_ceil(THREADS as u64).min(65_535 * 8) as u32;
        let stream = self.ctx.default_stream();
        let mut launch = stream.launch_builder(&self.update);
        launch.arg(&pg);
        state.args(&mut launch);
        launch.arg(&n);
        let hyper = Hyper::new(u);
        hyper.args(&mut launch);
        // SAFETY: the pointers are live contiguous CUDA buffers of n elements of their types (checked above)
        // that outlive the kernel (tch's caching allocator reuses memory in stream order, and the
        // kernel is on libtorch's stream); the arguments match the kernel's signature.
        unsafe { launch.launch(Self::config(blocks)) }.context("launching the fused AdamW kernel")?;
        Ok(())
    }

    /// The sum of the squares of `grads` (the table's tensors' bf16 gradients) as a one-element
    /// f64 tensor on the device, the same on every run for the same gradients.
    pub fn sum_squares(&self, table: &GradTable, grads: &TableGradients) -> Result<Tensor> {
        let addresses = table.check(grads)?;
        let partial = Tensor::zeros([table.count as i64], (Kind::Double, addresses.device()));
        if table.count > 0 {
            self.ctx.bind_to_thread()?;
            let (pa, pi, pp) = (addresses.data_ptr() as u64, table.items.data_ptr() as u64, partial.data_ptr() as u64);
            let stream = self.ctx.default_stream();
            let mut launch = stream.launch_builder(&self.sum_squares);
            launch.arg(&pa).arg(&pi).arg(&pp);
            // SAFETY: the address table holds live contiguous bf16 gradients of the lengths the items
            // cover (checked by `gradients`); the tables and `partial` (one f64 per item) are live
            // CUDA tensors that outlive the kernel on libtorch's stream.
            unsafe { launch.launch(Self::config(table.count)) }.context("launching the gradient norm kernel")?;
        }
        Ok(partial.sum(Kind::Double).reshape([1]))
    }

    /// `update` with the gradient read from the table's bf16 gradient tensors `grads`; `m`, `v`,
    /// `w`, `ema` and `publish` cover the flat state the table's offsets index.
    #[allow(clippy::too_many_arguments)]
    pub fn update_from_tensors(&self, table: &GradTable, grads: &TableGradients, m: &Tensor, v: &Tensor, w: &Tensor, ema: Option<&Tensor>, publish: Option<&Tensor>, u: &Update) -> Result<()> {
        let addresses = table.check(grads)?;
        let state = State::new(m, v, w, ema, publish, m.numel(), addresses.device())?;
        ensure!(table.end as usize <= m.numel(), "fused AdamW: the gradient table reaches element {} of a state of {}", table.end, m.numel());
        if table.count == 0 {
            return Ok(());
        }
        self.ctx.bind_to_thread()?;
        let (pa, pi, po) = (addresses.data_ptr() as u64, table.items.data_ptr() as u64, table.offsets.data_ptr() as u64);
        let stream = self.ctx.default_stream();
        let mut launch = stream.launch_builder(&self.update_tensors);
        launch.arg(&pa).arg(&pi).arg(&po);
        state.args(&mut launch);
        let hyper = Hyper::new(u);
        hyper.args(&mut launch);
        // SAFETY: as `update`, with the gradients behind the address table checked by `gradients`
        // and every item inside the state (checked above).
        unsafe { launch.launch(Self::config(table.count)) }.context("launching the fused AdamW kernel")?;
        Ok(())
    }

    fn config(blocks: u32) -> LaunchConfig {
        LaunchConfig { grid_dim: (blocks, 1, 1), block_dim: (THREADS, 1, 1), shared_mem_bytes: 0 }
    }
}

/// The state pointers of a launch (the kernels' STATE arguments).
struct State {
    m: u64,
    v: u64,
    w: u64,
    ema: u64,
    out_f32: u64,
    out_bf16: u64,
}

impl State {
    fn new(m: &Tensor, v: &Tensor, w: &Tensor, ema: Option<&Tensor>, publish: Option<&Tensor>, n: usize, device: Device) -> Result<Self> {
        for t in [m, v, w].into_iter().chain(ema) {
            ensure!(t.kind() == Kind::Float && t.is_contiguous() && t.numel() == n && t.device() == device, "fused AdamW: tensors must be contiguous f32 of one length and device");
        }
        if let Some(t) = publish {
            ensure!(
                matches!(t.kind(), Kind::Float | Kind::BFloat16) && t.is_contiguous() && t.numel() == n && t.device() == device,
                "fused AdamW: the published weights must be contiguous f32 or bf16 of the state's length and device"
            );
        }
        let ptr = |t: &Tensor| t.data_ptr() as u64;
        let published = |kind: Kind| publish.filter(|t| t.kind() == kind).map_or(0, ptr);
        Ok(Self { m: ptr(m), v: ptr(v), w: ptr(w), ema: ema.map_or(0, ptr), out_f32: published(Kind::Float), out_bf16: published(Kind::BFloat16) })
    }

    fn args<'a>(&'a self, launch: &mut cudarc::driver::LaunchArgs<'a>) {
        launch.arg(&self.m).arg(&self.v).arg(&self.w).arg(&self.ema).arg(&self.out_f32).arg(&self.out_bf16);
    }
}

/// The update's scalars as the kernels take them (HYPER), rounded to f32 from f64.
struct Hyper([f32; 9]);

impl Hyper {
    fn new(u: &Update) -> Self {
        let f = |x: f64| x as f32;
        let decay = if u.weight_decay > 0.0 { 1.0 - u.lr * u.weight_decay } else { 1.0 };
        Self([
            f(u.grad_scale),
            f(1.0 - u.b1),
            f(u.b2),
            f(1.0 - u.b2),
            f(decay),
            f(u.eps),
            f(u.bc2.sqrt()),
            f(u.lr / u.bc1),
            f(1.0 - u.ema_decay.unwrap_or(1.0)),
        ])
    }

    fn args<'a>(&'a self, launch: &mut cudarc::driver::LaunchArgs<'a>) {
        for x in &self.0 {
            launch.arg(x);
        }
    }
}
