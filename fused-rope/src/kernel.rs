//! The rotation's CUDA kernels, compiled with NVRTC once per device and launched on the stream
//! the C++ side reports as libtorch's current one (so that they also run inside a CUDA graph's
//! capture).

use std::ffi::c_void;
use std::sync::{Arc, Mutex, OnceLock};

use anyhow::{anyhow, ensure, Context, Result};
use cudarc::driver::{CudaContext, CudaFunction, CudaModule};

use crate::Shape;

/// One block per token. Where a head's pairs are a multiple of 4, each thread reads and writes 4
/// pairs at once (16 bytes of bf16); else one pair.
const SOURCE: &str = r#"
// fp32 -> bf16, rounding to nearest even (as c10::BFloat16 and __float2bfloat16_rn).
__device__ unsigned short to_bf16(float x) {
  unsigned int u = __float_as_uint(x);
  if ((u & 0x7fffffffu) > 0x7f800000u) return (unsigned short)((u >> 16) | 0x40u);
  return (unsigned short)((u + 0x7fffu + ((u >> 16) & 1u)) >> 16);
}

__device__ __forceinline__ void load(const float* x, long long g, int n, float* v) {
  if (n == 4) {
    float4 a = ((const float4*)x)[2 * g], b = ((const float4*)x)[2 * g + 1];
    v[0] = a.x; v[1] = a.y; v[2] = a.z; v[3] = a.w; v[4] = b.x; v[5] = b.y; v[6] = b.z; v[7] = b.w;
  } else {
    float2 a = ((const float2*)x)[g];
    v[0] = a.x; v[1] = a.y;
  }
}

__device__ __forceinline__ void load(const unsigned short* x, long long g, int n, float* v) {
  if (n == 4) {
    uint4 u = ((const uint4*)x)[g];
    unsigned int w[4] = {u.x, u.y, u.z, u.w};
    for (int h = 0; h < 4; h++) {
      v[2 * h] = __uint_as_float(w[h] << 16);
      v[2 * h + 1] = __uint_as_float(w[h] & 0xffff0000u);
    }
  } else {
    unsigned int u = ((const unsigned int*)x)[g];
    v[0] = __uint_as_float(u << 16);
    v[1] = __uint_as_float(u & 0xffff0000u);
  }
}

__device__ __forceinline__ void store(float* out, long long g, int n, const float* v) {
  if (n == 4) {
    ((float4*)out)[2 * g] = make_float4(v[0], v[1], v[2], v[3]);
    ((float4*)out)[2 * g + 1] = make_float4(v[4], v[5], v[6], v[7]);
  } else {
    ((float2*)out)[g] = make_float2(v[0], v[1]);
  }
}

__device__ __forceinline__ void store(unsigned short* out, long long g, int n, const float* v) {
  unsigned int w[4];
  for (int h = 0; h < n; h++) w[h] = (unsigned int)to_bf16(v[2 * h]) | ((unsigned int)to_bf16(v[2 * h + 1]) << 16);
  if (n == 4) {
    ((uint4*)out)[g] = make_uint4(w[0], w[1], w[2], w[3]);
  } else {
    ((unsigned int*)out)[g] = w[0];
  }
}

// Token blockIdx.x's groups of N pairs: `groups` per token, `per_head` per head; its rotations are
// row (token % len) of `rot`, pairs = per_head * N wide. sign -1 rotates back.
template <typename T, int N>
__device__ void rotate(const T* x, const float2* rot, T* out, int len, int groups, int per_head, float sign) {
  long long token = blockIdx.x;
  const float2* r = rot + (long long)(token % len) * per_head * N;
  for (int j = threadIdx.x; j < groups; j += blockDim.x) {
    long long g = token * groups + j;
    const float2* rj = r + (j % per_head) * N;
    float v[2 * N];
    load(x, g, N, v);
    for (int h = 0; h < N; h++) {
      float c = rj[h].x, s = sign * rj[h].y, a = v[2 * h], b = v[2 * h + 1];
      v[2 * h] = a * c - b * s;
      v[2 * h + 1] = a * s + b * c;
    }
    store(out, g, N, v);
  }
}

#define ARGS(T) const T* x, const float2* rot, T* out, int len, int groups, int per_head, float sign
extern "C" __global__ void rope_f32_4(ARGS(float)) { rotate<float, 4>(x, rot, out, len, groups, per_head, sign); }
extern "C" __global__ void rope_f32_1(ARGS(float)) { rotate<float, 1>(x, rot, out, len, groups, per_head, sign); }
extern "C" __global__ void rope_bf16_4(ARGS(unsigned short)) { rotate<unsigned short, 4>(x, rot, out, len, groups, per_head, sign); }
extern "C" __global__ void rope_bf16_1(ARGS(unsigned short)) { rotate<unsigned short, 1>(x, rot, out, len, groups, per_head, sign); }
"#;

pub(crate) struct Kernels {
    ctx: Arc<CudaContext>,
    // Holds the functions' module loaded.
    _module: Arc<CudaModule>,
    /// [f32, bf16] x [one pair, four pairs] per thread.
    functions: [[CudaFunction; 2]; 2],
}

impl Kernels {
    /// The kernels of CUDA device `index`, compiled at first use; the error (NVRTC missing, ...)
    /// is kept and repeated.
    pub(crate) fn for_device(index: usize) -> Result<Arc<Kernels>> {
        type Cache = Mutex<Vec<(usize, Result<Arc<Kernels>, String>)>>;
        static CACHE: OnceLock<Cache> = OnceLock::new();
        let mut cache = CACHE.get_or_init(Default::default).lock().map_err(|_| anyhow!("the rotary kernels' cache is poisoned"))?;
        if let Some((_, k)) = cache.iter().find(|(i, _)| *i == index) {
            return k.clone().map_err(|e| anyhow!(e));
        }
        let made = Self::compile(index).map(Arc::new).map_err(|e| format!("{e:#}"));
        cache.push((index, made.clone()));
        made.map_err(|e| anyhow!(e))
    }

    fn compile(index: usize) -> Result<Kernels> {
        // SAFETY: probing a shared library by name.
        ensure!(unsafe { cudarc::nvrtc::sys::is_culib_present() }, "NVRTC (libnvrtc.so) is not on the library path");
        // No multiply-add contraction: each product rounds as the CPU loop's does.
        let options = cudarc::nvrtc::CompileOptions { fmad: Some(false), ..Default::default() };
        let ptx = cudarc::nvrtc::compile_ptx_with_opts(SOURCE, options).context("compiling the rotary kernels with NVRTC")?;
        let ctx = CudaContext::new(index).context("binding the CUDA context")?;
        let module = ctx.load_module(ptx).context("loading the rotary kernels")?;
        let function = |name: &str| module.load_function(name).with_context(|| format!("the rotary kernel {name}"));
        let functions = [[function("rope_f32_1")?, function("rope_f32_4")?], [function("rope_bf16_1")?, function("rope_bf16_4")?]];
        Ok(Kernels { ctx, _module: module, functions })
    }

    /// Rotates x into out (device addresses of contiguous buffers of `shape`'s pairs, bf16 or f32)
    /// by the complex64 table at `rotations`, on `stream` (a CUstream).
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn launch(&self, stream: *mut c_void, bf16: bool, x: u64, rotations: u64, out: u64, s: Shape, inverse: bool) -> Result<()> {
        let n = if s.pairs % 4 == 0 { 4 } else { 1 };
        let (groups, per_head) = (s.heads * s.pairs / n, s.pairs / n);
        let groups = i32::try_from(groups).context("rotary kernel: too many pairs per token")?;
        let (len, per_head) = (i32::try_from(s.len)?, i32::try_from(per_head)?);
        let blocks = u32::try_from(s.tokens).ok().filter(|&b| b < 1 << 31).context("rotary kernel: too many tokens for one launch")?;
        let threads = (groups as u32).div_ceil(32).clamp(1, 4) * 32;
        let sign: f32 = if inverse { -1.0 } else { 1.0 };
        let f = &self.functions[bf16 as usize][(n == 4) as usize];
        self.ctx.bind_to_thread().context("binding the CUDA context")?;
        let (mut x, mut r, mut o, mut len, mut groups, mut per_head, mut sign) = (x, rotations, out, len, groups, per_head, sign);
        let mut params: [*mut c_void; 7] = [
            &mut x as *mut u64 as *mut c_void,
            &mut r as *mut u64 as *mut c_void,
            &mut o as *mut u64 as *mut c_void,
            &mut len as *mut i32 as *mut c_void,
            &mut groups as *mut i32 as *mut c_void,
            &mut per_head as *mut i32 as *mut c_void,
            &mut sign as *mut f32 as *mut c_void,
        ];
        // SAFETY: the buffers are live contiguous device allocations of the sizes `s` describes
        // (checked by the C++ side), used in order on libtorch's current stream; the parameters
        // match the kernel's signature.
        unsafe { cudarc::driver::result::launch_kernel(f.cu_function(), (blocks, 1, 1), (threads, 1, 1), 0, stream as cudarc::driver::sys::CUstream, &mut params) }
            .context("launching the rotary kernel")
    }
}
